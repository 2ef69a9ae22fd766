"""Action wrappers for the interface env."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


def discrete_to_multi(action: int) -> np.ndarray:
    """``Discrete(4)`` -> (fuse, optimise) with ``a = 2 * fuse + optimise``.

    The same mapping as ``policies.base.discrete_to_multi`` (a test checks they agree; the env
    does not import ``policies``, see docs/ARCHITECTURE.md).
    """
    a = int(action)
    if not 0 <= a < 4:
        raise ValueError(f"action={action!r} is invalid: must be in Discrete(4)")
    return np.array([a // 2, a % 2], dtype=np.int64)


class DiscreteActions(gym.ActionWrapper):
    """Offers the env's ``MultiDiscrete([2, 2])`` actions as ``Discrete(4)`` (for DQN)."""

    def __init__(self, env):
        super().__init__(env)
        self.action_space = spaces.Discrete(4)

    def action(self, action):
        return discrete_to_multi(action)
