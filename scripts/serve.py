"""Serve LabRobFail-VLM over HTTP (labrobfail_vlm/serve/cli.py; `--help` lists every setting).

Run as:
    python scripts/serve.py --model outputs/demo_train/final [--host 127.0.0.1] [--port 8100]
    LABROBFAIL_API_TOKEN=... python scripts/serve.py --model DIR --max-batch 16 --max-wait-ms 20
"""

from labrobfail_vlm.serve.cli import cli

if __name__ == "__main__":
    cli()
