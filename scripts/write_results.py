"""Write docs/RESULTS.md from a `make reproduce` run (and, where they exist, `make reproduce-rows` and `make ablate`).

Run as:
    python scripts/write_results.py run=outputs/reproduce out=docs/RESULTS.md

Reads <run>/dataset/stats.json, <run>/timeline.txt (one "<step> <unix seconds>" line per step), the main model's
<run>/train/{train_summary,progress}.json and final/eval_<split>/results.json, the tower card it started from,
`make reproduce-tuned`'s model <run>/tuned/, the optional rows (page.ROWS: <run>/rows/{scratch,wrist,more,rand,...}/)
and ablations <run>/ablate/{frozen,tuned,no_index}/ (same layout), `make reproduce-online`'s model <run>/online/, `make
online-bench`'s <run>/train/final/eval_online_*/online.json and `make recovery`'s tables
<run>/recovery/{scripted,act/<task>}/. Sections: the issue's targets, the tuned model's section, the tower and
sensor rows, the paper's ablation table, supervision (the online model on whole and prefix grids, the online bench,
the recovery table), the paper-comparable tables
(Q3-Q6 over failed trajectories) with 95 % intervals, failure detection as a score, the all-trajectory tables,
Q2 recall per failure type, the learning curve. The sealed runs the page it replaces listed stay on its list, and
`carry=[supervision]` (any of SECTIONS) keeps that page's section where the run has none, and under the run's where
it has one (`carry=[rows]`: no row of the replaced page is lost), marked as carried with that page's data, physics
and tower lines; a later `sections=[rows]` splice leaves the rows carried so in their block.

With `sections=[rand5_q]`, `[lit]`, `[lit_q]`, `[lit5_q]`, `[tuned]`, `[rows]`, `[ablation]` or `[supervision]` it
replaces only those sections of the existing page, from a run that holds just those folders (a fresh machine's
regeneration with the same seed, say): it checks first that the run's data are the page's (the same trajectories and
splits line); a run that ran sealed splits brings its datasets' ledgers of sealed runs, whose runs join the page's
list (which keeps every run it had; `sealed` alone splices nothing else, for a regeneration that re-ran only the
recipe's sealed benches, and takes a run whose data line differs from the page's: every look at a sealed split is
listed). What such a run lacks is carried from the page and said so: the rows table keeps the page's line for every
row the run has no seen test bench for (with its line at the val-chosen cut), the ablation's frozen row is the page's
shipped front + side row (the recipe's model is the frozen one), the online model's table and the online bench stay
when the run has only recovery tables, the online model's table and every recovery row stay when it has only the
online bench, and the page's recovery rows stay for cells the run did not re-measure (the table's lead line names
them as carried)."""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path
from typing import Any

from labrobfail_vlm.bench.online_page import online_md
from labrobfail_vlm.bench.page import (
    MAIN_KEPT,
    NOT_RUN,
    PAPER_TABLES,
    ROWS,
    SPLIT_TITLES,
    ablation_table,
    all_trajectory_tables,
    ci_cell,
    lit_table,
    named_rows,
    paper_tables,
    per_type,
    restate,
    rows_table,
    run_evals,
    sealed_claim,
    sealed_section,
    targets,
    tuned_table,
)
from labrobfail_vlm.config import ConfigError, cli_main, load_config
from labrobfail_vlm.io import atomic_write_bytes
from labrobfail_vlm.model.tower import raised_saturation
from sim_backends.generate import run_physics
from sim_backends.supervision.report import CARRIED as CARRIED_ROWS
from sim_backends.supervision.report import (
    LEAD,
    LEADS,
    block,
    page_recovery,
    recovery_files,
    recovery_md,
)

