"""Typed task metadata (`TaskMeta`, `Step`, `Goal`) and the state-trace schema.

These are the two things a backend hands the labeler (sim_backends/labeler.py)
besides nothing else: the recorded state trace and the task metadata. Written
down here, a second backend (ManiSkill/SAPIEN, a real robot log) fills them in
without reading the labeler. `TaskMeta.to_dict()` is also what a shard stores in
its `task_meta` column; its keys and their order are those of the untyped dict of
earlier versions plus `robot_base` (1 Dec), so shards written before and after read the same.
See docs/ARCHITECTURE.md, "Task metadata (TaskMeta) and the state trace".
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from typing import Any

# ---- state trace ------------------------------------------------------------------------------------
# A trace is a JSON object of columns (lists, one entry per sample) plus two non-sample entries:
# `kf_end` (sample index at which each executed keyframe ended and its images were taken) and
# `rate_hz` (samples per second). The labeler converts its time windows with `rate_hz`, so a
# backend sampling at another rate keeps the same detection behaviour. Optional `images_at`: the sample each
# keyframe's images show, written only where one differs from `kf_end` (a last keyframe drawn again at the settled
# state, `FailureSource._settled_images`); `image_samples` reads either.
Trace = dict[str, Any]
NON_SAMPLE = ("kf_end", "rate_hz", "images_at")  # trace entries that are not one value per sample
TRACE_COLUMNS = ("t", "kf", "ee_pos", "ee_quat", "width", "grip_cmd")  # every backend records these
MOVABLE = ("vessel", "rod")  # object kinds a gripper picks up and carries (the rest: ovens, buttons, zones)
OBJECT_COLUMNS = (".pos", ".quat", ".contacts")  # per MOVABLE object, prefixed with its name
LEGACY_RATE_HZ = 40.0  # traces written before the rate was recorded were all sampled at 40 Hz (PyBullet)


def trace_rate(trace: Trace) -> float:
    """Samples per second of a trace (40 Hz for traces from before the rate was recorded)."""
    return float(trace.get("rate_hz", LEGACY_RATE_HZ))


def samples_in(trace: Trace, seconds: float) -> int:
    """Whole number of samples spanning `seconds` at the trace's own rate."""
    return int(seconds * trace_rate(trace))


def image_samples(trace: Trace) -> list[int]:
    """The sample each executed keyframe's images show (its end, `kf_end`, unless `images_at` says otherwise)."""
    return list(trace.get("images_at") or trace["kf_end"])


def movables(trace: Trace, meta: dict[str, Any]) -> list[str]:
    """The task's MOVABLE objects that the trace records."""
    return [o for o, info in meta["objects"].items() if info["kind"] in MOVABLE and f"{o}.pos" in trace]


def trace_at(trace: Trace, j: int) -> Trace:
    """The trace as it stood at sample j: every per-sample column cut after it, the NON_SAMPLE entries as they are
    (a goal predicate reads the last sample)."""
    return {c: (v if c in NON_SAMPLE else v[: j + 1]) for c, v in trace.items()}


def trace_until(trace: Trace, keyframe: int) -> Trace:
    """The trace as it stood when executed keyframe `keyframe` (0-based) ended: its samples and keyframe ends up to
    that one (every image then showed its keyframe's end, so `images_at` is dropped)."""
    j = trace["kf_end"][keyframe]
    cut = trace_at(trace, j)
    cut["kf_end"] = [e for e in trace["kf_end"] if e <= j]
    cut.pop("images_at", None)
    return cut


def check_trace(trace: Trace, meta: "TaskMeta | None" = None) -> list[str]:
    """Schema problems of a trace (empty when it is well-formed): columns, lengths, keyframe ends."""
    errs = [f"missing column {c!r}" for c in (*TRACE_COLUMNS, "kf_end") if c not in trace]
    if "rate_hz" not in trace or not float(trace["rate_hz"]) > 0:
        errs.append("rate_hz must be a positive number")
    if errs:
        return errs
    n = len(trace["t"])
    errs += [
        f"column {c!r} has {len(v)} samples, not {n}" for c, v in trace.items() if c not in NON_SAMPLE and len(v) != n
    ]
    if any(not 0 <= j < n for j in trace["kf_end"]) or trace["kf_end"] != sorted(trace["kf_end"]):
        errs.append("kf_end must be increasing sample indices")
    shots = trace.get("images_at")
    if shots is not None and (
        len(shots) != len(trace["kf_end"]) or any(not e <= j < n for e, j in zip(trace["kf_end"], shots))
    ):
        errs.append("images_at must give each keyframe a sample from its end on")
    if meta is not None:
        if len(trace["kf_end"]) != len(meta.executed):
            errs.append(f"kf_end has {len(trace['kf_end'])} entries for {len(meta.executed)} executed keyframes")
        for name, o in meta.objects.items():
            if o.kind in MOVABLE:
                errs += [f"missing column {name + s!r}" for s in OBJECT_COLUMNS if name + s not in trace]
    return errs


# ---- task metadata ----------------------------------------------------------------------------------
def _drop_none(obj: Any) -> dict[str, Any]:
    """Dataclass -> dict without the optional fields left at None (a step only carries what it uses)."""
    return {f.name: getattr(obj, f.name) for f in fields(obj) if getattr(obj, f.name) is not None}


