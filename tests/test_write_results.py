"""docs/RESULTS.md from run folders: the recovery table read from `make recovery`'s results.json files, and a later run
on the page's data spliced into it section by section."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from scripts.write_results import supervision
from sim_backends.supervision.paired import paired_cell


def _results(
    path: Path,
    policy: str,
    tasks: dict[str, tuple[int, int]],
    model: str = "outputs/online/final",
    every: int = 0,
    seed: int | None = None,
    monitor: dict | None = None,
) -> None:
    """A results.json as labrobfail-supervise writes it: per task, the baseline and the VLM's summaries."""

    def summary(ok: int) -> dict:
        return {"success": ok, "trials": 25, "rate": 4.0 * ok, "episodes_with_intervention": 3, "stopped": 1}

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps(
            {
                "config": {
                    "policy": policy,
                    "supervisor": "vlm",
                    "trials": 25,
                    "variant": "seen",
                    "vlm": {"model": model, **(monitor or {})},
                    "loop": {"query_every": every, "final_query": True, "budget": 2, "on_manual": "stop"},
                    **({} if seed is None else {"seed": seed}),
                },
                "tasks": {
                    t: {
                        "policy": policy,
                        "none": summary(a),
                        "vlm": summary(b),
                        "improvement": 4.0 * (b - a),
                        # trial i succeeds without the supervisor for i < a, with it for i < b
                        "paired": paired_cell([i < a for i in range(25)], [i < b for i in range(25)]).summary(),
                    }
                    for t, (a, b) in tasks.items()
                },
            }
        )
    )


def test_the_recovery_table_has_a_row_per_task_and_policy(tmp_path: Path) -> None:
    assert supervision(tmp_path) == []  # nothing run: no section
    _results(tmp_path / "recovery" / "scripted" / "results.json", "scripted", {"pick": (6, 6), "place": (8, 16)})
    _results(tmp_path / "recovery" / "act" / "pour" / "results.json", "act", {"pour": (3, 2)})
    lines = supervision(tmp_path)
    assert "asked at every keyframe and once more when the policy stops, budget 2" in lines[0]
    rows = [r for r in lines if r.startswith("| ") and not r.startswith("| task")]
    assert rows == [
        # the paired 95 % interval (Agresti-Min, worked by hand), exact McNemar p, successes broken
        "| pick | scripted | 6/25 | 6/25 | +0 | no | [-7.3, +7.3] | 1 | 0/6 | 3 | 1 |",
        "| place | scripted | 8/25 | 16/25 | +32 | yes | [+10.9, +48.3] | 0.00781 | 0/8 | 3 | 1 |",
        "| pour | act | 3/25 | 2/25 | -4 | no | [-13.9, +6.5] | 1 | 1/3 | 3 | 1 |",
    ]


def test_a_cell_with_its_own_supervisor_setting_is_named_with_it(tmp_path: Path) -> None:
    """The ACT pour cell is reviewed by another model when the policy stops: the page says which cells ran how."""
    _results(tmp_path / "recovery" / "scripted" / "results.json", "scripted", {"pick": (6, 6), "place": (8, 16)})
    pour = tmp_path / "recovery" / "act" / "pour" / "results.json"
    _results(pour, "act", {"pour": (1, 2)}, "outputs/train/final", -1, seed=20000)
    head = supervision(tmp_path)[0]
    assert "scripted pick, scripted place: 25 trials per cell, variant seen" in head  # no seed recorded: none named
    assert "asked at every keyframe and once more when the policy stops" in head
    # The seed block the cell ran on, so that a reader can check it is the reporting block no choice saw.
    assert "act pour: 25 trials per cell (seeds 20000-20024), variant seen, supervisor vlm (`outputs/train" in head


def test_the_monitor_table_stands_apart_and_a_later_recovery_run_keeps_it(tmp_path: Path) -> None:
    """make recovery-monitor's cells (the robot-signal monitor deciding) are a table of their own under the recovery
    table, named with the monitor and its alpha; a later run of the other table carries them, and says so."""
    from sim_backends.supervision.report import LEAD, MONITOR_LEAD

    def at(lines: list[str], lead: str) -> int:
        return next(k for k, line in enumerate(lines) if line.startswith(lead))

    _results(tmp_path / "recovery" / "scripted" / "results.json", "scripted", {"pick": (6, 20)}, every=-1)
    watched = {"monitor": "m/monitor", "alpha": 0.05}
    _results(tmp_path / "recovery" / "monitor" / "results.json", "scripted", {"pick": (6, 24)}, monitor=watched)
    lines = supervision(tmp_path)
    i, j = at(lines, LEAD), at(lines, MONITOR_LEAD)
    assert i < j and "asked only when the policy stops" in lines[i]
    assert (
        "asked when the robot-signal monitor `m/monitor` (alpha 0.05), read at every keyframe, first sounds and, in an "
        "episode it flagged, once more when the policy stops, budget 2" in lines[j]
    )
    assert "| 6/25 | 20/25 |" in "\n".join(lines[i:j]) and "| 6/25 | 24/25 |" in "\n".join(lines[j:])
    later = tmp_path / "later"
    _results(later / "recovery" / "scripted" / "results.json", "scripted", {"pick": (6, 21)}, every=-1)
    again = supervision(later, lines)
    i, j = at(again, LEAD), at(again, MONITOR_LEAD)
    assert "| 6/25 | 21/25 |" in "\n".join(again[i:j]) and "20/25" not in "\n".join(again)
    assert again[j].endswith("(rows carried from the page, not re-run).") and "| 6/25 | 24/25 |" in again[-1]


def test_the_act_alarm_table_follows_the_monitor_table_and_names_its_calibrated_threshold(tmp_path: Path) -> None:
    """make recovery-act-alarm's cells (the model asked when the ACT stops, intervening only above the threshold its
    bench calibrated on that ACT's successes) are the last table, one row per task, named with the bench and alpha;
    a later run of the monitor table alone carries them."""
    from sim_backends.supervision.report import ALARM_LEAD, MONITOR_LEAD

    def at(lines: list[str], lead: str) -> int:
        return next(k for k, line in enumerate(lines) if line.startswith(lead))

    watched = {"monitor": "m/monitor", "alpha": 0.05}
    _results(tmp_path / "recovery" / "monitor" / "results.json", "scripted", {"pick": (6, 24)}, monitor=watched)
    alarm = {"alarm": "b/online.json", "alpha": 0.05}
    for task, cell in (("place", (2, 9)), ("pick", (5, 14))):
        _results(
            tmp_path / "recovery" / "act_alarm" / task / "results.json", "act", {task: cell}, "ft", -1, 25000, alarm
        )
    lines = supervision(tmp_path)
    j, k = at(lines, MONITOR_LEAD), at(lines, ALARM_LEAD)
    assert j < k and "b/online.json" not in lines[j]
    assert (
        "supervisor vlm (`ft`) asked only when the policy stops, intervening only above the threshold `b/online.json` "
        "calibrated at alpha 0.05, budget 2" in lines[k]
    )
    rows = [r for r in lines[k:] if r.startswith("| ") and not r.startswith("| task")]
    assert [r.split(" | ")[:4] for r in rows] == [
        ["| pick", "act", "5/25", "14/25"],
        ["| place", "act", "2/25", "9/25"],
    ]
    later = tmp_path / "later"
    _results(later / "recovery" / "monitor" / "results.json", "scripted", {"pick": (6, 23)}, monitor=watched)
    again = supervision(later, lines)
    k = at(again, ALARM_LEAD)
    assert again[k].endswith("(rows carried from the page, not re-run).") and "| 5/25 | 14/25 |" in "\n".join(again[k:])
    assert "| 6/25 | 23/25 |" in "\n".join(again[:k])


