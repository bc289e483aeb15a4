"""The results page's tables from bench results (one `results.json` dict per split): the principal issue's targets,
the paper-comparable tables, the all-trajectory tables, Q2 recall per failure type, a second model's section, the
sealed-split ledger, and the tables of a run's other models (the tuned continuation, the tower and sensor rows, the
ablation). scripts/write_results.py lays them out with the supervision section into docs/RESULTS.md.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Sequence

from labrobfail_vlm.bench.evaluate import BLIND, MAJORITY, sealed_runs

# the paper tables' heading (scripts/write_results.py inserts a spliced section that the page lacks before it)
PAPER_TABLES = "## Paper-comparable tables"
SPLIT_TITLES = {
    "test": "Seen (test split)",
    "val_object": "Validation: held-out objects",
    "val_scene": "Validation: held-out scene",
    "val_both": "Validation: held-out objects and scene",
    "test_object": "Sealed test: unseen objects",
    "test_scene": "Sealed test: unseen scene",
    "test_both": "Sealed test: unseen objects and scene",
}


def _scores(res: dict[str, Any], fo: bool) -> dict[str, Any]:
    """A split's scores over all its trajectories, or over the failed ones (`fo`: the paper-comparable scores)."""
    return res["failure_only"] if fo else res


def ci_cell(res: dict[str, Any], key: str, fo: bool = False) -> str:
    """'value [lo, hi]' for an accuracy (or ROUGE-L) with its 95 % interval."""
    src = _scores(res, fo)
    v = src["q6"]["rougeL"] if key == "rougeL" else src[key]
    ci = (src.get("ci95") or {}).get(key)
    if v is None:
        return "–"
    return (
        f"{v:.4f} [{ci[0]:.3f}, {ci[1]:.3f}]"
        if key == "rougeL" and ci
        else f"{v:.1f} [{ci[0]:.1f}, {ci[1]:.1f}]"
        if ci
        else f"{v}"
    )


# The principal issue's targets for the main row (front + side): the paper's 8B row on seen test, its unseen rows on
# the sealed splits. (key, title, split, failure-only, target); ROUGE-L targets are on the 0-1 scale.
TARGETS = (
    ("q2", "seen Q2", "test", False, 90.8),
    ("q3", "seen failure-only Q3", "test", True, 77.2),
    ("q4", "seen failure-only Q4", "test", True, 83.2),
    ("q5", "seen failure-only Q5", "test", True, 73.2),
    ("rougeL", "seen failure-only ROUGE-L", "test", True, 0.75),
    ("q2", "sealed unseen objects Q2", "test_object", False, 79.2),
    ("q2", "sealed unseen scene Q2", "test_scene", False, 85.6),
    ("q2", "sealed unseen objects and scene Q2", "test_both", False, 71.0),
)
MARGIN = 10.0  # points (0.10 for ROUGE-L) above the majority class and the blind model, on seen test
MARGIN_BASELINES = (MAJORITY, BLIND)  # a target is met only with both baselines run and both beaten by MARGIN


def _value(res: dict[str, Any], key: str, fo: bool) -> float | None:
    src = _scores(res, fo)
    return (src.get("q6") or {}).get("rougeL") if key == "rougeL" else src.get(key)


def _lower(res: dict[str, Any], key: str, fo: bool) -> float | None:
    """The lower end of a score's 95 % interval (by pair), None when the bench gave none."""
    ci = (_scores(res, fo).get("ci95") or {}).get(key)
    return float(ci[0]) if ci else None


WITHIN = "no: within its interval"  # a target's point reached, its 95 % interval reaching under it: not met