DEFAULTS = """
run: outputs/reproduce     # the make reproduce run folder
out: docs/RESULTS.md       # the page to write
sections: null             # null: the whole page; any of SECTIONS' names or sealed (e.g. [lit_q, rows]): only those
carry: []                  # whole page: sections of the page it replaces to keep (e.g. [supervision]: recovery
                           # tables made on another run; [rows]: its rows, under the run's), each marked as carried
"""
# the sections a run beside the main one can add: heading, opening sentence, the run folders that feed it
SECTIONS = {
    "rand5_q": (
        "## Five tuned stages, read from all four questions (the best front + side model on the tower shipped since "
        "6 Dec night)",
        "The principal issue's targets for `rows/rand5_q` of the rows table below, then its scores on every split it "
        "ran (95 % intervals by pair): `make reproduce`'s data and tower, the randomised row (`make reproduce-more "
        "MORE_FAMILY=randomised`), its tuned stages (`make reproduce-tuned TUNED_ROW=rand`, `rand2`, `rand3`), one "
        "more stage on the seen training split plus 4,000 more randomised episodes (pairs 10000-11999, in no split), "
        "and P(failure) read from all four closed questions (`failure_score: questions`): the chain each of whose "
        "steps was chosen on validation on 4-6 Dec, run once on seen test and the sealed splits (docs/EXPERIMENTS.md, "
        "6 Dec late night).",
        ("rows/rand5_q",),
    ),
    "lit": (
        "## The tuned chain drawn lit",
        "The principal issue's targets for `rows/lit` of the rows table below, then its scores on every split it ran "
        "(95 % intervals by pair): the randomised row and its four tuned stages remade on the same episodes drawn as "
        "`make reproduce` draws them since 5 Dec (broken glass, the button lamp), adopted over the unlit chain by a "
        "rule written before its figures and run once on seen test and the sealed splits (docs/EXPERIMENTS.md, 6 "
        "Dec). Its seen test differs from the page's in one trajectory's label (relabelled a Fatal failure by the "
        "5 Dec labeler).",
        ("rows/lit",),
    ),
    "lit_q": (
        "## The lit row with detection from all four closed questions",
        "The principal issue's targets for `rows/lit_q` of the rows table below, then its scores on every split it "
        "ran (95 % intervals by pair): the lit row's weights, its P(failure) read as the mean of Q2's P(Yes) and "
        "Q3-Q5's P(not None) (the model is taught None as their reply to every success; nothing fitted), adopted "
        "by a rule written before its figures and run once on seen test and the sealed splits (docs/EXPERIMENTS.md, "
        "6 Dec).",
        ("rows/lit_q",),
    ),
    "lit5_q": (
        "## A fifth lit stage, read from all four questions (the best front + side model so far)",
        "The principal issue's targets for `rows/lit5_q` of the rows table below, then its scores on every split it "
        "ran (95 % intervals by pair): the lit row taught one more tuned stage (3e-5, one epoch) on the seen "
        "training split plus 4,000 more randomised episodes drawn lit (pairs 10000-11999, in no split), its "
        "P(failure) read from all four closed questions as `rows/lit_q`'s, adopted by a rule written before its "
        "figures and run once on seen test and the sealed splits (docs/EXPERIMENTS.md, 6 Dec).",
        ("rows/lit5_q",),
    ),
    "tuned": (
        "## The tuned continuation (make reproduce-tuned)",
        "`make reproduce-tuned`: the model above taught more one-epoch stages with the vision tower and merger tuned "
        "(3e-5 each), each from the one before, the stage count chosen on the validation splits (docs/EXPERIMENTS.md); "
        "`make report-tuned` ran the seen test and the sealed splits once for this section. The principal issue's "
        "targets for this model, then its scores on every split it ran (95 % intervals by pair).",
        ("tuned",),
    ),
    "rows": (
        "## Tower and sensor rows",
        "The same bench on the same validation and test trajectories; each row names what differs (the tower, the "
        "views, the decoder's depth, the training episodes, the scenes' appearance). 95 % intervals: bootstrap over "
        "pairs.",
        tuple(f for f in ROWS if f != "train"),  # every row the table knows; the main row is the page's own
    ),
    "ablation": (
        "## Ablation (the paper's table, seen split)",
        "The same data and bench; only the variant differs. 95 % intervals: bootstrap over pairs.",
        ("ablate/tuned", "ablate/frozen", "ablate/no_index"),
    ),
    "supervision": (
        "## Supervision",
        "The online bench asks a model on each prefix grid (the first k keyframes, later cells blank); each table "
        "names its model: `train/final` is `make reproduce`'s, never taught prefix grids, `online/final` is `make "
        "reproduce-online`'s, taught them in a third stage. `make recovery`: the scripted and ACT policies with and "
        "without a VLM supervisor, each trial from the same seed both ways, on the reporting seed block "
        "(`RECOVERY_SEED`, 20000-20099 for 100 trials) that no choice saw (choices: seeds 0-49 and the development "
        "block 10000-10099); the line above its table names the model and when it was asked (`actft`: "
        "the model above taught one more epoch with the pour ACT's own rollouts, labeled by the labeler, for the ACT "
        "pour cell; chosen on the development block, docs/EXPERIMENTS.md 2 Dec). `make recovery-monitor`: the "
        "scripted cells the same way with the online bench's robot-signal alarm deciding while the policy runs (the "
        "row chosen on validation, saved by the bench) and the model asked only in episodes it flagged; its design "
        "chosen on the development block and reported on its own block, 23000-23099, with `online/final` diagnosing "
        "(docs/EXPERIMENTS.md, 7 Dec night to late night, third). `make recovery-act-alarm`: an ACT cell whose "
        "model was taught one epoch of that ACT's own rollouts and whose alarm was calibrated on that ACT's "
        "successes in other rollouts (FIPER's way; rollouts on seeds from 40000 up, apart from every block), the "
        "model asked once when the ACT stops and intervening only above the threshold; its design chosen on the "
        "development block, each task reported on its own block (docs/EXPERIMENTS.md, 7 Dec late night, seventh to "
        "ninth). The pour ACT succeeds in none of its rollouts: its cell has nothing to calibrate on.",
        ("online", "recovery", "train/final/eval_online_*", "online_power*"),
    ),
}
# the sections of rows made by hand (page.BY_HAND): each a lit_table of its one folder, never named as not run
BY_HAND_SECTIONS = ("rand5_q", "lit", "lit_q", "lit5_q")


def _load(path: Path) -> Any:
    if not path.is_file():
        raise ConfigError(f"results: {path} is missing (run `make reproduce` first)")
    return json.loads(path.read_text())


