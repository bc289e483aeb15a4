"""LabRobFail-Bench evaluator: predictions (from a model, a baseline or a JSONL file) -> scores and breakdowns.

A prediction is the reply to one record's question, keyed by the record id ("<trajectory>_Q<k>"), plus, where the
source has one, P(failure) per trajectory (`Predictions.p_failure`). Replies are parsed with bench.parse (an
unparseable reply counts as wrong and is logged). Q2 is scored as asked: for the "successfully"/"without issues"
variants, "Yes" means no failure.

Two scopes. Q1 and Q2 are scored over every trajectory. Q3-Q6 are scored twice: over every trajectory (a success's
reference is "None" / the no-correction sentence; the top-level keys, kept as the project's own table) and over the
failed trajectories only (`failure_only`), which is what the paper's table can mean: its Q4 and Q5 options have no
"None", and a success has nothing to localise, rate, classify or correct. Failure detection is also scored as a
ranking of P(failure) (`detection`: AUROC, AUPRC, ECE; labrobfail_vlm.bench.detection).
"""

from __future__ import annotations

import json
import math
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Callable

from PIL import Image

from labrobfail_vlm import questions as Q
from labrobfail_vlm.bench.metrics import accuracy, bleu, pair_bootstrap, rouge_l_values, within_one
from labrobfail_vlm.bench.parse import parse
from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.io import append_line
from labrobfail_vlm.taxonomy import HELD_OUT_SPLITS, REPLAY_SPLITS, SEALED_SPLITS, SEEN_SPLITS

# CLI split name -> file stem: every split by its file's name, its prefix grids (a dataset built with
# prefix.cuts > 0) as <split>_prefix, and "prefix" for the seen test split's.
_STEMS = (*reversed(SEEN_SPLITS), *HELD_OUT_SPLITS, *REPLAY_SPLITS)
SPLITS = {**{s: s for s in _STEMS}, **{f"{s}_prefix": f"{s}_prefix" for s in _STEMS if s != "train"}}
SPLITS["prefix"] = "test_prefix"


MAJORITY, BLIND = "majority class", "blind (grey grid)"  # the baselines' titles in results.json and the tables
SEALED_LEDGER = "sealed_runs.jsonl"  # in the dataset folder: one line per bench run on a sealed split


def count_sealed_run(dataset_dir: str | Path, split: str, source: str, res: dict[str, Any]) -> None:
    """A sealed split runs only for reported rows, and every run is counted: append this one (date, source,
    headline figures) to the dataset's ledger, which docs/RESULTS.md lists. Other splits are not recorded."""
    if split not in SEALED_SPLITS:
        return
    from datetime import datetime, timezone

    fo = res.get("failure_only") or {}
    entry = {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "split": split,
        "source": source,
        "q2": res.get("q2"),
        "q3_failures": fo.get("q3"),
        "q4_failures": fo.get("q4"),
        "q5_failures": fo.get("q5"),
        "rougeL_failures": (fo.get("q6") or {}).get("rougeL"),
    }
    append_line(Path(dataset_dir) / SEALED_LEDGER, json.dumps(entry))  # two benches at once: both counted


def sealed_runs(dataset_dir: str | Path) -> list[dict[str, Any]]:
    """The ledger's entries, oldest first (none when no sealed split was ever run on this dataset)."""
    ledger = Path(dataset_dir) / SEALED_LEDGER
    return [json.loads(line) for line in ledger.read_text().splitlines() if line.strip()] if ledger.is_file() else []


def check_operating_point(value: Any, key: str = "threshold") -> None:
    """A bench's operating point on P(failure): 0.5 (the decoder's argmax), val (the cut chosen on the model's own
    seen-val bench) or another number between 0 and 1; anything else a one-line error."""
    if value == 0.5 or value == "val":
        return
    from labrobfail_vlm.analyzer import check_threshold  # the analyzer's own range (imported only for a number)

    try:
        check_threshold(value)
    except ValueError:
        raise ConfigError(f"{key}: expected val or a number between 0 and 1 (exclusive), got {value!r}") from None


def bench_suffix(threshold: Any = 0.5, limit: int | None = None) -> str:
    """The folder suffix of a bench at operating point `threshold` on the split's first `limit` trajectories
    (None: all): _opval for the cut chosen on val, _t<threshold> for another given one, then _first<N>; none for
    the default bench (0.5, whole split)."""
    op = "" if threshold == 0.5 else "_opval" if threshold == "val" else f"_t{threshold}"
    return op + (f"_first{limit}" if limit else "")  # a partial run never lands over the whole split's bench


