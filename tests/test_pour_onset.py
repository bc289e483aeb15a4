"""A pour's liquid failure dated from the pour's alignment when the vessel was brought beside its target
(sim_backends/labeler.pour_alignment), on hand-made traces; and scripts/relabel_shards.py on a shard written here.

The pour case is tests/test_detectors.py's carry with a liquid goal, its carry step made a pour into a `dest` vessel
standing where the plan aligns over it: the first keyframe of the step (s1_carry) is the alignment.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from sim_backends.labeler import SPILL_PARTICLES, derive_labels, irreversible_sample, pour_alignment
from sim_backends.schema import meta_dict
from tests.test_detectors import S0, S1, TARGET, _case, _simulate

RADIUS = 0.03  # the destination vessel's


def _pour(
    off: float = 0.0, spill_at: str | None = "s1_lower", into_other_at: str | None = None, again: bool = False
) -> tuple[dict, dict]:
    """A pour of `obj` into `dest`: aligned `off` m beside the plan (in y) at the end of s1_carry; liquid leaves
    every vessel three samples before `spill_at` ends and enters a bystander three samples before `into_other_at`
    ends (None: never; both at their first occurrence). `again`: the pour's keyframes run a second time (a
    correction's retry), the second alignment on plan."""
    _, meta_obj = _case("protocol_violation")
    if again:  # carry and lower, then the whole pour step once more
        meta_obj.executed = [*S0, *S1[:2], *S1]
    tr = _simulate(meta_obj, shift={"s1_carry": (0, off, 0)}, spill_into="bystander")
    meta = meta_dict(meta_obj)
    meta["steps"][1] = {"index": 1, "action": "pour", "object": "obj", "dest": "dest", "keyframes": list(S1)}
    dims = {"radius": RADIUS, "height": 0.1, "neck": 0.0}
    meta["objects"]["dest"] = {"kind": "vessel", "dims": dims, "home": list(TARGET)}
    n = len(tr["t"])
    tr.update({"dest.pos": [list(TARGET)] * n, "dest.quat": [[0.0, 0.0, 0.0, 1.0]] * n, "dest.contacts": [0] * n})

    def rising(name: str | None, amount: int) -> list[int]:
        at = n if name is None else tr["kf_end"][meta["executed"].index(name)] - 3
        return [0 if k < at else amount for k in range(n)]

    tr["liquid.outside"] = rising(spill_at, SPILL_PARTICLES + 1)
    tr["liquid.bystander"] = rising(into_other_at, 3)
    if again:  # the retry aligns as planned: over where dest stands from then on (the first pour missed it)
        second = tr["kf_end"][len(S0) + 2]
        here = [*tr["ee_pos"][second][:2], 0.0]
        tr["dest.pos"] = tr["dest.pos"][:second] + [here] * (n - second)
    return tr, meta


def _aligned_at(meta: dict, tr: dict) -> int:
    return tr["kf_end"][meta["executed"].index("s1_carry")]


def test_a_pour_aligned_beside_its_target_spills_from_the_alignment():
    tr, meta = _pour(off=0.1)
    assert pour_alignment(tr, meta, "obj", "dest") == (_aligned_at(meta, tr), pytest.approx(0.1, abs=1e-3))
    lab = derive_labels(tr, meta)
    assert lab.failure_type == "target_positioning_deviation" and "aligned 0.100 m off" in lab.evidence
    assert lab.failure_keyframe == meta["executed"].index("s1_carry")
    assert lab.onset_s == pytest.approx(tr["t"][_aligned_at(meta, tr)] - tr["t"][0])
    spill = irreversible_sample(tr, meta)  # the event itself stays where the liquid left
    assert spill is not None and spill[1] == "spill" and tr["t"][spill[0]] - tr["t"][0] > lab.onset_s


def test_a_pour_aligned_as_planned_or_within_the_opening_keeps_the_spill_as_its_onset():
    for off in (0.0, RADIUS - 0.005):
        tr, meta = _pour(off=off)
        assert pour_alignment(tr, meta, "obj", "dest") is None
        lab = derive_labels(tr, meta)
        assert lab.failure_type == "target_positioning_deviation" and "aligned" not in lab.evidence
        assert lab.failure_keyframe == meta["executed"].index("s1_lower")


