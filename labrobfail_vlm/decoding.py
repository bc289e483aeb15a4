"""Structured decoding of the six answers: closed sets by exact scoring, free text by greedy decoding.

Closed-set answers (Yes/No; 1-4; 1-5; a frame within the grid; actions from the 8
primitives) are chosen by comparing the model's log-likelihood of every admissible answer
(followed by the end-of-turn token), so the reply is always one of the allowed strings.
Q1 is built greedily one action at a time from the same 8 candidates. Q6 is free text (greedy, no repeated
3-gram, stops at the end of turn), or in template mode the most likely of the paper's correction strategies
with their placeholders filled from the scene's object names (labrobfail_vlm.corrections.candidates).

One-pass mode prefills the image and preamble once; each question then continues from that
KV cache (cropped back after use) instead of re-encoding the image six times. The cached
and uncached paths see the same token ids at the same positions, so they pick the same
answers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import torch

from labrobfail_vlm import questions as Q
from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS


@dataclass
class Prefix:
    """Model state after a token sequence: the cache and the logits of its last position."""

    cache: Any
    length: int
    last_logits: torch.Tensor


class Decoder:
    def __init__(self, model: Any, processor: Any, max_new_tokens: int = 96, no_repeat_ngram: int = 3):
        self.model, self.proc = model, processor
        self.no_repeat_ngram = no_repeat_ngram
        self.tok = processor.tokenizer
        self.eos = self.tok.convert_tokens_to_ids("<|im_end|>")
        self.max_new_tokens = max_new_tokens
        self.device = next(model.parameters()).device

    # ---- low-level -------------------------------------------------------------------------------------
    def encode_ids(self, text: str) -> list[int]:
        return self.tok(text, add_special_tokens=False)["input_ids"]

    @torch.no_grad()
    def prefill(self, inputs: dict[str, torch.Tensor]) -> Prefix:
        from transformers import DynamicCache

        cache = DynamicCache()
        inputs = {k: v.to(self.device) for k, v in inputs.items()}
        out = self.model(**inputs, past_key_values=cache, use_cache=True)
        return Prefix(out.past_key_values, int(inputs["input_ids"].shape[1]), out.logits[0, -1].float())

    @torch.no_grad()
    def extend(self, pre: Prefix, ids: Sequence[int]) -> tuple[Prefix, torch.Tensor]:
        """Feed ids after `pre` (mutating its cache); returns the new prefix and logits for every fed position."""
        if not ids:
            return pre, pre.last_logits[None]
        x = torch.tensor([list(ids)], device=self.device)
        pos = torch.arange(pre.length, pre.length + len(ids), device=self.device)
        out = self.model(input_ids=x, past_key_values=pre.cache, use_cache=True, cache_position=pos)
        logits = out.logits[0].float()
        return Prefix(out.past_key_values, pre.length + len(ids), logits[-1]), logits

    def rewind(self, cur: Prefix, to: Prefix) -> Prefix:
        """Cut the shared cache of `cur` back to the earlier state `to` (same cache, shorter)."""
        if cur.length > to.length:  # transformers 5: a negative count removes that many trailing tokens
            cur.cache.crop(to.length - cur.length)
        return to

    def score_many(self, pre: Prefix, seqs: Sequence[Sequence[int]]) -> list[float]:
        """log p of each (non-empty) sequence after `pre`, walking them as a trie: a shared prefix is fed to
        the model once, and a run of tokens without a branch in one forward call."""
        out = [0.0] * len(seqs)
        self._walk(pre, [(i, list(s)) for i, s in enumerate(seqs)], out)
        return out

    def _walk(self, pre: Prefix, items: list[tuple[int, list[int]]], out: list[float]) -> None:
        lps = torch.log_softmax(pre.last_logits, -1)
        groups: dict[int, list[tuple[int, list[int]]]] = {}
        for i, s in items:
            out[i] += float(lps[s[0]])
            if len(s) > 1:
                groups.setdefault(s[0], []).append((i, s[1:]))
        for first, group in groups.items():
            rests = [r for _, r in group]
            k = 0  # tokens every sequence of the group shares after `first`
            while all(len(r) > k for r in rests) and len({r[k] for r in rests}) == 1:
                k += 1
            run = [first, *rests[0][:k]]
            ext, logits = self.extend(pre, run)
            idx = torch.tensor(run[1:], device=logits.device)[:, None]
            shared = float(torch.log_softmax(logits[:k], -1).gather(1, idx).sum()) if k else 0.0
            left = []
            for i, r in group:
                out[i] += shared
                if len(r) > k:
                    left.append((i, r[k:]))
            if left:
                self._walk(ext, left, out)
            self.rewind(ext, pre)

    # ---- answers ---------------------------------------------------------------------------------------
    def choose(self, pre: Prefix, candidates: Sequence[str]) -> str:
        """The candidate (followed by the end of turn) with the highest log-likelihood."""
        scores = self.score_many(pre, [self.encode_ids(c) + [self.eos] for c in candidates])
        return candidates[max(range(len(candidates)), key=scores.__getitem__)]

    def actions(self, pre: Prefix, max_actions: int = 12) -> str:
        chosen: list[str] = []
        cur = pre
        for _ in range(max_actions):
            opts = [(", " if chosen else "") + a for a in ATOMIC_ACTIONS]
            scores = self.score_many(cur, [self.encode_ids(o) for o in opts] + ([[self.eos]] if chosen else []))
            best = max(range(len(scores)), key=scores.__getitem__)
            if best == len(ATOMIC_ACTIONS):
                break
            chosen.append(ATOMIC_ACTIONS[best])
            cur, _ = self.extend(cur, self.encode_ids(opts[best]))
        self.rewind(cur, pre)
        return Q.format_actions(chosen)

    def free_text(self, pre: Prefix, avoid: Sequence[str] = ()) -> str:
        """Greedy text until the end of turn (see `free_tokens`)."""
        return self.tok.decode(self.free_tokens(pre, avoid), skip_special_tokens=True).strip()

    def free_tokens(self, pre: Prefix, avoid: Sequence[str] = ()) -> list[int]:
        """Greedy token ids until the end of turn; `avoid`: replies that must not be produced (their first tokens
        are barred at step one). No n-gram of `no_repeat_ngram` tokens is produced twice (a small model's greedy
        text otherwise loops: "...to secure the gripper to secure the gripper...")."""
        out: list[int] = []
        cur = pre
        barred = sorted({self.encode_ids(a)[0] for a in avoid if a})
        n = self.no_repeat_ngram
        for _ in range(self.max_new_tokens):
            logits = cur.last_logits.clone()
            if not out and barred:
                logits[barred] = float("-inf")
            if n and len(out) >= n - 1:
                tail = out[len(out) - n + 1:]
                seen = [out[i + n - 1] for i in range(len(out) - n + 1) if out[i:i + n - 1] == tail]
                if seen:
                    logits[seen] = float("-inf")
            t = int(logits.argmax())
            if t == self.eos:
                break
            out.append(t)
            cur, _ = self.extend(cur, [t])
        self.rewind(cur, pre)
        return out
