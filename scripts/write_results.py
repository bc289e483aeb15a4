"""Write docs/RESULTS.md from a `make reproduce` run (and, where they exist, `make reproduce-rows` and `make ablate`).

Run as:
    python scripts/write_results.py run=outputs/reproduce out=docs/RESULTS.md

Reads <run>/dataset/stats.json, <run>/timeline.txt (one "<step> <unix seconds>" line per step), the main model's
<run>/train/{train_summary,progress}.json and final/eval_<split>/results.json, the tower card it started from, and
the optional rows <run>/rows/{scratch,wrist}/ and ablations <run>/ablate/{frozen,tuned,no_index}/ (same layout),
`make reproduce-online`'s model <run>/online/ and `make recovery`'s tables <run>/recovery/{scripted,act/<task>}/.
Sections: the issue's targets, the tower and sensor rows, the paper's ablation table, supervision (the online model
on whole and prefix grids, the recovery table), the paper-comparable tables
(Q3-Q6 over failed trajectories) with 95 % intervals, failure detection as a score, the all-trajectory tables,
Q2 recall per failure type, the learning curve.

With `sections=[rows]`, `[ablation]` or `[supervision]` it replaces only those sections of the existing page, from a
run that holds just those folders (a fresh machine's regeneration with the same seed, say): it checks first that the
run's data are the page's (the same trajectories and splits line). What such a run lacks is carried from the page and
said so: the ablation's frozen row is the page's shipped front + side row (the recipe's model is the frozen one), and
the online model's table stays when the run has only a recovery table.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from labrobfail_vlm.config import ConfigError, cli_main, load_config

DEFAULTS = """
run: outputs/reproduce     # the make reproduce run folder
out: docs/RESULTS.md       # the page to write
sections: null             # null: the whole page; any of [rows, ablation, supervision]: replace only those
"""
# the sections a run beside the main one can add: heading, opening sentence, the run folders that feed it
SECTIONS = {
    "rows": (
        "## Tower and sensor rows",
        "The same data and bench; only the tower or the views differ. "
        "95 % intervals: Wilson for accuracies, bootstrap for ROUGE-L.",
        ("rows/scratch", "rows/wrist"),
    ),
    "ablation": (
        "## Ablation (the paper's table, seen split)",
        "The same data and bench; only the variant differs. 95 % intervals: Wilson for accuracies, bootstrap for "
        "ROUGE-L.",
        ("ablate/tuned", "ablate/frozen", "ablate/no_index"),
    ),
    "supervision": (
        "## Supervision",
        "`make reproduce-online`: the model above taught to read prefix grids (a third stage: the first k keyframes, "
        "later cells blank), so that it can be asked at every keyframe. `make recovery`: the scripted and ACT policies "
        "with and without a VLM supervisor; the line above its table names the model and when it was asked.",
        ("online", "recovery"),
    ),
}
# the first section after the ones above: where a spliced section that the page lacks is inserted, at the latest
PAPER_TABLES = "## Paper-comparable tables"
SPLIT_TITLES = {
    "test": "Seen (test split)",
    "object": "Unseen objects",
    "scene": "Unseen scene",
    "both": "Unseen objects and scene",
}
# optional training runs beside the main one: folder under the run -> row title
ROWS = {
    "rows/scratch": "scratch tower (random init, stage A grounding: the pre-tower recipe)",
    "train": "sim-pretrained tower (shipped), front + side",
    "rows/wrist": "sim-pretrained tower, front + wrist (sensor ablation, not the paper's views)",
}
RECOVERY_TARGET = 4  # points of success rate that supervision must add per task and policy (the tower issue)
ABLATIONS = {
    "ablate/tuned": "tuned tower and merger",
    "ablate/frozen": "frozen tower and merger",
    "ablate/no_index": "no temporal index (no labels drawn, none mentioned)",
}


def _load(path: Path) -> Any:
    if not path.is_file():
        raise ConfigError(f"results: {path} is missing (run `make reproduce` first)")
    return json.loads(path.read_text())


def _evals(folder: Path, splits: tuple[str, ...] = tuple(SPLIT_TITLES)) -> dict[str, Any] | None:
    """A training folder's bench results per split, or None when it has not been run."""
    files = {s: folder / "final" / f"eval_{s}" / "results.json" for s in splits}
    return {s: json.loads(f.read_text()) for s, f in files.items() if f.is_file()} or None


