"""Serve a project policy (ACT, scripted) behind OpenVLA's REST protocol, on loopback: a drop-in peer of
OpenVLA's `vla-scripts/deploy.py`.

Run as:
    python scripts/serve_policy.py policy=act act.checkpoint=outputs/act/pick/final port=8777
    python scripts/serve_policy.py policy=scripted port=0          # prints the port it got
    python scripts/serve_policy.py policy=scripted default_episode.scenario=pick_place_beaker_small

`POST /act` takes OpenVLA's request exactly as OpenVLA's own client sends it (`requests.post(url, json={"image":
uint8 HxWx3, "instruction": str})` after `json_numpy.patch()`, optional `unnorm_key`, or the `{"encoded":
"<json-numpy string>"}` form) and answers a json-numpy 7-D action (delta position, delta roll/pitch/yaw in the
base frame, gripper 1 = open; a JSON string holding it for the encoded form), as OpenVLA does. The project's
client may add optional extras: `images` (every view), `proprio` (ee_pos, ee_quat, width, grip_cmd) and
`episode` (scenario/seed/variant/id; a new one resets the policy). Without them (OpenVLA's client):
- the episode is `default_episode` (configs/serve_policy.yaml), and a new instruction starts a new one;
- the arm's state is the server's own account: the backend's home pose at the episode start, then each
  target it answered, taken as reached (the gripper width stays at its home value).
Errors, as OpenVLA's server (FastAPI) gives them: a body that is not json-numpy (bad JSON, too deep, an object
array) is HTTP 400, one that is not a JSON object 422, one over `max_body_mb` 413; a request the policy cannot
answer is HTTP 200 with the JSON string "error", and one line on stderr. Defaults: configs/serve_policy.yaml.
"""

from __future__ import annotations

import json
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
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


def content_length(value: str | None, max_body: int) -> tuple[int, int | None, str]:
    """(length, None, "") for an acceptable Content-Length; else (0, HTTP status, reason)."""
    if value is None:
        return 0, 411, "Content-Length required"
    try:
        n = int(value)
    except ValueError:
        return 0, 400, "bad Content-Length"
    if n < 0:
        return 0, 400, "bad Content-Length"
    if n > max_body:
        return 0, 413, f"request over {max_body} bytes"
    return n, None, ""


def log_error(what: str, e: BaseException) -> None:
    print(f"error: {what}: {type(e).__name__}: {wire.one_line(e)}", file=sys.stderr, flush=True)


def handler(service: PolicyService, max_body: int, timeout_s: float) -> type[BaseHTTPRequestHandler]:
    lock = threading.Lock()  # one policy and one backend: requests are answered one at a time

    class Handler(BaseHTTPRequestHandler):
        timeout = timeout_s  # a client that stops sending mid-request frees its thread

        def log_message(self, fmt: str, *args: Any) -> None:  # one line per failure, not per request
            pass

        def _send(self, code: int, body: str) -> None:
            data = body.encode()
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def _read(self) -> bytes | None:
            """The request body, or None once an HTTP error has been sent."""
            n, code, reason = content_length(self.headers.get("Content-Length"), max_body)
            if code is not None:
                self._send(code, json.dumps({"detail": reason}))
                return None
            return self.rfile.read(n)

        def do_POST(self) -> None:  # noqa: N802 - http.server's name
            if self.path.split("?")[0].rstrip("/") != "/act":
                self._send(404, json.dumps({"detail": "Not Found"}))
                return
            body = self._read()
            if body is None:
                return
            try:  # FastAPI's layer in OpenVLA's server: the body must be a JSON object
                payload = wire.loads(body, max_body)
            except wire.WireError as e:
                self._send(400, json.dumps({"detail": f"request body is not json-numpy: {e}"}))
                return
            if not isinstance(payload, dict):
                self._send(422, json.dumps({"detail": "the request must be a JSON object"}))
                return
            try:  # OpenVLA's predict_action: any failure is HTTP 200 and the string "error"
                payload, encoded = unwrap(payload, max_body)
                with lock:
                    action = service.answer(payload)
                reply = json.dumps(wire.dumps(action)) if encoded else wire.dumps(action)
            except Exception as e:  # noqa: BLE001 - the protocol answers every failure the same way
                log_error("request failed", e)
                reply = json.dumps("error")
            self._send(200, reply)

    return Handler


class Server(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A connection that broke (timed out, reset) is one line on stderr, not a traceback."""
        e = sys.exc_info()[1]
        if e is not None:
            log_error(f"connection from {client_address[0]}", e)


def main(argv: list[str]) -> int:
    cfg = load_config("serve_policy.yaml", argv)
    if not isinstance(cfg.max_body_mb, int) or cfg.max_body_mb < 1:
        raise ConfigError(f"max_body_mb: must be a positive integer, got {cfg.max_body_mb!r}")
    if not isinstance(cfg.request_timeout_s, (int, float)) or not cfg.request_timeout_s > 0:
        raise ConfigError(f"request_timeout_s: must be a positive number, got {cfg.request_timeout_s!r}")
    service = PolicyService(cfg)
    try:
        server = Server(
            (str(cfg.host), int(cfg.port)), handler(service, int(cfg.max_body_mb) << 20, float(cfg.request_timeout_s))
        )
    except (OSError, OverflowError) as e:
        service.close()
        raise ConfigError(
            f"port: cannot listen on {cfg.host}:{cfg.port} ({getattr(e, 'strerror', None) or e})"
        ) from None
    host, port = server.server_address[:2]
    print(f"serving {cfg.policy} on http://{host}:{port}/act", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        service.close()
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