def _data_line(stats: dict[str, Any]) -> str:
    """The page's trajectories line: what a run spliced into the page must match."""
    return (
        f"- Trajectories: {stats['trajectories_kept']} kept of {stats['trajectories_in']} "
        f"({stats['by_outcome']['success']} success, {stats['by_outcome']['failure']} failure); split sizes "
        "(trajectories): " + ", ".join(f"{k} {v['trajectories']}" for k, v in stats["splits"].items()) + "."
    )


def _sections(page: str) -> list[list[str]]:
    """The page cut at its "## " headings: the preamble first, then one list of lines per section."""
    out: list[list[str]] = [[]]
    for line in page.splitlines():
        if line.startswith("## "):
            out.append([])
        out[-1].append(line)
    return out


MADE_ON = "Made on `{}`, whose data are this page's."  # a spliced section's run (_made_elsewhere reads it back)


def relabelled(run: Path) -> list[str]:
    """A line for a run whose shards scripts/relabel_shards.py re-derived (their manifests' `relabelled` entries):
    the same episodes as the run it read, some labels moved by a later labeler; [] for a generated run."""
    entries = [m["relabelled"] for f in sorted(run.glob("shards/*/manifest.json")) if "relabelled" in (m := _load(f))]
    if not entries:
        return []
    changed = sum((Counter(e["changed"]) for e in entries), Counter())
    source = sorted({str(Path(e["from"]).parent) for e in entries})
    cols = ", ".join(f"{k} {n}" for k, n in sorted(changed.items())) or "none"
    return [
        f"Its shards are `{'`, `'.join(source)}`'s episodes with every label re-derived from their traces by "
        f"`scripts/relabel_shards.py` with a later labeler; episodes changed per label column: {cols}."
    ]


def _section(name: str, body: list[str], made_on: Path | None = None) -> list[str]:
    """A section of SECTIONS as the page prints it: heading, opening sentence (and the run a splice took it
    from, with its relabelling), the table."""
    heading, intro, _ = SECTIONS[name]
    return [
        heading,
        "",
        intro,
        *([MADE_ON.format(made_on), *relabelled(made_on)] if made_on else []),
        "",
        *body,
        "",
    ]


def _absent(name: str) -> str:
    """How the page names a section of SECTIONS it lacks: its heading and the run folders that would feed it."""
    heading, _, folders = SECTIONS[name]
    return f"{heading.removeprefix('## ')} (`{'`, `'.join(folders)}`)"


def _absent_line(part: list[str]) -> list[str]:
    """The whole page's line naming the sections it lacks: written after the last section present, so a splice
    of that section must carry it."""
    return [line for line in part if line.startswith(NOT_RUN) and any(_absent(n) in line for n in SECTIONS)]


def splice(run: Path, out: Path, names: list[str]) -> int:
    """Replace the named sections of the existing page with this run's, leaving every other line as it was."""
    unknown = sorted(set(names) - set(SECTIONS) - {"sealed"})
    if unknown:
        raise ConfigError(f"sections: unknown {unknown}; choose from {sorted(SECTIONS) + ['sealed']}")
    if not out.is_file():
        raise ConfigError(f"sections: {out} does not exist; write the whole page first (sections=null)")
    parts = _sections(out.read_text())
    tables = [n for n in names if n != "sealed"]  # sealed: the ledgers alone, spliced below
    # a table must be of the page's data; a sealed run is listed whatever data it was made on (every look counts)
    if tables and _data_line(_load(run / "dataset" / "stats.json")) not in (line for p in parts for line in p):
        raise ConfigError(f"sections: {run}'s data are not {out}'s (its trajectories and splits line differs)")
    shipped = next((line for p in parts for line in p if line.startswith(f"| {ROWS['train']} |")), None)
    cells = [c.strip() for c in shipped.strip("|").split("|")] if shipped else None
    old_sv = next((p for p in parts if p[0] == SECTIONS["supervision"][0]), [])
    rows_head = SECTIONS["rows"][0]
    bodies = {
        # the page's own rows only: rows it carried from a replaced page stay in their block, re-appended below
        "rows": lambda: rows_table(run, _beside(next((p for p in parts if p[0] == rows_head), []), rows_head)[0]),
        # the shipped row's seen Q2, Q3, Q5 and ROUGE-L cells
        "ablation": lambda: ablation_table(run, [cells[1], cells[3], cells[4], cells[5]] if cells else None),
        "supervision": lambda: supervision(run, old_sv),
        "tuned": lambda: tuned_table(run),
        **{n: (lambda n=n: lit_table(run, SECTIONS[n][2][0])) for n in BY_HAND_SECTIONS},
    }
    for name in tables:
        heading, _, folders = SECTIONS[name]
        if not any(_ran(run, f) for f in folders):
            raise ConfigError(f"sections: {run} has no results under {', '.join(folders)}")
        body = bodies[name]()
        if name == "supervision":  # the provenance of what it still carries from the page it once replaced
            body = [*_still_carried(old_sv, body), *body]
        new = _section(name, body, made_on=run)
        at = next((i for i, p in enumerate(parts) if p[0] == heading), None)
        if at is None:  # a new section goes where the whole page puts it: before the later ones
            later = [h for h, _, _ in list(SECTIONS.values())[list(SECTIONS).index(name) + 1 :]] + [PAPER_TABLES]
            at = next((i for i, p in enumerate(parts) if any(p[0].startswith(h) for h in later)), len(parts))
            parts.insert(at, new)
        else:
            kept = _absent_line(parts[at])
            block = _beside(parts[at], heading)[1]  # what the section carried from a replaced page stays
            parts[at] = new + ([*kept, ""] if kept else []) + ([_beside_heading(heading), "", *block] if block else [])
    _drop_absent(parts, tables)
    if not _splice_ledger(run, parts) and "sealed" in names:
        raise ConfigError(f"sections: {run} has no sealed runs in its datasets' ledgers")
    # what the splice kept from an older page reads as today's writer puts it (`page.restate`)
    atomic_write_bytes(out, ("\n".join(restate(line) for p in parts for line in p) + "\n").encode())
    print(out)
    return 0