@dataclass
class Step:
    """One atomic action of the plan and what the labeler checks it with.

    Field order is the JSON key order. Which optional fields a step sets depends on its skill:
    grasp: close_kf, grip_offset (end effector minus object position when held), width;
    place: dest, dest_xy, returning (back to where it came from), release_kf;
    open/close of a door or a button press: contact_kf, contact_point (handle/button), target_angle;
    pour/insert/stir: dest (and dest_xy for insert).
    """

    index: int
    action: str  # one of taxonomy.ATOMIC_ACTIONS
    object: str | None = None  # role name of the object acted on
    dest: str | None = None
    dest_xy: list[float] | None = None
    returning: bool | None = None
    target_angle: float | None = None
    keyframes: list[str] = field(default_factory=list)  # names of the step's nominal keyframes
    close_kf: str | None = None
    grip_offset: list[float] | None = None
    width: float | None = None
    release_kf: str | None = None
    contact_kf: str | None = None
    contact_point: list[float] | None = None

    def to_dict(self) -> dict[str, Any]:
        return _drop_none(self)


@dataclass
class Goal:
    """A success predicate of the task: `kind` names a predicate in sim_backends/goals.py, `args` its
    parameters (roles, tolerances), e.g. Goal("at", {"object": "obj", "xy": "target", "tol": 0.04})."""

    kind: str
    args: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, **self.args}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Goal":
        return cls(d["kind"], {k: v for k, v in d.items() if k != "kind"})


@dataclass
class ObjectInfo:
    kind: str  # vessel | rod | oven | button | rack
    dims: dict[str, float]  # vessel: radius, height, neck; rod: length, radius; oven: width, depth, height; ...
    home: list[float]  # initial position (x, y, z), metres


@dataclass
class NominalKeyframe:
    """The plan's keyframe as the labeler needs it (Keyframe without the controller's bookkeeping)."""

    name: str
    pos: list[float]
    quat: list[float]  # x, y, z, w
    gripper: int
    segment: int  # index of the Step it belongs to


@dataclass
class TaskMeta:
    """Everything the labeler needs besides the trace, for one episode."""

    steps: list[Step]
    goals: list[Goal]
    objects: dict[str, ObjectInfo]
    places: dict[str, list[float]]  # role or zone -> position, for goals and target substitution
    nominal: list[NominalKeyframe]
    executed: list[str]  # names of the executed keyframes, in order (index = image column)
    bench_top: float  # z of the bench surface
    liquid_total: dict[str, int]  # vessel -> particles it held at the start
    labels: dict[str, str]  # role -> words for task text and corrections
    description: str  # the task in words
    # World position of the arm's base; None in shards written before it was recorded (then no object is ever
    # read as out of the arm's reach: labeler.irreversible_sample).
    robot_base: list[float] | None = None

    @property
    def actions(self) -> list[str]:
        return [s.action for s in self.steps]

    def executed_steps(self) -> list[int]:
        """Step index of each executed keyframe (the keyframe's segment in the plan)."""
        seg = {k.name: k.segment for k in self.nominal}
        return [seg[n] for n in self.executed]

    def to_dict(self) -> dict[str, Any]:
        return {
            "steps": [s.to_dict() for s in self.steps],
            "goals": [g.to_dict() for g in self.goals],
            "objects": {k: {"kind": o.kind, "dims": o.dims, "home": o.home} for k, o in self.objects.items()},
            "places": self.places,
            "nominal": [
                {"name": k.name, "pos": k.pos, "quat": k.quat, "gripper": k.gripper, "segment": k.segment}
                for k in self.nominal
            ],
            "executed": self.executed,
            "bench_top": self.bench_top,
            "liquid_total": self.liquid_total,
            "labels": self.labels,
            "description": self.description,
            "robot_base": self.robot_base,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TaskMeta":
        return cls(
            steps=[Step(**s) for s in d["steps"]],
            goals=[Goal.from_dict(g) for g in d["goals"]],
            objects={k: ObjectInfo(o["kind"], dict(o["dims"]), list(o["home"])) for k, o in d["objects"].items()},
            places={k: list(v) for k, v in d["places"].items()},
            nominal=[
                NominalKeyframe(k["name"], list(k["pos"]), list(k["quat"]), int(k["gripper"]), int(k["segment"]))
                for k in d["nominal"]
            ],
            executed=list(d["executed"]),
            bench_top=float(d["bench_top"]),
            liquid_total=dict(d["liquid_total"]),
            labels=dict(d.get("labels", {})),
            description=str(d.get("description", "")),
            robot_base=None if d.get("robot_base") is None else [float(v) for v in d["robot_base"]],
        )

    @classmethod
    def from_json(cls, text: str) -> "TaskMeta":
        return cls.from_dict(json.loads(text))


def meta_dict(meta: "TaskMeta | dict[str, Any]") -> dict[str, Any]:
    """The JSON form the labeler and goal predicates read (what a shard stores), from either form."""
    return meta.to_dict() if isinstance(meta, TaskMeta) else meta
