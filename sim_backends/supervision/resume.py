"""A stopped `labrobfail-supervise` run goes on where it stopped: run it again with the same settings.

Trial i of a task runs from seed `seed + i` whatever ran before it (the backend, the policy's injection and the
supervisor are all reset from that seed), so a trial that finished need not run again. Its record is log.jsonl's
"episode" line, written when the trial ends (after its rollout shard, when `shards=true`). On a second run into an
out_dir, the trials with such a line are taken from it and the rest run (appending to the log); the lines a killed
trial left (its queries, a half-written line) are cut from the log first, so each trial's records are one run's.
More trials than before extend the run (trial i is the same trial whatever `trials` says); fewer summarise the
first `trials` in results.json, while the log and the shards keep every trial run.

What must match: out_dir/run_config.json, written before the first trial, holds the settings that decide a trial's
outcome (the config less trials, progress, out_dir and the sections of policies and supervisors not in use), each
setting that names a file or folder given as its content digest (a model retrained in place is another run; the
same model by another path is the same). Any difference, or an out_dir holding trials of a version without
run_config.json, is a one-line error: nothing there is overwritten. A run stopped before its first trial ended
left nothing to keep: its settings are replaced.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from labrobfail_vlm.config import ConfigError, first_difference
from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json, sha256_file

RUN_CONFIG = "run_config.json"
LOG = "log.jsonl"
# settings that do not change what any one trial does (a dotted key names one inside a section: vlm.check_drawing
# only refuses a run before its first trial)
PER_RUN = ("trials", "progress", "out_dir", "vlm.check_drawing")


def content_digest(path: Path) -> str:
    """A file's sha256, or a folder's over its top-level files (names and contents; subfolders such as a model's
    eval_* outputs are not the model)."""
    if path.is_file():
        return sha256_file(path)
    h = hashlib.sha256()
    for f in sorted(p for p in path.iterdir() if p.is_file()):
        h.update(f"{f.name}\0{sha256_file(f)}\n".encode())
    return h.hexdigest()


def fingerprint(cfg: DictConfig, sections: list[str]) -> dict[str, Any]:
    """What decides a trial's outcome: the config less PER_RUN and the unused policy and supervisor sections
    (`sections`: every such section name; those of the run's policy and supervisors stay), every value naming an
    existing file or folder replaced by its content digest."""
    conf: dict[str, Any] = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    used = {str(cfg.policy), str(cfg.supervisor)}
    for k in [*PER_RUN, *(s for s in sections if s not in used)]:
        *outer, last = k.split(".")
        node: Any = conf
        for part in outer:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(last, None)
    return {"config": _digested(conf)}


def _digested(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _digested(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_digested(x) for x in v]
    if isinstance(v, str) and v and Path(v).exists():
        return f"<content sha256 {content_digest(Path(v))}>"
    return v


def finished_trials(out: Path, fp: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The trials an earlier run of these settings finished in `out` (trial id -> its episode record); log.jsonl cut
    back to the last of them. {} for a new out_dir, after writing its run_config.json."""
    conf_f, log_f = out / RUN_CONFIG, out / LOG
    raw = log_f.read_text(encoding="utf-8") if log_f.is_file() else ""
    shards = any((out / "shards").glob("*/shard-*.parquet"))
    if not conf_f.is_file() and (raw or shards):
        raise ConfigError(f"out_dir: {out} holds trials of a run without {RUN_CONFIG}; give a new out_dir")
    lines = raw.split("\n")[:-1]  # complete lines only: what follows the last newline is a kill's half line
    done: dict[str, dict[str, Any]] = {}
    kept = 0
    for i, line in enumerate(lines):
        try:
            rec = json.loads(line)
        except ValueError:  # a line a kill cut short: nothing after it was written
            break
        if rec.get("event") == "episode":
            done[rec["trial"]], kept = rec, i + 1
    if not done and not shards:  # a new out_dir, or a run stopped before any trial ended: these settings
        atomic_write_json(conf_f, fp)
        log_f.unlink(missing_ok=True)
        return {}
    try:
        old = json.loads(conf_f.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"out_dir: cannot read {conf_f} ({e})") from None
    if (key := first_difference(old, json.loads(json.dumps(fp)))) is not None:
        raise ConfigError(f"out_dir: {out} holds trials of another run ({key} differs); give a new out_dir")
    if kept < len(lines) or not raw.endswith("\n"):
        atomic_write_bytes(log_f, "".join(f"{line}\n" for line in lines[:kept]).encode())
    return done
