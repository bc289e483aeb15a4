"""Where one diagnosis spends its time: image preprocessing, prompt building and tokenization, the vision
encoder, the language-model prefill, the six question suffixes, answer decoding (the candidate trie, Q1, Q6)
and the rest (Python overhead).

Run as:
    python scripts/profile_infer.py [model=DIR] [grid=1536x768] [batch=8] [repeats=5]
                                    [out=outputs/profile_infer.json]

Wall-clock timers wrap the analyzer's own components on this instance only (no profiler overhead), in one
pass, in six-prompt mode and per grid of a batch (`answers_batch` of `batch` grids). Same grid as bench_infer.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from labrobfail_vlm.config import ConfigError, cli_main, load_config, size_setting

DEFAULTS = """
model: null                      # model folder to profile; null = a tiny random model, built on the fly
repeats: 5                       # timed repeats of each mode (after one warm-up)
grid: 1536x768                   # grid size WxH, px
batch: 8                         # grids per answers_batch call in the batch row
out: outputs/profile_infer.json  # the JSON result
"""


class Sections:
    """Exclusive wall time per section: a section nested in another is subtracted from its parent."""

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.stack: list[list[Any]] = []  # [name, start, child time]

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        self.stack.append([name, time.perf_counter(), 0.0])
        try:
            yield
        finally:
            n, t0, child = self.stack.pop()
            dt = time.perf_counter() - t0
            self.total[n] += dt - child
            if self.stack:
                self.stack[-1][2] += dt

    def wrap(self, obj: Any, attr: str, name: str | Callable[..., str]) -> None:
        fn = getattr(obj, attr)

        def timed(*a: Any, **k: Any) -> Any:
            with self(name(*a, **k) if callable(name) else name):
                return fn(*a, **k)

        setattr(obj, attr, timed)


def instrument(fa: Any, s: Sections) -> None:
    dec, proc = fa.decoder, fa.processor
    s.wrap(dec.lm.model, "get_image_features", "vision encoder")
    s.wrap(proc.image_processor, "preprocess", "image preprocessing")
    # `processor(...)` looks __call__ up on the type: time it through a subclass of this instance only
    call = type(proc).__call__
    sub = type("Timed" + type(proc).__name__, (type(proc),), {})
    sub.__call__ = lambda self, *a, **k: _timed(s, "processor (tokenize + image)", call, self, *a, **k)
    proc.__class__ = sub
    s.wrap(fa, "_prompt", "prompt text (chat template)")
    s.wrap(dec, "prompt_ids", "tokenize")
    s.wrap(dec, "prefill", "LM prefill (image + preamble)")
    decoding = ("answer decoding", "python: answer logic")
    # an extend outside answer decoding feeds a question's own tokens after the shared prefix
    s.wrap(
        dec,
        "extend_rows",
        lambda *a, **k: "answer decoding" if s.stack and s.stack[-1][0] in decoding else "question suffixes",
    )
    s.wrap(fa, "_decode", "python: answer logic")
    for f in ("score_rows", "actions_rows", "free_tokens_rows"):
        s.wrap(dec, f, "answer decoding")


def _timed(s: Sections, name: str, fn: Callable[..., Any], *a: Any, **k: Any) -> Any:
    with s(name):
        return fn(*a, **k)


def main(argv: list[str]) -> int:
    a = load_config(DEFAULTS, argv)
    for key in ("repeats", "batch"):
        v = a[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"{key}: expected an integer >= 1, got {v!r}")
    if a.model is not None and not isinstance(a.model, str):
        raise ConfigError(f"model: expected a folder path, got {a.model!r}")
    w, h = size_setting("grid", a.grid, "1536x768")
    import torch

    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.io import write_report

    model = a.model
    if model is None:
        from labrobfail_vlm.model.tiny import build_tiny

        model = str(build_tiny(Path(tempfile.mkdtemp()) / "tiny"))
    fa = FailureAnalyzer.from_pretrained(model)
    from PIL import Image

    rng = np.random.default_rng(0)
    grid = Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    batch = [Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)) for _ in range(a.batch)]
    task = "pick up the small beaker"
    res: dict[str, Any] = {
        "model": "tiny (random)" if a.model is None else a.model,
        "grid": f"{w}x{h}",
        "threads": torch.get_num_threads(),
        "load_average": os.getloadavg()[0],
        "modes": {},
    }
    s = Sections()
    instrument(fa, s)
    runs = {
        "one_pass": (lambda: [fa.answers(grid, task)], 1),
        "six_prompts": (lambda: [fa.answers(grid, task, one_pass=False)], 1),
        f"batch_{a.batch}_per_grid": (lambda: fa.answers_batch(batch, [task] * a.batch), a.batch),
    }
    for mode, (run, n) in runs.items():
        run()  # warm-up
        s.total.clear()
        t = time.perf_counter()
        for _ in range(a.repeats):
            with s("other (python)"):
                ans = run()
        k = a.repeats * n
        per = {x: round(v / k * 1000, 1) for x, v in sorted(s.total.items(), key=lambda kv: -kv[1])}
        res["modes"][mode] = {
            "wall_ms": round((time.perf_counter() - t) / k * 1000, 1),
            "sections_ms": per,
            "q2": [x["Q2"] for x in ans],
        }
    return write_report(a.out, res)


if __name__ == "__main__":
    cli_main(main, __doc__)
