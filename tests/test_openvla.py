"""The OpenVLA REST client and server against real loopback peers, on the real json-numpy package: the project's
client against labrobfail-serve-policy and against a FastAPI stand-in of OpenVLA's deploy server; a client
written as OpenVLA's README writes one against labrobfail-serve-policy; faulty servers."""

import contextlib
import json
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, HTTPServer

import json_numpy
import numpy as np
import pytest
import requests
from conftest import free_port, scripted_server, supervise_front

from labrobfail_vlm.config import ConfigError
from sim_backends.policies import wire
from sim_backends.policies.base import PolicyError
from sim_backends.policies.openvla_client import (
    OpenVLAClient,
    action_to_target,
    check_reachable,
    proprio_vector,
    rpy_matrix,
    target_to_action,
)
from sim_backends.registry import make_backend
from sim_backends.supervision.loop import TaskFamily, episode_context
from sim_backends.types import matrix_to_quat, quat_to_matrix, rotation_angle


@pytest.fixture(scope="module")
def served():
    """labrobfail-serve-policy serving the scripted policy on a free loopback port."""
    yield from scripted_server()


@pytest.fixture(scope="module")
def served_default():
    """labrobfail-serve-policy serving the scripted plan of a default episode: what OpenVLA's own client needs
    (it sends no `episode` and no `proprio`)."""
    for url, _ in scripted_server(f"default_episode.scenario={SCENARIO}"):
        yield url


# A stand-in of OpenVLA's vla-scripts/deploy.py: its FastAPI route, json_numpy.patch(), request handling and replies,
# with a fixed function of the request in place of the 7B model. (deploy.py's encoded branch asserts
# `len(payload.keys() == 1)`, which always raises; the stand-in keeps the intended `len(payload.keys()) == 1`.)
STAND_IN = """
import json_numpy
json_numpy.patch()
import json
import sys
from typing import Any, Dict

import numpy as np
import uvicorn
from fastapi import FastAPI
from fastapi.responses import JSONResponse
from PIL import Image


def predict_action(payload: Dict[str, Any]) -> str:
    try:
        if double_encode := "encoded" in payload:
            assert len(payload.keys()) == 1, "Only uses encoded payload!"
            payload = json.loads(payload["encoded"])
        image, instruction = payload["image"], payload["instruction"]
        unnorm_key = payload.get("unnorm_key", None)
        rgb = np.asarray(Image.fromarray(image).convert("RGB"), np.float64)
        action = np.array([rgb.mean() / 25500, len(instruction) / 10000, image.shape[0] / 1e5, image.shape[1] / 1e5,
                           0.01 if unnorm_key == "bridge_orig" else 0.0, -0.02, 1.0])
        return JSONResponse(json_numpy.dumps(action)) if double_encode else JSONResponse(action)
    except Exception:
        return "error"


app = FastAPI()
app.post("/act")(predict_action)
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), log_level="warning")
"""


def stand_in_action(image: np.ndarray, instruction: str, unnorm_key: str | None = None) -> np.ndarray:
    return np.array(
        [
            image.astype(np.float64).mean() / 25500,
            len(instruction) / 10000,
            image.shape[0] / 1e5,
            image.shape[1] / 1e5,
            0.01 if unnorm_key == "bridge_orig" else 0.0,
            -0.02,
            1.0,
        ]
    )


