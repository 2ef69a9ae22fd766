"""What a copy of the env mid-episode costs: ``env.clone()`` against ``copy.deepcopy(env)``
(issue 39 item 1), and a re-seeded future's first decision.

Supports docs/PERFORMANCE.md, "Copies of the env for planning (issue 39)". Command::

    python scripts/performance/clone_cost.py --decisions 300 --repeats 20

Plays ``fixed-10s-optimise`` for ``--decisions`` decisions of world ``--world`` at level 2 (500
particles), then times each kind of copy ``--repeats`` times in CPU seconds (``process_time``)
and prints the minimum, median and maximum, and the size of a pickle of the env.
"""

from __future__ import annotations

import argparse
import copy
import pickle
import statistics
import sys
import time

import policies
from slam_gym.envs.hybrid_slam import HybridSLAMEnv


def _times(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        start = time.process_time()
        fn()
        out.append(time.process_time() - start)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--decisions", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--world", type=int, default=900001, help="a training-time world")
    parser.add_argument("--particles", type=int, default=500)
    args = parser.parse_args(argv)
    env = HybridSLAMEnv(clutter_level=2, n_particles=args.particles)
    rule = policies.make("fixed-10s-optimise")
    obs, info = env.reset(seed=0, options={"world_seed": args.world})
    for _ in range(args.decisions):
        obs, _, terminated, truncated, info = env.step(rule.act(obs, info))
        if terminated or truncated:
            break
    env.clone()  # warm

    def reseeded_step():
        twin = env.clone()
        twin.reseed_future(1)
        twin.step(rule.act(obs, info))

    def plain_step():
        env.clone().step(rule.act(obs, info))

    rows = {
        "env.clone()": _times(env.clone, args.repeats),
        "copy.deepcopy(env)": _times(lambda: copy.deepcopy(env), max(3, args.repeats // 5)),
        "clone + one decision": _times(plain_step, args.repeats),
        "clone + reseed + one decision": _times(reseeded_step, args.repeats),
    }
    sys.stdout.write(f"after {env.n_decisions} decisions, {args.particles} particles; pickle of "
                     f"the env {len(pickle.dumps(env)) / 1e6:.2f} MB\n")
    for name, values in rows.items():
        sys.stdout.write(f"{name:32s} min {1e3 * min(values):8.2f} ms  median "
                         f"{1e3 * statistics.median(values):8.2f} ms  max "
                         f"{1e3 * max(values):8.2f} ms\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