AS_THE_PAGE_HAD_IT = "as the page had it (this run has none)"  # a stand-in's lead (_still_carried looks for it)
STILL_CARRIED = (
    "The parts of this section marked as the page had them or carried from the page are older: made on another "
    "run, whose data line, tower and models are those their own lines name, not this page's."
)


def _still_carried(old: list[str], body: list[str]) -> list[str]:
    """The old Supervision section's provenance paragraph (it was carried whole from a replaced page) for a splice
    whose new section still carries some of it (recovery cells not re-run, the online model's table): without it
    the splice's "whose data are this page's" line would seem to claim those parts too. [] when nothing is carried
    or the old section had no such paragraph. It speaks of every carried part: a chain of splices that first
    re-measures some of them on this page's data and then carries those would keep it over them too (the parts
    carry no run of their own to tell apart)."""
    own = _beside(old, SECTIONS["supervision"][0])[0]  # not a block a whole-page rewrite put under it
    said = next((x for x in own if x.startswith((CARRIED_SECTION, STILL_CARRIED))), None)
    if said is None or not any(CARRIED_ROWS in x or AS_THE_PAGE_HAD_IT in x for x in body):
        return []
    return [STILL_CARRIED + said.removeprefix(CARRIED_SECTION).removeprefix(STILL_CARRIED), ""]


def _datasets(run: Path) -> list[Path]:
    """The run's dataset folders: `dataset` and the rows' (`dataset_wrist`, `dataset_noindex`), each with its ledger."""
    return [d for d in sorted(run.glob("dataset*")) if d.is_dir()]


def _drop_absent(parts: list[list[str]], names: list[str]) -> None:
    """Strike the spliced sections from the page's "Not run for this page" line (the line goes when none is left)."""
    spliced = {_absent(n) for n in names}
    for p in parts:
        for i, line in enumerate(p):
            if line.startswith(NOT_RUN):
                left = [a for a in line.removeprefix(NOT_RUN).removesuffix(".").split("; ") if a and a not in spliced]
                p[i] = NOT_RUN + "; ".join(left) + "." if left else ""


def _dated_rows(lines: list[str]) -> list[str]:
    """The sealed-run table's rows (each opens with its run's date), without its heading and rules."""
    return [line for line in lines if line.startswith("| 20")]


CARRIED_SECTION = (
    "Carried from the page this one replaced (`carry`): made on another run, whose data line, tower and models are "
    "those its own lines name, not this page's."
)
DATA_HEADING = "## Data and model"
CARRIED_FROM = (
    "- Trajectories:",
    "- Physics:",
    "- Vision tower:",
)  # the replaced page's lines a carried section's lead repeats


def model_sections(run: Path, out: Path, carry: list[str]) -> list[str]:
    """The whole page's sections of models beside the main one (SECTIONS, in its order): each from the run where it
    has one; else, when named in `carry`, the section of the page at `out` that this page replaces, marked as
    carried; else named on the page's "Not run" line. A section named in `carry` that the run has too (the rows
    table, say) is printed from the run, the replaced page's lines under it (`_beside`), marked as carried: no row is
    lost. A page written again from the same run (its data line unchanged) keeps what it carried as it was."""
    unknown = sorted(set(carry) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"carry: unknown {unknown}; choose from {sorted(SECTIONS)}")
    old_parts = _sections(out.read_text()) if carry and out.is_file() else []
    old = {p[0]: p for p in old_parts}
    if lacking := [n for n in carry if SECTIONS[n][0] not in old]:
        raise ConfigError(f"carry: {out} has no {', '.join(lacking)} section to carry")
    data = _data_line(_load(run / "dataset" / "stats.json"))
    same_run = any(line == data for p in old_parts if p[0] == DATA_HEADING for line in p)
    lead = [] if same_run else [CARRIED_SECTION + _old_provenance(old_parts)]
    lines: list[str] = []
    absent = []
    made = {n: lit_table(run, SECTIONS[n][2][0]) if _ran(run, SECTIONS[n][2][0]) else [] for n in BY_HAND_SECTIONS}
    made |= {"tuned": tuned_table(run) if _ran(run, "tuned") else [], "rows": rows_table(run)}
    made |= {"ablation": ablation_table(run), "supervision": supervision(run)}
    for name in SECTIONS:
        heading, intro, _ = SECTIONS[name]
        own, block = _beside(old.get(heading, [heading])[1:], heading)
        if made[name]:
            lines += _section(name, made[name])
            if name in carry:  # the old page's own table (unless this run's) under the lead, then what it carried
                kept = ([] if same_run else [*lead, *_trim(_kept([x for x in own if x != intro])), ""]) + _kept(block)
                lines += [_beside_heading(heading), "", *_trim(kept), ""] if _trim(kept) else []
        elif name in carry:  # a section carried before keeps its own lead (it names where it was made)
            carried_before = any(x.startswith(CARRIED_SECTION) for x in own)
            lines += [heading, "", *([] if carried_before else [*lead, ""]), *_trim(_kept(own)), ""]
        elif name not in BY_HAND_SECTIONS:  # a section no make target makes is never named as not run
            absent.append(_absent(name))
    if absent:  # say what this page lacks rather than leave a reader to notice a missing section
        lines += [NOT_RUN + "; ".join(absent) + ".", ""]
    return lines


