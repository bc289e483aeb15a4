"""The six LabRobFail-Bench questions: variants, the grid preamble, answer options and answer formats.

The single home of the paper's question-variant table and answer-option table
(appendix, LLM Annotation Pipeline). The dataset builder draws one variant per
dimension; inference asks the first variant of each and parses with the same
formats, so training and inference never disagree on wording or answer shape.

Answer formats (what the "gpt" turn contains):
  Q1  the ordered atomic actions, comma-separated: "grasp, place"
  Q2  "Yes" or "No"; for variants marked `positive` (they ask whether the task went
      well) the answer is flipped
  Q3  the 1-based frame number drawn on the grid, e.g. "5"
  Q4  the severity option number "1".."4"
  Q5  the category option number "1".."5"
  Q6  a correction instruction (labrobfail_vlm.corrections)
For a successful trajectory Q3, Q4 and Q5 answer NO_FAILURE ("None") and Q6 answers
NO_CORRECTION: the questions are still asked, so the model learns not to invent a failure.
"""

from __future__ import annotations

from dataclasses import dataclass

from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, Category, Severity

DIMENSIONS = ("Q1", "Q2", "Q3", "Q4", "Q5", "Q6")
DIMENSION_NAMES = {
    "Q1": "Task Understanding",
    "Q2": "Failure Detection",
    "Q3": "Temporal Localization",
    "Q4": "Severity Assessment",
    "Q5": "Failure Classification",
    "Q6": "Correction Strategy",
}

# Auxiliary training records (labrobfail_data/facts.py: per-frame state facts) end in _A<i>; the benchmark never
# asks them.
AUX_PREFIX = "A"

NO_FAILURE = "None"
NO_CORRECTION = "No correction is needed; the task was completed successfully."

PREAMBLE = (
    "The image consists of a series of sequential frames. Each row presents a different camera viewpoint, "
    "and each column corresponds to a later time step, with the time-step label shown in the top-left "
    "corner. These frames depict the robotic arm's motion during Task: {task_name}."
)
# The same preamble for grids whose rows are time steps (GridConfig.time_axis="rows").
PREAMBLE_TIME_ROWS = (
    "The image consists of a series of sequential frames. Each column presents a different camera "
    "viewpoint, and each row corresponds to a later time step, with the time-step label shown in "
    "the top-left corner. These frames depict the robotic arm's motion during Task: {task_name}."
)

# Without drawn time-step labels (the paper's "w/o temporal index" ablation, GridConfig.draw_index=False) the prompt
# must not point at labels that are not there: the preamble drops its label clause, and Q3 asks for the time step
# counted from the first one instead of "the frame number in the upper left corner".
LABEL_CLAUSE = ", with the time-step label shown in the top-left corner"


@dataclass(frozen=True)
class Variant:
    text: str
    positive: bool = False  # Q2 only: "Yes" means the task succeeded


_ACTIONS = ", ".join(ATOMIC_ACTIONS)
VARIANTS: dict[str, tuple[Variant, ...]] = {
    "Q1": (
        Variant(
            f"What atomic actions does the current task consist of? Please choose from: {_ACTIONS}, "
            "and list them in execution order."
        ),
        Variant(f"Break down the robot's operation into primitive actions. Available primitives: {_ACTIONS}."),
        Variant(f"Identify the sequence of manipulation primitives performed in this task. Options: {_ACTIONS}."),
        Variant(f"Which atomic actions are executed in this task and in what order? Choose from: {_ACTIONS}."),
    ),
    "Q2": (
        Variant("Is there any error in this task? (Yes/No)"),
        Variant("Does the robot successfully complete the intended operation? (Yes/No)", positive=True),
        Variant("Did anything go wrong during the execution? (Yes/No)"),
        Variant("Is there any anomaly or failure observed in this trajectory? (Yes/No)"),
        Variant("Was this task executed without issues? (Yes/No)", positive=True),
    ),
    "Q3": (
        Variant("At which frame does the failure occur? (Refer to the frame number in the upper left corner)"),
        Variant("Looking at the frame indices, when exactly does the error happen?"),
        Variant("Identify the timestep where the failure first manifests. (Use the frame number displayed)"),
        Variant("At what point in the sequence does the anomaly appear? (Specify the frame number)"),
        Variant("Which frame marks the onset of the failure?"),
    ),
    "Q4": (
        Variant("What is the severity level of this error?"),
        Variant("How severe is this failure in terms of laboratory safety?"),
        Variant("Assess the risk level of this failure."),
        Variant("Rate the severity of this anomaly."),
    ),
    "Q5": (
        Variant("What is the failure type? Select the most appropriate category."),
        Variant("How would you classify the root cause of this failure?"),
        Variant("Which category best describes this anomaly?"),
        Variant("Identify the failure mode from the following categories."),
    ),
    "Q6": (
        Variant("What is the correction solution for this failure?"),
        Variant("How should the robot recover from this situation?"),
        Variant("Propose a specific corrective action to address this failure."),
        Variant("What adjustments should be made to fix this error?"),
        Variant("Describe the recovery procedure for this anomaly."),
    ),
}

