"""``slam-gym reproduce conte-martinelli`` (slam_gym/commands/reproduce_cm.py)."""

from __future__ import annotations

import argparse
import json
import math
import pickle

import numpy as np
import pytest

from slam_gym.commands import reproduce_cm
from slam_gym.commands.reproduce_cm import (
    CM_KEYS,
    closing_scan_step,
    cm_markdown,
    cm_summary,
    run_cm,
    run_cm_job,
)
from slam_gym.evaluation import RESULT_KEYS, Job, read_results, validate_result
from slam_gym.world import make_stream

#: CM sim 1 on a 25 m square loop (~1000 iterations, closes at ~600)
SHORT_LOOP = dict(path_length_m=100.0, world_size_m=60.0)
NOISE_FREE_ISH = dict(chong_kleeman_k_m=1e-11, range_std_m=1e-5, bearing_std_rad=1e-5)
OWN_KEYS = (
    "esdf_map_error_before_m",
    "esdf_map_error_after_m",
    "hybrid_map_error_before_m",
    "hybrid_map_error_after_m",
    "esdf_time_s",
    "hybrid_filter_time_s",
    "hybrid_optimise_time_s",
    "optimiser_iterations",
    "n_loop_closures",
)


def test_closing_scan_is_a_return_after_a_long_absence():
    stream = make_stream("conte-martinelli-1", seed=0, **SHORT_LOOP)
    step_index = closing_scan_step(stream, gap_scans=10)
    assert step_index is not None
    scans = [s for s in stream if len(s.z)]
    k = next(i for i, s in enumerate(scans) if s.index == step_index)
    seen_before = [set(s.truth.landmark_ids[s.truth.landmark_ids >= 0].tolist()) for s in scans]
    closing = seen_before[k]
    # some landmark of the closing scan was seen before, but not in the last 9 scans
    recent = set().union(*seen_before[k - 9 : k])
    old = set().union(*seen_before[: k - 9])
    assert (closing & old) - recent
    # and no earlier scan was such a return
    for i in range(1, k):
        rec = set().union(*seen_before[max(0, i - 9) : i])
        assert not ((seen_before[i] & set().union(*seen_before[: max(0, i - 9)])) - rec)
    with pytest.raises(ValueError, match="gap_scans"):
        closing_scan_step(stream, gap_scans=0)


def test_run_function_keys_and_hybrid_improves_after_closure_on_noise_free_ish_data():
    row = run_cm("conte-martinelli-1", 0, **SHORT_LOOP, **NOISE_FREE_ISH)
    validate_result(row)
    for key in (*RESULT_KEYS, *OWN_KEYS):
        assert key in row
        if key not in ("failure_iteration",):
            assert isinstance(row[key], (bool, int, float)) and math.isfinite(float(row[key]))
    assert row["loop_closure_step"] is not None and row["n_loop_closures"] > 0
    assert row["hybrid_map_error_after_m"] <= row["hybrid_map_error_before_m"]
    assert row["hybrid_map_error_after_same_m"] <= row["hybrid_map_error_before_m"]
    # tiny noise: both estimates are within millimetres of the truth
    assert row["hybrid_map_error_after_m"] < 5e-3 and row["esdf_map_error_after_m"] < 5e-3
    assert row["optimiser_converged"] and row["optimiser_iterations"] >= 1
    assert row["map_error_m"] == row["hybrid_map_error_after_m"]
    assert row["n_fusions"] == 0 and row["n_optimisations"] == 1


def test_run_function_is_deterministic_and_picklable():
    job = Job("system", reproduce_cm.CM_SYSTEM, "conte-martinelli-1", None, 3,
              {"n_steps": 400, "method": "gauss-newton", "gap_scans": 10})
    pickle.dumps(run_cm_job)
    a, b = run_cm_job(job), run_cm_job(job)
    for key in ("esdf_map_error_after_m", "hybrid_map_error_after_m", "anees"):
        assert a[key] == b[key]
    assert a["loop_closure_step"] is None  # 400 iterations: no return to the start yet
    assert a["hybrid_map_error_before_m"] == pytest.approx(
        run_cm("conte-martinelli-1", 3, n_steps=400)["hybrid_map_error_before_m"]
    )
    with pytest.raises(ValueError, match="method"):
        run_cm("conte-martinelli-1", 0, n_steps=50, method="newton")


