"""OpenVLA through its REST deploy server: `POST /act` with the image and the instruction, a 7-D action back.

Request (json-numpy, policies/json_numpy.py): `{"image": uint8 HxWx3, "instruction": str, "unnorm_key"?}` or
the `{"encoded": "<json-numpy string>"}` form (`encoded: true`). The plain form also carries the project's
extras, which OpenVLA's server ignores and scripts/serve_policy.py uses: `images` (every view), `proprio`
(ee_pos, ee_quat, width, grip_cmd) and `episode` (scenario, seed, variant and a fresh id per episode: a new
episode resets the served policy).

Reply: a json-numpy 7-D action (delta position in metres, delta rotation as roll/pitch/yaw in radians, both
in the robot base frame, and the gripper in OpenVLA's convention, 1 = open, 0 = closed), or the JSON
string "error" (HTTP 200) when the server failed. A bad answer, an "error", a timeout or a refused
connection raise `PolicyError` with one clear line: the loop ends that trial and the run goes on.

The action is mapped onto the backend's end-effector controller: the target is the current pose plus the
deltas; a changed gripper command gets time to settle. Three near-zero actions in a row mean the policy is
done (OpenVLA has no stop signal).
"""

from __future__ import annotations

import json
import math
import socket
import urllib.error
import urllib.request
import uuid
from typing import Any
from urllib.parse import urlparse

import numpy as np

from labrobfail_vlm.config import ConfigError
from policies import json_numpy
from policies.base import Action, EpisodeContext, Policy, PolicyError, register_policy
from sim_backends.perturbations.control import so3_exp
from sim_backends.source import Observation
from sim_backends.types import matrix_to_quat, quat_to_matrix

PROPRIO = ("ee_pos", "ee_quat", "width", "grip_cmd")
IDLE_POS, IDLE_ROT = 1e-3, 1e-3


def proprio_vector(state: dict[str, Any]) -> np.ndarray:
    """ee_pos (3), ee_quat (4), width, grip_cmd: what a controller reports about the arm (float32, 9)."""
    return np.array([*state["ee_pos"], *state["ee_quat"], state["width"], state["grip_cmd"]], np.float32)


def rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    """Rotation of extrinsic roll-pitch-yaw (about base x, then y, then z)."""
    return so3_exp(np.array([0, 0, rpy[2]])) @ so3_exp(np.array([0, rpy[1], 0])) @ so3_exp(np.array([rpy[0], 0, 0]))


def matrix_rpy(r: np.ndarray) -> np.ndarray:
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    return np.array([math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])])


def action_to_target(a: np.ndarray, state: dict[str, Any]) -> Action:
    """7-D delta action -> absolute end-effector target from the current state."""
    pos = np.asarray(state["ee_pos"], float) + a[:3]
    rot = rpy_matrix(a[3:6]) @ quat_to_matrix(tuple(state["ee_quat"]))
    grip = 0 if a[6] >= 0.5 else 1
    settle = 0 if grip == int(state["grip_cmd"]) else (50 if grip else 40)
    return Action(tuple(map(float, pos)), matrix_to_quat(rot), grip, 0.3, settle)


def target_to_action(t: Action, state: dict[str, Any]) -> np.ndarray:
    """Absolute target -> 7-D delta action relative to `state` (the inverse of `action_to_target`)."""
    d = np.asarray(t.pos, float) - np.asarray(state["ee_pos"], float)
    r = quat_to_matrix(tuple(t.quat)) @ quat_to_matrix(tuple(state["ee_quat"])).T
    return np.array([*d, *matrix_rpy(r), 0.0 if t.gripper else 1.0], np.float32)


def check_reachable(url: str, key: str = "openvla.url", timeout: float = 2.0) -> None:
    u = urlparse(url)
    if u.scheme not in ("http", "https") or not u.hostname:
        raise ConfigError(f"{key}: not an http URL: {url!r}")
    try:
        socket.create_connection((u.hostname, u.port or (443 if u.scheme == "https" else 80)), timeout).close()
    except OSError as e:
        raise ConfigError(f"{key}: cannot reach {url} ({e.strerror or e})") from None