def test_the_first_liquid_astray_is_the_one_dated_from_the_alignment():
    """Spilled first, then into a bystander: still a spill, from the alignment; into the bystander first: the
    protocol violation, from the alignment. The later one never takes the alignment's sample (a tie would hand the
    type to whichever detector runs first)."""
    tr, meta = _pour(off=0.1, spill_at="s1_lower", into_other_at="s1_release")
    lab = derive_labels(tr, meta)
    assert lab.failure_type == "target_positioning_deviation" and lab.failure_keyframe == 4
    tr, meta = _pour(off=0.1, spill_at="s1_release", into_other_at="s1_lower")
    lab = derive_labels(tr, meta)
    assert lab.failure_type == "protocol_violation" and "entered bystander" in lab.evidence
    assert lab.failure_keyframe == meta["executed"].index("s1_carry")


def test_a_redated_liquid_failure_never_takes_an_earlier_event_of_another_detector(monkeypatch):
    """The detectors race on their own samples; only the winner is redated. A failure another detector finds between
    the alignment and the spill stays the label (its type, its sample), however astray the pour was aligned."""
    from sim_backends import labeler

    tr, meta = _pour(off=0.1)
    between = _aligned_at(meta, tr) + 2

    def twisted(trace: dict, meta: dict):
        return between, "pose_control_error", "twisted while lowering"

    monkeypatch.setattr(labeler, "DETECTORS", [*labeler.DETECTORS, twisted])
    lab = derive_labels(tr, meta)
    assert lab.failure_type == "pose_control_error" and lab.onset_s == pytest.approx(tr["t"][between] - tr["t"][0])


def test_the_live_supervisor_still_sees_the_spill_after_acting_past_the_alignment():
    """oracle.live_failure runs the detectors on the trace so far and keeps events after its last intervention: a
    spill found at its own sample, not at the alignment it is labelled from, so acting between the two hides
    nothing."""
    from sim_backends.schema import TaskMeta
    from sim_backends.supervision.oracle import live_failure

    tr, meta = _pour(off=0.1)
    ev = live_failure(tr, TaskMeta.from_dict(meta), after_sample=_aligned_at(meta, tr) + 1)
    assert ev is not None and ev[1] == "target_positioning_deviation" and "spill" in ev[2]
    assert ev[0] == tr["kf_end"][meta["executed"].index("s1_lower")] - 3


def test_a_pour_run_again_is_judged_by_its_own_alignment():
    """A misaligned pour retried on plan: a spill in the retry is the retry's (its own sample, so a supervisor that
    acted after the first alignment still sees it); the first alignment is found only before the second."""
    tr, meta = _pour(off=0.1, spill_at=None, again=True)
    second = tr["kf_end"][len(S0) + 2]
    n = len(tr["t"])
    tr["liquid.outside"] = [0 if k < second + 5 else SPILL_PARTICLES + 1 for k in range(n)]
    lab = derive_labels(tr, meta)
    assert lab.failure_type == "target_positioning_deviation" and "aligned" not in lab.evidence
    assert lab.onset_s == pytest.approx(tr["t"][second + 5] - tr["t"][0])
    assert pour_alignment(tr, meta, "obj", "dest") is None  # the latest alignment is on plan
    first = _aligned_at(meta, tr)
    assert pour_alignment(tr, meta, "obj", "dest", before=second)[0] == first
    assert pour_alignment(tr, meta, "obj", "dest", before=first) is None


def test_a_pour_that_delivers_is_a_success_however_it_was_aligned():
    tr, meta = _pour(off=0.1, spill_at=None)
    tr["liquid.dest"] = [0] * (len(tr["t"]) - 1) + [8]
    tr["liquid.obj"] = tr["liquid.obj"][:-1] + [2]
    assert derive_labels(tr, meta).success