def _eval(path: Path, q2: float) -> None:
    """A bench results.json with the fields the page's tables read (seen Q2, failure-only Q3/Q5/ROUGE-L, intervals)."""
    path.mkdir(parents=True, exist_ok=True)
    fo = {"q3": 61.0, "q5": 57.5, "q6": {"rougeL": 0.6}, "ci95": {"q3": [55.0, 66.0], "q5": [51.0, 63.0]}}
    fo["ci95"]["rougeL"] = [0.55, 0.65]
    (path / "results.json").write_text(json.dumps({"q2": q2, "ci95": {"q2": [q2 - 3, q2 + 3]}, "failure_only": fo}))


STATS = {
    "trajectories_kept": 10,
    "trajectories_in": 12,
    "by_outcome": {"success": 6, "failure": 4},
    "splits": {"train": {"trajectories": 8}, "test": {"trajectories": 2}},
}
SHIPPED = (
    "| sim-pretrained tower (shipped), front + side | 80.6 [77.7, 83.2] | 0.863 | 54.6 [48.8, 60.4] | "
    "50.7 [44.9, 56.5] | 0.5014 [0.455, 0.549] | 78.1 [70.7, 84.0] | 78.0 [70.7, 83.9] | 76.0 [68.5, 82.2] |"
)
PAGE = "\n".join(
    [
        "# results",
        "",
        "## Data and model",
        "",
        "- Trajectories: 10 kept of 12 (6 success, 4 failure); split sizes (trajectories): train 8, test 2.",
        "",
        "## Tower and sensor rows",
        "",
        SHIPPED,
        "",
        "## Supervision",
        "",
        "| grids | Q2 | majority Q2 | AUROC | Q3 (failures) | Q5 (failures) |",
        "|---|---|---|---|---|---|",
        "| seen, whole | 81.1 [78.3, 83.7] | 65.0 | 0.8782 | 59.3 [53.4, 64.9] | 56.8 [50.9, 62.5] |",
        "",
        "| pick | scripted | 6/25 | 23/25 | +68 | yes | 19 | 0 |",
        "",
        "## Paper-comparable tables",
        "",
    ]
)


def _page_and_run(tmp_path: Path) -> tuple[Path, Path]:
    """The test page, and a run folder holding only its dataset's stats (the page's data line)."""
    page, run = tmp_path / "RESULTS.md", tmp_path / "run"
    page.write_text(PAGE)
    (run / "dataset").mkdir(parents=True)
    (run / "dataset" / "stats.json").write_text(json.dumps(STATS))
    return page, run


def test_a_run_of_the_same_data_replaces_only_its_section(tmp_path: Path) -> None:
    """`sections=[ablation]`: a fresh run on the page's data (no main model) adds the ablation table, the frozen row
    carried from the page's shipped row, and leaves every other line of the page as it was; again: same page."""
    from scripts.write_results import main

    page, run = _page_and_run(tmp_path)
    _eval(run / "ablate" / "tuned" / "final" / "eval_test", 83.0)
    assert main([f"run={run}", f"out={page}", "sections=[ablation]"]) == 0
    text = page.read_text()
    head, rest = text.split("## Ablation (the paper's table, seen split)\n")
    table, tail = rest.split("## Supervision\n")
    assert head + "## Supervision\n" + tail == PAGE
    assert (
        "| tuned tower and merger | 83.0 [80.0, 86.0] | 61.0 [55.0, 66.0] | 57.5 [51.0, 63.0] | 0.6000 [0.550, 0.650] |"
        in table
    )
    frozen = "| frozen tower and merger (this page's `make reproduce` model) | 80.6 [77.7, 83.2] | 54.6 [48.8, 60.4] | "
    assert frozen + "50.7 [44.9, 56.5] | 0.5014 [0.455, 0.549] |" in table
    assert "Not run for this page: no temporal index" in table
    assert main([f"run={run}", f"out={page}", "sections=[ablation]"]) == 0
    assert page.read_text() == text


def test_a_rows_splice_keeps_the_pages_main_row_when_the_run_benched_its_model_on_validation_only(
    tmp_path: Path,
) -> None:
    """A run whose main model has validation benches but no seen test one (a lever's baseline) has no main row of its
    own: the page's row stays, named as carried, the new row is added, and the main row is not called "not run"."""
    from scripts.write_results import main

    page, run = _page_and_run(tmp_path)
    _eval(run / "train" / "final" / "eval_val_object", 82.6)
    _eval(run / "rows" / "deep4" / "final" / "eval_test", 82.0)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    table = page.read_text().split("## Tower and sensor rows\n")[1].split("## Supervision\n")[0]
    assert SHIPPED in table
    assert "| sim-pretrained tower, front + side, 4-layer decoder (chosen on validation" in table
    row = next(line for line in table.splitlines() if "4-layer decoder" in line)  # its own bench's figures
    assert "| 82.0 [79.0, 85.0] |" in row and "| 61.0 [55.0, 66.0] |" in row and "0.6000 [0.550, 0.650]" in row
    carried = next(line for line in table.splitlines() if line.startswith("Carried from the page"))
    assert "(`train`)" in carried and "Not run for this page: scratch tower" in table
    assert "(`train`)" not in table.split("Not run for this page: ")[1]
    # A later run that re-benches another row keeps every row the page has and it lacks (named as carried, its
    # figures as the page had them); a row no make target makes (rows/deep4) is never called "not run"; one that a
    # target makes and the page lacks (rows/more and rows/rand: make reproduce-more) is.
    shutil.rmtree(run / "rows" / "deep4")
    _eval(run / "rows" / "wrist" / "final" / "eval_test", 92.0)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    table = page.read_text().split("## Tower and sensor rows\n")[1].split("## Supervision\n")[0]
    assert "front + wrist" in table and "Not run for this page: scratch tower" in table
    assert row in table.splitlines() and SHIPPED in table.splitlines()
    carried = next(line for line in table.splitlines() if line.startswith("Carried from the page"))
    assert "(`rows/deep4`)" in carried and "(`train`)" in carried and "front + wrist" not in carried
    assert "(`rows/more`)" in table.split("Not run for this page: ")[1] and "(`rows/rand`)" in table
    # a run whose own `train` has a seen test bench (a later rerun of the recipe: another model) leaves the page's
    # main row as it was: the main row is the whole page's model
    _eval(run / "train" / "final" / "eval_test", 70.0)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    table = page.read_text().split("## Tower and sensor rows\n")[1].split("## Supervision\n")[0]
    assert SHIPPED in table.splitlines() and "| 70.0 [" not in table
    kept = next(line for line in table.splitlines() if line.startswith("Kept from the page: its main row"))
    assert "(`train`); the run's own `train` is another model." in kept
    assert "(`train`)" not in next(line for line in table.splitlines() if line.startswith("Carried from the page"))


