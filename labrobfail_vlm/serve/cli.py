"""Serve LabRobFail-VLM over HTTP: POST /diagnose (grid or per-view keyframes -> Diagnosis JSON), GET /health,
/info. The code behind the `labrobfail-serve` console script.

Run as:
    labrobfail-serve --model outputs/demo_train/final [--host 127.0.0.1] [--port 8100]
    LABROBFAIL_API_TOKEN=... labrobfail-serve --model DIR --max-batch 16 --max-wait-ms 20
    curl -F grid=@grid.png -F task="pick up the small beaker" http://127.0.0.1:8100/diagnose

Loopback only unless host says otherwise. With $LABROBFAIL_API_TOKEN set (or the variable token_env names),
every request but /health needs `Authorization: Bearer <token>`. Requests are batched: up to max_batch
diagnoses per model call, waiting at most max_wait_ms for a batch to fill. Ctrl-C / SIGTERM finishes the
requests in flight, then exits. Bad arguments or model directories give one line on stderr and exit code 2: the
model is validated before any tensor is built (config, size against max_model_gb / $LABROBFAIL_MAX_MODEL_GB,
default half the machine's memory, weights), so a bad checkpoint fails at start.

Memory bound besides the model: raw uploads <= max_connections x max_upload_mb, decoded images <=
max_decode_mb across all requests (<= max_request_decode_mb each, priced from the image headers before
decoding), plus the model's activations for max_batch grids. A body must arrive within body_timeout_s (408), and a
request's head within the same time of its connection (else the connection is closed).
Defaults: configs/serve.yaml.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.serve.http import app_log, bearer_token, listen, serve


def _num(a: Any, key: str, integer: bool = False, low: float = 0.0, strict: bool = True) -> None:
    v = a[key]
    ok = isinstance(v, int) if integer else isinstance(v, (int, float))
    if isinstance(v, bool) or not ok or not math.isfinite(v) or (v <= low if strict else v < low):
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"{key}: expected {kind} {'>' if strict else '>='} {low:g}, got {v!r}")


def check_bounds(a: Any) -> None:
    """Every number: the port, the batch and queue sizes, and the memory and time bounds (positive, finite, and
    one request's decode limit within the shared budget)."""
    _num(a, "port", integer=True, low=0, strict=False)
    if a.port > 65535:
        raise ConfigError(f"port: expected 0-65535, got {a.port}")
    for key in ("max_batch", "max_queue", "max_connections"):
        _num(a, key, integer=True)
    _num(a, "max_wait_ms", low=0, strict=False)
    for key in ("max_upload_mb", "max_decode_mb", "max_request_decode_mb", "body_timeout_s"):
        _num(a, key)
    if a.max_request_decode_mb > a.max_decode_mb:
        raise ConfigError(
            f"max_request_decode_mb ({a.max_request_decode_mb:g}) must not exceed max_decode_mb ({a.max_decode_mb:g})"
        )
    if a.q6_mode not in ("free", "template"):
        raise ConfigError(f"q6_mode: expected free or template, got {a.q6_mode!r}")
    if str(a.log_level) not in ("critical", "error", "warning", "info", "debug"):
        raise ConfigError(f"log_level: expected critical, error, warning, info or debug, got {a.log_level!r}")


def main(argv: list[str]) -> int:
    a = load_config("serve.yaml", argv)
    if not isinstance(a.model, str):
        raise ConfigError("model: give the model folder to serve (model=DIR or --model DIR)")
    check_bounds(a)

    from labrobfail_vlm.train.checkpoint import validate_checkpoint

    if not Path(a.model).is_dir():
        raise ConfigError(f"model: no such model directory {a.model!r}")
    validate_checkpoint(a.model, "model", a.max_model_gb)  # before any tensor is built: fail at start
    token = bearer_token(a.token_env, a.host)
    sock = listen(a.host, a.port)  # bind before loading the model: a taken port fails fast

    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.serve.app import ServeConfig, create_app

    fa = FailureAnalyzer.from_pretrained(a.model, q6_mode=a.q6_mode, max_model_gb=a.max_model_gb)
    cfg = ServeConfig(
        model_name=Path(a.model).resolve().name,
        max_batch=a.max_batch,
        max_wait_ms=a.max_wait_ms,
        max_queue=a.max_queue,
        max_upload_bytes=int(a.max_upload_mb * 1024 * 1024),
        token=token,
        max_decode_bytes=int(a.max_decode_mb * 1024 * 1024),
        max_request_decode_bytes=int(a.max_request_decode_mb * 1024 * 1024),
        body_timeout_s=a.body_timeout_s,
    )
    app_log("labrobfail.serve", a.log_level)
    port = sock.getsockname()[1]
    print(
        f"serving {cfg.model_name} on http://{a.host}:{port} (max batch {a.max_batch}, "
        f"token {'required' if token else 'off'})",
        flush=True,
    )
    serve(create_app(fa, cfg), sock, a.log_level, a.max_connections, a.body_timeout_s)
    return 0


def cli() -> None:
    """The `labrobfail-serve` console script."""
    cli_main(main, __doc__)
