"""FastSLAM2 of two versions stepped in turn in one process: CPU per step and equal poses.

Usage: python scripts/performance/fastslam_paired.py OLD_FASTSLAM.py [--steps N] [--rounds R]
e.g.   git show 35f0eee:filters/fastslam.py > /tmp/old_fastslam.py
       python scripts/performance/fastslam_paired.py /tmp/old_fastslam.py

Loads ``OLD_FASTSLAM.py`` as a module of its own (a copy in a temporary directory, so numba
compiles its functions there; it imports the rest of ``filters`` from this tree, so it must be
an older ``filters/fastslam.py`` that still runs against it) and runs it and this tree's
:class:`filters.fastslam.FastSLAM2` on the same world (level 2, world 1, 500 particles, the same
seed), one step each in turn (predict, update, pose; the order alternates every step), with a
restart every 100 steps as HYBRID's local maps have. Each step's CPU time is added to its
version; every pose of the two must be equal to the bit (else it stops with exit 1). Prints each
round's CPU per step and the ratio this tree / old; on a loaded machine the ratio is the figure
to read, since both versions run under the same load, step by step.

Supports docs/PERFORMANCE.md, "One compiled FastSLAM iteration (issue 40 item 3)". The command
behind it::

    git show 35f0eee:filters/fastslam.py > /tmp/old_fastslam.py
    python scripts/performance/fastslam_paired.py /tmp/old_fastslam.py --steps 1000 --rounds 5
"""

from __future__ import annotations

import argparse
import importlib.util
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from filters.fastslam import FastSLAM2
from slam_gym.world import make_stream

RESTART_EVERY_STEPS = 100


def load_module(path: str, directory: str):
    copy = Path(directory) / "fastslam_old.py"
    shutil.copy(path, copy)
    spec = importlib.util.spec_from_file_location("fastslam_old", copy)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def one_round(old_class, stream) -> tuple[float, float]:
    """CPU seconds of this tree's filter and of the old one over the stream, stepped in turn."""
    versions = [cls(stream.sensor, stream.clutter, stream.odometry_noise,
                   np.random.default_rng(0), n_particles=500, initial_pose=stream.initial_pose)
               for cls in (FastSLAM2, old_class)]
    seconds = [0.0, 0.0]
    for i, step in enumerate(stream):
        poses = [None, None]
        for which in ((0, 1) if i % 2 else (1, 0)):
            f = versions[which]
            start = time.process_time()
            f.predict(step.odometry, step.dt_s)
            f.update(step.z)
            poses[which] = f.pose()
            seconds[which] += time.process_time() - start
        for new, old in zip(poses[0], poses[1], strict=True):
            if not np.array_equal(new, old):
                raise SystemExit(f"step {i}: the poses differ: {new} against {old}")
        if i % RESTART_EVERY_STEPS == RESTART_EVERY_STEPS - 1:
            for f in versions:
                f.restart()
    return seconds[0], seconds[1]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("old", help="an older filters/fastslam.py")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    stream = make_stream("brooks-bailey", seed=1, clutter_level=2, n_steps=args.steps)
    with tempfile.TemporaryDirectory() as directory:
        old = load_module(args.old, directory)
        one_round(old.FastSLAM2, make_stream("brooks-bailey", seed=1, clutter_level=2,
                                             n_steps=20))  # warm-up: both compiled and loaded
        ratios = []
        for r in range(args.rounds):
            new_s, old_s = one_round(old.FastSLAM2, stream)
            ratios.append(new_s / old_s)
            print(f"round {r}: this tree {1e6 * new_s / len(stream):.1f} us a step, old "
                  f"{1e6 * old_s / len(stream):.1f} us, ratio {ratios[-1]:.3f}")
    print(f"ratio this tree / old: median {statistics.median(ratios):.3f} "
          f"({min(ratios):.3f}-{max(ratios):.3f}), {len(stream)} steps, every pose equal")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
