"""Serve a project policy (ACT, scripted) behind OpenVLA's REST protocol: a drop-in peer of OpenVLA's
`vla-scripts/deploy.py`, on the same FastAPI/uvicorn stack as the diagnosis server (labrobfail_vlm/serve/).

Run as:
    labrobfail-serve-policy policy=act act.checkpoint=outputs/act/pick/final port=8777
    labrobfail-serve-policy policy=scripted port=0          # prints the port it got
    labrobfail-serve-policy policy=scripted default_episode.scenario=pick_place_beaker_small
    LABROBFAIL_POLICY_TOKEN=... labrobfail-serve-policy policy=act act.checkpoint=DIR host=0.0.0.0

`POST /act` takes OpenVLA's request exactly as OpenVLA's own client sends it (`requests.post(url, json={"image":
uint8 HxWx3, "instruction": str})` after `json_numpy.patch()`, optional `unnorm_key`, or the `{"encoded":
"<json-numpy string>"}` form) and answers a json-numpy 7-D action (delta position, delta roll/pitch/yaw in the
base frame, gripper 1 = open; a JSON string holding it for the encoded form), as OpenVLA does. The project's
client may add optional extras: `images` (every view), `proprio` (ee_pos, ee_quat, width, grip_cmd) and
`episode` (scenario/seed/variant/id; a new one resets the policy). Without them (OpenVLA's client):
- the episode is `default_episode` (configs/serve_policy.yaml), and a new instruction starts a new one;
- the arm's state is the server's own account: the backend's home pose at the episode start, then each
  target it answered, taken as reached (the gripper width stays at its home value).
`GET /health` answers {"status": "ok", "policy": ..., "requests": n}.

The diagnosis server's limits, token and shutdown: loopback unless `host` says otherwise; with the variable
`token_env` names set (LABROBFAIL_POLICY_TOKEN), every request but /health needs `Authorization: Bearer <token>`
(the project's client sends it from `openvla.token_env`); a body over `max_body_mb` is 413 (checked before it is
read, and while it streams), one not complete `request_timeout_s` after its first read 408, more than
`max_connections` at once 503; Ctrl-C / SIGTERM finishes the request in flight, then exits 0.
Errors as OpenVLA's server (FastAPI) gives them, `{"detail": ...}`: a body that is not json-numpy (bad JSON, too
deep, an object array) is HTTP 400, one that is not a JSON object 422; a request the policy cannot answer is
HTTP 200 with the JSON string "error", and one line on stderr. Defaults: configs/serve_policy.yaml.
"""

import json
import sys
import threading
from typing import Any

import numpy as np

from labrobfail_vlm.config import ConfigError, cli_main, load_config
from sim_backends.policies import wire


def numbers(x: Any, n: int, name: str) -> np.ndarray:
    """`x` as n finite float64s: a real-valued array or a list of JSON numbers (bools and strings refused)."""
    if isinstance(x, np.ndarray) and x.dtype.kind in "fiu":
        a = x.astype(np.float64)
    elif isinstance(x, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in x):
        a = np.array([float(v) for v in x], np.float64)
    else:
        raise ValueError(f"{name} must be {n} numbers, got a {type(x).__name__}")
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be {n} finite numbers, got shape {a.shape}")
    return a


def check_image(x: Any, name: str) -> np.ndarray:
    if not (isinstance(x, np.ndarray) and x.dtype == np.uint8 and x.ndim == 3 and x.shape[2] == 3 and x.size):
        raise ValueError(f"{name} must be a uint8 HxWx3 array, got {getattr(x, 'shape', type(x).__name__)}")
    return x


def check_request(payload: dict[str, Any]) -> tuple[np.ndarray, str]:
    """OpenVLA's fields: the image, the instruction and an optional unnorm_key (project policies ignore it)."""
    if "image" not in payload or "instruction" not in payload:
        raise ValueError("the request needs `image` and `instruction`")
    if not isinstance(payload["instruction"], str):
        raise ValueError("instruction must be a string")
    if not isinstance(payload.get("unnorm_key"), (str, type(None))):
        raise ValueError("unnorm_key must be a string")
    return check_image(payload["image"], "image"), payload["instruction"]


def episode_key(payload: dict[str, Any], instruction: str) -> str:
    """Which episode a request belongs to. OpenVLA's client names none: a new instruction starts one."""
    ep = payload.get("episode")
    if ep is None:
        return "instruction:" + instruction
    if not isinstance(ep, dict):
        raise ValueError("episode must be a JSON object")
    return "episode:" + json.dumps(ep, sort_keys=True, default=str)


def proprio_state(p: Any) -> dict[str, Any]:
    v = numbers(p, 9, "proprio (ee_pos, ee_quat, width, grip_cmd)")
    return {"ee_pos": v[:3].tolist(), "ee_quat": v[3:7].tolist(), "width": float(v[7]), "grip_cmd": int(round(v[8]))}


def arm_state(state: dict[str, Any]) -> dict[str, Any]:
    """The part of a backend state sample that a client's proprio carries."""
    return {
        "ee_pos": list(state["ee_pos"]),
        "ee_quat": list(state["ee_quat"]),
        "width": float(state["width"]),
        "grip_cmd": int(state["grip_cmd"]),
    }


