"""The online bench's non-VLM baseline: a small MLP on the robot's own signals, in SAFE's manner.

Each grid frame of a trajectory carries its robot signals (labrobfail_data/robot_signals.py: hand position, finger
opening, gripper command, the commanded keyframe, tracking errors). The score of the prefix that shows k frames is
an MLP's P(failure has shown by frame k) on the k-th frame's signals, the running maxima of the tracking errors and
of the closed-finger opening over frames 1..k, and k's place in the trajectory. It is trained on the dataset's
train split (whole trajectories, every prefix; the label is the labelled failure frame <= k) and nothing else, so
the calibration and scored splits stay apart from its fitting. Its scores go through the same conformal alarm as
the model's.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

RUNNING = (9, 10, 11)  # tracking_error, segment_error_max, closed_width (labrobfail_data/robot_signals.SIGNALS)


def prefix_features(signals: Sequence[Sequence[float]]) -> np.ndarray:
    """One row per prefix k = 1..F: frame k's signals, the running maxima, k / F."""
    x = np.asarray(signals, float)
    run = np.maximum.accumulate(x[:, RUNNING], axis=0)
    pos = (np.arange(1, len(x) + 1) / len(x))[:, None]
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


def fit(train: Sequence[dict[str, Any]], seed: int = 0) -> Any:
    """The baseline fitted on `train`'s prefixes: scaling, then an MLP (32, 32), with early stopping on a tenth of
    them when there are enough (a test's handful of prefixes has too few to hold any out)."""
    from sklearn.neural_network import MLPClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    x, y = _xy(train)
    mlp = MLPClassifier(hidden_layer_sizes=(32, 32), max_iter=300, early_stopping=len(y) >= 200, random_state=seed)
    return make_pipeline(StandardScaler(), mlp).fit(x, y)


def score(model: Any, trajs: Sequence[dict[str, Any]]) -> list[list[float]]:
    """Per trajectory, the baseline's P(failure) on each of its prefixes."""
    return [[float(p) for p in model.predict_proba(prefix_features(t["robot_signals"]))[:, 1]] for t in trajs]