def _beside_heading(heading: str) -> str:
    """The sub-heading under which a section the run has too keeps the replaced page's lines."""
    return f"### {heading.removeprefix('## ')}: the page this one replaced"


def _beside(body: list[str], heading: str) -> tuple[list[str], list[str]]:
    """A section's lines after its heading cut at its carried sub-block (`_beside_heading`): its own lines, then the
    lines the block carried from an older page (without the sub-heading; [] when it has none)."""
    sub = _beside_heading(heading)
    if sub not in body:
        return body, []
    at = body.index(sub)
    return body[:at], _trim(body[at + 1 :])


def _trim(lines: list[str]) -> list[str]:
    """Lines without the blank ones at either end (a carried part is printed between one blank line and the next)."""
    first = next((i for i, x in enumerate(lines) if x), len(lines))
    last = next((i for i in range(len(lines), 0, -1) if lines[i - 1]), first)
    return lines[first:last]


def _kept(lines: list[str]) -> list[str]:
    """A carried section's lines as the new page prints them: without the "Not run" and "Kept from the page" lines
    (they spoke of the replaced page's own sections), "Made on" lines no longer claiming this page's data, and every
    line restated as today's writer puts it (`page.restate`)."""
    return [restate(_made_elsewhere(x)) for x in lines if not x.startswith((NOT_RUN, MAIN_KEPT))]


def _old_provenance(parts: list[list[str]]) -> str:
    """What the replaced page said of its data, physics and tower (its Data and model lines), for the lead of a
    section carried from it: a carried table's rows name none of them."""
    data = [restate(x) for p in parts if p[0] == DATA_HEADING for x in p]
    said = {key: next((x.removeprefix("- ") for x in data if x.startswith(key)), None) for key in CARRIED_FROM}
    if not said["- Trajectories:"]:
        return ""
    said["- Physics:"] = said["- Physics:"] or "Physics: not stated."
    return " That page's data and tower: " + " ".join(x for x in said.values() if x)


def _made_elsewhere(line: str) -> str:
    """A carried section's "Made on" line (a splice's), which said its run's data were the page's: no longer so."""
    made = re.fullmatch(re.escape(MADE_ON).replace(re.escape("{}"), "(.+)"), line)
    return f"Made on `{made[1]}`, on another data line than this page's." if made else line


def page_ledger(out: Path) -> list[str]:
    """The sealed runs an existing page lists (none for a new page): a whole page written over it keeps them, as a
    splice does, whatever data the new run was made on, since every look at a sealed split counts."""
    if not out.is_file():
        return []
    heading = sealed_section([])[0]
    return [row for p in _sections(out.read_text()) if p[0] == heading for row in _dated_rows(p)]


def _splice_ledger(run: Path, parts: list[list[str]]) -> bool:
    """A run that ran sealed splits brings its datasets' ledgers: their runs join the page's "Sealed test runs" list
    (made before the paper tables on a page without one), which keeps every run it listed (a ledger started afresh,
    a fresh machine's regeneration of the same episodes, brings only its own). Whether the run had any."""
    new = sealed_section(_datasets(run))
    if not _dated_rows(new):
        return False
    at = next((i for i, p in enumerate(parts) if p[0] == new[0]), None)
    if at is None:
        at = next((i for i, p in enumerate(parts) if p[0].startswith(PAPER_TABLES)), len(parts))
        parts.insert(at, [])
    parts[at] = sealed_section([], kept=[*_dated_rows(parts[at]), *_dated_rows(new)])
    return True


def _ran(run: Path, folder: str) -> bool:
    """Whether a section's run folder holds results: `make recovery`'s tables, an online bench of the main model
    (`make online-bench`) or a model-free one (`make online-power`: online_power*), or a bench of the seen test
    split."""
    if folder == "recovery":
        return any(recovery_files(run, lead) for lead in LEADS)
    if "*" in folder:
        return any(run.glob(f"{folder}/online.json"))
    return bool(run_evals(run / folder, ("test",)))


def _online_table(section: list[str]) -> list[str]:
    """The online model's table of an existing Supervision section (its header row to the blank line after it)."""
    return block(section, lambda line: line.startswith("| grids |"), lambda line: not line.startswith("|"))


