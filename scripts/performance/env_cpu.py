"""The env's CPU cost as a whole process, for paired comparisons of two commits (issue 27).

Usage: python scripts/performance/env_cpu.py [DECISIONS] [POLICY]
e.g.   /usr/bin/time -f "%U %S" python scripts/performance/env_cpu.py 300 fixed-10s

Plays ``POLICY`` (default ``fixed-10s``) in ``HybridSLAMEnv(n_particles=500,
clutter_level=2)`` for ``DECISIONS`` decisions (default 300) from ``reset(seed=0)``; an episode
that ends is followed by ``reset(seed=previous + 1)``, so resets (each simulates a new world) are
included. Prints the CPU seconds of the imports and of the decisions (the first reset, which
loads the compiled kernels from numba's cache, included) and the decisions per CPU second.
Run it alternately on the two commits (A B A B ..., each process timed from outside) and quote
the median of the pairwise ratios: the machine's speed drifts between runs.

Supports docs/PERFORMANCE.md, "The targets, measured on 2026-11-26: met" (and the paired
comparisons of "The same numbers, less work").
The command behind it::

    /usr/bin/time -f "%U %S" python scripts/performance/env_cpu.py 600 fixed-10s
"""

from __future__ import annotations

import argparse
import sys
import time

_START_CPU_S = time.process_time()

import policies  # noqa: E402
from slam_gym.envs.hybrid_slam import HybridSLAMEnv  # noqa: E402
from slam_gym.evaluation.core import play_decisions  # noqa: E402


def main(argv: list[str]) -> int:
    imported_cpu_s = time.process_time()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("decisions", nargs="?", type=int, default=300)
    parser.add_argument("policy", nargs="?", default="fixed-10s")
    args = parser.parse_args(argv)
    n_decisions, name = args.decisions, args.policy
    env = HybridSLAMEnv(n_particles=500, clutter_level=2)
    policy = policies.make(name)
    policy.reset()
    obs, info = env.reset(seed=0)
    n_worlds = play_decisions(env, policy, obs, info, n_decisions, seed=0)
    decisions_cpu_s = time.process_time() - imported_cpu_s
    print(
        f"import_cpu_s {imported_cpu_s - _START_CPU_S:.3f} decisions_cpu_s {decisions_cpu_s:.3f} "
        f"decisions_per_cpu_s {n_decisions / decisions_cpu_s:.1f} ({name}, {n_worlds} worlds)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
