"""The benchmark's measures inside a training loop: the SB3 callback and the plain function."""

import csv

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.logger import configure

from policies.learned import LearnedPolicy
from slam_gym.training.callbacks import BenchmarkEvalCallback
from slam_gym.training.evaluation import EVAL_METRICS, evaluate_policy, evaluation_env

ENV_KWARGS = {"n_particles": 10, "n_steps": 150}
"""15 s of BB's path with 10 particles: 14 decisions, a tiny episode."""


def test_callback_logs_the_benchmark_metrics_of_the_model_being_trained(tmp_path):
    env = gym.make("slam_gym:SlamGym/HybridSLAM-Light-v1", clutter_level=2, **ENV_KWARGS)
    model = PPO("MlpPolicy", env, n_steps=8, batch_size=8, n_epochs=1, seed=0, device="cpu")
    model.set_logger(configure(str(tmp_path / "sb3"), ["csv"]))
    callback = BenchmarkEvalCallback(
        eval_freq=8, env_id="SlamGym/HybridSLAM-Light-v1", env_kwargs=ENV_KWARGS,
        clutter_levels=(1, 2), seeds=(900_000,), log_path=tmp_path / "eval", verbose=0)
    model.learn(16, callback=callback)
    assert [e["timesteps"] for e in callback.evaluations] == [8, 16]
    for record in callback.evaluations:
        assert record["n_episodes"] == 2
        assert 0.0 <= record["success_rate"] <= 1.0 and record["anees"] > 0.0
        assert record["success_level_1"] in (0.0, 1.0) and record["success_level_2"] in (0.0, 1.0)
        assert record["mean_return"] < 0.0 and record["interface_cpu_s"] >= 0.0
    # on the model's logger under eval/ (SB3's EvalCallback convention), one row per evaluation
    with (tmp_path / "sb3" / "progress.csv").open() as fh:
        logged = [r for r in csv.DictReader(fh) if r.get("eval/success_rate")]
    assert len(logged) == 2
    for row, record in zip(logged, callback.evaluations, strict=True):
        for key in ("success_rate", "anees", "map_completeness", "interface_cpu_s",
                    "mean_return", "n_fusions"):
            assert float(row[f"eval/{key}"]) == pytest.approx(record[key])
    with (tmp_path / "eval" / "evaluations.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 2
    assert (tmp_path / "eval" / "best_model.zip").is_file()
    # the plain function on the saved snapshot, as a policy object, gives the same figures
    snapshot = tmp_path / "eval" / "evals" / "t16" / "model.zip"
    record = evaluate_policy(LearnedPolicy(path=snapshot), clutter_levels=(1, 2),
                             seeds=(900_000,), env_id="SlamGym/HybridSLAM-Light-v1",
                             env_kwargs=ENV_KWARGS)
    for key in EVAL_METRICS:
        if key != "interface_cpu_s":  # measured CPU time
            np.testing.assert_equal(record[key], callback.evaluations[-1][key], err_msg=key)


def test_evaluation_takes_the_training_envs_options_and_checks_them():
    """The evaluation's env is the training env's id with its options (all of them: issue 55),
    every feature observed, at the id's clutter levels unless told."""
    env = evaluation_env("SlamGym/HybridSLAM-Light-v1", {"features": ["ess_ratio"],
                                                         "w_nees": 2.0})
    assert env.get("n_particles") == 100 and env.get("w_nees") == 2.0
    assert env.get("features") is None and env.levels == (0, 1, 2, 3)
    assert evaluation_env("SlamGym/HybridSLAM-Zones-v1").scenario == "brooks-bailey-zones"
    assert evaluation_env("SlamGym/HybridSLAM-Interval-v1").env_id == "SlamGym/HybridSLAM-v1"
    assert evaluation_env(env, clutter_levels=(2,)).levels == (2,)
    with pytest.raises(ValueError, match="w_nees"):
        evaluation_env(None, {"w_nees": -2.0})
    with pytest.raises(ValueError, match="did you mean"):
        evaluation_env("SlamGym/Nope-v1")
    with pytest.raises(ValueError, match="eval_freq"):
        BenchmarkEvalCallback(eval_freq=0)
