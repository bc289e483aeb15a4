"""The diagnosis server's bounds (issue 33), against a real uvicorn server on loopback with the tiny model:
images priced from their headers and refused before decoding, a decoded-pixel budget shared by concurrent
requests, a body read timeout (408), every malformed field a 4xx, and a client that disconnects mid-upload
logged in one line. Every wait is bounded (socket and thread timeouts)."""

import asyncio
import json
import select
import socket
import struct
import threading
import time
import zlib

import numpy as np
import pytest
from conftest import cli, run, run_here
from PIL import Image
from test_serve import Server, png
from test_train import tiny  # noqa: F401  (session fixture)

MIB = 1 << 20
BUDGET_MB, REQUEST_MB, BODY_TIMEOUT_S = 4, 2, 2


@pytest.fixture(scope="module")
def server(tiny, tmp_path_factory):  # noqa: F811
    budgets = ["--max-decode-mb", str(BUDGET_MB), "--max-request-decode-mb", str(REQUEST_MB)]
    batching = ["--body-timeout-s", str(BODY_TIMEOUT_S), "--max-batch", "4", "--max-wait-ms", "50"]
    s = Server(tiny, tmp_path_factory.mktemp("bounds") / "server.log", *budgets, *batching, token=None)
    yield s
    assert s.stop() == 0
    log = s.log.read_text()
    assert "Traceback" not in log and "internal error" not in log, log[-3000:]


def png16_rgba(w, h):
    """A w x h PNG with four 16-bit channels (8 bytes a pixel decoded at file depth), of zeros: ~300 KB for
    6300 x 6300, written row by row so the test never holds the raw pixels."""
    row, z = b"\x00" + bytes(w * 8), zlib.compressobj(9)
    idat = b"".join([z.compress(row) for _ in range(h)] + [z.flush()])

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 6, 0, 0, 0))
        + chunk(b"IDAT", idat)
        + chunk(b"IEND", b"")
    )


def noise_png(side, seed):
    rng = np.random.default_rng(seed)
    return png(Image.fromarray(rng.integers(0, 255, (side, side, 3), dtype=np.uint8)))


def _status(pid):
    fields = dict(line.split(":", 1) for line in open(f"/proc/{pid}/status"))
    return {k: int(fields[k].split()[0]) * 1024 for k in ("VmRSS", "VmHWM")}


def _host_port(server):
    host, port = server.url.removeprefix("http://").split(":")
    return host, int(port)


def raw_request(server, head_and_body, drip=None, timeout=15):
    """Send bytes over a fresh connection (then `drip`: (chunk, seconds) pairs, until the server answers); return
    (status line, body, seconds from the first send to the first byte of the reply)."""
    with socket.create_connection(_host_port(server), timeout=timeout) as s:
        t = time.monotonic()
        s.sendall(head_and_body)
        for chunk, pause in drip or []:
            if select.select([s], [], [], pause)[0]:  # the server has answered: stop dripping
                break
            s.sendall(chunk)
        select.select([s], [], [], timeout)
        took = time.monotonic() - t
        data = b""
        while True:
            try:
                got = s.recv(65536)
            except (ConnectionResetError, socket.timeout):
                break
            if not got:
                break
            data += got
        head, _, body = data.partition(b"\r\n\r\n")
        return head.split(b"\r\n")[0].decode(), body, took


def _head(length, extra=""):
    return (
        f"POST /diagnose HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=B\r\n"
        f"Content-Length: {length}\r\n{extra}\r\n"
    ).encode()


PART = b'--B\r\nContent-Disposition: form-data; name="grid"; filename="g.png"\r\n\r\n'


