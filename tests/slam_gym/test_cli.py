"""The command line: output contracts of each command on tiny configurations."""

import json
import math

import numpy as np
import pytest

from slam_gym.cli import main
from slam_gym.evaluation import read_results


def run_json(capsys, argv):
    assert main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_simulate_json_keys_and_picture(tmp_path, capsys):
    out = run_json(capsys, ["simulate", "--scenario", "brooks-bailey", "--clutter-level", "2",
                            "--seed", "3", "--out", str(tmp_path)])
    for key in ("path_length_m", "iterations", "n_landmarks", "n_visible", "n_detections",
                "n_false_alarms", "loop_closed"):
        assert key in out
    assert 400 <= out["path_length_m"] <= 470 and out["n_landmarks"] == 35
    assert out["loop_closed"] is True
    # many turns (BB 5.5): far more than the ~10 rad of a square loop, within the turn-rate limit
    assert 15.0 < out["total_turning_rad"] < np.deg2rad(100.0) * out["iterations"] * 0.1
    assert 0.0 < out["fraction_fast_turning"] < 1.0
    # alpha = 0.4, beta = 0.04: detections and false alarms per landmark-in-range event
    assert out["n_detections"] / out["n_visible"] == pytest.approx(0.4, abs=0.03)
    assert out["n_false_alarms"] / out["n_visible"] == pytest.approx(0.04, abs=0.01)
    assert (tmp_path / "world.png").stat().st_size > 10_000


def test_bad_arguments_exit_with_a_message(tmp_path, capsys):
    assert main(["reproduce", "brooks-bailey", "--systems", "magic", "--out", str(tmp_path)]) == 2
    assert "systems" in capsys.readouterr().err


def test_reproduce_brooks_bailey_tiny_and_resumable(tmp_path, capsys):
    argv = ["reproduce", "brooks-bailey", "--systems", "fastslam,ekf", "--clutter-levels", "3",
            "--trials", "2", "--particles", "20", "--no-figures", "--workers", "2",
            "--out", str(tmp_path)]
    doc = run_json(capsys, argv)
    rows = read_results(tmp_path / "results.jsonl")
    assert len(rows) == 4 and {r["system"] for r in rows} == {"fastslam", "ekf-submap"}
    assert all(r["status"] == "ok" for r in rows)
    assert (tmp_path / "summary.json").exists() and (tmp_path / "table.md").exists()
    assert doc["summary"]["n_runs"] == 4
    run_json(capsys, argv)  # a rerun finds every run done
    assert len(read_results(tmp_path / "results.jsonl")) == 4


def test_reproduce_brooks_bailey_table1_both_existence_models_and_extension(tmp_path, capsys):
    """Dead-reckoning row, both readings of BB (11), paired differences over the same worlds, and
    a rerun with more --trials into the same --out runs only the new worlds."""
    argv = ["reproduce", "brooks-bailey", "--systems", "dead-reckoning,ekf,hybrid",
            "--clutter-levels", "1", "--trials", "1", "--particles", "20", "--no-figures",
            "--workers", "1", "--existence-model", "gate,bb", "--out", str(tmp_path)]
    doc = run_json(capsys, argv)
    assert doc["existence_models"] == ["gate", "bb"]
    rows = read_results(tmp_path / "results.jsonl")
    # dead reckoning has no existence model: one run per world, the two filters one per model
    assert len(rows) == 1 + 2 * 2
    models = {(r["system"], (r["options"] or {}).get("existence_model")) for r in rows}
    assert models == {("dead-reckoning", None), ("ekf-submap", "gate"), ("ekf-submap", "bb"),
                      ("hybrid", "gate"), ("hybrid", "bb")}
    table = doc["table1"]
    assert {(r["system"], r["existence_model"]) for r in table["rows"]} == {
        ("dead-reckoning", "-"), ("ekf-submap", "gate"), ("ekf-submap", "bb"),
        ("hybrid", "gate"), ("hybrid", "bb")}
    for row in table["rows"]:
        assert "map_completeness" in row and "anees" in row and row["n"] == 1
    by_model = {p["existence_model"]: p for p in table["paired"]}
    assert set(by_model) == {"gate", "bb"}
    for p in by_model.values():
        assert p["n_worlds"] == 1 and p["success_difference"]["mean"] in (-1.0, 0.0, 1.0)
    text = (tmp_path / "table1.md").read_text()
    assert "Existence model(s): gate, bb" in text and "dead-reckoning" in text
    argv[argv.index("--trials") + 1] = "2"
    run_json(capsys, argv)
    rows = read_results(tmp_path / "results.jsonl")
    assert len(rows) == 2 * 5 and sorted({r["seed"] for r in rows}) == [0, 1]
    assert main(["reproduce", "brooks-bailey", "--existence-model", "literal",
                 "--out", str(tmp_path / "bad")]) == 2
    assert "--existence-model literal is invalid" in capsys.readouterr().err


