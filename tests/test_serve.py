"""The diagnosis server, started for real on a free loopback port: answers equal FailureAnalyzer's, every bad
request is a 4xx with one JSON line, the bearer token, batching under concurrent clients, graceful shutdown."""

import io
import json
import os
import signal
import subprocess
import threading
import time

import pytest
from conftest import ROOT, cli, run, run_here
from PIL import Image
from serve_fixtures import TASKS, frame_lists, grids, mixed_model  # noqa: F401  (fixtures)

TOKEN = "t0k-" + "x" * 28


class Server:
    def __init__(self, model, log, *args, token=TOKEN):
        env = (
            {**os.environ, "LABROBFAIL_API_TOKEN": token}
            if token
            else {k: v for k, v in os.environ.items() if k != "LABROBFAIL_API_TOKEN"}
        )
        self.log = log
        self.proc = subprocess.Popen(
            [cli("serve"), "--model", str(model), "--port", "0", *args],
            cwd=ROOT,
            env=env,
            stdout=open(log, "w"),
            stderr=subprocess.STDOUT,
        )
        self.url = None
        for _ in range(600):
            text = log.read_text()
            if "startup complete" in text:
                self.url = next(w for w in text.split() if w.startswith("http://"))
                break
            assert self.proc.poll() is None, text
            time.sleep(0.1)
        assert self.url, log.read_text()

    def client(self, token=TOKEN):
        from labrobfail_vlm.serve.client import DiagnosisClient

        os.environ["_TEST_TOKEN"] = token or ""
        return DiagnosisClient(self.url, token_env="_TEST_TOKEN")

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                return self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()  # never leave a server behind; the caller's assert reports the hang
                return None
        return self.proc.returncode


@pytest.fixture(scope="module")
def server(mixed_model, tmp_path_factory):  # noqa: F811
    flags = ["--max-batch", "4", "--max-wait-ms", "300", "--max-upload-mb", "2"]
    s = Server(mixed_model, tmp_path_factory.mktemp("srv") / "server.log", *flags)
    yield s
    assert s.stop() == 0
    assert TOKEN not in s.log.read_text()  # the token is never logged


@pytest.fixture(scope="module")
def fa(mixed_model):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    return FailureAnalyzer.from_pretrained(mixed_model)


def png(img):
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def test_diagnosis_equals_the_analyzers(server, fa, grids):  # noqa: F811
    from labrobfail_vlm.analyzer import frames_to_grid

    c = server.client()
    for i, g in enumerate(grids[:4]):
        got = c.diagnose(grid=g, task=TASKS[i % 3])
        assert got == json.loads(fa.analyze(g, TASKS[i % 3]).to_json())
    assert {c.diagnose(grid=g)["failure"] for g in grids[:4]} == {True, False}
    frames = frame_lists(3, frames=5)
    got = c.diagnose(frames={"front": frames[0], "side": frames[1]}, task="stir the solution")
    assert got == json.loads(fa.analyze(frames, "stir the solution").to_json())
    got = c.diagnose(frames={"front": frames[0], "side": frames[1]}, task="stir the solution", prefix=2)
    want = fa.analyze(frames_to_grid(frames, fa.grid, visible=2), "stir the solution", frames=2)
    assert got == json.loads(want.to_json())
    assert got["failure_frame"] in (None, 1, 2)


