"""The online bench: how early and how reliably an alarm catches a failure while the trajectory runs.

Run as:
    labrobfail-evaluate mode=online model=outputs/reproduce/train/final dataset_dir=outputs/reproduce/dataset \
        split=test calibration=val
    labrobfail-evaluate mode=online model=DIR dataset_dir=DIR split=val_both calibration=val max_trajectories=200
    labrobfail-evaluate mode=online dataset_dir=outputs/reproduce/dataset \
        scored_dataset=outputs/reproduce/dataset_power split=test out_dir=outputs/reproduce/online_power

For every trajectory of `split` and of the `calibration` split, the model is asked Q2 on each prefix grid (the
first k keyframes shown, k = 1..F; the later cells blank, as labrobfail_data builds prefix grids) and its P(failure)
is the running score. The alarm (labrobfail_vlm/alarm.py) is calibrated per alpha on the calibration split's
successes only (split conformal: at most alpha of new exchangeable successes raise it, on average over calibration
draws; with `delta=`, with probability 1 - delta over the draw), then run on `split`:

- per alpha: the false-alarm rate on successes and its bound check (alarm.false_alarm_pvalue: how likely at least
  that many false alarms are if the guarantee holds), the detection rate on failures, the latency
  from the onset in grid frames (median and 90th percentile; the onset frame is the grid frame where the labelled
  failure first shows, from simulator state), the share caught at or before the onset frame;
- AUROC of the score at each keyframe against the trajectory's outcome (a curve, as SAFE plots it: PNG);
- per alpha, from the sim times the dataset keeps (datasets built from 29 Nov): the latency in seconds (median and
  90th percentile) and the share of failures with an irreversible event (spill, fall, breakage, out of reach)
  caught before it;
- rows: the model, the majority class (never alarms), the blind model (grey prefix grids: one score per k for
  every trajectory), a non-VLM baseline on the robot's own signals (robot_baseline.py, fitted on the train split),
  the model or the MLP (Sentinel's pairing of a cheap detector with a VLM: either alarm, each calibrated at
  alpha / 2, so the pair keeps the bound; alarm.AnyAlarm), and the labeler on live state (the ceiling: it alarms
  at the onset frame, never on a success);
- the same MLP checked at every sample of the state trace (40 Hz in PyBullet; datasets built from 3 Dec), alone,
  paired with the per-frame MLP (halves of alpha) and with the model, whose score stands from one grid frame to the
  next: an alarm between two frames can
  sound before an event that follows its onset within a keyframe (SAFE checks at every step); its latency in
  frames counts to the first grid frame taken once it sounded; one pair row per model's share of alpha in
  `pair_shares` (the MLP has the rest; a level under 1 / (n + 1) of the n calibration successes leaves its monitor
  out: its threshold is +inf, written null);
- the CPU time of one alarm check (one prefix grid's Q2);
- which row to report, chosen on the calibration split alone by cross-fitting (online_choice.py).
With `scored_dataset=`, `split` is read from that dataset (episodes drawn apart, e.g. `make online-power`'s block of
new seen pairs; built with the same grid, sharing no pair with dataset_dir), while the MLPs' training and the
calibration stay dataset_dir's.
Writes out_dir/online.json and out_dir/auroc_by_keyframe.png (out_dir: MODEL/eval_online_SPLIT by default); the
CLI adds online.md, the tables of online_page.py.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from PIL import Image

from labrobfail_vlm.bench import robot_baseline
from labrobfail_vlm.bench.online_alarm import ALPHAS, LABELER, alarm_rows, ceiling, on_axis
from labrobfail_vlm.bench.online_choice import Candidate, choose
from labrobfail_vlm.bench.robot_baseline import DENSE, ROBOT, ROBOT_PAIR
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.grid import BLANK, GridConfig

EITHER = "model or robot signals (alpha/2 each)"
DENSE_EITHER = "model or robot signals, every sample (alpha/2 each)"


def pair_name(share: float) -> str:
    """The every-sample pair's row at the model's `share` of alpha (the robot-signal MLP has the rest)."""
    return DENSE_EITHER if share == 0.5 else f"model or robot signals, every sample (alpha x {share:g} to the model)"


def check_pair_shares(shares: Any) -> list[float]:
    """`pair_shares`: the model's share(s) of alpha in the every-sample pair, each in (0, 1); one row per share
    (None: the halves alone)."""
    if shares is None:
        return [0.5]
    ok = isinstance(shares, Sequence) and not isinstance(shares, str) and len(shares) > 0
    if not ok or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and 0 < x < 1 for x in shares):
        raise ConfigError(f"pair_shares: expected a non-empty list of numbers in (0, 1), got {shares!r}")
    out = [float(x) for x in shares]
    if len({pair_name(x) for x in out}) < len(out):  # two shares would write one row
        raise ConfigError(f"pair_shares: each share once, got {list(shares)!r}")
    return out


def check_delta(delta: Any) -> float | None:
    """The bench's `delta`: None (a marginal alarm) or a number in (0, 1) (training-conditional, alarm.py)."""
    if delta is None:
        return None
    if isinstance(delta, bool) or not isinstance(delta, (int, float)) or not 0 < delta < 1:
        raise ConfigError(f"delta: expected null or a number in (0, 1), got {delta!r}")
    return float(delta)