def test_huge_16bit_rgba_png_is_refused_before_decoding(server):
    """6300 x 6300 x 4 channels x 16 bit: refused from its header (413) without the ~300 MB a decode would take."""
    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.images import ImageTooLarge
    from labrobfail_vlm.serve.form import Upload, plan

    big = png16_rgba(6300, 6300)
    with pytest.raises(ImageTooLarge, match="too large to decode: 6300x6300"):  # the default limit refuses it too
        plan([("grid", Upload("big.png", big))], GridConfig())
    pid = server.proc.pid
    try:  # reset the peak-RSS counter, so VmHWM below is this request's peak
        with open(f"/proc/{pid}/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    before = _status(pid)
    t = time.monotonic()
    code, body = server.client(None).post_form([("grid", ("big.png", big, "image/png"))])
    took = time.monotonic() - t
    after = _status(pid)
    assert code == 413 and "too large to decode: 6300x6300" in body["error"] and "per-request limit" in body["error"]
    assert took < 5, took
    grew = after["VmHWM"] - max(before["VmRSS"], 0)
    assert grew < 64 * MIB, f"peak RSS grew by {grew / MIB:.0f} MiB: the image was decoded"


def test_concurrent_uploads_share_the_decode_budget(server):
    """Eight clients at once, each with a 300x300 grid priced at 20 bytes a pixel (~1.7 MiB): all answered, the
    image memory the server holds never above its 4 MiB budget (two such requests at a time), nothing held
    afterwards; one request over 2 MiB is refused alone (413)."""
    grids = [noise_png(300, i) for i in range(8)]
    codes = [None] * len(grids)

    def ask(i):
        codes[i] = server.client(None).post_form([("grid", ("g.png", grids[i], "image/png"))])[0]

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(len(grids))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert codes == [200] * len(grids)
    h = server.client(None).health()
    assert 300 * 300 * 20 <= h["decode_bytes_peak"] <= BUDGET_MB * MIB == h["decode_budget_bytes"], h
    assert h["decode_bytes_held"] == 0, h
    code, body = server.client(None).post_form([("grid", ("big.png", noise_png(600, 9), "image/png"))])
    assert code == 413 and "per-request limit" in body["error"], body
    frames = [("frames.front", (f"{i}.png", noise_png(64, i), "image/png")) for i in range(4)]
    code, body = server.client(None).post_form(frames)  # the composed 1536x768 grid alone is over 2 MiB
    assert code == 413 and body["error"].startswith("frames: ") and "per-request limit" in body["error"], body


def test_a_body_short_of_its_length_gets_408(server):
    status, body, took = raw_request(server, _head(100_000) + PART + b"x" * 5000)
    assert status.startswith("HTTP/1.1 408") and "not received within 2 s" in json.loads(body)["error"], status
    assert BODY_TIMEOUT_S - 0.5 < took < BODY_TIMEOUT_S + 5, took
    # a client dripping its body never reaches the end either: the deadline counts from the first read
    status, _, took = raw_request(server, _head(100_000) + PART, drip=[(b"x" * 100, 0.3)] * 30)
    assert status.startswith("HTTP/1.1 408") and took < BODY_TIMEOUT_S + 5, (status, took)
    assert server.client(None).health()["status"] == "ok"


def test_malformed_fields_get_one_line_4xx(server):
    ok = png(Image.new("RGB", (256, 128), (200, 200, 200)))
    g = ("grid", ("g.png", ok, "image/png"))
    c = server.client(None)
    for parts, needle in [
        ([g, ("prefix", "²")], "prefix"),  # str.isdigit() says yes, int() says no: was a 500
        ([g, ("prefix", "٣")], "prefix"),
        ([g, ("prefix", "３")], "prefix"),
        ([g, ("prefix", "1e3")], "prefix"),
        ([g, ("prefix", "-1")], "prefix"),
        ([g, ("prefix", "9" * 40)], "prefix"),
        ([g, ("task", "pick\x00up")], "task: contains control characters"),
        ([g, ("objects", "beaker\x1b[31m")], "objects: contains control characters"),
        ([("grid", ("g.png", b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, "image/png"))], "grid"),
    ]:
        code, body = c.post_form(parts)
        assert 400 <= code < 500 and set(body) == {"error"} and "\n" not in body["error"], (parts[-1], code, body)
        assert needle in body["error"], (parts[-1], body)
    for ctype, raw in [
        ("multipart/form-data", PART + ok),
        ("multipart/form-data; boundary=B", b"garbage"),
        ("multipart/form-data; boundary=B", b"--B\r\nContent-Disposition: form-data\r\n\r\nx\r\n--B--"),
    ]:
        code, body = c.request("POST", "/diagnose", raw, {"Content-Type": ctype})
        assert 400 <= code < 500 and "\n" not in body["error"], (ctype, code, body)
    assert c.health()["status"] == "ok"


def test_a_client_gone_mid_upload_is_one_log_line(server):
    with socket.create_connection(_host_port(server), timeout=10) as s:
        s.sendall(_head(100_000) + PART + b"x" * 3000)
        time.sleep(0.3)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and "disconnected mid-upload" not in server.log.read_text():
        time.sleep(0.1)
    lines = [ln for ln in server.log.read_text().splitlines() if "disconnected mid-upload" in ln]
    assert len(lines) == 1 and "of 100,000 bytes received" in lines[0], lines
    assert "Traceback" not in server.log.read_text()
    assert server.client(None).health()["status"] == "ok"


def test_decode_budget_waits_shrinks_and_refuses():
    from labrobfail_vlm.serve.batcher import Busy
    from labrobfail_vlm.serve.budget import DecodeBudget

    async def exercise():
        b = DecodeBudget(4)
        first = await b.reserve(3, 1)
        with pytest.raises(Busy, match="retry later"):
            await b.reserve(2, 0.05)
        waiter = asyncio.create_task(b.reserve(2, 5))
        await asyncio.sleep(0.05)
        assert not waiter.done()
        await first.shrink(1)  # decoding over: only the kept grid stays held, the waiter gets its share
        second = await asyncio.wait_for(waiter, 5)
        assert (b.used, b.peak) == (3, 3)
        await first.release()
        await second.release()
        assert b.used == 0

    asyncio.run(exercise())


def test_bound_flags_are_checked(tiny):  # noqa: F811
    for args, needle in (
        (["--max-decode-mb", "4", "--max-request-decode-mb", "8"], "must not exceed"),
        (["--body-timeout-s", "0"], "body_timeout_s:"),
        (["--max-decode-mb", "nan"], "max_decode_mb:"),
        (["--max-connections", "0"], "max_connections:"),
    ):
        call = run if needle == "must not exceed" else run_here  # the first case as a real process
        r = call([cli("serve"), "--model", str(tiny), *args])
        assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_max_connections_bounds_raw_upload_memory(tiny, tmp_path):  # noqa: F811
    """--max-connections: a connection beyond the limit is answered 503 at once (uploads held <= limit x size). A
    client that connects and says nothing, or drips its request head, holds its slot no longer than the body
    timeout: the server closes it and the next client is served (uvicorn alone kept such a connection forever)."""
    s = Server(tiny, tmp_path / "log", "--max-connections", "1", "--body-timeout-s", str(BODY_TIMEOUT_S), token=None)
    health = b"GET /health HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
    try:  # one connection is served (uvicorn counted the asking connection: --max-connections 1 served none)
        assert raw_request(s, health)[0].startswith("HTTP/1.1 200")
        with socket.create_connection(_host_port(s), timeout=10) as hold:
            hold.sendall(_head(100_000) + PART)  # keeps the only slot while its body never finishes
            time.sleep(0.3)
            status, _, _ = raw_request(s, _head(len(b"--B--\r\n")) + b"--B--\r\n")
            assert status.startswith("HTTP/1.1 503"), status
        for drip in (b"", b"G"):  # silent; a header byte every 0.4 s
            with socket.create_connection(_host_port(s), timeout=10) as idle:
                time.sleep(0.3)
                assert raw_request(s, health)[0].startswith("HTTP/1.1 503")  # it holds the only slot
                t, closed = time.monotonic(), False
                while not closed and time.monotonic() - t < BODY_TIMEOUT_S + 5:
                    if drip:
                        idle.sendall(drip)
                    closed = bool(select.select([idle], [], [], 0.4)[0]) and idle.recv(1) == b""
                took = time.monotonic() - t
                assert closed and BODY_TIMEOUT_S - 1 < took < BODY_TIMEOUT_S + 5, (drip, took)  # 0.3 s before t
            status, _, _ = raw_request(s, health)
            assert status.startswith("HTTP/1.1 200"), (drip, status)
    finally:
        assert s.stop() == 0
