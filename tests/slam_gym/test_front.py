"""The learned policy's front (issue 29 item 4): paired comparisons, the goal, the command."""

import json

import numpy as np
import pytest

from slam_gym.evaluation.front import compare, compare_all_runs, goal, return_at_price


def row(level, seed, success, map_error, cpu, ret, term=1.0, w=10.0, n_opt=0):
    return {"status": "ok", "clutter_level": level, "seed": seed, "success": success,
            "map_error_m": map_error, "fusion_cpu_s": cpu, "optimise_cpu_s": 0.0,
            "return": ret, "compute_term_s": term, "w_compute": w, "n_fusions": 40,
            "n_optimisations": n_opt}


def test_compare_pairs_worlds_and_recomputes_returns_at_the_price():
    ref = [row(0, s, True, 2.0, 0.9, -100.0) for s in range(4)]
    mine = [row(0, 0, True, 1.5, 0.3, -90.0), row(0, 1, False, None, 0.3, -300.0),
            row(0, 2, True, 1.0, 0.3, -80.0), row(0, 3, True, 2.5, 0.3, -95.0)]
    c = compare(mine, ref, price=20.0)
    # means of four 0/1 (or 0/-100) values: exact in any summation order, but numpy's order
    # follows the CPU (issue 56), so compared to 1e-12 of their size
    assert c["success_rate"] == pytest.approx(0.75, abs=1e-12)
    assert c["success_diff_pp"] == pytest.approx(-25.0, abs=1e-10)
    assert c["n_map_pairs"] == 3
    assert c["map_error_diff_m"] == pytest.approx(np.mean([-0.5, -1.0, 0.5]))
    assert c["interface_cpu_ratio"] == pytest.approx(1 / 3)
    # at 20 /s each return loses (20 - 10) x 1 s, on both sides: the differences stay
    assert c["mean_return"] == pytest.approx(np.mean([-90, -300, -80, -95]) - 10.0)
    assert c["return_diff"] == pytest.approx(np.mean([10, -200, 20, 5]))
    assert return_at_price(mine[0], 0.0) == pytest.approx(-80.0)
    verdict = goal(c)
    assert verdict["interface_cpu"] and not verdict["success"] and not verdict["reached"]


def test_compare_refuses_unpaired_or_failed_runs():
    ref = [row(0, s, True, 2.0, 0.9, -100.0) for s in range(3)]
    with pytest.raises(ValueError, match="rows"):
        compare(ref[:2], ref, price=1.0)
    bad = [dict(r, status="error") for r in ref]
    with pytest.raises(ValueError, match="reference"):
        compare(ref, bad, price=1.0)


def test_compare_all_runs_pairs_robots_and_seeds_failed_runs_included():
    def real(robot, seed, success, map_error, rmse, cpu):
        return {**row(None, seed, success, map_error, cpu, -1.0),
                "scenario": f"mrclam:robot{robot}", "pose_rmse_m": rmse}
    ref = [real(r, s, True, 1.0, 0.5, 0.6) for r in (1, 2) for s in (0, 1)]
    # the same seed on two robots is two runs, not one world seen twice
    mine = [real(1, 0, False, 3.0, 1.5, 0.2), real(1, 1, True, 1.0, 0.5, 0.2),
            real(2, 0, True, 0.5, 0.25, 0.2), real(2, 1, True, 0.5, 0.25, 0.2)]
    c = compare_all_runs(mine, ref)
    assert c["n_runs"] == 4 and c["success_rate"] == pytest.approx(0.75, abs=1e-12)  # a mean
    assert c["map_error_m_diff"] == pytest.approx(np.mean([2.0, 0.0, -0.5, -0.5]))
    assert c["pose_rmse_m_diff"] == pytest.approx(np.mean([1.0, 0.0, -0.25, -0.25]))
    lo, hi = c["map_error_m_diff_ci"]
    assert lo < c["map_error_m_diff"] < hi
    assert c["interface_cpu_ratio"] == pytest.approx(0.2 / 0.6)
    with pytest.raises(ValueError, match="rows"):
        compare_all_runs(mine[:3], ref)


def test_goal_reached_only_when_all_four_hold():
    base = {"success_diff_ci_pp": [-4.0, 6.0], "map_error_diff_ci_m": [-0.2, 0.1],
            "interface_cpu_ratio": 0.3, "return_diff": 5.0}
    assert goal(base)["reached"]
    for key, value in (("success_diff_ci_pp", [-6.0, 3.0]), ("map_error_diff_ci_m", [0.1, 0.4]),
                       ("interface_cpu_ratio", 0.34), ("return_diff", -1.0)):
        assert not goal({**base, key: value})["reached"]


