"""``slam-gym reproduce mrclam`` / ``victoria-park`` (slam_gym.commands.reproduce_real).

Uses MRCLAM Dataset 7 and Victoria Park from tests/slam_gym/realdata.py (excerpts, or the whole
recordings in ``$SLAM_GYM_DATA``) beside the
repository (see its README); every run is cut to a short prefix.
"""

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
from realdata import MRCLAM_DIR, VP_DIR, needs_full_data
from scipy.spatial import cKDTree

from slam_gym.commands import real_tables
from slam_gym.commands import reproduce_real as rr
from slam_gym.datasets import load_mrclam
from slam_gym.evaluation import RESULT_KEYS, Job, read_results, validate_result
from slam_gym.evaluation import real_data as rd
from slam_gym.evaluation.results import check_row

FINITE_KEYS = ("map_error_m", "pose_rmse_m", "anees", "nees_in_band_fraction",
               "final_pose_error_m", "mean_pose_error_m", "filter_time_s")


def run_command(*argv):
    parser = argparse.ArgumentParser()
    targets = parser.add_subparsers(dest="target", required=True)
    rr.add_parser(targets)
    args = parser.parse_args([str(a) for a in argv])
    return args.run(args)


def mrclam_job(name, kind="system", robot=1, **options):
    opts = {"data": str(MRCLAM_DIR), "max_steps": 200, "n_particles": 20} | options
    return Job(kind, name, f"mrclam:robot{robot}", None, 0, opts)


@pytest.mark.parametrize("name, known", [("hybrid", False), ("ekf-slam", False),
                                         ("fastslam", True)])
def test_mrclam_run_function_returns_required_finite_keys(name, known):
    # robot 5 sees several landmarks in its first 20 s (robot 1 maps none there from the excerpt)
    row = validate_result(rd.run_real_job(mrclam_job(name, robot=5, known_association=known)))
    assert set(RESULT_KEYS) <= set(row)
    for key in FINITE_KEYS:
        assert isinstance(row[key], float) and math.isfinite(row[key]), key
    assert row["iterations"] == row["n_steps"] == 200
    assert row["robot"] == 5 and row["association"] == ("known" if known else "unknown")
    assert row["n_fusions"] == (2 if name == "hybrid" else 0)  # every 10 s over 20 s
    stream = load_mrclam(MRCLAM_DIR, 5, max_steps=200)
    assert row["alpha"] == stream.clutter.alpha and row["beta"] == stream.clutter.beta
    # the RMSE is at least the mean error and the figure path has one point per second
    assert row["pose_rmse_m"] >= row["mean_pose_error_m"] - 1e-12
    assert len(row["figure"]["est_path_xy"]) == len(row["figure"]["true_path_xy"]) == 20
    n_found = row["n_matched_landmarks"] + row["n_missed"]
    assert row["n_features"] >= row["n_matched_landmarks"] and n_found <= 15


def test_mrclam_noise_scale_reaches_the_filters():
    row = rd.run_real_job(mrclam_job("ekf-slam", noise_scale=3.0, max_steps=50))
    stream = load_mrclam(MRCLAM_DIR, 1, max_steps=50)
    assert row["range_std_m"] == pytest.approx(3.0 * stream.sensor.range_std_m)
    assert row["bearing_std_rad"] == pytest.approx(3.0 * stream.sensor.bearing_std_rad)


def test_policy_job_drives_hybrid_in_the_mrclam_env():
    row = validate_result(rd.run_real_job(mrclam_job("fixed-10s", kind="policy",
                                                     max_steps=250)))
    assert row["driven_system"] == "hybrid" and row["iterations"] == 250
    assert row["n_fusions"] == 2  # fixed 10 s rule within 25 s
    assert math.isfinite(row["pose_rmse_m"]) and math.isfinite(row["anees"])
    # the interface's CPU and the return, as the benchmark's policy rows carry them
    assert row["fusion_cpu_s"] > 0 and row["optimise_cpu_s"] == 0  # fixed-10s never optimises
    assert row["total_cpu_s"] >= row["filter_cpu_s"] + row["fusion_cpu_s"]
    assert math.isfinite(row["return"]) and row["compute_term_s"] > 0
    assert row["w_compute"] > 0


