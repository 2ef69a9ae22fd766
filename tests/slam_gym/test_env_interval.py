"""``SlamGym/HybridSLAM-Interval-v1``: one action per fusion (issue 39 item 3)."""

from __future__ import annotations

import pickle
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import policies
import slam_gym  # noqa: F401  (registers the ids)
from slam_gym.envs.hybrid_slam import HybridSLAMEnv
from slam_gym.envs.interval import (
    FUSION_INTERVALS_S,
    RULE_ACTION,
    IntervalActions,
    make_interval_env,
)

ENV_ID = "SlamGym/HybridSLAM-Interval-v1"
SMALL = {"n_particles": 20, "n_steps": 400}


def test_the_rule_as_a_constant_action_plays_the_rules_episode_to_the_bit():
    options = dict(n_particles=60, n_steps=700, clutter_level=1, w_compute=10.0)
    rule = policies.make("fixed-10s-optimise")
    env = HybridSLAMEnv(**options)
    obs, info = env.reset(seed=4, options={"world_seed": 1})
    rewards, done = [], False
    while not done:
        obs, reward, terminated, truncated, info = env.step(rule.act(obs, info))
        rewards.append(reward)
        done = terminated or truncated
    interval = IntervalActions(HybridSLAMEnv(**options))
    i_obs, i_info = interval.reset(seed=4, options={"world_seed": 1})
    i_rewards, covered, done = [], 0, False
    while not done:
        i_obs, reward, terminated, truncated, i_info = interval.step(RULE_ACTION)
        i_rewards.append(reward)
        covered += i_info["env_decisions"]
        done = terminated or truncated
    assert covered == len(rewards)
    assert len(i_rewards) < len(rewards) / 5  # one action per fusion
    assert np.array_equal(i_obs, obs)
    assert interval.unwrapped.episode_return == env.episode_return
    assert sum(i_rewards) == pytest.approx(sum(rewards), rel=1e-12)
    assert i_info["n_fusions"] == info["n_fusions"] > 3
    assert i_info["n_optimisations"] == info["n_optimisations"]


def test_an_action_fuses_at_its_interval_and_optimises_only_if_asked():
    env = make_interval_env(**SMALL, clutter_level=0)
    _, info = env.reset(seed=2)
    for index, optimise in ((0, 0), (2, 1), (1, 1)):
        before = (info["n_fusions"], info["n_optimisations"])
        _, _, terminated, truncated, info = env.step(np.array([index, optimise]))
        if terminated or truncated:
            break
        expected = FUSION_INTERVALS_S[index]
        # a local map is one decision (1 s) old at the first decision after a fusion (or the
        # reset), and the fusion happens at the decision where it is ``expected`` old
        assert info["env_decisions"] == int(expected)
        assert info["fusion_interval_s"] == expected
        assert info["n_fusions"] == before[0] + 1
        assert info["n_optimisations"] == before[1] + optimise


def test_registered_id_passes_the_checkers_and_repeats_per_seed():
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # the checkers run on the wrapper itself (its action space is the one to check); the
        # one warning allowed is Gymnasium's note that the env it checks is a wrapper
        warnings.filterwarnings("ignore", message=".*different from the unwrapped version")
        check_env(gym.make(ENV_ID, render_mode="rgb_array", **SMALL))
        sb3_check_env(make_interval_env(**SMALL), warn=True)

    def rollout(seed):
        env = gym.make(ENV_ID, **SMALL)
        obs, _ = env.reset(seed=seed)
        out = [obs.tobytes()]
        for k in range(6):
            obs, reward, terminated, truncated, _ = env.step(np.array([k % 9, k % 2]))
            out.append((obs.tobytes(), reward))
            if terminated or truncated:
                break
        return out

    assert rollout(3) == rollout(3)
    assert rollout(3) != rollout(4)


def test_the_wrapped_env_pickles_and_continues_identically():
    env = gym.make(ENV_ID, n_particles=60, n_steps=500, clutter_level=1)
    env.reset(seed=1, options={"world_seed": 1})
    assert not env.step(np.array([4, 1]))[2]
    copy = pickle.loads(pickle.dumps(env))
    a, b = env.step(np.array([2, 0])), copy.step(np.array([2, 0]))
    assert np.array_equal(a[0], b[0]) and a[1] == b[1]


def test_the_id_resolves_in_a_fresh_interpreter():
    code = ("import gymnasium as gym; import numpy as np; "
            f"env = gym.make('slam_gym:{ENV_ID}', n_particles=5, n_steps=60); "
            "env.reset(seed=0); env.step(np.array([0, 1])); "
            "assert env.action_space.nvec.tolist() == [9, 2]")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


@pytest.mark.parametrize("action", [np.array([9, 0]), np.array([0, 2]), np.array([1.0, 0.0]),
                                    np.array([1, 0, 1]), 3])
def test_invalid_actions_and_envs_name_the_field(action):
    env = make_interval_env(**SMALL)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(action)
    with pytest.raises(ValueError, match="env"):
        IntervalActions(gym.make("CartPole-v1"))
    with pytest.raises(ValueError, match="fusion_interval_s"):
        IntervalActions.action_of(9.0, True)
    assert IntervalActions.action_of(10.0, True).tolist() == RULE_ACTION.tolist()
