"""scripts/results/filter_noise.py: a rule on the same world with other filter draws."""

import json

import pytest
from script_loader import load_script

SCRIPT = "results/filter_noise.py"


def test_draw_0_is_the_benchmarks_run_and_another_draw_changes_only_the_filter():
    import policies
    from slam_gym.evaluation.core import run_policy_object

    script = load_script(SCRIPT)
    options = dict(n_particles=20, w_compute=10.0, compute_clip_s=0.2, n_steps=150)
    first = script.run_one("fixed-10s-optimise", 2, 3, 0, **options)
    episode, env = run_policy_object(policies.make("fixed-10s-optimise"), "brooks-bailey", 2, 3,
                                     **options)
    metrics = episode.metrics()
    assert first["success"] == bool(metrics["success"])
    assert first["map_error_m"] == metrics["map_error_m"]
    assert first["n_fusions"] == metrics["n_fusions"]
    assert first["return"] == pytest.approx(env.episode_return, abs=1e-9)
    other = script.run_one("fixed-10s-optimise", 2, 3, 1, **options)
    assert script.filter_reset_seed(3, 1) != 3
    assert other["map_error_m"] != first["map_error_m"]  # other particle draws, other map
    assert other["n_fusions"] == first["n_fusions"]  # the same path: the rule fuses alike


def test_discordance_counts_each_way_and_uses_the_fronts_interval():
    from slam_gym.evaluation.summary import mean_interval

    script = load_script(SCRIPT)
    outcomes = {0: [True, True, False, True, False], 1: [True, False, True, True, False]}
    rows = [{"clutter_level": 0, "seed": s, "draw": k, "success": ok}
            for k, oks in outcomes.items() for s, ok in enumerate(oks)]
    (summary,) = script.discordance(rows, 1)
    assert (summary["worlds"], summary["success_draw0"], summary["success_draw_k"]) == (5, 3, 3)
    assert (summary["only_draw0"], summary["only_draw_k"]) == (1, 1)
    assert summary["diff_pp"] == 0.0
    assert summary["diff_ci_pp"] == list(mean_interval([0.0, -100.0, 100.0, 0.0, 0.0]))


def test_bad_options_name_the_field(capsys):
    script = load_script(SCRIPT)
    for argv, field in ((["--draws", "0"], "draws"), (["--clutter-levels", "a"], "clutter_levels"),
                        (["--workers", "0"], "workers")):
        with pytest.raises(SystemExit):
            script.parse_args(argv)
        assert f"{field}=" in capsys.readouterr().err


def test_a_rerun_reuses_only_rows_of_the_same_options_and_survives_a_cut_line(tmp_path):
    script = load_script(SCRIPT)
    out = tmp_path / "noise"
    argv = ["--seeds", "1", "--clutter-levels", "2", "--draws", "1", "--n-steps", "100",
            "--workers", "1", "--out", str(out)]
    results = out / "results.jsonl"
    assert script.main([*argv, "--particles", "20"]) == 0
    first = results.read_text()
    assert len(first.splitlines()) == 2
    results.write_text(first + '{"policy": "fixed-10s-opt')  # a write cut short by a kill
    assert script.main([*argv, "--particles", "20"]) == 0  # nothing to run, the cut line dropped
    assert results.read_text().splitlines() == first.splitlines()
    assert script.main([*argv, "--particles", "30"]) == 0  # other options: run again, beside
    rows = [json.loads(line) for line in results.read_text().splitlines()]
    assert sorted(r["n_particles"] for r in rows) == [20, 20, 30, 30]
    summary = json.loads((out / "filter_noise.json").read_text())
    assert [s["worlds"] for s in summary] == [1]  # the 30-particle pair only
