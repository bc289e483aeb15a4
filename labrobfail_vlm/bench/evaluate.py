"""LabRobFail-Bench evaluator: predictions (from a model, a baseline or a JSONL file) -> scores and breakdowns.

A prediction is the reply to one record's question, keyed by the record id ("<trajectory>_Q<k>").
Replies are parsed with bench.parse (an unparseable reply counts as wrong and is logged).
Q2 is scored as asked: for the "successfully"/"without issues" variants, "Yes" means no failure.
"""

from __future__ import annotations

import json
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Callable

from PIL import Image

from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench.metrics import accuracy, bleu, rouge_l, within_one
from labrobfail_vlm.bench.parse import parse
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.taxonomy import SEEN_SPLITS, UNSEEN_SPLITS

# CLI split name -> file stem: the seen splits by name, each unseen variant by its suffix ("object" -> test_object).
SPLITS = {**{s: s for s in reversed(SEEN_SPLITS)},
          **{v.removeprefix("unseen_"): s for v, s in UNSEEN_SPLITS.items()},
          "prefix": "test_prefix"}  # prefix grids of the seen test split (dataset built with prefix.cuts > 0)


def q2_as_asked(question: str, failed: bool) -> str:
    """The Q2 reply meaning `failed`, for the variant the record asks (variant 0 when unrecognised)."""
    return Q.q2_answer(Q.q2_variant(question) or 0, success=not failed)


def load_split(dataset_dir: str | Path, split: str) -> tuple[list[dict], dict[str, dict]]:
    root = Path(dataset_dir)
    if split not in SPLITS:
        raise ConfigError(f"split: expected one of {', '.join(SPLITS)}, got {split!r}")
    f = root / f"{SPLITS[split]}.json"
    if not f.is_file():
        raise ConfigError(f"dataset_dir: {f} not found")
    try:
        recs = json.loads(f.read_text())
        traj = {t["trajectory"]: t for t in json.loads((root / "trajectories.json").read_text())}
    except (OSError, ValueError, KeyError) as e:
        raise ConfigError(f"dataset_dir: cannot read {root} ({type(e).__name__})") from None
    return recs, traj


def read_predictions(path: str | Path) -> dict[str, str]:
    out: dict[str, str] = {}
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise ConfigError(f"predictions: cannot read {path} ({e.strerror})") from None
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            out[str(obj["id"])] = str(obj["prediction"])
        except (ValueError, KeyError, TypeError):
            raise ConfigError(f"predictions: {path} line {i} is not a JSON object with id and prediction") from None
    return out


# ---- prediction sources -----------------------------------------------------------------------------------
def model_predictions(analyzer: Any, dataset_dir: str | Path, recs: list[dict], traj: dict[str, dict],
                      blind: bool = False, progress: bool = True, batch_size: int = 1) -> dict[str, str]:
    """Run the analyzer once per trajectory (one pass over the dimensions its records ask), `batch_size`
    trajectories per `answers_batch` call; `blind` blanks the grid."""
    from tqdm import tqdm

    by_traj: dict[str, list[dict]] = defaultdict(list)
    for r in recs:
        by_traj[Q.traj_of(r["id"])].append(r)
    items = list(by_traj.items())
    out: dict[str, str] = {}
    bar = tqdm(total=len(items), desc="blind" if blind else "model", disable=not progress)
    for c in range(0, len(items), max(1, batch_size)):
        chunk = items[c:c + max(1, batch_size)]
        images = []
        for _, rs in chunk:
            img = Image.open(Path(dataset_dir) / rs[0]["image"]).convert("RGB")
            images.append(Image.new("RGB", img.size, (128, 128, 128)) if blind else img)
        infos = [traj.get(t, {}) for t, _ in chunk]
        answers = analyzer.answers_batch(images, [i.get("task", "") for i in infos], [i.get("frames") for i in infos],
                                         [i.get("objects", ()) for i in infos],
                                         [{Q.dim_of(r["id"]) for r in rs} for _, rs in chunk], max_batch=batch_size)
        for (_, rs), ans in zip(chunk, answers):
            failed = ans["Q2"] == "Yes"
            for r in rs:
                d = Q.dim_of(r["id"])
                out[r["id"]] = q2_as_asked(r["conversations"][0]["value"], failed) if d == "Q2" else ans[d]
        bar.update(len(chunk))
    bar.close()
    return out


