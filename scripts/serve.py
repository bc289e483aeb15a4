"""Serve LabRobFail-VLM over HTTP: POST /diagnose (grid or per-view keyframes -> Diagnosis JSON), GET /health, /info.

Run as:
    python scripts/serve.py --model outputs/demo_train/final [--host 127.0.0.1] [--port 8100]
    LABROBFAIL_API_TOKEN=... python scripts/serve.py --model DIR --max-batch 16 --max-wait-ms 20
    curl -F grid=@grid.png -F task="pick up the small beaker" http://127.0.0.1:8100/diagnose

Loopback only unless --host says otherwise. With $LABROBFAIL_API_TOKEN set (or the variable --token-env names),
every request but /health needs `Authorization: Bearer <token>`. Requests are batched: up to --max-batch
diagnoses per model call, waiting at most --max-wait-ms for a batch to fill. Ctrl-C / SIGTERM finishes the
requests in flight, then exits. Bad arguments or model directories give one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import signal
import socket
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from labrobfail_vlm.config import ConfigError, cli_main  # noqa: E402


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2, like every other bad input
        raise ConfigError(f"usage: {message}")


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def main(argv: list[str]) -> int:
    ap = _Parser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="fine-tuned checkpoint, merged model or Qwen3-VL directory")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=8100, help="0 picks a free port (printed at start)")
    ap.add_argument("--max-batch", type=int, default=8, help="diagnoses per model call (1 = no batching)")
    ap.add_argument("--max-wait-ms", type=float, default=10.0, help="how long a batch waits to fill")
    ap.add_argument("--max-queue", type=int, default=1024, help="queued requests before 503")
    ap.add_argument("--max-upload-mb", type=float, default=32.0)
    ap.add_argument("--q6-mode", choices=("free", "template"), default="free")
    ap.add_argument("--token-env", default="LABROBFAIL_API_TOKEN", help="environment variable holding the token")
    ap.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))
    a = ap.parse_args(argv)
    if not 0 <= a.port <= 65535:
        raise ConfigError(f"--port: expected 0-65535, got {a.port}")
    if a.max_batch < 1 or a.max_queue < 1 or a.max_wait_ms < 0 or a.max_upload_mb <= 0:
        raise ConfigError("--max-batch/--max-queue must be >= 1, --max-wait-ms >= 0, --max-upload-mb > 0")

    from labrobfail_vlm.model.loading import check_model_dir
    from labrobfail_vlm.train.checkpoint import is_finetuned

    if not Path(a.model).is_dir():
        raise ConfigError(f"--model: no such model directory {a.model!r}")
    if not is_finetuned(a.model):
        check_model_dir(a.model, "--model")
    token = os.environ.get(a.token_env, "")
    if not _loopback(a.host) and not token:
        print(f"warning: serving on {a.host} without a token; set {a.token_env} to require one", file=sys.stderr)
    try:  # bind before loading the model: a taken port fails fast
        sock = socket.socket(socket.AF_INET6 if ":" in a.host else socket.AF_INET)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((a.host, a.port))
    except OSError as e:
        raise ConfigError(f"--host/--port: cannot listen on {a.host}:{a.port} ({e.strerror or e})") from None

    import uvicorn

    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.serve.app import ServeConfig, create_app

    fa = FailureAnalyzer.from_pretrained(a.model, q6_mode=a.q6_mode)
    cfg = ServeConfig(model_name=Path(a.model).resolve().name, max_batch=a.max_batch, max_wait_ms=a.max_wait_ms,
                      max_queue=a.max_queue, max_upload_bytes=int(a.max_upload_mb * 1024 * 1024), token=token or None)
    server = uvicorn.Server(uvicorn.Config(create_app(fa, cfg), log_level=a.log_level, lifespan="on"))
    port = sock.getsockname()[1]
    print(f"serving {cfg.model_name} on http://{a.host}:{port} (max batch {a.max_batch}, "
          f"token {'required' if token else 'off'})", flush=True)
    # uvicorn finishes the requests in flight on SIGINT/SIGTERM, then raises the signal again: handled here, so a
    # graceful stop exits 0
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: None)
    server.run(sockets=[sock])
    print("stopped: requests in flight finished", flush=True)
    return 0


if __name__ == "__main__":
    cli_main(main)
