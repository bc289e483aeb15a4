"""Closed-loop supervision: success rate per task without and with a supervisor (the paper's recovery table).
The code behind the `labrobfail-supervise` console script.

Run as:
    labrobfail-supervise policy=scripted supervisor=oracle task=place trials=25 backend=pybullet
    labrobfail-supervise policy=scripted supervisor=vlm vlm.model=outputs/demo_train/final task=place
    labrobfail-supervise policy=act act.checkpoint=outputs/act/pick/final supervisor=oracle task=pick
    labrobfail-supervise policy=openvla openvla.url=http://127.0.0.1:8777/act supervisor=none task=pour
    labrobfail-supervise policy=openvla openvla.encoded=true openvla.timeout_s=30 task=pick

Writes out_dir/results.json (per task: successes, rate, difference, query latency p50/p95, interventions,
policy errors), out_dir/results.md (the table), out_dir/log.jsonl (every query and episode) and out_dir/grids/.
Defaults: configs/supervise.yaml. A bad setting (unknown policy or task, missing checkpoint, unreachable
server, a client option of the wrong type) is a one-line error and exit code 2. A policy that cannot act (a
server that answers garbage, "error" or nothing) ends that trial with outcome "policy_error" and a one-line
reason, said on stderr; the run goes on and writes its results.
"""

from __future__ import annotations

from pathlib import Path

from labrobfail_vlm.config import cli_main, load_config


def main(argv: list[str]) -> int:
    from labrobfail_vlm.io import atomic_write_bytes, atomic_write_json
    from sim_backends.supervision.experiment import run, table_md

    cfg = load_config("supervise.yaml", argv)
    res = run(cfg)
    out = Path(cfg.out_dir)
    atomic_write_json(out / "results.json", res)
    md = table_md(res)
    atomic_write_bytes(out / "results.md", md.encode())
    print(md)
    return 0


def cli() -> None:
    """The `labrobfail-supervise` console script."""
    cli_main(main, __doc__)