def _ci(res: dict[str, Any], key: str, fo: bool = False) -> str:
    """'value [lo, hi]' for an accuracy (or ROUGE-L) with its 95 % interval."""
    src = res["failure_only"] if fo else res
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


def targets(evals: dict[str, Any]) -> list[str]:
    """The tower issue's goals, measured with the bench's failure-only scoring for Q3 and Q5."""
    t, both = evals["test"], evals.get("both")
    major = t["baselines"].get("majority class", {}).get("q2")
    rows = [
        ("seen Q2", t["q2"], 80, _ci(t, "q2")),
        (
            "seen Q2 minus the majority class",
            None if major is None else round(t["q2"] - major, 2),
            15,
            f"majority {major}",
        ),
        ("seen failure-only Q3", t["failure_only"]["q3"], 50, _ci(t, "q3", True)),
        ("seen failure-only Q5", t["failure_only"]["q5"], 50, _ci(t, "q5", True)),
        ("unseen objects and scene Q2", both["q2"] if both else None, 70, _ci(both, "q2") if both else "–"),
    ]
    out = ["| goal | reached | target | met | 95 % interval / note |", "|---|---|---|---|---|"]
    for name, got, want, note in rows:
        out.append(f"| {name} | {got} | >= {want} | {'yes' if got is not None and got >= want else 'no'} | {note} |")
    return out


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


def _section(name: str, body: list[str], made_on: Path | None = None) -> list[str]:
    """A section of SECTIONS as the page prints it: heading, opening sentence (and the run a splice took it
    from), the table."""
    heading, intro, _ = SECTIONS[name]
    return [
        heading,
        "",
        intro,
        *([f"Made on `{made_on}`, whose data are this page's."] if made_on else []),
        "",
        *body,
        "",
    ]


def splice(run: Path, out: Path, names: list[str]) -> int:
    """Replace the named sections of the existing page with this run's, leaving every other line as it was."""
    unknown = sorted(set(names) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"sections: unknown {unknown}; choose from {sorted(SECTIONS)}")
    if not out.is_file():
        raise ConfigError(f"sections: {out} does not exist; write the whole page first (sections=null)")
    parts = _sections(out.read_text())
    if _data_line(_load(run / "dataset" / "stats.json")) not in (line for p in parts for line in p):
        raise ConfigError(f"sections: {run}'s data are not {out}'s (its trajectories and splits line differs)")
    shipped = next((line for p in parts for line in p if line.startswith(f"| {ROWS['train']} |")), None)
    cells = [c.strip() for c in shipped.strip("|").split("|")] if shipped else None
    old_sv = next((p for p in parts if p[0] == SECTIONS["supervision"][0]), [])
    bodies = {
        "rows": lambda: rows_table(run, shipped),
        # the shipped row's seen Q2, Q3, Q5 and ROUGE-L cells
        "ablation": lambda: ablation_table(run, [cells[1], cells[3], cells[4], cells[5]] if cells else None),
        "supervision": lambda: supervision(run, _online_table(old_sv)),
    }
    for name in names:
        heading, _, folders = SECTIONS[name]
        if not any(_ran(run, f) for f in folders):
            raise ConfigError(f"sections: {run} has no results under {', '.join(folders)}")
        new = _section(name, bodies[name](), made_on=run)
        at = next((i for i, p in enumerate(parts) if p[0] == heading), None)
        if at is None:  # a new section goes where the whole page puts it: before the later ones
            later = [h for h, _, _ in list(SECTIONS.values())[list(SECTIONS).index(name) + 1 :]] + [PAPER_TABLES]
            at = next((i for i, p in enumerate(parts) if any(p[0].startswith(h) for h in later)), len(parts))
            parts.insert(at, new)
        else:
            parts[at] = new
    from labrobfail_vlm.io import atomic_write_bytes

    atomic_write_bytes(out, ("\n".join(line for p in parts for line in p) + "\n").encode())
    print(out)
    return 0


