"""A curriculum for a model trained from scratch: which records share a batch, and in which wording.

A pretrained LM reads negation for free; a randomly initialised one does not. Two of the five Q2 wordings ask
about success ("Does the robot successfully complete...?"), so for a from-scratch model the Q2 answer is the
XOR of "the grid shows a failure" and the wording's polarity, and a gradient that must learn both at once
has nothing to climb (the image feature helps only once the polarity is read, and the other way round).
Two levers, off by default and set by the tiny preset (configs/train.yaml, `curriculum`):

- `pairs`: the two trajectories of a success/failure pair (same scenario, seed and initial state) go into one
  micro-batch and are asked the same wording. The text is then identical inside the pair and only the image
  can tell the two answers apart.
- `polarity_warmup`: for this fraction of the optimizer steps, Q2 records are asked in one of the three
  failure-polarity wordings ("Is there any error...?"), so "Yes" always means a failure while the image
  feature forms; afterwards every record keeps its dataset wording (all five, as the benchmark asks).
- `detect_first`: for this fraction of the optimizer steps only the Q2 records carry loss (the others get
  weight 0). Trained on all six questions from the start, a random model settles on the text priors of
  Q1/Q3-Q6 and its Q2 stays at the majority answer; trained on Q2 alone it starts to read the grid. The
  other questions join once that image feature exists.

The benchmark is untouched: evaluation reads the test split as built. Rewording goes through
`questions.reask`, which recomputes a Q2 answer for the new polarity.
"""

from __future__ import annotations

import hashlib
import math
from typing import Any, Iterator, Sequence

import numpy as np
from torch.utils.data import Sampler
from transformers import TrainerCallback

from labrobfail_vlm import questions as Q

NEGATIVE_Q2 = [i for i, v in enumerate(Q.VARIANTS["Q2"]) if not v.positive]


def _stable(text: str) -> int:
    return int.from_bytes(hashlib.blake2s(text.encode(), digest_size=4).digest(), "little")


class PairSampler(Sampler[int]):
    """Record order in which both records of a (pair, question) unit sit in the same micro-batch.

    Units are shuffled per epoch (seeded); a pair that would straddle two micro-batches waits for the next one.
    """

    def __init__(self, ids: Sequence[str], group_of: dict[str, str], batch: int, seed: int = 0):
        units: dict[tuple[str, str, int], list[int]] = {}
        copies: dict[str, int] = {}  # an id drawn more than once an epoch (extra_repeat): each copy a unit of its own
        for i, rid in enumerate(ids):
            traj, copies[rid] = Q.traj_of(rid), copies.get(rid, -1) + 1
            units.setdefault((group_of.get(traj, traj), Q.dim_of(rid), copies[rid]), []).append(i)
        self.units = list(units.values())
        self.batch, self.seed, self.epoch = max(1, int(batch)), int(seed), 0
        self.n = len(ids)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[int]:
        rng = np.random.default_rng([self.seed, self.epoch])
        order: list[int] = []
        cur: list[int] = []
        held: list[list[int]] = []
        for k in rng.permutation(len(self.units)):
            unit = self.units[int(k)]
            if len(cur) + len(unit) > self.batch and len(unit) <= self.batch:
                held.append(unit)
                continue
            cur += unit
            while len(cur) >= self.batch:
                order += cur[: self.batch]
                cur = cur[self.batch :]
                while held and len(cur) + len(held[0]) <= self.batch:
                    cur += held.pop(0)
        order += cur + [i for u in held for i in u]
        return iter(order)


class Rewording:
    """Applied by the collator to each micro-batch: twins share a wording; Q2 polarity warm-up."""

    def __init__(self, group_of: dict[str, str], pairs: bool):
        self.group_of, self.pairs = group_of, pairs
        self.negative_only = False  # set by PolarityWarmup
        self.detect_only = False  # set by DetectFirst: records other than Q2 get loss weight 0

    def __call__(self, batch: list[dict[str, Any]]) -> list[dict[str, Any]]:
        chosen: dict[tuple[str, str], int] = {}
        out = []
        for b in batch:
            dim, traj = Q.dim_of(b["id"]), Q.traj_of(b["id"])
            if self.detect_only and dim != "Q2":
                b = {**b, "weight_scale": 0.0}
            v = Q.variant_of(dim, b["question"]) if dim in Q.VARIANTS else None
            if v is None:  # an auxiliary fact, or a wording of no known variant
                out.append(b)
                continue
            key = (self.group_of.get(traj, traj), dim)
            if self.pairs and key in chosen:
                v = chosen[key]
            elif self.negative_only and dim == "Q2" and Q.VARIANTS["Q2"][v].positive:
                v = NEGATIVE_Q2[_stable(key[0]) % len(NEGATIVE_Q2)]
            chosen[key] = v
            q, a = Q.reask(dim, b["question"], b["answer"], v)
            out.append({**b, "question": q, "answer": a})
        return out


class Phase(TrainerCallback):
    """Sets the Rewording's `flag` for the first `fraction` of the optimizer steps, clears it after."""

    flag = ""

    def __init__(self, rewording: Rewording, fraction: float):
        self.rewording, self.fraction = rewording, float(fraction)

    def on_step_begin(self, args, state, control, **kwargs):  # noqa: D102
        setattr(self.rewording, self.flag, state.global_step < self.fraction * max(1, state.max_steps))

    on_train_begin = on_step_begin


class PolarityWarmup(Phase):
    """Q2 in failure-polarity wordings only."""

    flag = "negative_only"


class DetectFirst(Phase):
    """Loss on Q2 records only."""

    flag = "detect_only"


class AugmentEpoch(TrainerCallback):
    """Tells the grid augmentation (train/data.GridAugment) which VQA epoch is beginning: its draws are seeded by it.
    A resumed run begins inside an epoch (state.epoch 2.37 is epoch 2); the small term keeps an epoch's float end
    (state.epoch after its last step) from reading as the one before."""

    def __init__(self, augment: Any):
        self.augment = augment

    def on_epoch_begin(self, args, state, control, **kwargs):  # noqa: D102
        self.augment.epoch = (1, math.floor(float(state.epoch or 0) + 1e-6))