def test_front_command_runs_rules_once_and_the_model_at_every_price(tmp_path):
    from slam_gym.cli import main
    from slam_gym.training.hyperparams import validate_hyperparams
    from slam_gym.training.run import TrainingSetup, train_run

    params = validate_hyperparams("ppo", {
        "n_timesteps": 64, "n_envs": 1, "compute_price_range": [1, 100],
        "env_kwargs": {"n_particles": 5, "n_steps": 120, "w_compute": 10.0,
                       "compute_clip_s": 0.2},
        "n_steps": 32, "batch_size": 32, "n_epochs": 1})
    setup = TrainingSetup("ppo", "SlamGym/HybridSLAM-v1", 0, params, clutter_levels=(0,),
                          eval_seeds=(7,), eval_every=64, eval_workers=1, checkpoint_every=64)
    train_run(setup, tmp_path / "run", progress=False)
    chosen = tmp_path / "chosen.json"
    chosen.write_text(json.dumps({"chosen": {
        "1": {"rule": "threshold-optimise[time_since_optimise_s>=20]",
              "feature": "time_since_optimise_s", "threshold": 20.0},
        "50": {"rule": "fixed-10s", "feature": None, "threshold": None}}}))
    out = tmp_path / "front"
    twin = tmp_path / "twin"  # the same model under another path: paired with itself
    twin.mkdir()
    for suffix in (".zip", ".json"):
        (twin / f"model{suffix}").write_bytes((tmp_path / "run" / f"model{suffix}").read_bytes())
    code = main(["front", "--model", str(tmp_path / "run" / "model.zip"), "--prices", "1,50",
                 "--compare-model", str(twin / "model.zip"),
                 "--threshold-rules", str(chosen), "--seeds", "2", "--seed-start", "400",
                 "--clutter-levels", "0", "--n-steps", "300", "--particles", "30",
                 "--workers", "1", "--quiet", "--out", str(out)])
    assert code == 0
    doc = json.loads((out / "front.json").read_text())
    assert set(doc["by_price"]) == {"1", "50"}
    at1 = doc["by_price"]["1"]
    assert at1["best_threshold_rule"] == "threshold-optimise[time_since_optimise_s>=20]"
    assert set(at1["policies"]) == {"fixed-10s", "fixed-10s-optimise", "esdf-innovation",
                                    "threshold-optimise[time_since_optimise_s>=20]",
                                    "learned @ 1/s", "compared @ 1/s"}
    against = at1["against_compared"]  # a model against its own copy: every difference is 0
    assert against["n_worlds"] == 2 and against["success_diff_pp"] == 0
    assert against["return_diff"] == 0 and against["interface_cpu_ratio"] > 0
    assert doc["compared_model"] == str((twin / "model.zip").resolve())
    reference = at1["policies"]["fixed-10s-optimise"]
    assert reference["success_diff_pp"] == 0 and reference["interface_cpu_ratio"] == 1
    assert set(at1["goal"]) == {"success", "map_error", "interface_cpu", "return", "reached"}
    rules = [json.loads(x) for x in (out / "rules" / "results.jsonl").read_text().splitlines()]
    assert len(rules) == 4 * 2 and {r["w_compute"] for r in rules} == {10.0}
    for price in ("1", "50"):
        for kind in ("learned", "compared"):
            rows = (out / f"{kind}-{price}" / "results.jsonl").read_text().splitlines()
            assert len(rows) == 2 and {json.loads(x)["w_compute"] for x in rows} == {float(price)}
    assert (out / "front.png").stat().st_size > 0 and "### Price 1 /s" in (
        out / "front.md").read_text()
    assert "learned - compared @ 50/s (paired, 95 %): success +0 pp" in (
        out / "front.md").read_text()
    # the model was trained on this code: its rows match, nothing is marked
    assert doc["model_matches_code"] is True and doc["model_differences"] == []
    assert "†" not in (out / "front.md").read_text()


def test_the_front_figure_takes_a_policy_that_spent_no_interface_cpu(tmp_path, monkeypatch):
    """A short path can end before any fusion: 0 s of interface CPU has no place on a log axis,
    so the axis turns linear instead of the figure failing (it did, on `--n-steps 300`); with
    every point above 0 s it is a log axis again. The axes are read from the saved figure."""
    from matplotlib.figure import Figure

    from slam_gym.evaluation.front import plot_front

    saved = []
    savefig = Figure.savefig

    def keep(fig, *args, **kwargs):
        saved.append(fig)
        return savefig(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)

    # as `slam-gym front --particles 20 --n-steps 300` gave: every run failed before a fusion
    point = {"success_rate": 0.0, "map_error_m": float("nan"), "success_diff_pp": 0.0,
             "success_diff_ci_pp": None, "map_error_diff_m": float("nan"),
             "map_error_diff_ci_m": None}
    points = [{**point, "label": "fixed-10s-optimise", "interface_cpu_s": 0.0},
              {**point, "label": "learned", "interface_cpu_s": 0.0, "learned": True}]
    path = plot_front(points, tmp_path / "front.png", title="no CPU")
    assert path.stat().st_size > 10_000
    assert [ax.get_xscale() for ax in saved[-1].axes] == ["linear", "linear"]
    assert all("linear" in ax.get_xlabel() for ax in saved[-1].axes)
    some_cpu = [{**p, "interface_cpu_s": 0.2, "map_error_m": 1.0} for p in points]
    log_path = plot_front(some_cpu, tmp_path / "log.png", title="some CPU")
    assert log_path.stat().st_size > 10_000
    assert [ax.get_xscale() for ax in saved[-1].axes] == ["log", "log"]
    assert not any("linear" in ax.get_xlabel() for ax in saved[-1].axes)
