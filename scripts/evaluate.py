"""Score a model (or a predictions file) on LabRobFail-Bench (labrobfail_vlm/bench/cli.py; `--help` lists every
setting).

Run as:
    python scripts/evaluate.py model=outputs/demo_train/final dataset_dir=outputs/demo_dataset split=test
    python scripts/evaluate.py predictions=preds.jsonl dataset_dir=outputs/dataset split=val_object
    python scripts/evaluate.py model=DIR dataset_dir=DIR executable.enabled=true executable.shards=SHARDS_DIR
"""

from labrobfail_vlm.bench.cli import cli

if __name__ == "__main__":
    cli()