def _shard_row(tr: dict, meta: dict, **labels: Any) -> dict[str, Any]:
    return {
        "episode_id": "ep0",
        "pair_id": "0",
        "role": "failure",
        "backend": "pybullet",
        "task": "pour",
        "scenario": "pour",
        "variant": "seen",
        "seed": 1,
        "actions": ["grasp", "pour"],
        "horizon": "short",
        "num_keyframes": len(meta["executed"]),
        "camera_names": ["front"],
        "images": [[b""]],
        "state_trace": json.dumps(tr),
        "task_meta": json.dumps(meta),
        "keyframes": "[]",
        "nominal_keyframes": "[]",
        "perturbation": json.dumps({"operator": "control:translate"}),
        "cameras": "null",
        **labels,
    }


def test_relabel_shards_rewrites_the_labels_from_the_trace_into_a_new_folder(tmp_path: Path, capsys):
    from scripts import relabel_shards
    from sim_backends.shards import SCHEMA, write_shard

    tr, meta = _pour(off=0.1)
    old = {"success": False, "failure_type": "target_positioning_deviation", "category": 0, "severity": 2}
    old |= {"failure_keyframe": 5, "onset_s": 9.0, "evidence": "spill"}
    src = tmp_path / "shards" / "seen"
    src.mkdir(parents=True)
    write_shard(src / "shard-00000.parquet", [_shard_row(tr, meta, **old)], SCHEMA)
    (src / "run.json").write_text('{"variant": "seen"}')
    (src / "manifest.json").write_text('{"episodes": 1, "nominal_redraws": {"count": 0}}')
    assert relabel_shards.main([f"shards={tmp_path / 'shards'}", f"out={tmp_path / 'new'}", "progress=false"]) == 0
    (row,) = pq.read_table(tmp_path / "new" / "seen" / "shard-00000.parquet").to_pylist()
    assert row["failure_keyframe"] == meta["executed"].index("s1_carry") and "aligned" in row["evidence"]
    assert row["state_trace"] == json.dumps(tr) and (src / "shard-00000.parquet").exists()
    man = json.loads((tmp_path / "new" / "seen" / "manifest.json").read_text())
    assert man["relabelled"]["changed"]["onset_s"] == 1 and man["nominal_redraws"] == {"count": 0}
    assert man["by_failure_type"]["target_positioning_deviation"] == 1
    assert json.loads((tmp_path / "new" / "relabel.json").read_text())["seen"]["onset_s"] == 1
    assert json.loads((tmp_path / "new" / "seen" / "run.json").read_text()) == {"variant": "seen"}
    # an outcome the labeler would now read otherwise is a new generation's business: refused, nothing written
    write_shard(src / "shard-00000.parquet", [_shard_row(tr, meta, **(old | {"success": True}))], SCHEMA)
    with pytest.raises(ValueError, match="ep0: the labeler now says failure"):
        relabel_shards.main([f"shards={src}", f"out={tmp_path / 'other'}", "progress=false"])
    assert not (tmp_path / "other" / "shard-00000.parquet").exists()
    with pytest.raises(ValueError, match="out: .* is the folder read"):
        relabel_shards.main([f"shards={src}", f"out={src}"])


def test_a_section_made_on_relabelled_shards_says_so(tmp_path: Path):
    """write_results' spliced section names the run it came from; a relabelled run's line also says whose episodes
    its shards hold and how many labels moved, summed over its variants; a generated run's says nothing more."""
    from scripts.write_results import relabelled

    for variant, n in (("seen", 3), ("val_both", 1)):
        (tmp_path / "shards" / variant).mkdir(parents=True)
        entry = {"from": f"outputs/r7dec/shards/{variant}", "changed": {"onset_s": n, "evidence": n}}
        (tmp_path / "shards" / variant / "manifest.json").write_text(json.dumps({"relabelled": entry}))
    (line,) = relabelled(tmp_path)
    assert "`outputs/r7dec/shards`'s episodes" in line and "evidence 4, onset_s 4" in line
    (tmp_path / "gen" / "shards" / "seen").mkdir(parents=True)
    (tmp_path / "gen" / "shards" / "seen" / "manifest.json").write_text("{}")
    assert relabelled(tmp_path / "gen") == []