def prefix_grid(grid: Image.Image, cfg: GridConfig, views: int, k: int) -> Image.Image:
    """The grid as a prefix grid of its first k keyframes: every later cell blank (build_grid(visible=k) draws
    neither the frame nor its index tag there, so blanking the cell gives the same pixels)."""
    arr = np.asarray(grid.convert("RGB")).copy()
    rows, cols = cfg.shape(views)
    cw, ch = cfg.width // cols, cfg.height // rows
    for v in range(views):
        for t in range(k, cfg.max_frames):
            r, c = cfg.cell(t, v, views)
            arr[r * ch : (r + 1) * ch, c * cw : (c + 1) * cw] = BLANK[0]
    return Image.fromarray(arr)


def read_trajectories(dataset: Path) -> list[dict[str, Any]]:
    """A dataset's trajectories.json (every split, prefix records too), or a one-line ConfigError."""
    try:
        return json.loads((dataset / "trajectories.json").read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"dataset_dir: cannot read {dataset / 'trajectories.json'} ({e})") from None


def trajectories(rows: list[dict[str, Any]], split: str, limit: int | None, dataset: Path) -> list[dict[str, Any]]:
    """`split`'s whole trajectories among `dataset`'s `rows` (no prefix records), in file order, at most `limit`."""
    out = [t for t in rows if t.get("split") == split and "prefix_of" not in t]
    if not out:
        raise ConfigError(f"split: {split!r} has no trajectories in {dataset}")
    return out[:limit] if limit else out


def _dataset_facts(where: Path, key: str) -> tuple[dict[str, Any], set[str]]:
    """A dataset's stats.json and its pairs (groups), or a one-line ConfigError naming `key`."""
    try:
        stats = json.loads((where / "stats.json").read_text())
        groups = {t.get("group", t["trajectory"]) for t in json.loads((where / "trajectories.json").read_text())}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"{key}: cannot read the dataset in {where} ({type(e).__name__}: {e})") from None
    if not isinstance(stats.get("grid"), dict):
        raise ConfigError(f"{key}: {where / 'stats.json'} names no grid (rebuild the dataset)")
    return stats, groups


def scored_apart(cfg: Any) -> Path | None:
    """`scored_dataset`, checked against dataset_dir: the same grid and views, and no pair in both (a shared pair
    would be a trajectory the MLPs were fitted or the alarm calibrated on, or its twin; pairs are named by variant
    and number, so a block drawn with another seed but the same numbers is refused too: number it apart). None when
    unset or dataset_dir itself. The CLI calls it once, before a model loads, and hands run_online its answer."""
    raw, dataset = cfg.get("scored_dataset"), Path(str(cfg.dataset_dir))
    if raw is None or Path(str(raw)).resolve() == dataset.resolve():
        return None
    other = Path(str(raw))
    (ours, our_pairs), (theirs, their_pairs) = (
        _dataset_facts(dataset, "dataset_dir"),
        _dataset_facts(other, "scored_dataset"),
    )
    if GridConfig.from_dict(theirs["grid"]) != GridConfig.from_dict(ours["grid"]) or theirs.get("views") != ours.get(
        "views"
    ):
        raise ConfigError(f"scored_dataset: {other} was built with another grid or views than dataset_dir's")
    if shared := sorted(our_pairs & their_pairs):
        raise ConfigError(f"scored_dataset: {len(shared)} pairs are also in dataset_dir ({shared[0]}, ...)")
    return other