@pytest.fixture(scope="module")
def openvla_stand_in(tmp_path_factory):
    script = tmp_path_factory.mktemp("openvla") / "deploy_stand_in.py"
    script.write_text(STAND_IN)
    port = free_port()
    p = subprocess.Popen(
        [sys.executable, str(script), str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    url = f"http://127.0.0.1:{port}/act"
    deadline = time.monotonic() + 60
    while True:
        try:
            check_reachable(url, timeout=0.5)
            break
        except ConfigError:
            assert p.poll() is None and time.monotonic() < deadline, p.stderr.read() if p.poll() is not None else ""
            time.sleep(0.2)
    yield url
    p.terminate()
    p.wait(timeout=10)


@contextlib.contextmanager
def json_numpy_patched():
    """OpenVLA's client calls json_numpy.patch(), which replaces the json module's functions for the whole process:
    they are put back afterwards, so the tests after this one see the standard json."""
    saved = {k: getattr(json, k) for k in ("dumps", "loads", "dump", "load")}
    json_numpy.patch()
    try:
        yield
    finally:
        for k, v in saved.items():
            setattr(json, k, v)


SCENARIO = "pick_place_beaker_small"


@pytest.fixture(scope="module")
def episode():
    src = make_backend("pybullet", image_size=32, cameras=["front"])
    src.reset("pick_place_beaker_small", 0, "seen")
    ctx = episode_context(src, TaskFamily("t", ["pick_place_beaker_small"]), "pick_place_beaker_small", 0, "seen")
    src.begin()
    yield src, ctx
    src.close()


def fake_server(reply: bytes, delay: float = 0.0):
    class H(BaseHTTPRequestHandler):
        def log_message(self, *a):
            pass

        def do_POST(self):
            self.rfile.read(int(self.headers.get("Content-Length") or 0))
            time.sleep(delay)
            try:
                self.send_response(200)
                self.send_header("Content-Length", str(len(reply)))
                self.end_headers()
                self.wfile.write(reply)
            except OSError:  # the client gave up
                pass

    srv = HTTPServer(("127.0.0.1", 0), H)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv, f"http://127.0.0.1:{srv.server_address[1]}/act"


def test_json_numpy_round_trip_and_refusals():
    """The real json-numpy package behind the project's guard: arrays round-trip, object arrays, deep JSON and
    oversized payloads are one-line WireErrors."""
    for a in (
        np.arange(6, dtype=np.uint8).reshape(1, 2, 3),
        np.linspace(0, 1, 7).astype(np.float32),
        np.array(3.5),
        np.arange(12, dtype=">i4").reshape(3, 4)[:, ::2],
    ):
        text = wire.dumps({"x": a})
        assert text == json_numpy.dumps({"x": a})  # the package's own encoding, byte for byte
        b = wire.loads(text, 1 << 20)["x"]
        assert np.array_equal(a, b) and np.asarray(b).dtype == a.dtype
    for bad, msg in [
        ('{"__numpy__": "AAAA", "dtype": "|O", "shape": [3]}', "object arrays are refused"),
        ('{"__numpy__": "AAAA", "dtype": [["a", "|O"]], "shape": [1]}', "object arrays are refused"),
        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
        ('{"__numpy__": "AAAA", "dtype": "<f8", "shape": [3]}', "buffer size"),
        ('{"__numpy__": "AAAA", "dtype": "nonsense", "shape": [3]}', "bad array dtype"),
        ("x" * 101, "over the limit of 100"),
    ]:
        with pytest.raises(wire.WireError, match=msg) as e:
            wire.loads(bad, 100 if bad.startswith("x") else 1 << 20)
        assert "\n" not in str(e.value)


def test_seven_d_action_maps_onto_the_end_effector_and_back():
    state = {"ee_pos": [0.4, 0.0, 0.2], "ee_quat": [0.0, 0.7071068, 0.0, 0.7071068], "width": 0.08, "grip_cmd": 0}
    a = np.array([0.02, -0.01, 0.03, 0.1, -0.2, 0.3, 0.0])  # gripper 0 = close (OpenVLA: 1 = open)
    t = action_to_target(a, state)
    assert np.allclose(t.pos, [0.42, -0.01, 0.23]) and t.gripper == 1 and t.settle > 0
    assert np.allclose(target_to_action(t, state), a, atol=1e-5)
    assert rotation_angle(t.quat, tuple(state["ee_quat"])) == pytest.approx(np.linalg.norm([0.1, 0.2, 0.3]), abs=0.05)


def test_good_answer_from_the_served_policy(served, episode):
    url, _ = served
    src, ctx = episode
    client = OpenVLAClient(url)
    client.reset(ctx)
    act = client.act(src.observe())
    first = ctx.nominal[0]
    assert np.allclose(act.pos, first.pos, atol=1e-4) and rotation_angle(act.quat, first.quat) < 1e-3
    assert act.gripper == first.gripper
    # the "encoded" request form gets an encoded answer
    obs = src.observe()
    payload = {
        "image": obs.images["front"],
        "instruction": ctx.instruction,
        "proprio": proprio_vector(obs.state),
        "episode": {"scenario": ctx.scenario, "seed": 1, "variant": "seen"},
    }
    a = OpenVLAClient(url, encoded=True).request(payload)
    assert a.shape == (7,) and np.all(np.isfinite(a))


def test_error_answer_is_a_policy_error_and_the_server_keeps_serving(served, episode):
    url, proc = served
    src, ctx = episode
    client = OpenVLAClient(url)
    with pytest.raises(PolicyError, match='answered "error"'):
        client.request({"image": np.zeros((4, 4), np.float32), "instruction": "x"})  # not a uint8 HxWx3 image
    client.reset(ctx)
    assert client.act(src.observe()) is not None  # the next request is served


def test_malformed_json_is_a_policy_error():
    srv, url = fake_server(b'{"__numpy__": "not base64!!", "dtype"')
    with pytest.raises(PolicyError, match="malformed JSON"):
        OpenVLAClient(url).request({"image": np.zeros((2, 2, 3), np.uint8), "instruction": "x"})
    srv.shutdown()
    srv, url = fake_server(json.dumps([1, 2, 3]).encode())
    with pytest.raises(PolicyError, match=r"shape \(3,\), not a 7-D action"):
        OpenVLAClient(url).request({"image": np.zeros((2, 2, 3), np.uint8), "instruction": "x"})
    srv.shutdown()


def test_timeout_is_a_policy_error():
    srv, url = fake_server(b"[]", delay=1.5)
    t = time.perf_counter()
    with pytest.raises(PolicyError, match="no answer within 0.3 s"):
        OpenVLAClient(url, timeout_s=0.3).request({"image": np.zeros((2, 2, 3), np.uint8), "instruction": "x"})
    assert time.perf_counter() - t < 1.4
    srv.shutdown()


def test_refused_connection():
    url = f"http://127.0.0.1:{free_port()}/act"
    with pytest.raises(ConfigError, match="openvla.url: cannot reach"):
        check_reachable(url)
    with pytest.raises(PolicyError, match="cannot reach"):
        OpenVLAClient(url, check=False).request({"image": np.zeros((2, 2, 3), np.uint8), "instruction": "x"})


def test_supervised_run_through_the_served_policy(served, tmp_path):
    url, _ = served
    out = tmp_path / "ov"
    r = supervise_front(out, ["policy=openvla", f"openvla.url={url}"], "open_oven_center", 1, 48)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "results.json").read_text())["tasks"]["open_oven_center"]
    assert res["none"]["success"] == 1 and res["oracle"]["success"] == 1  # the served nominal plan opens it


