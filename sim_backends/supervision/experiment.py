"""The recovery experiment behind labrobfail-supervise: trials per task family, with and without supervision.

Each task runs `trials` trials (trial i: scenario i mod n, seed `seed + i`), once without supervision (the
baseline, when `baseline` is on) and once under the chosen supervisor, on identical initial states and
failure injections. results.json holds per-task success counts and rates, the difference, the supervisor's
query latency (p50/p95), intervention counts and the trials that ended on a policy error (`policy_errors`:
trial and one-line reason; such a trial counts as run, its success judged on the state it left); results.md
is the paper's table. A stopped run goes on where it stopped when run again with the same settings
(sim_backends/supervision/resume.py).
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from labrobfail_vlm.config import ConfigError, is_int, make_dir, require_ints
from labrobfail_vlm.taxonomy import check_variant
from sim_backends.policies.base import POLICIES, Policy, make_policy
from sim_backends.supervision.base import SUPERVISORS, Supervisor, make_supervisor
from sim_backends.supervision.loop import LoopConfig, RunLog, TaskFamily, run_trial
from sim_backends.supervision.paired import paired_cell, paired_md
from sim_backends.supervision.resume import fingerprint, finished_trials


def families(cfg: DictConfig, templates: dict[str, str]) -> dict[str, TaskFamily]:
    """The task families of the config; `templates`: scenario -> its task template (the backend's catalogue).
    A family lists its scenarios or takes every scenario of its `template`, in catalogue order."""
    out = {}
    for name, f in OmegaConf.to_container(cfg.families, resolve=True).items():  # type: ignore[union-attr]
        scenarios = list(f.get("scenarios") or [s for s, t in templates.items() if t == f.get("template")])
        bad = [s for s in scenarios if s not in templates]
        if bad or not scenarios:
            raise ConfigError(
                f"families.{name}: "
                + (f"unknown scenario {bad[0]!r}" if bad else f"no scenario of template {f.get('template')!r}")
            )
        out[name] = TaskFamily(name, scenarios, f.get("steps"), f.get("goals"))
    return out


def scenario_templates(src: Any) -> dict[str, str]:
    return {s: src.scenario_info(s)["template"] for s in src.scenarios()}


def resolve_tasks(task: str, fams: dict[str, TaskFamily], scenarios: list[str]) -> list[TaskFamily]:
    names = list(fams) if task == "all" else [t.strip() for t in str(task).split(",") if t.strip()]
    out = []
    for n in names:
        if n in fams:
            out.append(fams[n])
        elif n in scenarios:
            out.append(TaskFamily(n, [n]))
        else:
            raise ConfigError(f"task: unknown task {n!r}; families: {', '.join(fams)} (or a scenario name)")
    return out


def policy_kwargs(cfg: DictConfig, name: str) -> dict[str, Any]:
    return dict(OmegaConf.to_container(cfg[name], resolve=True)) if name in cfg else {}  # type: ignore[arg-type]


def build_policy(cfg: DictConfig) -> Policy:
    if cfg.policy not in POLICIES.names():
        raise ConfigError(f"policy: unknown policy {cfg.policy!r}; available: {', '.join(POLICIES.names())}")
    return make_policy(cfg.policy, **policy_kwargs(cfg, cfg.policy))


def build_supervisor(cfg: DictConfig, name: str) -> Supervisor:
    if name not in SUPERVISORS.names():
        raise ConfigError(f"supervisor: unknown supervisor {name!r}; available: {', '.join(SUPERVISORS.names())}")
    kwargs = policy_kwargs(cfg, name)
    if kwargs.get("monitor") is not None and cfg.policy != "scripted":  # a learned policy's keyframes are its ticks
        raise ConfigError(
            f"vlm.monitor: its alarm was calibrated on the scripted policy's successes, not {cfg.policy}'s (whose "
            "every control tick is a keyframe); calibrate one on that policy's episodes"
        )
    return make_supervisor(name, **kwargs)


def percentile(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    s = sorted(xs)
    return round(s[min(len(s) - 1, int(round(q / 100 * (len(s) - 1))))], 4)


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    lat = [x for r in rows for x in r["latency_s"]]
    n = len(rows)
    ok = sum(bool(r["success"]) for r in rows)
    return {
        "success": ok,
        "trials": n,
        "rate": round(100.0 * ok / n, 2) if n else None,
        "interventions": sum(r["interventions"] for r in rows),
        "episodes_with_intervention": sum(r["interventions"] > 0 for r in rows),
        "stopped": sum(r["stopped"] is not None for r in rows),
        "policy_errors": [{"trial": r["trial"], "reason": r["error"]} for r in rows if r["outcome"] == "policy_error"],
        "latency_p50_s": percentile(lat, 50),
        "latency_p95_s": percentile(lat, 95),
        "latency_mean_s": round(statistics.fmean(lat), 4) if lat else None,
        "queries": len(lat),
    }


def rollout_sinks(
    cfg: DictConfig, tasks: list[TaskFamily], sups: list[str], out: Path, own: dict[str, Any]
) -> dict[str, Any]:
    """`shards=true`: per supervisor run, the trials' episodes as shards in out_dir/shards/<supervisor>/ (one per
    trial, named after it: a resumed run's trials add theirs beside the earlier ones)."""
    if cfg.shards not in (True, False):
        raise ConfigError(f"shards: true or false, got {cfg.shards!r}")
    if not cfg.shards:
        return {}
    from sim_backends.supervision.rollouts import RolloutShards, check_family

    if not is_int(cfg.shard_frames, 1):
        raise ConfigError(f"shard_frames: a positive number of grid frames, got {cfg.shard_frames!r}")
    for fam in tasks:
        check_family(fam)
    return {n: RolloutShards(out / "shards" / n, int(cfg.shard_frames), str(cfg.policy), n, own) for n in sups}


def run(cfg: DictConfig) -> dict[str, Any]:
    from sim_backends.registry import available_backends, backend_options, make_backend

    if cfg.backend not in available_backends():
        raise ConfigError(f"backend: unknown backend {cfg.backend!r}; available: {', '.join(available_backends())}")
    check_variant(cfg.variant)
    if not is_int(cfg.trials, 1):
        raise ConfigError(f"trials: must be a positive integer, got {cfg.trials!r}")
    require_ints(cfg, ("image_size",))
    require_ints(cfg, ("seed",), 0)
    try:
        loop = LoopConfig(**OmegaConf.to_container(cfg.loop, resolve=True))  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e)) from None
    own = backend_options(cfg.backend, OmegaConf.to_container(cfg.backend_kwargs, resolve=True) or {})
    kwargs = {"image_size": cfg.image_size, "cameras": list(cfg.cameras), **own}
    sups = (["none"] if cfg.baseline and cfg.supervisor != "none" else []) + [cfg.supervisor]
    src = make_backend(cfg.backend, **kwargs)
    try:
        templates = scenario_templates(src)
        tasks = resolve_tasks(cfg.task, families(cfg, templates), list(templates))
        # everything that can be refused is built before the first trial runs
        policy = build_policy(cfg)
        supervisors = {n: build_supervisor(cfg, n) for n in sups}
        for s in supervisors.values():
            s.check_cameras(list(src.camera_names))
            s.check_drawing(own)
        out = make_dir("out_dir", cfg.out_dir)
        sinks = rollout_sinks(cfg, tasks, sups, out, own)
        done = finished_trials(out, fingerprint(cfg, [*POLICIES.names(), *SUPERVISORS.names()]))
    except BaseException:
        src.close()
        raise
    log = RunLog(out)
    results: dict[str, Any] = {}
    try:
        total = len(tasks) * len(sups) * cfg.trials
        bar = tqdm(total=total, desc="trials", unit="trial", disable=not cfg.progress)
        for fam in tasks:
            per: dict[str, list[dict[str, Any]]] = {}
            for name in sups:
                rows = per.setdefault(name, [])
                for i in range(cfg.trials):
                    trial = f"{fam.name}-{name}-{i:03d}"
                    if trial not in done:
                        keep = None if name not in sinks else lambda ep, n=name, f=fam.name, i=i: sinks[n].add(ep, f, i)
                        scenario = fam.scenarios[i % len(fam.scenarios)]
                        args = (fam, scenario, int(cfg.seed) + i, cfg.variant, loop, log, trial)
                        done[trial] = run_trial(src, policy, supervisors[name], *args, keep=keep)
                        if done[trial]["outcome"] == "policy_error":  # said once per trial; the run goes on
                            tqdm.write(f"trial {trial}: policy error: {done[trial]['error']}", file=sys.stderr)
                    rows.append(done[trial])
                    bar.update(1)
            results[fam.name] = {"policy": cfg.policy, **{n: summarize(r) for n, r in per.items()}}
            if len(sups) == 2:
                base, sup = results[fam.name]["none"], results[fam.name][cfg.supervisor]
                results[fam.name]["improvement"] = round(sup["rate"] - base["rate"], 2)
                # trial i ran from the same seed with and without the supervisor: compared pair by pair
                outcomes = [[bool(r["success"]) for r in per[n]] for n in sups]
                results[fam.name]["paired"] = paired_cell(*outcomes).summary()
        bar.close()
    finally:  # the shards first (what the run made), then the rest whatever a sink raised
        try:
            for n, sink in sinks.items():
                sink.close([r for r in done.values() if r["supervisor"] == n])
        finally:
            log.close()
            src.close()
            policy.close()
    return {"config": OmegaConf.to_container(cfg, resolve=True), "tasks": results}


