"""Where an env decision's time goes: wall time of the main calls of a step (issue 27).

Usage: python scripts/performance/env_breakdown.py [POLICY] [DECISIONS]
e.g.   python scripts/performance/env_breakdown.py fixed-10s 400

Wraps the pieces of a ``HybridSLAMEnv(n_particles=500, clutter_level=2)`` step in
``perf_counter`` timers (since issue 47: the compiled iteration, the draws handed to it,
FastSLAM's and the sub-map system's iteration around it, the episode's iteration with its metrics,
the map score, the interface features, fusions, optimisations, resets), plays ``POLICY`` (default
``fixed-10s``) for ``DECISIONS`` decisions (default 400) from ``reset(seed=0)`` after a warm-up,
and prints each piece's milliseconds per decision and share of the wall time. Nested pieces
are included in their callers (the compiled call in FastSLAM's iteration, which is in the
sub-map system's, in the episode's, in the interval).

Supports docs/PERFORMANCE.md, "The code of 15bcb7d (2026-11-25 evening, the slower machine): five
more bit-identical speed-ups, and a sixth".
The command behind it::

    python scripts/performance/env_breakdown.py fixed-10s 400
"""

from __future__ import annotations

import argparse
import collections
import sys
import time

import filters.fastslam as fastslam
import filters.submap as submap
import policies
import slam_gym.envs.hybrid_slam as hybrid_slam
import slam_gym.episode as episode
from slam_gym.evaluation.core import play_decisions

PIECES = (
    (fastslam, "call_iteration",
     "compiled iteration: prediction, scan, votes, ids, clutter rate, culling, weights, "
     "resampling, innovation ratio, pose moments, composed pose, NEES"),
    (fastslam.FastSLAM2, "_iteration_draws", "the iteration's draws (each role's block)"),
    (fastslam.FastSLAM2, "run_iteration", "FastSLAM iteration (compiled call included)"),
    (submap.SubmapSLAM, "iterate", "sub-map system's iteration (FastSLAM's included)"),
    (episode.Episode, "_process", "episode's iteration (system's and metrics included)"),
    (episode.Episode, "map_score", "map score (reward)"),
    (episode.Episode, "fuse", "fusions"),
    (episode.Episode, "optimise", "optimisations"),
    (hybrid_slam.HybridSLAMEnv, "_features", "interface features"),
    (hybrid_slam.HybridSLAMEnv, "_run_interval", "decision interval (10 iterations)"),
    (hybrid_slam.HybridSLAMEnv, "reset", "resets"),
)


def _timed(function, label, seconds, calls):
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            seconds[label] += time.perf_counter() - start
            calls[label] += 1
    return wrapper


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("policy", nargs="?", default="fixed-10s")
    parser.add_argument("decisions", nargs="?", type=int, default=400)
    args = parser.parse_args(argv)
    name, n_decisions = args.policy, args.decisions
    seconds, calls = collections.defaultdict(float), collections.Counter()
    for owner, attribute, label in PIECES:
        setattr(owner, attribute, _timed(getattr(owner, attribute), label, seconds, calls))
    env = hybrid_slam.HybridSLAMEnv(n_particles=500, clutter_level=2)
    policy = policies.make(name)
    obs, info = env.reset(seed=0)
    policy.reset()
    for _ in range(30):  # warm-up: the compiled kernels loaded
        obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
        if terminated or truncated:  # the env raises on a step past the end
            break
    seconds.clear()
    calls.clear()
    obs, info = env.reset(seed=0)
    policy.reset()
    start = time.perf_counter()
    n_worlds = play_decisions(env, policy, obs, info, n_decisions, seed=0)
    wall_s = time.perf_counter() - start
    print(f"{name}: {n_decisions} decisions in {wall_s:.2f} s wall "
          f"({n_decisions / wall_s:.1f} decisions/s under the timers), {n_worlds} worlds")
    for label, s in sorted(seconds.items(), key=lambda kv: -kv[1]):
        print(f"  {label:36s} {s / n_decisions * 1e3:7.3f} ms a decision  "
              f"{s / wall_s * 100:5.1f} %  ({calls[label] / n_decisions:.2f} calls a decision)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
