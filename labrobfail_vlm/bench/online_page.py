"""The online bench's tables (online.md beside online.json, and the page's Supervision section): per row and alpha
the alarm's figures, the spills and falls caught before by kind of event, the row chosen on the calibration split
(online_choice.py) and the monitors that cannot fire. Reads a bench JSON only, so a JSON written by an earlier
version of the bench reads the same.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from labrobfail_vlm.bench.online import ROBOT_PAIR
from labrobfail_vlm.bench.online_alarm import ALPHAS, LABELER, bound_check, count_of, exact_ci
from labrobfail_vlm.bench.online_choice import GRAVE


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def _p(x: float | None) -> str:
    return "-" if x is None else f"{x:.2g}"


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:g}"


def online_md(res: dict[str, Any]) -> list[str]:
    """The bench's table: per row and alpha, false alarms on successes against alpha, detection, latency from the
    onset (grid frames and sim seconds: median / 90th percentile), caught at the onset frame and before an
    irreversible event (of how many such failures); brackets: exact 95 % intervals. "bound p": the false alarms' bound
    check (under 0.05: these successes are not exchangeable with the calibration ones)."""
    out = [
        f"Online bench, split {res['split']}{_apart(res)} ({res['trajectories']} trajectories), alarm calibrated on "
        f"{res['calibration_successes']} successes of {res['calibration']}{_guarantee(res)}; CPU per check: "
        f"{_checks(res)}.",
        "",
        "| row | alpha | false alarms (%) | bound p | detection (%) | latency frames (median / p90) "
        "| latency s (median / p90) | caught by onset (%) | before an irreversible event (%) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, per in res["rows"].items():
        for alpha, r in per.items() if name != LABELER else [("-", per)]:
            if "latency_frames_median" not in r:  # the majority class never alarms: one line says it
                if alpha != str(ALPHAS[0]):
                    continue
                alpha = "any"
            grave = _grave(r)
            fa, det = (
                _rate(r, "false_alarm_rate", "false_alarms", "successes"),
                _rate(r, "detection_rate", "detected", "failures"),
            )
            out.append(
                f"| {name} | {alpha} | {fa} | {_p(bound_check(r))} | {det} | "
                f"{_num(r.get('latency_frames_median'))} / {_num(r.get('latency_frames_p90'))} | "
                f"{_num(r.get('latency_s_median'))} / {_num(r.get('latency_s_p90'))} | "
                f"{_pct(r.get('caught_by_onset'))} | {grave} |"
            )
    out += _by_event_md(res["rows"])
    out += choice_md(res)
    left_out = _left_out(res["rows"])
    if left_out:  # a row whose monitor cannot fire reads like a weak one: say which
        out += [
            "",
            "Never fires (too few calibration successes for the level: under 1 / (n + 1) of n, or under 1 - "
            "delta ** (1 / n) training-conditionally, delta the monitor's share of it; threshold +inf): " + left_out,
        ]
    return out


EVENT_ORDER = ("spill", "fall", "breakage", "out_of_reach", "unknown")
BY_EVENT_ALPHA = "0.05"  # the targets are at alpha 0.05


def _by_event_md(rows: dict[str, Any]) -> list[str]:
    """Caught before the event, per kind of event, at alpha 0.05 and for the ceiling: the issue's target speaks of
    spills and falls, and a failed pour's onset can be its spill itself (no alarm at the onset comes before it),
    which the overall share hides under the breakages. [] for a JSON from before 7 Dec (no kinds)."""
    at = {n: (per if n == LABELER else per.get(BY_EVENT_ALPHA, {})) for n, per in rows.items()}
    at = {n: r["caught_before_by_event"] for n, r in at.items() if r.get("caught_before_by_event")}
    if not at:
        return []
    rank = {k: i for i, k in enumerate(EVENT_ORDER)}
    kinds = sorted({k for r in at.values() for k in r}, key=lambda k: (rank.get(k, len(rank)), k))
    grave = [k for k in kinds if k in GRAVE]  # pooled in a last column: the target's own figure, with its interval
    head = [k.replace("_", " ") for k in kinds] + (["spills and falls (%)"] if grave else [])
    cells = {n: [_of(r.get(k)) for k in kinds] + ([_pooled(r, grave)] if grave else []) for n, r in at.items()}
    return [
        "",
        f"Caught before the irreversible event, by kind (caught of such failures), at alpha {BY_EVENT_ALPHA}:",
        "",
        "| row | " + " | ".join(head) + " |",
        "|---|" + "---|" * len(head),
        *(f"| {n} | " + " | ".join(c) + " |" for n, c in cells.items()),
    ]


def _pooled(by_event: dict[str, list[int]], kinds: list[str]) -> str:
    """The share of `kinds`' failures caught before their event, with its exact 95 % interval and of how many."""
    k, n = (sum(by_event.get(e, [0, 0])[i] for e in kinds) for i in (0, 1))
    ci = exact_ci(k, n)
    return "-" if ci is None else f"{_pct(k / n)} [{_pct(ci[0])}, {_pct(ci[1])}] ({k} of {n})"


