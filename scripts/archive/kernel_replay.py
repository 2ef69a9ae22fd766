"""The compiled FastSLAM scan timed on captured scans, two versions side by side (issue 27).

Usage: python scripts/archive/kernel_replay.py capture SCANS.pkl
       python scripts/archive/kernel_replay.py time SCANS.pkl KERNEL_A.py KERNEL_B.py [...]
e.g.   git show c92c4a3:filters/fastslam_kernel.py > /tmp/old_kernel.py
       python scripts/archive/kernel_replay.py time /tmp/scans.pkl /tmp/old_kernel.py \\
           filters/fastslam_kernel.py

``capture`` plays 60 ``fixed-10s`` decisions of ``HybridSLAMEnv(n_particles=500)`` on world 5
at clutter level 2 and world 6 at level 3 and keeps every third call of ``scan_update`` with
copies of its arguments. ``time`` loads each kernel file as a module of its own (a fresh copy
in a temporary directory, so numba compiles it there and no cache is shared), replays every
captured scan through each version in turn, 9 rounds after one warm-up, and prints each
version's median time per scan, its median ratio to the first, and whether all its outputs
equal the first's to the bit.

Supports docs/PERFORMANCE.md, "The code of 15bcb7d (2026-11-25 evening, the slower machine): five
more bit-identical speed-ups, and a sixth".
The command behind it::

    python scripts/archive/kernel_replay.py capture /tmp/scans.pkl
    python scripts/archive/kernel_replay.py time /tmp/scans.pkl OLD_KERNEL.py \
        filters/fastslam_kernel.py
"""

from __future__ import annotations

import argparse
import importlib.util
import pickle
import shutil
import sys
import tempfile
import time

import numpy as np


def capture(path: str) -> int:
    import filters.fastslam as fastslam
    import policies
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    calls = []
    kernel = fastslam.scan_update

    def keep(*args):
        calls.append([a.copy() if isinstance(a, np.ndarray) else a for a in args])
        return kernel(*args)

    fastslam.scan_update = keep
    for level, seed in ((2, 5), (3, 6)):
        env = HybridSLAMEnv(n_particles=500, clutter_level=level)
        policy = policies.make("fixed-10s")
        obs, info = env.reset(seed=seed)
        policy.reset()
        for _ in range(60):
            obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
            if terminated or truncated:
                break
    fastslam.scan_update = kernel
    scans = calls[::3]
    with open(path, "wb") as f:
        pickle.dump(scans, f)
    print(f"{len(scans)} scans -> {path}")
    return 0


def _load(path: str, name: str):
    copy = f"{tempfile.mkdtemp()}/{name}.py"
    shutil.copy(path, copy)
    spec = importlib.util.spec_from_file_location(name, copy)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module.scan_update


def _replay(kernel, scans):
    outputs, total_s = [], 0.0
    for scan in scans:
        args = [a.copy() if isinstance(a, np.ndarray) else a for a in scan]
        start = time.perf_counter()
        kernel(*args)
        total_s += time.perf_counter() - start
        outputs.append(args)
    return total_s / len(scans), outputs


def _equal(a, b) -> bool:
    return all(
        np.array_equal(x, y, equal_nan=True) if isinstance(x, np.ndarray) else True
        for scan_a, scan_b in zip(a, b, strict=True) for x, y in zip(scan_a, scan_b, strict=True))


def time_versions(scans_path: str, kernel_paths: list[str]) -> int:
    with open(scans_path, "rb") as f:
        scans = pickle.load(f)
    kernels = [_load(p, f"kernel_version_{i}") for i, p in enumerate(kernel_paths)]
    for kernel in kernels:
        _replay(kernel, scans)  # compile and warm up
    times = np.zeros((len(kernels), 9))
    outputs = [None] * len(kernels)
    for r in range(times.shape[1]):
        for i, kernel in enumerate(kernels):
            times[i, r], outputs[i] = _replay(kernel, scans)
    for i, path in enumerate(kernel_paths):
        print(f"{path}: {np.median(times[i]) * 1e3:.4f} ms a scan, "
              f"{np.median(times[i] / times[0]):.3f} of the first, "
              f"outputs equal to the first's: {_equal(outputs[0], outputs[i])}")
    return 0


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("capture", help="capture scans").add_argument("scans")
    timing = commands.add_parser("time", help="time kernel versions on captured scans")
    timing.add_argument("scans")
    timing.add_argument("kernels", nargs="+")
    args = parser.parse_args(argv)
    if args.command == "capture":
        return capture(args.scans)
    return time_versions(args.scans, args.kernels)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
