"""The lookahead's planning CPU per episode on a task's worlds (issue 57 item 1): one line per
episode, to be paired with the same command run from another checkout.

Supports docs/PERFORMANCE.md, "The fast lookahead (issue 57)". Command, from each checkout in
turn (``PYTHONPATH=<checkout>``), the same worlds::

    python scripts/performance/lookahead_cpu.py --task SlamGym/HybridSLAM-Zones-v1 \\
        --policy lookahead --worlds 4820:2 --out out/cpu57.jsonl --label new

Plays ``--policy`` (a name ``policies.make`` accepts in that checkout) on each world
(``seed:level``) of ``--task`` (draw 0, price 10 /s, clip 0.2 s: issue 48's reward) and appends
to ``--out`` one JSON line per episode: the policy's planning CPU (``planning_cpu_s``, its own
``process_time`` around its planning), its simulated and planned decisions, the episode's
decisions and success, the process's CPU for the episode, and ``--label`` and the checkout's
commit. Prints the same line.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="SlamGym/HybridSLAM-Zones-v1")
    parser.add_argument("--policy", default="lookahead")
    parser.add_argument("--worlds", required=True, help="seed:level,...")
    parser.add_argument("--out", required=True)
    parser.add_argument("--label", default="")
    args = parser.parse_args(argv)

    import gymnasium as gym

    import policies
    import slam_gym

    root = Path(slam_gym.__file__).resolve().parent.parent
    commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    for spec in filter(None, (w.strip() for w in args.worlds.split(","))):
        seed, level = (int(v) for v in spec.split(":"))
        env = gym.make(args.task, clutter_level=level, w_compute=10.0, compute_clip_s=0.2)
        policy = policies.make(args.policy)
        start = time.process_time()
        obs, info = env.reset(seed=seed, options={"world_seed": seed})
        policy.reset()
        policy.bind_env(env)
        decisions, done = 0, False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
            decisions += 1
            done = terminated or truncated
        row = {"label": args.label, "commit": commit, "task": args.task, "policy": args.policy,
               "seed": seed, "level": level, "decisions": decisions,
               "success": not bool(info["failed"]),
               "episode_cpu_s": time.process_time() - start, **policy.episode_fields()}
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
