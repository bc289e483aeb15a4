"""docs/RESULTS.md's supervision section: the recovery table is read from `make recovery`'s results.json files."""

from __future__ import annotations

import json
from pathlib import Path

from scripts.write_results import supervision


def _results(path: Path, policy: str, tasks: dict[str, tuple[int, int]]) -> None:
    """A results.json as scripts/supervise.py writes it: per task, the baseline and the VLM's summaries."""

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
                    "vlm": {"model": "outputs/online/final"},
                    "loop": {"query_every": 0, "final_query": True, "budget": 2, "on_manual": "stop"},
                },
                "tasks": {
                    t: {"policy": policy, "none": summary(a), "vlm": summary(b), "improvement": 4.0 * (b - a)}
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
        "| pick | scripted | 6/25 | 6/25 | +0 | no | 3 | 1 |",
        "| place | scripted | 8/25 | 16/25 | +32 | yes | 3 | 1 |",
        "| pour | act | 3/25 | 2/25 | -4 | no | 3 | 1 |",
    ]