def test_a_rows_splice_keeps_rows_added_by_hand_where_they_stood_and_says_which_cut_was_never_run(
    tmp_path: Path,
) -> None:
    """A row no folder makes (added to the page by hand) stays under the row it stood under, named as carried; a
    carried row shown without its cut line still says that cut's bench was not run; a second splice changes
    nothing."""
    from labrobfail_vlm.bench.page import ROWS
    from scripts.write_results import main

    page, run = _page_and_run(tmp_path)
    hand = "| the recipe rerun (added by hand) | 81.4 [78.8, 83.9] | 0.8824 | - | - | - | - | - | - | - | - | - |"
    tuned = f"| {ROWS['rows/rand_tuned']} | 85.0 [82.4, 87.5] | 0.9268 | - | - | - | - | - | - | - | - | - |"
    page.write_text(PAGE.replace(SHIPPED + "\n", f"{SHIPPED}\n{hand}\n{tuned}\n"))
    _eval(run / "rows" / "wrist" / "final" / "eval_test", 92.0)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    text = page.read_text()
    table = text.split("## Tower and sensor rows\n")[1].split("## Supervision\n")[0].splitlines()
    assert table[table.index(SHIPPED) + 1] == hand and tuned in table
    carried = next(line for line in table if line.startswith("Carried from the page"))
    assert "; the recipe rerun (added by hand)." in carried and "(`rows/rand_tuned`)" in carried
    not_run = next(line for line in table if line.startswith("Not run for this page"))
    assert "at its operating point chosen on val (`rows/rand_tuned`, threshold=val)" in not_run
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    assert page.read_text() == text


@pytest.mark.parametrize(
    ("folder", "title"),
    [("rand", "drawn in randomised scenes"), ("rand_tuned", "then two one-epoch stages with the tower")],
)
def test_a_row_chosen_at_an_operating_point_on_val_gets_a_second_row_at_that_cut(
    tmp_path: Path, folder: str, title: str
) -> None:
    """A row's benches at its val-chosen cut (eval_<split>_opval) are a row of their own under its 0.5 row, the cut
    named; without them the table says that bench was not run."""
    from scripts.write_results import main

    page, run = _page_and_run(tmp_path)
    _eval(run / "rows" / folder / "final" / "eval_test", 82.4)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    table = page.read_text().split("## Tower and sensor rows\n")[1].split("## Supervision\n")[0]
    assert title in table and f"at its operating point chosen on val (`rows/{folder}`" in table
    for split, q2 in (("test", 81.9), ("test_both", 79.0)):
        _eval(run / "rows" / folder / "final" / f"eval_{split}_opval", q2)
        f = run / "rows" / folder / "final" / f"eval_{split}_opval" / "results.json"
        f.write_text(json.dumps({**json.loads(f.read_text()), "threshold": 0.4421825, "threshold_chosen_on": "val"}))
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    lines = page.read_text().split("## Tower and sensor rows\n")[1].split("## Supervision\n")[0].splitlines()
    i = next(k for k, line in enumerate(lines) if title in line)
    assert "| 82.4 [79.4, 85.4] |" in lines[i]
    assert lines[i + 1].startswith("| the row above at P(failure) >= 0.442, the cut chosen on its seen-val bench")
    assert "| 81.9 [78.9, 84.9] |" in lines[i + 1] and lines[i + 1].endswith("| 79.0 [76.0, 82.0] |")
    assert f"operating point chosen on val (`rows/{folder}`" not in "\n".join(lines)
    # a later splice from a run without this row keeps both its lines, in order
    shutil.rmtree(run / "rows" / folder)
    _eval(run / "rows" / "wrist" / "final" / "eval_test", 92.0)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    after = page.read_text().split("## Tower and sensor rows\n")[1].split("## Supervision\n")[0].splitlines()
    j = after.index(lines[i])
    assert after[j + 1] == lines[i + 1]
    assert any(line.startswith("| sim-pretrained tower, front + wrist") for line in after)


def test_a_run_of_other_data_or_without_the_section_is_refused(tmp_path: Path) -> None:
    """A section from a run of other data is refused, the page as it was; the sealed list alone takes that run's
    sealed runs (every look at a sealed split is listed, whatever data it was made on)."""
    import pytest

    from labrobfail_vlm.bench.evaluate import count_sealed_run
    from labrobfail_vlm.config import ConfigError
    from scripts.write_results import main

    page, run = tmp_path / "RESULTS.md", tmp_path / "run"
    page.write_text(PAGE)
    (run / "dataset").mkdir(parents=True)
    (run / "dataset" / "stats.json").write_text(json.dumps({**STATS, "trajectories_kept": 11}))
    _eval(run / "ablate" / "tuned" / "final" / "eval_test", 83.0)
    with pytest.raises(ConfigError, match="data are not"):
        main([f"run={run}", f"out={page}", "sections=[ablation]"])
    with pytest.raises(ConfigError, match="data are not"):  # a table with the ledger: still the page's data only
        main([f"run={run}", f"out={page}", "sections=[ablation,sealed]"])
    assert page.read_text() == PAGE
    # the ledger alone: a run of other data (a later recipe's drawing of the same pairs) still looked at sealed splits
    count_sealed_run(run / "dataset", "test_scene", "outputs/later/train/final", _scores(70, 50, 60, 50, 0.5))
    assert main([f"run={run}", f"out={page}", "sections=[sealed]"]) == 0
    listed = page.read_text()
    assert "| test_scene | `outputs/later/train/final` | 70 |" in listed and "(1 in all;" in listed
    assert listed.split("## Sealed test runs")[0] == PAGE.split("## Paper-comparable tables")[0]  # nothing else moved
    page.write_text(PAGE)
    (run / "dataset" / "stats.json").write_text(json.dumps(STATS))
    with pytest.raises(ConfigError, match="no results under rows/scratch"):
        main([f"run={run}", f"out={page}", "sections=[rows]"])
    with pytest.raises(ConfigError, match="unknown"):
        main([f"run={run}", f"out={page}", "sections=[tables]"])
    assert page.read_text() == PAGE


