"""Generation of LabRobFail-Sim episodes into Parquet shards (resumable, seeded, parallel).

Episode i belongs to pair i // 2 (role nominal for even i, injected for odd i);
pair j runs scenario order[j] with episode seed derived from (seed, variant, j), so the
same seed gives the same data whatever the number of workers, and no two variants
share an episode (a held-out split never replays a training pair in new colours;
`replay_seen=true` does that on purpose, under the replay_<variant> name). `first_pair` shifts
the pair numbers (ids and seeds) of a run, so a second run can add episodes to a
dataset without reusing an id or an initial state. Shard k holds
episodes [k*E, (k+1)*E); a finished shard is a complete file, so a rerun of
the same command after a kill skips finished shards and redoes the rest.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from omegaconf import DictConfig, OmegaConf

from labrobfail_vlm.config import CONFIG_DIR, ConfigError, is_int, make_dir, names, require_ints
from labrobfail_vlm.config import load_config as _load_config
from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json
from labrobfail_vlm.taxonomy import REPLAY_PREFIX, SCENE_VARIANTS, check_variant
from sim_backends.shards import episode_row, manifest, read_labels, write_shard

DEFAULTS = CONFIG_DIR / "generate.yaml"
# Keys that define the data; changing any of them in an existing out_dir is refused.
IDENTITY_KEYS = (
    "backend",
    "num_episodes",
    "seed",
    "episodes_per_shard",
    "variant",
    "scenarios",
    "image_size",
    "cameras",
    "backend_kwargs",
    "render_frames",
    "first_pair",
    "replay_seen",
)


def load_config(dotlist: list[str]) -> DictConfig:
    return _load_config(DEFAULTS, dotlist)


def validate(cfg: DictConfig) -> dict[str, Any]:
    """Check every field before anything is written; returns the backend's constructor kwargs.

    Generic keys are checked here; the backend checks its own `backend_kwargs` section
    (`FailureSource.prepare_kwargs`), so nothing here knows which simulator runs.
    """
    from sim_backends.registry import available_backends, backend_options, backend_spec

    if cfg.backend not in available_backends():
        raise ConfigError(f"backend: unknown backend {cfg.backend!r}; available: {', '.join(available_backends())}")
    require_ints(cfg, ("num_episodes", "first_pair", "seed"), 0)
    require_ints(cfg, ("workers", "episodes_per_shard", "image_size"))
    # a pair's seed is a SeedSequence of 32-bit words: a larger integer splits into two and can equal another
    # (seed, pair)'s (pair_seed(2**32, 7) is pair_seed(0, 1, 7)), so seeds and pair numbers stay under 2**32
    if cfg.seed >= 2**32 or cfg.first_pair + cfg.num_episodes // 2 > 2**32:
        raise ConfigError(
            f"seed and first_pair: seeds and pair numbers must stay under 2**32, got seed={cfg.seed}, "
            f"first_pair={cfg.first_pair}, num_episodes={cfg.num_episodes}"
        )
    rf = cfg.render_frames
    if rf is not None and not is_int(rf, 1):
        raise ConfigError(f"render_frames: must be a positive integer or null (every keyframe), got {rf!r}")
    if cfg.num_episodes % 2:
        raise ConfigError(f"num_episodes: must be even (success/failure pairs), got {cfg.num_episodes}")
    if cfg.episodes_per_shard % 2:
        raise ConfigError("episodes_per_shard: must be even (a shard holds whole success/failure pairs)")
    if cfg.executor not in ("process", "ray"):
        raise ConfigError(f"executor: must be 'process' or 'ray', got {cfg.executor!r}")
    check_variant(cfg.variant)
    if cfg.replay_seen not in (True, False):
        raise ConfigError(f"replay_seen: must be true or false, got {cfg.replay_seen!r}")
    if cfg.replay_seen and cfg.variant == "seen":
        raise ConfigError("replay_seen: replays the seen episodes under a held-out variant's appearance; give one")
    spec = backend_spec(cfg.backend)
    spec.cls.check_cameras(list(cfg.cameras))
    own = backend_options(cfg.backend, _own_section(cfg))
    kwargs = {"image_size": cfg.image_size, "cameras": list(cfg.cameras), **own}
    known = spec.cls.list_scenarios(**kwargs)
    cfg.scenarios = names(cfg.scenarios)
    for s in cfg.scenarios or []:
        if s not in known:
            raise ConfigError(f"scenarios: unknown task scenario {s!r}")
    if cfg.reuse_from is not None and Path(str(cfg.reuse_from)).resolve() == Path(str(cfg.out_dir)).resolve():
        raise ConfigError("reuse_from: names out_dir itself; give the folder of another run")
    make_dir("out_dir", cfg.out_dir, probe=True)  # made last: a bad setting above leaves no folder behind
    return kwargs


# What a run.json written before a key existed was made with, where that may not be the key's default.
LEGACY_BACKEND_KWARGS = {"physics": "reference"}


def run_physics(run_dir: str | Path) -> str | None:
    """The physics preset a PyBullet run folder's episodes were simulated with, read as a resumed run reads its
    run.json (`_upgrade_identity`: an older one's keys as LEGACY_BACKEND_KWARGS says); None for no run there or
    another backend."""
    path = Path(run_dir) / "run.json"
    if not path.is_file():
        return None
    try:
        run = json.loads(path.read_text())
    except ValueError as e:
        raise ConfigError(f"run.json: {path} is not valid JSON ({e})") from None
    if (
        not isinstance(run, dict)
        or run.get("backend") != "pybullet"
        or not isinstance(run.get("backend_kwargs", {}), dict)
    ):
        return None
    return str(_upgrade_identity(run, {"backend_kwargs": {}, "backend_files": {}})["backend_kwargs"]["physics"])


def check_same_physics(run_dir: str, setting: str, step: str) -> None:
    """A step that adds episodes to a run's data line generates with `setting` (`backend_kwargs.physics=NAME`):
    refused in one line when the run's episodes in `run_dir` were simulated with another preset, which would mix
    two data lines in one comparison or training set."""
    have, want = run_physics(run_dir), setting.rpartition("=")[2]
    if have is not None and have != want:
        raise ConfigError(
            f"REPRO_PHYSICS: {step} would simulate with physics={want}, but {run_dir} holds physics={have} episodes; "
            f"set REPRO_PHYSICS=backend_kwargs.physics={have} (or use a new R)"
        )


def _default_backend_kwargs() -> dict[str, Any]:
    return OmegaConf.to_container(OmegaConf.load(DEFAULTS).backend_kwargs, resolve=True) or {}


def _own_section(cfg: DictConfig) -> dict[str, Any]:
    """The keys of the shared `backend_kwargs` section that this backend takes. A key of another backend must
    keep its default (`sim_backend=gpu` with backend=pybullet is an error)."""
    from sim_backends.registry import backend_option_names

    section = OmegaConf.to_container(cfg.backend_kwargs, resolve=True) or {}
    takes = backend_option_names(cfg.backend)
    defaults = _default_backend_kwargs()
    preset = (cfg.get("presets") or {}).get(cfg.get("preset")) or {}
    from_preset = set(preset.get("backend_kwargs") or {})
    for k, v in section.items():
        if k not in takes and v != defaults.get(k):
            why = (
                f" (preset={cfg.preset} sets it: that world is not made for {cfg.backend})" if k in from_preset else ""
            )
            raise ConfigError(f"backend_kwargs.{k}: not an option of the {cfg.backend} backend{why}")
    return {k: v for k, v in section.items() if k in takes}


def _file_contents(section: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
    """The content of each file a `backend_kwargs` entry names (custom_scene, custom_objects), as the backend
    loaded it: run.json keeps it, so editing the file and rerunning into the same out_dir cannot mix two
    scenes in one dataset (the path alone would still match)."""
    return {k: kwargs[k] for k, v in section.items() if isinstance(v, str) and isinstance(kwargs.get(k), dict)}


def _upgrade_identity(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """A run.json written before `backend_kwargs` existed kept its PyBullet keys top level: move them there;
    keys added to the section since a run was written read as their defaults, or as LEGACY_BACKEND_KWARGS says
    where the runs before the key were made otherwise. One written before `backend_files` existed is taken to
    hold today's file contents (nothing else is known of them)."""
    if "backend_kwargs" not in old:
        legacy = {k: old.get(k) for k in ("wrist", "custom_objects", "custom_scene")}
        old = {**old, "backend_kwargs": {**(new["backend_kwargs"] or {}), **LEGACY_BACKEND_KWARGS, **legacy}}
    return {
        **old,
        "backend_kwargs": {**_default_backend_kwargs(), **LEGACY_BACKEND_KWARGS, **(old["backend_kwargs"] or {})},
        "backend_files": old.get("backend_files", new["backend_files"]),
        "first_pair": old.get("first_pair", 0),
        "replay_seen": old.get("replay_seen", False),
    }


def _variant_word(variant: str) -> list[int]:
    """The variant's word in a seed: none for seen (its seeds are those of runs made before variants had their
    own), the variant's index otherwise. SeedSequence pads its entropy with zeros to four words, so a trailing
    non-zero word after three always differs from every seen seed."""
    i = SCENE_VARIANTS.index(variant)
    return [i] if i else []


def scenario_order(
    scenarios: list[str], seed: int, pairs: int, repeats: dict[str, int] | None = None, variant: str = "seen"
) -> list[str]:
    """Round-robin over a seeded permutation per cycle: every scenario appears (`repeats[s]` times, to
    oversample longer tasks) before the next cycle starts. Each variant has its own order."""
    rng = np.random.default_rng([seed, 0x5CE7, 0] + _variant_word(variant))
    cycle = [s for s in scenarios for _ in range((repeats or {}).get(s, 1))]
    out: list[str] = []
    while len(out) < pairs:
        out.extend(cycle[i] for i in rng.permutation(len(cycle)))
    return out[:pairs]


def pair_seed(seed: int, pair: int, draw: int = 0, variant: str = "seen") -> int:
    """Seed of pair `pair`'s initial state in `variant`; `draw` > 0 is a redraw after a nominal plan failed.
    The variant is part of the seed, so the same (seed, pair) gives every variant its own initial state and
    perturbation (the injection's stream, failure_generator.perturbation_rng, follows from this seed)."""
    word = _variant_word(variant)
    return int(np.random.SeedSequence([seed, pair] + ([draw] if draw or word else []) + word).generate_state(1)[0])


MAX_DRAWS = 8  # initial states (and perturbations per state) tried for one pair before it is given up


def labelable_pair(
    src, scenario: str, seed: int, j: int, variant: str, stream: str | None = None
) -> tuple[Any, Any, list[dict[str, Any]]]:
    """A (nominal, injected) pair whose nominal plan succeeds and whose failure, if any, a detector explains.

    A nominal plan that fails is redrawn from a new initial state; an injected failure no detector explains
    is left out and the perturbation redrawn. Both are returned as records for the manifest. Deterministic:
    the draws follow from (seed, pair, stream), where `stream` is the variant whose episodes are drawn (the
    variant itself unless a replay names another). Returns (None, None, records) if no draw works.
    """
    from sim_backends.failure_generator import run_injected, run_nominal

    records: list[dict[str, Any]] = []
    for a in range(MAX_DRAWS):
        s = pair_seed(seed, j, a, stream or variant)
        nominal = run_nominal(src, scenario, s, variant, then_draw=0)
        if not nominal.labels.success:
            records.append(
                {
                    "kind": "nominal_redraw",
                    "pair": j,
                    "scenario": scenario,
                    "seed": s,
                    "reason": nominal.labels.failure_type or "unexplained",
                    "evidence": nominal.labels.evidence,
                }
            )
            continue
        for d in range(MAX_DRAWS):
            injected = run_injected(src, scenario, s, variant, d)
            if injected.labels.explained:
                return nominal, injected, records
            records.append(
                {
                    "kind": "left_out",
                    "pair": j,
                    "scenario": scenario,
                    "seed": s,
                    "draw": d,
                    "perturbation": injected.perturbation,
                    "evidence": injected.labels.evidence,
                }
            )
        break
    records.append({"kind": "given_up", "pair": j, "scenario": scenario})
    return None, None, records


def shard_jobs(cfg: DictConfig, scenarios: list[str], repeats: dict[str, int] | None = None) -> list[dict[str, Any]]:
    n, per, first = int(cfg.num_episodes), int(cfg.episodes_per_shard), int(cfg.first_pair)
    order = scenario_order(scenarios, int(cfg.seed), math.ceil(n / 2), repeats, _stream(cfg))
    jobs = []
    for k in range(math.ceil(n / per)):
        lo, hi = k * per, min(n, (k + 1) * per)
        # pair numbers from `first`; labelable_pair draws the seeds from them
        pairs = [(first + j, order[j]) for j in range(lo // 2, math.ceil(hi / 2))]
        jobs.append(
            {
                "shard": k,
                "lo": 2 * first + lo,  # episode numbers, which follow the pair numbers
                "hi": 2 * first + hi,
                "pairs": pairs,
                "seed": int(cfg.seed),
                "render_frames": cfg.get("render_frames"),
                "stream": _stream(cfg),
            }
        )
    return jobs


def _stream(cfg: DictConfig) -> str:
    """The variant whose episodes a run draws: its own, or seen's for a replay."""
    return "seen" if cfg.get("replay_seen") else cfg.variant


def run_shard(job: dict[str, Any], backend: str, kwargs: dict[str, Any], variant: str, out_dir: str) -> int:
    """Generate one shard's episodes and write it atomically. Returns the number of episodes."""
    src = _worker_source(backend, kwargs)
    src.render_frames = job.get("render_frames")
    rows, records = [], []
    for j, scenario in job["pairs"]:
        stream = job["stream"]
        nominal, injected, recs = labelable_pair(src, scenario, job["seed"], j, variant, stream)
        records.extend(recs)
        if nominal is None:
            continue
        for role_i, ep in enumerate((nominal, injected)):
            i = 2 * j + role_i
            if not job["lo"] <= i < job["hi"]:
                continue
            ep.episode_id, ep.pair_id, ep.role = f"ep{i:07d}", f"pair{j:07d}", ("nominal", "injected")[role_i]
            if stream != variant:  # seen episodes in a held-out appearance: never called val or test
                ep.variant = REPLAY_PREFIX + variant
            rows.append(episode_row(ep))
    # The shard's redraw/left-out records first: a shard file on disk always has its records beside it.
    atomic_write_json(Path(out_dir) / f"shard-{job['shard']:05d}.rejects.json", records)
    write_shard(Path(out_dir) / f"shard-{job['shard']:05d}.parquet", rows)
    return job["hi"] - job["lo"]


_SOURCES: dict[str, Any] = {}


def close_sources() -> None:
    """Close this process's cached simulators (a benchmark that times start-up again)."""
    while _SOURCES:
        _SOURCES.popitem()[1].close()


def _worker_source(backend: str, kwargs: dict[str, Any]):
    """One simulator per worker process, reused across shards."""
    from sim_backends.registry import make_backend

    key = json.dumps([backend, kwargs], sort_keys=True, default=str)
    if key not in _SOURCES:
        _SOURCES[key] = make_backend(backend, **kwargs)
    return _SOURCES[key]


def _run_process(jobs, cfg, kwargs) -> Iterator[int]:
    args = (cfg.backend, kwargs, cfg.variant, cfg.out_dir)
    if cfg.workers == 1:
        for job in jobs:
            yield run_shard(job, *args)
        return
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(cfg.workers) as pool:
        yield from pool.imap_unordered(_star_run_shard, [(job, *args) for job in jobs])


def _star_run_shard(a: tuple) -> int:
    return run_shard(*a)


def _run_ray(jobs, cfg, kwargs) -> Iterator[int]:
    import ray

    # workers import sim_backends from the installed package (pip install on every node of a cluster)
    ray.init(
        address=cfg.ray_address,
        num_cpus=None if cfg.ray_address else cfg.workers,
        include_dashboard=False,
        ignore_reinit_error=True,
        log_to_driver=False,
    )
    remote = ray.remote(num_cpus=1)(run_shard)
    pending = [remote.remote(job, cfg.backend, kwargs, cfg.variant, cfg.out_dir) for job in jobs]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        ray.shutdown()


def _differing(old: dict[str, Any], new: dict[str, Any], skip: tuple[str, ...] = ()) -> list[str]:
    """The IDENTITY_KEYS (less `skip`) on which a run.json, read by `_upgrade_identity`, differs from this run's."""
    return [k for k in IDENTITY_KEYS if k not in skip and old.get(k) != new[k]]


def _edited_files(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """The backend_kwargs whose file (custom_scene, custom_objects) holds other content than when `old` was written."""
    return [k for k, v in new["backend_files"].items() if old["backend_files"].get(k) != v]


def _reuse_source(cfg: DictConfig, identity: dict[str, Any]) -> dict[str, Any] | None:
    """The run.json of `reuse_from`, checked to be this run's identity but for num_episodes (refused in one line
    otherwise, before this run writes anything); None without reuse_from."""
    if cfg.reuse_from is None:
        return None
    src = Path(str(cfg.reuse_from))
    if not (src / "run.json").is_file():
        raise ConfigError(f"reuse_from: {str(src)!r} holds no labrobfail-generate run (no run.json)")
    try:
        other = _upgrade_identity(json.loads((src / "run.json").read_text()), identity)
    except (ValueError, TypeError, AttributeError, KeyError) as e:
        raise ConfigError(f"reuse_from: {src / 'run.json'} is not a run.json ({e})") from None
    diff = _differing(other, identity, skip=("num_episodes",))
    if diff:
        raise ConfigError(
            f"reuse_from: {str(src)!r} was generated with another {diff[0]} ({other.get(diff[0])!r}, "
            f"here {identity[diff[0]]!r}); its episodes are not this run's"
        )
    edited = _edited_files(other, identity)
    if edited:
        raise ConfigError(
            f"reuse_from: {str(src)!r} was generated from another content of the file of backend_kwargs.{edited[0]}; "
            "its episodes are not this run's"
        )
    if not is_int(other.get("num_episodes"), 0):
        raise ConfigError(f"reuse_from: {src / 'run.json'} has no num_episodes")
    return other


def _reuse_shards(
    cfg: DictConfig, other: dict[str, Any], todo: list[dict[str, Any]], scenarios: list[str], repeats: Any
) -> list[dict[str, Any]]:
    """Copy the shards of `todo` that the run in `reuse_from` (`other`, its run.json) wrote from the very same job
    (the same pairs, seeds and physics: the same bytes, as generation is deterministic) instead of simulating them
    again; returns the jobs left."""
    src = Path(str(cfg.reuse_from))
    theirs = OmegaConf.merge(cfg, {"num_episodes": other["num_episodes"]})
    same = {j["shard"]: j for j in shard_jobs(theirs, scenarios, repeats)}
    left, copied = [], 0
    for job in todo:
        name = f"shard-{job['shard']:05d}"
        parts = [src / f"{name}.rejects.json", src / f"{name}.parquet"]  # the parquet last: then the shard is done
        if same.get(job["shard"]) != job or not all(f.is_file() for f in parts):
            left.append(job)
            continue
        for f in parts:
            atomic_write_bytes(Path(cfg.out_dir) / f.name, f.read_bytes())
        copied += 1
    if copied:
        print(f"reuse_from: copied {copied} shard(s) from {src}", file=sys.stderr)
    return left


def generate(cfg: DictConfig) -> dict[str, Any]:
    from tqdm import tqdm

    from sim_backends.registry import backend_spec

    kwargs = validate(cfg)
    out = Path(cfg.out_dir)
    identity = {k: OmegaConf.to_container(cfg, resolve=True)[k] for k in IDENTITY_KEYS}
    identity["backend_files"] = _file_contents(identity["backend_kwargs"] or {}, kwargs)
    other = _reuse_source(cfg, identity)
    run_file = out / "run.json"
    if run_file.exists():
        old = _upgrade_identity(json.loads(run_file.read_text()), identity)
        diff = _differing(old, identity)
        if diff:
            raise ConfigError(
                f"{diff[0]}: out_dir {cfg.out_dir!r} holds a run with {diff[0]}={old.get(diff[0])!r}; "
                "use a new out_dir (nothing was changed)"
            )
        edited = _edited_files(old, identity)
        if edited:
            raise ConfigError(
                f"backend_kwargs.{edited[0]}: the file {identity['backend_kwargs'][edited[0]]!r} changed "
                f"since out_dir {cfg.out_dir!r} was started; use a new out_dir (nothing was changed)"
            )
    else:
        atomic_write_json(run_file, identity, indent=2)
    for stale in out.glob("*.tmp"):  # leftovers of a killed run; their shard is simply redone
        stale.unlink()
    repeats = backend_spec(cfg.backend).cls.scenario_repeats(**kwargs)  # every scenario name -> its repeat
    scenarios = list(cfg.scenarios) if cfg.scenarios else list(repeats)
    jobs = shard_jobs(cfg, scenarios, repeats)
    todo = [j for j in jobs if not (out / f"shard-{j['shard']:05d}.parquet").exists()]
    if other is not None:
        todo = _reuse_shards(cfg, other, todo, scenarios, repeats)
    done_eps = sum(j["hi"] - j["lo"] for j in jobs) - sum(j["hi"] - j["lo"] for j in todo)
    bar = tqdm(
        total=int(cfg.num_episodes),
        initial=done_eps,
        unit="ep",
        disable=not cfg.progress,
        desc=f"{cfg.backend}:{cfg.variant}",
    )
    runner = _run_ray if cfg.executor == "ray" else _run_process
    for n in runner(todo, cfg, kwargs):
        bar.update(n)
    bar.close()
    shards = sorted(out.glob("shard-*.parquet"))
    rows = read_labels(shards)
    records = (
        [r for s in shards for r in json.loads(s.with_suffix(".rejects.json").read_text())]
        if all(s.with_suffix(".rejects.json").exists() for s in shards)
        else None
    )
    man = manifest(
        rows,
        {
            "backend": cfg.backend,
            "variant": REPLAY_PREFIX + cfg.variant if cfg.replay_seen else cfg.variant,
            "replay_seen": bool(cfg.replay_seen),
            "seed": int(cfg.seed),
            "shards": [s.name for s in shards],
            "scenarios": scenarios,
        },
        records,
    )
    atomic_write_json(out / "manifest.json", man, indent=2)
    return man


def main(argv: list[str]) -> int:
    man = generate(load_config(argv))
    print(json.dumps({k: man[k] for k in ("episodes", "by_outcome", "by_failure_type", "by_action", "by_horizon")}))
    return 0


def cli() -> None:
    """The `labrobfail-generate` console script."""
    from labrobfail_vlm.config import cli_main

    cli_main(main, GENERATE_DOC)


GENERATE_DOC = """Generate labeled failure/success episode pairs into Parquet shards (labrobfail-generate).

Run as:
    labrobfail-generate backend=pybullet num_episodes=200 out_dir=outputs/shards seed=0 workers=2
    labrobfail-generate --num-episodes 100 --out-dir outputs/val_both --variant val_both
    labrobfail-generate num_episodes=1000 out_dir=outputs/big executor=ray workers=8

Rerunning the same command after a kill resumes; DIR/manifest.json summarises the run. Defaults:
configs/generate.yaml.
"""