def _bad_requests(tmp):
    ok = png(Image.new("RGB", (256, 128), (200, 200, 200)))
    bomb = io.BytesIO()
    Image.new("1", (9000, 5000)).save(bomb, format="PNG")
    f = lambda name, data: (name, ("x.png", data, "image/png"))  # noqa: E731
    return [
        ([("task", "no image")], 400, "missing image"),
        ([f("grid", b"hello, I am text")], 400, "not an image"),
        ([f("grid", b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)], 400, "grid"),
        ([f("grid", ok[: len(ok) // 2])], 400, "truncated"),
        ([f("grid", png(Image.new("RGB", (8, 8))))], 400, "at least 32 px"),
        ([f("grid", bomb.getvalue())], 413, "too large"),
        ([f("grid", ok), ("colour", "red")], 400, "unknown field 'colour'"),
        ([f("grid", ok), ("prefix", "abc")], 400, "prefix"),
        ([f("grid", ok), ("prefix", "0")], 400, "prefix"),
        ([f("grid", ok), ("prefix", "17")], 400, "from 1 to 16"),
        ([("grid", "not a file")], 400, "expected an uploaded image file"),
        ([f("grid", ok), f("grid", ok)], 400, "more than once"),
        ([f("grid", ok), f("frames.front", ok)], 400, "send exactly one of"),
        ([f("frames.front", ok), f("frames.front", ok), f("frames.side", ok)], 400, "unequal numbers"),
        ([f("frames.front", ok), ("prefix", "2")], 400, "from 1 to 1"),
        ([f("grid", ok), ("task", "x" * 3000)], 400, "longer than"),
        ([f("grid", os.urandom(3 * 1024 * 1024))], 413, "byte limit"),
    ]


def test_bad_requests_get_one_line_4xx(server, tmp_path):
    c = server.client()
    for parts, status, needle in _bad_requests(tmp_path):
        code, body = c.post_form(parts)
        assert code == status and set(body) == {"error"}, (parts[0][0], code, body)
        assert needle in body["error"] and "\n" not in body["error"] and "Traceback" not in body["error"], body
    # not multipart, unknown path, wrong method, a body streamed past the limit without a Content-Length
    assert c.request("POST", "/diagnose", b'{"grid": 1}', {"Content-Type": "application/json"})[0] == 415
    assert c.request("GET", "/nothing")[0] == 404 and c.request("GET", "/diagnose")[0] == 405
    import http.client

    host, port = server.url.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=60)
    head = b'--b\r\nContent-Disposition: form-data; name="grid"; filename="g.png"\r\n\r\n'
    conn.request(
        "POST",
        "/diagnose",
        body=iter([head] + [b"x" * (1 << 20)] * 3),
        encode_chunked=True,
        headers={"Authorization": f"Bearer {TOKEN}", "Content-Type": "multipart/form-data; boundary=b"},
    )
    r = conn.getresponse()
    assert r.status == 413 and "byte limit" in json.loads(r.read())["error"]
    conn.close()
    assert c.health()["status"] == "ok"  # still up


def test_token_is_required_and_checked(server):
    from labrobfail_vlm.serve.client import ServiceError

    for token in ("", "wrong", TOKEN[:-1]):
        c = server.client(token)
        code, body = c.request("GET", "/info")
        assert code == 401 and "bearer token" in body["error"] and TOKEN not in json.dumps(body)
        with pytest.raises(ServiceError, match="401"):
            c.diagnose(grid=Image.new("RGB", (64, 64)))
        assert c.health()["status"] == "ok"  # health needs no token
    info = server.client().info()
    assert info["serve"]["token_required"] is True and "token" not in info["serve"]
    assert info["grid"]["max_frames"] == 16 and info["version"]
    assert (
        info["threshold"] == 0.5 and info["option_bias"] == {} and info["failure_score"] == "q2"
    )  # the operating points a reply was decided at


def test_concurrent_requests_are_batched_with_the_same_answers(server, fa, grids):  # noqa: F811
    want = [json.loads(fa.analyze(g, f"task {i}").to_json()) for i, g in enumerate(grids)]
    got = [None] * len(grids)

    def ask(i):
        got[i] = server.client().diagnose(grid=grids[i], task=f"task {i}")

    before = server.client().health()["batches"]
    threads = [threading.Thread(target=ask, args=(i,)) for i in range(len(grids))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    # each client got its own grid's diagnosis (P(failure): float sums over padded rows, equal to rounding)
    assert [g.pop("p_failure") for g in got] == pytest.approx([w.pop("p_failure") for w in want], abs=1e-4)
    assert got == want
    h = server.client().health()
    assert h["largest_batch"] > 1 and h["batches"] - before < len(grids)


def test_shutdown_finishes_requests_in_flight(mixed_model, grids, tmp_path):  # noqa: F811
    s = Server(mixed_model, tmp_path / "log", "--max-batch", "2", "--max-wait-ms", "50", token=None)
    codes = []

    def ask(i):
        codes.append(s.client(None).post_form([("grid", ("g.png", png(grids[i]), "image/png"))])[0])

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    time.sleep(0.5)
    assert s.stop() == 0
    for t in threads:
        t.join()
    assert codes == [200] * 6
    assert "stopped: requests in flight finished" in s.log.read_text()
    from labrobfail_vlm.serve.client import DiagnosisClient

    with pytest.raises(OSError):
        DiagnosisClient(s.url, timeout_s=5).health()


def test_bad_arguments_are_one_line_errors(tmp_path):
    for args, needle in (
        (["--model", str(tmp_path / "none")], "no such model directory"),
        (["--model", str(tmp_path), "--port", "70000"], "port:"),
        (["--model", str(tmp_path), "--max-batch", "0"], "max_batch:"),
    ):
        call = run if needle.startswith("no such") else run_here  # the first case as a real process
        r = call([cli("serve"), *args])
        assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_videos_are_diagnosed_as_the_analyzer_does_and_bad_ones_refused(server, fa, tmp_path):  # noqa: F811
    """video.<view> fields: the server picks the keyframes as FailureAnalyzer.analyze_video does."""
    import cv2

    paths = {}
    for view, frames in zip(("front", "side"), frame_lists(5, frames=30, side=64)):
        paths[view] = tmp_path / f"{view}.mp4"
        w = cv2.VideoWriter(str(paths[view]), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 64))
        for f in frames:
            w.write(f)
        w.release()
    c = server.client()
    for mode in ("uniform", "motion"):
        got = c.diagnose(videos=paths, task="stir the solution", keyframes=mode)
        want = fa.analyze_video(list(paths.values()), "stir the solution", keyframes=mode)
        assert got == json.loads(want.to_json())
    for videos, needle in [
        ({"front": b"not a video at all"}, "video.front: 'front.mp4' is not a video"),
        ({"front": paths["front"].read_bytes()[:3000]}, "header is truncated"),
    ]:
        code, body = c.post_form([(f"video.{v}", (f"{v}.mp4", d, "video/mp4")) for v, d in videos.items()])
        assert code == 400 and needle in body["error"] and "\n" not in body["error"], (code, body)
    code, body = c.post_form([("video.front", ("f.mp4", b"x", "video/mp4")), ("keyframes", "random")])
    assert code == 400 and "keyframes: expected uniform or motion" in body["error"], body
