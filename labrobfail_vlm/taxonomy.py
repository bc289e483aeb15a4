"""The LabRobFail failure taxonomy, severity scale and atomic-action vocabulary.

This module is the single source of truth for the paper's contract tables:
the 5 failure categories (Q5 options, numbered as in the paper), the 11
fine-grained failure types, the 4 severity levels (Q4 options) and the 8
atomic actions (Q1 vocabulary). Everything else imports from here.

Pure Python: the simulator backends import it without pulling in torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class Category(IntEnum):
    """Q5 answer options; the integer is the option number in the paper."""

    PERCEPTION = 1
    GRASPING = 2
    MOTION = 3
    LOGIC = 4
    SAFETY = 5

    @property
    def title(self) -> str:
        return f"{self.name.capitalize()} Failure"

    @property
    def definition(self) -> str:
        return CATEGORY_DEFINITIONS[self]


CATEGORY_DEFINITIONS: dict[Category, str] = {
    Category.PERCEPTION: "Failed to locate target objects or positions",
    Category.GRASPING: "Object slippage or unstable grasp",
    Category.MOTION: "Motion execution incomplete",
    Category.LOGIC: "Incorrect order or omitted steps",
    Category.SAFETY: "Violating laboratory safety protocols",
}


class Severity(IntEnum):
    """Q4 answer options; the integer is the option number in the paper."""

    RISK = 1
    DANGEROUS = 2
    FATAL = 3
    MANAGEMENT_INCIDENT = 4

    @property
    def title(self) -> str:
        return SEVERITY_TITLES[self]

    @property
    def definition(self) -> str:
        return SEVERITY_DEFINITIONS[self]

    @property
    def main_text(self) -> str:
        return SEVERITY_MAIN_TEXT[self]

    @property
    def display(self) -> str:
        """How a person is shown this level: the answer option with the main text's name beside it."""
        return f"{self.title} (option {self.value}; the paper's main text: {self.main_text})"


SEVERITY_TITLES: dict[Severity, str] = {
    Severity.RISK: "Risk Level",
    Severity.DANGEROUS: "Dangerous Level",
    Severity.FATAL: "Fatal Level",
    Severity.MANAGEMENT_INCIDENT: "Management Incident",
}

# The paper names the four levels twice: its appendix answer options (above; the dataset keeps these) and its
# main text (Minor, Recoverable, Critical, Catastrophic, "four hierarchical risk levels"). It never pairs them, so
# the project pairs them by position, option 1 with the first level named, and says so wherever a severity is
# shown to a person. The definitions differ in places (the main text's Catastrophic is about safety violations or
# equipment damage, the appendix's option 4 about non-compliant operations): docs/GUIDE.md, "Fidelity to the paper".
SEVERITY_MAIN_TEXT: dict[Severity, str] = {
    Severity.RISK: "Minor",
    Severity.DANGEROUS: "Recoverable",
    Severity.FATAL: "Critical",
    Severity.MANAGEMENT_INCIDENT: "Catastrophic",
}

SEVERITY_DEFINITIONS: dict[Severity, str] = {
    Severity.RISK: "Collision, liquid spillage, or potential falling",
    Severity.DANGEROUS: "Requires manual intervention to proceed",
    Severity.FATAL: "Equipment damage, requiring manual intervention",
    Severity.MANAGEMENT_INCIDENT: "Non-compliant operations (e.g., unclosed cabinet)",
}


@dataclass(frozen=True)
class FailureType:
    name: str
    category: Category
    description: str


# Order follows the paper's appendix (grouped by category, Safety first).
FAILURE_TYPES: dict[str, FailureType] = {
    ft.name: ft
    for ft in (
        FailureType(
            "protocol_violation",
            Category.SAFETY,
            "A laboratory protocol is broken, e.g. reagent delivered to the wrong vessel.",
        ),
        FailureType(
            "improper_handling", Category.SAFETY, "Equipment is not returned to its designated place after use."
        ),
        FailureType("sequence_reversal", Category.LOGIC, "Steps of the workflow are executed in the wrong order."),
        FailureType("step_omission", Category.LOGIC, "A required step of the workflow is skipped."),
        FailureType(
            "pose_control_error", Category.MOTION, "An abnormal end-effector twist spoils the placement or operation."
        ),
        FailureType(
            "incomplete_trajectory", Category.MOTION, "The motion stops before the task's final keyframes are reached."
        ),
        FailureType(
            "gripper_control_failure",
            Category.GRASPING,
            "The gripper does not close enough to acquire an aligned object.",
        ),
        FailureType(
            "object_slippage", Category.GRASPING, "A grasped object drifts out of the gripper during transport."
        ),
        FailureType(
            "target_positioning_deviation",
            Category.PERCEPTION,
            "The object is released outside the designated target region.",
        ),
        FailureType(
            "operation_position_error",
            Category.PERCEPTION,
            "The end effector misses a handle or button, so the operation has no effect.",
        ),
        FailureType(
            "grasp_target_misalignment",
            Category.PERCEPTION,
            "The gripper closes beside the object and fails to acquire it.",
        ),
    )
}

