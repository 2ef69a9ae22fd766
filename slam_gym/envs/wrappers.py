"""Action wrappers for the interface env."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

# the one Discrete(4) encoding (a = 2 fuse + optimise) and its exact mask, shared with the
# learned policies that act through it
from policies.base import discrete_action_mask, discrete_to_multi


class DiscreteActions(gym.ActionWrapper):
    """Offers the env's ``MultiDiscrete([2, 2])`` actions as ``Discrete(4)`` (DQN, MaskablePPO).

    :meth:`action_masks` (found through ``get_wrapper_attr``, as sb3-contrib's
    ``get_action_masks`` and SB3's vector envs look it up) and ``info["action_mask"]`` give the
    exact ``Discrete(4)`` mask (:func:`discrete_action_mask`), replacing the env's factorised one.
    """

    def __init__(self, env):
        super().__init__(env)
        self.action_space = spaces.Discrete(4)

    def action(self, action):
        return discrete_to_multi(action)

    def action_masks(self) -> np.ndarray:
        redundant = self.env.get_wrapper_attr("optimisation_is_redundant")()
        return discrete_action_mask(redundant)

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        return obs, self._with_mask(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, reward, terminated, truncated, self._with_mask(info)

    @staticmethod
    def _with_mask(info):
        if "optimise_redundant" not in info:
            return info
        return {**info, "action_mask": discrete_action_mask(info["optimise_redundant"])}


TRAINING_WORLD_SEED_OFFSET = 1_000_000
"""Training worlds have seeds >= this; evaluation and benchmarks use seeds below it, so a
learned policy is never evaluated on a world it was trained on."""


class RandomClutterLevel(gym.Wrapper):
    """Each episode in a random clutter level and a fresh training world (for training).

    The level is drawn from ``levels`` and the world seed from
    [TRAINING_WORLD_SEED_OFFSET, TRAINING_WORLD_SEED_OFFSET + 1e9), both with the wrapper's own
    generator seeded by ``reset(seed=...)``.
    """

    def __init__(self, env, levels=(0, 1, 2, 3)):
        super().__init__(env)
        self.levels = tuple(int(v) for v in levels)
        if not self.levels:
            raise ValueError("levels=() is invalid: must name at least one clutter level")
        self._rng = np.random.default_rng()

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        options = dict(options or {})
        options.setdefault("clutter_level", int(self._rng.choice(self.levels)))
        options.setdefault(
            "world_seed", TRAINING_WORLD_SEED_OFFSET + int(self._rng.integers(0, 10**9))
        )
        return self.env.reset(seed=seed, options=options)


class RandomComputePrice(gym.Wrapper):
    """Each episode at a random price of compute (for a policy conditioned on the price).

    The reward's ``w_compute`` (per second of modelled compute) is drawn log-uniformly from
    ``[low, high]`` with the wrapper's own generator, seeded by ``reset(seed=...)``, and passed
    as the reset option ``w_compute``; the env shows it as the feature ``compute_price_per_s``
    (select it with the env's ``features`` option so the policy observes it).
    """

    def __init__(self, env, low: float, high: float):
        super().__init__(env)
        if not (np.isfinite(low) and np.isfinite(high) and 0 < low <= high):
            raise ValueError(f"low, high=({low!r}, {high!r}) is invalid: must be "
                             "0 < low <= high, finite")
        self.low, self.high = float(low), float(high)
        self._rng = np.random.default_rng()

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng([int(seed), 104729])
        options = dict(options or {})
        price = float(np.exp(self._rng.uniform(np.log(self.low), np.log(self.high))))
        options.setdefault("w_compute", price)
        return self.env.reset(seed=seed, options=options)


class LogFeatures(gym.ObservationWrapper):
    """``log1p`` of the (non-negative) features: puts seconds, metres and counts on one scale.

    The learned policy applies the same transform (its model's config says so), see
    ``policies.learned``.
    """

    def __init__(self, env):
        super().__init__(env)
        high = np.log1p(env.observation_space.high).astype(np.float32)
        self.observation_space = spaces.Box(
            low=np.zeros_like(high), high=high, dtype=np.float32
        )

    def observation(self, observation):
        return np.log1p(observation).astype(np.float32)


class RuleAnchor(gym.Wrapper):
    """Kickstarting toward a rule (issue 39 item 2): every action that differs from
    ``rule_action(info)`` (the rule's action at the same decision, from the info before it)
    costs ``weight`` in the reward. ``set_anchor_weight`` changes the weight (a training callback
    decays it to 0, through ``VecEnv.env_method``); at 0 the reward is the env's own. The
    decision is whole: an action differs when any of its components does."""

    def __init__(self, env, rule_action, weight: float = 0.0):
        super().__init__(env)
        self.rule_action = rule_action
        self.set_anchor_weight(weight)
        self._info: dict = {}

    def set_anchor_weight(self, weight: float) -> None:
        if not (isinstance(weight, (int, float)) and np.isfinite(weight) and weight >= 0):
            raise ValueError(f"weight={weight!r} is invalid: must be a finite number >= 0")
        self.weight = float(weight)

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._info = info
        return obs, info

    def step(self, action):
        differs = not np.array_equal(np.asarray(action).reshape(-1),
                                     np.asarray(self.rule_action(self._info)).reshape(-1))
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._info = info
        return obs, reward - (self.weight if differs else 0.0), terminated, truncated, info