def test_a_recovery_table_alone_replaces_the_pages_and_keeps_its_online_table(tmp_path: Path) -> None:
    """`sections=[supervision]` from a run with `make recovery`'s tables and no online model: the new recovery rows
    replace the old, the page's online table is carried (and said to be), every other section is untouched."""
    from scripts.write_results import main

    page, run = tmp_path / "RESULTS.md", tmp_path / "run"
    row = "| pick | scripted | 6/25 | 23/25 | +68 | yes | 19 | 0 |\n"
    absent = (
        "Not run for this page: Ablation (the paper's table, seen split) (`ablate/tuned`, `ablate/frozen`, "
        "`ablate/no_index`)."
    )
    page.write_text(PAGE.replace(row, f"{row}\n{absent}\n"))  # where the whole page puts it: in its last section
    (run / "dataset").mkdir(parents=True)
    (run / "dataset" / "stats.json").write_text(json.dumps(STATS))
    _results(run / "recovery" / "scripted" / "results.json", "scripted", {"pick": (6, 25)})
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0
    text = page.read_text()
    head, rest = text.split("## Supervision\n")
    section, tail = rest.split("## Paper-comparable tables\n")
    assert head == PAGE.split("## Supervision\n")[0] and tail == PAGE.split("## Paper-comparable tables\n")[1]
    assert "| seen, whole | 81.1 [78.3, 83.7] |" in section and "as the page had it" in section
    assert section.count(absent) == 1  # the page's line on the sections it lacks survives the splice
    assert "| pick | scripted | 6/25 | 25/25 | +76 | yes | [+51.7, +89.1] | 3.81e-06 | 0/6 | 3 | 1 |" in section
    assert "23/25" not in section
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0
    assert page.read_text() == text


def test_a_timeline_without_done_is_not_called_end_to_end() -> None:
    """The wall-clock line says "end to end" only for a run whose timeline reached "done"; a run stopped earlier
    (its learning curve interrupted, say) names the step where its clock stops."""
    from scripts.write_results import timing

    stamps = [["generate", "0"], ["train", "600"], ["learning_curve", "900"]]
    stopped = timing(stamps)[0]
    assert "until its `learning_curve` step" in stopped and "end to end" not in stopped
    assert "**15.0 min**" in stopped and "generate 10.0 min, train 5.0 min" in stopped
    done = timing([*stamps, ["done", "960"]])[0]
    assert "end to end: **16.0 min**" in done and "learning_curve 1.0 min" in done
    assert timing([["generate", "0"]]) == []


def _scores(q2: float, q3: float, q4: float, q5: float, rouge: float) -> dict:
    """The parts of a bench results.json that the targets table reads."""
    fo = {"q3": q3, "q4": q4, "q5": q5, "q6": {"rougeL": rouge}, "ci95": {}}
    return {"q2": q2, "ci95": {}, "failure_only": fo}


def test_the_targets_table_needs_the_margin_over_both_baselines_and_says_what_was_not_run() -> None:
    from scripts.write_results import targets

    test = {
        **_scores(92.0, 80.0, 85.0, 75.0, 0.76),
        "baselines": {
            "majority class": _scores(64.0, 60.0, 74.0, 30.0, 0.43),
            "blind (grey grid)": _scores(64.0, 71.0, 74.0, 30.0, 0.43),
        },
        "q2_by_type": {"object_slippage": {"q2": 75.0, "n": 20, "ci95": [60, 88]}, "success": {"q2": 99, "n": 400}},
    }
    val = {
        **_scores(80.0, 50.0, 70.0, 50.0, 0.5),
        "baselines": {"majority class": _scores(60.0, 40.0, 76.0, 30.0, 0.4)},
    }
    sealed = {**_scores(79.33, 70.0, 70.0, 60.0, 0.6), "baselines": {}, "ci95": {"q2": [73.3, 85.3]}}
    rows = {line.split(" | ")[0].strip("| "): line for line in targets({"test": test, "val_both": val})}
    got = {line.split(" | ")[0].strip("| "): line for line in targets({"test": test, "test_object": sealed})}
    assert "| no: within its interval |" in got["sealed unseen objects Q2"]  # 79.33 >= 79.2, but 73.3 is under it
    assert "| yes |" in rows["seen Q2"] and "| yes |" in rows["seen failure-only Q4"]
    assert "| no |" in rows["seen failure-only Q3"]  # 80 is 9 points over the blind model's 71: under the margin
    assert "not run" in rows["sealed unseen objects and scene Q2"] and "| no |" in rows["sealed unseen scene Q2"]
    assert "not on val_both" in rows["failure-only Q4 above the majority class on every split"]  # 70 <= 76
    assert "object_slippage 75" in rows["seen Q2 recall >= 80 % for each failure type with >= 20 test failures"]
    # a margin met exactly: 0.85 - 0.75 is 0.0999... in floating point, and the tie must pass
    tie = {**test, "failure_only": {**test["failure_only"], "q6": {"rougeL": 0.85}}}
    tie["baselines"] = {b: _scores(64.0, 60.0, 74.0, 30.0, 0.75) for b in test["baselines"]}
    assert "| yes |" in next(line for line in targets({"test": tie}) if line.startswith("| seen failure-only ROUGE-L"))


def test_a_splice_restates_a_kept_targets_row_that_read_yes_by_its_point_alone(tmp_path: Path) -> None:
    """A targets table written before 3 Dec's rule read "yes" for a point over its target whose interval reaches
    under it; a splice keeps that table and writes it by today's rule, touching no other row. A page's claim later
    found wrong (the sealed family's colours, which the tower's augmentation reaches) is restated the same way."""
    from labrobfail_vlm.bench.evaluate import count_sealed_run
    from labrobfail_vlm.bench.page import SEALED_CLAIM
    from scripts.write_results import main

    old = "| sealed unseen objects and scene Q2 | 76.67 | >= 71.0 | yes | 76.7 [70.7, 82.7] |"
    kept = [
        "| seen Q2 | 93.62 | >= 90.8 | yes | 93.6 [91.9, 95.4]; majority class 64.75, blind (grey grid) 35.25 |",
        "| seen failure-only ROUGE-L | 0.8026 | >= 0.75 | yes | 0.8026 [0.762, 0.843]; majority class 0.0969 |",
        "| sealed unseen scene Q2 | 80.67 | >= 85.6 | no | 80.7 [74.0, 86.7] |",
    ]
    table = ["## Targets of the principal issue", "", "| goal | reached | target | met | 95 % interval |", "|---|"]
    page, run = _page_and_run(tmp_path)
    claim = "Splits: `test_both` (the sealed catalogue and scene family, which nothing trained, pretrained or tuned"
    claim += " draws from; run only for the rows reported here)"
    body = [claim, "", *table, old, *kept, "", "## Tower and sensor rows"]
    page.write_text(PAGE.replace("## Tower and sensor rows", "\n".join(body)))
    count_sealed_run(run / "dataset", "test_both", "outputs/r/train/final", _scores(77.0, 60.0, 67.0, 58.0, 0.62))
    assert main([f"run={run}", f"out={page}", "sections=[sealed]"]) == 0
    text = page.read_text()
    assert old not in text and old.replace("| yes |", "| no: within its interval |") in text
    assert all(row in text for row in kept)
    assert f"Splits: `test_both` ({SEALED_CLAIM} run only" in text and "which nothing trained" not in text


