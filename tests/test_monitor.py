"""The robot-signal monitor the online bench saves (labrobfail_vlm/monitor.py) and the supervisor running it live
(sim_backends/supervision/monitor.py) on real PyBullet episodes."""

import json
from pathlib import Path

import numpy as np
import pytest
from test_supervise import records, supervise
from test_train import tiny  # noqa: F401  (session fixture: a tiny Qwen3-VL checkpoint)

from labrobfail_vlm.bench import robot_baseline
from labrobfail_vlm.bench.robot_baseline import DENSE, ROBOT, ROBOT_PAIR
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.monitor import CONFIG, WEIGHTS, Mlp, RobotMonitor, read_mlps, save_monitor


def _fitted(features: int, seed: int = 0):
    """A tiny real pipeline of the bench's kind on `features` columns (about a third labelled failed)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(300, features))
    return robot_baseline._mlp(x, x[:, 0] + 0.3 * x[:, 3] > 0.4, seed)


def _rows(thresholds: dict[str, list]) -> dict:
    """Bench rows with the given thresholds per row name at alphas 0.05 and 0.1 (a pair: two per alpha)."""
    out = {}
    for name, ths in thresholds.items():
        one = {"threshold": ths[0], "alpha": 0.05} if len(ths) == 1 else {"thresholds": ths, "alphas": [0.025] * 2}
        out[name] = {"0.05": one, "0.1": {"threshold": None, "alpha": 0.1} if len(ths) == 1 else one}
    return out


def write_monitor(where: Path, frame: float | None, dense: float | None, chosen: str | None = ROBOT_PAIR) -> Path:
    """A monitor of the three robot rows whose members sound above `frame` and `dense` (a real fitted MLP each)."""
    models = {"frame": _fitted(16), "dense": _fitted(17, 1)}
    rows = _rows({ROBOT: [frame], DENSE: [dense], ROBOT_PAIR: [frame, dense]})
    return save_monitor(where, models, rows, {"chosen_on_calibration": chosen, "max_frames": 8, "delta": 0.1})


def test_a_saved_monitor_gives_scikit_learns_p_failure_and_the_bench_thresholds(tmp_path):
    pipe = _fitted(16)
    x = np.random.default_rng(5).normal(size=(50, 16)) * 3
    want = pipe.predict_proba(x)[:, 1]
    assert np.allclose(Mlp.from_sklearn(pipe).p_failure(x), want, rtol=0, atol=1e-12)
    where = write_monitor(tmp_path / "m", 0.4, 0.6)
    assert sorted(p.name for p in where.iterdir()) == [CONFIG, WEIGHTS]  # no pickle: arrays and JSON
    m = RobotMonitor.load(where, 0.05)  # the row the bench chose (the pair), at 0.05
    assert m.row == ROBOT_PAIR and m.delta == 0.1 and m.max_frames == 8
    assert {k: t for k, (_, t) in m.members.items()} == {"frame": 0.4, "dense": 0.6}
    assert np.allclose(
        m.frame_scores(x[:, :12], 8), pipe.predict_proba(robot_baseline.prefix_features(x[:, :12], 8))[:, 1]
    )
    s = np.asarray([0.1, 0.4, 0.41, 0.9])
    assert m.sounds("frame", s) == 2 and m.sounds("dense", s) == 3  # strictly above, as the alarm
    assert list(RobotMonitor.load(where, 0.05, DENSE).members) == ["dense"]
    # a chosen row that is not a robot-signal one (the model's): the pair, the monitor a supervisor can run alone
    assert RobotMonitor.load(write_monitor(tmp_path / "n", 0.4, 0.6, "model"), 0.05).row == ROBOT_PAIR


@pytest.mark.parametrize(
    "change, kwargs, needle",
    [
        ("nothing", {"alpha": 0.2}, "vlm.alpha: 0.2 was not calibrated for this monitor (it has 0.05, 0.1)"),
        ("nothing", {"alpha": 0.1, "row": ROBOT}, "too few calibration successes for alpha 0.1"),
        ("nothing", {"alpha": 0.05, "row": "model"}, "vlm.monitor_row: 'model' is not in"),
        ("config", {"alpha": 0.05}, "holds no readable monitor.json"),
        ("format", {"alpha": 0.05}, "is not a robot-signal monitor"),
        ("weights", {"alpha": 0.05}, "cannot read"),
        ("frames", {"alpha": 0.05}, "gives no grid size (max_frames)"),
        ("threshold", {"alpha": 0.05}, "not a P(failure) in [0, 1]"),
        ("rows", {"alpha": 0.05}, "is not a robot-signal monitor"),
        ("members", {"alpha": 0.05}, "is malformed"),
        ("stale", {"alpha": 0.05}, "its sha256 is not the one monitor.json names"),
        ("width", {"alpha": 0.05}, "its frame MLP reads 20 features, the robot's signals give 16"),
    ],
)
def test_a_bad_monitor_is_a_one_line_error(tmp_path, change, kwargs, needle):
    where = write_monitor(tmp_path / "m", 0.4, 0.6)
    config = json.loads((where / CONFIG).read_text())
    if change == "config":
        (where / CONFIG).write_text("{not json")
    elif change == "format":
        (where / CONFIG).write_text(json.dumps({**config, "format": "something else"}))
    elif change == "weights":
        (where / WEIGHTS).write_bytes(b"not safetensors")
    elif change == "frames":
        (where / CONFIG).write_text(json.dumps({**config, "max_frames": None}))
    elif change == "threshold":
        config["rows"][ROBOT_PAIR]["alphas"]["0.05"]["thresholds"] = [0.4, 7]
        (where / CONFIG).write_text(json.dumps(config))
    elif change == "rows":
        (where / CONFIG).write_text(json.dumps({**config, "rows": [1, 2]}))
    elif change == "members":
        config["rows"][ROBOT_PAIR]["members"] = "frame"
        (where / CONFIG).write_text(json.dumps(config))
    elif change == "stale":  # the weights of another run beside this run's thresholds (a crash between the writes)
        save_monitor(tmp_path / "other", {"frame": _fitted(16, 7), "dense": _fitted(17, 8)}, _rows({ROBOT: [0.4]}), {})
        (where / WEIGHTS).write_bytes((tmp_path / "other" / WEIGHTS).read_bytes())
    elif change == "width":  # a monitor whose MLP the live signals cannot feed: refused at load, not mid-run
        save_monitor(where, {"frame": _fitted(20), "dense": _fitted(17)}, _rows({ROBOT: [0.4]}), {"max_frames": 8})
    with pytest.raises(ConfigError) as e:
        RobotMonitor.load(where, **kwargs)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_the_feature_widths_are_the_robots_signals() -> None:
    from sim_backends.robot_signals import SIGNALS

    assert robot_baseline.SIGNAL_COUNT == len(SIGNALS)
    assert robot_baseline.prefix_features(np.zeros((3, len(SIGNALS)))).shape[1] == robot_baseline.FEATURES["frame"]
    table = np.zeros((5, 2 + len(SIGNALS)))  # t, keyframe, signals
    assert robot_baseline.dense_features(table).shape[1] == robot_baseline.FEATURES["dense"]


def reproduces_bench(out: Path, dataset: Path, res: dict) -> None:
    """The monitor a model-free online bench saved in `out` is the bench's: its MLPs give the scores of the MLPs the
    bench fits (fitted again here: the fit is seeded) on the scored trajectories, its thresholds are the rows', and
    where a threshold is finite it sounds exactly where the rows say (the same false alarms and detections)."""
    trajs = [t for t in json.loads((dataset / "trajectories.json").read_text()) if "prefix_of" not in t]
    scored, train = ([t for t in trajs if t["split"] == s] for s in (res["split"], "train"))
    tables = robot_baseline.read_dense(dataset, [t["trajectory"] for t in trajs])
    config = json.loads((out / res["monitor"] / CONFIG).read_text())
    assert config["rows"].keys() == {ROBOT, DENSE, ROBOT_PAIR} and config["calibration"] == res["calibration"]
    mlps = read_mlps(out / res["monitor"], config)
    for t, want in zip(scored, robot_baseline.score(robot_baseline.fit(train), scored)):
        got = mlps["frame"].p_failure(robot_baseline.prefix_features(t["robot_signals"]))
        assert np.allclose(got, want, rtol=0, atol=1e-12), t["trajectory"]
    dense = robot_baseline.score_dense(robot_baseline.fit_dense(train, tables), scored, tables)
    for t, want in zip(scored, dense):
        got = mlps["dense"].p_failure(robot_baseline.dense_features(tables[t["trajectory"]]))
        assert np.allclose(got, want, rtol=0, atol=1e-12), t["trajectory"]
    for name, row in config["rows"].items():
        for alpha, levels in row["alphas"].items():
            bench = res["rows"][name][alpha]
            assert levels["thresholds"] == bench.get("thresholds", [bench.get("threshold")]), (name, alpha)
            if all(t is None for t in levels["thresholds"]):
                continue
            m = RobotMonitor.load(out / res["monitor"], float(alpha), name)
            sounded = [
                m.sounds("frame", m.frame_scores(t["robot_signals"], len(t["robot_signals"]))) is not None
                or m.sounds("dense", m.dense_scores(tables[t["trajectory"]])) is not None
                for t in scored
            ]
            assert sum(s for s, t in zip(sounded, scored) if t["success"]) == bench["false_alarms"], (name, alpha)
            assert sum(s for s, t in zip(sounded, scored) if not t["success"]) == bench["detected"], (name, alpha)


def _supervise(tiny_model, out: Path, *args: str, check: bool = True):  # noqa: F811
    """labrobfail-supervise (tests/test_supervise.py's) with the VLM supervisor on one open-oven trial."""
    vlm = ["supervisor=vlm", f"vlm.model={tiny_model}", "baseline=false", "task=open_oven_center", "trials=1"]
    return supervise(*vlm, f"out_dir={out}", *args, check=check)


def test_the_supervisor_intervenes_where_the_monitor_sounds_and_asks_the_model_only_then(tmp_path, tiny):  # noqa: F811
    def queries(out: str) -> list[dict]:
        return [q for q in records(tmp_path / out) if q["event"] == "query"]

    quiet = write_monitor(tmp_path / "q", 1.0, 1.0)  # no score is above 1
    _supervise(tiny, tmp_path / "quiet", f"vlm.monitor={quiet}", "vlm.alpha=0.05")
    qs = queries("quiet")  # never a failure, never the model's answer: not even once the policy stops
    assert len(qs) > 2 and all(q["diagnosis"] == {"failure": False, "monitor": None} for q in qs)
    assert [q["final"] for q in qs].count(True) == 1
    loud = write_monitor(tmp_path / "l", 1.0, 0.0)  # the every-sample MLP sounds at the first sample
    _supervise(tiny, tmp_path / "loud", f"vlm.monitor={loud}", "vlm.alpha=0.05", "loop.budget=2")
    first, *later = queries("loud")
    hit = first["diagnosis"]["monitor"]
    assert first["failure"] and hit["member"] == "dense" and hit["t_s"] == 0.0 and hit["threshold"] == 0.0
    assert first["diagnosis"]["category"] is not None and first["primitives"] == first["diagnosis"]["primitives"]
    # after its correction the monitor stands down (its bound is on a first alarm): quiet until the policy stops,
    # then the model reviews the episode the monitor flagged (its own P(failure) at vlm.threshold)
    assert later and all(q["diagnosis"] == {"failure": False, "monitor": None} for q in later if not q["final"])
    final = [q for q in later if q["final"]]
    assert final and all(q["diagnosis"]["monitor"] is None and "p_failure" in q["diagnosis"] for q in final)
    frames = write_monitor(tmp_path / "f", 0.0, 1.0)  # the per-frame MLP sounds at the first grid frame
    _supervise(tiny, tmp_path / "frames", f"vlm.monitor={frames}", "vlm.alpha=0.05", "loop.budget=2")
    first = queries("frames")[0]
    hit = first["diagnosis"]["monitor"]  # the first frame's keyframe and the sim time its images were taken
    assert first["failure"] and hit["member"] == "frame" and hit["keyframe"] == 0 and hit["t_s"] > 0
    with pytest.raises(ConfigError, match="calibrated on the scripted policy's successes, not act's"):
        from omegaconf import OmegaConf

        from sim_backends.supervision.experiment import build_supervisor

        build_supervisor(OmegaConf.create({"policy": "act", "vlm": {"monitor": str(frames)}}), "vlm")
    for args, needle in (
        ([f"vlm.monitor={loud}"], "vlm.monitor: give vlm.alpha too"),
        ([f"vlm.monitor={loud}", "vlm.alpha=0.05", f"vlm.alarm={loud}/x.json"], "one alarm decides"),
        (["vlm.monitor_row=x"], "vlm.monitor_row: names a row of vlm.monitor"),
        ([f"vlm.monitor={tmp_path}", "vlm.alpha=0.05"], "holds no readable monitor.json"),
    ):
        r = _supervise(tiny, tmp_path / "bad", *args, check=False)
        assert r.returncode == 2 and needle in r.stderr.strip().splitlines()[-1] and "Traceback" not in r.stderr
    assert not (tmp_path / "bad" / "log.jsonl").exists()