@register_policy("openvla")
class OpenVLAClient(Policy):
    name = "openvla"

    def __init__(self, url: str = "http://127.0.0.1:8777/act", timeout_s: float = 10.0, unnorm_key: str | None = None,
                 view: str = "front", encoded: bool = False, idle_stop: int = 3, check: bool = True):
        if check:
            check_reachable(url)
        self.url, self.timeout, self.unnorm_key, self.view = url, float(timeout_s), unnorm_key, view
        self.encoded, self.idle_stop = bool(encoded), int(idle_stop)
        self.ctx: EpisodeContext | None = None
        self.idle = 0

    def reset(self, ctx: EpisodeContext) -> list:
        self.ctx, self.idle = ctx, 0
        self.episode_token = uuid.uuid4().hex  # two trials of one scenario and seed are still two episodes
        return []

    def request(self, payload: dict[str, Any]) -> np.ndarray:
        """POST one request; the 7-D action, or PolicyError naming what went wrong."""
        body = json_numpy.dumps({"encoded": json_numpy.dumps(payload)} if self.encoded else payload).encode()
        req = urllib.request.Request(self.url, body, {"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                text = r.read()
        except urllib.error.HTTPError as e:
            raise PolicyError(f"{self.url} answered HTTP {e.code}") from None
        except urllib.error.URLError as e:
            reason = e.reason
            if isinstance(reason, (socket.timeout, TimeoutError)):
                raise PolicyError(f"{self.url} gave no answer within {self.timeout:g} s") from None
            raise PolicyError(f"cannot reach {self.url} ({getattr(reason, 'strerror', None) or reason})") from None
        except (socket.timeout, TimeoutError):
            raise PolicyError(f"{self.url} gave no answer within {self.timeout:g} s") from None
        except OSError as e:
            raise PolicyError(f"{self.url}: connection failed ({e.strerror or e})") from None
        return parse_reply(text, self.url)

    def act(self, obs: Observation) -> Action | None:
        if self.view not in obs.images:
            raise PolicyError(f"openvla.view: no camera view {self.view!r}; views: {', '.join(obs.images)}")
        payload: dict[str, Any] = {"image": np.ascontiguousarray(obs.images[self.view], np.uint8),
                                   "instruction": self.ctx.instruction if self.ctx else ""}
        if self.unnorm_key:
            payload["unnorm_key"] = self.unnorm_key
        if not self.encoded:  # the project's extras (OpenVLA's server only reads image/instruction/unnorm_key)
            payload.update(images={k: np.ascontiguousarray(v, np.uint8) for k, v in obs.images.items()},
                           proprio=proprio_vector(obs.state))
            if self.ctx is not None:
                payload["episode"] = {"backend": self.ctx.backend, "scenario": self.ctx.scenario,
                                      "seed": self.ctx.seed, "variant": self.ctx.variant, "id": self.episode_token}
        a = self.request(payload)
        target = action_to_target(a, obs.state)
        idle = float(np.linalg.norm(a[:3])) < IDLE_POS and float(np.linalg.norm(a[3:6])) < IDLE_ROT \
            and target.gripper == int(obs.state["grip_cmd"])
        self.idle = self.idle + 1 if idle else 0
        return None if self.idle_stop and self.idle >= self.idle_stop else target


def parse_reply(text: bytes, url: str) -> np.ndarray:
    """The 7-D action of a reply body; PolicyError for "error" or anything that is not one."""
    try:
        out = json_numpy.loads(text)
        if isinstance(out, str) and out != "error":  # the "encoded" form: a json-numpy document in a string
            out = json_numpy.loads(out)
    except (ValueError, TypeError, KeyError) as e:
        raise PolicyError(f"{url} answered malformed JSON ({str(e).splitlines()[0][:80]})") from None
    if isinstance(out, str) and out == "error":
        raise PolicyError(f'{url} answered "error" (the server failed on this request; see its log)')
    try:
        a = np.asarray(out, dtype=np.float64)
    except (ValueError, TypeError):
        a = np.zeros(0)
    if a.shape != (7,) or not np.all(np.isfinite(a)):
        raise PolicyError(f"{url} answered a {type(out).__name__} of shape {a.shape}, not a 7-D finite action")
    return a
