"""Diagnose through an OpenAI-compatible server (vLLM serving a merged checkpoint) instead of a local model.

    from labrobfail_vlm.endpoint import EndpointAnalyzer
    fa = EndpointAnalyzer("http://127.0.0.1:8000/v1")          # the model: the one the server lists
    print(fa.analyze(grid_image, task="pick up the small beaker").to_json())

The same questions, in the same order and with the same Q2-consistency as FailureAnalyzer (analyzer.plan_reply),
one chat request each: the grid image first, the question after it, so the server's prefix cache holds the
image and preamble after the first question. Closed-set replies go through vLLM's structured outputs
(`{"structured_outputs": {"choice": [...]}}`; Q1 as a regex over the eight actions), Q6 is free text (or a
choice among the filled correction templates in template mode); replies are mapped to the bench's canonical
answers by labrobfail_vlm.bench.parse. Grids are diagnosed `concurrency` at a time in `answers_batch`.
"""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Collection, Sequence

from PIL import Image

from labrobfail_vlm import questions as Q
from labrobfail_vlm.analyzer import Q6_MODES, Ask, FailureAnalyzer, asked_dims, batch_settings, plan_reply
from labrobfail_vlm.bench.parse import parse
from labrobfail_vlm.grid import GridConfig
from labrobfail_vlm.llm_client import ChatClient, image_data_url
from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS

_ACTION = "(" + "|".join(map(re.escape, ATOMIC_ACTIONS)) + ")"
ACTIONS_REGEX = f"{_ACTION}(, {_ACTION}){{0,11}}"  # Q1: 1-12 actions, as the local decoder builds them
TRANSPORT_ERRORS = (OSError, ValueError, KeyError, IndexError, TypeError)


class EndpointError(ValueError):
    """The endpoint could not be reached or answered in an unexpected format (one line, no key in it)."""


class EndpointAnalyzer(FailureAnalyzer):
    """FailureAnalyzer's API (answers, answers_batch, analyze, analyze_batch) with the model behind HTTP.

    `grid`: the layout the served model was trained on (frames lists are composed in it; Q3 asks 1..max_frames
    unless `frames` is given). `one_pass` arguments are accepted and ignored: every question is its own request
    and the server's prefix cache shares the image between them."""

    failure_score = "q2"  # the server's replies come without option scores: Q2's reply is the verdict

    def __init__(
        self,
        base_url: str,
        model: str | None = None,
        api_key_env: str = "OPENAI_API_KEY",
        timeout_s: float = 120.0,
        grid: GridConfig = GridConfig(),
        q6_mode: str = "free",
        concurrency: int = 8,
        max_tokens: int = 96,
    ):
        if q6_mode not in Q6_MODES:
            raise ValueError(f"q6_mode: expected one of {', '.join(Q6_MODES)}, got {q6_mode!r}")
        self.q6_mode, self.grid = q6_mode, grid
        self.num_frames, self.time_axis, self.index = grid.max_frames, grid.time_axis, grid.draw_index
        self.concurrency, self.max_tokens = max(1, int(concurrency)), int(max_tokens)
        self.client = ChatClient(base_url, model or "", api_key_env, timeout_s)
        if not model:
            self.client.model = self._served_model()

    def __repr__(self) -> str:
        return f"EndpointAnalyzer({self.client.base!r}, model={self.client.model!r})"

    def _served_model(self) -> str:
        try:
            names = self.client.models()
        except TRANSPORT_ERRORS as e:
            raise EndpointError(f"endpoint: cannot list models at {self.client.base}/models ({_why(e)})") from None
        if len(names) != 1:
            raise EndpointError(
                f"endpoint: the server lists {len(names)} models ({', '.join(names[:5])}); "
                "name one (--endpoint-model / endpoint_model=)"
            )
        return names[0]

    def _ask(self, image_url: str, question: str, ask: Ask) -> str:
        content = [{"type": "image_url", "image_url": {"url": image_url}}, {"type": "text", "text": question}]
        extra: dict[str, Any] = {}
        if ask.kind == "choose":
            extra["structured_outputs"] = {"choice": list(ask.options)}
        elif ask.kind == "actions":
            extra["structured_outputs"] = {"regex": ACTIONS_REGEX}
        err: BaseException | None = None
        for _ in range(2):  # one retry for a dropped connection
            try:
                return self.client.chat([{"role": "user", "content": content}], 0.0, self.max_tokens, **extra)
            except TRANSPORT_ERRORS as e:
                err = e
        raise EndpointError(f"endpoint: request to {self.client.url} failed ({_why(err)})")

    def answers(
        self,
        image: Image.Image,
        task: str,
        one_pass: bool = True,
        frames: int | None = None,
        objects: Sequence[str] = (),
        dims: Collection[str] = Q.DIMENSIONS,
    ) -> dict[str, str]:
        frames = frames or self.num_frames
        url = image_data_url(image)
        out: dict[str, str] = {}
        failed: bool | None = None
        need = asked_dims(dims, self.q6_mode)
        for dim in Q.DIMENSIONS:
            if dim not in need:
                continue
            p = plan_reply(dim, failed, frames, objects, self.q6_mode, out)
            if isinstance(p, Ask):
                text = Q.question_text(dim, 0, task, self.time_axis, self.index)
                reply = self._ask(url, text.removeprefix("<image>\n"), p)
                p = _canonical(dim, reply, p)
            out[dim] = p
            if dim == "Q2":
                failed = p == "Yes"
        return out

    def answers_batch(
        self,
        images: Sequence[Image.Image],
        tasks: Sequence[str],
        frames: Sequence[int | None] | None = None,
        objects: Sequence[Sequence[str]] | None = None,
        dims: Sequence[Collection[str]] | None = None,
        max_batch: int | None = None,
    ) -> list[dict[str, str]]:
        """`answers` for many grids, `concurrency` (or `max_batch`) grids in flight at once."""
        n = len(images)
        frames, objects, dims = batch_settings(n, tasks, frames, objects, dims)
        with ThreadPoolExecutor(max(1, min(n, max_batch or self.concurrency))) as pool:
            jobs = [
                pool.submit(self.answers, images[i], tasks[i], True, frames[i], objects[i], dims[i]) for i in range(n)
            ]
            return [j.result() for j in jobs]


def _canonical(dim: str, reply: str, ask: Ask) -> str:
    """A reply in the bench's canonical form: a choice as given, free text stripped, anything else parsed
    (a server without structured outputs may answer in words); other unparseable text is kept for the log and
    scores as wrong. Q2's is an EndpointError: kept, it would read as "no failure" and settle Q3-Q6 with it."""
    text = (reply or "").strip()
    if ask.kind == "free" or (ask.kind == "choose" and text in ask.options):
        return text
    got = parse(dim, text)
    if dim == "Q2" and got not in ask.options:
        raise EndpointError(f"endpoint: the model's reply to Q2 is neither Yes nor No: {text[:80]!r}")
    return got or text


def _why(e: BaseException | None) -> str:
    msg = str(e).splitlines()[0][:160] if e is not None and str(e) else ""
    return f"{type(e).__name__}: {msg}" if msg else type(e).__name__
