"""``SlamGym/HybridSLAM-Interval-v1``: the interface decided once per fusion (issue 39 item 3).

The same system, world and reward as ``SlamGym/HybridSLAM-v1``
(:class:`~slam_gym.envs.hybrid_slam.HybridSLAMEnv`); one action chooses *when the next fusion
happens and whether to optimise at it*, so an episode on BB's path has ~40 decisions instead of
~430 and a learner can credit a fusion's consequences to the decision that caused them.

Action space
    ``MultiDiscrete([len(FUSION_INTERVALS_S), 2])``: (index into :data:`FUSION_INTERVALS_S`, the
    time in seconds from the last fusion to the next one; optimise at that fusion?). The wrapped
    env then decides "neither" until its local map is that old (its ``local_map_age_s``; the
    first local map's age counts from the start of the episode) and fuses, optimising or not, at
    the first decision where it is. BB's rule with CM's optimiser after every fusion
    (``fixed-10s-optimise``) is the constant action :data:`RULE_ACTION` = (10 s, optimise), and
    plays the rule's episode to the bit (a test checks it).

Observation space
    The wrapped env's, at the decision after the fusion (its local map one decision old).

Reward
    The sum of the wrapped env's rewards over the decisions the action covered (the module
    docstring of :mod:`slam_gym.envs.hybrid_slam`): the same return per episode as the same
    decisions taken one by one.

Episode end
    When the wrapped env's episode ends (end of the path, BB's failure criterion, or its
    ``max_decisions``), possibly before the chosen fusion: the last action then covers the
    decisions up to the end. ``info`` is the wrapped env's last, plus ``env_decisions`` (how many
    decisions of the wrapped env the action covered) and ``fusion_interval_s``.

Every keyword of :class:`~slam_gym.envs.hybrid_slam.HybridSLAMConfig` is accepted by
``gym.make("SlamGym/HybridSLAM-Interval-v1", ...)``; :class:`IntervalActions` wraps an env
someone already made.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from filters.validation import require
from policies.heuristics import AGE_TOLERANCE_S
from slam_gym.envs.hybrid_slam import HybridSLAMEnv

FUSION_INTERVALS_S: tuple[float, ...] = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 17.0, 20.0)
"""The times between fusions an action may choose (s): BB's 10 s in the middle, from five times
as often to half as often."""

RULE_ACTION = np.array([FUSION_INTERVALS_S.index(10.0), 1], dtype=np.int64)
"""``fixed-10s-optimise`` as an action of this env: fuse 10 s after the last fusion, optimise."""


class IntervalActions(gym.Wrapper):
    """One action per fusion: (time to the next fusion, optimise at it?) (module docstring)."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        inner = env.unwrapped
        require(isinstance(inner, HybridSLAMEnv), "env", inner,
                "a slam_gym HybridSLAMEnv (or a wrapper of one)")
        self.action_space = spaces.MultiDiscrete([len(FUSION_INTERVALS_S), 2])
        self.observation_space = env.observation_space
        self._info: dict = {}

    @staticmethod
    def action_of(fusion_interval_s: float, optimise: bool) -> np.ndarray:
        """The action that fuses ``fusion_interval_s`` after the last fusion (one of
        :data:`FUSION_INTERVALS_S`) and optimises at it or not."""
        require(fusion_interval_s in FUSION_INTERVALS_S, "fusion_interval_s", fusion_interval_s,
                f"one of {FUSION_INTERVALS_S}")
        return np.array([FUSION_INTERVALS_S.index(fusion_interval_s), int(bool(optimise))],
                        dtype=np.int64)

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._info = info
        return obs, {**info, "env_decisions": 0, "fusion_interval_s": None}

    def step(self, action):
        action = np.asarray(action)
        require(action.shape == (2,) and np.issubdtype(action.dtype, np.integer)
                and self.action_space.contains(action.astype(np.int64)), "action", action,
                f"two integers in MultiDiscrete([{len(FUSION_INTERVALS_S)}, 2]): (index into "
                f"{FUSION_INTERVALS_S}, optimise)")
        interval_s = FUSION_INTERVALS_S[int(action[0])]
        optimise = int(action[1])
        total, decisions = 0.0, 0
        info = self._info
        while True:
            age_s = float(info["features"]["local_map_age_s"])
            fuse = age_s + AGE_TOLERANCE_S >= interval_s
            obs, reward, terminated, truncated, info = self.env.step(
                np.array([int(fuse), optimise if fuse else 0], dtype=np.int64))
            total += float(reward)
            decisions += 1
            if fuse or terminated or truncated:
                break
        self._info = info
        return obs, total, terminated, truncated, {
            **info, "env_decisions": decisions, "fusion_interval_s": interval_s}


def make_interval_env(render_mode: str | None = None, **config) -> IntervalActions:
    """The registered id's entry point: a :class:`HybridSLAMEnv` with ``config``, wrapped."""
    return IntervalActions(HybridSLAMEnv(render_mode=render_mode, **config))