class PolicyService:
    """One project policy answering OpenVLA requests; a new episode (see `episode_key`) resets it."""

    def __init__(self, cfg: Any):
        from omegaconf import OmegaConf

        from sim_backends.registry import backend_options
        from sim_backends.supervision.experiment import build_policy

        if cfg.policy == "openvla":
            raise ConfigError("policy: openvla is the client; serve a project policy (act, scripted)")
        self.cfg = cfg
        self.backend_kwargs = backend_options(
            cfg.backend, OmegaConf.to_container(cfg.backend_kwargs, resolve=True) or {}
        )
        self.src: Any = None
        self.default = self._default_episode(cfg.default_episode)
        self.policy = build_policy(cfg)
        self.key: str | None = None
        self.state: dict[str, Any] | None = None  # the server's account of the arm (clients without proprio)

    def _backend(self) -> Any:
        from sim_backends.registry import make_backend

        if self.src is None:
            self.src = make_backend(self.cfg.backend, render=False, **self.backend_kwargs)
        return self.src

    def _default_episode(self, d: Any) -> dict[str, Any]:
        from labrobfail_vlm.taxonomy import check_variant

        check_variant(d.variant, "default_episode.variant")
        if not isinstance(d.seed, int):
            raise ConfigError(f"default_episode.seed: must be an integer, got {d.seed!r}")
        if d.scenario is not None and str(d.scenario) not in self._backend().scenarios():
            raise ConfigError(
                f"default_episode.scenario: unknown scenario {d.scenario!r} of the {self.cfg.backend} backend"
            )
        return {"scenario": None if d.scenario is None else str(d.scenario), "seed": d.seed, "variant": d.variant}

    def _reset(self, episode: dict[str, Any] | None, instruction: str) -> None:
        """Start an episode: the request's `episode` fields over `default_episode`."""
        from sim_backends.policies.base import EpisodeContext
        from sim_backends.supervision.loop import TaskFamily, episode_context

        ep = {**self.default, **(episode or {})}
        scenario, seed, variant = ep["scenario"], int(ep["seed"]), str(ep["variant"])
        self.state = None
        if scenario is None:
            if self.cfg.policy == "scripted":
                raise ValueError("the scripted policy needs a scenario: send `episode` or set default_episode.scenario")
            ctx = EpisodeContext("", "", 0, "seen", instruction, [], {}, [], [])
        else:
            src = self._backend()
            src.reset(str(scenario), seed, variant)
            ctx = episode_context(src, TaskFamily("served", [str(scenario)]), str(scenario), seed, variant)
            src.begin()
            self.state = arm_state(src.observe().state)
        if self.policy.reset(ctx):
            print("note: physics injections of the served policy do not reach the client", file=sys.stderr)

    def _home(self) -> dict[str, Any]:
        """The backend's home pose (PyBullet: one for every scenario), for a client that sends no proprio."""
        src = self._backend()
        src.reset(src.scenarios()[0], 0, "seen")
        src.begin()
        return arm_state(src.observe().state)

    def answer(self, payload: dict[str, Any]) -> np.ndarray:
        from sim_backends.policies.openvla_client import target_to_action
        from sim_backends.source import Observation

        image, instruction = check_request(payload)
        key = episode_key(payload, instruction)
        if key != self.key:
            self.key = None  # a reset that fails leaves no half-started episode behind
            self._reset(payload.get("episode"), instruction)
            self.key = key
        if payload.get("proprio") is not None:
            state = proprio_state(payload["proprio"])
        else:
            state = self.state = self.state if self.state is not None else self._home()
        images = payload.get("images") or {"front": image}
        if not isinstance(images, dict):
            raise ValueError("images must be a JSON object of view name -> image")
        images = {str(k): check_image(v, f"images.{k}") for k, v in images.items()}
        act = self.policy.act(Observation(images, state, 0))
        if act is None:  # done: stand still (the client stops after a few idle actions)
            return np.array([0, 0, 0, 0, 0, 0, 0.0 if state["grip_cmd"] else 1.0], np.float32)
        # the server's account moves on to the target, taken as reached
        self.state = {**state, "ee_pos": list(act.pos), "ee_quat": list(act.quat), "grip_cmd": int(act.gripper)}
        return target_to_action(act, state)

    def close(self) -> None:
        if self.src is not None:
            self.src.close()
        self.policy.close()


def unwrap(payload: dict[str, Any], max_body: int) -> tuple[dict[str, Any], bool]:
    """The request and whether it came in the "encoded" form (a json-numpy document inside a JSON string)."""
    if "encoded" not in payload:
        return payload, False
    if len(payload) != 1 or not isinstance(payload["encoded"], str):
        raise ValueError("the encoded form carries only `encoded`, a string")
    inner = wire.loads(payload["encoded"], max_body)
    if not isinstance(inner, dict):
        raise ValueError("the encoded request must be a JSON object")
    return inner, True


def log_error(what: str, e: BaseException) -> None:
    print(f"error: {what}: {type(e).__name__}: {wire.one_line(e)}", file=sys.stderr, flush=True)