def test_a_failing_server_ends_trials_not_the_run(tmp_path):
    srv, url = fake_server(b"<html>oops</html>")
    out = tmp_path / "bad"
    r = supervise_front(out, ["policy=openvla", f"openvla.url={url}", "supervisor=none"], "pick_place_bottle", 2, 32)
    srv.shutdown()
    assert r.returncode == 0, r.stderr
    eps = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines() if '"episode"' in x]
    assert len(eps) == 2 and all(
        e["stopped"].startswith("policy error:") and "malformed JSON" in e["stopped"] for e in eps
    )
    assert all(e["outcome"] == "policy_error" and "malformed JSON" in e["error"] for e in eps)


def test_openvla_readme_client_against_the_served_policy(served_default):
    """OpenVLA's README client, as written there (requests + json_numpy.patch(), only `image` and `instruction`),
    drives our server through the default episode's plan: its deltas, summed from the home pose, walk the plan."""
    url = served_default
    src = make_backend("pybullet", render=False)
    try:
        src.reset(SCENARIO, 0, "seen")
        plan = episode_context(src, TaskFamily("t", [SCENARIO]), SCENARIO, 0, "seen").nominal
        src.begin()
        home = src.observe().state
    finally:
        src.close()
    image = np.zeros((256, 256, 3), dtype=np.uint8)
    with json_numpy_patched():
        actions = [
            requests.post(url, json={"image": image, "instruction": "pick up the beaker"}).json()
            for _ in range(len(plan) + 1)
        ]
        # the encoded form; a new instruction starts a new episode
        reply = requests.post(url, json={"encoded": json.dumps({"image": image, "instruction": "again"})}).json()
        encoded = json.loads(reply)
    assert all(isinstance(a, np.ndarray) and a.shape == (7,) and a.dtype == np.float32 for a in actions)
    pos, rot = np.asarray(home["ee_pos"], float), quat_to_matrix(tuple(home["ee_quat"]))
    for a, kf in zip(actions, plan):
        pos, rot = pos + a[:3], rpy_matrix(a[3:6]) @ rot
        assert np.allclose(pos, kf.pos, atol=1e-4) and rotation_angle(matrix_to_quat(rot), kf.quat) < 1e-3
        assert (a[6] < 0.5) == bool(kf.gripper)  # OpenVLA's gripper: 1 = open
    assert np.allclose(actions[-1][:6], 0)  # the plan is done: stand still
    assert isinstance(encoded, np.ndarray) and np.allclose(encoded, actions[0], atol=1e-6)


def test_project_client_against_a_stand_in_of_openvlas_deploy_server(openvla_stand_in, episode):
    """The project's client in both request forms against OpenVLA's deploy-server contract (FastAPI, json-numpy)."""
    url = openvla_stand_in
    src, ctx = episode
    obs = src.observe()
    image = obs.images["front"]
    for kwargs in (
        {},
        {"encoded": True},
        {"unnorm_key": "bridge_orig"},
        {"encoded": True, "unnorm_key": "bridge_orig"},
    ):
        client = OpenVLAClient(url, **kwargs)
        client.reset(ctx)
        a = stand_in_action(image, ctx.instruction, kwargs.get("unnorm_key"))
        t = client.act(obs)
        expected = action_to_target(a, obs.state)
        assert np.allclose(t.pos, expected.pos, atol=1e-9) and rotation_angle(t.quat, expected.quat) < 1e-6, kwargs
        assert t.gripper == 0  # 1.0 = open
    with pytest.raises(PolicyError, match='answered "error"'):  # a request its model cannot take
        OpenVLAClient(url).request({"image": np.zeros((4, 4, 3), np.int64), "instruction": "x"})
    with pytest.raises(PolicyError, match="answered HTTP 422"):  # FastAPI's answer to a body that is not an object
        OpenVLAClient(url).request([1, 2, 3])  # type: ignore[arg-type]