def rows_table(run: Path, shipped: str | None = None) -> list[str]:
    """Tower and sensor rows side by side: seen Q2 and AUROC, failure-only Q3/Q5/ROUGE-L, unseen Q2.
    `shipped` (the page's own row) stands in for a run without the main model."""
    head = [
        "| row | seen Q2 | seen AUROC | seen Q3 (failures) | seen Q5 (failures) | ROUGE-L (failures) | "
        "object Q2 | scene Q2 | both Q2 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    lines, missing = [], []
    for folder, title in ROWS.items():
        ev = _evals(run / folder)
        if folder == "train" and shipped and not ev:
            lines.append(shipped)
            continue
        if not ev or "test" not in ev:
            missing.append(f"{title} (`{folder}`)")
            continue
        t = ev["test"]
        det = (t.get("detection") or {}).get("auroc")
        lines.append(
            f"| {title} | {_ci(t, 'q2')} | {det} | {_ci(t, 'q3', True)} | {_ci(t, 'q5', True)} | "
            f"{_ci(t, 'rougeL', True)} | "
            + " | ".join(_ci(ev[s], "q2") if s in ev else "–" for s in ("object", "scene", "both"))
            + " |"
        )
    return head + lines + _not_run(missing) if lines else []


def _not_run(missing: list[str]) -> list[str]:
    """The closing line of a table that names the runs it lacks (`make reproduce-rows` / `make ablate` steps)."""
    return ["", "Not run for this page: " + "; ".join(missing) + "."] if missing else []


def ablation_table(run: Path, frozen_cells: list[str] | None = None) -> list[str]:
    """The paper's ablation table (seen split: Q2, Q3, Q5, Q6 ROUGE-L) for the runs `make ablate` made.
    `frozen_cells` (Q2, Q3, Q5, ROUGE-L as the page shows them) stand in for a run without `ablate/frozen`."""
    from labrobfail_vlm.bench.report import PAPER_ABLATION

    lines, missing = [], []
    for folder, title in ABLATIONS.items():
        ev = _evals(run / folder, ("test",))
        if not ev and folder == "ablate/frozen" and frozen_cells:
            lines.append(f"| {title} (this page's `make reproduce` model) | " + " | ".join(frozen_cells) + " |")
        elif ev:
            t = ev["test"]
            lines.append(
                f"| {title} | {_ci(t, 'q2')} | {_ci(t, 'q3', True)} | {_ci(t, 'q5', True)} | {_ci(t, 'rougeL', True)} |"
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


def _recovery_files(run: Path) -> list[Path]:
    """`make recovery`'s results.json files of a run: the scripted policy's, then each ACT task's."""
    rec = run / "recovery"
    return [
        f for f in (rec / "scripted" / "results.json", *sorted((rec / "act").glob("*/results.json"))) if f.is_file()
    ]


def _ran(run: Path, folder: str) -> bool:
    """Whether a section's run folder holds results: `make recovery`'s tables, or a bench of the seen test split."""
    return bool(_recovery_files(run)) if folder == "recovery" else bool(_evals(run / folder, ("test",)))


def _online_table(section: list[str]) -> list[str]:
    """The online model's table of an existing Supervision section (its header row to the blank line after it)."""
    at = next((i for i, line in enumerate(section) if line.startswith("| grids |")), None)
    if at is None:
        return []
    end = next((i for i in range(at, len(section)) if not section[i].startswith("|")), len(section))
    return section[at:end]


def supervision(run: Path, online_stand_in: list[str] | None = None) -> list[str]:
    """The online model (make reproduce-online) on whole and prefix grids, and the recovery table (make recovery):
    success out of the trials per task and policy, without a supervisor and with the VLM. `online_stand_in` (the
    page's own online table) stands in for a run without the online model, and says so."""
    lines = []
    ev = _evals(run / "online", ("test", "prefix", "both"))
    titles = {"test": "seen, whole", "prefix": "seen, prefix (first k keyframes)", "both": "unseen both, whole"}
    if not ev and online_stand_in:
        lines += ["The online model as the page had it (this run has none):", "", *online_stand_in, ""]
    if ev:
        lines += [
            "| grids | Q2 | majority Q2 | AUROC | Q3 (failures) | Q5 (failures) |",
            "|---|---|---|---|---|---|",
            *(
                f"| {titles[s]} | {_ci(r, 'q2')} | {r['baselines'].get('majority class', {}).get('q2')} | "
                f"{(r.get('detection') or {}).get('auroc')} | {_ci(r, 'q3', True)} | {_ci(r, 'q5', True)} |"
                for s, r in ev.items()
            ),
            "",
        ]
    rows: list[str] = []
    settings: dict[str, list[str]] = {}  # each supervisor setting and the cells it ran (a task may need its own)
    for f in _recovery_files(run):
        res = json.loads(f.read_text())
        cfg = res["config"]
        sup, loop = cfg["supervisor"], cfg["loop"]
        asked = {0: "at every keyframe", -1: "only when the policy stops"}.get(
            loop["query_every"], f"every {loop['query_every']} policy steps"
        )
        setting = (
            f"{cfg['trials']} trials per cell, variant {cfg['variant']}, supervisor {sup} "
            f"(`{(cfg.get(sup) or {}).get('model', '')}`) asked {asked}"
            + (" and once more when the policy stops" if loop["final_query"] and loop["query_every"] >= 0 else "")
            + f", budget {loop['budget']}, a manual correction: {loop['on_manual']}"
        )
        for task, r in res["tasks"].items():
            settings.setdefault(setting, []).append(f"{r['policy']} {task}")
            base, got = r.get("none"), r.get(sup)
            if base and got:
                rows.append(
                    f"| {task} | {r['policy']} | {base['success']}/{base['trials']} | {got['success']}/{got['trials']} "
                    f"| {r['improvement']:+.0f} | {'yes' if r['improvement'] >= RECOVERY_TARGET else 'no'} | "
                    f"{got['episodes_with_intervention']} | {got['stopped']} |"
                )
    if rows:
        lines += [
            "Recovery: the same initial states and injections with and without the supervisor; "
            + (
                next(iter(settings))
                if len(settings) == 1
                else "; ".join(f"{', '.join(cells)}: {s}" for s, cells in settings.items())
            )
            + ".",
            "",
            f"| task | policy | none | +VLM | diff (points) | >= +{RECOVERY_TARGET} | episodes with an intervention "
            "| stopped early |",
            "|---|---|---|---|---|---|---|---|",
            *rows,
        ]
    return lines


def per_type(run: Path, res: dict[str, Any]) -> list[str]:
    from labrobfail_vlm.bench.metrics import wilson

    traj = json.loads((run / "dataset" / "trajectories.json").read_text())
    counts: dict[str, int] = {}
    for t in traj:
        if t.get("split") == "test" and "prefix_of" not in t and not t["success"]:
            counts[t["failure_type"]] = counts.get(t["failure_type"], 0) + 1
    out = ["| type | Q2 recall | 95 % interval | n |", "|---|---|---|---|"]
    for key, dims in sorted(res["breakdown"].items()):
        if key.startswith("type:") and "Q2" in dims:
            name = key.split(":", 1)[1]
            n = (
                counts.get(name)
                if name != "success"
                else sum(1 for t in traj if t.get("split") == "test" and t["success"] and "prefix_of" not in t)
            )
            ci = wilson(round(dims["Q2"] * n / 100), n) if n else None
            out.append(
                f"| {name} | {dims['Q2']:.1f} | "
                + (f"{100 * ci[0]:.0f}-{100 * ci[1]:.0f}" if ci else "–")
                + f" | {n or '–'} |"
            )
    return out


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


def main(argv: list[str]) -> int:
    from labrobfail_vlm.bench.report import PAPER_ROWS, PAPER_UNSEEN_ROWS, detection_markdown, markdown, paper_row, row

    cfg = load_config(DEFAULTS, argv)
    run, out = Path(str(cfg.run)), Path(str(cfg.out))
    if cfg.sections:
        return splice(run, out, [str(n) for n in cfg.sections])
    stats = _load(run / "dataset" / "stats.json")
    summary = _load(run / "train" / "train_summary.json")
    progress = _load(run / "train" / "progress.json")
    evals = {s: _load(run / "train" / "final" / f"eval_{s}" / "results.json") for s in SPLIT_TITLES}
    stamps = [line.split() for line in (run / "timeline.txt").read_text().splitlines() if line.strip()]
    grid = stats["grid"]
    card = summary.get("tower")
    lines = [
        "# LabRobFail-Bench results of the CPU recipe",
        "",
        "Made by `make reproduce` (2 CPU cores, no GPU, no downloaded weights): PyBullet generation of seen and "
        "unseen data, the dataset, the tiny Qwen3-VL (`preset=tiny`) starting from the project's sim-pretrained "
        "vision tower (`labrobfail_vlm/assets/tower`, made by `make tower`), the bench on every split with the "
        "majority and blind baselines, and the learning curve; the tower and sensor rows come from `make "
        "reproduce-rows` and the ablation table from `make ablate` on the same data. Everything here is "
        "written by `scripts/write_results.py`; nothing is edited by hand.",
        "",
    ]
    lines += timing(stamps)
    params = sum(v for k, v in summary["trainable_parameters"].items() if k != "frozen")
    frozen = summary["trainable_parameters"].get("frozen", 0)
    man_file = run / "shards" / "seen" / "manifest.json"
    inj = json.loads(man_file.read_text()).get("injection") if man_file.is_file() else None
    lines += [
        "## Data and model",
        "",
        _data_line(stats),
        *(
            [
                "- Injections of the seen run, drawn as the paper writes them (outcome per operator: "
                + "; ".join(
                    f"{k} {v.get('failure', 0)} failed / {v.get('success', 0)} succeeded"
                    for k, v in inj["by_operator"].items()
                )
                + "). Physics events by parameter and sign of delta: "
                + ", ".join(f"{k} {v}" for k, v in inj["physics_events"].items())
                + f"; gripper faults {inj['gripper_faults']}; draws rejected by the min_norm filter "
                + f"{inj['filter_rejections']}."
            ]
            if inj
            else []
        ),
        f"- Grid: {grid['width']}x{grid['height']} px, {grid['max_frames']} keyframes x 2 views "
        f"({', '.join(stats.get('views') or ['every view'])}), {grid['columns']} time steps per band "
        f"({(grid['width'] // 32) * (grid['height'] // 32)} visual tokens).",
        f"- Model: Qwen3-VL architecture at tiny size, {params / 1e6:.2f} M parameters trained"
        + (f", {frozen / 1e6:.2f} M frozen" if frozen else "")
        + f"; {summary['global_step']} optimizer steps, "
        f"{progress[-1]['examples'] if progress else '?'} training records, "
        f"{progress[-1]['wall_s'] / 60 if progress else 0:.1f} min of training.",
        *(
            [
                f"- Vision tower: `{card['path']}` (sha256 `{card['sha256'][:16]}...`, {card['parameters']:,} "
                f"parameters; what it learned and how well, held out: its TOWER_CARD.md)."
            ]
            if card
            else []
        ),
        "",
    ]
    lines += ["## Targets of the tower issue", "", *targets(evals), ""]
    rt = rows_table(run)
    if rt:
        lines += _section("rows", rt)
    at = ablation_table(run)
    if at:
        lines += _section("ablation", at)
    sv = supervision(run)
    if sv:
        lines += _section("supervision", sv)

    def named(res: dict[str, Any]) -> dict[str, dict[str, Any]]:
        return {
            "tiny LabRobFail-VLM (ours, free Q6)": res,
            **{
                f"tiny LabRobFail-VLM (ours, {k.split(', ')[-1]})" if k.endswith("Q6 template") else k: v
                for k, v in res["baselines"].items()
            },
        }

    lines += [
        PAPER_TABLES,
        "",
        "Q1 and Q2 over every trajectory of the split; Q3, Q4, Q5 and Q6 (BLEU, ROUGE-L) over its failed "
        'trajectories only, as the paper\'s table can be read (its Q4 and Q5 options have no "None"). The '
        "majority class answers Q3-Q6 with the most frequent answer among training failures. Where the blind "
        'baseline reaches Q1 = 100 (the preamble names the task), a tie at 100 counts as "above blind". '
        "Severity options are the paper's appendix ones; its main text names the same four levels Minor, "
        "Recoverable, Critical, Catastrophic (paired by position: option 1 = Minor ... 4 = Catastrophic).",
        "",
    ]
    for split, title in SPLIT_TITLES.items():
        res = evals[split]
        fo = res["failure_only"]
        rows = {k: paper_row(v) for k, v in named(res).items()}
        rows.update(
            {"LabRobFail-VLM (paper, 8B)": PAPER_UNSEEN_ROWS[split]}
            if split in PAPER_UNSEEN_ROWS
            else {k: v for k, v in PAPER_ROWS.items()}
        )
        n_traj = res["detection"]["trajectories"] if res.get("detection") else "?"
        lines += [
            markdown(rows, f"{title}: {n_traj} trajectories, Q3-Q6 over the {fo['trajectories']} failed ones"),
            "95 % intervals (ours, free Q6): "
            + ", ".join(f"{k} {_ci(res, k.lower(), k in ('Q3', 'Q4', 'Q5'))}" for k in ("Q1", "Q2", "Q3", "Q4", "Q5"))
            + f", ROUGE-L {_ci(res, 'rougeL', True)}.",
            "",
        ]
    lines += [
        "## Failure detection as a score (Q2)",
        "",
        "P(failure) is the model's softmax over its two admissible Q2 replies; the majority class scores every "
        "grid with the training failure rate (AUROC 0.5). ECE: ten equal-width bins. Reliability diagrams: "
        "`docs/reliability_<split>.png`.",
        "",
    ]
    for split, title in SPLIT_TITLES.items():
        lines += [detection_markdown(named(evals[split]), title), ""]
        png = run / "train" / "final" / f"eval_{split}" / "reliability_q2.png"
        if png.is_file():
            shutil.copyfile(png, out.parent / f"reliability_{split}.png")
            lines += [f"![reliability, {title}](reliability_{split}.png)", ""]
    lines += [
        "## All-trajectory tables (the project's own; not comparable with the paper)",
        "",
        'Q3-Q6 over every trajectory: a success\'s reference is "None" / the no-correction sentence, so the '
        "majority class scores high on them.",
        "",
    ]
    for split, title in SPLIT_TITLES.items():
        res = evals[split]
        lines += [
            markdown(
                {k: row(v) for k, v in named(res).items()}, f"{title}: {res['records']} records, all trajectories"
            ),
            "",
        ]
    lines += ["## Failure detection (Q2) per failure type, seen test split", "", *per_type(run, evals["test"])]
    curve = run / "train" / "learning_curve.png"
    if curve.is_file():
        shutil.copyfile(curve, out.parent / "learning_curve.png")
        lines += ["", "## Learning curve (validation split)", "", "![learning curve](learning_curve.png)"]
    lines += ["", f"Run timeline (unix seconds): {json.dumps({n: int(t) for n, t in stamps})}", ""]
    from labrobfail_vlm.io import atomic_write_bytes

    atomic_write_bytes(out, "\n".join(lines).encode())
    print(out)
    return 0


if __name__ == "__main__":
    cli_main(main, __doc__)
