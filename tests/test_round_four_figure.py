"""scripts/results/round_four_figure.py: the figure shows the committed reports' numbers."""

import json
from pathlib import Path

import pytest
from script_loader import load_script

SCRIPT = "results/round_four_figure.py"


def test_arms_are_the_reports_numbers_in_points():
    module = load_script(SCRIPT)
    task = "SlamGym/HybridSLAM-ZonesStarved-v1"
    rows = module.arms(task)
    labels = [row["label"] for row in rows]
    assert labels == ["DAgger (Learner 1)", "PPO (Learner 2)", "fixed-10s-optimise",
                      "lookahead-full", "lookahead (fast)", "bound (privileged)"]
    report = json.loads((module.RESULTS / "gap-starved-rl" / "headroom.json").read_text())
    mean, lo, hi = report["policies"]["learned"]["success_diff"]
    ppo = rows[1]
    assert ppo["diff_pp"] == pytest.approx(100 * mean)
    assert ppo["ci_pp"] == pytest.approx((100 * lo, 100 * hi))
    gap = report["gap_closed"]["learned"]["lookahead-full"]
    assert ppo["gap_closed"] == pytest.approx(gap["point"]["success"])
    # every learner's interval holds its point; the references carry no gap
    for row in rows:
        assert row["ci_pp"][0] <= row["diff_pp"] <= row["ci_pp"][1]
        assert (row["gap_closed"] is None) == (not row["learner"])


def test_an_unknown_task_or_a_missing_report_names_the_field(tmp_path: Path):
    module = load_script(SCRIPT)
    with pytest.raises(ValueError, match="task="):
        module.arms("SlamGym/HybridSLAM-v1")
    with pytest.raises(ValueError, match="report="):
        module.arms("SlamGym/HybridSLAM-Zones-v1", results=tmp_path)


def test_the_figure_is_written(tmp_path: Path):
    module = load_script(SCRIPT)
    out = module.draw(tmp_path / "figure.png")
    assert out.is_file() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
