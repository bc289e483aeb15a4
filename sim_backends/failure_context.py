"""The failure as a correction needs it: which step failed, on what, towards where (the Context that fills the
placeholders of the paper's correction-strategy table, labrobfail_vlm/corrections.py), read from an episode's
task metadata and state trace. The dataset's Q6 answers (labrobfail_data/annotate.py) and the oracle supervisor
(sim_backends/supervision/oracle.py) both use it.
"""

from __future__ import annotations

from typing import Any

from labrobfail_vlm.corrections import Context
from labrobfail_vlm.taxonomy import Severity
from sim_backends.goals import object_fell
from sim_backends.schema import TaskMeta


def failure_context(
    row: dict[str, Any], meta: dict[str, Any], trace: dict[str, list], fatal: bool | None = None
) -> Context:
    """Fill the correction placeholders from task metadata (which step failed, on what, towards where).
    `fell` is read from `trace` (a prefix's trace: fallen by then); `fatal` defaults to the row's severity."""
    steps, labels = meta["steps"], meta.get("labels", {})
    ran = TaskMeta.from_dict(meta).executed_steps()  # step index (Keyframe.segment) of each executed keyframe
    kf = min(int(row["failure_keyframe"] or 0), len(ran) - 1)
    st = steps[ran[kf]] if ran else steps[0]
    word = lambda role: labels.get(role, str(role).replace("_", " "))  # noqa: E731
    obj = st.get("object")
    kind = meta["objects"].get(obj, {}).get("kind", "")
    device = {"oven": "door", "button": "button"}.get(kind, "")
    if row["failure_type"] == "sequence_reversal":  # redo the task's first grasp-and-place
        st = next((s for s in steps if s["action"] == "grasp"), st)
        obj = st.get("object")
    dest = st.get("dest") or next(
        (s["dest"] for s in steps[st["index"] :] if s.get("object") == obj and s.get("dest")), None
    )
    destination = "its original position" if dest is not None and dest == obj else word(dest or "target")
    pour = next((s for s in steps if s["action"] == "pour"), None)
    done = set(ran)
    omitted = next((s["action"] for s in steps if s["index"] not in done), st["action"])
    return Context(
        failure_type=row["failure_type"],
        action=st["action"],
        device=device,
        fell=object_fell(trace, meta),
        fatal=row["severity"] == int(Severity.FATAL) if fatal is None else fatal,
        target=word(obj) if obj else "object",
        destination=destination,
        source=word(pour["object"]) if pour else word(obj or "container"),
        omitted=omitted,
        opening=st["action"] == "open",
    )
