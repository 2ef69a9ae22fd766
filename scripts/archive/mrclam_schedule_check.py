"""Issue 16 item 3: the MRCLAM runs where optimising after every fusion ends worse than never.

Usage: python scripts/archive/mrclam_schedule_check.py DATA_DIR [--robots 1,2,3,4,5] [--seeds 0,1,2]
[--particles 200]

Plays HYBRID over each robot and seed on BB's 10 s schedule (as ``reproduce mrclam`` does) three
ways: never optimising, never optimising with 1e-6 (m, rad) of Gaussian noise added to the global
state after every fusion (a perturbation far below any physical meaning: if the back-end's
associations were numerically chaotic, it alone would move the map error), and optimising after
every fusion. Per run it reports the final map error of each, and for ``never`` and
``every-fusion`` the largest global heading error at a fusion and the first fusion where it
exceeds 0.2 rad.

Supports docs/results/history.md, "optimise() on MRCLAM, step by step to the small-sample factor
(issue 16 items 2, 3)".
The command behind it::

    python scripts/archive/mrclam_schedule_check.py .../MRCLAM_Dataset7
"""

from __future__ import annotations

import argparse
import logging

import numpy as np

from filters.geometry import wrap_angle
from slam_gym.envs.mrclam import mrclam_stream
from slam_gym.episode import Episode
from slam_gym.evaluation.core import filter_rng
from slam_gym.systems import make_system

logger = logging.getLogger(__name__)

FUSION_INTERVAL_STEPS = 100  # 10 s at 0.1 s steps (BB)
NOISE = 1e-6
HEADING_LIMIT_RAD = 0.2


def play(stream, seed, particles, mode, noise_rng=None):
    """Final map error and the global heading error (rad) at every fusion."""
    system = make_system("hybrid", stream, filter_rng(seed), n_particles=particles)
    episode = Episode(system, stream, record_trace=False)
    headings = []
    while not episode.done:
        episode.advance(FUSION_INTERVAL_STEPS)
        episode.fuse()
        if mode == "every-fusion":
            episode.optimise()
        elif mode == "perturbed":
            back = system.back_end
            back.x = back.x + noise_rng.normal(0.0, NOISE, size=np.shape(back.x))
        origin, _ = system.back_end.origin()
        headings.append(abs(wrap_angle(episode.last_step.truth.pose[2] - origin[2])))
    return episode.map_score().map_error_m, np.asarray(headings)


def first_above(headings) -> int:
    above = np.flatnonzero(headings > HEADING_LIMIT_RAD)
    return int(above[0]) if above.size else -1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--particles", type=int, default=200)
    args = parser.parse_args(argv)
    rows = []
    for robot in [int(r) for r in args.robots.split(",")]:
        stream = mrclam_stream(args.data, robot)
        for seed in [int(s) for s in args.seeds.split(",")]:
            never, h_never = play(stream, seed, args.particles, "never")
            perturbed, _ = play(stream, seed, args.particles, "perturbed",
                                np.random.default_rng([robot, seed, 99]))
            every, h_every = play(stream, seed, args.particles, "every-fusion")
            rows.append((never, perturbed, every, first_above(h_never) == first_above(h_every)))
            logger.info(
                "robot %d seed %d: map error never %.3f, perturbed %.3f, every-fusion %.3f; "
                "heading error max %.2f / %.2f rad, first above %.1f rad at fusion %d / %d",
                robot, seed, never, perturbed, every, h_never.max(), h_every.max(),
                HEADING_LIMIT_RAD, first_above(h_never), first_above(h_every))
    r = np.array(rows, dtype=float)
    logger.info(
        "%d runs: largest |perturbed - never| %.4f m; every-fusion worse than never in %d "
        "(by %s m); heading first above the limit at the same fusion in both in %d",
        len(r), np.max(np.abs(r[:, 1] - r[:, 0])), np.sum(r[:, 2] > r[:, 0]),
        np.round(np.sort((r[:, 2] - r[:, 0])[r[:, 2] > r[:, 0]]), 3).tolist(), int(r[:, 3].sum()))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