Q3_NO_INDEX: tuple[Variant, ...] = (
    Variant("At which frame does the failure occur? (Count the time steps from 1)"),
    Variant("Counting the time steps from 1, when exactly does the error happen?"),
    Variant("Identify the timestep where the failure first manifests. (Count the time steps from 1)"),
    Variant("At what point in the sequence does the anomaly appear? (Specify the time step, counted from 1)"),
    Variant("Which frame marks the onset of the failure?"),
)

OPTIONS: dict[str, str] = {
    "Q4": "Options:\n" + "\n".join(f"({s.value}) {s.title}" for s in Severity),
    "Q5": "Options:\n" + "\n".join(f"({c.value}) {c.title}" for c in Category),
}


def preamble(task_name: str, time_axis: str = "columns", index: bool = True) -> str:
    """`index`: the grid draws time-step labels (False: the preamble does not mention them)."""
    text = PREAMBLE if time_axis == "columns" else PREAMBLE_TIME_ROWS
    return (text if index else text.replace(LABEL_CLAUSE, "")).format(task_name=task_name)


def variants(dim: str, index: bool = True) -> tuple[Variant, ...]:
    """The wordings of `dim` as asked of a grid with (`index`) or without drawn frame numbers (Q3 differs)."""
    return VARIANTS[dim] if index or dim != "Q3" else Q3_NO_INDEX


def question_text(dim: str, variant: int, task_name: str, time_axis: str = "columns", index: bool = True) -> str:
    """The human turn: image token, preamble, question and (Q4/Q5) the option list."""
    q = variants(dim, index)[variant].text
    opts = OPTIONS.get(dim)
    return f"<image>\n{preamble(task_name, time_axis, index)} {q}" + (f"\n{opts}" if opts else "")


def record_id(trajectory: str, dim: str) -> str:
    """A VQA record's id: one record per trajectory and dimension."""
    return f"{trajectory}_{dim}"


def dim_of(rid: str) -> str:
    return rid.rsplit("_", 1)[-1]


def is_aux(dim: str) -> bool:
    return dim.startswith(AUX_PREFIX) and dim[len(AUX_PREFIX) :].isdigit()


def traj_of(rid: str) -> str:
    return rid.rsplit("_", 1)[0]


def variant_of(dim: str, question: str) -> int | None:
    """Which variant of `dim` a question text asks (None if none of them)."""
    return next((i for i, v in enumerate(VARIANTS[dim]) if v.text in question), None)


def q2_variant(question: str) -> int | None:
    """Which Q2 variant a question text asks (None if none of them)."""
    return variant_of("Q2", question)


def reask(dim: str, question: str, answer: str, variant: int) -> tuple[str, str]:
    """The same record asked in another of its dimension's wordings: (question, answer).

    Only Q2's answer depends on the wording (the "successfully"/"without issues" variants flip Yes/No);
    a question in no known wording (e.g. paraphrased) is returned unchanged.
    """
    old = variant_of(dim, question) if dim in VARIANTS else None
    if old is None or old == variant:
        return question, answer
    new_q = question.replace(VARIANTS[dim][old].text, VARIANTS[dim][variant].text, 1)
    if dim != "Q2":
        return new_q, answer
    failed = (answer == "Yes") != VARIANTS["Q2"][old].positive
    return new_q, q2_answer(variant, not failed)


def q2_answer(dim_variant: int, success: bool) -> str:
    failed = not success
    if VARIANTS["Q2"][dim_variant].positive:
        return "No" if failed else "Yes"
    return "Yes" if failed else "No"


def format_actions(actions: list[str]) -> str:
    return ", ".join(actions)