def test_a_page_made_on_the_tower_shipped_until_6_dec_says_so_once_another_is_shipped() -> None:
    """The 6 Dec afternoon page called its tower `shipped` and its augmentation the shipped tower's; once the tower
    without saturation gain replaced it, a splice names the page's own tower instead, by its sha256."""
    from labrobfail_vlm.bench.page import SEALED_CLAIM, restate

    then = SEALED_CLAIM.replace("the page's tower's colour", "the shipped tower's colour")
    assert then != SEALED_CLAIM and restate(f"Splits: `test_both` ({then} run only") == (
        f"Splits: `test_both` ({SEALED_CLAIM} run only"
    )
    line = (
        "- Vision tower: `shipped` (sha256 `b64d9663c780c584...`, 1,515,008 parameters; what it learned and how "
        "well, held out: its TOWER_CARD.md)."
    )
    assert restate(line).startswith("- Vision tower: the one shipped until 6 Dec (sha256 `b64d9663c780c584...`")
    other = line.replace("b64d9663c780c584", "414fed7eec8fa82f")  # a page made on today's shipped tower: kept
    assert restate(other) == other


def _supervision_page(tmp_path: Path, section: list[str]) -> tuple[Path, Path]:
    """A page whose Supervision section is `section`, and a run folder of the page's data (nothing else yet)."""
    page, run = tmp_path / "RESULTS.md", tmp_path / "run"
    head, tail = PAGE.split("## Supervision\n")[0], PAGE.split("\n\n## Paper-comparable tables")[1]
    page.write_text(head + "\n".join(section) + "\n## Paper-comparable tables" + tail)
    (run / "dataset").mkdir(parents=True)
    (run / "dataset" / "stats.json").write_text(json.dumps(STATS))
    return page, run


def _scripted_pick() -> list[str]:
    """An old page's recovery table: one scripted pick cell of 25 trials."""
    from sim_backends.supervision.report import HEADER, LEAD

    return [
        f"{LEAD}25 trials per cell, variant seen, supervisor vlm (`m`) asked only when the policy stops, budget 2.",
        "",
        HEADER,
        "|---|---|---|---|---|---|---|---|---|---|---|",
        "| pick | scripted | 6/25 | 23/25 | +68 | yes | - | - | - | 19 | 0 |",
        "",
    ]


def test_a_rerun_of_some_cells_keeps_the_pages_other_cells_and_online_bench(tmp_path: Path) -> None:
    """`sections=[supervision]` from a run that re-measured one ACT cell only (a fresh machine): that row is the run's,
    the page's scripted rows and online bench are carried and named as carried; splicing again changes nothing."""
    from scripts.write_results import ONLINE_GUARANTEE, main
    from sim_backends.supervision.report import HEADER, LEAD

    setting = "25 trials per cell, variant seen, supervisor vlm (`m`) asked only when the policy stops, budget 2"
    old = [
        "## Supervision",
        "",
        ONLINE_GUARANTEE,
        "",
        "| row | alpha | false alarms (%) |",
        "",
        f"{LEAD}{setting}.",
        "",
        HEADER,
        "|---|---|---|---|---|---|---|---|---|---|---|",
        "| pick | scripted | 6/25 | 23/25 | +68 | yes | - | - | - | 19 | 0 |",
        "| pick | act | 1/25 | 2/25 | +4 | yes | - | - | - | 3 | 0 |",
        "",
    ]
    page, run = _supervision_page(tmp_path, old)
    _results(run / "recovery" / "act" / "pick" / "results.json", "act", {"pick": (2, 12)}, "m", -1)
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0
    text = page.read_text()
    section = text.split("## Supervision\n")[1].split("## Paper-comparable tables")[0]
    assert "The online bench as the page had it (this run has none):" in section
    assert "| row | alpha | false alarms (%) |" in section
    rows = [r for r in section.splitlines() if r.startswith("| pick |")]
    assert rows[0] == "| pick | scripted | 6/25 | 23/25 | +68 | yes | - | - | - | 19 | 0 |"
    assert rows[1].startswith("| pick | act | 2/25 | 12/25 | +40 | yes |") and len(rows) == 2
    lead = next(line for line in section.splitlines() if line.startswith(LEAD))
    assert f"act pick: {setting}, a manual correction: stop" in lead
    assert f"scripted pick: {setting} (rows carried from the page, not re-run)" in lead
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0
    assert page.read_text() == text


def test_an_online_bench_alone_replaces_the_pages_and_carries_the_rest(tmp_path: Path) -> None:
    """`sections=[supervision]` from a run that ran only `make online-bench` (the main model's online bench): its
    tables replace the page's, the online model's table and every recovery cell are carried and named as carried,
    and the section's old provenance (it was carried whole from an older page) now speaks of those parts alone."""
    import pytest

    from labrobfail_vlm.config import ConfigError
    from scripts.write_results import CARRIED_SECTION, ONLINE_GUARANTEE, STILL_CARRIED, _still_carried, main
    from sim_backends.supervision.report import LEAD

    old = [
        "## Supervision",
        "",
        CARRIED_SECTION + " That page's data and tower: the old line.",
        "",
        "| grids | Q2 | majority Q2 | AUROC | Q3 (failures) | Q5 (failures) |",
        "|---|---|---|---|---|---|",
        "| seen, whole | 80.0 | 60.0 | 0.8 | 50.0 | 50.0 |",
        "",
        ONLINE_GUARANTEE,
        "",
        "| row | alpha | false alarms (%) | the old bench |",
        "",
        *_scripted_pick(),
    ]
    page, run = _supervision_page(tmp_path, old)
    bench = run / "train" / "final" / "eval_online_test" / "online.json"
    with pytest.raises(ConfigError, match="no results under online, recovery, train/final/eval_online_"):
        main([f"run={run}", f"out={page}", "sections=[supervision]"])  # nothing to splice yet
    bench.parent.mkdir(parents=True)
    majority = {"false_alarm_rate": 0.0, "detection_rate": 0.0}
    res = {"split": "test", "calibration": "val", "trajectories": 3, "calibration_successes": 2}
    bench.write_text(json.dumps(res | {"rows": {"majority class": {a: majority for a in ("0.01", "0.05")}}}))
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0
    section = page.read_text().split("## Supervision\n")[1].split("## Paper-comparable tables")[0]
    assert "The online model as the page had it (this run has none):" in section and "| seen, whole |" in section
    assert "`train/final`, eval_online_test:" in section and "| majority class | any | 0.0 |" in section
    assert "the old bench" not in section and "Made on `" in section
    assert "| pick | scripted | 6/25 | 23/25 | +68 | yes |" in section
    assert "(rows carried from the page, not re-run)" in next(x for x in section.splitlines() if x.startswith(LEAD))
    said = [x for x in section.splitlines() if "the old line" in x]
    assert said == [STILL_CARRIED + " That page's data and tower: the old line."]
    assert _still_carried(old, ["| pick | scripted | 6/25 | 24/25 |"]) == []  # all re-measured: nothing older left
    carried = ["(rows carried from the page, not re-run)"]
    assert _still_carried(["## Supervision", "", "| row |"], carried) == []  # the section was the page's own
    nested = ["## Supervision", "", "| row |", "", "### Supervision: the page this one replaced", "", old[2]]
    assert _still_carried(nested, carried) == []  # a block a whole-page rewrite kept under it speaks for itself
    text = page.read_text()
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0 and page.read_text() == text
    # make online-power's model-free bench of a block drawn apart joins the section after the model's benches
    from scripts.write_results import POWER_LEAD

    power = run / "online_power" / "online.json"
    power.parent.mkdir()
    power.write_text(
        bench.read_text().replace('"split": "test"', '"split": "test", "scored_dataset": "r/dataset_power"')
    )
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0
    section = page.read_text().split("## Supervision\n")[1]
    assert section.index("`train/final`, eval_online_test:") < section.index(f"{POWER_LEAD} `online_power`:")
    assert "split test of dataset_power, a dataset drawn apart (3 trajectories)" in section


