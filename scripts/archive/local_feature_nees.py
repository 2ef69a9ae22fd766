"""Feature NEES (2 dof) of FastSLAM's converted local maps at BB's fusion points, on the simulator.

Usage: python scripts/archive/local_feature_nees.py LEVELS SEEDS N_STEPS [N_PARTICLES]
e.g.   python scripts/archive/local_feature_nees.py 0,3 4 2000

FastSLAM 2.0 with the true associations (so that every converted feature has a known landmark)
over BB's path, restarted every 100 steps by :func:`slam_gym.local_consistency.local_maps`; at
every fusion each converted feature's mean and marginal
covariance are compared with its landmark's true position in the frame of the true pose at the
local map's start. SEEDS is a count (seeds 0 .. SEEDS-1). The reference for the same measurement
on MRCLAM is ``scripts/archive/mrclam_optimise_diagnosis.py`` (docs/RESULTS.md, issue 16 item 3).
FastSLAM keeps the filter's default existence clip 0.999, with which its figures in
docs/results/history.md were measured (HYBRID's front-end now uses the float guard,
:data:`filters.fastslam.LOCAL_MAP_MAX_EXISTENCE`; ``scripts/archive/local_pose_nees.py``
measures both).

Supports docs/results/history.md, "optimise() on MRCLAM, step by step to the small-sample factor
(issue 16 items 2, 3)".
The command behind it::

    python scripts/archive/local_feature_nees.py 0,1,2,3 4 2000
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np
from scipy.stats import chi2

from filters.fastslam import FastSLAM2
from filters.geometry import point_to_frame
from slam_gym.local_consistency import local_maps
from slam_gym.world import make_stream

logger = logging.getLogger(__name__)


def feature_nees(level, seed, n_steps, n_particles):
    stream = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=n_steps)
    f = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise,
                  np.random.default_rng([seed, 11]), n_particles=n_particles)
    landmark_of = {}  # the filter's feature id -> true landmark, within one local map
    values = []
    for step, start, at_fusion in local_maps(f, stream, 100, known_association=True):
        for fid, lid in zip(np.asarray(f.last_associations), step.truth.landmark_ids,
                            strict=True):
            if fid >= 0 and lid >= 0:
                landmark_of[int(fid)] = int(lid)
        if not at_fusion:
            continue
        g = f.to_gaussian()
        for k, fid in enumerate(np.asarray(g.ids)):
            if int(fid) in landmark_of:
                truth = point_to_frame(start, stream.landmarks_true[landmark_of[int(fid)]])
                block = slice(3 + 2 * k, 5 + 2 * k)
                error = truth - g.x[block]
                values.append(float(error @ np.linalg.solve(g.P[block, block], error)))
        landmark_of = {}
    return values


def main(argv) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("levels", help="clutter levels, e.g. 0,3")
    parser.add_argument("seeds", type=int, help="a count N: seeds 0..N-1")
    parser.add_argument("n_steps", type=int)
    parser.add_argument("n_particles", nargs="?", type=int, default=500)
    args = parser.parse_args(argv)
    argv = [args.levels]
    levels = [int(x) for x in args.levels.split(",")]
    seeds, n_steps, n_particles = range(args.seeds), args.n_steps, args.n_particles
    v = np.array([x for level in levels for seed in seeds
                  for x in feature_nees(level, seed, n_steps, n_particles)])
    logger.info("%d features at fusion, levels %s, seeds 0-%d, %d particles: NEES median %.2f "
                "(chi-square 2 dof: 1.39), over its 97.5 %% point %.3f, over its 99 %% point %.3f",
                len(v), argv[0], seeds[-1], n_particles, np.median(v),
                np.mean(v > chi2.ppf(0.975, 2)), np.mean(v > chi2.ppf(0.99, 2)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
