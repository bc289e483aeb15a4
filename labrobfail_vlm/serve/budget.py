"""The decoded-image memory budget shared by all requests of one server.

A request reserves, before it decodes anything, the most memory its images will take (priced from their headers:
labrobfail_vlm.serve.form.plan) and keeps the reservation until its reply is sent: the decoded grid waits in the
batch queue and the model thread works on copies of it, so that is held memory too. Once decoding is over, the
reservation shrinks to what the request still holds. A request that finds the budget full waits up to `wait_s`,
then gets a 503 (Busy), so any number of concurrent worst-case uploads holds at most `total` bytes of images.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

from labrobfail_vlm.serve.batcher import Busy


def mb(n: int) -> str:
    return f"{n / (1 << 20):,.1f} MiB"


@dataclass
class DecodeBudget:
    total: int
    used: int = 0
    peak: int = 0
    _cond: asyncio.Condition = field(default_factory=asyncio.Condition, repr=False)

    async def reserve(self, n: int, wait_s: float) -> "Reservation":
        """`n` bytes (n <= total: the per-request limit is checked first), waiting at most `wait_s` for them."""
        if n > self.total:
            raise ValueError(f"decode budget: {n} bytes asked of a {self.total} byte budget")
        async with self._cond:
            try:
                await asyncio.wait_for(self._cond.wait_for(lambda: self.used + n <= self.total), wait_s)
            except asyncio.TimeoutError:
                raise Busy(
                    f"busy: other uploads hold {mb(self.used)} of the {mb(self.total)} image-decoding "
                    f"budget and {mb(n)} more was needed for {wait_s:g} s; retry later"
                ) from None
            self.used += n
            self.peak = max(self.peak, self.used)
        return Reservation(self, n)

    async def _give_back(self, n: int) -> None:
        async with self._cond:
            self.used -= n
            self._cond.notify_all()


@dataclass
class Reservation:
    budget: DecodeBudget
    n: int

    async def shrink(self, to: int) -> None:
        """Keep only `to` bytes (what stays in memory after decoding: the grid)."""
        if to < self.n:
            give, self.n = self.n - max(0, to), max(0, to)
            await self.budget._give_back(give)

    async def release(self) -> None:
        await self.shrink(0)
