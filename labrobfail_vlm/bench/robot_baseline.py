"""The online bench's non-VLM baseline: a small MLP on the robot's own signals, in SAFE's manner.

Each grid frame of a trajectory carries its robot signals (sim_backends/robot_signals.py: hand position, finger
opening, gripper command, the commanded keyframe, tracking errors). The score of the prefix that shows k frames is
an MLP's P(failure has shown by frame k) on the k-th frame's signals, the running maxima of the tracking errors and
of the closed-finger opening over frames 1..k, and k's place in the trajectory. It is trained on the dataset's
train split (whole trajectories, every prefix; the label is the labelled failure frame <= k) and nothing else, so
the calibration and scored splits stay apart from its fitting. Its scores go through the same conformal alarm as
the model's.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from labrobfail_vlm.config import ConfigError

# the online bench's rows of these monitors (labrobfail_vlm/bench/online.py; a saved monitor names them too)
ROBOT = "robot signals (MLP)"
DENSE = "robot signals, every trace sample (MLP)"
ROBOT_PAIR = "robot signals per grid frame or every sample (alpha/2 each)"
RUNNING = (9, 10, 11)  # tracking_error, segment_error_max, closed_width (sim_backends/robot_signals.SIGNALS)
SIGNAL_COUNT = 12  # len(sim_backends/robot_signals.SIGNALS) (tests/test_monitor.py checks)
# the features each MLP reads: the signals and their running maxima, then k / F (per frame) or keyframe and time
FEATURES = {"frame": SIGNAL_COUNT + len(RUNNING) + 1, "dense": SIGNAL_COUNT + len(RUNNING) + 2}
# The same signals at every sample of the state trace (40 Hz), per whole trajectory, beside trajectories.json: what a
# monitor checked at the robot's own rate sees between two grid frames. Columns: trajectory, t (s since the trace
# began), keyframe (0-based: the commanded keyframe the sample belongs to), signals (the SIGNALS, row after row).
DENSE_FILE = "robot_signals.parquet"
# The dense MLP is fitted on every FIT_EVERY-th sample (10 Hz: about 720,000 for make reproduce's 6,400 train
# trajectories), which keeps its fitting to a few minutes on 2 cores; it is scored at every sample.
FIT_EVERY = 4


def prefix_features(signals: Sequence[Sequence[float]], total: int | None = None) -> np.ndarray:
    """One row per prefix k = 1..F: frame k's signals, the running maxima, k / F. `total`: the grid's frames when
    `signals` are its first ones only (a live episode's so far: labrobfail_vlm/monitor.py); None: all of them."""
    x = np.asarray(signals, float)
    run = np.maximum.accumulate(x[:, RUNNING], axis=0)
    pos = (np.arange(1, len(x) + 1) / (total or len(x)))[:, None]
    return np.hstack([x, run, pos])


def _xy(trajs: Sequence[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = [], []
    for t in trajs:
        f = prefix_features(t["robot_signals"])
        xs.append(f)
        frame = t.get("frame")
        ys.extend(frame is not None and frame <= k for k in range(1, len(f) + 1))
    return np.vstack(xs), np.asarray(ys, bool)


def has_signals(trajs: Sequence[dict[str, Any]]) -> bool:
    """Whether every trajectory carries robot signals (datasets built before 29 Nov do not)."""
    return bool(trajs) and all(t.get("robot_signals") for t in trajs)


def fit(train: Sequence[dict[str, Any]], seed: int = 0) -> Any | None:
    """The baseline fitted on `train`'s prefixes: scaling, then an MLP (32, 32), with early stopping on a tenth of
    them when there are enough (a test's handful of prefixes has too few to hold any out). None when there are no
    prefixes (a dataset built without a train split: an ACT's rollouts, say) or all carry one label (failed by
    their frame or not)."""
    if not train:
        return None
    x, y = _xy(train)
    return _mlp(x, y, seed) if 0 < y.sum() < len(y) else None


def _mlp(x: np.ndarray, y: np.ndarray, seed: int) -> Any:
    from sklearn.neural_network import MLPClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    mlp = MLPClassifier(hidden_layer_sizes=(32, 32), max_iter=300, early_stopping=len(y) >= 200, random_state=seed)
    return make_pipeline(StandardScaler(), mlp).fit(x, y)


def score(model: Any, trajs: Sequence[dict[str, Any]]) -> list[list[float]]:
    """Per trajectory, the baseline's P(failure) on each of its prefixes."""
    return [[float(p) for p in model.predict_proba(prefix_features(t["robot_signals"]))[:, 1]] for t in trajs]


# -- the same baseline at the trace's rate ---------------------------------------------------------------------------


def dense_bytes(trajectories: Sequence[str], tables: Sequence[np.ndarray]) -> bytes:
    """DENSE_FILE's bytes: per trajectory its dense table (rows [t, keyframe, *signals], one per trace sample)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = {
        "trajectory": pa.array(list(trajectories), pa.string()),
        "t": pa.array([np.asarray(x[:, 0], np.float32) for x in tables], pa.list_(pa.float32())),
        "keyframe": pa.array([np.asarray(x[:, 1], np.int16) for x in tables], pa.list_(pa.int16())),
        "signals": pa.array([np.asarray(x[:, 2:], np.float32).ravel() for x in tables], pa.list_(pa.float32())),
    }
    buf = io.BytesIO()
    pq.write_table(pa.table(cols), buf)
    return buf.getvalue()


def read_dense(dataset: Path, names: Iterable[str]) -> dict[str, np.ndarray] | None:
    """The dense tables of `names` (trajectory -> rows [t, keyframe, *signals]); None for a dataset without the file
    (built before 3 Dec) or one missing any of them."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    path = Path(dataset) / DENSE_FILE
    if not path.is_file():
        return None
    want = list(dict.fromkeys(names))
    try:
        table = pq.read_table(path, columns=["trajectory", "t", "keyframe", "signals"])
        table = table.filter(pc.field("trajectory").isin(want))
        if table.num_rows == 0:
            return None
        t, kf, sig = (table.column(c).combine_chunks() for c in ("t", "keyframe", "signals"))  # list arrays, flat
        cuts = t.offsets.to_numpy() - t.offsets[0].as_py()
        flat_t, flat_kf, flat_sig = (a.flatten().to_numpy() for a in (t, kf, sig))
        flat_sig = flat_sig.reshape(len(flat_t), -1)
    except (pa.ArrowException, AttributeError, ValueError) as e:
        raise ConfigError(f"dataset_dir: cannot read {path} ({type(e).__name__}: {e}); rebuild the dataset") from None
    out: dict[str, np.ndarray] = {}
    for i, name in enumerate(table.column("trajectory").to_pylist()):
        a, b = cuts[i], cuts[i + 1]
        out[name] = np.column_stack([flat_t[a:b], flat_kf[a:b], flat_sig[a:b]]).astype(np.float64)
    return out if all(n in out for n in want) else None


def dense_features(table: np.ndarray) -> np.ndarray:
    """One row per trace sample: its signals, the running maxima so far, its keyframe's index and its time. Each row
    reads samples up to its own only (no share of a whole, whose length a failure can change)."""
    x = table[:, 2:]
    run = np.maximum.accumulate(x[:, RUNNING], axis=0)
    return np.hstack([x, run, table[:, 1:2], table[:, 0:1]])


def fit_dense(train: Sequence[dict[str, Any]], tables: dict[str, np.ndarray], seed: int = 0) -> Any | None:
    """The baseline fitted on `train`'s samples (every FIT_EVERY-th): the label is whether the failure's onset
    (onset_s, from simulator state, to 0.1 ms as the sample times are read) has passed; failures without an onset
    are left out. None when the samples hold one class only (no failure with an onset, or no success)."""
    xs, ys = [], []
    for t in train:
        if not t["success"] and t.get("onset_s") is None:
            continue
        tab = tables[t["trajectory"]]
        xs.append(dense_features(tab)[::FIT_EVERY])
        when = np.round(tab[::FIT_EVERY, 0], 4)
        ys.append(np.zeros(len(when), bool) if t["success"] else when >= float(t["onset_s"]))
    y = np.concatenate(ys) if ys else np.zeros(0, bool)
    return _mlp(np.vstack(xs), y, seed) if 0 < y.sum() < len(y) else None


def check_seconds(model: Any, table: np.ndarray, n: int = 200) -> float:
    """CPU seconds of one online check: the MLP on one sample's features, as a robot stack would call it each tick
    (the mean over up to n samples of `table`)."""
    import time

    x = dense_features(table)[:n]
    c0 = time.process_time()
    for row in x:
        model.predict_proba(row[None, :])
    return (time.process_time() - c0) / max(len(x), 1)


def score_dense(model: Any, trajs: Sequence[dict[str, Any]], tables: dict[str, np.ndarray]) -> list[np.ndarray]:
    """Per trajectory, the baseline's P(failure) at each trace sample."""
    return [model.predict_proba(dense_features(tables[t["trajectory"]]))[:, 1] for t in trajs]
