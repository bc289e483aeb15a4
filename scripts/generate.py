"""Generate labeled failure/success episode pairs into Parquet shards (sim_backends/generate.py; `--help` lists
every setting).

Run as:
    python scripts/generate.py backend=pybullet num_episodes=200 out_dir=outputs/shards seed=0 workers=2
    python scripts/generate.py num_episodes=100 out_dir=outputs/val_both variant=val_both
    python scripts/generate.py num_episodes=1000 out_dir=outputs/big executor=ray workers=8

Rerunning the same command after a kill resumes; DIR/manifest.json summarises the run.
"""

from sim_backends.generate import cli

if __name__ == "__main__":
    cli()
