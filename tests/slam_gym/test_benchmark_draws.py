"""Draws as a design factor of the benchmark (issue 46 item 2; it replaces
the script filter_noise.py of 66af76f, whose checks are here)."""

import numpy as np
import pytest

import policies
from slam_gym.envs.hybrid_slam import HybridSLAMEnv
from slam_gym.evaluation import benchmark
from slam_gym.evaluation.summary import draw_discordance, markdown_table, summarise

ENV_KWARGS = {"n_particles": 20, "n_steps": 150, "w_compute": 10.0, "compute_clip_s": 0.2}
SMALL = dict(clutter_levels=[2], seeds=[3], env_kwargs=ENV_KWARGS, baselines=[], figures=False,
             executor="serial")


def _play(env, reset_seed, world_seed):
    policy = policies.make("fixed-10s-optimise")
    obs, info = env.reset(seed=reset_seed, options={"world_seed": world_seed})
    while True:
        obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
        if terminated or truncated:
            return env.episode.metrics()


def test_ordered_draws_reproduce_the_rows_filter_noise_recorded(tmp_path):
    """With -v0's ordered streams, draw 0 is the benchmark's run and draw k > 0 the generator
    ``reset(seed=<derived from world and k>)`` gave filter_noise.py (its recorded rows in
    docs/training_runs/train39/filter_noise*/ stay reproducible)."""
    result = benchmark(["fixed-10s-optimise"], draws=2, env="SlamGym/HybridSLAM-v0",
                       out=tmp_path / "b", **SMALL)
    rows = {r["draw"]: r for r in result.rows}
    assert sorted(rows) == [0, 1]
    old_seed = int(np.random.SeedSequence([3, 1, 104729]).generate_state(1)[0])
    config = dict(clutter_level=2, n_particles=20, n_steps=150, w_compute=10.0,
                  compute_clip_s=0.2, random_streams="ordered")
    for draw, reset_seed in ((0, 3), (1, old_seed)):
        metrics = _play(HybridSLAMEnv(**config), reset_seed, 3)
        assert rows[draw]["map_error_m"] == metrics["map_error_m"]
        assert rows[draw]["n_fusions"] == metrics["n_fusions"]
    assert rows[0]["map_error_m"] != rows[1]["map_error_m"]  # other particle draws, other map


def test_synchronised_draws_are_one_group_and_repeat(tmp_path):
    first = benchmark(["fixed-10s", "fixed-10s-optimise"], draws=2, out=tmp_path / "a",
                      **SMALL)
    again = benchmark(["fixed-10s", "fixed-10s-optimise"], draws=2, out=tmp_path / "b",
                      **SMALL)
    assert [r["map_error_m"] for r in first.rows] == [r["map_error_m"] for r in again.rows]
    assert {(r["policy"], r["draw"]) for r in first.rows} == {
        (p, k) for p in ("fixed-10s", "fixed-10s-optimise") for k in (0, 1)}
    groups = first.summary["groups"]
    assert len(groups) == 2  # draws are runs of a group, not groups
    assert all(g["n"] == 2 and g["n_worlds"] == 1 and g["worlds_with_draws"] == 1
               for g in groups)
    by_draw = {r["draw"]: r["map_error_m"] for r in first.rows if r["policy"] == "fixed-10s"}
    assert by_draw[0] != by_draw[1]


def test_discordance_counts_worlds_whose_outcome_changes_with_the_draw():
    outcomes = {0: [True, True, False, True, False], 1: [True, False, True, True, False]}
    rows = [{"policy": "p", "scenario": "s", "clutter_level": 0, "seed": s, "draw": k,
             "success": ok, "status": "ok", "options": {"draw": k}}
            for k, oks in outcomes.items() for s, ok in enumerate(oks)]
    assert draw_discordance(rows) == (5, 2)
    (group,) = summarise(rows)
    assert (group["n"], group["n_worlds"], group["worlds_outcome_varies"]) == (10, 5, 2)
    assert group["success_rate"] == pytest.approx(0.6)
    lo, hi = group["success_ci95"]  # over the 5 worlds' rates, not 10 independent runs
    assert 0.0 <= lo < 0.6 < hi <= 1.0
    assert "2 of 5" in markdown_table([group])
    assert draw_discordance(rows[:5]) == (0, 0)  # one draw a world: nothing to compare


def test_draws_are_validated_before_any_run(tmp_path, caplog):
    with pytest.raises(ValueError, match="^draws="):
        benchmark(["fixed-10s"], draws=0, out=tmp_path / "x", **SMALL)
    with pytest.raises(ValueError, match="^random_streams="):
        benchmark(["fixed-10s"], env_kwargs=ENV_KWARGS | {"random_streams": "both"},
                  out=tmp_path / "y", **{k: v for k, v in SMALL.items() if k != "env_kwargs"})
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    # the streams of a -v0 id overridden: run, and said in one line (never in silence)
    with caplog.at_level("WARNING", logger="slam_gym.envs.spec"):
        rows = benchmark(["fixed-10s"], env="SlamGym/HybridSLAM-v0",
                         env_kwargs=ENV_KWARGS | {"random_streams": "synchronised"},
                         out=tmp_path / "z", **{k: v for k, v in SMALL.items()
                                                if k != "env_kwargs"}).rows
    assert rows[0]["env_kwargs"]["random_streams"] == "synchronised"
    assert [r.getMessage() for r in caplog.records] == [
        "SlamGym/HybridSLAM-v0: random_streams='synchronised' overrides the id's "
        "random_streams='ordered'"]
