"""A robot-signal monitor saved for the supervisor: the online bench's MLPs on the robot's own signals and the
thresholds it calibrated for them, in a directory that a robot stack loads without the dataset and without pickles.

    <dir>/monitor.safetensors  per member ("frame": the MLP read at each grid frame, robot_baseline.fit; "dense": the
                               MLP read at every trace sample, fit_dense) the scaler's mean and scale and each
                               layer's weight and bias (float64, as scikit-learn fitted them)
    <dir>/monitor.json         the format, per robot-signal row of the bench (the per-frame MLP, the every-sample
                               MLP, the two paired) its members and, per alpha, each member's threshold as
                               calibrated (null: too few calibration successes, that member never sounds), the
                               calibration split and its successes, delta, and the row the bench chose on it

The MLP's forward pass is scikit-learn's MLPClassifier (ReLU hidden layers, a logistic output) written out in numpy,
so that loading runs no code from a file: the same P(failure) to 1e-12 (tests/test_monitor.py). The alarm is the
bench's: a member sounds where its score is strictly above its threshold, a pair where either does
(labrobfail_vlm/alarm.py AnyAlarm: one bound, alpha split between them). What the bound promises, and what it does
not, is alarm.py's: successes exchangeable with the calibration ones (the scripted policy in the scenes the
calibration split was drawn from); another policy or scene needs calibrating anew.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from labrobfail_vlm.alarm import first_alarm
from labrobfail_vlm.bench import robot_baseline
from labrobfail_vlm.bench.online_alarm import alpha_key
from labrobfail_vlm.config import ConfigError, is_int, is_number

FORMAT = "labrobfail-robot-monitor/1"
WEIGHTS, CONFIG = "monitor.safetensors", "monitor.json"
# The bench's robot-signal rows (labrobfail_vlm/bench/online.py) and the MLPs each runs, in the order of its thresholds
ROWS = {
    robot_baseline.ROBOT: ("frame",),
    robot_baseline.DENSE: ("dense",),
    robot_baseline.ROBOT_PAIR: ("frame", "dense"),
}


@dataclass(frozen=True)
class Mlp:
    """A fitted make_pipeline(StandardScaler(), MLPClassifier(...)) as arrays: P(failure) = the logistic of the last
    layer, after ReLU hidden layers, on the scaled features."""

    mean: np.ndarray
    scale: np.ndarray
    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]

    @classmethod
    def from_sklearn(cls, pipe: Any) -> "Mlp":
        scaler, mlp = pipe[0], pipe[-1]
        if mlp.activation != "relu" or mlp.out_activation_ != "logistic" or list(mlp.classes_) != [False, True]:
            raise ValueError("monitor: only a binary ReLU MLPClassifier (the bench's) can be saved")
        return cls(scaler.mean_, scaler.scale_, tuple(mlp.coefs_), tuple(mlp.intercepts_))

    def p_failure(self, x: np.ndarray) -> np.ndarray:
        h = (np.asarray(x, np.float64) - self.mean) / self.scale
        for w, b in zip(self.weights[:-1], self.biases[:-1]):
            h = np.maximum(h @ w + b, 0.0)
        z = (h @ self.weights[-1] + self.biases[-1])[:, 0]
        return 1.0 / (1.0 + np.exp(-np.clip(z, -500, 500)))

    def tensors(self, name: str) -> dict[str, np.ndarray]:
        out = {f"{name}.mean": self.mean, f"{name}.scale": self.scale}
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            out |= {f"{name}.layer{i}.weight": w, f"{name}.layer{i}.bias": b}
        return {k: np.ascontiguousarray(v, np.float64) for k, v in out.items()}

    @classmethod
    def from_tensors(cls, t: dict[str, np.ndarray], name: str, layers: int) -> "Mlp":
        ws = tuple(t[f"{name}.layer{i}.weight"] for i in range(layers))
        bs = tuple(t[f"{name}.layer{i}.bias"] for i in range(layers))
        mlp = cls(t[f"{name}.mean"], t[f"{name}.scale"], ws, bs)
        dims = [len(mlp.mean), *(w.shape[1] for w in ws)]
        ok = len(mlp.scale) == dims[0] and dims[-1] == 1 and all(b.shape == (w.shape[1],) for w, b in zip(ws, bs))
        if not ok or any(w.shape[0] != d for w, d in zip(ws, dims)):
            raise ValueError(f"the {name} MLP's arrays do not chain")
        return mlp


def save_monitor(out: Path, models: dict[str, Any], rows: dict[str, Any], meta: dict[str, Any]) -> Path | None:
    """Write the monitor of the bench's robot-signal `rows` whose MLPs are all in `models` ("frame", "dense": fitted
    pipelines); `meta` goes to monitor.json as it is (calibration, delta, chosen row). None when there is no such
    row."""
    from safetensors.numpy import save

    from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json

    keep = {name: members for name, members in ROWS.items() if name in rows and all(m in models for m in members)}
    if not keep:
        return None
    used = sorted({m for members in keep.values() for m in members})
    mlps = {m: Mlp.from_sklearn(models[m]) for m in used}
    out.mkdir(parents=True, exist_ok=True)
    tensors = {k: v for m in used for k, v in mlps[m].tensors(m).items()}
    data = save(tensors)
    atomic_write_bytes(out / WEIGHTS, data)
    config = {
        "format": FORMAT,
        "weights_sha256": hashlib.sha256(data).hexdigest(),  # a crash between the two writes is caught on load
        "layers": {m: len(mlps[m].weights) for m in used},
        "rows": {name: {"members": list(members), "alphas": _levels(rows[name])} for name, members in keep.items()},
        **meta,
    }
    atomic_write_json(out / CONFIG, config)
    return out


def _levels(row: dict[str, Any]) -> dict[str, Any]:
    """Per alpha of a bench row, each member's threshold (null: never sounds) and level."""
    out = {}
    for alpha, r in row.items():
        ths = r.get("thresholds", [r.get("threshold")])
        out[alpha] = {"thresholds": ths, "alphas": r.get("alphas", [r.get("alpha")])}
    return out