def bench_dir(source: str | Path, split: str, suffix: str = "") -> Path:
    """Where a bench of `source` (a model's folder, or a predictions file: its folder) on `split` is written:
    eval_<split><suffix> (the suffix names a non-default operating point or a first-N run)."""
    src = Path(source)
    return (src.parent if src.is_file() else src) / f"eval_{split}{suffix}"


def q2_as_asked(question: str, failed: bool) -> str:
    """The Q2 reply meaning `failed`, for the variant the record asks (variant 0 when unrecognised)."""
    return Q.q2_answer(Q.q2_variant(question) or 0, success=not failed)


def load_split(dataset_dir: str | Path, split: str, limit: int | None = None) -> tuple[list[dict], dict[str, dict]]:
    """The split's records and every trajectory's metadata; with `limit`, only the records of the split's first
    `limit` trajectories in file order (e.g. split=train limit=800: how well a model fits its own training data)."""
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
    if limit:
        first = set(list(dict.fromkeys(Q.traj_of(r["id"]) for r in recs))[:limit])
        recs = [r for r in recs if Q.traj_of(r["id"]) in first]
    return recs, traj


FAILURE_ONLY_DIMS = ("Q3", "Q4", "Q5", "Q6")


class Predictions(dict[str, str]):
    """Replies keyed by record id, P(failure) keyed by trajectory where the source scored it, and keyed by record id
    the log-likelihood of each option of a closed failure-only reply the model chose (Q3-Q5, before any option
    bias: what labrobfail-calibrate fits its biases on)."""

    def __init__(
        self,
        *args: Any,
        p_failure: dict[str, float] | None = None,
        option_scores: dict[str, list[float]] | None = None,
    ):
        super().__init__(*args)
        self.p_failure: dict[str, float] = dict(p_failure or {})
        self.option_scores: dict[str, list[float]] = dict(option_scores or {})


def read_predictions(path: str | Path) -> Predictions:
    """JSONL of {"id", "prediction"}; a line may add "p_failure" (a number in [0, 1]) for its trajectory and
    "scores" (a list of finite numbers: its options' log-likelihoods)."""
    out = Predictions()
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(
            f"predictions: cannot read {path} ({getattr(e, 'strerror', None) or type(e).__name__})"
        ) from None
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            out[str(obj["id"])] = str(obj["prediction"])
            if obj.get("p_failure") is not None:
                p = float(obj["p_failure"])
                if not 0.0 <= p <= 1.0:
                    raise ValueError
                out.p_failure[Q.traj_of(str(obj["id"]))] = p
            if obj.get("scores") is not None:
                raw = obj["scores"]
                if not isinstance(raw, list) or not raw or any(isinstance(v, bool) for v in raw):
                    raise ValueError
                sc = [float(v) for v in raw]
                if not all(math.isfinite(v) for v in sc):
                    raise ValueError
                out.option_scores[str(obj["id"])] = sc
        except (ValueError, KeyError, TypeError, AttributeError):
            raise ConfigError(
                f"predictions: {path} line {i} is not a JSON object with id, prediction, an "
                "optional p_failure in [0, 1] and optional scores (finite numbers)"
            ) from None
    return out


# ---- prediction sources -----------------------------------------------------------------------------------
def model_predictions(
    analyzer: Any,
    dataset_dir: str | Path,
    recs: list[dict],
    traj: dict[str, dict],
    blind: bool = False,
    progress: bool = True,
    batch_size: int = 1,
) -> Predictions:
    """Run the analyzer once per trajectory (one pass over the dimensions its records ask), `batch_size`
    trajectories per `answers_batch` call; `blind` blanks the grid. P(failure) is kept where the analyzer gives it."""
    from tqdm import tqdm

    by_traj: dict[str, list[dict]] = defaultdict(list)
    for r in recs:
        by_traj[Q.traj_of(r["id"])].append(r)
    items = list(by_traj.items())
    out = Predictions()
    bar = tqdm(total=len(items), desc="blind" if blind else "model", disable=not progress)
    for c in range(0, len(items), max(1, batch_size)):
        chunk = items[c : c + max(1, batch_size)]
        images = []
        for _, rs in chunk:
            img = Image.open(Path(dataset_dir) / rs[0]["image"]).convert("RGB")
            images.append(Image.new("RGB", img.size, (128, 128, 128)) if blind else img)
        infos = [traj.get(t, {}) for t, _ in chunk]
        answers = analyzer.answers_batch(
            images,
            [i.get("task", "") for i in infos],
            [i.get("frames") for i in infos],
            [i.get("objects", ()) for i in infos],
            [{Q.dim_of(r["id"]) for r in rs} for _, rs in chunk],
            max_batch=batch_size,
        )
        for (t, rs), ans in zip(chunk, answers):
            failed = ans["Q2"] == "Yes"
            if getattr(ans, "p_failure", None) is not None:
                out.p_failure[t] = float(ans.p_failure)
            scored = getattr(ans, "option_scores", {})
            for r in rs:
                d = Q.dim_of(r["id"])
                out[r["id"]] = q2_as_asked(r["conversations"][0]["value"], failed) if d == "Q2" else ans[d]
                if d in scored:
                    out.option_scores[r["id"]] = [round(float(v), 5) for v in scored[d]]
        bar.update(len(chunk))
    bar.close()
    return out


