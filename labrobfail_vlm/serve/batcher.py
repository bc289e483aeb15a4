"""Queue requests and run them in batches on one model thread.

The first request that arrives opens a batch; the batch closes when it holds `max_batch` requests or
`max_wait_s` after it opened, whichever comes first, and the model thread runs it while the next one fills.
Each request gets exactly its own result: results come back in the order of the batch. When a batch
fails as a whole, each of its requests is run alone, so one bad request cannot fail its neighbours.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Generic, Sequence, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_STOP = object()


class Busy(RuntimeError):
    """The queue is full, or the service is shutting down (a 503 for the client)."""


@dataclass
class BatchStats:
    batches: int = 0
    items: int = 0
    largest: int = 0
    failed: int = 0


class Batcher(Generic[T, R]):
    def __init__(
        self, run: Callable[[list[T]], Sequence[R]], max_batch: int = 8, max_wait_s: float = 0.01, max_queue: int = 1024
    ):
        if max_batch < 1 or max_wait_s < 0 or max_queue < 1:
            raise ValueError("batcher: max_batch and max_queue must be >= 1 and max_wait_s >= 0")
        self.run, self.max_batch, self.max_wait_s, self.max_queue = run, max_batch, max_wait_s, max_queue
        self.stats = BatchStats()
        self._queue: asyncio.Queue[Any] | None = None
        self._task: asyncio.Task[None] | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._closing = False

    @property
    def queued(self) -> int:
        return self._queue.qsize() if self._queue is not None else 0

    async def start(self) -> None:
        self._queue = asyncio.Queue()
        # one thread owns the model: torch uses its own threads inside, and the model keeps per-call state
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="labrobfail-model")
        self._task = asyncio.create_task(self._loop())

    async def submit(self, item: T) -> R:
        if self._queue is None or self._closing:
            raise Busy("the service is shutting down")
        if self._queue.qsize() >= self.max_queue:
            raise Busy(f"the queue is full ({self.max_queue} requests waiting); retry later")
        fut: asyncio.Future[R] = asyncio.get_running_loop().create_future()
        self._queue.put_nowait((item, fut))
        return await fut

    async def stop(self) -> None:
        """Finish everything queued so far, then stop the model thread."""
        self._closing = True
        if self._queue is not None and self._task is not None:
            self._queue.put_nowait(_STOP)
            await self._task
        if self._pool is not None:
            self._pool.shutdown(wait=True)

    async def _next_batch(self) -> tuple[list[tuple[T, asyncio.Future[R]]], bool]:
        assert self._queue is not None
        loop = asyncio.get_running_loop()
        first = await self._queue.get()
        if first is _STOP:
            return [], True
        batch = [first]
        deadline = loop.time() + self.max_wait_s
        while len(batch) < self.max_batch:
            try:
                left = deadline - loop.time()
                nxt = self._queue.get_nowait() if left <= 0 else await asyncio.wait_for(self._queue.get(), left)
            except (asyncio.QueueEmpty, asyncio.TimeoutError):
                break
            if nxt is _STOP:
                return batch, True
            batch.append(nxt)
        return batch, False

    async def _loop(self) -> None:
        loop = asyncio.get_running_loop()
        stop = False
        while not stop:
            batch, stop = await self._next_batch()
            live = [(x, f) for x, f in batch if not f.done()]  # a client that went away was cancelled
            if not live:
                continue
            results = await loop.run_in_executor(self._pool, self._run_each, [x for x, _ in live])
            self.stats.batches += 1
            self.stats.items += len(live)
            self.stats.largest = max(self.stats.largest, len(live))
            for (_, fut), res in zip(live, results):
                if fut.done():
                    continue
                if isinstance(res, BaseException):
                    self.stats.failed += 1
                    fut.set_exception(res)
                else:
                    fut.set_result(res)

    def _run_each(self, items: list[T]) -> list[R | BaseException]:
        err: BaseException
        try:
            out = list(self.run(items))
            if len(out) == len(items):
                return out
            err = RuntimeError(f"batch returned {len(out)} results for {len(items)} requests")
        except Exception as e:  # noqa: BLE001 - reported to the request(s) it belongs to
            err = e
        if len(items) == 1:
            return [err]
        return [r for it in items for r in self._run_each([it])]  # isolate the request that failed the batch
