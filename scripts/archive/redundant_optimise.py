"""What an optimisation with no fusion since the previous one changes, and what the reward
charges for it (#15).

Usage: python scripts/archive/redundant_optimise.py [SEED] [CLUTTER_LEVEL]
e.g.   python scripts/archive/redundant_optimise.py 900001 3

Plays ``fixed-10s-optimise`` on one world of ``SlamGym/HybridSLAM-v0`` twice: as it is, and with
an extra optimisation at every decision that follows an optimisation and fuses nothing. Prints
the features that differ between the two runs (expected: ``time_since_optimise_s`` only), the
map errors, both returns and the largest per-decision difference in reward: the compute term's
charge for an optimisation that changes nothing.

Supports docs/results/history.md, "Learned interface policies (issue 15)".
The command behind it::

    python scripts/archive/redundant_optimise.py 900001 3
"""

from __future__ import annotations

import argparse
import logging
import sys

import gymnasium as gym
import numpy as np

import policies
import slam_gym  # noqa: F401  (registers the env ids)
from policies.base import INTERFACE_FEATURES

logger = logging.getLogger(__name__)


def play(seed: int, level: int, extra: bool):
    env = gym.make("SlamGym/HybridSLAM-v0", clutter_level=level)
    policy = policies.make("fixed-10s-optimise")
    obs, info = env.reset(seed=seed)
    policy.reset()
    rewards, observations, optimised_last, done = [], [], False, False
    while not done:
        action = np.asarray(policy.act(obs, info), dtype=np.int64)
        if extra and optimised_last and action[0] == 0:
            action = np.array([0, 1])
        optimised_last = bool(action[1])
        obs, reward, terminated, truncated, info = env.step(action)
        rewards.append(reward)
        observations.append(np.asarray(obs, dtype=float).copy())
        done = terminated or truncated
    env.close()
    return np.array(rewards), np.array(observations), info


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("seed", nargs="?", type=int, default=900001)
    parser.add_argument("clutter_level", nargs="?", type=int, default=3)
    args = parser.parse_args(argv)
    seed, level = args.seed, args.clutter_level
    r0, o0, i0 = play(seed, level, extra=False)
    r1, o1, i1 = play(seed, level, extra=True)
    n = min(len(r0), len(r1))
    differing = np.abs(o0[:n] - o1[:n]).max(axis=0)
    extra = i1["n_optimisations"] - i0["n_optimisations"]
    logger.info("world %d, level %d: %d and %d decisions; %d and %d optimisations (%d extra)",
                seed, level, len(r0), len(r1), i0["n_optimisations"], i1["n_optimisations"],
                extra)
    logger.info("features that differ: %s",
                {INTERFACE_FEATURES[i]: float(differing[i]) for i in np.nonzero(differing)[0]})
    logger.info("map error %s m and %s m; return %.2f and %.2f (difference %.2f, %.4f per extra "
                "optimisation, largest per decision %.4f)", i0["map_error_m"], i1["map_error_m"],
                r0.sum(), r1.sum(), r0.sum() - r1.sum(), (r0.sum() - r1.sum()) / max(extra, 1),
                np.abs(r0[:n] - r1[:n]).max())
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