def create_app(service: PolicyService, max_body: int, token: str | None = None, body_timeout_s: float = 30.0) -> Any:
    """The ASGI app: POST /act and GET /health behind the diagnosis server's Guard (token, size, body deadline).
    FastAPI (the `serve` extra) is imported here: the module's annotations are evaluated, not postponed, so the
    routes' `Request` is this function's."""
    from fastapi import FastAPI, Request
    from fastapi.responses import JSONResponse, Response
    from starlette.concurrency import run_in_threadpool
    from starlette.requests import ClientDisconnect

    from labrobfail_vlm.serve.app import BodyTimeout, BodyTooLarge, Guard

    lock = threading.Lock()  # one policy and one backend: requests are answered one at a time
    served = {"requests": 0}

    def answer(payload: dict[str, Any]) -> str:
        try:  # OpenVLA's predict_action: any failure is HTTP 200 and the string "error"
            payload, encoded = unwrap(payload, max_body)
            with lock:
                action = service.answer(payload)
                served["requests"] += 1
            return json.dumps(wire.dumps(action)) if encoded else wire.dumps(action)
        except Exception as e:  # noqa: BLE001 - the protocol answers every failure the same way
            log_error("request failed", e)
            return json.dumps("error")

    app = FastAPI(title="LabRobFail policy server", docs_url=None, redoc_url=None, openapi_url=None)

    @app.exception_handler(BodyTooLarge)
    async def too_large(_: Request, __: BodyTooLarge) -> JSONResponse:
        return JSONResponse({"detail": f"request over {max_body} bytes"}, status_code=413)

    @app.exception_handler(BodyTimeout)
    async def too_slow(_: Request, __: BodyTimeout) -> JSONResponse:
        detail = f"request body not received within {body_timeout_s:g} s"
        return JSONResponse({"detail": detail}, status_code=408, headers={"connection": "close"})

    @app.exception_handler(ClientDisconnect)
    async def gone(_: Request, __: ClientDisconnect) -> Response:
        return Response(status_code=400)  # nobody reads it

    @app.get("/health")
    async def health() -> dict[str, Any]:
        return {"status": "ok", "policy": str(service.cfg.policy), "requests": served["requests"]}

    @app.post("/act")
    async def act(request: Request) -> Response:
        try:  # FastAPI's layer in OpenVLA's server: the body must be a JSON object
            payload = wire.loads(await request.body(), max_body)
        except wire.WireError as e:
            return JSONResponse({"detail": f"request body is not json-numpy: {e}"}, status_code=400)
        if not isinstance(payload, dict):
            return JSONResponse({"detail": "the request must be a JSON object"}, status_code=422)
        return Response(await run_in_threadpool(answer, payload), media_type="application/json")

    return Guard(app, token, max_body, body_timeout_s, error_key="detail")


def check_config(cfg: Any) -> None:
    if not isinstance(cfg.max_body_mb, int) or isinstance(cfg.max_body_mb, bool) or cfg.max_body_mb < 1:
        raise ConfigError(f"max_body_mb: must be a positive integer, got {cfg.max_body_mb!r}")
    if not isinstance(cfg.request_timeout_s, (int, float)) or not cfg.request_timeout_s > 0:
        raise ConfigError(f"request_timeout_s: must be a positive number, got {cfg.request_timeout_s!r}")
    if not isinstance(cfg.max_connections, int) or cfg.max_connections < 1:
        raise ConfigError(f"max_connections: must be a positive integer, got {cfg.max_connections!r}")
    if not isinstance(cfg.port, int) or not 0 <= cfg.port <= 65535:
        raise ConfigError(f"port: expected 0-65535, got {cfg.port!r}")
    if str(cfg.log_level) not in ("critical", "error", "warning", "info", "debug"):
        raise ConfigError(f"log_level: expected critical, error, warning, info or debug, got {cfg.log_level!r}")


def main(argv: list[str]) -> int:
    from labrobfail_vlm.serve.http import bearer_token, listen, serve

    cfg = load_config("serve_policy.yaml", argv)
    check_config(cfg)
    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError:
        raise ConfigError(
            "labrobfail-serve-policy needs FastAPI and uvicorn: pip install 'labrobfail[serve]'"
        ) from None
    token = bearer_token(str(cfg.token_env), str(cfg.host))
    sock = listen(str(cfg.host), int(cfg.port))  # before the policy loads: a taken port fails fast
    service = PolicyService(cfg)
    try:
        app = create_app(service, int(cfg.max_body_mb) << 20, token, float(cfg.request_timeout_s))
        host, port = sock.getsockname()[:2]
        print(f"serving {cfg.policy} on http://{host}:{port}/act", flush=True)  # clients read the URL off this line
        if token:
            print("token required", file=sys.stderr, flush=True)
        serve(app, sock, str(cfg.log_level), int(cfg.max_connections), float(cfg.request_timeout_s))
    finally:
        service.close()
    return 0


def cli() -> None:
    """The `labrobfail-serve-policy` console script."""
    cli_main(main, __doc__)