def score_prefixes(
    fa: Any, dataset: Path, trajs: Sequence[dict[str, Any]], cfg: GridConfig, blind: bool = False
) -> tuple[list[list[float]], float]:
    """Per trajectory, P(failure) on each of its prefix grids; and the CPU seconds of one check (the mean)."""
    scores: list[list[float]] = []
    cpu = 0.0
    checks = 0
    grey = Image.new("RGB", (cfg.width, cfg.height), (128, 128, 128))
    seen: dict[tuple[str, int, int], list[float]] = {}  # the blind model's grids differ only in task and length
    for t in trajs:
        n, key = int(t["frames"]), (t["task"], int(t["frames"]), int(t["views"]))
        if blind and key in seen:
            scores.append(seen[key])
            continue
        full = grey if blind else Image.open(dataset / "images" / f"{t['trajectory']}.png").convert("RGB")
        grids = [prefix_grid(full, cfg, int(t["views"]), k) for k in range(1, n + 1)]
        c0 = time.process_time()
        ans = fa.answers_batch(grids, [t["task"]] * n, list(range(1, n + 1)), None, [{"Q2"}] * n)
        cpu += time.process_time() - c0
        checks += n
        scores.append([float(a.p_failure) for a in ans])
        seen[key] = scores[-1]
    return scores, cpu / max(checks, 1)


def auroc_by_keyframe(scores: list[list[float]], trajs: Sequence[dict[str, Any]]) -> list[float | None]:
    """AUROC of the score at keyframe k (1-based position in the list) against the trajectory's outcome."""
    from sklearn.metrics import roc_auc_score

    longest = max(len(s) for s in scores)
    out: list[float | None] = []
    for k in range(longest):
        y = [not t["success"] for s, t in zip(scores, trajs) if len(s) > k]
        p = [s[k] for s in scores if len(s) > k]
        out.append(round(float(roc_auc_score(y, p)), 4) if 0 < sum(y) < len(y) else None)
    return out