def test_a_run_with_only_a_power_block_carries_the_pages_other_benches_block_by_block(tmp_path: Path) -> None:
    """`sections=[supervision]` from a run that ran only `make online-power POWER_NAME=power2`: its block is the
    run's, the page's model bench and its first power block are carried, each lead marked as the page had it, in the
    page's order; splicing again changes nothing."""
    from scripts.write_results import AS_THE_PAGE_HAD_IT, ONLINE_GUARANTEE, POWER_LEAD, main

    old = [
        "## Supervision",
        "",
        ONLINE_GUARANTEE,
        "",
        "`train/final`, eval_online_test:",
        "",
        "| the model's old bench |",
        "",
        f"{POWER_LEAD} `online_power`:",
        "",
        "| the first block's old bench |",
        "",
        *_scripted_pick(),
    ]
    page, run = _supervision_page(tmp_path, old)
    bench = run / "online_power2" / "online.json"
    bench.parent.mkdir()
    majority = {"false_alarm_rate": 0.0, "detection_rate": 0.0}
    res = {"split": "test", "scored_dataset": "r/dataset_power2", "calibration": "val", "trajectories": 3}
    bench.write_text(json.dumps(res | {"calibration_successes": 2, "rows": {"majority class": {"0.01": majority}}}))
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0
    section = page.read_text().split("## Supervision\n")[1].split("## Paper-comparable tables")[0].splitlines()
    leads = [x for x in section if x.startswith(("`train/final`", POWER_LEAD))]
    assert leads == [
        f"`train/final`, eval_online_test, {AS_THE_PAGE_HAD_IT}:",
        f"{POWER_LEAD} `online_power`, {AS_THE_PAGE_HAD_IT}:",
        f"{POWER_LEAD} `online_power2`:",
    ]
    assert "| the model's old bench |" in section and "| the first block's old bench |" in section
    assert "split test of dataset_power2, a dataset drawn apart (3 trajectories)" in "\n".join(section)
    text = page.read_text()
    assert main([f"run={run}", f"out={page}", "sections=[supervision]"]) == 0 and page.read_text() == text


def test_the_tuned_model_is_spliced_with_its_sealed_runs_and_a_fresh_ledger_joins_the_page_list(tmp_path: Path) -> None:
    """`sections=[tuned]`: the tuned model's targets and per-split scores go before the tower rows; the run's ledger
    joins the page's "Sealed test runs" list, which keeps every run it listed (`sections=[sealed]`: the list alone)."""
    import pytest

    from labrobfail_vlm.bench.evaluate import SEALED_LEDGER, count_sealed_run
    from labrobfail_vlm.config import ConfigError
    from scripts.write_results import main

    old_run = "| 2026-11-29 02:18 UTC | test_both | `outputs/r14/train/final` | 76.67 | 56.9 | 68.97 | 56.9 | 0.6267 |"
    sealed = ["## Sealed test runs", "", "| date | split | model | Q2 | Q3 | Q4 | Q5 | ROUGE-L |", "|---|", old_run, ""]
    page_text = PAGE.replace("## Paper-comparable tables", "\n".join([*sealed, "## Paper-comparable tables"]))
    page, run = tmp_path / "RESULTS.md", tmp_path / "run"
    page.write_text(page_text)
    (run / "dataset").mkdir(parents=True)
    (run / "dataset" / "stats.json").write_text(json.dumps(STATS))
    tuned = run / "tuned" / "final"
    majority, blind = _scores(64.0, 60.0, 74.0, 30.0, 0.43), _scores(50.0, 25.0, 45.0, 13.0, 0.36)
    bases = {"majority class": majority, "blind (grey grid)": blind}
    for split, q2 in (("val", 80.9), ("test", 84.0), ("test_both", 77.0)):
        (tuned / f"eval_{split}").mkdir(parents=True)
        res = {**_scores(q2, 60.0, 67.0, 58.0, 0.62), "baselines": bases, "detection": {"auroc": 0.9}}
        (tuned / f"eval_{split}" / "results.json").write_text(json.dumps(res))
    bare = tmp_path / "bare"  # a run whose ledgers hold nothing: sections=[sealed] refused, the page as it was
    (bare / "dataset").mkdir(parents=True)
    (bare / "dataset" / "stats.json").write_text(json.dumps(STATS))
    with pytest.raises(ConfigError, match="has no sealed runs"):
        main([f"run={bare}", f"out={page}", "sections=[sealed]"])
    assert page.read_text() == page_text
    # a ledger started afresh (a fresh machine's regeneration of the same episodes) lacks the page's run: it joins
    count_sealed_run(run / "dataset", "test_both", str(tuned), _scores(77.0, 60.0, 67.0, 58.0, 0.62))
    assert main([f"run={run}", f"out={page}", "sections=[sealed]"]) == 0
    joined = page.read_text()
    assert old_run in joined and f"| test_both | `{tuned}` | 77.0 |" in joined and "(2 in all;" in joined
    assert joined.index(old_run) < joined.index(f"`{tuned}`")  # oldest first
    assert joined.split("## Sealed test runs")[0] == page_text.split("## Sealed test runs")[0]  # nothing else moved
    assert joined.split("## Paper-comparable tables")[1] == page_text.split("## Paper-comparable tables")[1]
    page.write_text(page_text)
    ledger = run / "dataset" / SEALED_LEDGER
    carried = {"date": "2026-11-29 02:18 UTC", "split": "test_both", "source": "outputs/r14/train/final", "q2": 76.67}
    carried |= {"q3_failures": 56.9, "q4_failures": 68.97, "q5_failures": 56.9, "rougeL_failures": 0.6267}
    ledger.write_text(json.dumps(carried) + "\n" + ledger.read_text())
    (run / "dataset_wrist").mkdir()
    count_sealed_run(run / "dataset_wrist", "test_scene", "outputs/r/rows/wrist/final", _scores(70, 50, 60, 50, 0.5))
    assert main([f"run={run}", f"out={page}", "sections=[tuned]"]) == 0
    text = page.read_text()
    assert "| test_scene | `outputs/r/rows/wrist/final` | 70 |" in text  # a sensor row's dataset keeps its own ledger
    head, rest = text.split("## The tuned continuation (make reproduce-tuned)\n")
    section, tail = rest.split("## Tower and sensor rows\n")
    assert "| seen Q2 | 84.0 | >= 90.8 | no |" in section and "| sealed unseen objects and scene Q2 | 77.0 |" in section
    assert "| val | 80.9 | 0.9 | 60.0 | 67.0 | 58.0 | 0.62 |" in section
    assert old_run in tail and f"| test_both | `{tuned}` | 77.0 | 60.0 | 67.0 | 58.0 | 0.62 |" in tail
    assert "(3 in all;" in tail
    assert head == page_text.split("## Tower and sensor rows\n")[0]


