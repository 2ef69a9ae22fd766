"""Local-pose NEES of a front-end's local maps at BB's fusion points (#14, docs/RESULTS.md).

Usage: python scripts/archive/local_pose_nees.py FRONT_END LEVELS SEEDS N_STEPS [N_PARTICLES]
           [known]
e.g.   python scripts/archive/local_pose_nees.py fastslam 0,1,2,3 4 1000 500
SEEDS is a count (seeds 0 .. SEEDS-1) or a range FIRST-LAST (inclusive), e.g. 4-11.
FRONT_END is fastslam, fastslam-no-small-sample (the lineage term without the small-sample
factor, ``small_sample_correction=False``), fastslam-no-lineage (BB (7) alone,
``lineage_correction=False``), fastslam-sampled-clutter (the earlier DAS rule,
``sample_clutter=True``, with both corrections) or ekf; ``known`` gives FastSLAM the true
associations. FastSLAM is built as HYBRID's front-end (existence clip
:data:`filters.fastslam.LOCAL_MAP_MAX_EXISTENCE`); a FastSLAM name ending in ``+clip`` keeps the
filter's default clip 0.999 instead (how the figures in docs/results/history.md,
"Local maps at fusion with FastSLAM's 0.999 existence clip", were measured; the current ones in
docs/RESULTS.md, "Local maps at fusion", are without it).

Supports docs/RESULTS.md, "Local maps at fusion: local-pose NEES".
The command behind it::

    PYTHONPATH=. python scripts/archive/local_pose_nees.py fastslam 0,1,2,3 28-43 2000 500
"""

import argparse
import logging
import sys

import numpy as np
from scipy.stats import chi2

from filters.ekf_slam import EKFSLAM
from filters.fastslam import LOCAL_MAP_MAX_EXISTENCE, FastSLAM2
from slam_gym.local_consistency import add_fusion_run_arguments, local_pose_nees_at_fusion
from slam_gym.world import make_stream


def main(argv) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("front_end")
    add_fusion_run_arguments(parser)
    args = parser.parse_args(argv)
    front, n_steps, seeds = args.front_end, args.n_steps, args.seeds
    levels = ",".join(str(level) for level in args.levels)
    n_particles, known = args.n_particles, args.known
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    name = front.removesuffix("+clip")
    max_existence = 0.999 if front.endswith("+clip") else LOCAL_MAP_MAX_EXISTENCE
    values = []
    for level in (int(x) for x in levels.split(",")):
        for seed in seeds:
            s = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=n_steps)
            if name in ("fastslam", "fastslam-no-small-sample", "fastslam-no-lineage",
                        "fastslam-sampled-clutter"):
                f = FastSLAM2(s.sensor, s.clutter, s.odometry_noise,
                              np.random.default_rng([seed, 11]), n_particles=n_particles,
                              sample_clutter=name == "fastslam-sampled-clutter",
                              lineage_correction=name != "fastslam-no-lineage",
                              small_sample_correction=name != "fastslam-no-small-sample",
                              max_existence=max_existence)
            elif front == "ekf":
                f = EKFSLAM(s.sensor, s.clutter, s.odometry_noise)
            else:
                raise ValueError(f"front_end={front!r} is invalid: must be fastslam, "
                                 "fastslam-no-small-sample, fastslam-no-lineage, "
                                 "fastslam-sampled-clutter (each optionally +clip) or ekf")
            values.append(local_pose_nees_at_fusion(f, s, 100, known))
    v = np.concatenate(values)
    logging.getLogger(__name__).info(
        "%s levels %s seeds %d-%d, %d steps, %d particles, known=%s: %d fusions, "
        "outside the 95 %% band %.3f (over-confident %.3f, under-confident %.3f), worst %.3g",
        front, levels, seeds[0], seeds[-1], n_steps, n_particles, known, len(v),
        np.mean((v < lo) | (v > hi)), np.mean(v > hi), np.mean(v < lo), v.max(),
    )
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(main(sys.argv[1:]))