def table_md(res: dict[str, Any]) -> str:
    """The paper's table: Task | Baseline | Rate | +Supervisor | Rate | Improv."""
    cfg = res["config"]
    sup = cfg["supervisor"]
    lines = [
        f"Success rate of downstream policy recovery ({cfg['policy']} policy, supervisor {sup}, "
        f"{cfg['trials']} trials per task, variant {cfg['variant']})",
        "",
        f"| Task | Baseline | Rate (%) | +{sup} | Rate (%) | Improv. | 95 % CI | McNemar p | successes broken |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for task, r in res["tasks"].items():
        base = r.get("none")
        s = r.get(sup, base)
        lines.append(
            f"| {task} | {cfg['policy']} | {base['rate'] if base else '-'} | {s['success']}/{s['trials']} | "
            f"{s['rate']} | {('%+.0f%%' % r['improvement']) if 'improvement' in r else '-'} | "
            f"{paired_md(r.get('paired'))} |"
        )
    errors = sum(
        len(v.get("policy_errors", [])) for r in res["tasks"].values() for v in r.values() if isinstance(v, dict)
    )
    if errors:
        lines += ["", f"{errors} trial(s) ended on a policy error (results.json `policy_errors`, log.jsonl `error`)."]
    return "\n".join(lines) + "\n"