def targets(evals: dict[str, Any]) -> list[str]:
    """The principal issue's targets, each with its 95 % interval (by pair) and, on seen test, its margin over the
    majority class and the blind model; a split that was not run reads "not run". A target whose interval reaches
    under it is not met ("no: within its interval"), however its point estimate reads."""
    out = ["| goal | reached | target | met | 95 % interval / margin |", "|---|---|---|---|---|"]
    for key, name, split, fo, want in TARGETS:
        res = evals.get(split)
        got = _value(res, key, fo) if res else None
        margin = MARGIN / 100 if key == "rougeL" else MARGIN
        note, ok = (ci_cell(res, key, fo), got is not None and got >= want) if res else ("not run", False)
        if res and split == "test":
            bases = res["baselines"]
            over = {b: v for b in MARGIN_BASELINES if b in bases and (v := _value(bases[b], key, fo)) is not None}
            # rounded: 0.85 - 0.75 is 0.0999... in floating point, and a tie at the margin passes
            ok = ok and len(over) == 2 and all(round(got - v, 6) >= margin for v in over.values())
            note += "; " + ", ".join(f"{b} {over[b]}" if b in over else f"{b} not run" for b in MARGIN_BASELINES)
        met = "yes" if ok else "no"
        if ok and (lo := _lower(res, key, fo)) is not None and lo < want:
            met = WITHIN
        out.append(f"| {name} | {got if got is not None else '–'} | >= {want} | {met} | {note} |")
    q4 = [
        s
        for s, r in evals.items()
        if (major := (r["baselines"].get(MAJORITY) or {}).get("failure_only", {}).get("q4")) is not None
        and (r["failure_only"].get("q4") or 0) <= major
    ]
    out.append(
        "| failure-only Q4 above the majority class on every split | "
        + ("every split" if not q4 else "not on " + ", ".join(q4))
        + f" | all {len(evals)} run | {'yes' if not q4 else 'no'} | |"
    )
    low = [
        f"{t} {r['q2']:.0f}"
        for t, r in (evals["test"].get("q2_by_type") or {}).items()
        if t != "success" and r["n"] >= 20 and r["q2"] < 80
    ]
    out.append(
        "| seen Q2 recall >= 80 % for each failure type with >= 20 test failures | "
        + ("every type" if not low else ", ".join(low))
        + f" | >= 80 | {'yes' if not low else 'no'} | |"
    )
    return out


# What the page says of the sealed splits. Their shapes, sizes and texture kinds are drawn by nothing else, and their
# colour ranges by no family as drawn, but the colour augmentation of the tower shipped until 6 Dec (saturation up to
# x1.75, any hue) reaches those ranges (found 6 Dec); the claim a page written before then makes is restated by a
# splice. A run whose tower kept every pixel's saturation at most what was rendered claims the ranges unreached.
SEALED_CLAIM = (
    "the sealed catalogue and scene family: shapes, sizes and texture kinds that nothing trained, pretrained or "
    "tuned draws from, colour ranges outside every family drawn, which the page's tower's colour augmentation "
    "(saturation up to x1.75, any hue) nonetheless reaches;"
)
SEALED_CLAIM_KEPT = (
    "the sealed catalogue and scene family: shapes, sizes and texture kinds that nothing trained, pretrained or "
    "tuned draws from, colour ranges outside every family drawn and outside what the page's tower's colour "
    "augmentation makes of them (it never raised a pixel's saturation; the recipe's VQA training does not augment);"
)


def sealed_claim(raised: bool) -> str:
    """The page's words on the sealed splits for a run whose tower was pretrained raising saturation or not
    (model.tower.raised_saturation)."""
    return SEALED_CLAIM if raised else SEALED_CLAIM_KEPT


RESTATED_CLAIMS = {
    "the sealed catalogue and scene family, which nothing trained, pretrained or tuned draws from;": SEALED_CLAIM,
    # the words of 6 Dec afternoon, when the tower that raised saturation was still the shipped one
    "which the shipped tower's colour augmentation (saturation up to x1.75, any hue) nonetheless reaches;": (
        "which the page's tower's colour augmentation (saturation up to x1.75, any hue) nonetheless reaches;"
    ),
    "- Vision tower: `shipped` (sha256 `b64d9663c780c584...`, 1,515,008 parameters; what it learned and how well, "
    "held out: its TOWER_CARD.md).": (
        "- Vision tower: the one shipped until 6 Dec (sha256 `b64d9663c780c584...`, 1,515,008 parameters; what it "
        "learned and how well, held out: its TOWER_CARD.md in the history before 6 Dec's replacement)."
    ),
}


