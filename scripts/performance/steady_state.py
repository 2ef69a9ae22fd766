"""Decisions per CPU second of a plain ``gym.make`` env in steady state (issue 57).

Usage: python scripts/performance/steady_state.py [--env ID] [--schedule S] [--warmup W]
                                                  [--decisions N] [--seed S]
e.g.   python scripts/performance/steady_state.py --schedule fixed-10s --decisions 800

Makes ``--env`` (default ``SlamGym/HybridSLAM-v1``, its defaults) with ``gym.make``, resets it
on world ``--seed`` and plays ``slam-gym speed``'s schedule ``--schedule`` (``fixed-10s``,
``fixed-10s-optimise``, ...: :func:`slam_gym.commands.speed.schedule_action`); an episode that
ends is followed by ``reset(seed=previous + 1)``, so two commits play the same worlds. The first
``--warmup`` decisions (the compiled kernels loaded, the caches warm) are not counted; of the next
``--decisions`` the CPU time of the steps alone (``time.process_time`` around each ``step``; the
resets, which simulate a new world, are counted apart) is printed with the decisions per CPU
second. Run it from two checkouts in turn (A B A B ...) and quote the pairwise ratios: the
machine's speed drifts between runs.

Supports docs/PERFORMANCE.md, "The decision compiled around the filter (issue 57 items 2-4)".
The command behind it::

    python scripts/performance/steady_state.py --schedule fixed-10s --warmup 100 --decisions 800
"""

from __future__ import annotations

import argparse
import sys
import time

import gymnasium as gym

import slam_gym  # noqa: F401  (registers the env ids)
from slam_gym.commands.speed import schedule_action


def measure(env_id: str, schedule: str, warmup: int, decisions: int, seed: int) -> dict:
    """Play ``warmup + decisions`` decisions of ``schedule``; the CPU of the counted steps."""
    env = gym.make(env_id)
    world = seed
    env.reset(seed=world)
    step_cpu_s = reset_cpu_s = 0.0
    resets = 0
    for k in range(warmup + decisions):
        action = schedule_action(schedule, env.unwrapped.episode.iteration)
        start = time.process_time()
        *_, terminated, truncated, _ = env.step(action)
        if k >= warmup:
            step_cpu_s += time.process_time() - start
        if terminated or truncated:
            world += 1
            start = time.process_time()
            env.reset(seed=world)
            if k >= warmup:
                reset_cpu_s += time.process_time() - start
                resets += 1
    env.close()
    return {"decisions": decisions, "step_cpu_s": step_cpu_s, "reset_cpu_s": reset_cpu_s,
            "resets": resets, "worlds": world - seed + 1,
            "decisions_per_cpu_s": decisions / step_cpu_s}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="SlamGym/HybridSLAM-v1")
    parser.add_argument("--schedule", default="fixed-10s")
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--decisions", type=int, default=800)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.warmup < 0 or args.decisions < 1:
        parser.error("--warmup must be >= 0 and --decisions >= 1")
    r = measure(args.env, args.schedule, args.warmup, args.decisions, args.seed)
    print(f"{args.env} {args.schedule}: {r['decisions']} decisions after {args.warmup} "
          f"in {r['step_cpu_s']:.3f} CPU s of steps: {r['decisions_per_cpu_s']:.1f} decisions "
          f"per CPU s ({r['resets']} resets, {r['reset_cpu_s']:.2f} CPU s apart; "
          f"{r['worlds']} worlds)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