def test_a_spliced_section_leaves_the_not_run_line_and_brings_a_sealed_list_the_page_lacked(tmp_path: Path) -> None:
    from labrobfail_vlm.bench.evaluate import count_sealed_run
    from scripts.write_results import NOT_RUN, _absent, main

    not_run = NOT_RUN + _absent("tuned") + "; " + _absent("ablation") + "."
    page_text = PAGE.replace("## Paper-comparable tables", not_run + "\n\n## Paper-comparable tables")
    page, run = tmp_path / "RESULTS.md", tmp_path / "run"
    page.write_text(page_text)
    (run / "dataset").mkdir(parents=True)
    (run / "dataset" / "stats.json").write_text(json.dumps(STATS))
    bases = {"majority class": _scores(64.0, 60.0, 74.0, 30.0, 0.43)}
    (run / "tuned" / "final" / "eval_test").mkdir(parents=True)
    res = {**_scores(84.0, 60.0, 67.0, 58.0, 0.62), "baselines": bases}
    (run / "tuned" / "final" / "eval_test" / "results.json").write_text(json.dumps(res))
    count_sealed_run(run / "dataset", "test_scene", "outputs/r/tuned/stage2/final", res)
    assert main([f"run={run}", f"out={page}", "sections=[tuned]"]) == 0
    text = page.read_text()
    assert NOT_RUN + _absent("ablation") + "." in text and _absent("tuned") not in text
    sealed = text.split("## Sealed test runs\n")[1].split("## Paper-comparable tables")[0]
    assert "(1 in all;" in sealed and "| test_scene | `outputs/r/tuned/stage2/final` | 84.0 |" in sealed
    assert "| test | 84.0 | – |" in text  # no AUROC in this result: a dash, not "None"


def test_the_lit_chain_gets_its_own_targets_section_and_a_row_it_never_lists_as_not_run(tmp_path: Path) -> None:
    """`sections=[lit,rows]` from a run holding rows/lit (the tuned chain remade on lit episodes): its targets table
    goes before the rows table and its row into it; a run without rows/lit never names it as missing."""
    from labrobfail_vlm.bench.page import ROWS
    from scripts.write_results import SECTIONS, main

    page, run = _page_and_run(tmp_path)
    test = {
        **_scores(92.0, 80.0, 85.0, 75.0, 0.76),
        "baselines": {b: _scores(64.0, 60.0, 74.0, 30.0, 0.43) for b in ("majority class", "blind (grey grid)")},
        "q2_by_type": {"success": {"q2": 99, "n": 400}},
        "ci95": {"q2": [90.9, 93.0]},
    }
    (run / "rows" / "lit" / "final" / "eval_test").mkdir(parents=True)
    (run / "rows" / "lit" / "final" / "eval_test" / "results.json").write_text(json.dumps(test))
    assert main([f"run={run}", f"out={page}", "sections=[lit,rows]"]) == 0
    text = page.read_text()
    lit, rows = text.index("## The tuned chain drawn lit"), text.index("## Tower and sensor rows")
    assert lit < rows and "| seen Q2 | 92.0 | >= 90.8 | yes | 92.0 [90.9, 93.0]" in text[lit:rows]
    assert f"| {ROWS['rows/lit']} | 92.0 [90.9, 93.0] |" in text[rows:] and "rows/lit_q" not in text
    # the lit row read from all four questions: its own section, after the lit row's and before the rows table
    (run / "rows" / "lit_q" / "final" / "eval_test").mkdir(parents=True)
    (run / "rows" / "lit_q" / "final" / "eval_test" / "results.json").write_text(json.dumps(test))
    assert main([f"run={run}", f"out={page}", "sections=[lit_q,rows]"]) == 0
    text = page.read_text()
    q = text.index("## The lit row with detection from all four closed questions")
    assert lit < q < text.index("## Tower and sensor rows") and f"| {ROWS['rows/lit_q']} | 92.0 [90.9, 93.0] |" in text
    # the five-stage chain on the shipped tower: its section goes first, before the lit ones
    (run / "rows" / "rand5_q" / "final" / "eval_test").mkdir(parents=True)
    (run / "rows" / "rand5_q" / "final" / "eval_test" / "results.json").write_text(json.dumps(test))
    assert main([f"run={run}", f"out={page}", "sections=[rand5_q,rows]"]) == 0
    text = page.read_text()
    five = text.index(SECTIONS["rand5_q"][0])
    assert five < text.index("## The tuned chain drawn lit")
    assert f"| {ROWS['rows/rand5_q']} | 92.0 [90.9, 93.0] |" in text[text.index("## Tower and sensor rows") :]
    page.write_text(PAGE)
    shutil.rmtree(run / "rows" / "lit")
    _eval(run / "rows" / "more" / "final" / "eval_test", 81.0)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    assert "rows/lit" not in page.read_text()


def test_a_whole_page_keeps_the_sealed_runs_the_page_it_replaces_listed(tmp_path: Path) -> None:
    """A whole page written over another (a run on another data line, say) starts from that page's sealed-run list:
    every look at a sealed split stays counted; its other sections are the run's alone."""
    from labrobfail_vlm.bench.evaluate import count_sealed_run
    from labrobfail_vlm.bench.page import sealed_section
    from scripts.write_results import page_ledger

    old_run = "| 2026-11-29 02:18 UTC | test_both | `outputs/r14/train/final` | 76.67 | 56.9 | 68.97 | 56.9 | 0.6267 |"
    sealed = ["## Sealed test runs", "", "| date | split | model | Q2 | Q3 | Q4 | Q5 | ROUGE-L |", "|---|", old_run, ""]
    page = tmp_path / "RESULTS.md"
    assert page_ledger(page) == []  # no page yet
    page.write_text(PAGE.replace("## Paper-comparable tables", "\n".join([*sealed, "## Paper-comparable tables"])))
    assert page_ledger(page) == [old_run]
    (tmp_path / "dataset").mkdir()
    count_sealed_run(tmp_path / "dataset", "test_scene", "outputs/c/rows/c5_q", _scores(90.0, 80.0, 82.0, 75.0, 0.8))
    lines = sealed_section([tmp_path / "dataset"], kept=page_ledger(page))
    assert "(2 in all;" in lines[2] and lines[-3] == old_run and "`outputs/c/rows/c5_q` | 90.0 |" in lines[-2]


