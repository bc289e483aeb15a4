"""The Action Dictionary: correction instructions (Q6) -> executable control primitives.

The paper's appendix tables ("Action Dictionary: Position and Orientation mappings", "... Gripper action
mappings") map phrases of a correction to primitives of a Franka arm. This module is that mapping, on the
model side (no simulator): `to_primitives(text, objects)` splits an instruction into clauses and maps each
clause through an ordered list of phrase rules; names in the text ({target}, {destination}, {source}) are
resolved against the scene's object and place names. A clause no rule covers becomes
`{"op": "manual", "args": {"phrase": ...}}`: never a guess. sim_backends/executor.py runs the result.

A primitive is `{"op": name, "args": {...}}`; the 14 names and their arguments (paper notation):

  position     hold_position()  delta_pos(direction, dist[, until, into])  oscillate(axis, amp, n)
               align_to(target_id[, stage])  move_above(dest_id, h[, obj])  align_above(src, dest)
               move_to_pose(pose_id)
  orientation  set_orient(roll, pitch)  hold_orientation()  rotate(axis, angle)  tilt_pour(angle, v)
  gripper      hold_gripper()  gripper_open()  gripper_close()

Frames (the executor's contract): "forward"/"backward" run along the gripper's approach axis (the paper's
x = +d for its horizontal gripper; for a top-down gripper, forward is down), up/down along world z,
left/right along world y; `rotate` turns about a world axis; `set_orient(roll=0, pitch=0)` levels the gripper
to the plan's orientation for the step, keeping its heading (yaw).

Special names a correction may use besides the scene's: "door handle" (the handle of the device being
operated), "its original position" (the held object's home), "target position" (where the plan puts it),
"omitted:<action>" (pose id: the first keyframe of the step with that action that never ran; for a grasp that ran but
did not take, where the plan has the object in the hand and the hand does not hold it, that grasp made again).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS

PRIMITIVES: dict[str, tuple[str, ...]] = {  # name -> arguments (paper appendix, plus optional extras)
    "hold_position": (),
    "delta_pos": ("direction", "dist", "until", "into"),
    "oscillate": ("axis", "amp", "n"),
    "align_to": ("target_id", "stage"),
    "move_above": ("dest_id", "h", "obj"),
    "align_above": ("src", "dest"),
    "move_to_pose": ("pose_id",),
    "set_orient": ("roll", "pitch"),
    "hold_orientation": (),
    "rotate": ("axis", "angle"),
    "tilt_pour": ("angle", "v"),
    "hold_gripper": (),
    "gripper_open": (),
    "gripper_close": (),
}
MANUAL = "manual"  # not a primitive: a phrase the dictionary cannot map (or the paper's manual strategy)

# Default magnitudes (metres, radians, rad/s): the paper's d, amp, n, h, theta, v.
STEP_D = 0.05  # delta_pos without a stated distance
MAX_TRAVEL = 0.40  # delta_pos with an `until` condition stops after this far at the latest
PRESS_TRAVEL = 0.03
INSERT_D = 0.08
OSC_AMP, OSC_N = 0.01, 3
ABOVE_H = 0.01  # move_above: the held object's bottom this far above the destination surface
POUR_ANGLE, POUR_V = 2.0, 0.6
TILT_ANGLE = 0.5

DOOR_HANDLE = "door handle"
ORIGINAL = "its original position"
TARGET_POSITION = "target position"
_SPECIAL = {
    DOOR_HANDLE: ("door handle", "handle", "door", "handle of door", "oven door", "door of oven"),
    ORIGINAL: (
        "its original position",
        "original position",
        "its home",
        "home position",
        "its place",
        "where it came from",
        "its original place",
    ),
    TARGET_POSITION: ("target position", "target location", "destination"),
}


def prim(op: str, **args: Any) -> dict[str, Any]:
    if op not in PRIMITIVES and op != MANUAL:
        raise ValueError(f"action dictionary: unknown primitive {op!r}")
    return {"op": op, "args": args}


def manual(phrase: str) -> dict[str, Any]:
    return prim(MANUAL, phrase=phrase)


def format_primitive(p: dict[str, Any]) -> str:
    """`align_to(target_id='small beaker')`: the paper's notation, for logs and reports."""
    return f"{p['op']}({', '.join(f'{k}={v!r}' for k, v in p['args'].items())})"


def norm(text: str) -> str:
    """Lower case, no articles, single spaces, no trailing punctuation: the form rules and names are matched in."""
    t = re.sub(r"[^a-z0-9'\-/ ,;:]+", " ", text.lower().replace("centre", "center"))
    t = re.sub(r"\b(the|a|an)\b", " ", t)
    return re.sub(r"\s+", " ", t).strip(" ,;:")


