"""The recovery table as docs/RESULTS.md prints it, from `labrobfail-supervise`'s results.json files: success out
of the trials per task and policy, without a supervisor and with it, and the paired statistics of each cell.

A later run that re-measures some cells (a fresh machine's rerun of the ACT cells, say) replaces those rows of the
page and keeps the page's other rows, each named with the setting it ran under: `recovery_md(..., page=...)`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable

from sim_backends.supervision.paired import paired_md

RECOVERY_TARGET = 4  # points of success rate that supervision must add per task and policy (the tower issue)
HEADER = (
    f"| task | policy | none | +VLM | diff (points) | >= +{RECOVERY_TARGET} | 95 % CI (paired) | McNemar p "
    "| successes broken | episodes with an intervention | stopped early |"
)
LEAD = "Recovery: the same initial states and injections with and without the supervisor; "
# make recovery-monitor's table: the VLM supervisor with a saved robot-signal monitor deciding while the policy runs
MONITOR_LEAD = "Recovery with the robot-signal monitor, the same initial states and injections with and without it; "
# make recovery-act-alarm's table: beside an ACT, the model's alarm calibrated on that ACT's own successes
ALARM_LEAD = (
    "Recovery with an alarm calibrated on the policy's own successes, the same initial states and injections with "
    "and without it; "
)
LEADS = (LEAD, MONITOR_LEAD, ALARM_LEAD)  # the page's recovery tables, in its order
TASK_ORDER = ("pick", "place", "pour")
CARRIED = " (rows carried from the page, not re-run)"


def recovery_files(run: Path, lead: str = LEAD) -> list[Path]:
    """`make recovery`'s results.json files of a run: the scripted policy's, then each ACT task's; with
    MONITOR_LEAD, `make recovery-monitor`'s; with ALARM_LEAD, each task's of `make recovery-act-alarm`."""
    rec = run / "recovery"
    if lead == MONITOR_LEAD:
        return [f for f in (rec / "monitor" / "results.json",) if f.is_file()]
    if lead == ALARM_LEAD:  # the tasks' reported cells only (a development run writes elsewhere)
        return [f for f in (rec / "act_alarm" / t / "results.json" for t in TASK_ORDER) if f.is_file()]
    return [
        f for f in (rec / "scripted" / "results.json", *sorted((rec / "act").glob("*/results.json"))) if f.is_file()
    ]


def setting(cfg: dict[str, Any]) -> str:
    """How a results.json's cells ran: trials, variant, supervisor and model, when it was asked, budget."""
    sup, loop = cfg["supervisor"], cfg["loop"]
    given = cfg.get(sup) or {}  # the supervisor's own settings (none for supervisor=none)
    asked = {0: "at every keyframe", -1: "only when the policy stops"}.get(
        loop["query_every"], f"every {loop['query_every']} policy steps"
    )
    more = " and once more when the policy stops" if loop["final_query"] and loop["query_every"] >= 0 else ""
    alarm = given.get("alarm")
    if alarm:  # sim_backends/supervision/vlm.py: the model intervenes only above the threshold its bench calibrated
        more += f", intervening only above the threshold `{alarm}` calibrated at alpha {given.get('alpha')}"
    monitor = given.get("monitor")
    if monitor and loop["query_every"] >= 0:  # sim_backends/supervision/vlm.py: the monitor decides, the model says
        asked = f"when the robot-signal monitor `{monitor}` (alpha {given.get('alpha')}), read {asked}, first sounds"
        more = more and " and, in an episode it flagged, once more when the policy stops"
    seeds = f" (seeds {cfg['seed']}-{cfg['seed'] + cfg['trials'] - 1})" if isinstance(cfg.get("seed"), int) else ""
    return (
        f"{cfg['trials']} trials per cell{seeds}, variant {cfg['variant']}, supervisor {sup} "
        f"(`{given.get('model', '')}`) asked {asked}{more}"
        + f", budget {loop['budget']}, a manual correction: {loop['on_manual']}"
    )


