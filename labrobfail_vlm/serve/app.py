"""The diagnosis server's FastAPI app: `create_app(analyzer, ServeConfig(...))`.

    POST /diagnose  multipart form (labrobfail_vlm.serve.form) -> the Diagnosis JSON (Diagnosis.to_json())
    GET  /health    {"status": "ok", queue and batch counters}; never needs the token
    GET  /info      model, grid layout, operating points (threshold, option biases), version, batching settings

Errors are one JSON line, {"error": "..."}: 400 bad field or image, 401 missing/wrong token, 404/405,
408 body not received within `body_timeout_s`, 413 upload over the limit, a decompression bomb or images too
large to decode (per-request limit), 415 not multipart, 503 queue full, decode budget busy or shutting down,
500 (never with a traceback) if the model itself fails. The token (if set) is compared in constant time and
never logged or echoed. A client that disconnects mid-upload is logged in one line.

Memory: images are priced from their headers (labrobfail_vlm.serve.form) and decoded only within a budget
shared by all requests (labrobfail_vlm.serve.budget), held until each reply: the image memory of all requests
together never exceeds `max_decode_bytes`, one request's never `max_request_decode_bytes` (larger: 413).
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
from contextlib import asynccontextmanager
from dataclasses import asdict, dataclass
from typing import Any, Awaitable, Callable, MutableMapping

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect

from labrobfail_vlm.analyzer import DiagnosisRequest
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.images import ImageTooLarge
from labrobfail_vlm.serve.batcher import Batcher, Busy
from labrobfail_vlm.serve.budget import DecodeBudget, Reservation, mb
from labrobfail_vlm.serve.form import FIELDS, MAX_REQUEST_DECODE_BYTES, Upload, build, plan

log = logging.getLogger("labrobfail.serve")
Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]
Send = Callable[[MutableMapping[str, Any]], Awaitable[None]]


@dataclass(frozen=True)
class ServeConfig:
    model_name: str = "model"
    max_batch: int = 8
    max_wait_ms: float = 10.0
    max_queue: int = 1024
    max_upload_bytes: int = 32 * 1024 * 1024
    max_files: int = 256
    token: str | None = None  # the bearer token; None or "" = no token required
    max_decode_bytes: int = 1 << 30  # image memory held by all requests together (form.plan prices it)
    max_request_decode_bytes: int = MAX_REQUEST_DECODE_BYTES  # ... by one request (larger: 413)
    body_timeout_s: float = 30.0  # the whole body must arrive within this, from its first read (else 408)
    decode_wait_s: float = 30.0  # how long a request waits for decode budget before a 503

    def __post_init__(self) -> None:
        if not 0 < self.max_request_decode_bytes <= self.max_decode_bytes:
            raise ValueError("serve: max_request_decode_bytes must be > 0 and at most max_decode_bytes")
        if not (self.body_timeout_s > 0 and self.decode_wait_s >= 0):
            raise ValueError("serve: body_timeout_s must be > 0 and decode_wait_s >= 0")

    def public(self) -> dict[str, Any]:
        """The settings /info shows (never the token)."""
        d = asdict(self)
        d.pop("token")
        d["token_required"] = bool(self.token)
        return d


class BodyTooLarge(Exception):
    pass


class BodyTimeout(Exception):
    """The body did not arrive in time (a client that sends less than its Content-Length, or too slowly)."""


class Guard:
    """ASGI middleware in front of the app: the bearer token (every path but /health) and the upload size, both
    checked before the body is read; a body streamed past the limit stops with BodyTooLarge, one that has not
    fully arrived `body_timeout_s` after the app started reading it with BodyTimeout. A client that goes away
    before its body is complete is logged here, in one line (the app then drops the request quietly)."""

    def __init__(
        self, app: Any, token: str | None, max_bytes: int, body_timeout_s: float = 30.0, error_key: str = "error"
    ):
        self.app, self.max_bytes, self.body_timeout_s = app, max_bytes, body_timeout_s
        self.error_key = error_key  # the JSON field of an error reply: "error" here, "detail" on OpenVLA's wire
        self._expected = f"Bearer {token}".encode() if token else None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        if self._expected is not None and scope.get("path") != "/health":
            given = headers.get(b"authorization", b"")
            if not hmac.compare_digest(given, self._expected):
                return await _reply(
                    send,
                    self.error_key,
                    401,
                    "missing or wrong bearer token (Authorization: Bearer <token>)",
                    [(b"www-authenticate", b"Bearer")],
                )
        length = headers.get(b"content-length", b"")
        if length.isdigit() and int(length) > self.max_bytes:
            return await _reply(
                send, self.error_key, 413, f"upload of {int(length):,} bytes is over the {self.max_bytes:,} byte limit"
            )
        seen, done, deadline = 0, False, 0.0
        loop = asyncio.get_running_loop()

        async def counted() -> MutableMapping[str, Any]:
            nonlocal seen, done, deadline
            if done:  # body complete: later reads only wait for a disconnect, which has no deadline
                return await receive()
            deadline = deadline or loop.time() + self.body_timeout_s
            try:
                msg = await asyncio.wait_for(receive(), max(0.0, deadline - loop.time()))
            except asyncio.TimeoutError:
                raise BodyTimeout() from None
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.max_bytes:
                    raise BodyTooLarge()
                done = not msg.get("more_body", False)
            elif msg["type"] == "http.disconnect":
                done = True
                host = ":".join(map(str, scope.get("client") or ("?",)))
                log.warning(
                    "client %s disconnected mid-upload (%s of %s bytes received); request dropped",
                    host,
                    f"{seen:,}",
                    f"{int(length):,}" if length.isdigit() else "?",
                )
            return msg

        await self.app(scope, counted, send)


async def _reply(
    send: Send, key: str, status: int, message: str, extra: list[tuple[bytes, bytes]] | None = None
) -> None:
    body = json.dumps({key: message}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *(extra or []),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


def version() -> str:
    """The installed labrobfail package's version (`unknown` when run from a source tree that is not installed)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as pkg_version

    try:
        return pkg_version("labrobfail")
    except PackageNotFoundError:
        return "unknown"