def same_kind(train: list[dict], train_traj: dict[str, dict], recs: list[dict], traj: dict[str, dict]) -> list[dict]:
    """The training records of the scored records' kind: whole trajectories for a whole-grid split, prefix grids for
    a prefix split. A dataset built with prefix cuts trains on both, and a whole grid's majority answer and failure
    rate are its whole trajectories' (a prefix of a failure before its onset answers "no failure yet"). All of them
    when the training split has none of that kind."""

    def is_prefix(r: dict, meta: dict[str, dict]) -> bool:
        return "prefix_of" in meta.get(Q.traj_of(r["id"]), {})

    want = any(is_prefix(r, traj) for r in recs)
    return [r for r in train if is_prefix(r, train_traj) == want] or train


def majority_predictions(train: list[dict], recs: list[dict], failures_only: bool = False) -> Predictions:
    """The most frequent training answer per dimension (Q2 as the most frequent outcome, asked either way), with
    P(failure) the training failure rate. `failures_only`: Q3-Q6 take the most frequent answer among training
    failures (the failure-only scores' baseline; a success's "None" and no-correction answers are not counted).

    Needs training answers for every dimension the split asks: a one-line ConfigError names the missing ones."""
    counts: dict[str, Counter] = defaultdict(Counter)
    for r in train:
        d, a = Q.dim_of(r["id"]), r["conversations"][1]["value"]
        if d == "Q2":
            a = str(a != q2_as_asked(r["conversations"][0]["value"], failed=False))  # "True" = failed
        elif failures_only and d in FAILURE_ONLY_DIMS and a in (Q.NO_FAILURE, Q.NO_CORRECTION):
            continue  # a success's answer: every failure answer is something else
        counts[d][a] += 1
    top = {d: c.most_common(1)[0][0] for d, c in counts.items()}
    missing = sorted({Q.dim_of(r["id"]) for r in recs} - set(top))
    if missing:
        raise ConfigError(f"majority baseline: the training split has no answers for {', '.join(missing)}")
    q2 = counts.get("Q2", Counter())
    rate = q2["True"] / max(1, sum(q2.values()))
    out = Predictions(p_failure={Q.traj_of(r["id"]): rate for r in recs})
    for r in recs:
        d = Q.dim_of(r["id"])
        q = r["conversations"][0]["value"]
        out[r["id"]] = q2_as_asked(q, top[d] == "True") if d == "Q2" else top.get(d, "")
    return out


# ---- scoring ------------------------------------------------------------------------------------------------
def failed_records(recs: list[dict], traj: dict[str, dict]) -> list[dict]:
    """The Q3-Q6 records of failed trajectories: what the failure-only scores are taken over."""
    return [
        r
        for r in recs
        if Q.dim_of(r["id"]) in FAILURE_ONLY_DIMS and not traj.get(Q.traj_of(r["id"]), {}).get("success", True)
    ]


def says_failed(rec: dict, preds: dict[str, str]) -> bool:
    """Whether the reply to a Q2 record says "failed", in the wording the record asks."""
    return parse("Q2", preds.get(rec["id"]) or "") == q2_as_asked(rec["conversations"][0]["value"], failed=True)


def called_failed(recs: list[dict], preds: dict[str, str]) -> set[str]:
    """The trajectories whose Q2 reply says "failed"."""
    return {Q.traj_of(r["id"]) for r in recs if Q.dim_of(r["id"]) == "Q2" and says_failed(r, preds)}