FAILURE_TYPE_NAMES: tuple[str, ...] = tuple(FAILURE_TYPES)

ATOMIC_ACTIONS: tuple[str, ...] = ("grasp", "place", "open", "close", "pour", "shake", "insert", "stir")

HORIZONS: tuple[str, ...] = ("short", "medium", "long")


def horizon_of(num_keyframes: int) -> str:
    """Task complexity level from the number of keyframes (paper: <=10, 10-30, >30)."""
    if num_keyframes <= 10:
        return "short"
    if num_keyframes <= 30:
        return "medium"
    return "long"


def category_of(failure_type: str) -> Category:
    try:
        return FAILURE_TYPES[failure_type].category
    except KeyError:
        raise ValueError(
            f"unknown failure type {failure_type!r}; expected one of {', '.join(FAILURE_TYPE_NAMES)}"
        ) from None


# Scene variants (paper: seen / unseen object / unseen scene / both) and the dataset split each one feeds.
# The one home of these names: the simulator backends, the generator, the split logic and the bench import them.
# - seen: the training catalogue and scene family, cut 8:1:1 by pair into train / val / test.
# - val_object / val_scene / val_both: the held-out catalogue and scene family on which every choice is taken
#   (epochs, thresholds, recipes, catalogue changes).
# - test_object / test_scene / test_both: the sealed catalogue and scene family. Nothing that trains, pretrains
#   the tower or augments draws from them (tests/test_splits_sealed.py checks the families); they run only for the
#   rows docs/RESULTS.md reports, and the page lists every such run.
# Each variant draws its own episodes (sim_backends.generate.pair_seed): no seed, initial state or injection of one
# variant appears in another. A held-out variant's episodes replayed in new colours ("same episode, new
# appearance", generate.py replay_seen=true) are named replay_<variant>: a split of their own, never val or test.
SCENE_VARIANTS: tuple[str, ...] = (
    "seen",
    "val_object",
    "val_scene",
    "val_both",
    "test_object",
    "test_scene",
    "test_both",
)
SEEN_SPLITS: tuple[str, ...] = ("train", "val", "test")  # the seen variant is cut 8:1:1 into these
HELD_OUT_SPLITS: tuple[str, ...] = SCENE_VARIANTS[1:]  # each held-out variant is a split of its own, named alike
SEALED_SPLITS: tuple[str, ...] = ("test_object", "test_scene", "test_both")  # reported rows only
REPLAY_PREFIX = "replay_"
REPLAY_SPLITS: tuple[str, ...] = tuple(REPLAY_PREFIX + v for v in HELD_OUT_SPLITS)
DATA_VARIANTS: tuple[str, ...] = SCENE_VARIANTS + REPLAY_SPLITS  # what a shard's `variant` column may hold
# Names used before the split fix (their episodes replayed the seen run's): a one-line pointer to the new names.
RENAMED_VARIANTS: dict[str, str] = {
    f"unseen_{k}": f"val_{k} (the former unseen catalogue and scene family) or test_{k} (sealed)"
    for k in ("object", "scene", "both")
}


def check_variant(variant: str, field: str = "variant") -> str:
    """The variant, or a ConfigError (a ValueError) "<field>: ..." naming the valid ones (and the new name of a
    renamed one): the one check behind the generator, the supervisor, the policy server and a backend's reset."""
    from labrobfail_vlm.config import ConfigError

    if variant in SCENE_VARIANTS:
        return variant
    if variant in RENAMED_VARIANTS:
        raise ConfigError(f"{field}: {variant!r} was renamed; use {RENAMED_VARIANTS[variant]}")
    raise ConfigError(f"{field}: unknown variant {variant!r}; expected one of {', '.join(SCENE_VARIANTS)}")


def _held_out_set(variant: str, held: str) -> str:
    for prefix, name in (("val_", "val"), ("test_", "sealed")):
        if variant in (prefix + held, prefix + "both"):
            return name
    return "seen"


def scene_set(variant: str) -> str:
    """Which scene family a variant draws its bench, floor and light from: seen, val or sealed."""
    return _held_out_set(variant, "scene")


def object_set(variant: str) -> str:
    """Which object catalogue a variant draws its glassware from: seen, val or sealed."""
    return _held_out_set(variant, "object")