# ---- names ------------------------------------------------------------------------------------------------
@dataclass
class _Names:
    """Resolves a phrase from the text to a scene name (exactly, or as the only name containing its words)."""

    objects: list[str]
    last: str | None = None  # the object most recently named: "keep the gripper open until centered" needs it
    errors: list[str] = field(default_factory=list)

    def resolve(self, phrase: str) -> str | None:
        p = norm(phrase)
        for key, forms in _SPECIAL.items():
            if p in forms:
                return key
        if not self.objects:  # no scene given: keep the phrase as it is (the executor checks it)
            self.last = p
            return p
        exact = [o for o in self.objects if norm(o) == p]
        words = set(p.split())
        partial = [o for o in self.objects if words and words <= set(norm(o).split())]
        hit = exact[0] if exact else partial[0] if len(partial) == 1 else None
        if hit is not None:
            self.last = hit
        return hit


# ---- phrase rules -----------------------------------------------------------------------------------------
_ARM = r"(?:(?:robotic |robot )?arm|gripper|end-effector|end effector|hand)"
_MOVE = r"(?:move|bring|shift|drive|guide|take|carry)(?: it)?"
_OBJ = r"(?P<{}>[a-z0-9][a-z0-9 '\-/]*?)"
_DIRS = r"(?P<dir>forward|forwards|backward|backwards|back|up|upward|upwards|down|downward|downwards|left|right)"
_DIR_CANON = {
    "forwards": "forward",
    "backwards": "backward",
    "back": "backward",
    "upward": "up",
    "upwards": "up",
    "downward": "down",
    "downwards": "down",
    "lower": "down",
    "raise": "up",
    "lift": "up",
}


def _o(name: str) -> str:
    return _OBJ.format(name)


Builder = Callable[[re.Match, _Names], "list[dict[str, Any]] | None"]  # None: a name did not resolve


def _named(n: _Names, m: re.Match, group: str) -> str | None:
    return n.resolve(m.group(group)) if m.group(group) else None


def _direction(m: re.Match) -> str:
    d = m.group("dir")
    return _DIR_CANON.get(d, d)


def _dist(m: re.Match, default: float) -> float:
    if "d" not in m.groupdict() or not m.group("d"):
        return default
    return round(float(m.group("d")) * {"cm": 0.01, "mm": 0.001, "m": 1.0}[m.group("u")], 4)


def _b_delta(m: re.Match, n: _Names) -> list[dict[str, Any]]:
    return [prim("delta_pos", direction=_direction(m), dist=_dist(m, STEP_D))]


def _b_door(m: re.Match, n: _Names) -> list[dict[str, Any]]:
    word = m.group("state") or m.group("verb")
    n.last = DOOR_HANDLE
    until = "door_open" if word in ("open", "opened") else "door_closed"
    return [prim("delta_pos", direction=_direction(m), dist=MAX_TRAVEL, until=until)]


