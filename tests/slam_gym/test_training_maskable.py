"""``slam-gym train --algo maskable-ppo`` (issue 29 item 2): sb3-contrib's MaskablePPO on the
Discrete(4) actions with the exact mask, its start at the configured action probabilities, and a
saved model that ``LearnedPolicy`` loads and runs with the mask applied at every decision."""

import json

import gymnasium as gym
import numpy as np
import pytest
from untrained import train_tiny, untrained_model

from slam_gym.envs.hybrid_slam import FEATURE_NAMES
from slam_gym.training.hyperparams import load_hyperparams
from slam_gym.training.run import TrainingSetup


def _untrained_model(tmp_path, fuse, optimise):
    return untrained_model(tmp_path, "maskable-ppo", fuse, optimise)


def test_packaged_maskable_ppo_hyperparams_are_ppos():
    for env_id in ("SlamGym/HybridSLAM-v1", "SlamGym/HybridSLAM-Light-v1"):
        masked = load_hyperparams("maskable-ppo", env_id)
        assert masked == load_hyperparams("ppo", env_id)  # they compare on the mask alone
    setup = TrainingSetup("maskable-ppo", "SlamGym/HybridSLAM-v1", 0, masked)
    assert setup.discrete and setup.samples


def test_the_untrained_maskable_policy_starts_at_the_joint_action_probabilities(tmp_path):
    model, _ = _untrained_model(tmp_path, 0.1, 0.03)
    obs = np.random.default_rng(1).uniform(0, 5, (64, len(FEATURE_NAMES))).astype(np.float32)
    dist = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0])
    probs = dist.distribution.probs.detach().numpy()
    want = [0.9 * 0.97, 0.9 * 0.03, 0.1 * 0.97, 0.1 * 0.03]
    np.testing.assert_allclose(probs, np.broadcast_to(want, probs.shape), atol=0.01)


@pytest.mark.parametrize("deterministic", [True, False])
def test_learned_policy_applies_the_mask_at_every_decision(tmp_path, deterministic):
    """An untrained model that mostly wants to optimise alone (chances: fuse 0.1, optimise 0.8,
    so the mode is "optimise only") asked at every decision of an episode in which the env fuses
    every 4th decision (so the optimisation is real after each fusion): it never asks for the
    no-op the mask excludes, and (deterministic) asks for the optimisation whenever it is real."""
    import policies

    _, path = _untrained_model(tmp_path, 0.1, 0.8)
    policy = policies.make("learned", path=str(path), deterministic=deterministic)
    assert policy.algo == "maskable-ppo" and policy.maskable and policy.discrete
    env = gym.make("slam_gym:SlamGym/HybridSLAM-v1", n_particles=10, n_steps=300)
    env.unwrapped.terminate_on_failure = False  # the masks, not the filter, are under test
    obs, info = env.reset(seed=2)
    policy.reset()
    done, counts, t = False, {"masked": 0, "real": 0}, 0
    while not done:
        action = policy.act(obs, info)
        if info["optimise_redundant"]:
            counts["masked"] += 1
            assert tuple(action) != (0, 1)
            if deterministic:
                assert tuple(action) == (0, 0)  # the mode of the rest: 0.18 against 0.08, 0.02
        else:
            counts["real"] += 1
            if deterministic:
                assert tuple(action) == (0, 1)
        if t % 4 == 3:
            action = np.array([1, action[1]])
        obs, _, terminated, truncated, info = env.step(action)
        done, t = terminated or truncated, t + 1
    assert counts["masked"] >= 3 and counts["real"] >= 3
    # unmasked (no optimise_redundant in the info), the mode is the no-op
    if deterministic:
        assert tuple(policy.act(obs, {"features": info["features"]})) == (0, 1)


def test_a_tiny_maskable_ppo_training_saves_a_model_learned_policy_runs(tmp_path, capsys):
    import policies
    from slam_gym.envs.spec import resolve_env
    from slam_gym.evaluation.core import run_policy_object

    tiny = resolve_env(None, {"n_particles": 10, "n_steps": 120})

    config = train_tiny(tmp_path, "maskable-ppo")
    assert json.loads(capsys.readouterr().out)["summary"]["chosen_seed"] == 0
    assert config["algo"] == "maskable-ppo" and config["timesteps"] >= 128
    assert "sb3-contrib" in config["versions"]
    final = config["final_evaluation"]
    assert final["n_episodes"] == 1 and final["sampled_n_episodes"] == 1  # both modes evaluated
    policy = policies.make("learned", path=str(tmp_path / "model.zip"))
    assert policy.algo == "maskable-ppo"
    seen = []
    episode, _ = run_policy_object(policy, tiny, 1, 5,
                                   on_step=lambda action, info: seen.append(tuple(action)))
    assert seen and all(a in {(0, 0), (0, 1), (1, 0), (1, 1)} for a in seen)
    assert episode.done or episode.failure.failed  # ran to the episode's end