def test_known_association_only_where_the_system_has_it():
    stream = load_mrclam(MRCLAM_DIR, 1, max_steps=5)
    assert rr.supports_known_association("fastslam", stream)
    assert rr.supports_known_association("ekf-slam", stream)
    assert not rr.supports_known_association("hybrid", stream)
    with pytest.raises(ValueError, match="known_association"):
        rd.run_real_job(mrclam_job("ekf-submap", known_association=True, max_steps=20))
    row = rd.run_real_job(mrclam_job("ekf-slam", known_association=True, max_steps=300))
    assert row["association"] == "known" and row["n_spurious"] == 0


def test_mrclam_corrections_and_calibration_part_reach_the_stream():
    """By default the loader's corrections are on and calibrated on the first 300 s;
    ``corrections=False`` and ``calibration_s`` reach the stream; the row reports the pose
    RMSE over the held-out steps (none here: 20 s) and the map completeness."""
    row = rd.run_real_job(mrclam_job("ekf-slam", max_steps=200))
    stream = load_mrclam(MRCLAM_DIR, 1, max_steps=200)
    assert row["corrections"] is True and row["calibration_s"] == 300.0
    assert row["range_std_m"] == stream.sensor.range_std_m
    assert row["pose_rmse_held_out_m"] is None
    assert row["completeness"] is None or 0.0 <= row["completeness"] <= 1.0
    plain = rd.run_real_job(mrclam_job("ekf-slam", max_steps=200, corrections=False,
                                       calibration_s=10.0))
    ref = load_mrclam(MRCLAM_DIR, 1, max_steps=200, corrections=False, calibration_s=10.0)
    assert plain["range_std_m"] == ref.sensor.range_std_m != row["range_std_m"]
    assert plain["pose_rmse_held_out_m"] is not None and plain["pose_rmse_held_out_m"] > 0.0


def test_mrclam_calibration_and_fastslam_options_reach_stream_and_filters(monkeypatch):
    row = rd.run_real_job(mrclam_job("ekf-slam", noise_window_s=30.0, max_steps=50))
    stream = load_mrclam(MRCLAM_DIR, 1, max_steps=50, noise_window_s=30.0)
    assert row["range_std_m"] == stream.sensor.range_std_m
    assert row["bearing_std_rad"] == stream.sensor.bearing_std_rad
    assert row["noise_window_s"] == 30.0 and row["landmark_density_per_m2"] is None
    # the FastSLAM options go to FASTSLAM and to HYBRID's front-end, not to the EKF filters
    fs = rd.fastslam_options(1e-4, 40.0)
    assert fs == {"new_landmark_density_per_m2": 1e-4, "gate_chi2": 40.0}
    assert rd._system_options("hybrid", fs) == {"front_new_landmark_density_per_m2": 1e-4,
                                                "front_gate_chi2": 40.0}
    assert rd._system_options("ekf-slam", fs) == {} == rd._system_options("ekf-submap", fs)
    built = {}
    from slam_gym import systems

    real = systems.make_system

    def spy(name, stream, rng, **kwargs):
        system = real(name, stream, rng, **kwargs)
        built[name] = system
        return system

    monkeypatch.setattr(systems, "make_system", spy)
    for name in ("fastslam", "hybrid"):
        rd.run_real_job(mrclam_job(name, landmark_density_per_m2=1e-4, gate_chi2=40.0,
                                   max_steps=20))
    f = built["fastslam"].estimator
    h = built["hybrid"].estimator.front_end
    assert f.new_landmark_density == h.new_landmark_density == 1e-4
    assert f.gate_chi2 == h.gate_chi2 == 40.0


def test_learned_without_a_model_is_skipped_with_the_reason(tmp_path):
    usable, skipped = rr.available_policies(
        ["fixed-10s", "learned"], model_path=str(tmp_path / "none.zip"))
    assert usable == ["fixed-10s"] and "none.zip" in skipped["learned"]


