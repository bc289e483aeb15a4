"""Structured decoding of the six answers: closed sets by exact scoring, free text by greedy decoding.

Closed-set answers (Yes/No; 1-4; 1-5; a frame within the grid; actions from the 8
primitives) are chosen by comparing the model's log-likelihood of every admissible answer
(followed by the end-of-turn token), so the reply is always one of the allowed strings.
Q1 is built greedily one action at a time from the same 8 candidates. Q6 is free text (greedy, no repeated
3-gram, stops at the end of turn), or in template mode the most likely of the paper's correction strategies
with their placeholders filled from the scene's object names (labrobfail_vlm.corrections.candidates).

Every operation works on B >= 1 rows in lockstep (a batch of grids), and a single grid is the batch of one.
Rows grow by different numbers of tokens, so the cache holds holes: each row's real slots are in
`Prefix.mask`, and each new token gets its rope position explicitly (`Prefix.pos`, the row's own count
plus Qwen3-VL's rope delta for the image), so a row sees exactly the positions and tokens it would see
alone. Candidate answers are scored as a token tree in one forward call: every trie node attends to the
prefix and its own ancestors only (a custom 4-D attention mask), and the tree is cut off the cache again.

One-pass mode prefills the image and preamble once; each question then continues from that
KV cache (cropped back after use) instead of re-encoding the image six times.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Sequence

import numpy as np
import torch

from labrobfail_vlm import questions as Q
from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS


@dataclass
class Prefix:
    """Model state after one token sequence per row: the cache (`length` slots per row, `mask` marking each
    row's real tokens; holes are left padding and the padding of ragged extensions), the rope position of each
    row's next token, and the logits after each row's last real token."""

    cache: Any
    length: int
    last: torch.Tensor  # (B, V)
    mask: torch.Tensor  # (B, length) bool
    pos: torch.Tensor  # (B,) long

    @property
    def rows(self) -> int:
        return int(self.last.shape[0])

    @property
    def last_logits(self) -> torch.Tensor:
        """(V,) logits after the last token of a single-row prefix."""
        assert self.rows == 1, "last_logits: a single-row prefix only"
        return self.last[0]


class Decoder:
    def __init__(
        self, model: Any, processor: Any, max_new_tokens: int = 96, no_repeat_ngram: int = 3, logit_rows: int = 256
    ):
        self.model, self.proc = model, processor
        # peft keeps the LoRA layers inside the base model's modules, so its forward is the adapted model's
        self.lm = model.get_base_model() if hasattr(model, "get_base_model") else model
        self.no_repeat_ngram = no_repeat_ngram
        self.tok = processor.tokenizer
        self.eos = self.tok.convert_tokens_to_ids("<|im_end|>")
        self.image_id = self.tok.convert_tokens_to_ids(processor.image_token)
        pad = self.tok.pad_token_id
        self.pad = int(pad if pad is not None else self.eos)
        self.max_new_tokens = max_new_tokens
        self.logit_rows = logit_rows  # lm_head rows per call when scoring a tree (bounds memory at large vocabularies)
        self.device = next(model.parameters()).device
        self.dtype = next(model.parameters()).dtype
        self._ids = lru_cache(maxsize=16384)(self._tokenize)

    # ---- tokens ------------------------------------------------------------------------------------------
    def _tokenize(self, text: str) -> tuple[int, ...]:
        return tuple(self.tok(text, add_special_tokens=False)["input_ids"])

    def encode_ids(self, text: str) -> list[int]:
        return list(self._ids(text))

    def prompt_ids(self, text: str, image_tokens: int) -> list[int]:
        """Token ids of a chat prompt whose image placeholder stands for `image_tokens` visual tokens, as the
        processor tokenizes it. Special tokens split the text before BPE, so the parts around the placeholder
        are tokenized (and cached) alone instead of a string with ~1,000 placeholders per prompt."""
        before, after = text.split(self.proc.image_token, 1)
        return [*self._ids(before), *[self.image_id] * image_tokens, *self._ids(after)]

    # ---- model state -------------------------------------------------------------------------------------
    @torch.no_grad()
    def prefill(self, inputs: dict[str, torch.Tensor]) -> Prefix:
        """Run a processor-style batch (input_ids, attention_mask with left padding, pixel values, ...)."""
        from transformers import DynamicCache

        inputs = {k: v.to(self.device) for k, v in inputs.items()}
        ids = inputs["input_ids"]
        mask = inputs.get("attention_mask")
        mask = torch.ones_like(ids, dtype=torch.bool) if mask is None else mask.bool()
        inner = getattr(self.lm, "model", None)
        if inner is not None and hasattr(inner, "rope_deltas"):
            inner.rope_deltas = None  # model state left by the last call: this prefill sets its own
        out = self.lm(**inputs, past_key_values=DynamicCache(), use_cache=True, logits_to_keep=1)
        # Qwen3-VL's rope delta of each row (the image takes fewer positions than tokens), set by this prefill
        delta = getattr(inner, "rope_deltas", None)
        pos = mask.sum(1) + (delta.view(-1).to(self.device) if delta is not None else 0)
        return Prefix(out.past_key_values, int(ids.shape[1]), out.logits[:, -1].float(), mask, pos.long())

    def prefill_rows(
        self, rows: Sequence[Sequence[int]], pixel_values: torch.Tensor, image_grid_thw: torch.Tensor
    ) -> Prefix:
        """Prefill token sequences (one image each, in order), left-padded to one length."""
        n = max(len(r) for r in rows)
        ids = torch.full((len(rows), n), self.pad, dtype=torch.long)
        mask = torch.zeros((len(rows), n), dtype=torch.long)
        for i, r in enumerate(rows):
            ids[i, n - len(r) :] = torch.tensor(list(r), dtype=torch.long)
            mask[i, n - len(r) :] = 1
        return self.prefill(
            {
                "input_ids": ids,
                "attention_mask": mask,
                "pixel_values": pixel_values,
                "mm_token_type_ids": (ids == self.image_id).int(),
                "image_grid_thw": image_grid_thw,
            }
        )

    @torch.no_grad()
    def _forward(
        self, pre: Prefix, chunks: Sequence[Sequence[int]], parents: Sequence[Sequence[int]] | None = None
    ) -> torch.Tensor:
        """Feed one chunk of tokens per row after `pre` (appending to its cache); hidden states (B, m, H).

        `parents[i][j]`: the chunk index token j follows (-1: the prefix); None means a plain run (j - 1). A token
        attends to the row's real prefix slots and its own ancestors; shorter rows are padded with tokens that
        nothing attends to."""
        tok, tree, depth = _tree_inputs(chunks, parents, self.pad)
        b, m = tok.shape
        allowed = torch.cat(
            [pre.mask[:, None, :].expand(b, m, pre.length), torch.from_numpy(tree).to(self.device)], dim=2
        )[:, None]
        mask4 = torch.zeros(allowed.shape, dtype=self.dtype, device=self.device)
        mask4.masked_fill_(~allowed, torch.finfo(self.dtype).min)
        pos = pre.pos[:, None] + torch.from_numpy(depth).to(self.device)
        out = self.lm.model(
            input_ids=torch.from_numpy(tok).to(self.device),
            attention_mask=mask4,
            position_ids=pos[None].expand(3, b, m),
            past_key_values=pre.cache,
            use_cache=True,
        )
        return out.last_hidden_state

    @torch.no_grad()
    def _logits(self, hidden: torch.Tensor) -> torch.Tensor:
        return self.lm.lm_head(hidden).float()

    def extend_rows(
        self, pre: Prefix, seqs: Sequence[Sequence[int]], all_logits: bool = False
    ) -> tuple[Prefix, torch.Tensor | None]:
        """Feed `seqs[i]` after row i (mutating the shared cache; an empty sequence leaves the row as it is).
        Returns the new prefix and, with `all_logits`, the logits (B, m, V) of every fed position."""
        lens = [len(s) for s in seqs]
        if not max(lens, default=0):
            return pre, (pre.last[:, None] if all_logits else None)
        h = self._forward(pre, seqs)
        m = h.shape[1]
        n = torch.tensor(lens, device=self.device)
        real = torch.arange(m, device=self.device)[None] < n[:, None]
        grown = [i for i, k in enumerate(lens) if k]
        last = pre.last.clone()
        last[grown] = self._logits(h[grown, n[grown] - 1])
        new = Prefix(pre.cache, pre.length + m, last, torch.cat([pre.mask, real], 1), pre.pos + n)
        return new, (self._logits(h) if all_logits else None)

    def extend(self, pre: Prefix, ids: Sequence[int]) -> tuple[Prefix, torch.Tensor]:
        """Feed ids after a single-row `pre` (mutating its cache); returns the new prefix and logits for every fed
        position."""
        new, logits = self.extend_rows(pre, [list(ids)], all_logits=True)
        assert logits is not None
        return new, logits[0]

    def select(self, pre: Prefix, rows: Sequence[int]) -> Prefix:
        """A prefix of some of the rows of `pre` on a cache of their own (copied): the rows a question concerns
        are decoded without carrying the others along."""
        idx = torch.tensor(list(rows), device=self.device)
        cache = copy.copy(pre.cache)
        cache.layers = [copy.copy(layer) for layer in pre.cache.layers]
        cache.batch_select_indices(idx)  # re-indexes each layer's tensors: the shared cache is left as it was
        return Prefix(cache, pre.length, pre.last[idx], pre.mask[idx], pre.pos[idx])

    def rewind(self, cur: Prefix, to: Prefix) -> Prefix:
        """Cut the shared cache of `cur` back to the earlier state `to` (same cache, shorter)."""
        if cur.length > to.length:  # transformers 5: a negative count removes that many trailing tokens
            cur.cache.crop(to.length - cur.length)
        return to

    # ---- scoring -----------------------------------------------------------------------------------------
    def score_rows(self, pre: Prefix, seqs: Sequence[Sequence[Sequence[int]]]) -> list[list[float]]:
        """log p of each (non-empty) sequence `seqs[i][k]` after row i, in one forward call: the proper prefixes
        of a row's sequences form a trie fed as one tree (a shared prefix is fed once)."""
        chunks, parents, asks = _trie(seqs)
        out = [[0.0] * len(row) for row in seqs]
        first = torch.log_softmax(pre.last, -1)
        deep: list[tuple[int, int, int, int]] = []
        for i, k, at, t in asks:
            if at < 0:
                out[i][k] += float(first[i, t])
            else:
                deep.append((i, k, at, t))
        if not deep:
            return out
        h = self._forward(pre, chunks, parents)
        self.rewind(Prefix(pre.cache, pre.length + h.shape[1], pre.last, pre.mask, pre.pos), pre)
        where = sorted({(i, at) for i, _, at, _ in deep})  # the nodes whose next-token distribution is needed
        index = {w: r for r, w in enumerate(where)}
        rows_i = torch.tensor([w[0] for w in where], device=self.device)
        rows_j = torch.tensor([w[1] for w in where], device=self.device)
        lp = torch.empty(len(deep), dtype=torch.float32)
        ask_row = torch.tensor([index[(i, at)] for i, _, at, _ in deep])
        ask_tok = torch.tensor([t for *_, t in deep])
        for c in range(0, len(where), self.logit_rows):  # vocab-sized rows, a bounded number at a time
            logits = self._logits(h[rows_i[c : c + self.logit_rows], rows_j[c : c + self.logit_rows]]).cpu()
            sel = (ask_row >= c) & (ask_row < c + self.logit_rows)
            r = ask_row[sel] - c
            lp[sel] = logits[r, ask_tok[sel]] - torch.logsumexp(logits, -1)[r]
        for (i, k, _, _), v in zip(deep, lp.tolist()):
            out[i][k] += v
        return out

    def score_many(self, pre: Prefix, seqs: Sequence[Sequence[int]]) -> list[float]:
        """log p of each (non-empty) sequence after a single-row `pre`."""
        return self.score_rows(pre, [seqs])[0]

    # ---- answers -----------------------------------------------------------------------------------------
    def choose_rows(
        self, pre: Prefix, candidates: Sequence[Sequence[str] | None], per_token: Sequence[bool] | None = None
    ) -> list[str | None]:
        """Per row, the candidate (followed by the end of turn) with the highest log-likelihood; None rows skip.
        A row with `per_token` true ranks by the mean log-likelihood per token instead: sentences of 16 to 30
        tokens (the correction strategies) are otherwise decided by their length, a small model's per-token
        doubt adding up over the longer ones (docs/EXPERIMENTS.md, 2026-11-23 "With Q5 and Q6 on prefix grids ...")."""
        scores = self.option_scores_rows(pre, candidates, per_token)
        return [
            cands[max(range(len(cands)), key=sc.__getitem__)] if cands else None
            for cands, sc in zip(candidates, scores)
        ]

    def option_scores_rows(
        self, pre: Prefix, candidates: Sequence[Sequence[str] | None], per_token: Sequence[bool] | None = None
    ) -> list[list[float]]:
        """Per row, the log-likelihood of each candidate followed by the end of turn (per token where `per_token`);
        `choose_rows` takes the argmax, a softmax over them is the constrained decoder's distribution."""
        seqs = [[self.encode_ids(c) + [self.eos] for c in cands] if cands else [] for cands in candidates]
        scores = self.score_rows(pre, seqs)
        norm = per_token or [False] * len(seqs)
        return [[v / len(s) for v, s in zip(sc, row)] if n else sc for sc, row, n in zip(scores, seqs, norm)]

    def choose(self, pre: Prefix, candidates: Sequence[str], per_token: bool = False) -> str:
        return str(self.choose_rows(pre, [candidates], [per_token])[0])

    def actions_rows(self, pre: Prefix, active: Sequence[bool], max_actions: int = 12) -> list[str | None]:
        """Per active row, the ordered atomic actions, one greedy choice at a time (or the end of the list)."""
        chosen: list[list[str]] = [[] for _ in active]
        going = list(active)
        cur = pre
        for _ in range(max_actions):
            if not any(going):
                break
            opts = [
                [(", " if chosen[i] else "") + a for a in ATOMIC_ACTIONS] if going[i] else []
                for i in range(len(active))
            ]
            seqs = [
                [self.encode_ids(o) for o in opts[i]] + ([[self.eos]] if going[i] and chosen[i] else [])
                for i in range(len(active))
            ]
            scores = self.score_rows(cur, seqs)
            feed: list[list[int]] = []
            for i, sc in enumerate(scores):
                best = max(range(len(sc)), key=sc.__getitem__) if going[i] else -1
                if best < 0 or best == len(ATOMIC_ACTIONS):
                    going[i] = False
                    feed.append([])
                else:
                    chosen[i].append(ATOMIC_ACTIONS[best])
                    feed.append(self.encode_ids(opts[i][best]))
            if any(going):
                cur, _ = self.extend_rows(cur, feed)
        self.rewind(cur, pre)
        return [Q.format_actions(c) if a else None for c, a in zip(chosen, active)]

    def actions(self, pre: Prefix, max_actions: int = 12) -> str:
        return str(self.actions_rows(pre, [True], max_actions)[0])

    def free_tokens_rows(
        self, pre: Prefix, avoid: Sequence[Sequence[str]], active: Sequence[bool]
    ) -> list[list[int] | None]:
        """Per active row, greedy token ids until the end of turn (see `free_tokens`)."""
        out: list[list[int]] = [[] for _ in active]
        going = list(active)
        barred = [sorted({self.encode_ids(a)[0] for a in av if a}) for av in avoid]
        n = self.no_repeat_ngram
        cur = pre
        for _ in range(self.max_new_tokens):
            if not any(going):
                break
            logits = cur.last.clone()
            feed: list[list[int]] = []
            for i in range(len(active)):
                if not going[i]:
                    feed.append([])
                    continue
                o = out[i]
                if not o and barred[i]:
                    logits[i, barred[i]] = float("-inf")
                seen = _ngram_repeats(o, n)
                if seen:
                    logits[i, seen] = float("-inf")
                t = int(logits[i].argmax())
                if t == self.eos:
                    going[i] = False
                    feed.append([])
                else:
                    o.append(t)
                    feed.append([t])
            if any(going):
                cur, _ = self.extend_rows(cur, feed)
        self.rewind(cur, pre)
        return [o if a else None for o, a in zip(out, active)]

    def free_tokens(self, pre: Prefix, avoid: Sequence[str] = ()) -> list[int]:
        """Greedy token ids until the end of turn; `avoid`: replies that must not be produced (their first tokens
        are barred at step one). No n-gram of `no_repeat_ngram` tokens is produced twice (a small model's greedy
        text otherwise loops: "...to secure the gripper to secure the gripper...")."""
        return self.free_tokens_rows(pre, [avoid], [True])[0] or []

    def text(self, ids: Sequence[int]) -> str:
        return self.tok.decode(list(ids), skip_special_tokens=True).strip()

    def free_text(self, pre: Prefix, avoid: Sequence[str] = ()) -> str:
        """Greedy text until the end of turn (see `free_tokens`)."""
        return self.text(self.free_tokens(pre, avoid))


def _tree_inputs(
    chunks: Sequence[Sequence[int]], parents: Sequence[Sequence[int]] | None, pad: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arrays `Decoder._forward` feeds for one chunk per row: token ids (B, m) padded with `pad`, the tree
    mask (B, m, m: token j attends to token j') and each token's depth below the prefix (B, m).

    `parents[i][j]`: the chunk index token j follows (-1: the prefix); None means a plain run (j - 1)."""
    b, m = len(chunks), max(len(c) for c in chunks)
    tok = np.full((b, m), pad, np.int64)
    tree = np.zeros((b, m, m), bool)
    depth = np.zeros((b, m), np.int64)
    for i, c in enumerate(chunks):
        k = len(c)
        tok[i, :k] = c
        if parents is None:
            tree[i, :k, :k] = np.tril(np.ones((k, k), bool))
            depth[i, :k] = np.arange(k)
        else:
            for j, p in enumerate(parents[i]):
                if p >= 0:
                    tree[i, j] = tree[i, p]
                    depth[i, j] = depth[i, p] + 1
                tree[i, j, j] = True
        tree[i, range(k, m), range(k, m)] = True  # padding attends to itself only (no empty softmax row)
    return tok, tree, depth


def _trie(
    seqs: Sequence[Sequence[Sequence[int]]],
) -> tuple[list[list[int]], list[list[int]], list[tuple[int, int, int, int]]]:
    """Per row, the trie of the proper prefixes of its sequences (`seqs[i][k]`) as one chunk of tokens and their
    parents (`Decoder._forward`'s tree; a shared prefix is one node), and every token whose log p is asked:
    (row, sequence, trie node or -1 for the prefix, next token)."""
    chunks: list[list[int]] = []
    parents: list[list[int]] = []
    asks: list[tuple[int, int, int, int]] = []  # (row, sequence, trie node or -1 for the prefix, next token)
    for i, row in enumerate(seqs):
        nodes: dict[tuple[int, int], int] = {}
        toks: list[int] = []
        par: list[int] = []
        for k, s in enumerate(row):
            at = -1
            for t in s[:-1]:
                asks.append((i, k, at, t))
                if (at, t) not in nodes:
                    nodes[(at, t)] = len(toks)
                    toks.append(t)
                    par.append(at)
                at = nodes[(at, t)]
            asks.append((i, k, at, s[-1]))
        chunks.append(toks)
        parents.append(par)
    return chunks, parents, asks


def _ngram_repeats(o: Sequence[int], n: int) -> list[int]:
    """The tokens that would follow the last n - 1 tokens of `o` as they were followed before (a repeated n-gram);
    none when n is 0 or `o` is shorter than n - 1."""
    if not (n and len(o) >= n - 1):
        return []
    tail = o[len(o) - n + 1 :]
    return [o[j + n - 1] for j in range(len(o) - n + 1) if o[j : j + n - 1] == tail]
