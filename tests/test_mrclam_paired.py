"""scripts/results/mrclam_paired.py: a learner against a rule on recorded data, paired by robot
and draw, the robot the unit."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from script_loader import load_script

SCRIPT = "results/mrclam_paired.py"
RULE = "threshold-optimise[global_position_std_m>=2]"


def row(policy, robot, draw, map_error, in_band, success=False):
    return {"status": "ok", "policy": policy, "env_kwargs": {"robot": robot}, "draw": draw,
            "success": success, "map_error_m": map_error, "nees_in_band_fraction": in_band,
            "anees": 5.0, "fusion_cpu_s": 0.2, "optimise_cpu_s": 0.1, "n_fusions": 80,
            "n_optimisations": 40}


def write(folder: Path, rows):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_differences_are_paired_by_draw_and_the_interval_is_over_robots(tmp_path):
    module = load_script(SCRIPT)
    rng = np.random.default_rng(4)
    shift = {1: 0.1, 2: -0.3, 3: 0.2}  # the learner's map error minus the rule's, per robot
    folders = []
    for robot, d in shift.items():
        base = rng.uniform(1, 3, size=3)
        rows = [row(RULE, robot, k, base[k], 0.5) for k in range(3)]
        rows += [row("learned", robot, k, base[k] + d, 0.6, success=k == 0) for k in range(3)]
        rows.append({**row("learned", robot, 9, 99.0, 0.0), "status": "error"})  # dropped
        write(tmp_path / f"robot-{robot}", rows)
        folders.append(tmp_path / f"robot-{robot}")
    rep = module.report(folders, RULE, "learned")
    diffs = np.array(list(shift.values()))
    assert [e["robot"] for e in rep["per_robot"]] == [1, 2, 3]
    assert all(e["draws"] == 3 and e["survived_b"] == 1 for e in rep["per_robot"])
    for e in rep["per_robot"]:
        assert e["map_error_m"]["b_minus_a"] == pytest.approx(shift[e["robot"]])
    overall = rep["overall"]["map_error_m"]
    low, high = stats.t.interval(0.95, 2, loc=diffs.mean(), scale=stats.sem(diffs))
    assert overall["b_minus_a"] == pytest.approx(diffs.mean())
    assert overall["ci95"] == pytest.approx([low, high])
    assert rep["overall"]["nees_in_band_fraction"]["b_minus_a"] == pytest.approx(0.1)
    assert "robot" in module.markdown(rep)


def test_a_folder_with_two_robots_is_refused_by_name(tmp_path):
    module = load_script(SCRIPT)
    write(tmp_path / "mixed", [row(RULE, 1, 0, 1.0, 0.5), row("learned", 2, 0, 1.0, 0.5)])
    with pytest.raises(ValueError, match="rows_dir"):
        module.report([tmp_path / "mixed"], RULE, "learned")
