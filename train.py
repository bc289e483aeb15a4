"""Fine-tune LabRobFail-VLM (labrobfail_vlm/train/cli.py; `--help` lists every setting).

Run as:
    python train.py preset=tiny dataset_dir=outputs/demo_dataset output_dir=outputs/demo_train max_steps=50
    python train.py model.path=/models/Qwen3-VL-8B-Instruct dataset_dir=outputs/dataset output_dir=outputs/run
    deepspeed --num_gpus 2 train.py deepspeed=configs/ds_zero3.json model.path=... dataset_dir=... output_dir=...
"""

from labrobfail_vlm.train.cli import cli

if __name__ == "__main__":
    cli()