def majority_predictions(train: list[dict], recs: list[dict]) -> dict[str, str]:
    """The most frequent training answer per dimension (Q2 as the most frequent outcome, asked either way).

    Needs training answers for every dimension the split asks: a one-line ConfigError names the missing ones."""
    counts: dict[str, Counter] = defaultdict(Counter)
    for r in train:
        d, a = Q.dim_of(r["id"]), r["conversations"][1]["value"]
        if d == "Q2":
            a = str(a != q2_as_asked(r["conversations"][0]["value"], failed=False))  # "True" = failed
        counts[d][a] += 1
    top = {d: c.most_common(1)[0][0] for d, c in counts.items()}
    missing = sorted({Q.dim_of(r["id"]) for r in recs} - set(top))
    if missing:
        raise ConfigError(f"majority baseline: the training split has no answers for {', '.join(missing)}")
    out = {}
    for r in recs:
        d = Q.dim_of(r["id"])
        q = r["conversations"][0]["value"]
        out[r["id"]] = q2_as_asked(q, top[d] == "True") if d == "Q2" else top.get(d, "")
    return out


# ---- scoring ------------------------------------------------------------------------------------------------
def score(recs: list[dict], preds: dict[str, str], traj: dict[str, dict],
          log: Callable[[str], None] | None = None) -> dict[str, Any]:
    pairs: dict[str, list[tuple[str | None, str]]] = defaultdict(list)
    q6_ref, q6_hyp = [], []
    unparseable: Counter[str] = Counter()
    groups: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    confusion: dict[str, Counter] = {"Q2": Counter(), "Q4": Counter(), "Q5": Counter()}
    for r in recs:
        d, ref = Q.dim_of(r["id"]), r["conversations"][1]["value"]
        reply = preds.get(r["id"])
        p = parse(d, reply) if reply is not None else None
        if p is None:
            unparseable[d] += 1
            if log:
                log(f"unparseable {r['id']}: {reply!r}")
        if d == "Q6":
            q6_ref.append(ref)
            q6_hyp.append(p or "")
            continue
        pairs[d].append((p, ref))
        if d in confusion:
            confusion[d][(ref, p or "?")] += 1
        info = traj.get(Q.traj_of(r["id"]), {})
        cat = str(info.get("category")) if not info.get("success", True) else "success"
        groups[f"category:{cat}"][d].append(p == ref)
        groups[f"task:{info.get('scenario', '?')}"][d].append(p == ref)
        # per failure type (Q2 here is the recall of that type), so a type the model cannot see shows up
        groups[f"type:{info.get('failure_type') or 'success'}"][d].append(p == ref)
    # A dimension with no records in the split (e.g. a Q2-only probe) is null, not a misleading 0.
    res: dict[str, Any] = {d.lower(): round(100 * accuracy(pairs[d]), 2) if pairs[d] else None
                           for d in ("Q1", "Q2", "Q3", "Q4", "Q5")}
    res["q3_within1"] = round(100 * within_one(pairs["Q3"]), 2) if pairs["Q3"] else None
    res["q6"] = ({**{k: round(v, 4) for k, v in bleu(q6_ref, q6_hyp).items()},
                  "rougeL": round(rouge_l(q6_ref, q6_hyp), 4)} if q6_ref else
                 dict.fromkeys(("bleu1", "bleu2", "bleu3", "bleu4", "rougeL")))
    res["records"] = len(recs)
    res["unparseable"] = dict(unparseable)
    res["breakdown"] = {g: {d: round(100 * sum(v) / len(v), 2) for d, v in dims.items()}
                        for g, dims in sorted(groups.items())}
    res["confusion"] = {d: [[ref, pred, n] for (ref, pred), n in sorted(c.items())] for d, c in confusion.items()}
    return res


def external_predictions(client: Any, dataset_dir: str | Path, recs: list[dict], progress: bool = True,
                         log: Callable[[str], None] | None = None) -> dict[str, str]:
    """Ask an OpenAI-compatible chat model each record's question with its grid (a data: URL)."""
    from tqdm import tqdm

    from labrobfail_vlm.llm_client import image_data_url

    cache: dict[str, str] = {}
    out: dict[str, str] = {}
    for r in tqdm(recs, desc="external", disable=not progress):
        if r["image"] not in cache:
            cache = {r["image"]: image_data_url(Image.open(Path(dataset_dir) / r["image"]))}
        q = r["conversations"][0]["value"].removeprefix("<image>\n")
        hint = {"Q1": "Answer with the actions only, comma-separated.", "Q2": "Answer Yes or No.",
                "Q3": "Answer with the frame number only, or None if nothing failed.",
                "Q4": "Answer with the option number only, or None.", "Q5": "Answer with the option number only, "
                "or None.", "Q6": "Answer with one instruction sentence."}[Q.dim_of(r["id"])]
        msgs = [{"role": "user", "content": [{"type": "image_url", "image_url": {"url": cache[r["image"]]}},
                                             {"type": "text", "text": f"{q}\n{hint}"}]}]
        try:
            out[r["id"]] = client.chat(msgs)
        except (OSError, ValueError, KeyError, IndexError, TypeError) as e:
            out[r["id"]] = ""
            if log:
                log(f"request failed {r['id']}: {type(e).__name__}")
    return out