def restate(line: str) -> str:
    """A line of an older page as today's writer would put it: a targets row by today's rule (`restate_verdict`),
    a claim later found wrong corrected (RESTATED_CLAIMS)."""
    for old, new in RESTATED_CLAIMS.items():
        line = line.replace(old, new)
    return restate_verdict(line)


def restate_verdict(row: str) -> str:
    """A targets row as a page holds it, its verdict restated by `targets`' rule where the row reads "yes" and the
    lower end of its own printed interval is under the target (rows written before 3 Dec's rule read "yes" by the
    point alone, and a splice keeps them); any other line as it is."""
    cells = [c.strip() for c in row.strip().strip("|").split("|")] if row.startswith("| ") else []
    if len(cells) != 5 or cells[3] != "yes" or not cells[2].startswith(">= "):
        return row
    lo = re.match(r"-?[\d.]+ \[(-?[\d.]+), -?[\d.]+\]", cells[4])
    if lo is None or float(lo.group(1)) >= float(cells[2][3:]):
        return row
    return row.replace("| yes |", f"| {WITHIN} |", 1)


def per_type(res: dict[str, Any]) -> list[str]:
    """Q2 per failure type (the recall of that type) with its bootstrap-over-pairs interval, from the bench's
    `q2_by_type`; a results file written before the bench kept it has no interval to show."""
    out = ["| type | Q2 recall | 95 % interval (by pair) | n |", "|---|---|---|---|"]
    for name, row in (res.get("q2_by_type") or {}).items():
        lo, hi = row["ci95"]
        out.append(f"| {name} | {row['q2']:.1f} | {lo:.0f}-{hi:.0f} | {row['n']} |")
    return out