def test_benchmark_tiny(tmp_path, capsys):
    doc = run_json(capsys, ["benchmark", "--policies", "fixed-10s,always", "--clutter-levels",
                            "0", "--seeds", "1", "--particles", "10", "--no-figures",
                            "--workers", "1", "--executor", "serial", "--out", str(tmp_path)])
    rows = read_results(tmp_path / "results.jsonl")
    policy_rows = [r for r in rows if r.get("policy")]
    assert {r["policy"] for r in policy_rows} == {"fixed-10s", "always"}
    fused = {r["policy"]: r["n_fusions"] for r in policy_rows}
    assert fused["always"] >= fused["fixed-10s"]
    assert doc["summary"]["n_runs"] == 3  # and the dead-reckoning baseline on the same world


def test_benchmark_reports_accuracy_against_compute_with_a_pareto_figure(tmp_path, capsys):
    # the compass scenario (BB Fig. 3): both rules survive there, so every figure has points;
    # its first 2000 steps (200 s) hold every property checked here, at a fraction of the cost
    doc = run_json(capsys, ["benchmark", "--env", "SlamGym/HybridSLAM-Relative-v1", "--policies",
                            "fixed-10s,fixed-10s-optimise", "--scenario", "brooks-bailey-compass",
                            "--clutter-levels", "0", "--seeds", "2", "--particles", "100",
                            "--n-steps", "2000", "--workers", "1", "--executor", "serial",
                            "--out", str(tmp_path)])
    groups = {g.get("policy") or g.get("system"): g for g in doc["summary"]["groups"]}
    assert set(groups) == {"fixed-10s", "fixed-10s-optimise", "dead-reckoning"}
    opt, plain = groups["fixed-10s-optimise"], groups["fixed-10s"]
    assert opt["optimise_cpu_s"] > 0.0 == plain["optimise_cpu_s"]
    assert opt["total_cpu_s"] > opt["fusion_cpu_s"] > 0.0
    for g in (opt, plain):
        lo, hi = g["ci95"]["map_error_m"]
        assert lo <= g["map_error_m"]["mean"] <= hi
        assert "return" in g and g["map_completeness"] > 0.5
    assert groups["dead-reckoning"]["map_completeness"] == 0.0  # succeeds, maps nothing
    assert "map_error_m_succeeded" not in groups["dead-reckoning"]
    rows = read_results(tmp_path / "results.jsonl")
    assert {r["env_kwargs"]["back_end"] for r in rows if r.get("policy")} == {"relative"}
    assert doc["figures"]["pareto"].endswith("pareto.png")
    assert (tmp_path / "pareto.png").stat().st_size > 10_000
    assert (tmp_path / "pareto_interface.png").stat().st_size > 10_000
    assert (tmp_path / "decisions.png").stat().st_size > 10_000
    assert opt["interface_cpu_s"] == pytest.approx(opt["fusion_cpu_s"] + opt["optimise_cpu_s"])
    table = (tmp_path / "table.md").read_text()
    assert "CPU fusion / optimise / total (s)" in table and "completeness" in table


def test_benchmark_rejects_unknown_envs_and_baselines(tmp_path):
    base = ["benchmark", "--policies", "always", "--seeds", "1", "--out", str(tmp_path)]
    assert main([*base, "--env", "SlamGym/Nope-v1"]) == 2
    assert main([*base, "--baselines", "teleport"]) == 2