def test_mrclam_command_end_to_end_and_resume(tmp_path, capsys):
    out = tmp_path / "mrclam"
    argv = ["mrclam", "--data", MRCLAM_DIR, "--robots", "1", "--max-steps", 120,
            "--systems", "ekf-slam,fastslam", "--policies", "fixed-10s,learned",
            "--model-path", tmp_path / "no-model.zip", "--known-association",
            "--particles", 10, "--workers", 1, "--out", out, "--quiet", "--json"]
    assert run_command(*argv) == 0
    doc = json.loads(capsys.readouterr().out)
    for name in ("results.jsonl", "summary.json", "table.md", "real_table.md"):
        assert (out / name).is_file(), name
    rows = read_results(out / "results.jsonl")
    for row in rows:
        check_row(row)
        assert row["status"] == "ok", row.get("error")
    labels = sorted((r.get("system") or r.get("policy"), r["association"]) for r in rows)
    assert labels == [("ekf-slam", "known"), ("ekf-slam", "unknown"), ("fastslam", "known"),
                      ("fastslam", "unknown"), ("fixed-10s", "unknown")]
    assert "learned" in doc["skipped_policies"] and doc["no_known_association_mode"] == []
    table = (out / "real_table.md").read_text()
    assert "| fastslam | 1 | known |" in table and "| hybrid + fixed-10s | 1 | unknown |" in table
    assert "| ekf-slam | 1 | known |" in table
    assert "Policy learned skipped" in table
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_runs"] == 5 and summary["n_errors"] == 0
    assert any(Path(p).is_file() for p in doc["figures"].values())
    # a rerun into the same directory runs nothing again
    assert run_command(*argv) == 0
    assert len((out / "results.jsonl").read_text().splitlines()) == 5


