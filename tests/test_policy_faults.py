"""Bad policy replies end their trial, never the run; hostile uploads get clean HTTP errors from our server.

A real loopback HTTP server stands in for the policy and answers whatever bytes a test gives it; the client is
sim_backends/policies/openvla_client.py on the real json-numpy package, inside the real supervised loop on PyBullet.
"""

import base64
import http.client
import json
import socket
import socketserver
import threading
import time

import json_numpy
import numpy as np
import pytest
from conftest import cli, run, scripted_server, serve_policy, supervise_front
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim_backends.policies.base import PolicyError
from sim_backends.policies.openvla_client import OpenVLAClient
from sim_backends.registry import make_backend
from sim_backends.supervision.base import make_supervisor
from sim_backends.supervision.loop import LoopConfig, RunLog, TaskFamily, episode_context, run_trial

SCENARIO = "pick_place_beaker_small"
PAYLOAD = {"image": np.zeros((8, 8, 3), np.uint8), "instruction": "pick up the beaker"}


class RawPolicyServer(socketserver.ThreadingTCPServer):
    """Answers each POST with `replies[i]` (raw bytes: status line, headers and body, or any garbage), in turn."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, replies: list[bytes]):
        self.replies, self.served = list(replies), 0
        super().__init__(("127.0.0.1", 0), _RawHandler)
        threading.Thread(target=self.serve_forever, daemon=True).start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/act"

    def next_reply(self) -> bytes:
        reply = self.replies[self.served % len(self.replies)]
        self.served += 1
        return reply


class _RawHandler(socketserver.StreamRequestHandler):
    def handle(self) -> None:
        if not self.rfile.readline():  # a bare connect (the client's reachability check) takes no reply
            return
        length = 0
        while (line := self.rfile.readline()) not in (b"\r\n", b"\n", b""):
            name, _, value = line.decode("latin-1").partition(":")
            if name.strip().lower() == "content-length":
                length = int(value)
        self.rfile.read(length)
        try:
            self.wfile.write(self.server.next_reply())  # type: ignore[attr-defined]
        except OSError:  # the client gave up
            pass


def http_reply(body: bytes, status: str = "200 OK", headers: str | None = None) -> bytes:
    if headers is None:
        headers = f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
    return f"HTTP/1.1 {status}\r\n{headers}Connection: close\r\n\r\n".encode() + body


def numpy_doc(data: bytes | str, dtype: object, shape: object) -> bytes:
    b64 = base64.b64encode(data).decode() if isinstance(data, bytes) else data
    return json.dumps({"__numpy__": b64, "dtype": dtype, "shape": shape}).encode()


# ---- strategies: arbitrary and malformed replies -------------------------------------------------------------
DTYPES = [
    "<f8",
    "<f4",
    ">f8",
    "<f2",
    "<f16",
    "<i8",
    "|u1",
    "|b1",
    "<c16",
    "<U2",
    "|S3",
    "|O",
    "|V8",
    "<M8[s]",
    "<m8[s]",
    [["a", "<f4"]],
    [["a", "|O"]],
    "nonsense",
]
SHAPES = [[7], [], [1, 7], [7, 1], [6], [8], [0], [-1], [2, -4]]

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda kids: st.lists(kids, max_size=8) | st.dictionaries(st.text(max_size=6), kids, max_size=4),
    max_leaves=16,
)


@st.composite
def numpy_bodies(draw: st.DrawFn) -> bytes:
    """json-numpy documents: any dtype (object ones too), any shape, bytes of the right length or not."""
    dtype = draw(st.sampled_from(DTYPES) | json_values)
    shape = draw(st.sampled_from(SHAPES) | st.lists(st.integers(-3, 10), max_size=4) | json_values)
    exact = None
    if draw(st.booleans()):
        try:
            exact = int(np.dtype(dtype).itemsize * np.prod(shape, dtype=np.int64))
        except Exception:  # not a dtype or not a shape: any bytes
            pass
    n = exact if exact is not None and 0 <= exact <= 512 else None
    data = draw(st.binary(min_size=n, max_size=n) if n is not None else st.binary(max_size=80) | st.text(max_size=20))
    return numpy_doc(data, dtype, shape)


@st.composite
def actions(draw: st.DrawFn) -> bytes:
    """Well-formed 7-vectors of several dtypes; values may be NaN, inf or far out of reach."""
    part = st.floats(-0.2, 0.2) | st.floats()  # position, rotation and gripper each small or anything
    values = [*draw(st.tuples(part, part, part)), *draw(st.tuples(part, part, part)), draw(part)]
    if draw(st.booleans()):  # a small step, so the rotation and gripper checks are reached
        values[:3] = draw(st.tuples(*[st.floats(-0.2, 0.2)] * 3))
    dtype = draw(st.sampled_from(["<f8", "<f4", ">f8", "<f2", "<i4"]))
    with np.errstate(all="ignore"):
        a = np.array(values).astype(dtype)
    return json_numpy.dumps(a).encode()


def deep(n: int, kind: str) -> bytes:
    return ("[" * n + "]" * n if kind == "list" else '{"a":' * n + "0" + "}" * n).encode()


plain_bodies = st.one_of(
    st.binary(max_size=120),
    json_values.map(lambda v: json.dumps(v).encode()),  # NaN and Infinity included (Python's json writes them)
    st.lists(st.integers() | st.floats() | st.booleans() | st.text(max_size=4) | st.none(), min_size=6, max_size=8).map(
        lambda v: json.dumps(v).encode()
    ),
    numpy_bodies(),
    actions(),
    st.builds(deep, st.integers(900, 200_000), st.sampled_from(["list", "dict"])),
    st.just(b'"error"'),
)
bodies = plain_bodies | plain_bodies.map(lambda b: json.dumps(b.decode("utf-8", "replace")).encode())  # encoded


@st.composite
def responses(draw: st.DrawFn) -> bytes:
    """A body inside a good HTTP reply, mostly; otherwise a broken or hostile one."""
    body = draw(bodies)
    kind = draw(st.sampled_from(["ok"] * 6 + ["status", "short", "no-length", "bad-chunk", "redirect", "raw"]))
    if kind == "status":
        return http_reply(
            body,
            draw(
                st.sampled_from(
                    ["201 Created", "400 Bad Request", "422 Unprocessable", "500 Internal Server Error", "503 Busy"]
                )
            ),
        )
    if kind == "short":  # announces more than it sends, then closes
        return http_reply(body, headers=f"Content-Length: {len(body) + 10}\r\n")
    if kind == "no-length":
        return http_reply(body, headers="")
    if kind == "bad-chunk":
        return http_reply(b"zz\r\n" + body, headers="Transfer-Encoding: chunked\r\n")
    if kind == "redirect":
        return http_reply(b"", "302 Found", "Location: http://127.0.0.1:9/elsewhere\r\nContent-Length: 0\r\n")
    if kind == "raw":
        return draw(st.binary(max_size=100))
    return http_reply(body)


# ---- fixtures --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def world(tmp_path_factory):
    src = make_backend("pybullet", image_size=32, cameras=["front"])
    src.reset(SCENARIO, 0, "seen")
    ctx = episode_context(src, TaskFamily("t", [SCENARIO]), SCENARIO, 0, "seen")
    out = tmp_path_factory.mktemp("faults")
    log = RunLog(out)
    server = RawPolicyServer([http_reply(b'"error"')])
    yield src, ctx, log, out / "log.jsonl", server
    server.shutdown()
    server.server_close()
    log.close()
    src.close()


def one_line(text: object) -> bool:
    return isinstance(text, str) and 0 < len(text) < 400 and text.isprintable()


@settings(
    max_examples=60,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example],
)
@given(reply=responses())
def test_any_reply_is_an_action_or_a_clean_per_trial_error(world, reply):
    src, ctx, log, log_path, server = world
    server.replies = [reply]
    client = OpenVLAClient(server.url, timeout_s=3.0, check=False)
    client.reset(ctx)
    try:
        a = client.request(PAYLOAD)
    except PolicyError as e:
        assert one_line(str(e)), repr(str(e))
        failed = True
    else:
        assert a.dtype == np.float64 and a.shape == (7,) and np.all(np.isfinite(a)) and np.linalg.norm(a[:3]) <= 1.0
        assert np.all(np.abs(a[3:6]) <= 2 * np.pi)
        failed = False
    # the same reply inside the supervised loop: the trial ends with it, nothing escapes
    row = run_trial(
        src,
        client,
        make_supervisor("none"),
        TaskFamily("t", [SCENARIO]),
        SCENARIO,
        0,
        "seen",
        LoopConfig(max_steps=2, final_query=False),
        log,
        "fuzz",
    )
    if failed:
        assert row["outcome"] == "policy_error" and one_line(row["error"]) and row["steps"] == 0, row
    else:
        assert row["outcome"] in ("success", "failure") and row["error"] is None and row["steps"] >= 1, row
    last = json.loads(log_path.read_text().splitlines()[-1])
    assert (last["trial"], last["outcome"], last["error"]) == ("fuzz", row["outcome"], row["error"])


# One bad reply per trial, each kind the issue names; the reasons the run must record, in order.
BAD = [
    (http_reply(json_numpy.dumps(np.array([0.0, np.nan, 0, 0, 0, 0, 1])).encode()), "NaN or inf"),
    (http_reply(json_numpy.dumps(np.zeros(8)).encode()), "shape (8,)"),
    (http_reply(json_numpy.dumps(np.zeros(7, bool)).encode()), "dtype '|b1'"),
    (http_reply(numpy_doc(b"\0" * 56, "|O", [7])), "object arrays are refused"),
    (http_reply(deep(50_000, "list")), "nested too deeply"),
    (http_reply(json.dumps(["0", "0", "0", "0", "0", "0", "1"]).encode()), "a list, not a 7-D action"),
    (http_reply(json.dumps(json_numpy.dumps(np.full(7, np.inf))).encode()), "NaN or inf"),  # the encoded form
    (http_reply(json_numpy.dumps(np.array([5.0, 0, 0, 0, 0, 0, 1])).encode()), "a step of 5 m"),
    (http_reply(json_numpy.dumps(np.array([0, 0, 0, 0, 0, 1.3e154, 1])).encode()), "over a full turn"),
    (http_reply(b'"error"'), 'answered "error"'),
    (http_reply(b"<html>busy</html>", "500 Internal Server Error"), "answered HTTP 500"),
    (http_reply(b"zz\r\n", headers="Transfer-Encoding: chunked\r\n"), "broken HTTP"),
    (b"\x00garbage\r\n\r\n", "broken HTTP"),
]


def test_a_run_of_bad_replies_writes_its_results(tmp_path):
    server = RawPolicyServer([r for r, _ in BAD])
    out = tmp_path / "bad"
    try:
        policy = ["policy=openvla", f"openvla.url={server.url}", "openvla.timeout_s=5", "supervisor=none"]
        r = supervise_front(out, policy, SCENARIO, len(BAD), 32)
    finally:
        server.shutdown()
        server.server_close()
    assert r.returncode == 0, r.stderr
    errors = json.loads((out / "results.json").read_text())["tasks"][SCENARIO]["none"]["policy_errors"]
    assert len(errors) == len(BAD)
    for e, (_, reason) in zip(errors, BAD):
        assert reason in e["reason"] and one_line(e["reason"]), (reason, e)
    eps = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines() if '"episode"' in x]
    assert [e["outcome"] for e in eps] == ["policy_error"] * len(BAD)
    assert [e["error"] for e in eps] == [e["reason"] for e in errors]
    assert f"{len(BAD)} trial(s) ended on a policy error" in (out / "results.md").read_text()
    assert sum("policy error:" in line for line in r.stderr.splitlines()) == len(BAD)


@pytest.mark.parametrize(
    "args, msg",
    [
        (["openvla.timeout_s=soon"], "openvla.timeout_s: expected a number"),
        (["openvla.timeout_s=0"], "openvla.timeout_s: must be a positive number of seconds"),
        (["openvla.encoded=maybe"], "openvla.encoded: expected true or false"),
        (["openvla.max_step_m=-1"], "openvla.max_step_m: must be a positive number"),
        (["openvla.idle_stop=1.5"], "openvla.idle_stop: must be an integer >= 0"),
    ],
)
def test_bad_client_settings_are_one_line_errors(tmp_path, args, msg):
    r = run(
        [
            cli("supervise"),
            "policy=openvla",
            "openvla.url=http://127.0.0.1:9/act",
            *args,
            "progress=false",
            f"out_dir={tmp_path / 'x'}",
        ],
        120,
    )
    assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_client_settings_from_the_command_line_reach_the_client(tmp_path):
    """openvla.encoded / timeout_s from the command line: an encoded request to a server that takes 1.5 s is
    refused after the 0.5 s timeout, and the request it sent was the encoded form."""
    seen: list[bytes] = []

    class Slow(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            if not self.rfile.readline():
                return
            length = 0
            while (line := self.rfile.readline()) not in (b"\r\n", b""):
                if line.lower().startswith(b"content-length:"):
                    length = int(line.split(b":")[1])
            seen.append(self.rfile.read(length))
            time.sleep(1.5)

    srv = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Slow)
    srv.daemon_threads = True
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    out = tmp_path / "slow"
    try:
        url = f"http://127.0.0.1:{srv.server_address[1]}/act"
        policy = ["policy=openvla", f"openvla.url={url}", "openvla.encoded=true", "openvla.timeout_s=0.5"]
        r = supervise_front(out, [*policy, "supervisor=none"], SCENARIO, 1, 32, timeout=300)
    finally:
        srv.shutdown()
        srv.server_close()
    assert r.returncode == 0, r.stderr
    ep = next(json.loads(x) for x in (out / "log.jsonl").read_text().splitlines() if '"episode"' in x)
    assert ep["outcome"] == "policy_error" and "no answer within 0.5 s" in ep["error"]
    body = json.loads(seen[0])
    assert list(body) == ["encoded"] and isinstance(json_numpy.loads(body["encoded"])["image"], np.ndarray)


def test_a_reply_dripped_a_byte_at_a_time_is_cut_off_at_the_timeout():
    """Each byte comes well within the socket timeout; the whole reply would take 4 s, the client allows 0.5."""

    class Drip(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            while self.rfile.readline() not in (b"\r\n", b""):
                pass
            self.wfile.write(b"HTTP/1.1 200 OK\r\nContent-Length: 40\r\n\r\n")
            try:
                for _ in range(40):
                    self.wfile.write(b" ")
                    self.wfile.flush()
                    time.sleep(0.1)
            except OSError:  # the client gave up
                pass

    srv = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Drip)
    srv.daemon_threads = True
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    t = time.monotonic()
    try:
        with pytest.raises(PolicyError, match="no complete answer within 0.5 s"):
            OpenVLAClient(f"http://127.0.0.1:{srv.server_address[1]}/act", timeout_s=0.5, check=False).request(PAYLOAD)
    finally:
        srv.shutdown()
        srv.server_close()
    assert time.monotonic() - t < 1.5


# ---- hostile uploads to labrobfail-serve-policy ------------------------------------------------------------------
@pytest.fixture(scope="module")
def server():
    for url, p in scripted_server("max_body_mb=1", "request_timeout_s=1"):
        yield int(url.split(":")[-1].split("/")[0]), p


def post(port: int, body: bytes, headers: dict[str, str] | None = None, path: str = "/act") -> tuple[int, bytes]:
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        c.request("POST", path, body, {"Content-Type": "application/json", **(headers or {})})
        r = c.getresponse()
        return r.status, r.read()
    finally:
        c.close()


def raw_exchange(port: int, data: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(data)
        return s.recv(65536)


def good_request(**extra: object) -> bytes:
    return json_numpy.dumps(
        {
            "image": np.zeros((8, 8, 3), np.uint8),
            "instruction": "x",
            "episode": {"scenario": SCENARIO, "seed": 0, "variant": "seen"},
            **extra,
        }
    ).encode()


def image_doc(dtype: str) -> bytes:
    return b'{"image": ' + numpy_doc(b"\0" * 8 * 8 * 3 * 8, dtype, [8, 8, 3]) + b', "instruction": "x"}'


@pytest.mark.parametrize(
    "body, headers, status, detail",
    [
        (b"not json", None, 400, b"not json-numpy"),
        (b"[" * 100_000 + b"]" * 100_000, None, 400, b"nested too deeply"),
        (image_doc("|O"), None, 400, b"object arrays are refused"),
        (b"[1, 2, 3]", None, 422, b"JSON object"),
        (b"{}", {"Content-Length": "-5"}, 400, b"Invalid HTTP request"),  # uvicorn's own answer
        (b"", {"Content-Length": str(2 << 20)}, 413, b"over the 1,048,576 byte limit"),  # refused before reading
        (good_request(), None, 200, b'{"__numpy__"'),
        (good_request(proprio=[0.0] * 8), None, 200, b'"error"'),  # proprio must be 9 numbers
        (good_request(proprio=["0"] * 9), None, 200, b'"error"'),
        (image_doc("<f8"), None, 200, b'"error"'),  # not a uint8 image
        (
            json_numpy.dumps({"image": np.zeros((8, 8, 3), np.uint8), "instruction": "x"}).encode(),
            None,
            200,
            b'"error"',
        ),  # the scripted policy needs a scenario: none sent, no default_episode.scenario
        (json.dumps({"encoded": good_request().decode(), "extra": 1}).encode(), None, 200, b'"error"'),
        (json.dumps({"encoded": good_request().decode()}).encode(), None, 200, b'"{\\"__numpy__\\"'),
    ],
)
def test_hostile_uploads_get_clean_answers_and_the_server_keeps_serving(server, body, headers, status, detail):
    port, proc = server
    code, reply = post(port, body, headers)
    assert code == status and detail in reply, (code, reply[:200])
    assert post(port, good_request())[0] == 200 and proc.poll() is None


def test_server_bounds_a_chunked_upload_and_survives_a_stalled_upload_and_a_silent_connection(server):
    port, proc = server
    chunk = b"x" * 65536
    chunked = b"".join(b"%x\r\n%s\r\n" % (len(chunk), chunk) for _ in range(20)) + b"0\r\n\r\n"  # 1.25 MiB
    head = b"POST /act HTTP/1.1\r\nHost: x\r\nConnection: close\r\nTransfer-Encoding: chunked\r\n\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(head + chunked)
        reply = b""
        while part := s.recv(65536):
            reply += part
    assert reply.startswith(b"HTTP/1.1 413") and b"request over 1048576 bytes" in reply, reply[:200]
    with socket.create_connection(("127.0.0.1", port), timeout=10) as stalled:
        stalled.sendall(b'POST /act HTTP/1.1\r\nHost: x\r\nContent-Length: 1000\r\n\r\n{"image"')
        t = time.monotonic()
        assert post(port, good_request())[0] == 200  # served at once beside the stalled upload
        assert time.monotonic() - t < 1.0
        answer = b""
        while part := stalled.recv(4096):  # a 408 after request_timeout_s=1, then the connection closes
            answer += part
        assert answer.startswith(b"HTTP/1.1 408") and b"not received within 1 s" in answer, answer[:200]
        assert time.monotonic() - t < 5.0
    with socket.create_connection(("127.0.0.1", port), timeout=10) as silent:  # connects, never sends a request
        t = time.monotonic()
        assert silent.recv(1) == b""  # closed by the server once request_timeout_s has passed without a head
        assert 0.5 < time.monotonic() - t < 5.0
    assert post(port, good_request())[0] == 200 and proc.poll() is None


def test_a_token_guards_every_path_but_health_and_sigterm_stops_cleanly(monkeypatch):
    """The diagnosis server's token and shutdown on the policy server: without the bearer token a request is 401
    (and the token is never echoed), the project's client sends it from the environment, /health stays open, and
    SIGTERM ends the server with exit code 0."""
    import os
    import signal

    token = "s3cret-policy-token"
    p = serve_policy(
        "policy=scripted",
        "port=0",
        f"default_episode.scenario={SCENARIO}",
        env={**os.environ, "LABROBFAIL_POLICY_TOKEN": token},
    )
    try:
        url = p.stdout.readline().split()[-1]
        port = int(url.split(":")[-1].split("/")[0])
        code, reply = post(port, good_request())
        assert code == 401 and b"bearer token" in reply and token.encode() not in reply, (code, reply)
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        c.request("GET", "/health")
        health = c.getresponse()
        assert health.status == 200 and json.loads(health.read())["policy"] == "scripted"
        c.close()
        monkeypatch.setenv("LABROBFAIL_POLICY_TOKEN", token)
        action = OpenVLAClient(url, timeout_s=30).request(PAYLOAD)
        assert action.shape == (7,) and np.all(np.isfinite(action))
        monkeypatch.setenv("LABROBFAIL_POLICY_TOKEN", "wrong")
        with pytest.raises(PolicyError, match="answered HTTP 401"):
            OpenVLAClient(url, timeout_s=30).request(PAYLOAD)
    finally:
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=30)
    assert p.returncode == 0 and "stopped" in out and token not in out + err, (p.returncode, out, err[-500:])
