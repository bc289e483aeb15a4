"""The supervised loop and labrobfail-supervise on real PyBullet episodes."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, begin_episode, cli, run, run_here
from test_train import tiny  # noqa: F401  (session fixture: a tiny Qwen3-VL checkpoint)

from labrobfail_vlm.actions import PRIMITIVES

FAST = ["image_size=48", "progress=false", "cameras=[front]"]


def supervise(*args, check=True, here=True):
    """labrobfail-supervise in this process (run_here), or as a process with here=False."""
    argv = [cli("supervise"), *FAST, *args]
    r = run_here(argv) if here else run(argv)
    if check:
        assert r.returncode == 0, r.stderr
    return r


def records(out):
    return [json.loads(line) for line in (Path(out) / "log.jsonl").read_text().splitlines()]


def test_three_oracle_trials_write_the_log_and_the_table(tmp_path):
    out = tmp_path / "sup"
    r = supervise(
        "policy=scripted",
        "supervisor=oracle",
        "baseline=false",
        "task=pick_place_beaker_small",
        "trials=3",
        f"out_dir={out}",
        here=False,  # the console script as a real process once in this file
    )
    recs = records(out)
    eps = [x for x in recs if x["event"] == "episode"]
    assert len(eps) == 3 and all(e["supervisor"] == "oracle" for e in eps)
    queries = [x for x in recs if x["event"] == "query"]
    assert queries and all(isinstance(q["latency_s"], float) for q in queries)
    for q in (q for q in queries if q["failure"]):  # every intervention logs its grid, primitives and outcome
        assert (out / q["grid"]).is_file() and q["primitives"] and "executed" in q["outcome"]
        assert q["strategy"] and q["correction"]
    assert sum(e["interventions"] for e in eps) >= 1  # seeds 0-2 of this scenario inject failures the oracle sees
    res = json.loads((out / "results.json").read_text())
    row = res["tasks"]["pick_place_beaker_small"]["oracle"]
    assert row["trials"] == 3 and row["success"] == sum(e["success"] for e in eps)
    assert "| pick_place_beaker_small | scripted |" in r.stdout


def test_supervision_helps_and_runs_repeat_exactly(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        supervise("supervisor=oracle", "task=pick", "trials=2", f"out_dir={out}")
    ra, rb = (json.loads((o / "results.json").read_text())["tasks"]["pick"] for o in (a, b))
    ea, eb = (
        [{k: v for k, v in x.items() if k != "latency_s"} for x in records(o) if x["event"] == "episode"]
        for o in (a, b)
    )
    assert ea == eb  # same seed, same episodes (latencies aside)
    assert ra["oracle"]["success"] >= ra["none"]["success"]
    assert ra["improvement"] == ra["oracle"]["rate"] - ra["none"]["rate"]


def test_a_stopped_run_goes_on_where_it_stopped_and_another_runs_settings_are_refused(tmp_path):
    """A run of 1 trial per arm, then the lines a kill leaves in its log (a query of the next trial, half a line),
    then the same command with 3 trials: each trial's log records and the table equal a run of 3 from nothing
    (latencies aside), the
    finished trial was not run again (its record, latency included, is the first run's), and the kill's lines are
    gone. The same out_dir with another budget is a one-line error naming it, and nothing there changes."""
    whole, part = tmp_path / "whole", tmp_path / "part"
    args = ["supervisor=oracle", "task=pick_place_beaker_small"]
    supervise(*args, "trials=3", f"out_dir={whole}")
    supervise(*args, "trials=1", f"out_dir={part}")
    first = [x for x in records(part) if x["event"] == "episode"]
    with open(part / "log.jsonl", "a") as f:
        f.write(json.dumps({"event": "query", "trial": "pick_place_beaker_small-none-001"}) + '\n{"event": "epi')
    supervise(*args, "trials=3", f"out_dir={part}")

    def by_trial(out):  # each trial's records in order (a resumed run logs the arms' later trials after the first)
        recs = [{k: v for k, v in x.items() if k != "latency_s"} for x in records(out)]
        return {t: [x for x in recs if x["trial"] == t] for t in sorted({x["trial"] for x in recs})}

    assert by_trial(part) == by_trial(whole) and len(by_trial(part)) == 6
    assert [x for x in records(part) if x["event"] == "episode" and x["trial"].endswith("-000")] == first
    res = [json.loads((o / "results.json").read_text())["tasks"] for o in (whole, part)]
    assert [{k: v for k, v in r["pick_place_beaker_small"]["oracle"].items() if "latency" not in k} for r in res] == [
        {k: v for k, v in res[0]["pick_place_beaker_small"]["oracle"].items() if "latency" not in k}
    ] * 2
    before = (part / "log.jsonl").read_bytes()
    r = supervise(*args, "trials=3", "loop.budget=1", f"out_dir={part}", check=False)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "holds trials of another run (config.loop.budget differs)" in r.stderr
    assert (part / "log.jsonl").read_bytes() == before
    # a run stopped before its first trial ended left nothing to keep: other settings are taken
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "run_config.json").write_text('{"config": {"seed": 7}}')
    (cut / "log.jsonl").write_text('{"event": "query", "trial": "x-none-000"}\n{"eve')
    supervise(*args, "trials=1", "baseline=false", f"out_dir={cut}")
    assert [x["event"] for x in records(cut)][-1] == "episode" and "x-none-000" not in (cut / "log.jsonl").read_text()


def test_vlm_supervisor_queries_the_analyzer_on_prefix_grids(tmp_path, tiny):  # noqa: F811
    out = tmp_path / "vlm"
    supervise(
        "supervisor=vlm",
        f"vlm.model={tiny}",
        "baseline=false",
        "task=open_oven_center",
        "trials=1",
        "loop.grids=all",
        "loop.budget=1",
        "loop.query_every=5",
        f"out_dir={out}",
    )
    qs = [x for x in records(out) if x["event"] == "query"]
    assert qs and all((out / q["grid"]).is_file() for q in qs)
    assert all(set(q["diagnosis"]) >= {"failure", "correction", "primitives"} for q in qs)
    for d in (q["diagnosis"] for q in qs if q["diagnosis"]["failure"]):  # template Q6: always executable
        assert d["primitives"] and all(p["op"] in PRIMITIVES for p in d["primitives"]), d
    lat = json.loads((out / "results.json").read_text())["tasks"]["open_oven_center"]["vlm"]
    assert lat["latency_p50_s"] > 0 and lat["latency_p95_s"] >= lat["latency_p50_s"]
    # a grid view the backend does not render is refused before the first trial
    r = supervise("supervisor=vlm", f"vlm.model={tiny}", "vlm.views=[front,wrist]", f"out_dir={out}_x", check=False)
    last = r.stderr.strip().splitlines()[-1]  # after the weights' loading bar
    assert r.returncode == 2 and last == "error: vlm.views: the backend renders ['front'], not ['wrist']", r.stderr
    assert "Traceback" not in r.stderr and not (out.parent / "vlm_x" / "log.jsonl").exists()


def test_a_family_runs_in_make_demos_world_from_the_command_line(tmp_path):
    """The backend's own options and a family's scenarios are command-line settings, as in generate.py: the
    demo model is supervised in the world it was trained in, and can be asked only once the policy stops."""
    from sim_backends.registry import backend_options

    out = tmp_path / "demo_world"
    world = [
        "backend_kwargs.custom_scene=configs/scenes/demo_bench.yaml",
        "backend_kwargs.camera_jitter=false",
        "backend_kwargs.max_distractors=0",
        "families.pick.scenarios=[pick_far_beaker_large]",
    ]
    supervise(
        "supervisor=oracle", "baseline=false", "task=pick", "trials=2", "loop.query_every=-1", *world, f"out_dir={out}"
    )
    eps = [x for x in records(out) if x["event"] == "episode"]
    assert [e["scenario"] for e in eps] == ["pick_far_beaker_large"] * 2
    queries = [x for x in records(out) if x["event"] == "query"]  # query_every=-1: only reviews once it stops
    assert queries and all(q["final"] for q in queries)
    for e in eps:  # a review that corrects hands control back; the next review finds nothing more to correct
        mine = [q["failure"] for q in queries if q["trial"] == e["trial"]]
        assert mine == [True] * e["interventions"] + [False] and e["interventions"] >= 1 and e["success"]
    cfg = json.loads((out / "results.json").read_text())["config"]
    assert cfg["backend_kwargs"]["custom_scene"] == "configs/scenes/demo_bench.yaml"
    # the scene file is loaded (a path the backend could not read would be refused before any trial)
    scene = backend_options("pybullet", {"custom_scene": str(ROOT / "configs/scenes/demo_bench.yaml")})
    assert scene["custom_scene"]["bench"] == [0.80, 0.78, 0.74, 1.0]


@pytest.mark.parametrize(
    "args, msg",
    [
        (["policy=teleop"], "policy: unknown policy 'teleop'"),
        (["task=juggle"], "task: unknown task 'juggle'"),
        (["policy=act"], "act.checkpoint: no checkpoint directory"),
        (["policy=openvla", "openvla.url=http://127.0.0.1:9/act"], "openvla.url: cannot reach"),
        (["supervisor=vlm", "vlm.model=/nonexistent"], "vlm.model: no such model directory"),
        (["loop.on_manual=panic"], "loop.on_manual"),
        (["trials=0"], "trials: must be a positive integer"),
        (["backend_kwargs.warp_drive=true"], "backend_kwargs.warp_drive: not an option of the pybullet backend"),
        (["backend_kwargs.custom_scene=tests/data/bad_vary_scene.yaml"], "backend_kwargs.custom_scene: vary"),
        (["families.place.scenarios=[juggle]"], "families.place: unknown scenario 'juggle'"),
        (["loop.query_every=-1", "loop.final_query=false"], "loop.query_every=-1 asks only the final query"),
    ],
)
def test_bad_settings_are_one_line_errors(tmp_path, args, msg):
    if args == ["policy=teleop"]:  # the first case as a real process, the rest in this one
        r = supervise(*args, f"out_dir={tmp_path / 'x'}", check=False, here=False)
    else:
        r = run_here([cli("supervise"), *FAST, *args, f"out_dir={tmp_path / 'x'}"])
    assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_stopped_learned_policy_is_reviewed_on_its_whole_trajectory():
    """ACT's ticks that the phase tracker cannot place on the plan all carry the first keyframe's name. While the
    policy runs they are one keyframe of a prefix grid; once it stops, the review grid spreads its cells over the
    ticks (a whole-trajectory grid), and a scripted run that stopped early keeps no blank cells for the steps it
    never ran."""
    import dataclasses

    from labrobfail_vlm.grid import GridConfig
    from sim_backends.registry import make_backend
    from sim_backends.supervision.base import live_grid

    cfg = GridConfig(width=256, height=64, max_frames=8, columns=8)
    src = make_backend("pybullet", image_size=32, cameras=["front"], max_distractors=0)
    try:
        plan = begin_episode(src)
        for k in plan + plan[::-1][:4]:  # twelve ticks along the plan, all named as its first keyframe
            src.step(dataclasses.replace(k, name=plan[0].name, segment=0))
        running, stopped = live_grid(src, plan, cfg), live_grid(src, plan, cfg, final=True)
        assert running.visible == 1 and running.keyframes == [11]
        assert stopped.visible == 8 and stopped.keyframes[0] == 0 and stopped.keyframes[-1] == 11
        assert len(set(stopped.keyframes)) == 8

        src.reset("pick_place_beaker_small", 0, "seen")
        src.begin()
        for k in plan[:6]:  # a scripted run that stopped after six of its eight keyframes
            src.step(k)
        small = dataclasses.replace(cfg, max_frames=4, columns=4)
        running, stopped = live_grid(src, plan, small), live_grid(src, plan, small, final=True)
        # while running, cells are kept (blank) for the plan's last two keyframes; the stopped run fills all four
        assert running.visible < 4 and stopped.visible == 4 and stopped.keyframes[-1] == 5
    finally:
        src.close()


def test_the_live_grid_keeps_to_the_supervisors_views_when_the_policy_sees_a_wrist_camera():
    """An ACT with a wrist camera needs the backend's wrist view, but the VLM was trained on front + side grids:
    its grid must show just those, in its order, and a view the backend does not render is a config error."""
    from labrobfail_vlm.config import ConfigError
    from labrobfail_vlm.grid import GridConfig
    from sim_backends.registry import make_backend
    from sim_backends.supervision.base import live_grid, view_indices

    cfg = GridConfig(width=128, height=64, max_frames=4, columns=4)
    src = make_backend("pybullet", image_size=32, cameras=["front", "side"], wrist=True, max_distractors=0)
    try:
        assert src.camera_names == ["front", "side", "wrist"]
        src.reset("pick_place_beaker_small", 0, "seen")
        plan = src.scripted_keyframes()
        src.begin()
        for k in plan[:4]:
            src.step(k)
        every = np.asarray(live_grid(src, plan, cfg).image)
        grid = lambda names: np.asarray(live_grid(src, plan, cfg, views=view_indices(src.camera_names, names)).image)  # noqa: E731
        fs, sf = grid(["front", "side"]), grid(["side", "front"])
    finally:
        src.close()
    # two views: rows of 32 px cells, one row per view in the order asked; every view: three rows (the wrist too)
    assert np.array_equal(fs[:32], sf[32:]) and np.array_equal(fs[32:], sf[:32])
    assert np.abs(fs[:32].astype(int) - fs[32:].astype(int)).mean() > 3
    assert not np.array_equal(every, fs)
    assert view_indices(["front", "side", "wrist"], None) is None
    with pytest.raises(ConfigError, match=r"vlm.views: the backend renders \['front', 'wrist'\], not \['side'\]"):
        view_indices(["front", "wrist"], ["front", "side"])


def test_oracle_names_a_stopped_policy_with_an_unmet_goal_an_incomplete_trajectory():
    """A policy (ACT, OpenVLA) that stops short of its goal leaves no detector signature; the oracle must still
    act at the final query: incomplete trajectory, corrected by resuming the unfinished grasp."""
    from sim_backends.registry import make_backend
    from sim_backends.supervision.loop import TaskFamily, episode_context
    from sim_backends.supervision.oracle import OracleSupervisor

    src = make_backend("pybullet", render=False)
    try:
        fam = TaskFamily("pick", ["pick_place_beaker_small"], 1, [{"kind": "held", "object": "obj"}])
        src.reset("pick_place_beaker_small", 0, "seen")
        src.begin()
        src.step(src.scripted_keyframes()[0])  # the approach above the beaker, then the policy stops
        oracle = OracleSupervisor()
        oracle.reset(episode_context(src, fam, "pick_place_beaker_small", 0, "seen"))
        assert not oracle.query(src).failure  # nothing has gone wrong while the policy still runs
        v = oracle.query(src, final=True)
        assert v.failure and v.failure_type == "incomplete_trajectory"
        assert "'held' unmet" in v.diagnosis["evidence"]
        assert [p["op"] for p in v.primitives][-1] == "gripper_close"  # G2: align with the beaker, then grasp
    finally:
        src.close()


def test_oracle_leaves_a_finished_success_alone(tmp_path):
    """Seed 10 of make demo's place scenario twists the wrist 1.1 rad while placing, yet the beaker still ends
    upright on the target: the labeler calls it a success (every goal holds). Once the policy has stopped the
    oracle follows the labeler; a correction there would pick the beaker up again and undo the placement."""
    out = tmp_path / "success"
    supervise(
        "supervisor=oracle",
        "task=pick_place_beaker_large",
        "trials=1",
        "seed=10",
        "loop.query_every=-1",
        "backend_kwargs.custom_scene=configs/scenes/demo_bench.yaml",
        "backend_kwargs.camera_jitter=false",
        "backend_kwargs.max_distractors=0",
        f"out_dir={out}",
    )
    eps = {e["supervisor"]: e for e in records(out) if e["event"] == "episode"}
    assert eps["none"]["success"] and eps["none"]["labels"]["failure_type"] is None
    assert eps["oracle"]["success"] and eps["oracle"]["interventions"] == 0


def test_a_refused_plan_is_no_intervention_and_leaves_the_policy_alone():
    """A supervisor that cries wolf at every keyframe with a plan the executor refuses (a pause, then a return to a
    grasp that was never omitted) must leave the run exactly as the unsupervised one: the arm never moves for it,
    the policy is never told to re-plan, and the budget stays unspent. A plan that did move the arm (a pause) is
    an intervention and the policy re-plans."""
    from sim_backends.policies.scripted import ScriptedPolicy
    from sim_backends.registry import make_backend
    from sim_backends.supervision.base import Supervisor, Verdict
    from sim_backends.supervision.loop import LoopConfig, TaskFamily, run_trial
    from sim_backends.supervision.oracle import NoSupervisor

    class Wolf(Supervisor):
        name = "wolf"

        def __init__(self, plan):
            self.plan = plan

        def query(self, src, final=False):
            return Verdict(True, "step_omission", 0, "return", "L2", [dict(p) for p in self.plan])

    class Counting(ScriptedPolicy):
        def reset(self, ctx):
            self.told = 0
            return super().reset(ctx)

        def after_correction(self, obs, executed=True, step=None):
            self.told += 1
            super().after_correction(obs, executed, step)

    hold = {"op": "hold_position", "args": {}}
    refused = [hold, {"op": "move_to_pose", "args": {"pose_id": "omitted:grasp"}}]
    fam = TaskFamily("pick", ["pick_place_beaker_small"], 1, [{"kind": "held", "object": "obj"}])
    src = make_backend("pybullet", render=False, max_distractors=0)
    runs = {}
    try:
        for name, sup in (("none", NoSupervisor()), ("refused", Wolf(refused)), ("hold", Wolf([hold]))):
            pol = Counting(inject_prob=0.0)
            ep = run_trial(src, pol, sup, fam, "pick_place_beaker_small", 0, "seen", LoopConfig(), None, name)
            runs[name] = (ep, pol.told, (ep["steps"], ep["keyframes"], ep["labels"]))
    finally:
        src.close()
    (none, _, path0), (ref, told_ref, path_ref) = runs["none"], runs["refused"]
    held, told_hold, path_hold = runs["hold"]
    assert ref["queries"] >= 3 and ref["interventions"] == 0 and told_ref == 0
    assert path_ref == path0 and ref["success"] == none["success"]  # the world went as if nobody had watched
    assert held["interventions"] == LoopConfig().budget and told_hold == held["interventions"]
    assert path_hold[1] > path0[1]  # each pause was a keyframe of its own


def test_an_unnamed_policy_is_first_asked_once_it_has_reached_a_plan_keyframe():
    """ACT and OpenVLA name no step: the tracker names each tick after the plan keyframe it heads for, and a
    query is due when that name changes. Its first tick heads for the first keyframe without reaching it: asking
    there would show the supervisor a one-cell grid of a move just begun (the wide-world model read it as an
    omitted step), so queries wait until a plan keyframe has been reached. A named (scripted) step is a whole
    keyframe and is asked after at once."""
    import dataclasses

    from sim_backends.policies.base import Action, Policy
    from sim_backends.registry import make_backend
    from sim_backends.supervision.base import Supervisor, Verdict
    from sim_backends.supervision.loop import LoopConfig, TaskFamily, run_trial

    class Replay(Policy):  # the plan's keyframes; unnamed, as a learned policy would, from a point half-way there
        name = "replay"

        def __init__(self, named):
            self.named = named

        def reset(self, ctx):
            self.plan = [Action.from_keyframe(k) for k in ctx.nominal]
            if not self.named:
                self.plan = [None] + [dataclasses.replace(a, name=None) for a in self.plan]
            return []

        def act(self, obs):
            if self.plan and self.plan[0] is None:  # half-way from where the hand starts to the first keyframe
                first = self.plan[1]
                mid = tuple((p + h) / 2 for p, h in zip(first.pos, obs.state["ee_pos"]))
                self.plan[0] = dataclasses.replace(first, pos=mid)
            return self.plan.pop(0) if self.plan else None

    class Count(Supervisor):
        name = "count"

        def reset(self, ctx):
            super().reset(ctx)
            self.seen = []

        def query(self, src, final=False):
            self.seen.append((len(src.executed_so_far()), final))
            return Verdict(False)

    fam = TaskFamily("pick", ["pick_place_beaker_small"], 2, [{"kind": "held", "object": "obj"}])
    src = make_backend("pybullet", render=False, max_distractors=0)
    asked = {}
    try:
        for named in (True, False):
            sup = Count()
            run_trial(src, Replay(named), sup, fam, "pick_place_beaker_small", 0, "seen", LoopConfig(), None, "t")
            asked[named] = sup.seen
    finally:
        src.close()
    n = asked[True][-1][0]  # the plan's keyframes, all run
    assert n >= 3 and asked[True] == [(k, False) for k in range(1, n + 1)] + [(n, True)]
    # unnamed: the half-way tick and the first keyframe (reached, its name unchanged) are not asked after; the
    # move on to the second keyframe is
    assert asked[False] == [(k, False) for k in range(3, n + 2)] + [(n + 1, True)]


def test_the_vlm_supervisor_takes_the_threshold_the_online_bench_calibrated(tmp_path, tiny):  # noqa: F811
    """vlm.alarm + vlm.alpha: the analyzer intervenes exactly where the alarm fires (strictly above the calibrated
    threshold); an alpha the bench did not calibrate, or one with too few successes, is a one-line error."""
    from labrobfail_vlm.config import ConfigError
    from sim_backends.supervision.base import make_supervisor

    alarm = tmp_path / "online.json"
    rows = {"0.05": {"threshold": 0.73, "alpha": 0.05}, "0.01": {"threshold": None, "alpha": 0.01}}
    alarm.write_text(json.dumps({"rows": {"model": rows}}))
    sup = make_supervisor("vlm", model=str(tiny), alarm=str(alarm), alpha=0.05)
    assert 0.73 < sup.fa.threshold < 0.7300001  # P = 0.73 does not fire, anything above does
    for alpha, needle in ((0.2, "was not calibrated"), (0.01, "too few calibration successes")):
        with pytest.raises(ConfigError, match=needle):
            make_supervisor("vlm", model=str(tiny), alarm=str(alarm), alpha=alpha)
    with pytest.raises(ConfigError, match="give both"):
        make_supervisor("vlm", model=str(tiny), alpha=0.05)
    robot_only = tmp_path / "robot_only.json"  # a model-free bench (make online-power): no alarm the VLM can take
    robot_only.write_text(json.dumps({"rows": {"robot signals (MLP)": rows}}))
    with pytest.raises(ConfigError, match="has no model row .* not the robot-signal monitors"):
        make_supervisor("vlm", model=str(tiny), alarm=str(robot_only), alpha=0.05)
    # a softmax can read exactly 1.0: a calibrated 1.0 never fires (refused as above); the float under 1 fires at 1.0
    rows = {"0.01": {"threshold": 1.0}, "0.05": {"threshold": math.nextafter(1.0, 0.0)}, "0.1": {"threshold": "x"}}
    alarm.write_text(json.dumps({"rows": {"model": rows}}))
    with pytest.raises(ConfigError, match="is 1.0: it never fires"):
        make_supervisor("vlm", model=str(tiny), alarm=str(alarm), alpha=0.01)
    assert make_supervisor("vlm", model=str(tiny), alarm=str(alarm), alpha=0.05).fa.threshold == 1.0
    with pytest.raises(ConfigError, match="not a P\\(failure\\) in \\[0, 1\\]"):
        make_supervisor("vlm", model=str(tiny), alarm=str(alarm), alpha=0.1)