ONLINE_GUARANTEE = (
    "The online bench's alarm is a threshold on the running P(failure), set on the calibration split's successes "
    "only (split conformal). It guarantees that at most alpha of new successes exchangeable with those (same "
    "scenes, policy, cameras and task mix) raise it, on average over calibration draws (a single draw's rate lands "
    "above alpha on roughly 40 % of draws) or, where the bench's first line names a training-conditional "
    "calibration (delta), with probability 1 - delta over the draw; it guarantees nothing on a new scene or object "
    "set (val_both below is one), and no detection rate or latency: those are measured. Latency is from the "
    "failure's onset in simulator state (negative: the alarm came first); an irreversible event is a spill, a "
    "fall, glassware moving fast enough to break or, in data generated from 1 Dec, an object pushed out of the "
    "arm's reach. Intervals in brackets (false alarms, detection, the last column, spills and falls) are exact "
    "(Clopper-Pearson, 95 %, given the calibrated threshold: they leave out the calibration draw's variation), and "
    "for an alarm at or after the onset its ceiling is the labeler's row: an alarm at the onset "
    "itself comes before the event only where the failure began before it. A row pairing two monitors (the model "
    "and a robot-signal MLP, or the per-frame and every-sample MLPs) alarms when either does, on the same "
    "successes, the first set at its share of alpha (a half unless the row names another, a share chosen on "
    "validation) and the second at the rest: the pair keeps the same bound (a union bound). A share whose level "
    "is under 1 / (n + 1) of the n calibration successes (more for a "
    "training-conditional alarm) leaves the model out (its threshold is +inf): under 199 successes (919 at delta "
    '0.1), the 0.1 share at alpha 0.05 and 0.01 is the MLP alone. "bound p" is the chance of at least that many '
    "false alarms if the guarantee holds (beta-binomial over the calibration draw and the scored successes; for "
    "the pair, a union bound on it): a rate above alpha with a large p is what the bound allows; under 0.05 (a "
    "test per row: among a table's rows one may fall there by chance) it says the scored successes are not "
    "exchangeable with the calibration ones. Under each bench, the row to report is chosen on the calibration "
    "split alone (cross-fitting by pair), never on the scored split."
)


POWER_LEAD = (
    "`make online-power` (no model): the robot-signal monitors on a block of new seen pairs (numbered from 100,000 "
    "up, in no split), fitted on the train split and calibrated on seen val as above, scored once for the alarm "
    "issue's targets by their intervals (docs/EXPERIMENTS.md, 7 Dec evening and late evening),"
)


def _page_online_benches(section: list[str]) -> list[str]:
    """The online bench's lines of an existing Supervision section: its guarantee paragraph up to a recovery
    table's lead (or the section's end)."""
    # a page may hold any recovery table without the others
    return block(section, lambda line: line.startswith(ONLINE_GUARANTEE[:40]), lambda line: line.startswith(LEADS))


def _bench_lead(line: str) -> str | None:
    """A bench block's lead line as the run writes it (a model's "`train/final`, eval_online_test:", make
    online-power's), the mark of a carried one removed; None for any other line."""
    core = line.replace(f", {AS_THE_PAGE_HAD_IT}:", ":")
    named = core.startswith("`") and "eval_online_" in core or core.startswith(POWER_LEAD)
    return core if named and core.endswith(":") else None


def _blocks(lines: list[str]) -> dict[str, list[str]]:
    """A section's bench lines cut into blocks by their leads (lead -> the lines after it); lines before the first
    lead (the guarantee paragraph) are left out."""
    out: dict[str, list[str]] = {}
    key = None
    for line in lines:
        lead = _bench_lead(line)
        if lead is not None:
            key = lead
            out[key] = []
        elif key is not None:
            out[key].append(line)
    return out


def _bench_order(lead: str) -> tuple:
    """The page's order: the models' benches (the recipe's model first, seen test first), then make online-power's."""
    power = lead.startswith(POWER_LEAD)
    # a power block by its folder (online_power before online_power2), as the run's folders sort
    return power, "`online/" in lead, "eval_online_test:" not in lead, lead.split("`")[-2] if power else lead


def online_benches(run: Path, page: list[str] | None = None) -> list[str]:
    """The online bench's tables (labrobfail-evaluate mode=online) of the run's models and make online-power's
    blocks, seen split first. `page` (an existing Supervision section): a bench the page has and the run does not is
    carried, block by block, its lead marked as the page had it; a run with no bench carries the page's whole."""
    own: dict[str, list[str]] = {}
    for model in ("train", "online"):
        for f in (run / model / "final").glob("eval_online_*/online.json"):
            own[f"`{model}/final`, {f.parent.name}:"] = ["", *online_md(json.loads(f.read_text())), ""]
    for power in run.glob("online_power*/online.json"):
        own[f"{POWER_LEAD} `{power.parent.name}`:"] = ["", *online_md(json.loads(power.read_text())), ""]
    theirs = _page_online_benches(page or [])
    if not own:
        return [f"The online bench {AS_THE_PAGE_HAD_IT}:", "", *theirs] if theirs else []
    carried = {f"{k[:-1]}, {AS_THE_PAGE_HAD_IT}:": v for k, v in _blocks(theirs).items() if k not in own}
    every = own | carried
    out = [
        line for lead in sorted(every, key=lambda k: _bench_order(_bench_lead(k) or k)) for line in (lead, *every[lead])
    ]
    return [ONLINE_GUARANTEE, "", *out]


