"""Serve a project policy (ACT, scripted) behind OpenVLA's REST protocol, on loopback.

Run as:
    python scripts/serve_policy.py policy=act act.checkpoint=outputs/act/pick/final port=8777
    python scripts/serve_policy.py policy=scripted port=0          # prints the port it got

`POST /act` takes OpenVLA's request (json-numpy `image`, `instruction`, optional `unnorm_key`, or the
`{"encoded": ...}` form) plus the project's extras the client sends (`images`: every view, `proprio`:
ee_pos, ee_quat, width, grip_cmd, `episode`: scenario/seed/variant), and answers a json-numpy 7-D action
(delta position, delta roll/pitch/yaw in the base frame, gripper 1 = open) as OpenVLA does; on any failure it
answers HTTP 200 with the JSON string "error" and logs one line, as OpenVLA's server does. A new `episode`
resets the policy. Defaults: configs/serve_policy.yaml.
"""

from __future__ import annotations

import json
import sys
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from labrobfail_vlm.config import ConfigError, cli_main, load_config  # noqa: E402


class PolicyService:
    """One project policy answering OpenVLA requests; a new `episode` in a request resets it."""

    def __init__(self, cfg: Any):
        from omegaconf import OmegaConf

        from sim_backends.registry import backend_options
        from supervision.experiment import build_policy

        if cfg.policy == "openvla":
            raise ConfigError("policy: openvla is the client; serve a project policy (act, scripted)")
        self.cfg = cfg
        self.policy = build_policy(cfg)
        self.episode: Any = None
        self.src: Any = None
        self.backend_kwargs = backend_options(cfg.backend,
                                              OmegaConf.to_container(cfg.backend_kwargs, resolve=True) or {})

    def _reset(self, episode: Any, instruction: str) -> None:
        from policies.base import EpisodeContext
        from sim_backends.registry import make_backend
        from supervision.loop import TaskFamily, episode_context

        if isinstance(episode, dict) and "scenario" in episode:
            if self.src is None:
                self.src = make_backend(self.cfg.backend, render=False, **self.backend_kwargs)
            self.src.reset(str(episode["scenario"]), int(episode.get("seed", 0)), str(episode.get("variant", "seen")))
            ctx = episode_context(self.src, TaskFamily("served", [episode["scenario"]]), str(episode["scenario"]),
                                  int(episode.get("seed", 0)), str(episode.get("variant", "seen")))
        elif self.cfg.policy == "scripted":
            raise ValueError("the scripted policy needs the request's `episode` (scenario, seed, variant)")
        else:
            ctx = EpisodeContext("", "", 0, "seen", instruction, [], {}, [], [])
        if self.policy.reset(ctx):
            print("note: physics injections of the served policy do not reach the client", file=sys.stderr)
        self.episode = episode

    def answer(self, payload: dict[str, Any]) -> np.ndarray:
        from policies.openvla_client import target_to_action
        from sim_backends.source import Observation

        image, instruction = payload["image"], payload["instruction"]
        if not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3):
            raise ValueError(f"image must be a uint8 HxWx3 array, got {getattr(image, 'shape', type(image).__name__)}")
        if not isinstance(instruction, str):
            raise ValueError("instruction must be a string")
        p = np.asarray(payload.get("proprio", []), float)
        if p.shape != (9,):
            raise ValueError("a project policy needs `proprio` (ee_pos, ee_quat, width, grip_cmd)")
        episode = payload.get("episode")
        if self.episode is None or episode != self.episode:
            self._reset(episode, instruction)
        state = {"ee_pos": p[:3].tolist(), "ee_quat": p[3:7].tolist(), "width": float(p[7]), "grip_cmd": int(round(p[8]))}
        images = payload.get("images") or {"front": image}
        act = self.policy.act(Observation(dict(images), state, 0))
        if act is None:  # done: stand still (the client stops after a few idle actions)
            return np.array([0, 0, 0, 0, 0, 0, 0.0 if state["grip_cmd"] else 1.0], np.float32)
        return target_to_action(act, state)

    def close(self) -> None:
        if self.src is not None:
            self.src.close()
        self.policy.close()


def handler(service: PolicyService, max_body: int) -> type[BaseHTTPRequestHandler]:
    from policies import json_numpy

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, fmt: str, *args: Any) -> None:  # one line per failure, not per request
            pass

        def _send(self, code: int, body: str) -> None:
            data = body.encode()
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def do_POST(self) -> None:  # noqa: N802 - http.server's name
            if self.path.rstrip("/") != "/act":
                self._send(404, json.dumps({"detail": "Not Found"}))
                return
            n = int(self.headers.get("Content-Length") or 0)
            if n > max_body:
                self._send(413, json.dumps({"detail": f"request over {max_body} bytes"}))
                return
            try:
                payload = json_numpy.loads(self.rfile.read(n))
                encoded = isinstance(payload, dict) and "encoded" in payload
                if encoded:
                    if len(payload) != 1:
                        raise ValueError("the encoded form carries only `encoded`")
                    payload = json_numpy.loads(payload["encoded"])
                if not isinstance(payload, dict):
                    raise ValueError("the request must be a JSON object")
                action = service.answer(payload)
                self._send(200, json.dumps(json_numpy.dumps(action)) if encoded else json_numpy.dumps(action))
            except Exception as e:  # OpenVLA's protocol: HTTP 200 and the string "error"
                print(f"error: request failed: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}",
                      file=sys.stderr, flush=True)
                self._send(200, json.dumps("error"))

    return Handler


def main(argv: list[str]) -> int:
    cfg = load_config("serve_policy.yaml", argv)
    service = PolicyService(cfg)
    try:
        server = HTTPServer((str(cfg.host), int(cfg.port)), handler(service, int(cfg.max_body_mb) << 20))
    except OSError as e:
        raise ConfigError(f"port: cannot listen on {cfg.host}:{cfg.port} ({e.strerror})") from None
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
    cli_main(main)
