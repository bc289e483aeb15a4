"""The OpenVLA REST client against real loopback servers: scripts/serve_policy.py and two faulty ones."""

import json
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, HTTPServer

import numpy as np
import pytest

from conftest import ROOT, free_port
from labrobfail_vlm.config import ConfigError
from policies import json_numpy
from policies.base import PolicyError
from policies.openvla_client import (OpenVLAClient, action_to_target, check_reachable, proprio_vector,
                                     target_to_action)
from sim_backends.registry import make_backend
from sim_backends.types import rotation_angle
from supervision.loop import TaskFamily, episode_context


@pytest.fixture(scope="module")
def served():
    """scripts/serve_policy.py serving the scripted policy on a free loopback port."""
    p = subprocess.Popen([sys.executable, "scripts/serve_policy.py", "policy=scripted", "port=0"], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = p.stdout.readline()
    assert line.startswith("serving scripted on http://127.0.0.1:"), line + p.stderr.read()
    yield line.split()[-1], p
    p.terminate()
    p.wait(timeout=10)


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
    for a in (np.arange(6, dtype=np.uint8).reshape(1, 2, 3), np.linspace(0, 1, 7).astype(np.float32),
              np.array(3.5)):
        b = json_numpy.loads(json_numpy.dumps({"x": a}))["x"]
        assert np.array_equal(a, b) and np.asarray(b).dtype == a.dtype
    with pytest.raises(ValueError):
        json_numpy.loads('{"__numpy__": "AAAA", "dtype": "|O", "shape": [3]}')


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
    payload = {"image": obs.images["front"], "instruction": ctx.instruction, "proprio": proprio_vector(obs.state),
               "episode": {"scenario": ctx.scenario, "seed": 1, "variant": "seen"}}
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
    with pytest.raises(PolicyError, match="not a 7-D finite action"):
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
    r = subprocess.run([sys.executable, "scripts/supervise.py", "policy=openvla", f"openvla.url={url}",
                        "task=open_oven_center", "trials=1", "image_size=48", "cameras=[front]", "progress=false",
                        f"out_dir={out}"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "results.json").read_text())["tasks"]["open_oven_center"]
    assert res["none"]["success"] == 1 and res["oracle"]["success"] == 1  # the served nominal plan opens it


def test_a_failing_server_ends_trials_not_the_run(tmp_path):
    srv, url = fake_server(b"<html>oops</html>")
    out = tmp_path / "bad"
    r = subprocess.run([sys.executable, "scripts/supervise.py", "policy=openvla", f"openvla.url={url}",
                        "supervisor=none", "task=pick_place_bottle", "trials=2", "image_size=32", "cameras=[front]",
                        "progress=false", f"out_dir={out}"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    srv.shutdown()
    assert r.returncode == 0, r.stderr
    eps = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines() if '"episode"' in x]
    assert len(eps) == 2 and all(e["stopped"].startswith("policy error:") and "malformed JSON" in e["stopped"]
                                 for e in eps)
