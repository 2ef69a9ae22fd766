"""Whole env episodes written out for a bit-for-bit comparison of two commits (issue 27).

Usage: PYTHONPATH=<tree> python scripts/performance/episode_bits.py dump OUT.pkl
       python scripts/performance/episode_bits.py compare A.pkl B.pkl

``dump`` plays ``fixed-10s``, ``fixed-10s-optimise`` and ``always`` on ``SlamGym/HybridSLAM-v0``
(500 particles; clutter levels 0, 2 and 3, worlds 0, 1 and 2) and ``fixed-10s`` and
``fixed-10s-optimise`` on ``SlamGym/EKFSubmap-v0`` and ``SlamGym/HybridSLAM-Relative-v0``
(level 2, world 4), and pickles every observation, reward, termination flag and info, and the
final pose and map. ``compare`` prints every entry that differs (NaN equals NaN) and the number
of differing episodes; a change meant to leave the numbers alone must print 0.

Supports docs/PERFORMANCE.md, "The code of 15bcb7d (2026-11-25 evening, the slower machine): five
more bit-identical speed-ups, and a sixth" (every speed-up leaves the episodes bit for bit).
The command behind it::

    PYTHONPATH=<tree of A> python scripts/performance/episode_bits.py dump /tmp/a.pkl
    python scripts/performance/episode_bits.py dump /tmp/b.pkl
    python scripts/performance/episode_bits.py compare /tmp/a.pkl /tmp/b.pkl
"""

from __future__ import annotations

import argparse
import pickle
import sys

import gymnasium as gym
import numpy as np

import policies
import slam_gym  # noqa: F401  (registers the env ids)

EPISODES = (
    *(("SlamGym/HybridSLAM-v0", name, level, seed)
      for name in ("fixed-10s", "fixed-10s-optimise", "always")
      for level, seed in ((0, 0), (2, 1), (3, 2))),
    *((env_id, name, 2, 4)
      for env_id in ("SlamGym/EKFSubmap-v0", "SlamGym/HybridSLAM-Relative-v0")
      for name in ("fixed-10s", "fixed-10s-optimise")),
)


def play(env_id: str, name: str, level: int, seed: int) -> list:
    env = gym.make(env_id, clutter_level=level).unwrapped
    policy = policies.make(name)
    obs, info = env.reset(seed=seed)
    policy.reset()
    record = [obs, info]
    while True:
        obs, reward, terminated, truncated, info = env.step(policy.act(obs, info))
        record.append((obs, reward, terminated, truncated, info))
        if terminated or truncated:
            break
    system = env.episode.system
    landmarks = system.landmarks()
    record.append((system.pose(), (landmarks.ids, landmarks.means, landmarks.covs,
                                   landmarks.existence)))
    return record


def differences(a, b, path: str) -> list[str]:
    """Where two nested records differ (dicts, sequences, arrays, scalars)."""
    if isinstance(a, dict):
        if set(a) != set(b):
            return [f"{path}: keys {sorted(a)} against {sorted(b)}"]
        return [d for k in a for d in differences(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} against {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True))
                for d in differences(x, y, f"{path}[{i}]")]
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        x, y = np.asarray(a), np.asarray(b)
        same = x.shape == y.shape and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc")
        return [] if same else [f"{path}: arrays differ"]
    if isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b):
        return []
    return [] if a == b else [f"{path}: {a!r} against {b!r}"]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("dump", help="play the episodes, pickle them").add_argument("out")
    compare = commands.add_parser("compare", help="print where two dumps differ")
    compare.add_argument("a")
    compare.add_argument("b")
    args = parser.parse_args(argv)
    argv = [args.command, args.out] if args.command == "dump" else [args.command, args.a, args.b]
    if len(argv) == 2 and argv[0] == "dump":
        records = [(episode, play(*episode)) for episode in EPISODES]
        with open(argv[1], "wb") as f:
            pickle.dump(records, f)
        print(f"{len(records)} episodes, {sum(len(r) - 3 for _, r in records)} decisions "
              f"-> {argv[1]}")
        return 0
    if len(argv) == 3 and argv[0] == "compare":
        with open(argv[1], "rb") as f:
            a = pickle.load(f)
        with open(argv[2], "rb") as f:
            b = pickle.load(f)
        n_differing = 0
        for (episode, x), (_, y) in zip(a, b, strict=True):
            found = differences(x, y, "/".join(map(str, episode)))
            n_differing += bool(found)
            for line in found[:20]:
                print(line)
        print(f"{len(a)} episodes, {n_differing} differing")
        return 0
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
