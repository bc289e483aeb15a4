"""Closed-loop supervision, the paper's recovery table (sim_backends/supervision/cli.py; `--help` lists every
setting).

Run as:
    python scripts/supervise.py policy=scripted supervisor=oracle task=place trials=25 backend=pybullet
    python scripts/supervise.py policy=scripted supervisor=vlm vlm.model=outputs/demo_train/final task=place
    python scripts/supervise.py policy=act act.checkpoint=outputs/act/pick/final supervisor=oracle task=pick
"""

from sim_backends.supervision.cli import cli

if __name__ == "__main__":
    cli()
