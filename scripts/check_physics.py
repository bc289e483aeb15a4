"""Check that a PyBullet physics preset keeps the labels of another on a fixed set of episodes, and write JSON.

Run as:
    python scripts/check_physics.py [a=reference] [b=fast] [pairs=200] [first_pair=0] [seed=0] [variant=seen]
                                    [out=outputs/check_physics.json]

The set: pairs first_pair .. first_pair + pairs - 1 of the generator's seed-`seed` plan in `variant`'s scenes
(seen, or a validation variant's glassware and benches; the sealed ones run for reported rows only), each pair's
nominal run and its first injected draw from the pair's first initial state (no redraws, so both presets run the
same episodes), physics only (labels read the simulator's trace, never an image). Each preset runs in its own
process, the two side by side. Cheaper physics changes every episode a little; what must not change is the data's
make-up, so five distributions are tested, each two-sided with the two runs as samples (within noise: p >= 0.05):
the nominal success rate (Fisher's exact test), the injected runs' outcome (success, explained failure, failure no
detector explains), and among the injected failures the failure type, the category and the severity (chi-square
homogeneity by permutation, fixed seed; a failure no detector explains counts as a type, category and severity
"None" of its own). Beside them, not ruled on: the nominal successes' paired test (exact McNemar on the runs one
preset won and the other lost, which reads a one-sided loss the unpaired test misses), the paired agreement
(episodes whose label is the same) and every changed episode, for a person to look at.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from labrobfail_vlm.config import ConfigError, cli_main, load_config, require_ints
from labrobfail_vlm.io import write_report

DEFAULTS = """
a: reference                       # the preset the labels are kept from (sim_backends/pybullet/backend.py PHYSICS)
b: fast                            # the candidate
pairs: 200                         # pairs of the plan: 2 x pairs episodes per preset
first_pair: 0                      # the set's first pair (a later candidate is judged on a set no choice has seen)
seed: 0                            # the generator's seed whose pair plan is run
variant: seen                      # seen | val_object | val_scene | val_both
out: outputs/check_physics.json
"""
ALPHA = 0.05
RESAMPLES = 9999


def run_preset(args: tuple[str, range, int, str, int]) -> dict[str, Any]:
    """The labels of the fixed set under one preset (in a worker process), with its physics-only speed."""
    from tqdm import tqdm

    from sim_backends.failure_generator import run_injected, run_nominal
    from sim_backends.generate import pair_seed, scenario_order
    from sim_backends.registry import backend_spec, make_backend

    preset, pairs, seed, variant, position = args
    src = make_backend("pybullet", cameras=[], physics=preset)
    order = scenario_order(src.scenarios(), seed, pairs.stop, backend_spec("pybullet").cls.scenario_repeats())
    rows, t = [], time.perf_counter()
    for j in tqdm(pairs, desc=preset, position=position, leave=False):
        s = pair_seed(seed, j, 0, variant)
        for role, ep in (
            ("nominal", run_nominal(src, order[j], s, variant, then_draw=0)),  # as the generator runs a pair
            ("injected", run_injected(src, order[j], s, variant)),
        ):
            lab = ep.labels
            outcome = "success" if lab.success else ("explained" if lab.explained else "unexplained")
            rows.append(
                {
                    "pair": j,
                    "scenario": order[j],
                    "role": role,
                    "outcome": outcome,
                    "failure_type": lab.failure_type,
                    "category": lab.category,
                    "severity": lab.severity,
                }
            )
    dt = time.perf_counter() - t
    src.close()
    return {"rows": rows, "episodes_per_hour_per_core": round(3600.0 * 2 * len(pairs) / dt, 1)}


def homogeneity(a: list[Any], b: list[Any]) -> dict[str, Any]:
    """Counts of each value in two samples and the p-value of 'same distribution' (chi-square by permutation)."""
    from scipy.stats import PermutationMethod, chi2_contingency

    values = sorted({*a, *b}, key=str)
    ca, cb = Counter(a), Counter(b)
    table = np.array([[ca[v] for v in values], [cb[v] for v in values]])
    if len(values) < 2 or min(len(a), len(b)) == 0:
        p = 1.0  # one value only, or a side with none (how many each side has is the outcome test's question)
    else:
        method = PermutationMethod(n_resamples=RESAMPLES, rng=np.random.default_rng(0))
        p = float(chi2_contingency(table, correction=False, method=method).pvalue)
    return {"values": [str(v) for v in values], "a": table[0].tolist(), "b": table[1].tolist(), "p": p}


def compare(ra: list[dict[str, Any]], rb: list[dict[str, Any]]) -> dict[str, Any]:
    """The five tests of the module's docstring, the paired agreement and the changed episodes."""
    from scipy.stats import fisher_exact

    from sim_backends.supervision.paired import mcnemar_exact

    if [(r["pair"], r["role"]) for r in ra] != [(r["pair"], r["role"]) for r in rb]:
        raise ValueError("the two runs do not hold the same episodes in the same order")

    def of(rows, role, key, failed=False):
        return [r[key] for r in rows if r["role"] == role and (not failed or r["outcome"] != "success")]

    na, nb = of(ra, "nominal", "outcome"), of(rb, "nominal", "outcome")
    sa, sb = na.count("success"), nb.count("success")
    fisher = fisher_exact([[sa, len(na) - sa], [sb, len(nb) - sb]]).pvalue
    lost = sum(x == "success" != y for x, y in zip(na, nb))  # a nominal run a succeeds in and b fails
    won = sum(y == "success" != x for x, y in zip(na, nb))
    paired = mcnemar_exact(lost, won)
    tests = {
        "nominal_success": {"a": [sa, len(na)], "b": [sb, len(nb)], "p": float(fisher)},
        "injected_outcome": homogeneity(of(ra, "injected", "outcome"), of(rb, "injected", "outcome")),
        **{
            f"injected_{key}": homogeneity(of(ra, "injected", key, True), of(rb, "injected", key, True))
            for key in ("failure_type", "category", "severity")
        },
    }
    label = lambda r: (r["outcome"], r["failure_type"], r["category"], r["severity"])  # noqa: E731
    changed = [
        {"pair": x["pair"], "scenario": x["scenario"], "role": x["role"], "a": list(label(x)), "b": list(label(y))}
        for x, y in zip(ra, rb)
        if label(x) != label(y)
    ]
    keeps = all(t["p"] >= ALPHA for t in tests.values())  # the unrounded p decides
    for t in tests.values():
        t["p"] = round(t["p"], 4)
    return {
        "tests": tests,
        "keeps_labels": keeps,
        "nominal_success_paired": {"lost": lost, "won": won, "p": round(paired, 4), "ruled_on": False},
        "paired_agreement": round(1.0 - len(changed) / len(ra), 4),
        "changed": changed,
    }