def test_victoria_park_end_to_end_writes_the_map_png(tmp_path, capsys):
    out = tmp_path / "vp"
    assert run_command("victoria-park", "--data", VP_DIR, "--max-steps", 1200,
                       "--systems", "ekf-submap,hybrid", "--particles", 10,
                       "--executor", "serial", "--out", out, "--quiet", "--json") == 0
    doc = json.loads(capsys.readouterr().out)
    for name in ("results.jsonl", "summary.json", "table.md", "real_table.md",
                 "victoria_park_map_hybrid.png", "victoria_park_map_ekf-submap.png"):
        assert (out / name).is_file(), name
    png = (out / "victoria_park_map_hybrid.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    rows = read_results(out / "results.jsonl")
    assert len(rows) == 2
    for row in rows:
        assert row["status"] == "ok", row.get("error")
        # no truth: NEES, success and map error are undefined
        for key in ("success", "anees", "nees_in_band_fraction", "map_error_m"):
            assert row[key] is None
        assert row["iterations"] == 1200 and row["n_fusions"] == 3  # 30 s, fused every 10 s
        assert 0.0 <= row["gps_rmse_m"] < 20.0 and row["n_gps_fixes_used"] >= 10
        assert row["gps_median_error_m"] <= row["gps_max_error_m"]
        assert 0 <= row["n_trees"] <= row["n_features"]
    assert "path RMSE vs GPS" in (out / "real_table.md").read_text()
    assert set(doc["figures"]) == {"ekf-submap", "hybrid"}


def test_victoria_park_aligned_path_is_in_the_gps_frame_and_matches_the_rmse():
    from slam_gym.datasets import load_victoria_park

    row = rd.run_real_job(Job("system", "ekf-submap", "victoria-park", None, 0,
                              {"data": str(VP_DIR), "max_steps": 1600}))
    assert math.isclose(row["duration_s"], 40.0)
    est = np.asarray(row["figure"]["est_path_xy"])  # aligned, one point per second
    assert est.shape == (40, 2)
    t_est = 0.025 * (1 + 40 * np.arange(40))
    gps = load_victoria_park(VP_DIR, max_steps=10).metadata["gps"]
    gps = gps[(gps[:, 0] >= t_est[0]) & (gps[:, 0] <= t_est[-1])]
    at_gps = np.column_stack([np.interp(gps[:, 0], t_est, est[:, 0]),
                              np.interp(gps[:, 0], t_est, est[:, 1])])
    rmse = float(np.sqrt(np.mean(np.sum((at_gps - gps[:, 1:3]) ** 2, axis=1))))
    # the 1 Hz path resampled at the GPS times reproduces the reported error (the car moves
    # less than ~4 m per second, the interpolation error is a small part of it)
    assert rmse == pytest.approx(row["gps_rmse_m"], abs=0.5)
    assert row["final_pose_error_m"] <= row["gps_max_error_m"] + 1e-12


@pytest.mark.parametrize(
    "argv, field",
    [
        (["mrclam", "--data", MRCLAM_DIR, "--robots", "7"], "robot"),
        (["mrclam", "--data", MRCLAM_DIR, "--systems", "ekf,slam"], "--systems"),
        (["mrclam", "--data", "/no/such/dir"], "--data"),
        (["mrclam", "--data", MRCLAM_DIR, "--particles", "0"], "--particles"),
        (["mrclam", "--data", MRCLAM_DIR, "--noise-scale", "-1"], "--noise-scale"),
        (["mrclam", "--data", MRCLAM_DIR, "--noise-window", "0"], "--noise-window"),
        (["mrclam", "--data", MRCLAM_DIR, "--landmark-density", "-1"], "--landmark-density"),
        (["mrclam", "--data", MRCLAM_DIR, "--gate-chi2", "nan"], "--gate-chi2"),
        (["victoria-park", "--data", VP_DIR, "--max-steps", "0"], "--max-steps"),
        (["victoria-park", "--data", VP_DIR, "--systems", "esdf"], "--systems"),
    ],
)
def test_bad_arguments_raise_value_error_naming_the_field(tmp_path, argv, field):
    with pytest.raises(ValueError, match=field):
        run_command(*argv, "--out", tmp_path, "--quiet")


@needs_full_data
def test_victoria_park_hybrid_maps_each_tree_once_on_a_stream_that_drifted_before():
    """Issue 16 item 4 on the whole recording, HYBRID's random stream 1 (before the lineage term:
    path RMSE 21.5 m, 494 trees): the path within 20 % of EKF sub-mapping's (5.62 m); no more
    trees than EKF sub-mapping (280, 61 of them in pairs closer than 1 m), fewer than 20 such
    pairs (EKF-SLAM: 203 trees, none), and at least 90 % of EKF-SLAM's count once a tree of each
    pair is discounted. Measured 5.37 m, 206 trees, 8 pairs (with the front-end's old 0.999
    existence clip: 5.34 m, 198, 28; lineage term alone: 5.23 m, 241, 79) (docs/RESULTS.md,
    Victoria Park)."""
    row = rd.run_real_job(Job("system", "hybrid", "victoria-park", None, 1, {"data": str(VP_DIR)}))
    assert row["iterations"] == 61944
    assert row["gps_rmse_m"] <= 1.2 * 5.62
    assert row["n_trees"] <= 280
    trees = np.asarray(row["figure"]["trees_xy"], dtype=float)
    assert len(trees) == row["n_trees"]
    pairs = len(cKDTree(trees).query_pairs(1.0))
    assert pairs < 20
    assert row["n_trees"] - pairs >= 0.9 * 203


def test_mrclam_paired_table_pairs_each_policy_with_fixed_10s_optimise():
    def row(policy, robot, seed, map_error, cpu):
        return {"status": "ok", "driven_system": "hybrid", "policy": policy,
                "scenario": f"mrclam:robot{robot}", "clutter_level": None, "seed": seed,
                "success": True, "map_error_m": map_error, "pose_rmse_m": map_error / 2,
                "fusion_cpu_s": cpu, "optimise_cpu_s": cpu, "n_fusions": 80,
                "n_optimisations": 10}
    ref = [row("fixed-10s-optimise", r, s, 1.0, 0.5) for r in (1, 2) for s in (0, 1)]
    rule = [row("fixed-10s", r, s, 1.0 + 0.1 * r, 0.25) for r in (1, 2) for s in (0, 1)]
    text = real_tables.mrclam_paired_table(ref + rule)
    line = next(ln for ln in text.splitlines() if ln.startswith("| fixed-10s |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1] == "4" and cells[3].startswith("+0.15")  # mean of +0.1, +0.1, +0.2, +0.2
    assert cells[7] == "0.50"  # interface CPU ratio
    assert real_tables.mrclam_paired_table(rule) is None  # no reference, no pairing
