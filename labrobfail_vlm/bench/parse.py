"""Robust parsing of free-form replies (external models) into the bench's canonical answers.

Canonical forms: Q1 "a, b"; Q2 "Yes"/"No"; Q3 a frame number or "None"; Q4/Q5 an option
number or "None"; Q6 the text. `parse` returns None for an unparseable reply, which the
evaluator counts as wrong and logs.
"""

from __future__ import annotations

import re

from labrobfail_vlm import questions as Q
from labrobfail_vlm.taxonomy import ATOMIC_ACTIONS, Category, Severity

_NONE = re.compile(r"\b(none|no failure|not applicable|n/?a|no error)\b", re.I)
_YES = re.compile(r"\b(yes|yeah|true|correct)\b", re.I)
_NO = re.compile(r"\b(no|not|false|incorrect)\b", re.I)
_ALIASES = {
    "stirring": "stir",
    "pouring": "pour",
    "shaking": "shake",
    "inserting": "insert",
    "grasping": "grasp",
    "placing": "place",
    "opening": "open",
    "closing": "close",
    "stirred": "stir",
    "placed": "place",
    "poured": "pour",
    "shook": "shake",
    "inserted": "insert",
    "grasped": "grasp",
    "opened": "open",
    "closed": "close",
}


def _action(word: str) -> str | None:
    """An atomic action from a word and its inflections (grasps, placing, poured, shook, ...)."""
    if word in ATOMIC_ACTIONS:
        return word
    if word in _ALIASES:
        return _ALIASES[word]
    if word.endswith("s") and word[:-1] in ATOMIC_ACTIONS:
        return word[:-1]
    return None


def _option(text: str, names: dict[int, str], hi: int) -> str | None:
    t = text.strip()
    m = re.match(r"^\(?([1-9])\)?(?:\b|$)", t)
    if m and 1 <= int(m.group(1)) <= hi:
        return m.group(1)
    low = t.lower()
    hits = [k for k, n in names.items() if n.lower() in low]
    if len(hits) == 1:
        return str(hits[0])
    nums = [n for n in re.findall(r"(?<![\d.])([1-9])(?![\d.])", t) if 1 <= int(n) <= hi]
    if len(set(nums)) == 1:
        return nums[0]
    if _NONE.search(t):
        return Q.NO_FAILURE
    return None


def parse(dim: str, reply: str) -> str | None:
    text = (reply or "").strip()
    if not text:
        return None
    if dim == "Q1":
        acts = [a for w in re.findall(r"[a-z]+", text.lower()) if (a := _action(w))]
        return Q.format_actions(acts) if acts else None
    if dim == "Q2":
        y, n = _YES.search(text), _NO.search(text)
        if y and (not n or y.start() < n.start()):
            return "Yes"
        if n:
            return "No"
        return None
    if dim == "Q3":
        m = re.search(r"(?:frame|step|time ?step|index|t\s*=)?\s*#?\s*(\d{1,3})\b", text, re.I)
        if m:
            return str(int(m.group(1)))
        return Q.NO_FAILURE if _NONE.search(text) else None
    if dim == "Q4":
        return _option(text, {s.value: s.title.replace(" Level", "") for s in Severity}, len(Severity))
    if dim == "Q5":
        return _option(text, {c.value: c.name.lower() for c in Category}, len(Category))
    if dim == "Q6":
        return text
    raise ValueError(f"parse: unknown dimension {dim!r}")