def failure_scores(q2: list[dict], preds: dict[str, str]) -> tuple[list[float], str]:
    """P(failure) per Q2 record, and "probability"; or "hard" where some trajectory has no probability, whose hard
    Q2 reply is then its score (1 for failed, 0 otherwise)."""
    probs = getattr(preds, "p_failure", {})
    ps = [probs.get(Q.traj_of(r["id"])) for r in q2]
    kind = "probability" if all(p is not None for p in ps) else "hard"
    return [float(says_failed(r, preds)) if p is None else p for r, p in zip(q2, ps)], kind


def detection(recs: list[dict], preds: dict[str, str], traj: dict[str, dict]) -> dict[str, Any] | None:
    """AUROC/AUPRC/ECE of P(failure) over the split's trajectories that are asked Q2 (None when none are).
    Without a probability for a trajectory, its hard Q2 reply is the score (0 or 1)."""
    from labrobfail_vlm.bench.detection import detection_metrics

    q2 = [r for r in recs if Q.dim_of(r["id"]) == "Q2"]
    ys = [not traj.get(Q.traj_of(r["id"]), {}).get("success", True) for r in q2]
    return detection_metrics(ys, *failure_scores(q2, preds)) if ys else None


def score(
    recs: list[dict],
    preds: dict[str, str],
    traj: dict[str, dict],
    log: Callable[[str], None] | None = None,
    failure_preds: dict[str, str] | None = None,
) -> dict[str, Any]:
    """All-trajectory scores (top level), `failure_only` (Q3-Q6 over failed trajectories, from `failure_preds`
    where a baseline answers failures differently; its `detected`: over the failed trajectories that Q2 called
    failed, which separates diagnosing a failure from finding it) and `detection` (P(failure) as a score)."""
    res = _score(recs, preds, traj, log)
    fails = failed_records(recs, traj)
    fpreds = failure_preds if failure_preds is not None else preds
    fo = _score(fails, fpreds, traj) if fails else None
    caught = called_failed(recs, preds)
    hit = [r for r in fails if Q.traj_of(r["id"]) in caught]
    dx = _score(hit, fpreds, traj) if hit else None
    res["failure_only"] = {
        "trajectories": len({Q.traj_of(r["id"]) for r in fails}),
        "records": len(fails),
        **(
            {k: fo[k] for k in ("q3", "q3_within1", "q4", "q5", "q6", "unparseable", "ci95")}
            if fo
            else dict.fromkeys(("q3", "q3_within1", "q4", "q5", "q6"))
        ),
        "detected": {
            "trajectories": len({Q.traj_of(r["id"]) for r in hit}),
            **({k: dx[k] for k in ("q3", "q4", "q5", "q6")} if dx else dict.fromkeys(("q3", "q4", "q5", "q6"))),
        },
    }
    res["detection"] = detection(recs, preds, traj)
    res["scope"] = {"q1-q6": "all trajectories", "failure_only": "Q3-Q6 over failed trajectories (as the paper)"}
    return res


