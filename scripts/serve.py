"""Serve LabRobFail-VLM over HTTP: POST /diagnose (grid or per-view keyframes -> Diagnosis JSON), GET /health, /info.

Run as:
    python scripts/serve.py --model outputs/demo_train/final [--host 127.0.0.1] [--port 8100]
    LABROBFAIL_API_TOKEN=... python scripts/serve.py --model DIR --max-batch 16 --max-wait-ms 20
    curl -F grid=@grid.png -F task="pick up the small beaker" http://127.0.0.1:8100/diagnose

Loopback only unless --host says otherwise. With $LABROBFAIL_API_TOKEN set (or the variable --token-env names),
every request but /health needs `Authorization: Bearer <token>`. Requests are batched: up to --max-batch
diagnoses per model call, waiting at most --max-wait-ms for a batch to fill. Ctrl-C / SIGTERM finishes the
requests in flight, then exits. Bad arguments or model directories give one line on stderr and exit code 2: the
model is validated before any tensor is built (config, size against --max-model-gb / $LABROBFAIL_MAX_MODEL_GB,
default half the machine's memory, weights), so a bad checkpoint fails at start.

Memory bound besides the model: raw uploads <= --max-connections x --max-upload-mb, decoded images <=
--max-decode-mb across all requests (<= --max-request-decode-mb each, priced from the image headers before
decoding), plus the model's activations for --max-batch grids. A body must arrive within --body-timeout-s (408).
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import math
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


def check_bounds(a: argparse.Namespace) -> None:
    """The memory and time bounds: positive, finite, and one request's decode limit within the shared budget."""
    for flag in ("max_decode_mb", "max_request_decode_mb", "body_timeout_s"):
        v = getattr(a, flag)
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(f"--{flag.replace('_', '-')}: expected a positive number, got {v}")
    if a.max_request_decode_mb > a.max_decode_mb:
        raise ConfigError(f"--max-request-decode-mb ({a.max_request_decode_mb:g}) must not exceed --max-decode-mb "
                          f"({a.max_decode_mb:g})")
    if a.max_connections < 1:
        raise ConfigError(f"--max-connections: expected a positive integer, got {a.max_connections}")


def app_log(level: str) -> None:
    """The app's own lines (a client gone mid-upload, an internal error) in uvicorn's format, one line each."""
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s:  %(message)s"))
    lg = logging.getLogger("labrobfail.serve")
    lg.addHandler(handler)
    lg.setLevel(level.upper())
    lg.propagate = False


def main(argv: list[str]) -> int:
    ap = _Parser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="fine-tuned checkpoint, merged model or Qwen3-VL directory")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=8100, help="0 picks a free port (printed at start)")
    ap.add_argument("--max-batch", type=int, default=8, help="diagnoses per model call (1 = no batching)")
    ap.add_argument("--max-wait-ms", type=float, default=10.0, help="how long a batch waits to fill")
    ap.add_argument("--max-queue", type=int, default=1024, help="queued requests before 503")
    ap.add_argument("--max-upload-mb", type=float, default=32.0)
    ap.add_argument("--max-connections", type=int, default=64,
                    help="connections served at once (more get 503): bounds raw upload memory to this x upload size")
    ap.add_argument("--max-decode-mb", type=float, default=1024.0,
                    help="MiB of decoded images held by all requests together (others wait, then 503)")
    ap.add_argument("--max-request-decode-mb", type=float, default=256.0,
                    help="MiB one request's images may take decoded (larger: 413 before decoding)")
    ap.add_argument("--body-timeout-s", type=float, default=30.0,
                    help="seconds a request body may take to arrive (else 408)")
    ap.add_argument("--max-model-gb", type=float, default=None,
                    help="refuse models whose weights would take more (default: $LABROBFAIL_MAX_MODEL_GB, else half "
                         "the machine's memory)")
    ap.add_argument("--q6-mode", choices=("free", "template"), default="free")
    ap.add_argument("--token-env", default="LABROBFAIL_API_TOKEN", help="environment variable holding the token")
    ap.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))
    a = ap.parse_args(argv)
    if not 0 <= a.port <= 65535:
        raise ConfigError(f"--port: expected 0-65535, got {a.port}")
    if a.max_batch < 1 or a.max_queue < 1 or a.max_wait_ms < 0 or a.max_upload_mb <= 0:
        raise ConfigError("--max-batch/--max-queue must be >= 1, --max-wait-ms >= 0, --max-upload-mb > 0")
    check_bounds(a)

    from labrobfail_vlm.train.checkpoint import validate_checkpoint

    if not Path(a.model).is_dir():
        raise ConfigError(f"--model: no such model directory {a.model!r}")
    validate_checkpoint(a.model, "--model", a.max_model_gb)  # before any tensor is built: fail at start
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

    fa = FailureAnalyzer.from_pretrained(a.model, q6_mode=a.q6_mode, max_model_gb=a.max_model_gb)
    cfg = ServeConfig(model_name=Path(a.model).resolve().name, max_batch=a.max_batch, max_wait_ms=a.max_wait_ms,
                      max_queue=a.max_queue, max_upload_bytes=int(a.max_upload_mb * 1024 * 1024), token=token or None,
                      max_decode_bytes=int(a.max_decode_mb * 1024 * 1024),
                      max_request_decode_bytes=int(a.max_request_decode_mb * 1024 * 1024),
                      body_timeout_s=a.body_timeout_s)
    app_log(a.log_level)
    server = uvicorn.Server(uvicorn.Config(create_app(fa, cfg), log_level=a.log_level, lifespan="on",
                                           limit_concurrency=a.max_connections))
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