def test_cm_summary_and_table_on_hand_made_rows():
    rows = []
    for seed, scale in enumerate((1.0, 2.0, 3.0)):
        row = {"scenario": "conte-martinelli-1", "status": "ok", "seed": seed}
        row.update({k: scale for k in CM_KEYS})
        row.update(optimiser_iterations=10, n_loop_closures=2)
        rows.append(row)
    rows.append({"scenario": "conte-martinelli-1", "status": "error"})
    s = cm_summary(rows)
    assert set(s) == {"1"} and s["1"]["n"] == 3
    e = s["1"]["hybrid_map_error_after_m"]
    assert e["mean"] == pytest.approx(2.0) and e["median"] == 2.0 and e["paper"] == 0.15
    text = cm_markdown(s)
    assert "2.02 -> 1.01" in text and "1.30 -> 0.15" in text and "2.00 / 2.00" in text


def test_command_end_to_end(tmp_path):
    parser = argparse.ArgumentParser()
    targets = parser.add_subparsers(dest="target", required=True)
    reproduce_cm.add_parser(targets)
    out = tmp_path / "cm"
    args = parser.parse_args(
        ["conte-martinelli", "--sims", "1", "--trials", "1", "--n-steps", "700", "--workers",
         "1", "--out", str(out), "--quiet", "--json"]
    )
    assert args.run(args) == 0
    rows = read_results(out)
    assert len(rows) == 1 and rows[0]["status"] == "ok", rows[0].get("error")
    assert rows[0]["system"] == reproduce_cm.CM_SYSTEM
    for name in ("results.jsonl", "summary.json", "table.md", "cm_table.md", "cm_sim1_maps.png"):
        assert (out / name).stat().st_size > 0
    doc = json.loads((out / "summary.json").read_text())
    assert doc["n_ok"] == 1
    assert "| 1 | ESDF | 1 |" in (out / "cm_table.md").read_text()
    from PIL import Image

    with Image.open(out / "cm_sim1_maps.png") as im:
        assert im.size[0] > 500 and im.size[1] > 500
    # a rerun skips the finished run
    assert args.run(args) == 0
    assert len(read_results(out)) == 1
    with pytest.raises(ValueError, match="sims"):
        bad = parser.parse_args(["conte-martinelli", "--sims", "3", "--out", str(out)])
        bad.run(bad)


def test_cm_paper_values_are_the_papers():
    p = reproduce_cm.CM_PAPER
    assert (p[1]["esdf_map_error_before_m"], p[1]["esdf_map_error_after_m"]) == (2.02, 1.01)
    assert (p[1]["hybrid_map_error_before_m"], p[1]["hybrid_map_error_after_m"]) == (1.30, 0.15)
    assert (p[2]["esdf_map_error_before_m"], p[2]["esdf_map_error_after_m"]) == (3.91, 0.58)
    assert (p[2]["hybrid_map_error_before_m"], p[2]["hybrid_map_error_after_m"]) == (3.17, 0.38)
    assert np.isclose(p[1]["hybrid_filter_time_s"] + p[1]["hybrid_optimise_time_s"], 16.20)
    assert np.isclose(p[2]["hybrid_filter_time_s"] + p[2]["hybrid_optimise_time_s"], 46.37)


def test_optimiser_beats_the_esdf_after_closure_on_cm_sim1():
    """CM IV.B's claim on the full sim 1 (first scan at the start pose, calibrated wheel base).

    Over 4 worlds the hybrid's mean map error after the optimisation is well below the ESDF's
    after loop closure, and well below its own error before the closure (the closure's
    information is used); the ESDF, linearised at drifted estimates, is inconsistent.
    """
    rows = [run_cm("conte-martinelli-1", seed) for seed in range(4)]
    mean = {k: np.mean([r[k] for r in rows]) for k in OWN_KEYS[:4]}
    assert mean["hybrid_map_error_after_m"] < 0.5 * mean["esdf_map_error_after_m"]
    assert mean["hybrid_map_error_after_m"] < 0.5 * mean["hybrid_map_error_before_m"]
    assert all(r["loop_closure_step"] is not None and r["optimiser_converged"] for r in rows)
    assert np.median([r["esdf_anees"] for r in rows]) > np.median([r["hybrid_anees"] for r in rows])