def test_speed_tiny(tmp_path, capsys):
    out = run_json(capsys, ["speed", "--systems", "hybrid", "--particles", "10,40",
                            "--clutter-levels", "1", "--iterations", "400", "--env-decisions",
                            "5", "--env-particles", "10,20", "--schedule-particles", "10",
                            "--env-schedules", "fixed-10s-optimise,fuse-optimise-every-decision",
                            "--optimise-counts", "2,3", "--optimise-seeds", "0",
                            "--skip-paper-episode", "--skip-first-reset", "--skip-esdf",
                            "--full-path-episodes", "0", "--out", str(tmp_path)])
    rows = out["systems"]
    assert [r["n_particles"] for r in rows] == [10, 40]
    for r in rows:
        assert r["iterations"] == 400 and r["iterations_per_s"] > 0
        assert r["real_time_ratio"] == pytest.approx(r["iterations_per_s"] * 0.1)
    assert [e["n_particles"] for e in out["env_runs"]] == [10, 20]
    assert out["env"] == out["env_runs"][-1] and out["env"]["decisions"] == 5
    assert all(e["resets"] >= 1 and e["decisions_per_s"] > 0 for e in out["env_runs"])
    assert "env_first_reset" not in out
    assert "env_paper_episode" not in out and "env_full_path" not in out
    schedules = out["env_schedules"]
    assert [e["schedule"] for e in schedules] == ["fixed-10s-optimise",
                                                  "fuse-optimise-every-decision"]
    assert all(e["decisions"] == 5 and e["n_particles"] == 10 for e in schedules)
    # fusing every 5 s over 400 iterations: 8 sub-maps, each optimisation warm and then redundant
    assert [r["stored_submaps"] for r in out["optimise"]] == [2, 3]
    assert all(r["median_ms"] > 0 and r["redundant_median_us"] > 0 for r in out["optimise"])
    assert json.loads((tmp_path / "speed.json").read_text())["systems"] == rows


def test_speed_times_the_first_reset_in_a_fresh_process():
    from slam_gym.commands.speed import measure_first_reset

    row = measure_first_reset(0, n_particles=10)
    assert row["n_particles"] == 10
    assert row["first_reset_cpu_s"] > 0 and row["import_cpu_s"] > 0


