"""What a simulator drew into the grids a model learned from: the backend options that change the pictures, not
the physics (broken glass as shards, the button's lamp). A dataset records them from its shards' run.json
(labrobfail-build-dataset, stats.json's `drawing`), a training run from its datasets (the checkpoint's
labrobfail.json), and `labrobfail-supervise` refuses to run a model in a simulator that draws otherwise: a
model taught that a pressed button lights its lamp reads an unlit button as a failed press.

Each key is true, false, or "mixed" (its shards or datasets disagree: nothing to check); a missing `drawing`
(older datasets and checkpoints, a merged model) checks nothing.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

# backend_kwargs that change only what is drawn; absent from a run's options = the backend's default, off
DRAWING_KEYS = ("broken_glass", "button_lamp")
MIXED = "mixed"


def of_shards(shard_dir: str | Path) -> dict[str, Any] | None:
    """The drawing options of one generation run or a supervised run's rollouts (their run.json's backend_kwargs),
    or None when the folder's run.json is missing, unreadable or does not say."""
    try:
        run = json.loads((Path(shard_dir) / "run.json").read_text())
    except (OSError, ValueError):
        return None
    return of_run(run)


def of_run(run: Any) -> dict[str, Any] | None:
    """`of_shards` of a run.json already read (its parsed contents)."""
    kw = run.get("backend_kwargs") if isinstance(run, dict) else None
    if kw is not None and not isinstance(kw, dict):
        return None
    return None if kw is None else {k: bool(kw.get(k, False)) for k in DRAWING_KEYS}


def merge(drawings: list[dict[str, Any] | None]) -> dict[str, Any] | None:
    """One record for data drawn by several runs: a key they disagree on (or one unknown for some) is "mixed";
    None when no run's options are known."""
    known = [d for d in drawings if isinstance(d, dict)]
    if not known:
        return None
    out: dict[str, Any] = {}
    for k in DRAWING_KEYS:
        values = {d.get(k, MIXED) for d in known}
        out[k] = values.pop() if len(values) == 1 and len(known) == len(drawings) else MIXED
    return out


def mismatches(trained: dict[str, Any] | None, options: dict[str, Any]) -> list[str]:
    """The keys a model was trained with one way (true or false) that a run's backend options draw the other way."""
    if not isinstance(trained, dict):
        return []
    return [
        k for k, v in trained.items() if k in DRAWING_KEYS and isinstance(v, bool) and bool(options.get(k, False)) != v
    ]
