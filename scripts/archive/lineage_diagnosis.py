"""Local maps at fusion against their lineage count (#14 item 2, docs/RESULTS.md).

Usage: python scripts/archive/lineage_diagnosis.py LEVELS SEEDS N_STEPS [N_PARTICLES] [known]
e.g.   python scripts/archive/lineage_diagnosis.py 0,1,2,3 0-3 1000 500 known

Runs FastSLAM 2.0 over BB's path with :func:`slam_gym.local_consistency.local_maps` (restart
every 100 steps, the same random streams as scripts/archive/local_pose_nees.py) and, at every
fusion, converts the local map three ways: by BB (7) alone, with the lineage term, and with the
lineage term and the small-sample factor (the filtering is the same; only the Gaussian differs).
Reports the median number of lineages (distinct ancestors at the restart) and of effective
lineages (1 / sum of squared lineage weights) at fusion, the per-component mean square error of
the local pose over its reported variance, the share of over-confident fusions by lineage count,
and by the effective degrees of freedom ``nu`` of :func:`filters.conversion.small_sample_factor`.
SEEDS is a count or a range FIRST-LAST (inclusive).
FastSLAM keeps the filter's default existence clip 0.999, with which its figures in
docs/results/history.md were measured (HYBRID's front-end now uses the float guard,
:data:`filters.fastslam.LOCAL_MAP_MAX_EXISTENCE`; ``scripts/archive/local_pose_nees.py``
measures both).

Supports docs/results/history.md, "Local maps at fusion with FastSLAM's 0.999 existence clip (issue
14 item 2)".
The command behind it::

    python scripts/archive/lineage_diagnosis.py 0,1,2,3 0-3 1000 500 known
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np
from scipy.stats import chi2

from filters.fastslam import FastSLAM2
from filters.geometry import relative, wrap_angle
from slam_gym.local_consistency import add_fusion_run_arguments, local_maps
from slam_gym.world import make_stream

logger = logging.getLogger(__name__)
BINS = ((1, 5), (5, 10), (10, 20), (20, 50), (50, 10**9))
NU_BINS = ((0, 5), (5, 10), (10, 20), (20, 50), (50, np.inf))


CONVERSIONS = (("BB (7) alone", False, False), ("with the lineage term", True, False),
               ("with the lineage term and the small-sample factor", True, True))


def fusion_records(level, seed, n_steps, n_particles, known):
    """Per fusion: lineage count, effective lineage count, ``nu``, then for each of
    :data:`CONVERSIONS` the NEES and the squared error over the variance of x, y and heading."""
    stream = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=n_steps)
    f = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise,
                  np.random.default_rng([seed, 11]), n_particles=n_particles)
    rows = []
    for step, start, at_fusion in local_maps(f, stream, 100, known):
        if not at_fusion:
            continue
        _, group = np.unique(f.lineages, return_inverse=True)
        mass = np.bincount(group, weights=f.weights)
        row = [len(mass), 1.0 / np.sum(mass**2)]
        covs = []
        for _, lineage, small_sample in CONVERSIONS:
            f.lineage_correction, f.small_sample_correction = lineage, small_sample
            g = f.to_gaussian()
            error = relative(start, step.truth.pose) - g.x[:3]
            error[2] = wrap_angle(error[2])
            covs.append(g.P[:3, :3])
            row += [float(error @ np.linalg.solve(covs[-1], error)),
                    *(error**2 / np.diag(covs[-1]))]
        f.lineage_correction = f.small_sample_correction = True
        factor = covs[2][0, 0] / covs[1][0, 0]  # small_sample_factor = nu / (nu - 4)
        row.insert(2, 4.0 * factor / (factor - 1.0) if factor > 1.0 else np.inf)
        rows.append(row)
    return rows


def main(argv) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_fusion_run_arguments(parser)
    args = parser.parse_args(argv)
    levels, seeds, n_steps = args.levels, args.seeds, args.n_steps
    n_particles, known = args.n_particles, args.known
    r = np.array([row for level in levels for seed in seeds
                  for row in fusion_records(level, seed, n_steps, n_particles, known)])
    hi = chi2.ppf(0.975, 3)
    lineages, nu = r[:, 0], r[:, 2]
    logger.info("%d fusions, %d particles, known=%s: median lineages at fusion %.0f, "
                "effective lineages %.1f, nu %.1f", len(r), n_particles, known,
                np.median(lineages), np.median(r[:, 1]), np.median(nu))
    for k, (name, _, _) in enumerate(CONVERSIONS):
        col = 3 + 4 * k
        nees = r[:, col]
        logger.info("%s: over the band %.3f; mean square error / variance (x, y, heading) %s",
                    name, np.mean(nees > hi), np.round(r[:, col + 1:col + 4].mean(axis=0), 2))
        for label, key, bins in (("lineages", lineages, BINS), ("nu", nu, NU_BINS)):
            for lo_n, hi_n in bins:
                in_bin = (key >= lo_n) & ((key < hi_n) | (hi_n == np.inf))
                if in_bin.any():
                    logger.info("  %s %g-%g: %d fusions, over the band %.3f", label, lo_n,
                                hi_n, in_bin.sum(), np.mean(nees[in_bin] > hi))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
