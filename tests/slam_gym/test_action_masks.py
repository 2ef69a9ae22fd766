"""Action masks (issue 29 item 2): the env's mask and the Discrete(4) wrapper's exact one, what
sb3-contrib's MaskablePPO reads through wrappers and vector envs, and that a masked action is
exactly the no-op it is masked for."""

import copy
import warnings

import gymnasium as gym
import numpy as np
import pytest

from slam_gym.envs.wrappers import DiscreteActions, LogFeatures, discrete_action_mask

SMALL = {"n_particles": 20, "n_steps": 400}


def make_discrete(**kwargs):
    return DiscreteActions(gym.make("slam_gym:SlamGym/HybridSLAM-v1", **(SMALL | kwargs)))


def _optimise_records(env):
    return sum(kind == "optimise" for kind, _, _ in env.unwrapped.compute_records)


def test_the_mask_is_exactly_whether_optimising_alone_is_a_no_op():
    """At every decision of an episode, two copies of the env step "optimise only" and
    "nothing": where the mask excludes "optimise only" the two continue identically (observation,
    reward and its terms, infos, counts, nothing charged for the optimiser); where it allows it,
    the optimisation happens (counted and charged), so the mask forbids no real action."""
    env = make_discrete()
    obs, info = env.reset(seed=4)
    schedule = [0, 1, 2, 1, 1, 0, 3, 1, 0, 2, 0, 1, 3, 3, 1, 2, 2, 1, 0, 1]
    masked = allowed = 0
    for a in schedule:
        mask = env.action_masks()
        np.testing.assert_array_equal(mask, info["action_mask"])
        assert mask[0] and mask[2] and mask[3]  # fusing is never a no-op
        opt, idle = copy.deepcopy(env), copy.deepcopy(env)
        before = (opt.unwrapped.episode.n_optimisations, _optimise_records(opt))
        out_opt, out_idle = opt.step(1), idle.step(0)
        after = (opt.unwrapped.episode.n_optimisations, _optimise_records(opt))
        if not mask[1]:
            masked += 1
            np.testing.assert_array_equal(out_opt[0], out_idle[0])
            assert out_opt[1] == out_idle[1]
            assert out_opt[4]["reward_components"] == out_idle[4]["reward_components"]
            assert after == before  # not counted, nothing charged
            assert opt.unwrapped.system.estimator.back_end.x.tobytes() == \
                idle.unwrapped.system.estimator.back_end.x.tobytes()
        else:
            allowed += 1
            assert after == (before[0] + 1, before[1] + 1)
        obs, _, terminated, truncated, info = env.step(a)
        assert not (terminated or truncated)
    assert masked >= 3 and allowed >= 3  # the schedule exercised both cases


def test_before_any_fusion_optimising_is_masked_and_a_fusion_unmasks_it():
    env = make_discrete()
    _, info = env.reset(seed=1)
    assert info["optimise_redundant"] and not info["action_mask"][1]
    info = env.step(2)[4]  # fuse
    assert not info["optimise_redundant"] and info["action_mask"].all()
    info = env.step(1)[4]  # optimise: the optimum is applied, so again redundant
    assert info["n_optimisations"] == 1 and info["optimise_redundant"]
    np.testing.assert_array_equal(info["action_mask"], [True, False, True, True])


def test_the_env_mask_is_factorised_all_true_and_in_every_info():
    """On ``MultiDiscrete([2, 2])`` a factorised mask that excluded optimise=1 would also exclude
    fuse-then-optimise, which is never a no-op: the exact factorised mask allows everything."""
    env = gym.make("slam_gym:SlamGym/HybridSLAM-v1", **SMALL)
    _, info = env.reset(seed=0)
    assert info["action_mask"].dtype == bool and info["action_mask"].all()
    assert info["optimise_redundant"] is True
    info = env.step(np.array([1, 1]))[4]
    assert info["n_optimisations"] == 1 and info["action_mask"].shape == (4,)
    assert env.get_wrapper_attr("action_masks")().all()
    assert info["optimise_redundant"] == env.get_wrapper_attr("optimisation_is_redundant")()


def test_policies_compute_the_same_mask():
    from policies.base import discrete_action_mask as policies_mask

    for redundant in (False, True):
        np.testing.assert_array_equal(discrete_action_mask(redundant), policies_mask(redundant))


def test_env_checkers_pass_with_masks_in_the_infos():
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make("slam_gym:SlamGym/HybridSLAM-v1", **SMALL)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(make_discrete(), warn=True)


def test_maskable_ppo_finds_the_exact_mask_through_wrappers_and_vector_envs():
    """sb3-contrib's ``get_action_masks`` calls ``env_method("action_masks")``, which SB3's vector
    envs resolve with ``get_wrapper_attr``: the outermost definition, the wrapper's exact mask,
    must win over the env's factorised one, in-process and in a subprocess."""
    from sb3_contrib.common.maskable.utils import get_action_masks, is_masking_supported
    from stable_baselines3.common.vec_env import (
        DummyVecEnv,
        SubprocVecEnv,
        VecMonitor,
        VecNormalize,
    )

    def make():
        return LogFeatures(make_discrete())

    for vec in (DummyVecEnv([make]), SubprocVecEnv([make, make], start_method="spawn")):
        vec = VecNormalize(VecMonitor(vec))
        vec.seed(3)
        vec.reset()
        assert is_masking_supported(vec)
        masks = get_action_masks(vec)
        assert masks.shape == (vec.num_envs, 4)
        np.testing.assert_array_equal(masks, [[True, False, True, True]] * vec.num_envs)
        vec.step(np.array([2] * vec.num_envs))  # fuse: optimising becomes real
        assert get_action_masks(vec).all()
        vec.close()


@pytest.mark.parametrize("level", [0, 3])
def test_mask_at_every_decision_of_a_rule_driven_episode_matches_the_optimiser(level):
    """Over a whole (short) episode driven by fixed-10s-optimise's pattern, the mask in the info
    says "optimise only is masked" exactly when the optimiser reports a redundant call."""
    env = make_discrete(clutter_level=level, n_steps=300)
    _, info = env.reset(seed=level)
    done, t = False, 0
    while not done:
        redundant = env.unwrapped.system.estimator.optimisation_is_redundant()
        assert info["optimise_redundant"] == redundant == (not info["action_mask"][1])
        a = 3 if t % 10 == 9 else (1 if t % 7 == 3 else 0)
        n_before = info["n_optimisations"]
        _, _, terminated, truncated, info = env.step(a)
        if a == 1:
            assert info["n_optimisations"] == n_before + (not redundant)
        done, t = terminated or truncated, t + 1