def _b_insert(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    t = _named(n, m, "t")
    return None if t is None else [prim("delta_pos", direction="forward", dist=INSERT_D, into=t)]


def _b_align(m: re.Match, n: _Names, stage: str | None = None) -> list[dict[str, Any]] | None:
    t = _named(n, m, "t")
    if t is None:
        return None
    return [prim("align_to", target_id=t, **({"stage": stage} if stage else {}))]


def _b_center_last(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    """ "keep the gripper open until centered": open, then centre on the object named before."""
    if n.last is None:
        return None
    return [prim("gripper_open"), prim("align_to", target_id=n.last)]


def _b_grasp(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    t = _named(n, m, "t")
    return None if t is None else [prim("gripper_open"), prim("align_to", target_id=t), prim("gripper_close")]


def _b_above(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    obj, dest = _named(n, m, "t"), _named(n, m, "d")
    if obj is None or dest is None:
        return None
    n.last = obj
    return [prim("move_above", dest_id=dest, h=ABOVE_H, obj=obj)]


def _b_align_above(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    src, dest = _named(n, m, "t"), _named(n, m, "d")
    if src is None or dest is None:
        return None
    n.last = src
    return [prim("align_above", src=src, dest=dest)]


def _b_move_to(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    before = n.last  # the object named earlier is the one being carried
    dest = _named(n, m, "d")
    if dest is None:
        return None
    held = before if before not in (None, DOOR_HANDLE, dest) else None
    n.last = held or dest
    out = [prim("move_above", dest_id=dest, h=ABOVE_H, **({"obj": held} if held else {}))]
    if m.group("level"):
        out.append(prim("set_orient", roll=0.0, pitch=0.0))
    return out


def _b_place(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    obj = _named(n, m, "t")
    dest = _named(n, m, "d") if m.group("d") else TARGET_POSITION
    if obj is None or dest is None:
        return None
    return [prim("move_above", dest_id=dest, h=ABOVE_H, obj=obj), prim("gripper_open")]


def _b_omitted(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    a = norm(m.group("a"))
    return [prim("move_to_pose", pose_id=f"omitted:{a}")] if a in ATOMIC_ACTIONS else None


def _b_close(m: re.Match, n: _Names) -> list[dict[str, Any]] | None:
    if m.groupdict().get("t"):
        if _named(n, m, "t") is None:
            return None
    return [prim("gripper_close")]


def _fixed(*prims: dict[str, Any]) -> Builder:
    return lambda m, n: [dict(p, args=dict(p["args"])) for p in prims]


_LEVEL = r"(?P<level> while (?:maintaining|keeping|holding) (?:gripper )?orientation (?:horizontal|level))?"
# Ordered: the first rule whose pattern matches the whole clause wins (specific phrasings first).
RULES: list[tuple[str, Builder]] = [
    # conditions and purposes that carry no motion of their own
    (r"(?:in order )?to (?:complete|finish) (?:experiment|task|operation)(?: safely)?", _fixed()),
    (r"after (?:completing|finishing) (?:operation|current operation|step|task)", _fixed()),
    (
        r"(?:then )?(?:resume|continue)(?: with)? (?:remaining |rest of )?(?:workflow|execution|task|plan|steps)",
        _fixed(),
    ),
    (rf"{_MOVE} {_ARM}", _fixed()),  # "move the robotic arm," whose goal the next clause names (S2)
    # position
    (
        rf"(?:keep|hold|maintain) (?:{_ARM} )?position (?:unchanged|fixed|still|steady)|(?:keep|hold) {_ARM} "
        r"(?:still|in place|stationary)|pause(?: current)? execution|stop(?: {_ARM})?(?: motion| moving)?"
        r"|hold(?: current)? position",
        _fixed(prim("hold_position")),
    ),
    (rf"{_MOVE} (?:{_ARM} )?forward to insert(?: it)? into {_o('t')}", _b_insert),
    (
        rf"{_MOVE} (?:{_ARM} )?(?P<dir>forward|down|downward) until(?: it is| button is)? pressed",
        lambda m, n: [prim("delta_pos", direction=_direction(m), dist=PRESS_TRAVEL, until="pressed")],
    ),
    (
        rf"{_MOVE} (?:{_ARM} )?{_DIRS} (?:until door is (?:fully )?(?P<state>open|opened|closed|shut)"
        r"|to (?P<verb>open|close) door)",
        _b_door,
    ),
    (
        rf"(?:{_MOVE} (?:{_ARM} )?(?:from )?side to side(?: repeatedly)?|stir(?: liquid)?)"
        r"(?: until(?: liquid is)? (?:fully |well |thoroughly )?(?:stirred|mixed))?",
        _fixed(prim("oscillate", axis="y", amp=OSC_AMP, n=OSC_N)),
    ),
    (rf"{_MOVE} (?:{_ARM} )?{_DIRS}(?: by (?P<d>[0-9.]+) ?(?P<u>cm|mm|m))?", _b_delta),
    (rf"(?P<dir>lower|raise|lift)(?: {_ARM}| it)?(?: by (?P<d>[0-9.]+) ?(?P<u>cm|mm|m))?", _b_delta),
    (rf"{_MOVE} (?:{_ARM} )?to (?:center|align) (?:gripper )?(?:on|with|over|at) {_o('t')}", _b_align),
    (
        rf"(?:keep gripper open and )?{_MOVE} (?:{_ARM} )?until {_o('t')} is centered"
        r"(?: (?:within|in|between) (?:gripper|fingers))?",
        _b_align,
    ),
    (rf"(?:reposition|re-position|realign|re-align) (?:{_ARM} )?to center {_o('t')}", _b_align),
    (rf"(?:center|align) (?:gripper )?(?:on|with|over) {_o('t')}", _b_align),
    (rf"{_MOVE} (?:{_ARM} )?to (?:position|place|put|hold) {_o('t')} (?:above|over) {_o('d')}", _b_above),
    (rf"{_MOVE} (?:{_ARM} )?to align {_o('t')} (?:above|over|with) {_o('d')}", _b_align_above),
    (
        rf"(?:return|go back) to (?:perform|do|execute|carry out|redo) (?:omitted|skipped|missing|missed) {_o('a')}"
        r"(?: step| action)?",
        _b_omitted,
    ),
    (
        rf"{_MOVE} (?:{_ARM} )?(?:toward|towards|to approach|closer to) {_o('t')}",
        lambda m, n: _b_align(m, n, stage="pre"),
    ),
    (rf"(?:{_MOVE} (?:{_ARM} )?to )?(?:grasp|grab|pick up|pick) {_o('t')}(?: with gripper closed)?", _b_grasp),
    (rf"{_MOVE} (?:{_ARM} )?to {_o('d')}{_LEVEL}", _b_move_to),
    (
        rf"(?:place|put|set) (?:down )?{_o('t')}(?: down)?(?: (?:at|on|in|into) {_o('d')})?"
        r"(?: steadily| stably| carefully| gently| upright)?",
        _b_place,
    ),
    # orientation
    (
        rf"(?:keep|adjust|set|return|restore|maintain|hold|level)(?:ing)? (?:{_ARM} )?(?:orientation )?(?:to )?"
        r"(?:horizontal|level)(?: orientation)?|(?:while )?(?:maintaining|keeping) orientation (?:horizontal|level)",
        _fixed(prim("set_orient", roll=0.0, pitch=0.0)),
    ),
    (
        rf"(?:keep|maintain|hold)(?:ing)? (?:{_ARM} )?orientation(?: unchanged| fixed| constant| same)?"
        r"|orientation (?:unchanged|fixed|constant)",
        _fixed(prim("hold_orientation")),
    ),
    (
        rf"(?:progressively |gradually |slowly )?tilt (?:{_ARM}|it|{_o('s')})(?: progressively| gradually)? until "
        r"(?:liquid is |it is )?(?:fully |completely )?poured(?: out)?|pour (?:out )?(?:liquid|it)(?: into .*)?",
        _fixed(prim("tilt_pour", angle=POUR_ANGLE, v=POUR_V)),
    ),
    (rf"tilt (?:{_ARM}|it)", _fixed(prim("rotate", axis="y", angle=TILT_ANGLE))),
    # gripper
    (
        r"(?:keep|maintain|hold) (?:current )?gripper state(?: unchanged)?|maintain gripper",
        _fixed(prim("hold_gripper")),
    ),
    (r"keep gripper open until (?:it is )?centered", _b_center_last),
    (
        r"keep (?:gripper )?open|open (?:gripper|fingers)(?: to (?:release|place|let go|drop))?"
        rf"|release(?: gripper| it| {_o('t')})?|let go(?: of .*)?",
        _fixed(prim("gripper_open")),
    ),
    (
        r"(?:close|shut) (?:gripper|fingers)(?: firmly| tightly)?(?: to (?:grasp|grip|secure|hold)"
        rf"(?: (?:grasp|grip|it|{_o('t')}))?)?|grip (?:it )?(?:firmly|tightly)|secure (?:grasp|grip)",
        _b_close,
    ),
    (rf"(?:keep|hold) (?:gripper )?closed(?: (?:on|to secure|around) {_o('t')})?", _b_close),
]
_COMPILED = [(re.compile(p), b) for p, b in RULES]
# clause boundaries: commas, "then", "and", and before a trailing purpose ("... to complete the experiment")
_SPLIT = re.compile(
    r"\s*(?:,\s*(?:and\s+)?(?:then\s+)?|;\s*|\s+then\s+|\s+and\s+(?:then\s+)?"
    r"|\s+(?=(?:in order )?to (?:complete|finish) ))"
)
_LEAD = re.compile(r"^(?:first|then|and|finally|next|afterwards|after that)\s+")
_MANUAL_TEXT = re.compile(r"\bmanual(?:ly)?\b|\bhuman\b|\boperator\b")


def clauses(text: str) -> list[str]:
    """The clauses of an instruction, normalised (see `norm`), in order."""
    parts = [_LEAD.sub("", c.strip()) for c in _SPLIT.split(norm(text))]
    return [c for c in parts if c]


def to_primitives(text: str, objects: Sequence[str] = ()) -> list[dict[str, Any]]:
    """Map a correction instruction to primitives; `objects` are the scene's object and place names.

    The no-correction sentence and empty text give []. The manual strategy and every clause that no rule maps
    (or whose object is not in the scene) give a `manual` entry with the phrase.
    """
    from labrobfail_vlm.questions import NO_CORRECTION

    if not text.strip() or norm(text) == norm(NO_CORRECTION):
        return []
    if _MANUAL_TEXT.search(norm(text)):
        return [manual(text.strip())]
    names = _Names([o for o in objects if o])
    out: list[dict[str, Any]] = []
    for c in clauses(text):
        got = None
        for rx, build in _COMPILED:
            m = rx.fullmatch(c)
            if m is not None:
                got = build(m, names)
                break
        out.extend(got if got is not None else [manual(c)])
    return out


def executable(prims: Sequence[dict[str, Any]]) -> bool:
    """True when every entry is a primitive (no `manual` phrase) and there is at least one."""
    return bool(prims) and all(p["op"] != MANUAL for p in prims)