def auroc_png(curves: dict[str, list[float | None]], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from labrobfail_vlm.io import save_figure

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for name, ys in curves.items():
        xs = [k + 1 for k, y in enumerate(ys) if y is not None]
        ax.plot(xs, [y for y in ys if y is not None], marker="o", label=name)
    ax.axhline(0.5, color="grey", lw=0.8, ls=":")
    ax.set(xlabel="keyframes shown", ylabel="AUROC (outcome)", title=title, ylim=(0.4, 1.0))
    ax.legend(fontsize=8)
    save_figure(fig, path)


def dense_rows(
    dirs: tuple[Path, Path],
    train_t: Sequence[dict[str, Any]],
    cal: tuple[Sequence[dict[str, Any]], Sequence[list[float]] | None],
    ev: tuple[Sequence[dict[str, Any]], Sequence[list[float]] | None],
    rows: dict[str, Any],
    curves: dict[str, Any],
    shares: Sequence[float] = (0.5,),
    cands: dict[str, Candidate] | None = None,
    delta: float | None = None,
    frame_mlp: tuple[Sequence[list[float]], Sequence[list[float]]] | None = None,
) -> tuple[dict[str, Any], Any]:
    """The robot-signal MLP checked at every trace sample (robot_baseline.DENSE_FILE), alone, paired with the
    per-frame MLP (`frame_mlp`: its calibration and scored running scores; halves of alpha) and with the model when
    there is one (one pair row per model's share of alpha in `shares`; a per-frame score stands from one grid frame
    to the next): adds their rows and curve (and their calibration scores to `cands`), returns the CPU seconds of one
    dense check and the fitted MLP, every alarm calibrated with `delta` (alarm_rows). Nothing ({}, None) for a
    dataset built without the dense file (before 3 Dec). Train and calibration tables are read from dirs[0], the
    scored ones from dirs[1]."""
    cands = {} if cands is None else cands
    (cal_t, cal_s), (ev_t, ev_s) = cal, ev
    if dirs[0] == dirs[1]:
        tables = robot_baseline.read_dense(dirs[0], [t["trajectory"] for t in (*train_t, *cal_t, *ev_t)])
    else:
        ours = robot_baseline.read_dense(dirs[0], [t["trajectory"] for t in (*train_t, *cal_t)])
        theirs = robot_baseline.read_dense(dirs[1], [t["trajectory"] for t in ev_t])
        tables = None if ours is None or theirs is None else ours | theirs
    if tables is None or not all(t.get("frame_times_s") for t in (*cal_t, *ev_t)):
        return {}, None
    fitted = robot_baseline.fit_dense(train_t, tables)
    if fitted is None:
        return {}, None
    dev = robot_baseline.score_dense(fitted, ev_t, tables)
    dcal = robot_baseline.score_dense(fitted, cal_t, tables)
    cpu = robot_baseline.check_seconds(fitted, tables[ev_t[0]["trajectory"]])
    cal_ax = [np.round(tables[t["trajectory"]][:, 0], 4) for t in cal_t]
    ev_ax = [np.round(tables[t["trajectory"]][:, 0], 4) for t in ev_t]
    rows[DENSE] = alarm_rows([dcal], cal_t, [dev], ev_t, ev_ax, delta=delta)
    cands[DENSE] = Candidate([dcal], cal_ax)
    both = ((cal_t, ev_t), (cal_ax, ev_ax))
    if frame_mlp is not None:  # two cheap monitors: one reads each grid frame's prefix, one every trace sample
        rows[ROBOT_PAIR], cands[ROBOT_PAIR] = _with_dense(frame_mlp, (dcal, dev), *both, 0.5, delta)
    if cal_s is not None and ev_s is not None:
        for share in shares:
            rows[pair_name(share)], cands[pair_name(share)] = _with_dense(
                (cal_s, ev_s), (dcal, dev), *both, share, delta
            )
    at_frames = [d[np.searchsorted(a, t["frame_times_s"])] for d, a, t in zip(dev, ev_ax, ev_t)]
    curves[DENSE] = auroc_by_keyframe([list(map(float, x)) for x in at_frames], ev_t)
    return {"cpu_s_per_dense_check": float(f"{cpu:.3g}")}, fitted


def _with_dense(
    per_frame: tuple[Sequence[list[float]], Sequence[list[float]]],
    dense: tuple[list[np.ndarray], list[np.ndarray]],
    trajs: tuple[Sequence[dict[str, Any]], Sequence[dict[str, Any]]],
    axes: tuple[list[np.ndarray], list[np.ndarray]],
    share: float,
    delta: float | None,
) -> tuple[dict[str, Any], Candidate]:
    """A per-grid-frame monitor (its calibration and scored running scores) paired with the every-sample MLP, at
    `share` of alpha to the first: either sounds (alarm.AnyAlarm, one bound). Its rows and its candidate."""
    (cal_t, ev_t), (cal_ax, ev_ax) = trajs, axes
    fcal = [on_axis(s, t["frame_times_s"], a) for s, t, a in zip(per_frame[0], cal_t, cal_ax)]
    fev = [on_axis(s, t["frame_times_s"], a) for s, t, a in zip(per_frame[1], ev_t, ev_ax)]
    pair = (share, 1 - share)
    rows = alarm_rows([fcal, dense[0]], cal_t, [fev, dense[1]], ev_t, ev_ax, pair, delta)
    return rows, Candidate([fcal, dense[0]], cal_ax, pair)


def model_rows(
    fa: Any,
    dirs: tuple[Path, Path],
    grid: GridConfig,
    cal_t: list,
    ev_t: list,
    rows: dict,
    curves: dict,
    delta: float | None,
) -> tuple:
    """The model's and the blind model's rows and curves (added to `rows`, `curves`), the calibration trajectories'
    grids read from dirs[0] and the scored ones' from dirs[1]; returns the model's running scores of the calibration
    and scored trajectories and the CPU seconds of one check."""
    cal, _ = score_prefixes(fa, dirs[0], cal_t, grid)
    ev, cpu = score_prefixes(fa, dirs[1], ev_t, grid)
    bcal, _ = score_prefixes(fa, dirs[0], cal_t, grid, blind=True)
    bev, _ = score_prefixes(fa, dirs[1], ev_t, grid, blind=True)
    rows["model"] = alarm_rows([cal], cal_t, [ev], ev_t, delta=delta)
    rows["blind (grey grid)"] = alarm_rows([bcal], cal_t, [bev], ev_t, delta=delta)
    curves |= {"model": auroc_by_keyframe(ev, ev_t), "blind (grey grid)": auroc_by_keyframe(bev, ev_t)}
    return cal, ev, cpu


def run_online(cfg: Any, fa: Any | None, out_dir: Path, apart: Path | None) -> dict[str, Any]:
    """The online bench of `cfg.split`, calibrated on `cfg.calibration`; writes online.json and the AUROC PNG.
    Without a model (`fa` None), the robot-signal monitors, the majority class and the labeler only. `apart`:
    scored_apart(cfg), the dataset `cfg.split` is read from when it is not dataset_dir (None: dataset_dir)."""
    from labrobfail_vlm.io import atomic_write_json
    from labrobfail_vlm.monitor import save_monitor

    dataset = Path(str(cfg.dataset_dir))
    stats = json.loads((dataset / "stats.json").read_text())
    grid = GridConfig(**stats["grid"])
    if cfg.calibration == cfg.split and apart is None:
        raise ConfigError("calibration: must be another split than the one scored (split conformal)")
    dirs = (dataset, apart or dataset)
    limit = cfg.get("max_trajectories")
    delta = check_delta(cfg.get("delta"))
    everything = read_trajectories(dataset)  # read once: the calibration split, the scored one if here, train
    cal_t = trajectories(everything, str(cfg.calibration), limit, dataset)
    ev_t = trajectories(everything if apart is None else read_trajectories(apart), str(cfg.split), limit, dirs[1])
    rows: dict[str, Any] = {
        "majority class": {str(a): {"false_alarm_rate": 0.0, "detection_rate": 0.0} for a in ALPHAS}
    }
    curves: dict[str, Any] = {}
    cal = ev = None
    extra: dict[str, Any] = {"cpu_s_per_check": None}
    cands: dict[str, Candidate] = {}  # the alarms the report's row is chosen from (online_choice; not the blind model)
    models: dict[str, Any] = {}  # the robot-signal MLPs fitted here, saved with their thresholds (monitor.py)
    if fa is not None:
        cal, ev, cpu = model_rows(fa, dirs, grid, cal_t, ev_t, rows, curves, delta)
        cands["model"] = Candidate([cal])
        rows = {"model": rows.pop("model"), **rows}  # the model's rows first, as the page reads them
        extra["cpu_s_per_check"] = round(cpu, 4)
    train_t = [t for t in everything if t.get("split") == "train" and "prefix_of" not in t]
    # fitted on the train split, so it is calibrated and scored on others only
    # (a train split of a dataset drawn apart is none of the fit's trajectories)
    apart_from_fit = "train" not in (cfg.calibration, cfg.split if apart is None else "")
    signals = apart_from_fit and robot_baseline.has_signals([*train_t, *cal_t, *ev_t])
    fitted = robot_baseline.fit(train_t) if signals else None
    if fitted is not None:  # none without a train split holding both outcomes: the model's rows only
        rcal, rev = robot_baseline.score(fitted, cal_t), robot_baseline.score(fitted, ev_t)
        rows[ROBOT] = alarm_rows([rcal], cal_t, [rev], ev_t, delta=delta)
        cands[ROBOT] = Candidate([rcal])
        if cal is not None and ev is not None:  # Sentinel's pairing, one shared bound
            rows[EITHER] = alarm_rows([cal, rcal], cal_t, [ev, rev], ev_t, delta=delta)
            cands[EITHER] = Candidate([cal, rcal])
        curves[ROBOT] = auroc_by_keyframe(rev, ev_t)
        shares = check_pair_shares(cfg.get("pair_shares"))
        more, models["dense"] = dense_rows(
            dirs, train_t, (cal_t, cal), (ev_t, ev), rows, curves, shares, cands, delta, (rcal, rev)
        )
        extra |= more
        models["frame"] = fitted
    if fa is None and ROBOT not in rows:
        why = (
            "calibration/split is train, where the robot-signal MLPs are fitted"
            if not apart_from_fit
            else "the dataset has no robot signals (built before 29 Nov)"
            if not signals
            else "its train split holds no prefixes of both outcomes to fit the robot-signal MLPs on"
        )
        raise ConfigError(f"mode=online without model=: {why}")
    rows[LABELER] = ceiling(ev_t)
    res = {
        "dataset": str(dataset),
        "split": str(cfg.split),
        **({} if apart is None else {"scored_dataset": str(apart)}),  # the scored split is another dataset's
        "calibration": str(cfg.calibration),
        "trajectories": len(ev_t),
        "calibration_successes": sum(t["success"] for t in cal_t),
        **({} if delta is None else {"delta": delta}),  # training-conditional; absent: marginal (every JSON before)
        **extra,
        "rows": rows,
        "auroc_by_keyframe": curves,
        "auroc_majority": auroc_by_keyframe([[0.0] * int(t["frames"]) for t in ev_t], ev_t)[:1],
        "chosen_on_calibration": choose(cands, cal_t, delta=delta),
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {k: res.get(k) for k in ("dataset", "calibration", "calibration_successes", "delta")}
    meta["chosen_on_calibration"] = res["chosen_on_calibration"]["chosen"]  # the row a supervisor takes by default
    meta["max_frames"] = grid.max_frames  # the per-frame MLP read k / F of grids this size
    monitor = save_monitor(out_dir / "monitor", {k: v for k, v in models.items() if v is not None}, rows, meta)
    if monitor is None and (out_dir / "monitor").is_dir():  # an earlier run's monitor would outlive its bench
        shutil.rmtree(out_dir / "monitor")
    res["monitor"] = None if monitor is None else "monitor"  # the robot-signal alarms, for labrobfail-supervise
    atomic_write_json(out_dir / "online.json", res)
    auroc_png(res["auroc_by_keyframe"], f"online bench, {cfg.split}", out_dir / "auroc_by_keyframe.png")
    return res