def test_speed_times_exactly_one_whole_env_episode():
    from slam_gym.commands.speed import measure_env

    e = measure_env(None, 0, n_particles=10, n_steps=95)
    # one episode, not reset: it ended (end of the cut path or a failure); reset() itself runs
    # the first interval, every decision one more (the last one possibly cut short)
    assert 10 < e["iterations"] <= 95 and e["decisions"] == -(-(e["iterations"] - 10) // 10)
    assert e["cpu_time_s"] > 0 and e["n_particles"] == 10


def test_speed_times_a_task_episode_by_thirds_and_records_it():
    from slam_gym.commands.speed import measure_task, record_figures

    t = measure_task("SlamGym/HybridSLAM-LongMission-v1", n_particles=100, n_steps=350)
    assert not t["failed"] and t["decisions"] == 34 and len(t["thirds"]) == 3
    assert t["episode_cpu_s"] > 0
    sub = [p["stored_submaps_at_end"] for p in t["thirds"]]
    assert sub == sorted(sub) and sub[-1] >= 1  # fused every 10 s
    figures = record_figures({"tasks": [t]})
    assert figures["task_hybridslam_longmission_v1_decisions_per_s"]["higher_is_better"]
    with pytest.raises(ValueError, match="did you mean"):
        measure_task("SlamGym/HybridSLAM-LongMision-v1")


def test_speed_full_path_figures_leave_failed_episodes_out():
    from slam_gym.commands.speed import measure_full_path, record_figures
    from slam_gym.commands.speed_record import figure

    row = measure_full_path("fixed-10s-optimise", 1, n_particles=30, n_steps=420)
    assert row["full_path_episodes"] == 1 and row["decisions"] == 41
    assert row["decisions_per_s"] > 0 and row["cpu_time_s"] > 0
    # fused and optimised every 100 iterations: the last optimisation over all 4 sub-maps
    assert row["last_optimisation_submaps"] == 4 and row["last_optimisation_ms"] > 0
    assert row["last_optimisation_variables"] > 3 * 4
    # one particle fails at once: every seed tried is counted as failed, no figure
    none = measure_full_path("fixed-10s", 1, n_particles=1, seeds=(0, 1), clutter_level=3,
                             n_steps=420)
    assert none["full_path_episodes"] == 0 and none["failed_episodes"] == 2
    assert none["decisions_per_s"] is None and none["last_optimisation_ms"] is None
    figures = record_figures({"env_full_path": [row, none]})
    assert figures == {
        "env_full_path_fixed_10s_optimise_decisions_per_s": figure(row["decisions_per_s"],
                                                                   "decisions/s", True),
        "optimise_last_full_path_ms": figure(row["last_optimisation_ms"], "ms", False),
    }


def test_benchmark_where_every_run_fails_still_writes_its_table(tmp_path, capsys):
    doc = run_json(capsys, ["benchmark", "--policies", "never", "--clutter-levels", "3",
                            "--seeds", "1", "--particles", "5", "--baselines", "", "--workers",
                            "1", "--executor", "serial", "--out", str(tmp_path)])
    assert doc["summary"]["groups"][0]["success_rate"] == 0.0
    assert "pareto" not in doc["figures"] and (tmp_path / "table.md").exists()


def _record(**figures):
    return {"date_utc": "2026-11-25T00:00:00Z", "commit": "abc",
            "figures": {k: {"value": v, "unit": u, "higher_is_better": h}
                        for k, (v, u, h) in figures.items()}}


def test_speed_record_comparison_fails_below_half_and_on_a_missing_figure():
    from slam_gym.commands.speed_record import compare

    baseline = _record(rate=(180.0, "decisions/s", True), time=(4.0, "ms", False))
    same = _record(rate=(170.0, "decisions/s", True), time=(4.5, "ms", False))
    rows, ok = compare(same, baseline)
    assert ok and {r[0]: r[-1] for r in rows} == {"rate": "ok", "time": "ok"}
    # a threefold loss (the regression of issue 27) fails, in a rate and in a time
    for slow in (_record(rate=(60.0, "decisions/s", True), time=(4.0, "ms", False)),
                 _record(rate=(180.0, "decisions/s", True), time=(12.0, "ms", False))):
        rows, ok = compare(slow, baseline)
        assert not ok and "SLOWER" in [r[-1] for r in rows]
        ratios = [r[4] for r in rows if r[-1] == "SLOWER"]
        assert ratios == [pytest.approx(1 / 3)]
    rows, ok = compare(_record(rate=(180.0, "decisions/s", True)), baseline)
    assert not ok and ("time", 4.0, None, "ms") == rows[1][:4] and rows[1][-1] == "MISSING"
    rows, ok = compare(_record(rate=(180.0, "decisions/s", True), time=(4.0, "ms", False),
                               extra=(1.0, "x", True)), baseline)
    assert ok and rows[0][0] == "extra" and rows[0][-1] == "new"


def test_speed_record_ratios_are_for_the_machine_when_both_records_carry_its_reference():
    from slam_gym.commands.speed_record import compare, comparison_lines, machine_factor

    baseline = {**_record(rate=(90.0, "decisions/s", True), time=(4.0, "ms", False)),
                "machine_reference_s": 0.030}
    # on a machine three times as fast, a threefold loss measures as the baseline's figures:
    # the raw ratios pass, the ratios for the machine fail
    fast_and_slower = {**_record(rate=(90.0, "decisions/s", True), time=(4.0, "ms", False)),
                       "machine_reference_s": 0.010}
    assert machine_factor(fast_and_slower, baseline) == pytest.approx(1 / 3)
    assert compare({k: v for k, v in fast_and_slower.items() if k != "machine_reference_s"},
                   baseline)[1]
    rows, ok = compare(fast_and_slower, baseline)
    assert not ok and [r[4] for r in rows] == [pytest.approx(1 / 3)] * 2
    # unchanged code on a machine 2.5 times as slow passes, with ratios 1
    slow_machine = {**_record(rate=(36.0, "decisions/s", True), time=(10.0, "ms", False)),
                    "machine_reference_s": 0.075}
    assert not compare({k: v for k, v in slow_machine.items() if k != "machine_reference_s"},
                       baseline)[1]
    rows, ok = compare(slow_machine, baseline)
    assert ok and [r[4] for r in rows] == [pytest.approx(1.0)] * 2
    assert "0.40 times as fast" in "\n".join(comparison_lines(rows, slow_machine, baseline))
    for broken in (None, 0.0, "x"):
        assert math.isnan(machine_factor({**slow_machine, "machine_reference_s": broken},
                                         baseline))


def test_speed_compare_exits_1_against_a_much_faster_baseline(tmp_path, capsys):
    args = ["speed", "--systems", "hybrid", "--particles", "10", "--clutter-levels", "1",
            "--iterations", "40", "--env-decisions", "3", "--env-particles", "",
            "--env-schedules", "fixed-10s", "--optimise-counts", "", "--skip-paper-episode",
            "--skip-first-reset", "--skip-esdf", "--full-path-episodes", "0",
            "--out", str(tmp_path), "--json"]
    assert main(args) == 0
    measured = json.loads(capsys.readouterr().out)
    assert "record" not in measured  # a record only with --quick or --compare
    fast = _record(hybrid_10p_level1_iterations_per_s=(1e9, "iterations/s", True))
    (tmp_path / "fast.json").write_text(json.dumps(fast))
    assert main([*args, "--compare", str(tmp_path / "fast.json")]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["comparison"]["passed"] is False
    record = json.loads((tmp_path / "speed_record.json").read_text())
    assert record["machine_reference_s"] > 0
    assert record["figures"]["hybrid_10p_level1_iterations_per_s"]["value"] > 0
    assert "env_fixed_10s_decisions_per_s" in record["figures"] and record["commit"]
    (tmp_path / "own.json").write_text(json.dumps(record))
    assert main([*args, "--compare", str(tmp_path / "own.json")]) == 0
    capsys.readouterr()
    (tmp_path / "bad.json").write_text("{}")
    assert main([*args, "--compare", str(tmp_path / "bad.json")]) == 2


def test_simulate_json_reports_the_waypoint_jitter_and_the_turning(tmp_path, capsys):
    argv = ["simulate", "--seed", "3", "--out", str(tmp_path)]
    default = run_json(capsys, argv)
    straight = run_json(capsys, argv + ["--path-perturbation-m", "0.5"])
    assert default["path_perturbation_m"] == 5.0 and straight["path_perturbation_m"] == 0.5
    # a less jittered path turns less (the 99 m loop's four corners and the start turn remain)
    assert 6.0 < straight["total_turning_rad"] < default["total_turning_rad"] - 10.0
    assert main(argv + ["--path-perturbation-m", "-1"]) == 2
    assert "--path-perturbation-m -1 is invalid" in capsys.readouterr().err


def test_reproduce_brooks_bailey_runs_the_given_waypoint_jitter(tmp_path, capsys):
    argv = ["reproduce", "brooks-bailey", "--systems", "dead-reckoning", "--clutter-levels", "0",
            "--trials", "1", "--seed-start", "2", "--no-figures", "--workers", "1",
            "--out", str(tmp_path)]
    doc = run_json(capsys, argv + ["--path-perturbation-m", "1.5"])
    assert doc["table1"]["path_perturbation_m"] == 1.5
    rows = read_results(tmp_path / "results.jsonl")
    assert [r["options"] for r in rows] == [{"path_perturbation_m": 1.5}]
    assert (tmp_path / "table1.md").read_text().startswith(
        "World: brooks-bailey, path_perturbation_m=1.5\n")
    # the jitter is part of the job: the scenario's default is another job, run anew
    run_json(capsys, argv)
    rows = read_results(tmp_path / "results.jsonl")
    assert len(rows) == 2 and rows[1]["options"] == {}
    assert rows[0]["iterations"] != rows[1]["iterations"]  # another path


def test_table1_says_whether_bb_is_inside_and_pools_the_paired_differences():
    from slam_gym.commands.reproduce import bb_table, bb_table_markdown

    rows = [{"status": "ok", "system": system, "clutter_level": level, "seed": seed,
             "success": system == "hybrid" or seed == 0, "options": {"existence_model": "gate"},
             "map_error_m": 1.0}
            for seed in range(4) for level in (0, 3) for system in ("hybrid", "ekf-submap")]
    table = bb_table(rows)
    inside = {(r["system"], r["clutter_level"]): r["paper_inside_ci95"] for r in table["rows"]}
    # EKF 1 / 4 (Wilson [5, 70] %): BB's 79 % outside at level 0, its 30 % inside at level 3;
    # HYBRID 4 / 4 ([51, 100] %) holds both of BB's
    assert inside == {("ekf-submap", 0): False, ("ekf-submap", 3): True,
                      ("hybrid", 0): True, ("hybrid", 3): True}
    (pooled,) = table["pooled"]
    # a mean of eight 0/1 differences: to 1e-12, whatever order numpy sums them in
    assert pooled["n_pairs"] == 8
    assert pooled["success_difference"]["mean"] == pytest.approx(0.75, abs=1e-12)
    text = bb_table_markdown(table)
    assert "79 % (outside)" in text and "| gate | 8 | 75 pp" in text