def read_mlps(where: Path, config: dict[str, Any]) -> dict[str, Mlp]:
    """Every MLP of a monitor directory (`config`: its monitor.json), or a one-line ConfigError."""
    from safetensors import SafetensorError
    from safetensors.numpy import load

    try:
        data = (where / WEIGHTS).read_bytes()
        if hashlib.sha256(data).hexdigest() != config.get("weights_sha256"):  # the two files are one monitor
            raise ValueError(f"its sha256 is not the one {CONFIG} names (written by another bench run?)")
        tensors = load(data)
        return {m: Mlp.from_tensors(tensors, m, int(n)) for m, n in config["layers"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError, IndexError, SafetensorError) as e:
        raise ConfigError(f"vlm.monitor: cannot read {where / WEIGHTS} ({type(e).__name__}: {e})") from None


def _read_config(where: Path) -> dict[str, Any]:
    try:
        config = json.loads((where / CONFIG).read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"vlm.monitor: {where} holds no readable {CONFIG} ({type(e).__name__})") from None
    if not isinstance(config, dict) or config.get("format") != FORMAT or not isinstance(config.get("rows"), dict):
        raise ConfigError(f"vlm.monitor: {where / CONFIG} is not a robot-signal monitor ({FORMAT})")
    return config


def _row(config: dict[str, Any], row: str | None, where: Path) -> tuple[str, dict[str, Any]]:
    """The row asked for, or by default the one chosen on calibration if saved here, else the pair, else any."""
    rows, chosen = config["rows"], config.get("chosen_on_calibration")
    if row is None:
        row = next((r for r in (chosen, robot_baseline.ROBOT_PAIR, *rows) if r in rows), None)
        if row is None:
            raise ConfigError(f"vlm.monitor: {where / CONFIG} holds no row")
    if row not in rows:
        raise ConfigError(f"vlm.monitor_row: {row!r} is not in {where / CONFIG} (it has {', '.join(rows)})")
    return row, rows[row]


def _thresholds(entry: dict[str, Any], alpha: Any, name: str, where: Path) -> list[float]:
    """A row's members' thresholds at alpha (+inf: that member never sounds), or a one-line ConfigError."""
    levels = entry["alphas"].get(alpha_key(alpha))
    if levels is None:
        have = ", ".join(entry["alphas"])
        raise ConfigError(f"vlm.alpha: {alpha!r} was not calibrated for this monitor (it has {have})")
    raw = levels.get("thresholds") if isinstance(levels, dict) else None
    if not isinstance(raw, list) or not all(t is None or (is_number(t) and 0 <= t <= 1) for t in raw):
        raise ConfigError(
            f"vlm.monitor: {where / CONFIG} gives {name} at {alpha} thresholds {raw!r}, not a P(failure) in [0, 1]"
        )
    if all(t is None for t in raw):
        raise ConfigError(f"vlm.alpha: too few calibration successes for alpha {alpha}: the monitor never sounds")
    return [math.inf if t is None else float(t) for t in raw]


@dataclass(frozen=True)
class RobotMonitor:
    """One robot-signal row of a saved monitor at one alpha: its members' MLPs and thresholds."""

    row: str
    alpha: float
    members: dict[str, tuple[Mlp, float]]  # "frame" / "dense" -> (MLP, threshold; +inf: never sounds)
    max_frames: int  # the grid the per-frame MLP was fitted on (its k / F)
    delta: float | None = None

    @classmethod
    def load(cls, path: str | Path, alpha: Any, row: str | None = None) -> "RobotMonitor":
        """The monitor in `path` at `alpha` (one the bench calibrated), row `row` (None: the row the bench chose on
        its calibration split when that is a robot-signal row, else the pair). One-line ConfigErrors."""
        where = Path(str(path))
        config = _read_config(where)
        try:
            name, entry = _row(config, row, where)
            ths = _thresholds(entry, alpha, name, where)
            mlps = read_mlps(where, config)
            members = {m: (mlps[m], t) for m, t in zip(entry["members"], ths, strict=True)}
        except (KeyError, ValueError, TypeError, AttributeError) as e:
            raise ConfigError(f"vlm.monitor: {where / CONFIG} is malformed ({type(e).__name__}: {e})") from None
        for m, (mlp, _) in members.items():  # a width the live features would not match fails here, not mid-run
            if len(mlp.mean) != robot_baseline.FEATURES[m]:
                raise ConfigError(
                    f"vlm.monitor: its {m} MLP reads {len(mlp.mean)} features, the robot's signals give "
                    f"{robot_baseline.FEATURES[m]}"
                )
        frames = config.get("max_frames")
        if "frame" in members and not is_int(frames, 1):
            raise ConfigError(f"vlm.monitor: {where / CONFIG} gives no grid size (max_frames) for its per-frame MLP")
        return cls(name, float(alpha), members, frames if is_int(frames, 1) else 0, config.get("delta"))

    def frame_scores(self, signals: Sequence[Sequence[float]], total: int) -> np.ndarray | None:
        """The per-frame MLP's running score at each of the frames shown so far (`signals`, one row per grid frame),
        of a grid of `total` frames; None when this row has no per-frame member or nothing is shown yet."""
        if "frame" not in self.members or not len(signals):
            return None
        return self.members["frame"][0].p_failure(robot_baseline.prefix_features(signals, total))

    def dense_scores(self, table: np.ndarray) -> np.ndarray | None:
        """The every-sample MLP's score at each row of a dense table (robot_baseline.dense_features' input)."""
        if "dense" not in self.members or not len(table):
            return None
        return self.members["dense"][0].p_failure(robot_baseline.dense_features(table))

    def sounds(self, member: str, scores: np.ndarray | None) -> int | None:
        """The first index at which `member`'s scores are above its threshold (the alarm's rule), or None."""
        if scores is None or member not in self.members:
            return None
        return first_alarm(scores, self.members[member][1])
