"""Benchmark the diagnosis server on loopback: latency, throughput with and without batching, memory, a load run.

Run as:
    python scripts/bench_serve.py [model=DIR] [grid=512x512] [seconds=8] [load_requests=2000]
                                  [load_clients=16] [malformed=0.1] [out=outputs/bench_serve.json]
    python scripts/bench_serve.py --seconds 2 --load-requests 0

Starts labrobfail-serve as its own process (the tiny random model, built on the fly, unless model is given)
and measures, with real HTTP clients in threads:
  - single-request latency p50/p95 (one client, sequential);
  - throughput (diagnoses/s) at 1, 8 and 16 concurrent clients, for a fixed time each, with batching
    (max_batch=8) and without (max_batch=1; a second server);
  - the server's peak RSS (VmHWM) under each;
  - a bounded load run (a third server, Q6 in template mode): load_requests requests from load_clients
    clients, a `malformed` share of them bad (not an image, no image, bad prefix, unknown field, decompression
    bomb), each good one with its own task text, which its reply must echo: every request must get exactly one
    reply, its own, and the server must be alive at the end with as many diagnoses counted as good requests sent.
The default run takes about 4-5 minutes on 2 CPU cores shared with other work.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from labrobfail_vlm.config import ConfigError, cli_main, load_config, size_setting
from labrobfail_vlm.serve.client import DiagnosisClient, Part

ROOT = Path(__file__).resolve().parents[1]  # labrobfail-serve runs with the repository root as its cwd
SERVE = Path(sys.executable).with_name("labrobfail-serve")  # the console script of this venv

DEFAULTS = """
model: null                    # model folder to serve; null = a tiny random model, built on the fly
grid: 512x512                  # uploaded grid size WxH (512x512: 256 visual tokens)
seconds: 8.0                   # seconds per throughput level
clients: "1,8,16"              # concurrent clients of the throughput levels, comma-separated
max_batch: 8                   # the batched server's max_batch (the unbatched one runs max_batch=1)
max_wait_ms: 10.0              # every server's max_wait_ms
load_requests: 2000            # requests in the load run (0 = no load run)
load_clients: 16               # concurrent clients in the load run
malformed: 0.1                 # share of the load run's requests that are bad (0-1)
out: outputs/bench_serve.json  # the JSON result
"""


def png(img: Any) -> bytes:
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


class ServerProcess:
    def __init__(self, model: str, log: Path, *args: str):
        env = {k: v for k, v in os.environ.items() if k != "LABROBFAIL_API_TOKEN"}
        self.log = log
        self.proc = subprocess.Popen(
            [str(SERVE), f"model={model}", "port=0", "log_level=warning", *args],
            cwd=ROOT,
            env=env,
            stdout=open(log, "w"),
            stderr=subprocess.STDOUT,
        )
        self.url = ""
        for _ in range(1200):
            text = log.read_text()
            if self.proc.poll() is not None:
                raise SystemExit(f"error: the server did not start:\n{text[-2000:]}")
            if "serving " in text:
                self.url = next(w for w in text.split() if w.startswith("http://"))
                try:
                    DiagnosisClient(self.url, timeout_s=5).health()
                    return
                except OSError:
                    pass
            time.sleep(0.1)
        raise SystemExit("error: the server did not answer /health within 120 s")

    def peak_rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
        return float("nan")

    def stop(self) -> int:
        self.proc.terminate()
        return self.proc.wait(timeout=120)


def grid_parts(grid_wh: tuple[int, int], n: int = 8) -> list[bytes]:
    from PIL import Image

    rng = np.random.default_rng(0)
    w, h = grid_wh
    return [png(Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8))) for _ in range(n)]


def in_threads(run: Any, clients: int) -> float:
    """Run `run(k)` for k in range(clients) in threads; the wall seconds until all are done."""
    t = time.perf_counter()
    threads = [threading.Thread(target=run, args=(k,)) for k in range(clients)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    return time.perf_counter() - t


def latency(url: str, grids: list[bytes], n: int = 20) -> dict[str, float]:
    c = DiagnosisClient(url)
    verdicts = [c.post_form([("grid", ("g.png", g, "image/png"))])[1]["failure"] for g in grids]  # and warm-up
    ts = []
    for i in range(n):
        t = time.perf_counter()
        code, _ = c.post_form([("grid", ("g.png", grids[i % len(grids)], "image/png")), ("task", f"lat {i}")])
        ts.append(time.perf_counter() - t)
        assert code == 200, code
    # a failure verdict costs Q3-Q6 (Q6: up to 96 tokens of free text from a random model) on top of Q1-Q2
    return {
        "p50_ms": round(1000 * float(np.percentile(ts, 50)), 1),
        "p95_ms": round(1000 * float(np.percentile(ts, 95)), 1),
        "requests": n,
        "grids_with_failure_verdict": f"{sum(verdicts)}/{len(grids)}",
    }


def throughput(url: str, grids: list[bytes], clients: int, seconds: float) -> dict[str, float]:
    done, errors = [0] * clients, [0] * clients
    stop = time.perf_counter() + seconds

    def run(k: int) -> None:
        c = DiagnosisClient(url)
        i = 0
        while time.perf_counter() < stop:
            code, _ = c.post_form([("grid", ("g.png", grids[(k + i) % len(grids)], "image/png"))])
            i += 1
            if code == 200:
                done[k] += 1
            else:
                errors[k] += 1

    wall = in_threads(run, clients)  # includes the requests in flight at the deadline
    return {
        "clients": clients,
        "diagnoses_per_s": round(sum(done) / wall, 2),
        "diagnoses": sum(done),
        "errors": sum(errors),
        "seconds": round(wall, 1),
    }


def malformed_parts(kind: int, grid: bytes) -> tuple[list[Part], int]:
    from PIL import Image

    if kind == 0:
        return [("grid", ("x.png", b"not an image at all", "image/png"))], 400
    if kind == 1:
        return [("task", "no image here")], 400
    if kind == 2:
        return [("grid", ("g.png", grid, "image/png")), ("prefix", "-3")], 400
    if kind == 3:
        return [("grid", ("g.png", grid, "image/png")), ("colour", "red")], 400
    bomb = io.BytesIO()
    Image.new("1", (9000, 5000)).save(bomb, format="PNG")
    return [("grid", ("bomb.png", bomb.getvalue(), "image/png"))], 413


def load_run(
    server: ServerProcess, grids: list[bytes], requests: int, clients: int, malformed: float
) -> dict[str, Any]:
    rng = np.random.default_rng(1)
    bad = set(rng.choice(requests, int(round(requests * malformed)), replace=False).tolist())
    bad_parts = [malformed_parts(k, grids[0]) for k in range(5)]
    before = DiagnosisClient(server.url).health()["diagnoses"]
    replies: dict[int, list[tuple[int, Any]]] = {i: [] for i in range(requests)}
    failures: list[str] = []
    lock = threading.Lock()

    def run(k: int) -> None:
        c = DiagnosisClient(server.url)
        for i in range(k, requests, clients):
            parts, _ = (
                bad_parts[i % 5]
                if i in bad
                else ([("grid", ("g.png", grids[i % len(grids)], "image/png")), ("task", f"load request {i}")], 200)
            )
            try:
                got = c.post_form(parts)
            except OSError as e:  # a lost reply
                with lock:
                    failures.append(f"{i}: {type(e).__name__}")
                c.close()
                continue
            with lock:
                replies[i].append(got)

    wall = in_threads(run, clients)
    ok = wrong = rejected = 0
    for i, rs in replies.items():
        if len(rs) != 1:
            continue
        code, body = rs[0]
        if i in bad:
            want = bad_parts[i % 5][1]
            good = code == want and isinstance(body, dict) and set(body) == {"error"} and "\n" not in body["error"]
            rejected += good
            wrong += not good
        elif code == 200 and body.get("task") == f"load request {i}":
            ok += 1
        else:
            wrong += 1
    h = DiagnosisClient(server.url).health()
    return {
        "requests": requests,
        "clients": clients,
        "malformed_sent": len(bad),
        "answered_ok": ok,
        "rejected_4xx": rejected,
        "wrong_or_crossed": wrong,
        "lost": sum(1 for rs in replies.values() if not rs),
        "duplicated": sum(1 for rs in replies.values() if len(rs) > 1),
        "transport_errors": len(failures),
        "diagnoses_counted_by_server": h["diagnoses"] - before,
        "server_alive": h["status"] == "ok",
        "all_accounted_for": ok + rejected == requests and h["diagnoses"] - before == requests - len(bad),
        "seconds": round(wall, 1),
        "requests_per_s": round(requests / wall, 1),
        "largest_batch": h["largest_batch"],
    }


def check(a: Any) -> tuple[tuple[int, int], list[int]]:
    """Every setting, one-line errors; returns the grid's (W, H) and the throughput levels."""

    def number(key: str, low: float, integer: bool = False, strict: bool = True) -> None:
        v = a[key]
        ok = isinstance(v, int) if integer else isinstance(v, (int, float))
        if isinstance(v, bool) or not ok or (v <= low if strict else v < low):
            raise ConfigError(
                f"{key}: expected {'an integer' if integer else 'a number'} "
                f"{'>' if strict else '>='} {low:g}, got {v!r}"
            )

    if a.model is not None and not isinstance(a.model, str):
        raise ConfigError(f"model: expected a folder path, got {a.model!r}")
    w, h = size_setting("grid", a.grid, "512x512")
    try:
        levels = [int(x) for x in str(a.clients).split(",")]
    except ValueError:
        levels = []
    if not levels or min(levels) < 1:
        raise ConfigError(f"clients: expected positive client counts, comma-separated (e.g. 1,4,16), got {a.clients!r}")
    number("seconds", 0)
    number("max_batch", 0, integer=True)
    number("max_wait_ms", 0, strict=False)
    number("load_requests", 0, integer=True, strict=False)
    number("load_clients", 0, integer=True)
    number("malformed", 0, strict=False)
    if a.malformed > 1:
        raise ConfigError(f"malformed: expected a share between 0 and 1, got {a.malformed!r}")
    return (w, h), levels


