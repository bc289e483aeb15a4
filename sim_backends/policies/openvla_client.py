"""OpenVLA through its REST deploy server: `POST /act` with the image and the instruction, a 7-D action back.

Request (json-numpy, the real `json_numpy` package behind sim_backends/policies/wire.py): `{"image": uint8 HxWx3,
"instruction": str, "unnorm_key"?}`, as OpenVLA's own client sends it, or the `{"encoded": "<json-numpy
string>"}` form (`encoded: true`; note that OpenVLA's deploy.py fails on it, see docs/GUIDE.md). The plain form also
carries the project's extras, which OpenVLA's server ignores and labrobfail-serve-policy uses: `images` (every
view), `proprio` (ee_pos, ee_quat, width, grip_cmd) and `episode` (scenario, seed, variant and a fresh id per
episode: a new episode resets the served policy).

Reply: a json-numpy 7-D action (delta position in metres, delta rotation as roll/pitch/yaw in radians, both
in the robot base frame, and the gripper in OpenVLA's convention, 1 = open, 0 = closed), or the JSON
string "error" (HTTP 200) when the server failed. Anything else is refused with `PolicyError` and one clear
line: "error", an HTTP error, a timeout, a refused or broken connection, a redirect, a reply over
`max_reply_bytes`, JSON that is malformed or nested too deeply, an object array, a reply that is not a
real-valued array of 7 numbers (bools, complex, strings and datetimes are refused, not converted), NaN or
inf, a step longer than `max_step_m` or a rotation over a full turn. The loop ends that trial (outcome
"policy_error") and the run goes on.

The action is mapped onto the backend's end-effector controller: the target is the current pose plus the
deltas; a changed gripper command gets time to settle. Three near-zero actions in a row mean the policy is
done (OpenVLA has no stop signal).
"""

from __future__ import annotations

import http.client
import math
import os
import socket
import time
import urllib.error
import urllib.request
import uuid
from typing import Any
from urllib.parse import urlparse

import numpy as np

from labrobfail_vlm.config import ConfigError, is_int
from labrobfail_vlm.llm_client import OPENER  # OpenVLA's server never redirects: a 3xx is refused
from sim_backends.perturbations.control import so3_exp
from sim_backends.policies import wire
from sim_backends.policies.base import Action, EpisodeContext, Policy, PolicyError, register_policy
from sim_backends.source import Observation
from sim_backends.types import matrix_to_quat, quat_to_matrix