def _of(tally: list[int] | None) -> str:
    return "-" if not tally else f"{tally[0]} of {tally[1]}"


def _rate(r: dict[str, Any], rate_key: str, count_key: str, of: str) -> str:
    """A rate (false alarms of successes, detection of failures) with its exact 95 % interval, from the row's count
    (online_alarm.count_of); none for a row without n (the majority class, the ceiling)."""
    k = count_of(r, rate_key, count_key, of)
    ci = None if k is None else exact_ci(k, r.get(of))
    return _pct(r.get(rate_key)) + ("" if ci is None else f" [{_pct(ci[0])}, {_pct(ci[1])}]")


def _grave(r: dict[str, Any]) -> str:
    """The irreversible column: the share, its 95 % interval (JSONs from before 7 Dec have none) and of how many."""
    n = r.get("irreversible_failures")
    if n is None:
        return _pct(r.get("caught_before_irreversible"))
    ci = r.get("caught_before_irreversible_ci")
    band = f" [{_pct(ci[0])}, {_pct(ci[1])}]" if ci else ""
    return f"{_pct(r.get('caught_before_irreversible'))}{band} (of {n})"


def _left_out(rows: dict[str, Any]) -> str:
    """The rows and alphas at which a monitor's threshold is +inf (written null), naming which of a pair's two
    monitors (the model first, as the bench pairs them; the per-frame MLP first in the MLPs' pair)."""
    parts = []
    for name, per in rows.items():
        first, second = (
            ("the per-frame MLP", "the every-sample MLP") if name == ROBOT_PAIR else ("the model", "the MLP")
        )
        who = {(0,): f" ({first})", (1,): f" ({second})", (0, 1): " (both)"}
        at = []
        for alpha, r in per.items() if name != LABELER else []:
            ths = r.get("thresholds", [r["threshold"]] if "threshold" in r else [])
            dead = tuple(i for i, th in enumerate(ths) if th is None)
            if dead:
                at.append(alpha + (who.get(dead, "") if len(ths) > 1 else ""))
        if at:
            parts.append(f"{name} at alpha {', '.join(at)}")
    return "; ".join(parts) + "." if parts else ""


def _apart(res: dict[str, Any]) -> str:
    """Where the scored split came from when it is not the calibration's dataset (scored_dataset=)."""
    d = res.get("scored_dataset")
    return "" if d is None else f" of {Path(d).name}, a dataset drawn apart"


def _guarantee(res: dict[str, Any]) -> str:
    """The calibration's promise, named when it is training-conditional (a bench JSON without delta: marginal)."""
    d = res.get("delta")
    return "" if d is None else f" (training-conditional: at most alpha with probability {1 - d:g} over that draw)"


def _checks(res: dict[str, Any]) -> str:
    """The CPU time of one check per monitor that ran (a bench JSON of 2 Dec or before has the model's only)."""
    out = [f"model {res['cpu_s_per_check']} s"] if res.get("cpu_s_per_check") is not None else []
    if res.get("cpu_s_per_dense_check") is not None:
        out.append(f"robot signals per sample {res['cpu_s_per_dense_check']} s")
    return ", ".join(out) or "-"


def choice_md(res: dict[str, Any]) -> list[str]:
    """The page's lines on the choice: the rule, the chosen row and every candidate's cross-fitted figures."""
    ch = res.get("chosen_on_calibration")
    if not ch or ch.get("chosen") is None:
        return []
    out = [
        "",
        f"The row to report, chosen on {res['calibration']} alone ({ch['folds']}-fold cross-fitting, twins in one "
        f"fold; rule: most of the four targets met at alpha {ch['alpha']:g}, then detection, then spills and falls "
        f"caught before): **{ch['chosen']}**. Cross-fitted on {res['calibration']}:",
        "",
        "| candidate | false alarms (%) | detection (%) | latency frames (median) | spills and falls before "
        "| targets met |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in ch["candidates"].items():
        early, of = r["spills_and_falls"]
        out.append(
            f"| {name} | {_pct(r['false_alarm_rate'])} | {_pct(r['detection_rate'])} | "
            f"{_num(r['latency_frames_median'])} | {early} of {of} | {len(r['targets_met'])} of 4 |"
        )
    return out