def _row(task: str, r: dict[str, Any], sup: str) -> str | None:
    base, got = r.get("none"), r.get(sup)
    if not (base and got):
        return None
    return (
        f"| {task} | {r['policy']} | {base['success']}/{base['trials']} | {got['success']}/{got['trials']} "
        f"| {r['improvement']:+.0f} | {'yes' if r['improvement'] >= RECOVERY_TARGET else 'no'} | "
        f"{paired_md(r.get('paired'))} | {got['episodes_with_intervention']} | {got['stopped']} |"
    )


def _cell(row: str) -> tuple[str, str]:
    """(task, policy) of a table row."""
    cells = [c.strip() for c in row.strip("|").split("|")]
    return cells[0], cells[1]


def _order(cell: tuple[str, str]) -> tuple[int, int, str]:
    """Scripted before ACT, then pick, place, pour: the page's order."""
    task, policy = cell
    return (policy != "scripted", TASK_ORDER.index(task) if task in TASK_ORDER else len(TASK_ORDER), task)


def block(section: list[str], starts: Callable[[str], bool], ends: Callable[[str], bool], skip: int = 0) -> list[str]:
    """A page section's lines from the first that `starts` up to (not including) the first that `ends`, looked for
    from `skip` lines after the start on (or the section's end); [] when no line starts it."""
    at = next((i for i, line in enumerate(section) if starts(line)), None)
    if at is None:
        return []
    end = next((i for i in range(at + skip, len(section)) if ends(section[i])), len(section))
    return section[at:end]


def page_recovery(section: list[str], lead: str = LEAD) -> tuple[str, list[str]]:
    """An existing Supervision section's recovery setting (its line opening with `lead`, less the lead) and the rows
    of the table that follows it; ("", []) when it has no such line."""
    at = next((i for i, line in enumerate(section) if line.startswith(lead)), None)
    if at is None:
        return "", []
    table = block(section[at:], lambda line: line == HEADER, lambda line: not line.startswith("| "), skip=2)
    return section[at].removeprefix(lead).removesuffix("."), table[2:]


def _page_settings(line: str) -> dict[str, str]:
    """The page's setting line as {"policy task": setting}; a line with one setting for every cell gives {}."""
    out: dict[str, str] = {}
    for part in line.split("; "):
        names, sep, rest = part.partition(": ")
        cells = names.split(", ")
        if not sep or not all(re.fullmatch(r"\S+ \S+", c) for c in cells):
            return {}
        out.update(dict.fromkeys(cells, rest))
    return out


def recovery_md(
    results: list[dict[str, Any]], page: tuple[str, list[str]] | None = None, lead: str = LEAD
) -> list[str]:
    """The setting line (opening with `lead`) and the table of these results; `page` (page_recovery's) adds the
    page's rows for cells the results lack, under the setting the page gave them."""
    rows: dict[tuple[str, str], str] = {}
    settings: dict[str, list[str]] = {}  # each supervisor setting and the cells it ran (a task may need its own)
    for res in results:
        cfg = res["config"]
        for task, r in res["tasks"].items():
            row = _row(task, r, cfg["supervisor"])
            if row:
                settings.setdefault(setting(cfg), []).append(f"{r['policy']} {task}")
                rows[task, r["policy"]] = row
    old_line, old_rows = page or ("", [])
    old_settings = _page_settings(old_line)
    for row in old_rows:
        if _cell(row) in rows:
            continue
        name = " ".join(reversed(_cell(row)))
        old = old_settings.get(name, old_line)
        settings.setdefault(old if old.endswith(CARRIED) else old + CARRIED, []).append(name)
        rows[_cell(row)] = row
    if not rows:
        return []
    line = (
        next(iter(settings))
        if len(settings) == 1
        else "; ".join(f"{', '.join(cells)}: {s}" for s, cells in settings.items())
    )
    return [
        lead + line + ".",
        "",
        HEADER,
        "|---|---|---|---|---|---|---|---|---|---|---|",
        *(rows[c] for c in sorted(rows, key=_order)),
    ]