PROPRIO = ("ee_pos", "ee_quat", "width", "grip_cmd")
IDLE_POS, IDLE_ROT = 1e-3, 1e-3
MAX_REPLY_BYTES = 1 << 20  # a 7-D action is ~100 bytes; more is a broken or hostile server
MAX_TURN = 2 * math.pi  # rad per axis in one step: beyond a full turn a delta is garbage (and 1e154 breaks sin())


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
    if not isinstance(url, str):
        raise ConfigError(f"{key}: not an http URL: {url!r}")
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

    def __init__(
        self,
        url: str = "http://127.0.0.1:8777/act",
        timeout_s: float = 10.0,
        unnorm_key: str | None = None,
        view: str = "front",
        encoded: bool = False,
        idle_stop: int = 3,
        max_step_m: float = 1.0,
        max_reply_bytes: int = MAX_REPLY_BYTES,
        check: bool = True,
        token_env: str | None = "LABROBFAIL_POLICY_TOKEN",
    ):
        check_options(
            {
                "timeout_s": timeout_s,
                "idle_stop": idle_stop,
                "max_step_m": max_step_m,
                "encoded": encoded,
                "max_reply_bytes": max_reply_bytes,
                "view": view,
                "unnorm_key": unnorm_key,
                "token_env": token_env,
            }
        )
        if check:
            check_reachable(url)
        self.url, self.timeout, self.unnorm_key, self.view = url, float(timeout_s), unnorm_key, view
        self.encoded, self.idle_stop, self.max_step = bool(encoded), int(idle_stop), float(max_step_m)
        self.max_reply = int(max_reply_bytes)
        # a bearer token for a server that asks for one (labrobfail-serve-policy with its token set); never logged
        token = os.environ.get(token_env, "") if token_env else ""
        self.headers = {"Content-Type": "application/json"} | ({"Authorization": f"Bearer {token}"} if token else {})
        self.ctx: EpisodeContext | None = None
        self.idle = 0

    def reset(self, ctx: EpisodeContext) -> list:
        self.ctx, self.idle = ctx, 0
        self.episode_token = uuid.uuid4().hex  # two trials of one scenario and seed are still two episodes
        return []

    def request(self, payload: dict[str, Any]) -> np.ndarray:
        """POST one request; the 7-D action, or PolicyError naming what went wrong."""
        body = wire.dumps({"encoded": wire.dumps(payload)} if self.encoded else payload).encode()
        return parse_reply(self._post(body), self.url, self.max_reply, self.max_step)

    def _post(self, body: bytes) -> bytes:
        """The reply body (at most max_reply + 1 bytes are read); PolicyError for any transport failure."""
        req = urllib.request.Request(self.url, body, self.headers)
        deadline = time.monotonic() + self.timeout
        try:
            with OPENER.open(req, timeout=self.timeout) as r:
                return self._read_capped(r, deadline)
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
            raise PolicyError(f"{self.url}: connection failed ({e.strerror or wire.one_line(e)})") from None
        except (http.client.HTTPException, ValueError) as e:  # a broken status line, headers or chunking
            raise PolicyError(f"{self.url} answered broken HTTP ({type(e).__name__}: {wire.one_line(e)})") from None

    def _read_capped(self, r: Any, deadline: float) -> bytes:
        """At most max_reply + 1 bytes of the body, by the deadline: the socket timeout alone bounds each read,
        so a server dripping a byte at a time could otherwise hold the trial for hours."""
        chunks: list[bytes] = []
        size = 0
        while size <= self.max_reply:
            chunk = r.read1(min(65536, self.max_reply + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
            if time.monotonic() > deadline:
                raise PolicyError(f"{self.url} gave no complete answer within {self.timeout:g} s")
        return b"".join(chunks)

    def act(self, obs: Observation) -> Action | None:
        if self.view not in obs.images:
            raise PolicyError(f"openvla.view: no camera view {self.view!r}; views: {', '.join(obs.images)}")
        payload: dict[str, Any] = {
            "image": np.ascontiguousarray(obs.images[self.view], np.uint8),
            "instruction": self.ctx.instruction if self.ctx else "",
        }
        if self.unnorm_key:
            payload["unnorm_key"] = self.unnorm_key
        if not self.encoded:  # the project's extras (OpenVLA's server only reads image/instruction/unnorm_key)
            payload.update(
                images={k: np.ascontiguousarray(v, np.uint8) for k, v in obs.images.items()},
                proprio=proprio_vector(obs.state),
            )
            if self.ctx is not None:
                payload["episode"] = {
                    "backend": self.ctx.backend,
                    "scenario": self.ctx.scenario,
                    "seed": self.ctx.seed,
                    "variant": self.ctx.variant,
                    "id": self.episode_token,
                }
        a = self.request(payload)
        target = action_to_target(a, obs.state)
        idle = (
            float(np.linalg.norm(a[:3])) < IDLE_POS
            and float(np.linalg.norm(a[3:6])) < IDLE_ROT
            and target.gripper == int(obs.state["grip_cmd"])
        )
        self.idle = self.idle + 1 if idle else 0
        return None if self.idle_stop and self.idle >= self.idle_stop else target


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def check_options(opts: dict[str, Any]) -> None:
    """One-line ConfigErrors for client settings (YAML values are untyped: `encoded=maybe` arrives as a string)."""
    checks = {
        "timeout_s": (lambda v: _is_number(v) and v > 0, "a positive number of seconds"),
        "idle_stop": (lambda v: is_int(v, 0), "an integer >= 0"),
        "max_step_m": (lambda v: _is_number(v) and v > 0, "a positive number of metres"),
        "max_reply_bytes": (lambda v: is_int(v, 2), "an integer >= 2"),
        "encoded": (lambda v: isinstance(v, bool), "true or false"),
        "view": (lambda v: isinstance(v, str) and v != "", "a camera view name"),
        "unnorm_key": (lambda v: v is None or isinstance(v, str), "null or a string"),
        "token_env": (lambda v: v is None or isinstance(v, str), "null or an environment variable's name"),
    }
    for key, (ok, what) in checks.items():
        if not ok(opts[key]):
            raise ConfigError(f"openvla.{key}: must be {what}, got {opts[key]!r}")


def parse_reply(body: bytes, url: str, max_bytes: int = MAX_REPLY_BYTES, max_step_m: float = 1.0) -> np.ndarray:
    """The 7-D action of a reply body; PolicyError for "error" or anything that is not one."""
    if len(body) > max_bytes:
        raise PolicyError(f"{url} answered more than {max_bytes} bytes (a 7-D action takes about 100)")
    try:
        out = wire.loads(body, max_bytes)
        if isinstance(out, str) and out != "error":  # the "encoded" form: a json-numpy document in a string
            out = wire.loads(out, max_bytes)
    except wire.WireError as e:
        raise PolicyError(f"{url} answered malformed JSON ({e})") from None
    if isinstance(out, str) and out == "error":
        raise PolicyError(f'{url} answered "error" (the server failed on this request; see its log)')
    a = as_action(out, url)
    with np.errstate(over="ignore"):  # finite components whose norm overflows: inf, refused
        step = float(np.linalg.norm(a[:3]))
    if step > max_step_m:  # finite but out of reach: an un-normalised or garbage action, not a step
        raise PolicyError(f"{url} answered a step of {step:.3g} m (over openvla.max_step_m={max_step_m:g})")
    turn = float(np.max(np.abs(a[3:6])))
    if turn > MAX_TURN:
        raise PolicyError(f"{url} answered a rotation of {turn:.3g} rad about one axis (over a full turn)")
    return a


def as_action(out: Any, url: str) -> np.ndarray:
    """A decoded reply as a finite float64 7-vector: an ndarray of a real number dtype or a list of JSON numbers.
    Other types are refused rather than converted (numpy would turn "1.5" or True into a number)."""
    if isinstance(out, np.ndarray):
        if out.dtype.kind not in "fiu":
            raise PolicyError(f"{url} answered an array of dtype {out.dtype.str!r}, not real numbers")
        with np.errstate(over="ignore"):  # a float128 beyond float64's range becomes inf, refused below
            a = out.astype(np.float64)
    elif isinstance(out, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in out):
        try:
            a = np.array([float(x) for x in out], np.float64)
        except OverflowError:  # a JSON integer too large for a float
            raise PolicyError(f"{url} answered a number too large for an action") from None
    else:
        raise PolicyError(f"{url} answered a {type(out).__name__}, not a 7-D action")
    if a.shape != (7,):
        raise PolicyError(f"{url} answered shape {a.shape}, not a 7-D action")
    if not np.all(np.isfinite(a)):
        raise PolicyError(f"{url} answered a 7-D action with NaN or inf")
    return a
