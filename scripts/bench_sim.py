"""Benchmark LabRobFail-Sim throughput on this machine and write JSON.

Run as:
    python scripts/bench_sim.py [backend=pybullet] [episodes=48] [image_size=192] [rounds=2]
                                [out=outputs/bench_sim_BACKEND.json]
    python scripts/bench_sim.py --backend maniskill --episodes 8

Every row runs the same episodes: the generator's own pair plan for seed 0 (the same scenario mix,
short, medium and long, with its oversampling), so rows compare side by side in one run:
physics only (no camera), two rendered views with each rendering variant the backend offers
(PyBullet: the stock Panda meshes against the low-poly ones, and the whole scene at every keyframe against the
layered backdrop) at every keyframe, the default rendering at only the keyframes the generator's default
`render_frames` grid shows, and end to end into shards (the generator's defaults) with 1 worker and with 2
workers (speed-up = ratio), and on 1 worker with the whole scene rendered; each physics preset other than the
generator's default, physics only and end to end on 1 worker. Peak memory of the main process and of
a worker. This machine's speed drifts by more than a lever's gain within minutes, so the rows run interleaved,
`rounds` times, each row's figure is its median, and each variant's speed is also given as a ratio to its base row
measured in the same round (median over rounds): the figure to compare variants by.
"""

from __future__ import annotations

import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints
from labrobfail_vlm.io import write_report
from sim_backends.generate import close_sources, generate, labelable_pair, scenario_order
from sim_backends.generate import load_config as generate_config
from sim_backends.registry import available_backends, backend_spec, make_backend

DEFAULTS = """
backend: pybullet                       # registered FailureSource (sim_backends/registry.py)
episodes: 48                            # episodes per row (even: they run as nominal/injected pairs)
image_size: 192                         # square rendered views, px
rounds: 2                               # every row once per round, rows interleaved; a row's figure is its median
out: outputs/bench_sim_${backend}.json  # the JSON result (${backend}: the backend above)
"""

# Rendering variants compared per backend (backend kwargs); the first is the backend's default.
RENDER_VARIANTS = {
    "pybullet": {
        "lowpoly_robot": {"lowpoly_robot": True},
        "stock_meshes": {"lowpoly_robot": False},
        "whole_scene": {"layered_render": False},  # every keyframe renders every body (before the backdrop)
    }
}
# Physics presets timed beside the generator's default one, physics only and end to end (sim_backends/pybullet/
# backend.py PHYSICS; whether a preset keeps the labels is scripts/check_physics.py's question, not this one's).
PHYSICS_VARIANTS = {"pybullet": ("reference", "fast", "prefix")}


def per_hour(n: int, seconds: float) -> float:
    return round(3600.0 * n / seconds, 1)


def in_process(backend: str, pairs: int, render_frames: int | None = None, **kwargs) -> float:
    """Seconds for the generator's pairs (redraws included) in this process."""
    src = make_backend(backend, **kwargs)
    src.render_frames = render_frames
    order = scenario_order(src.scenarios(), 0, pairs, backend_spec(backend).cls.scenario_repeats(**kwargs))
    t = time.perf_counter()
    for j, scenario in enumerate(order):
        labelable_pair(src, scenario, 0, j, "seen")
    dt = time.perf_counter() - t
    src.close()
    return dt


def end_to_end(backend: str, workers: int, n: int, image_size: int, extra: tuple[str, ...] = ()) -> float:
    close_sources()  # every round starts its simulator, as a generation does (and the 2-worker row's pool)
    with tempfile.TemporaryDirectory() as d:
        cfg = generate_config(
            [
                f"backend={backend}",
                f"out_dir={d}/s",
                f"num_episodes={n}",
                f"workers={workers}",
                "progress=false",
                "episodes_per_shard=2",
                "seed=0",
                f"image_size={image_size}",
                *extra,
            ]
        )
        t = time.perf_counter()
        generate(cfg)
        return time.perf_counter() - t