def main(argv: list[str]) -> int:
    a = load_config(DEFAULTS, argv)
    (w, h), levels = check(a)
    import torch

    from labrobfail_vlm.io import write_report

    model = a.model
    tmp = Path(tempfile.mkdtemp())
    if model is None:
        from labrobfail_vlm.model.tiny import build_tiny

        model = str(build_tiny(tmp / "tiny"))
    grids = grid_parts((w, h))
    res: dict[str, Any] = {
        "model": "tiny (random)" if a.model is None else a.model,
        "grid": f"{w}x{h}",
        "cpu_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "load_average_start": os.getloadavg()[0],
    }
    t0 = time.perf_counter()
    runs = [("batched", [f"max_batch={a.max_batch}"]), ("unbatched", ["max_batch=1"])]
    if a.load_requests:
        # every load request carries its own task text, which flips the random model's Q2 verdict for many of
        # them; Q6 template mode keeps a failure verdict at a few forward calls (free text would run 96 tokens)
        runs.append(("load_run", [f"max_batch={a.max_batch}", "q6_mode=template"]))
    for name, args in runs:
        s = ServerProcess(model, tmp / f"{name}.log", *args, f"max_wait_ms={a.max_wait_ms}")
        try:
            row: dict[str, Any] = {"server_args": " ".join(args)}
            if name == "load_run":
                row.update(load_run(s, grids, a.load_requests, a.load_clients, a.malformed))
            else:
                if name == "batched":
                    row["latency"] = latency(s.url, grids)
                row["throughput"] = [throughput(s.url, grids, c, a.seconds) for c in levels]
            row["peak_rss_mb"] = s.peak_rss_mb()
            row["exit_code"] = s.stop()
        finally:
            if s.proc.poll() is None:
                s.proc.kill()
        res[name] = row
        print(json.dumps({name: row}), flush=True)
    res["speedup_batching_at_16"] = round(
        res["batched"]["throughput"][-1]["diagnoses_per_s"] / res["unbatched"]["throughput"][-1]["diagnoses_per_s"], 2
    )
    res["load_average_end"] = os.getloadavg()[0]
    res["total_s"] = round(time.perf_counter() - t0, 1)
    return write_report(a.out, res)


if __name__ == "__main__":
    cli_main(main, __doc__)