def error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status)


def add_error_handlers(app: FastAPI, cfg: ServeConfig) -> None:
    """Every failure as one JSON line {"error": ...}: HTTP errors, validation, the Guard's size and time limits, a
    client gone mid-upload, and anything the model raises (500, logged in one line, never a traceback)."""

    @app.exception_handler(HTTPException)
    async def http_error(_: Request, exc: HTTPException) -> JSONResponse:
        return error(exc.status_code, str(exc.detail).splitlines()[0] if exc.detail else "error")

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        return error(400, "invalid request")

    @app.exception_handler(BodyTooLarge)
    async def too_large(_: Request, __: BodyTooLarge) -> JSONResponse:
        return error(413, f"upload is over the {cfg.max_upload_bytes:,} byte limit")

    @app.exception_handler(BodyTimeout)
    async def too_slow(_: Request, __: BodyTimeout) -> JSONResponse:
        # the rest of the body may still come: close the connection rather than read it
        return JSONResponse(
            {
                "error": f"request body not received within {cfg.body_timeout_s:g} s (shorter than "
                f"its Content-Length, or too slow)"
            },
            status_code=408,
            headers={"connection": "close"},
        )

    @app.exception_handler(ClientDisconnect)
    async def gone(_: Request, __: ClientDisconnect) -> Response:
        return Response(status_code=400)  # nobody reads it; the Guard has logged the disconnect

    @app.exception_handler(Exception)
    async def internal(_: Request, exc: Exception) -> JSONResponse:
        log.error("internal error: %s: %s", type(exc).__name__, str(exc).splitlines()[0][:200] if str(exc) else "")
        return error(500, f"internal error ({type(exc).__name__})")


async def read_form(request: Request, max_files: int) -> list[tuple[str, str | Upload]]:
    """The multipart form's fields, files read into memory (the Guard bounds the whole body)."""
    form = await request.form(max_files=max_files, max_fields=16, max_part_size=64 * 1024)
    try:
        return [
            (k, Upload(v.filename or "", await v.read()) if isinstance(v, UploadFile) else v)
            for k, v in form.multi_items()
        ]
    finally:
        await form.close()


