"""Where does an ACT put its grasp? The grasp position an ACT predicts, against its demonstrations' own.

Run as:
    python scripts/probe_act.py checkpoint=outputs/act/pour/final demos=outputs/act/pour/demos.npz
    python scripts/probe_act.py checkpoint=... demos=... every=6 ahead=[8,14] out=outputs/probe_act.json

For every `every`-th demonstration of a demos.npz (scripts/train_act.py's cache, recorded from simulator state),
the ACT is shown the views and proprio `ahead` ticks before the demonstration closes the gripper; the position its
chunk commands at the close is compared, in the plane, with the demonstration's. The spread of the
demonstrations' grasps around their mean is what an ACT that ignores the pictures would score. With auxiliary
points (`model.aux_weight` > 0) the auxiliary head's grasp is scored too. A fit on the training demonstrations:
it says whether the ACT localises the vessel at all, not how it generalises. Writes JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints

DEFAULTS = """
checkpoint: null             # a scripts/train_act.py final/ directory
demos: null                  # the demos.npz it was trained on (its cameras and image size)
every: 6                     # probe every n-th demonstration
ahead: [8, 14]               # ticks before the close (at most the chunk size - 1)
out: outputs/probe_act.json
"""


def main(argv: list[str]) -> int:
    import torch

    from sim_backends.policies.act.checkpoint import load_checkpoint
    from sim_backends.policies.act.data import close_tick
    from sim_backends.policies.act.modeling_act import AUX_SCALE

    cfg = load_config(DEFAULTS, argv)
    require_ints(cfg, ["every"])
    if cfg.demos is None or not Path(str(cfg.demos)).is_file():
        raise ConfigError(f"demos: no demos.npz at {cfg.demos!r}")
    try:
        model, act = load_checkpoint(cfg.checkpoint, "cpu", key="checkpoint")
    except ValueError as e:
        raise ConfigError(str(e)) from None
    try:
        ahead = [int(a) for a in cfg.ahead]
    except (TypeError, ValueError):
        ahead = []
    if not ahead or min(ahead) < 1 or max(ahead) >= act.chunk_size:
        raise ConfigError(f"ahead: a list of ticks from 1 to {act.chunk_size - 1} (the chunk), not {cfg.ahead!r}")
    try:
        with np.load(str(cfg.demos), allow_pickle=False) as z:
            ident = json.loads(str(z["identity"]))
            bounds, state, action, images = z["bounds"], z["state"], z["action"], z["images"]
    except (OSError, ValueError, KeyError):
        raise ConfigError(f"demos: {cfg.demos} is not a train_act.py demos.npz") from None
    if ident.get("cameras") != act.cameras or ident.get("image_size") != act.image_size:
        raise ConfigError(
            f"demos: recorded for {ident.get('cameras')} at {ident.get('image_size')} px, the ACT "
            f"sees {act.cameras} at {act.image_size} px"
        )
    sm, ss, am, as_ = act.stat_arrays()
    grasps, errors = [], {a: {"chunk": [], "aux": []} for a in ahead}
    for i in range(0, len(bounds) - 1, int(cfg.every)):
        a0, a1 = int(bounds[i]), int(bounds[i + 1])
        tick = close_tick(action[a0:a1])
        if not tick:  # never closes, or starts holding (a regrasp demonstration): no approach to probe
            continue
        close = a0 + tick
        grasps.append(action[close, :2])
        for a in ahead:
            t = close - a
            if t < a0:
                continue
            img = torch.from_numpy(images[t]).permute(0, 3, 1, 2).float()[None] / 255.0
            x = torch.from_numpy((state[t] - sm) / ss)[None]
            with torch.no_grad():
                chunk, aux = model.decode(img, x, torch.zeros(1, act.latent_dim))
            pred = chunk[0, a].numpy() * as_ + am
            errors[a]["chunk"].append(float(np.linalg.norm(pred[:2] - action[close, :2])))
            if aux is not None:
                grasp = state[t][:3] + aux[0, 0].numpy() * AUX_SCALE
                errors[a]["aux"].append(float(np.linalg.norm(grasp[:2] - action[close, :2])))
    if not grasps:
        raise ConfigError(f"demos: no demonstration in {cfg.demos} closes the gripper after its first tick")
    g = np.asarray(grasps)
    cm = lambda v: round(100 * float(np.median(v)), 2) if v else None  # noqa: E731
    res = {
        "checkpoint": str(cfg.checkpoint),
        "demos": str(cfg.demos),
        "probed": len(g),
        "grasp_spread_cm": round(100 * float(np.linalg.norm(g - g.mean(0), axis=1).mean()), 2),
        "median_error_cm": {str(a): {"chunk": cm(e["chunk"]), "aux": cm(e["aux"])} for a, e in errors.items()},
    }
    from labrobfail_vlm.io import atomic_write_json

    atomic_write_json(Path(str(cfg.out)), res)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