def named_rows(res: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The model's row and its baselines, titled as the tables print them."""
    return {
        "tiny LabRobFail-VLM (ours, free Q6)": res,
        **{
            f"tiny LabRobFail-VLM (ours, {k.split(', ')[-1]})" if k.endswith("Q6 template") else k: v
            for k, v in res["baselines"].items()
        },
    }


def paper_tables(evals: dict[str, Any]) -> list[str]:
    """The paper-comparable table of every split that was run, beside the paper's rows for its setting."""
    from labrobfail_vlm.bench.report import PAPER_ROWS, markdown, paper_row, paper_unseen_row

    lines = [
        PAPER_TABLES,
        "",
        "Q1 and Q2 over every trajectory of the split; Q3, Q4, Q5 and Q6 (BLEU, ROUGE-L) over its failed "
        'trajectories only, as the paper\'s table can be read (its Q4 and Q5 options have no "None"). The '
        "majority class answers Q3-Q6 with the most frequent answer among training failures. Where the blind "
        'baseline reaches Q1 = 100 (the preamble names the task), a tie at 100 counts as "above blind". '
        "Severity options are the paper's appendix ones; its main text names the same four levels Minor, "
        "Recoverable, Critical, Catastrophic (paired by position: option 1 = Minor ... 4 = Catastrophic). The "
        "paper's unseen rows stand beside both the validation and the sealed split of the same setting.",
        "",
    ]
    for split, res in evals.items():
        fo = res["failure_only"]
        rows = {k: paper_row(v) for k, v in named_rows(res).items()}
        unseen = paper_unseen_row(split)
        rows.update({"LabRobFail-VLM (paper, 8B)": unseen} if unseen else dict(PAPER_ROWS))
        n_traj = res["detection"]["trajectories"] if res.get("detection") else "?"
        lines += [
            markdown(
                rows, f"{SPLIT_TITLES[split]}: {n_traj} trajectories, Q3-Q6 over the {fo['trajectories']} failed ones"
            ),
            "95 % intervals by pair (ours, free Q6): "
            + ", ".join(
                f"{k} {ci_cell(res, k.lower(), k in ('Q3', 'Q4', 'Q5'))}" for k in ("Q1", "Q2", "Q3", "Q4", "Q5")
            )
            + f", ROUGE-L {ci_cell(res, 'rougeL', True)}.",
            "",
        ]
    return lines


def all_trajectory_tables(evals: dict[str, Any]) -> list[str]:
    from labrobfail_vlm.bench.report import markdown, row

    lines = [
        "## All-trajectory tables (the project's own; not comparable with the paper)",
        "",
        'Q3-Q6 over every trajectory: a success\'s reference is "None" / the no-correction sentence, so the '
        "majority class scores high on them.",
        "",
    ]
    for split, res in evals.items():
        title = f"{SPLIT_TITLES[split]}: {res['records']} records, all trajectories"
        lines += [markdown({k: row(v) for k, v in named_rows(res).items()}, title), ""]
    return lines


def model_section(evals: dict[str, Any]) -> list[str]:
    """A model beside the page's main one: the principal issue's targets for it (on the page's splits, as the main
    model's), then its scores on every split it ran (seen val too)."""
    lines = [
        *targets({s: r for s, r in evals.items() if s in SPLIT_TITLES}),
        "",
        "| split | Q2 | AUROC | Q3 (failures) | Q4 (failures) | Q5 (failures) | ROUGE-L (failures) |",
        "|---|---|---|---|---|---|---|",
    ]
    for s, r in evals.items():
        auroc = (r.get("detection") or {}).get("auroc")
        cells = [ci_cell(r, "q2"), "–" if auroc is None else str(auroc)]
        cells += [ci_cell(r, k, True) for k in ("q3", "q4", "q5", "rougeL")]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return lines


def sealed_section(dataset_dirs: Sequence[Path], kept: Sequence[str] = ()) -> list[str]:
    """Every bench run on a sealed split of the run's datasets (the bench's ledgers: the main dataset and those of the
    rows built from the same episodes with other views), oldest first, so a reader can count them. `kept`: the table
    rows a page already lists (a splice keeps them: a regeneration of the same episodes on a fresh machine brings a
    ledger of its own runs only, and no run the page counted may drop off it)."""
    entries = (e for d in dataset_dirs for e in sealed_runs(d))
    rows = list(dict.fromkeys([*kept, *map(_sealed_row, entries)]))  # a run listed twice counts once
    rows.sort(key=lambda r: r.split(" | ")[0])  # stable: each row opens with its date; same-minute runs keep order
    lines = [
        "## Sealed test runs",
        "",
        f"Every bench run on a sealed split of these episodes, oldest first ({len(rows)} in all; the bench appends "
        "one line per run to its dataset's `sealed_runs.jsonl`; a sensor row's dataset has its own). Figures: Q2 over "
        "all trajectories, the rest over failed ones.",
        "",
    ]
    if not rows:
        return lines + ["None yet.", ""]
    return [
        *lines,
        "| date | split | model | Q2 | Q3 | Q4 | Q5 | ROUGE-L |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
    ]


def _sealed_row(e: dict[str, Any]) -> str:
    """One ledger line as the page's table row."""
    cells = [e.get(k) for k in ("q2", "q3_failures", "q4_failures", "q5_failures", "rougeL_failures")]
    return (
        f"| {e['date']} | {e['split']} | `{e['source']}` | "
        + " | ".join("–" if c is None else str(c) for c in cells)
        + " |"
    )


# -- a run's model rows (scripts/write_results.py lays them out as the page's sections) --------------------

HELD_OUT_COLUMNS = ("val_object", "val_scene", "val_both", "test_object", "test_scene", "test_both")
# optional training runs beside the main one: folder under the run -> row title. rows/deep4: the 4-layer decoder beside
# the page's 2-layer main row on the same data (chosen on validation, 3 Dec; the recipe's REPRO_LAYERS since, so a
# page made by a later `make reproduce` has it as its main row); rows/more: the 4-layer recipe with 1.6x the seen
# training episodes at the same steps (chosen on validation, 4 Dec; `make reproduce-more`); rows/rand: the same extra
# pairs drawn in randomised scenes (4 Dec evening; `make reproduce-more MORE_FAMILY=randomised`); rows/rand_tuned: that
# row taught two one-epoch stages with the tower and merger tuned, on its data (4 Dec late night; `make reproduce-tuned
# TUNED_ROW=rand`); rows/rand2_tuned: one more such stage on its data plus 4,000 new randomised episodes (4 Dec
# midnight; `make reproduce-tuned TUNED_ROW=rand2`); rows/rand3_tuned: one more stage from that row on the seen data
# plus 4,000 further new randomised episodes (5 Dec; `TUNED_ROW=rand3`); rows/lit: the same chain of commands on the
# episodes drawn as `make reproduce` draws them since 5 Dec (broken glass, the button lamp; 6 Dec, docs/EXPERIMENTS.md);
# rows/lit_cal: that model with option biases fitted on its seen val (labrobfail-calibrate); rows/lit_q: that model
# reading P(failure) from Q2-Q5 (failure_score questions); rows/lit5_q: that row taught a fifth tuned stage on 4,000
# more lit randomised episodes; rows/rand5_q: the same five stages read from Q2-Q5 on `make reproduce`'s data and
# tower (6 Dec late night). No make target makes rows/deep4, the lit rows or rows/rand5_q alone, so a page never
# lists them as not run (BY_HAND).
ROWS = {
    "rows/scratch": "scratch tower (random init, stage A grounding: the pre-tower recipe)",
    "train": "sim-pretrained tower (shipped), front + side",
    "rows/wrist": "sim-pretrained tower, front + wrist (sensor ablation, not the paper's views)",
    "rows/three": (
        "sim-pretrained tower, front + side + wrist (sensor ablation, not the paper's views; a 512x768 grid of the "
        "same 128-px cells)"
    ),
    "rows/deep4": (
        "sim-pretrained tower, front + side, 4-layer decoder (chosen on validation; the recipe since 3 Dec)"
    ),
    "rows/more": (
        "sim-pretrained tower, front + side, 4-layer decoder, 1.6x the seen training episodes at the same steps "
        "(chosen on validation, 4 Dec)"
    ),
    "rows/rand": (
        "sim-pretrained tower, front + side, 4-layer decoder, 4,000 extra seen episodes (1.6x) drawn in randomised "
        "scenes at the same steps (chosen on validation, 4 Dec evening)"
    ),
    "rows/rand_tuned": (
        "the randomised-scenes row, then two one-epoch stages with the tower and merger tuned (3e-5) on its data "
        "(chosen on validation, 4 Dec late night)"
    ),
    "rows/rand2_tuned": (
        "the two-stage row above, then a third tuned stage on its data plus 4,000 new seen episodes in randomised "
        "scenes (chosen on validation, 4 Dec midnight)"
    ),
    "rows/rand3_tuned": (
        "the row above, then a fourth tuned stage on the seen training split plus 4,000 further new seen episodes in "
        "randomised scenes (chosen on validation, 5 Dec)"
    ),
    "rows/lit": (
        "the four-stage row above remade on the same episodes drawn lit (broken glass and the button lamp, as `make "
        "reproduce` draws them since 5 Dec; one seen-test trajectory relabelled Fatal by the 5 Dec labeler; chosen "
        "on validation, 6 Dec)"
    ),
    "rows/lit_cal": (
        "the lit row above with option biases for Q3-Q5 fitted on its seen-val bench (`labrobfail-calibrate`, "
        "likelihood; Q2 untouched; chosen on validation, 6 Dec)"
    ),
    "rows/lit_q": (
        "the lit row above reading P(failure) from all four closed questions (the mean of Q2's P(Yes) and Q3-Q5's "
        "P(not None): `failure_score: questions`; nothing fitted; chosen on validation, 6 Dec)"
    ),
    "rows/lit5_q": (
        "the lit row taught a fifth tuned stage on the seen training split plus 4,000 more lit randomised episodes "
        "(pairs 10000-11999), read as the row above from all four questions (chosen on validation, 6 Dec)"
    ),
    "rows/rand5_q": (
        "the randomised row and four tuned stages on `make reproduce`'s data from the tower shipped since 6 Dec night "
        "(sha256 `ae35c909...`; `make reproduce-more "
        "MORE_FAMILY=randomised`, `make reproduce-tuned`), then a fifth tuned stage on the seen training split plus "
        "4,000 more randomised episodes (pairs 10000-11999), P(failure) read from all four closed questions (6 Dec's "
        "best lit chain, each step chosen on validation on 4-6 Dec)"
    ),
}
BY_HAND = ("rows/deep4", "rows/lit", "rows/lit_cal", "rows/lit_q", "rows/lit5_q", "rows/rand5_q")
# rows also shown at the operating point chosen on their own seen-val bench (eval_<split>_opval, `labrobfail-evaluate
# threshold=val`), with the date the cut was adopted on validation (docs/EXPERIMENTS.md); make reproduce-more
# (rows/rand) and make report-tuned (the tuned rows) bench it
OPVAL_ROWS = {"rows/rand": "4 Dec night", "rows/rand_tuned": "4 Dec late night", "rows/rand3_tuned": "5 Dec"}
ABLATIONS = {
    "ablate/tuned": "tuned tower and merger",
    "ablate/frozen": "frozen tower and merger",
    "ablate/no_index": "no temporal index (no labels drawn, none mentioned)",
}
NOT_RUN = "Not run for this page: "  # how a table or the page names the runs it lacks
CARRIED = "Carried from the page (not benched in the run it was spliced from): "
MAIN_KEPT = "Kept from the page: its main row, the model its other sections describe, "
OPVAL_LINE = "| the row above at "  # a row at its val-chosen cut, the line under its 0.5 row


def run_evals(folder: Path, splits: tuple[str, ...] = tuple(SPLIT_TITLES), suffix: str = "") -> dict[str, Any] | None:
    """A training folder's bench results per split (benches named eval_<split><suffix>), or None when it has not
    been run."""
    files = {s: folder / "final" / f"eval_{s}{suffix}" / "results.json" for s in splits}
    return {s: json.loads(f.read_text()) for s, f in files.items() if f.is_file()} or None


def lit_table(run: Path, row: str = "rows/lit") -> list[str]:
    """A model row made by hand on lit episodes (rows/lit, rows/lit_q, rows/lit5_q: see ROWS): the principal
    issue's targets again, then every split."""
    return model_section(run_evals(run / row, ("val", *SPLIT_TITLES)) or {})


def tuned_table(run: Path) -> list[str]:
    """`make reproduce-tuned`'s model: the principal issue's targets again, then its scores on every split it ran."""
    return model_section(run_evals(run / "tuned", ("val", *SPLIT_TITLES)) or {})  # val: a row, not a target split


def rows_table(run: Path, page: list[str] | None = None) -> list[str]:
    """Tower and sensor rows side by side: seen Q2 and AUROC, failure-only Q3/Q5/ROUGE-L, Q2 on each held-out split
    (validation, then sealed). `page` (the existing page's lines, when a splice replaces its rows table): a row the
    run has no seen test bench for keeps the page's line (and the line at its val-chosen cut under it), named as
    carried, so a run that re-benched one row never drops the others; the main row (`train`) is the whole page's
    model, described by its other sections, so a splice keeps the page's line for it whatever the run holds (a later
    run's `train` is another model: its own whole page, or a row added by hand)."""
    head = [
        "| row | seen Q2 | seen AUROC | seen Q3 (failures) | seen Q5 (failures) | ROUGE-L (failures) | "
        + " | ".join(f"{s.replace('_', ' ')} Q2" for s in HELD_OUT_COLUMNS)
        + " |",
        "|---|---|---|---|---|---|" + "---|" * len(HELD_OUT_COLUMNS),
    ]
    blocks: dict[str | None, list[str]] = {None: []}  # per ROWS title, its lines (None: before the first)
    missing, carried, own = [], [], []
    for folder, title in ROWS.items():
        ev = run_evals(run / folder) or {}
        not_cut = f"{title}, at its operating point chosen on val (`{folder}`, threshold=val)"
        kept = _page_row(page or [], title)
        if kept and ("test" not in ev or folder == "train"):
            blocks[title] = kept
            if "test" in ev:  # the main row, benched in the run, but as another model than the page's
                own = [f"{MAIN_KEPT}{title} (`{folder}`); the run's own `{folder}` is another model."]
                continue
            carried.append(f"{title} (`{folder}`)")
            if folder in OPVAL_ROWS and len(kept) == 1:
                missing.append(not_cut)
            continue
        if "test" not in ev:
            if folder not in BY_HAND:
                missing.append(f"{title} (`{folder}`)")
            continue
        blocks[title] = [_rows_line(title, ev)]
        if folder in OPVAL_ROWS:
            if "test" not in (op := run_evals(run / folder, suffix="_opval") or {}):
                missing.append(not_cut)
                continue
            cut = f"P(failure) >= {op['test']['threshold']:.3f}"
            blocks[title].append(
                _rows_line(f"{OPVAL_LINE[2:]}{cut}, the cut chosen on its seen-val bench ({OPVAL_ROWS[folder]})", op)
            )
    for above, line in _hand_rows(page or []):  # rows no folder makes stay where the page had them
        blocks.setdefault(above if above in blocks else None, []).append(line)
        name = line.split(" | ")[0].removeprefix("| ")
        carried.append(name if "added by hand" in name else f"{name} (added by hand)")
    lines = [line for block in blocks.values() for line in block]
    if not lines:
        return []
    said = ["", CARRIED + "; ".join(carried) + "."] if carried else []
    return head + lines + said + (["", *own] if own else []) + _not_run(missing)


def _hand_rows(page: list[str]) -> list[tuple[str | None, str]]:
    """The page's table rows that no ROWS title makes (added by hand), each with the ROWS title of the row above it
    (None: none above)."""
    out: list[tuple[str | None, str]] = []
    above = None
    for line in page:
        if not line.startswith("| ") or line.startswith(("| row |", OPVAL_LINE)):
            continue
        title = next((t for t in ROWS.values() if line.startswith(f"| {t} |")), None)
        if title is None:
            out.append((above, line))
        above = title or above
    return out


def _page_row(page: list[str], title: str) -> list[str]:
    """The page's line of the row titled `title` and the line at its cut right under it (none: [])."""
    at = next((i for i, line in enumerate(page) if line.startswith(f"| {title} |")), None)
    if at is None:
        return []
    below = page[at + 1 : at + 2]
    return [page[at], *(line for line in below if line.startswith(OPVAL_LINE))]


def _rows_line(title: str, ev: dict[str, Any]) -> str:
    """One row of the rows table from a model's benches (seen test, then each held-out split it ran)."""
    t = ev["test"]
    det = (t.get("detection") or {}).get("auroc")
    return (
        f"| {title} | {ci_cell(t, 'q2')} | {det} | {ci_cell(t, 'q3', True)} | {ci_cell(t, 'q5', True)} | "
        f"{ci_cell(t, 'rougeL', True)} | "
        + " | ".join(ci_cell(ev[s], "q2") if s in ev else "–" for s in HELD_OUT_COLUMNS)
        + " |"
    )


def _not_run(missing: list[str]) -> list[str]:
    """The closing line of a table that names the runs it lacks (`make reproduce-rows` / `make ablate` steps)."""
    return ["", NOT_RUN + "; ".join(missing) + "."] if missing else []


def ablation_table(run: Path, frozen_cells: list[str] | None = None) -> list[str]:
    """The paper's ablation table (seen split: Q2, Q3, Q5, Q6 ROUGE-L) for the runs `make ablate` made.
    `frozen_cells` (Q2, Q3, Q5, ROUGE-L as the page shows them) stand in for a run without `ablate/frozen`."""
    from labrobfail_vlm.bench.report import PAPER_ABLATION

    lines, missing = [], []
    for folder, title in ABLATIONS.items():
        ev = run_evals(run / folder, ("test",))
        if not ev and folder == "ablate/frozen" and frozen_cells:
            lines.append(f"| {title} (this page's `make reproduce` model) | " + " | ".join(frozen_cells) + " |")
        elif ev:
            t = ev["test"]
            lines.append(
                f"| {title} | {ci_cell(t, 'q2')} | {ci_cell(t, 'q3', True)} | {ci_cell(t, 'q5', True)} | "
                f"{ci_cell(t, 'rougeL', True)} |"
            )
        else:
            missing.append(f"{title} (`{folder}`)")
    if not lines:
        return []
    return [
        "| variant | Q2 | Q3 (failures) | Q5 (failures) | Q6 ROUGE-L (failures) |",
        "|---|---|---|---|---|",
        *lines,
        *(f"| {k} | {v[0]} | {v[1]} | {v[2]} | {v[3]} |" for k, v in PAPER_ABLATION.items()),
        *_not_run(missing),
    ]
