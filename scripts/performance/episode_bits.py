"""Whole env episodes written out for a bit-for-bit comparison of two commits (issue 27).

Usage: PYTHONPATH=<tree> python scripts/performance/episode_bits.py dump OUT.pkl
       python scripts/performance/episode_bits.py compare A.pkl B.pkl
       python scripts/performance/episode_bits.py record benchmarks/episode-bits.json
       python scripts/performance/episode_bits.py check benchmarks/episode-bits.json

The episodes: ``fixed-10s``, ``fixed-10s-optimise`` and ``always`` on ``SlamGym/HybridSLAM-v1``
(500 particles; clutter levels 0, 2 and 3, worlds 0, 1 and 2) and ``fixed-10s`` and
``fixed-10s-optimise`` on ``SlamGym/EKFSubmap-v1`` and ``SlamGym/HybridSLAM-Relative-v1``
(level 2, world 4); each one's record is every observation, reward, termination flag and info,
and the final pose and map. (Until issue 47 they were the ``-v0`` ids; a commit's own docstring
names what it played.)

``dump`` pickles the records; ``compare`` prints every entry of two dumps that differs (NaN
equals NaN) and the number of differing episodes. ``record`` writes one SHA-256 digest per
episode (:func:`digest`: the record's bytes in a canonical walk) with the commit into a small
JSON file, the reference kept in the repository (``benchmarks/episode-bits.json``, recorded when
issue 47 changed the filter's rounding); ``check`` plays the episodes again and prints those whose
digest differs from the reference's, exit 1 if any. A change meant to leave the numbers alone
must print 0 differing.

Supports docs/PERFORMANCE.md, "The code of 15bcb7d (2026-11-25 evening, the slower machine): five
more bit-identical speed-ups, and a sixth" (every speed-up leaves the episodes bit for bit).
The command behind it::

    PYTHONPATH=<tree of A> python scripts/performance/episode_bits.py dump /tmp/a.pkl
    python scripts/performance/episode_bits.py dump /tmp/b.pkl
    python scripts/performance/episode_bits.py compare /tmp/a.pkl /tmp/b.pkl
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import pickle
import struct
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

import policies
import slam_gym  # noqa: F401  (registers the env ids)

EPISODES = (
    *(("SlamGym/HybridSLAM-v1", name, level, seed)
      for name in ("fixed-10s", "fixed-10s-optimise", "always")
      for level, seed in ((0, 0), (2, 1), (3, 2))),
    *((env_id, name, 2, 4)
      for env_id in ("SlamGym/EKFSubmap-v1", "SlamGym/HybridSLAM-Relative-v1")
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


def _walk(value, update) -> None:
    """Feed ``value``'s bytes to ``update`` in a canonical order, each kind tagged (dict keys
    sorted; arrays by dtype, shape and C-order bytes; floats as IEEE doubles)."""
    if isinstance(value, dict):
        update(b"d%d" % len(value))
        for key in sorted(value, key=str):
            _walk(str(key), update)
            _walk(value[key], update)
    elif isinstance(value, (list, tuple)):
        update(b"l%d" % len(value))
        for item in value:
            _walk(item, update)
    elif isinstance(value, np.ndarray):
        update(b"a" + value.dtype.str.encode() + repr(value.shape).encode())
        update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, (bool, np.bool_)):
        update(b"b1" if value else b"b0")
    elif isinstance(value, (float, np.floating)):
        update(b"f" + struct.pack("<d", float(value)))
    elif isinstance(value, (int, np.integer)):
        update(b"i" + str(int(value)).encode())
    elif value is None:
        update(b"n")
    else:
        update(b"s" + str(value).encode())


def digest(record) -> str:
    """SHA-256 of an episode's record in :func:`_walk`'s canonical order: equal records give
    equal digests, and one changed bit of any number a different one."""
    h = hashlib.sha256()
    _walk(record, h.update)
    return h.hexdigest()


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def digests() -> list[dict]:
    """Every episode played, as ``{"env_id", "policy", "clutter_level", "seed", "decisions",
    "sha256"}``."""
    out = []
    for env_id, name, level, seed in EPISODES:
        record = play(env_id, name, level, seed)
        out.append({"env_id": env_id, "policy": name, "clutter_level": level, "seed": seed,
                    "decisions": len(record) - 3, "sha256": digest(record)})
    return out


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
    commands.add_parser("record", help="write the episodes' digests (the reference)"
                        ).add_argument("out")
    commands.add_parser("check", help="play the episodes, compare with a recorded reference"
                        ).add_argument("reference")
    args = parser.parse_args(argv)
    if args.command == "record":
        doc = {"commit": _commit(), "date": datetime.datetime.now(datetime.UTC)
               .strftime("%Y-%m-%d %H:%M UTC"), "episodes": digests()}
        Path(args.out).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(f"{len(doc['episodes'])} episodes, "
              f"{sum(e['decisions'] for e in doc['episodes'])} decisions -> {args.out}")
        return 0
    if args.command == "check":
        reference = json.loads(Path(args.reference).read_text(encoding="utf-8"))
        expected = {(e["env_id"], e["policy"], e["clutter_level"], e["seed"]): e
                    for e in reference["episodes"]}
        n_differing = 0
        for now in digests():
            key = (now["env_id"], now["policy"], now["clutter_level"], now["seed"])
            then = expected.get(key)
            if then is None or then["sha256"] != now["sha256"]:
                n_differing += 1
                print(f"{'/'.join(map(str, key))}: differs from {reference['commit']}'s"
                      f" ({now['decisions']} decisions now)")
        print(f"{len(expected)} episodes, {n_differing} differing from {reference['commit']}")
        return 1 if n_differing else 0
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