def _older_page(page: Path) -> None:
    """The test page as another run wrote it: another data line and tower, section intros, a "Made on" line and a
    "Kept from the page" line of its own."""
    from scripts.write_results import MAIN_KEPT, SECTIONS

    sv, rows = SECTIONS["supervision"], SECTIONS["rows"]
    text = PAGE.replace("10 kept of 12", "20 kept of 24").replace(
        "(trajectories): train 8, test 2.", "(trajectories): train 8, test 2.\n- Vision tower: `shipped` (old)."
    )
    text = text.replace(f"{sv[0]}\n", f"{sv[0]}\n\n{sv[1]}\nMade on `outputs/r15`, whose data are this page's.\n")
    text = text.replace(f"{rows[0]}\n", f"{rows[0]}\n\n{rows[1]}\n")
    page.write_text(text.replace(f"{SHIPPED}\n", f"{SHIPPED}\n\n{MAIN_KEPT}the old main row.\n"))


def test_a_whole_page_carries_only_the_sections_it_is_told_to_and_marks_them(tmp_path: Path) -> None:
    """`carry=[supervision]`: a whole page from another run's page keeps its Supervision section (intro included),
    marked as carried with that page's data and tower lines, its "Made on" line no longer claiming the page's data;
    without `carry` the section is named as not run; a section the old page lacks is refused in one line."""
    import pytest

    from labrobfail_vlm.config import ConfigError
    from scripts.write_results import CARRIED_SECTION, NOT_RUN, SECTIONS, main, model_sections

    page, run = _page_and_run(tmp_path)
    _older_page(page)
    lines = model_sections(run, page, ["supervision"])
    at = lines.index("## Supervision")
    lead = f"{CARRIED_SECTION} That page's data and tower: Trajectories: 20 kept of 24 (6 success, 4 failure)"
    assert lines[at + 2].startswith(lead) and lines[at + 2].endswith(
        "Physics: not stated. Vision tower: `shipped` (old)."
    )
    assert (
        SECTIONS["supervision"][1] in lines[at:] and "| pick | scripted | 6/25 | 23/25 | +68 | yes | 19 | 0 |" in lines
    )
    assert "Made on `outputs/r15`, on another data line than this page's." in lines[at:]
    not_run = next(line for line in lines if line.startswith(NOT_RUN))
    assert "Supervision" not in not_run and "Ablation" in not_run
    plain = model_sections(run, page, [])
    assert "## Supervision" not in plain and "Supervision (`online`" in next(x for x in plain if x.startswith(NOT_RUN))
    with pytest.raises(ConfigError, match="^carry: .* has no ablation section to carry"):
        model_sections(run, page, ["ablation"])
    with pytest.raises(ConfigError, match="^carry: only for a whole page"):
        main([f"run={run}", f"out={page}", "sections=[rows]", "carry=[supervision]"])
    # written again over its own output (the run's data line): the same lines, the first lead kept
    page.write_text("\n".join(["# results", "", "## Data and model", "", PAGE.split("\n")[4], "", *lines, ""]))
    assert model_sections(run, page, ["supervision"]) == lines


def test_carried_rows_sit_under_the_runs_own_and_stay_there(tmp_path: Path) -> None:
    """`carry=[rows]` with a run that has rows: the run's table, then the replaced page's rows under a sub-heading,
    marked (its intro and "Kept from the page" line dropped); the page written again from the same run keeps that
    block once, lead and all, and never carries the run's own table; a later `sections=[rows]` splice re-benches the
    page's own rows and leaves the block's rows in the block."""
    from labrobfail_vlm.bench.page import MAIN_KEPT, ROWS
    from scripts.write_results import CARRIED_SECTION, SECTIONS, main, model_sections

    page, run = _page_and_run(tmp_path)
    _older_page(page)
    _eval(run / "rows" / "wrist" / "final" / "eval_test", 92.0)
    wrist = f"| {ROWS['rows/wrist']} | 92.0"
    lines = model_sections(run, page, ["rows"])
    at, beside = (
        lines.index(SECTIONS["rows"][0]),
        lines.index(f"### {SECTIONS['rows'][0][3:]}: the page this one replaced"),
    )
    assert lines[at + 4].startswith("| row |") and any(x.startswith(wrist) for x in lines[at:beside])
    assert lines[beside + 2].startswith(f"{CARRIED_SECTION} That page's data and tower: Trajectories: 20 kept of 24")
    assert lines.index(SHIPPED) > beside and not any(x.startswith(wrist) for x in lines[beside:])
    assert SECTIONS["rows"][1] not in lines[beside:] and not any(x.startswith(MAIN_KEPT) for x in lines)
    # written again over its own output (the run's data line): one block, the first lead, no run rows in it
    page.write_text("\n".join(["# results", "", "## Data and model", "", PAGE.split("\n")[4], "", *lines, ""]))
    again = model_sections(run, page, ["rows"])
    block = again[again.index(lines[beside]) :]
    assert again.count(lines[beside]) == 1 and block[2] == lines[beside + 2] and SHIPPED in block
    assert not any(x.startswith(wrist) for x in block)
    # a splice of the rows: the page's own rows from the run, the block's rows left in the block
    page.write_text("\n".join([*PAGE.split("\n")[:6], *lines, "## Paper-comparable tables", ""]))
    _eval(run / "rows" / "wrist" / "final" / "eval_test", 91.0)
    assert main([f"run={run}", f"out={page}", "sections=[rows]"]) == 0
    text = page.read_text()
    cut = text.index(lines[beside])
    assert f"| {ROWS['rows/wrist']} | 91.0" in text[:cut] and SHIPPED in text[cut:] and SHIPPED not in text[:cut]


def test_a_tower_given_by_path_is_named_as_the_shipped_one_when_its_bytes_are() -> None:
    """A main row trained from a candidate tower's folder before it was adopted: the page says it is the bytes shipped
    when the page was written (by sha256), and says nothing for another tower or for `shipped` itself."""
    from labrobfail_vlm.model.tower import read_card, shipped_dir
    from scripts.write_results import _shipped_bytes

    sha = read_card(shipped_dir())["sha256"]
    assert (
        _shipped_bytes({"path": "outputs/tower_c/export", "sha256": sha})
        == ", the bytes shipped when this page was written"
    )
    assert _shipped_bytes({"path": "outputs/tower/export", "sha256": "0" * 64}) == ""
    assert _shipped_bytes({"path": "shipped", "sha256": sha}) == ""