def rows(
    backend: str, n: int, size: int, default_physics: str | None, rf: int
) -> tuple[dict[str, Callable[[], float]], dict[str, str]]:
    """Each row's timing (seconds for the n episodes) by its JSON key, and the row each other row is a ratio to
    (`default_physics`, `rf`: the generator's physics preset and `render_frames`)."""
    pairs, out, base = n // 2, {}, {}
    out["physics_only"] = lambda: in_process(backend, pairs, cameras=[])
    others = [v for v in PHYSICS_VARIANTS.get(backend, ()) if v != default_physics]
    for name in others:  # the unnamed rows run the generator's default preset
        key = f"physics_only_{name}_physics"
        out[key], base[key] = (lambda name=name: in_process(backend, pairs, cameras=[], physics=name)), "physics_only"
    render = RENDER_VARIANTS.get(backend, {"default": {}})
    first = f"rendered_2x{size}_{next(iter(render))}"
    for name, kw in render.items():
        key = f"rendered_2x{size}_{name}"
        out[key] = lambda kw=kw: in_process(backend, pairs, image_size=size, **kw)
        if key != first:
            base[key] = first
    # The backend's default rendering, only at the keyframes a grid of `render_frames` shows (the generator's
    # default), against every keyframe in the row above.
    out[f"rendered_2x{size}_grid_keyframes_{rf}"] = lambda: in_process(
        backend, pairs, render_frames=rf, image_size=size
    )
    base[f"rendered_2x{size}_grid_keyframes_{rf}"] = first
    out["end_to_end"] = lambda: end_to_end(backend, 1, n, size)
    for name, kw in render.items():  # before the backdrop, end to end beside it
        if kw.get("layered_render") is False:
            flags = tuple(f"backend_kwargs.{k}={str(v).lower()}" for k, v in kw.items())
            out[f"end_to_end_{name}"], base[f"end_to_end_{name}"] = (
                (lambda flags=flags: end_to_end(backend, 1, n, size, flags)),
                "end_to_end",
            )
    for name in others:
        key = f"end_to_end_{name}_physics"
        out[key] = lambda name=name: end_to_end(backend, 1, n, size, (f"backend_kwargs.physics={name}",))
        base[key] = "end_to_end"
    out["end_to_end_2_workers"] = lambda: end_to_end(backend, 2, n, size)
    return out, base


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    backend = str(cfg.backend)
    if backend not in available_backends():
        raise ConfigError(f"backend: unknown backend {backend!r}; available: {', '.join(available_backends())}")
    require_ints(cfg, ("episodes",), 2)
    if cfg.episodes % 2:  # the end-to-end timing runs the generator, which takes whole pairs
        raise ConfigError(f"episodes: must be even (success/failure pairs), got {cfg.episodes}")
    require_ints(cfg, ("image_size", "rounds"))
    n, size, rounds = cfg.episodes, cfg.image_size, cfg.rounds
    defaults = generate_config([])
    default_physics = defaults.backend_kwargs.get("physics")
    timed, base = rows(backend, n, size, default_physics, int(defaults.render_frames))
    seconds: dict[str, list[float]] = {k: [] for k in timed}
    for _ in tqdm(range(rounds), desc="rounds"):  # every row once per round: a drift reaches every row alike
        for key, run in timed.items():
            seconds[key].append(run())
    res: dict = {
        "backend": backend,
        "episodes": n,
        "image_size": size,
        "rounds": rounds,
        "scenario_mix": "the generator's pair plan for seed 0 (all scenarios, oversampled by horizon)",
        "scenarios": len(backend_spec(backend).cls.list_scenarios()),
        "physics_default": default_physics,
    }
    for key, t in seconds.items():
        workers = 2 if key.endswith("_2_workers") else 1
        res[f"{key}_episodes_per_hour" + ("" if workers > 1 else "_per_core")] = per_hour(n, statistics.median(t))
    # per round, the row's speed over its base row's (>1: faster), then the median over rounds
    res["speed_ratio_to_base"] = {
        f"{key} / {b}": round(statistics.median(tb / tk for tb, tk in zip(seconds[b], seconds[key])), 3)
        for key, b in base.items()
    }
    res["speedup_2_workers"] = round(
        statistics.median(a / b for a, b in zip(seconds["end_to_end"], seconds["end_to_end_2_workers"])), 2
    )
    res["seconds_per_round"] = {k: [round(x, 2) for x in v] for k, v in seconds.items()}
    res["peak_rss_mb_main_process"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    res["peak_rss_mb_worker"] = round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1)
    return write_report(Path(str(cfg.out)), res)


if __name__ == "__main__":
    cli_main(main, __doc__)