def main(argv: list[str]) -> int:
    cfg = load_config(DEFAULTS, argv)
    require_ints(cfg, ("pairs",), 1)
    require_ints(cfg, ("seed", "first_pair"), 0)
    from sim_backends.pybullet.backend import physics_preset

    presets = {}
    for key in ("a", "b"):
        try:
            presets[str(cfg[key])] = asdict(physics_preset(cfg[key]))
        except ValueError as e:
            raise ConfigError(f"{key}: {e}") from None
    from labrobfail_vlm.taxonomy import SCENE_VARIANTS, SEALED_SPLITS

    allowed = [v for v in SCENE_VARIANTS if v not in SEALED_SPLITS]
    if cfg.variant not in allowed:
        raise ConfigError(f"variant: expected one of {', '.join(allowed)} (sealed ones run for reported rows only)")
    if cfg.a == cfg.b:
        raise ConfigError(f"b: the same preset as a ({cfg.a!r}); name two")
    pairs = range(int(cfg.first_pair), int(cfg.first_pair) + int(cfg.pairs))
    jobs = [(str(cfg[k]), pairs, int(cfg.seed), str(cfg.variant), i) for i, k in enumerate(("a", "b"))]
    with mp.get_context("spawn").Pool(2) as pool:
        res_a, res_b = pool.map(run_preset, jobs)
    report = {
        "a": str(cfg.a),
        "b": str(cfg.b),
        "presets": presets,  # what each preset meant when this ran
        "episodes": 2 * len(pairs),
        "set": f"pairs {pairs.start}-{pairs.stop - 1} of the seed-{cfg.seed} plan, {cfg.variant}: nominal + first draw",
        "physics_only_episodes_per_hour_per_core": {
            str(cfg.a): res_a["episodes_per_hour_per_core"],
            str(cfg.b): res_b["episodes_per_hour_per_core"],
        },
        "alpha": ALPHA,
        **compare(res_a["rows"], res_b["rows"]),
    }
    return write_report(Path(str(cfg.out)), report)


if __name__ == "__main__":
    cli_main(main, __doc__)
