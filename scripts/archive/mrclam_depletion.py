"""Issue 16 item 2: particle depletion of FASTSLAM over a whole MRCLAM recording, against
HYBRID's local maps (which restart at every fusion).

For each robot, plays FASTSLAM and HYBRID (fusion every 10 s) over the recording and records at
every resampling decision the effective sample size ratio ``N_eff / P`` (the filter's own
``ess_ratio``), and the number of *distinct ancestors*: how many of the particles present at the
start (FASTSLAM) or at the last restart of the local map (HYBRID) still have descendants. One
distinct ancestor means every particle shares one history: the filter's spread then only
describes the motion since the lineages coalesced, whatever the true uncertainty (BB 5.3: the
over-confidence that makes FASTSLAM fail). The resampling indices are recomputed from a copy of
the filter's generator state, so the filter runs exactly as it does without this script.

Usage: ``python scripts/archive/mrclam_depletion.py DATA_DIR [--robots 1,2,3,4,5] [--particles 200]
[--seed 0]``.

Supports docs/results/real_data.md, "HYBRID, robots 1-5, seeds 0-2, 200 particles, fusion every 10
s, the loader's defaults".
The command behind it::

    python scripts/archive/mrclam_depletion.py .../MRCLAM_Dataset7
"""

from __future__ import annotations

import argparse
import copy
import logging

import numpy as np

from slam_gym.envs.mrclam import mrclam_stream
from slam_gym.episode import Episode
from slam_gym.evaluation.core import filter_rng
from slam_gym.systems import make_system

logger = logging.getLogger(__name__)

FUSION_INTERVAL_STEPS = 100


class AncestorTracker:
    """Follows the resampling of a :class:`filters.fastslam.FastSLAM2` (without changing it)."""

    def __init__(self, filt):
        self.filt = filt
        self.ancestors = np.arange(filt.n_particles)
        self.samples = []  # (t, ess_ratio, distinct ancestors) at each resampling decision
        original = filt._maybe_resample
        original_restart = filt.restart

        def maybe_resample():
            w = filt.weights
            n_eff = 1.0 / np.sum(w * w)
            if n_eff < filt.resample_threshold * filt.n_particles:
                rng = copy.deepcopy(filt.rng)  # the draw the filter is about to make
                P = filt.n_particles
                positions = (rng.random() + np.arange(P)) / P
                cdf = np.cumsum(w)
                cdf[-1] = 1.0
                idx = np.minimum(np.searchsorted(cdf, positions, side="right"), P - 1)
                self.ancestors = self.ancestors[idx]
            original()
            self.samples.append((self.t, filt._ess_ratio, len(np.unique(self.ancestors))))

        def restart():
            original_restart()
            self.ancestors = np.arange(filt.n_particles)

        filt._maybe_resample = maybe_resample
        filt.restart = restart
        self.t = 0.0


def run(stream, name, seed, particles):
    system = make_system(name, stream, filter_rng(seed), n_particles=particles)
    filt = system.front_end if name == "hybrid" else system.estimator
    tracker = AncestorTracker(filt)
    episode = Episode(system, stream, record_trace=True)
    at_fusion = []  # HYBRID: distinct ancestors of each local map when it is fused
    while not episode.done:
        for _ in range(FUSION_INTERVAL_STEPS):
            if episode.advance(1) == 0:
                break
            tracker.t = episode.t_s
        if name == "hybrid":
            at_fusion.append(len(np.unique(tracker.ancestors)))
            episode.fuse()
    s = np.asarray(tracker.samples, dtype=float)
    out = {
        "ess_ratio_median": float(np.median(s[:, 1])),
        "ess_ratio_below_0.1": float(np.mean(s[:, 1] < 0.1)),
        "distinct_ancestors_at_end": int(s[-1, 2]) if name == "fastslam" else None,
    }
    if at_fusion:  # HYBRID: each local map's lineages when it is fused
        a = np.asarray(at_fusion)
        out["ancestors_at_fusion_median"] = float(np.median(a))
        out["local_maps_with_1_ancestor"] = float(np.mean(a == 1))
        out["local_maps_with_at_most_5"] = float(np.mean(a <= 5))
    else:  # FASTSLAM: lineages left since the start
        for t in (10.0, 60.0, 300.0):
            past = s[s[:, 0] >= t]
            out[f"distinct_ancestors_at_{t:g}s"] = int(past[0, 2]) if len(past) else -1
    return out, episode


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for robot in [int(r) for r in args.robots.split(",")]:
        stream = mrclam_stream(args.data, robot)
        for name in ("fastslam", "hybrid"):
            out, episode = run(stream, name, args.seed, args.particles)
            nees = np.asarray(episode.trace.nees, dtype=float)
            out["anees"] = float(np.mean(nees))
            logger.info("robot %d %s: %s", robot, name, ", ".join(
                f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in out.items()))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
