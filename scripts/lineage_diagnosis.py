"""Local maps at fusion against their lineage count (#14 item 2, docs/RESULTS.md).

Usage: python scripts/lineage_diagnosis.py LEVELS SEEDS N_STEPS [N_PARTICLES] [known]
e.g.   python scripts/lineage_diagnosis.py 0,1,2,3 0-3 1000 500 known

Runs FastSLAM 2.0 over BB's path as :func:`slam_gym.local_consistency.local_pose_nees_at_fusion`
does (restart every 100 steps, the same random streams as scripts/local_pose_nees.py) and, at
every fusion, converts the local map both ways: by BB (7) alone and with the lineage term (the
filtering is the same; only the Gaussian differs). Reports the median number of lineages
(distinct ancestors at the restart) at fusion, the per-component mean square error of the local
pose over its reported variance, and the share of over-confident fusions by lineage count.
SEEDS is a count or a range FIRST-LAST (inclusive).
"""

from __future__ import annotations

import logging
import sys

import numpy as np
from scipy.stats import chi2

from filters.fastslam import FastSLAM2
from filters.geometry import relative, wrap_angle
from slam_gym.scenarios import make_stream

logger = logging.getLogger(__name__)
BINS = ((1, 5), (5, 10), (10, 20), (20, 50), (50, 10**9))


def fusion_records(level, seed, n_steps, n_particles, known):
    """Per fusion: lineage count, then for BB (7) alone and with the term the NEES and the
    squared error over the variance of x, y and heading."""
    stream = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=n_steps)
    f = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise,
                  np.random.default_rng([seed, 11]), n_particles=n_particles)
    start = np.asarray(stream.initial_pose, dtype=float).copy()
    rows = []
    for i, step in enumerate(stream):
        f.predict(step.odometry, step.dt_s)
        f.update(step.z, step.truth.landmark_ids if known else None)
        if (i + 1) % 100:
            continue
        row = [len(np.unique(f.lineages))]
        for correction in (False, True):
            f.lineage_correction = correction
            g = f.to_gaussian()
            error = relative(start, step.truth.pose) - g.x[:3]
            error[2] = wrap_angle(error[2])
            cov = g.P[:3, :3]
            row += [float(error @ np.linalg.solve(cov, error)), *(error**2 / np.diag(cov))]
        f.lineage_correction = True
        rows.append(row)
        f.restart()
        start = np.asarray(step.truth.pose, dtype=float).copy()
    return rows


def main(argv) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    levels = [int(x) for x in argv[0].split(",")]
    first, _, last = argv[1].partition("-")
    seeds = range(int(first), int(last) + 1) if last else range(int(first))
    n_steps = int(argv[2])
    n_particles = int(argv[3]) if len(argv) > 3 else 500
    known = len(argv) > 4 and argv[4] == "known"
    r = np.array([row for level in levels for seed in seeds
                  for row in fusion_records(level, seed, n_steps, n_particles, known)])
    hi = chi2.ppf(0.975, 3)
    lineages = r[:, 0]
    logger.info("%d fusions, %d particles, known=%s: median lineages at fusion %.0f",
                len(r), n_particles, known, np.median(lineages))
    for name, col in (("BB (7) alone", 1), ("with the lineage term", 5)):
        nees = r[:, col]
        logger.info("%s: over the band %.3f; mean square error / variance (x, y, heading) %s",
                    name, np.mean(nees > hi), np.round(r[:, col + 1:col + 4].mean(axis=0), 2))
        for lo_n, hi_n in BINS:
            in_bin = (lineages >= lo_n) & (lineages < hi_n)
            if in_bin.any():
                logger.info("  lineages %d-%d: %d fusions, over the band %.3f", lo_n,
                            min(hi_n, 10**4) - 1, in_bin.sum(), np.mean(nees[in_bin] > hi))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