def _score(
    recs: list[dict], preds: dict[str, str], traj: dict[str, dict], log: Callable[[str], None] | None = None
) -> dict[str, Any]:
    pairs: dict[str, list[tuple[str | None, str]]] = defaultdict(list)
    pair_of: dict[str, list[str]] = defaultdict(list)  # per dimension, each record's pair (for the intervals)
    q6_ref, q6_hyp = [], []
    unparseable: Counter[str] = Counter()
    groups: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    confusion: dict[str, Counter] = {"Q2": Counter(), "Q4": Counter(), "Q5": Counter()}
    type_pairs: dict[str, list[tuple[bool, str]]] = defaultdict(list)  # Q2 per failure type: (right, pair)
    for r in recs:
        d, ref = Q.dim_of(r["id"]), r["conversations"][1]["value"]
        reply = preds.get(r["id"])
        p = parse(d, reply) if reply is not None else None
        if p is None:
            unparseable[d] += 1
            if log:
                log(f"unparseable {r['id']}: {reply!r}")
        info = traj.get(Q.traj_of(r["id"]), {})
        pair_of[d].append(str(info.get("group") or Q.traj_of(r["id"])))  # no pair known: the trajectory alone
        if d == "Q6":
            q6_ref.append(ref)
            q6_hyp.append(p or "")
            continue
        pairs[d].append((p, ref))
        if d in confusion:
            confusion[d][(ref, p or "?")] += 1
        cat = str(info.get("category")) if not info.get("success", True) else "success"
        groups[f"category:{cat}"][d].append(p == ref)
        groups[f"task:{info.get('scenario', '?')}"][d].append(p == ref)
        # per failure type (Q2 here is the recall of that type), so a type the model cannot see shows up
        groups[f"type:{info.get('failure_type') or 'success'}"][d].append(p == ref)
        if d == "Q2":
            type_pairs[info.get("failure_type") or "success"].append((p == ref, pair_of[d][-1]))
    # A dimension with no records in the split (e.g. a Q2-only probe) is null, not a misleading 0.
    res: dict[str, Any] = {
        d.lower(): round(100 * accuracy(pairs[d]), 2) if pairs[d] else None for d in ("Q1", "Q2", "Q3", "Q4", "Q5")
    }
    res["q3_within1"] = round(100 * within_one(pairs["Q3"]), 2) if pairs["Q3"] else None
    rl = rouge_l_values(q6_ref, q6_hyp)
    res["q6"] = (
        {**{k: round(v, 4) for k, v in bleu(q6_ref, q6_hyp).items()}, "rougeL": round(sum(rl) / len(rl), 4)}
        if q6_ref
        else dict.fromkeys(("bleu1", "bleu2", "bleu3", "bleu4", "rougeL"))
    )
    # 95 % intervals: a seeded bootstrap over pairs (both twins of a pair drawn together: they share an initial
    # state, so counting them as independent samples would make the intervals too narrow)
    res["ci95"] = {
        d.lower(): [round(100 * x, 2) for x in ci]
        for d in ("Q1", "Q2", "Q3", "Q4", "Q5")
        if (ci := pair_bootstrap([float(p == r) for p, r in pairs[d]], pair_of[d]))
    }
    if (ci := pair_bootstrap(rl, pair_of["Q6"])) is not None:
        res["ci95"]["rougeL"] = [round(x, 4) for x in ci]
    res["ci_method"] = "percentile bootstrap over pairs, 1000 resamples, seed 0"
    res["records"] = len(recs)
    res["unparseable"] = dict(unparseable)
    res["breakdown"] = {
        g: {d: round(100 * sum(v) / len(v), 2) for d, v in dims.items()} for g, dims in sorted(groups.items())
    }
    res["confusion"] = {d: [[ref, pred, n] for (ref, pred), n in sorted(c.items())] for d, c in confusion.items()}
    # Q2 per failure type (the recall of that type; "success": the specificity) with its pair-bootstrap interval
    res["q2_by_type"] = {
        t: {
            "q2": round(100 * sum(ok for ok, _ in v) / len(v), 2),
            "n": len(v),
            "ci95": [round(100 * x, 2) for x in pair_bootstrap([float(ok) for ok, _ in v], [g for _, g in v])],
        }
        for t, v in sorted(type_pairs.items())
    }
    return res


def external_predictions(
    client: Any,
    dataset_dir: str | Path,
    recs: list[dict],
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> dict[str, str]:
    """Ask an OpenAI-compatible chat model each record's question with its grid (a data: URL)."""
    from tqdm import tqdm

    from labrobfail_vlm.llm_client import image_data_url

    cache: dict[str, str] = {}
    out: dict[str, str] = {}
    for r in tqdm(recs, desc="external", disable=not progress):
        if r["image"] not in cache:
            cache = {r["image"]: image_data_url(Image.open(Path(dataset_dir) / r["image"]))}
        q = r["conversations"][0]["value"].removeprefix("<image>\n")
        hint = {
            "Q1": "Answer with the actions only, comma-separated.",
            "Q2": "Answer Yes or No.",
            "Q3": "Answer with the frame number only, or None if nothing failed.",
            "Q4": "Answer with the option number only, or None.",
            "Q5": "Answer with the option number only, or None.",
            "Q6": "Answer with one instruction sentence.",
        }[Q.dim_of(r["id"])]
        msgs = [
            {
                "role": "user",
                "content": [
                    {"type": "image_url", "image_url": {"url": cache[r["image"]]}},
                    {"type": "text", "text": f"{q}\n{hint}"},
                ],
            }
        ]
        try:
            out[r["id"]] = client.chat(msgs)
        except (OSError, ValueError, KeyError, IndexError, TypeError) as e:
            out[r["id"]] = ""
            if log:
                log(f"request failed {r['id']}: {type(e).__name__}")
    return out