def supervision(run: Path, page: list[str] | None = None) -> list[str]:
    """The online model (make reproduce-online) on whole and prefix grids, the online bench, and the recovery table
    (make recovery). `page` (the page's own Supervision section, for a splice) stands in for what the run lacks (the
    online model's table, the online bench, recovery cells not re-run), and the section says so."""
    lines = []
    online_stand_in = _online_table(page or [])
    ev = run_evals(run / "online", ("test", "prefix", "val_both"))
    titles = {"test": "seen, whole", "prefix": "seen, prefix (first k keyframes)", "val_both": "val both, whole"}
    if not ev and online_stand_in:
        lines += [f"The online model {AS_THE_PAGE_HAD_IT}:", "", *online_stand_in, ""]
    if ev:
        lines += [
            "| grids | Q2 | majority Q2 | AUROC | Q3 (failures) | Q5 (failures) |",
            "|---|---|---|---|---|---|",
            *(
                f"| {titles[s]} | {ci_cell(r, 'q2')} | {r['baselines'].get('majority class', {}).get('q2')} | "
                f"{(r.get('detection') or {}).get('auroc')} | {ci_cell(r, 'q3', True)} | {ci_cell(r, 'q5', True)} |"
                for s, r in ev.items()
            ),
            "",
        ]
    lines += online_benches(run, page)
    for lead in LEADS:  # make recovery's table, then make recovery-monitor's and make recovery-act-alarm's
        table = recovery_md(
            [json.loads(f.read_text()) for f in recovery_files(run, lead)], page_recovery(page or [], lead), lead
        )
        lines += ["", *table] if table and lead != LEAD else table
    return lines


def timing(stamps: list[list[str]]) -> list[str]:
    """The page's wall-clock line from timeline.txt's ("<step>", "<unix seconds>") stamps: the time from the first
    stamp to the last and each step's share; "end to end" only when the last stamp is "done"."""
    if len(stamps) < 2:
        return []
    steps = [(a[0], int(b[1]) - int(a[1])) for a, b in zip(stamps, stamps[1:])]
    total_min = (int(stamps[-1][1]) - int(stamps[0][1])) / 60
    # A run stopped (or still running) before it wrote "done" was not timed end to end: say where its clock stops
    # rather than pass the partial time off as the whole recipe's.
    span = "end to end" if stamps[-1][0] == "done" else f"until its `{stamps[-1][0]}` step (the timeline ends there)"
    line = (
        f"`make reproduce` {span}: **{total_min:.1f} min** wall-clock. Steps: "
        + ", ".join(f"{n} {s / 60:.1f} min" for n, s in steps)
        + "."
    )
    # a rerun resumes complete shards in seconds: say so rather than pass it off as generation time
    if dict(steps).get("generate", 60) < 60:
        line += " Generation found its shards already complete, so their generation time is not in this figure."
    return [line, ""]


def _header(run: Path, stats: dict[str, Any], stamps: list[list[str]]) -> list[str]:
    """The page's opening: what made it, how choices were taken, the wall clock, the data and the model."""
    summary = _load(run / "train" / "train_summary.json")
    progress = _load(run / "train" / "progress.json")
    grid = stats["grid"]
    card = summary.get("tower")
    claim = sealed_claim(raised_saturation(card))
    lines = [
        "# LabRobFail-Bench results of the CPU recipe",
        "",
        "Made by `make reproduce` (2 CPU cores, no GPU, no downloaded weights): PyBullet generation of seen, "
        "validation and sealed test data, the dataset, the tiny Qwen3-VL (`preset=tiny`) starting from the "
        "project's sim-pretrained vision tower (`labrobfail_vlm/assets/tower`, made by `make tower`), the bench on "
        "every split with the majority and blind baselines, and the learning curve; the tower and sensor rows come "
        "from `make reproduce-rows` and the ablation table from `make ablate` on the same data. Everything here is "
        "written by `scripts/write_results.py`; nothing is edited by hand.",
        "",
        "Splits: seen train / val / test (8:1:1 by pair); `val_object`, `val_scene`, `val_both` (the held-out "
        "catalogue and scene family: from 29 Nov 2026 every recipe, epoch count and threshold is chosen on them and "
        "on seen val; the recipe's tower stages and epoch count are older, chosen on seen test and on these sets' "
        "replayed predecessors, its decoder depth on these (3 Dec), docs/EXPERIMENTS.md); "
        f"`test_object`, `test_scene`, `test_both` ({claim} run only for the rows reported here, and every "
        'run is listed in "Sealed test runs"). Every variant draws its own episodes. Intervals: 95 %, percentile '
        "bootstrap over pairs (both twins of a pair drawn together).",
        "",
    ]
    lines += timing(stamps)
    params = sum(v for k, v in summary["trainable_parameters"].items() if k != "frozen")
    frozen = summary["trainable_parameters"].get("frozen", 0)
    conf = run / "train" / "final" / "config.json"
    layers = json.loads(conf.read_text()).get("text_config", {}).get("num_hidden_layers") if conf.is_file() else None
    man_file = run / "shards" / "seen" / "manifest.json"
    inj = json.loads(man_file.read_text()).get("injection") if man_file.is_file() else None
    physics = run_physics(run / "shards" / "seen")
    lines += [
        DATA_HEADING,
        "",
        _data_line(stats),
        *([_injection_line(inj)] if inj else []),
        *([f"- Physics: PyBullet preset `{physics}` (sim_backends/pybullet/backend.py PHYSICS)."] if physics else []),
        f"- Grid: {grid['width']}x{grid['height']} px, {grid['max_frames']} keyframes x 2 views "
        f"({', '.join(stats.get('views') or ['every view'])}), {grid['columns']} time steps per band "
        f"({(grid['width'] // 32) * (grid['height'] // 32)} visual tokens).",
        "- Model: Qwen3-VL architecture at tiny size"
        + (f" ({layers} decoder layers)" if layers else "")
        + f", {params / 1e6:.2f} M parameters trained"
        + (f", {frozen / 1e6:.2f} M frozen" if frozen else "")
        + f"; {summary['global_step']} optimizer steps, "
        f"{progress[-1]['examples'] if progress else '?'} training records, "
        f"{progress[-1]['wall_s'] / 60 if progress else 0:.1f} min of training.",
        *(
            [
                f"- Vision tower: `{card['path']}`{_shipped_bytes(card)} (sha256 `{card['sha256'][:16]}...`, "
                f"{card['parameters']:,} parameters; what it learned and how well, held out: its TOWER_CARD.md)."
            ]
            if card
            else []
        ),
        "",
    ]
    return lines