def create_app(analyzer: Any, cfg: ServeConfig = ServeConfig()) -> Guard:
    """The app for one loaded FailureAnalyzer (the model is loaded once, by the caller)."""
    __version__ = version()

    def run(batch: list[Any]) -> list[str]:
        return [d.to_json() for d in analyzer.analyze_batch(batch, max_batch=cfg.max_batch)]

    batcher: Batcher[Any, str] = Batcher(run, cfg.max_batch, cfg.max_wait_ms / 1000, cfg.max_queue)
    budget = DecodeBudget(cfg.max_decode_bytes)

    @asynccontextmanager
    async def lifespan(_: Any):  # type: ignore[no-untyped-def]
        await batcher.start()
        yield
        await batcher.stop()  # after uvicorn has let in-flight requests finish: drain what is queued

    app = FastAPI(
        title="LabRobFail-VLM diagnosis",
        version=__version__,
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
        openapi_url=None,
    )

    add_error_handlers(app, cfg)

    @app.get("/health")
    async def health() -> dict[str, Any]:
        s = batcher.stats
        return {
            "status": "ok",
            "queued": batcher.queued,
            "batches": s.batches,
            "diagnoses": s.items,
            "largest_batch": s.largest,
            "failed": s.failed,
            "decode_bytes_held": budget.used,
            "decode_bytes_peak": budget.peak,
            "decode_budget_bytes": budget.total,
        }

    @app.get("/info")
    async def info() -> dict[str, Any]:
        p = next(analyzer.model.parameters())
        return {
            "model": cfg.model_name,
            "version": __version__,
            "grid": asdict(analyzer.grid),
            "q6_mode": analyzer.q6_mode,
            "threshold": analyzer.threshold,  # the Q2 operating point
            "option_bias": {k: list(v) for k, v in analyzer.option_bias.items()},  # Q3-Q5, if fitted
            "failure_score": analyzer.failure_score,  # how P(failure) is read (failure_score.py)
            "device": str(p.device),
            "dtype": str(p.dtype).removeprefix("torch."),
            "serve": cfg.public(),
            "fields": FIELDS,
        }

    @app.post("/diagnose")
    async def diagnose(request: Request) -> Response:
        ctype = request.headers.get("content-type", "")
        if not ctype.startswith("multipart/form-data"):
            return error(415, f"expected a multipart/form-data upload ({FIELDS})")
        try:
            req, held = await prepare(await read_form(request, cfg.max_files))
        except ImageTooLarge as e:
            return error(413, str(e))
        except ConfigError as e:
            return error(400, str(e))
        except Busy as e:
            return error(503, str(e))
        try:
            body = await batcher.submit(req)
        except Busy as e:
            return error(503, str(e))
        except ConfigError as e:  # the request's own fault found by the model thread: a 400, like the form's
            return error(400, str(e))
        finally:  # the decoded grid waited in the queue until now: its memory counted until the reply
            await held.release()
        return Response(body, media_type="application/json")

    async def prepare(items: list[tuple[str, str | Upload]]) -> tuple[DiagnosisRequest, Reservation]:
        """Fields checked and images priced from their headers, memory reserved, then decoded (off the event
        loop); the reservation shrinks to what the request still holds. The raw uploads are dropped on return."""
        p = await run_in_threadpool(plan, items, analyzer.grid, cfg.max_request_decode_bytes, analyzer.fit_grid)
        held = await budget.reserve(p.cost, cfg.decode_wait_s)
        try:
            req = await run_in_threadpool(build, p, analyzer.grid)
        except BaseException:
            await held.release()
            raise
        await held.shrink(p.kept)
        log.debug("decoded %s (held now %s of %s)", mb(p.cost), mb(budget.used), mb(budget.total))
        return req, held

    return Guard(app, cfg.token, cfg.max_upload_bytes, cfg.body_timeout_s)