def _shipped_bytes(card: dict[str, Any]) -> str:
    """A note when a tower given by path is the one this checkout ships (a candidate tower trained from before it was
    adopted), so the page says which tower `make reproduce` started from when the page was written."""
    from labrobfail_vlm.model.tower import CARD_FILE, shipped_dir

    try:  # the card's own sha256 (the weights may be absent, as in an LFS checkout): a page is written regardless
        shipped = json.loads((shipped_dir() / CARD_FILE).read_text())["sha256"]
    except (OSError, ValueError, KeyError, TypeError):
        return ""
    return (
        ", the bytes shipped when this page was written"
        if card["path"] != "shipped" and shipped == card["sha256"]
        else ""
    )


def _injection_line(inj: dict[str, Any]) -> str:
    return (
        "- Injections of the seen run, drawn as the paper writes them (outcome per operator: "
        + "; ".join(
            f"{k} {v.get('failure', 0)} failed / {v.get('success', 0)} succeeded" for k, v in inj["by_operator"].items()
        )
        + "). Physics events by parameter and sign of delta: "
        + ", ".join(f"{k} {v}" for k, v in inj["physics_events"].items())
        + f"; gripper faults {inj['gripper_faults']}; draws rejected by the min_norm filter "
        + f"{inj['filter_rejections']}."
    )


def detection_section(run: Path, out: Path, evals: dict[str, Any]) -> list[str]:
    """Q2 as a score per split, with the reliability diagrams copied beside the page."""
    from labrobfail_vlm.bench.report import detection_markdown

    lines = [
        "## Failure detection as a score (Q2)",
        "",
        "P(failure) is the model's softmax over its two admissible Q2 replies; the majority class scores every "
        "grid with the training failure rate (AUROC 0.5). ECE: ten equal-width bins. Reliability diagrams: "
        "`docs/reliability_<split>.png`.",
        "",
    ]
    for split, res in evals.items():
        title = SPLIT_TITLES[split]
        lines += [detection_markdown(named_rows(res), title), ""]
        png = run / "train" / "final" / f"eval_{split}" / "reliability_q2.png"
        if png.is_file():
            atomic_write_bytes(out.parent / f"reliability_{split}.png", png.read_bytes())
            lines += [f"![reliability, {title}](reliability_{split}.png)", ""]
    return lines


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    run, out = Path(str(cfg.run)), Path(str(cfg.out))
    if cfg.sections:
        if cfg.carry:  # a splice keeps every section it does not name already
            raise ConfigError(
                "carry: only for a whole page (sections=null); a splice keeps the sections it does not name"
            )
        return splice(run, out, [str(n) for n in cfg.sections])
    stats = _load(run / "dataset" / "stats.json")
    _load(run / "train" / "final" / "eval_test" / "results.json")  # the seen test split is the page's least
    evals = run_evals(run / "train") or {}
    stamps = [line.split() for line in (run / "timeline.txt").read_text().splitlines() if line.strip()]
    lines = _header(run, stats, stamps)
    lines += ["## Targets of the principal issue (main row: front + side)", "", *targets(evals), ""]
    lines += model_sections(run, out, [str(n) for n in cfg.carry])
    lines += sealed_section(_datasets(run), kept=page_ledger(out))
    lines += paper_tables(evals)
    lines += detection_section(run, out, evals)
    lines += all_trajectory_tables(evals)
    lines += ["## Failure detection (Q2) per failure type, seen test split", "", *per_type(evals["test"])]
    curve = run / "train" / "learning_curve.png"
    if curve.is_file():
        atomic_write_bytes(out.parent / "learning_curve.png", curve.read_bytes())
        lines += ["", "## Learning curve (validation split)", "", "![learning curve](learning_curve.png)"]
    lines += ["", f"Run timeline (unix seconds): {json.dumps({n: int(t) for n, t in stamps})}", ""]
    atomic_write_bytes(out, "\n".join(lines).encode())
    print(out)
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
