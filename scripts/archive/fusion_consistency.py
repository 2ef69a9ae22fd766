"""Why the sub-map systems fail after fusions (docs/RESULTS.md): consistency at every fusion.

Usage: python scripts/archive/fusion_consistency.py SEEDS [NOISE_SCALE] [N_STEPS]
e.g.   python scripts/archive/fusion_consistency.py 0-9          # BB's path as is
       python scripts/archive/fusion_consistency.py 0-5 0.01     # every noise std times 0.01

Runs ``ekf-submap`` on ``brooks-bailey`` at clutter level 0 with BB's fusion every 100 steps,
to the end of the path (no stop at BB's failure), with every noise std of the world (odometry
fractions and floors, range, bearing) multiplied by NOISE_SCALE. At each fusion it records, with
the simulator's truth ids (the votes of :class:`slam_gym.metrics.FeatureTruth`):

* the global-pose NEES just before and just after the fusion, and the heading part of the latter;
* the full-state NEES (pose and confirmed features) of the fused local map in its own frame
  (origin: the true pose at the previous fusion);
* fusion associations whose two features stand for different landmarks (wrong) and local
  features of an already mapped landmark left unmatched (missed);
* a *synthetic* back-end: a second :class:`filters.back_ends.GlobalMap` fed, at each fusion, the
  same local map's covariance and feature set with its mean redrawn around the truth,
  ``x ~ N(x_true, P_L)``: consistent local maps by construction, so only the back-end (fusion
  equations and their linearisation) can make it inconsistent. Its pose NEES after each fusion.

Supports docs/RESULTS.md, "Why the sub-map systems fail after fusions".
The command behind it::

    PYTHONPATH=. python scripts/archive/fusion_consistency.py 0-9
"""

import argparse
import logging
import sys

import numpy as np
from scipy.stats import chi2

from filters.back_ends import GlobalMap
from filters.geometry import point_to_frame, relative, wrap_angle
from filters.types import GaussianMap
from slam_gym.episode import Episode
from slam_gym.evaluation.core import filter_rng
from slam_gym.metrics import nees
from slam_gym.scenarios import get_scenario
from slam_gym.systems import make_system
from slam_gym.world import make_stream

logger = logging.getLogger(__name__)

NOISE_FIELDS = ("v_noise_fraction", "omega_noise_fraction", "v_noise_floor_mps",
                "omega_noise_floor_radps", "range_std_m", "bearing_std_rad")
BAND_3 = chi2.ppf([0.025, 0.975], 3)


def parse_seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = (int(x) for x in text.split("-"))
        return list(range(lo, hi + 1))
    return [int(x) for x in text.split(",")]


def scaled_stream(seed: int, noise_scale: float, n_steps):
    if not noise_scale > 0.0:
        raise ValueError(f"noise_scale={noise_scale!r} is invalid: must be positive")
    base = get_scenario("brooks-bailey")
    overrides = {k: getattr(base, k) * noise_scale for k in NOISE_FIELDS}
    if n_steps is not None:
        overrides["n_steps"] = n_steps
    return make_stream("brooks-bailey", seed=seed, clutter_level=0, **overrides)


def state_nees(x, P, x_true) -> tuple[float, int]:
    """NEES of a [pose, features] state (heading wrapped); features without truth left out."""
    e = np.asarray(x_true, dtype=float) - x
    e[2] = wrap_angle(e[2])
    ok = np.isfinite(e)
    return float(e[ok] @ np.linalg.solve(P[np.ix_(ok, ok)], e[ok])), int(ok.sum())


def local_truth(origin_true, pose_true, landmarks):
    """The true local state: pose and landmark points in the frame of the true origin."""
    parts = [relative(origin_true, pose_true)]
    parts += [point_to_frame(origin_true, p) for p in landmarks]
    return np.concatenate(parts)


def run(seed: int, noise_scale: float, n_steps) -> list[dict]:
    stream = scaled_stream(seed, noise_scale, n_steps)
    truth_xy = stream.landmarks_true
    system = make_system("ekf-submap", stream, filter_rng(seed))
    episode = Episode(system, stream, record_trace=False)
    synthetic = GlobalMap(initial_pose=stream.initial_pose)
    rng = np.random.default_rng([seed, 2024])
    landmark_of: dict[int, int] = {}  # feature id -> true landmark (frozen at its fusion)
    origin_true = np.asarray(stream.initial_pose, dtype=float)
    rows = []
    while not episode.done:
        episode.advance(100)
        pose_true = np.asarray(episode.last_step.truth.pose, dtype=float)
        mean, cov = system.pose()
        nees_before = nees(pose_true, mean, cov)
        local = system.front_end.to_gaussian()
        lms = [episode.feature_truth.landmark_of(int(i)) for i in local.ids]
        nan = np.full(2, np.nan)
        x_true = local_truth(origin_true, pose_true, [truth_xy[k] if k >= 0 else nan for k in lms])
        local_value, local_dof = state_nees(local.x, local.P, x_true)
        mapped = {landmark_of.get(int(g), -1) for g in system.back_end.ids}
        report = episode.fuse()
        for i, k in zip(local.ids, lms, strict=True):
            landmark_of.setdefault(int(i), k)
        pairs = [(lo, gl) for lo, gl in report.id_map.items() if lo != gl]
        wrong = sum(landmark_of[lo] != landmark_of[gl] for lo, gl in pairs)
        missed = sum(lo == gl and landmark_of[lo] in mapped and landmark_of[lo] >= 0
                     for lo, gl in report.id_map.items())
        mean, cov = system.pose()
        e_heading = wrap_angle(pose_true[2] - mean[2])
        synthetic_nees = fuse_synthetic(synthetic, local, lms, x_true, rng, pose_true)
        rows.append(dict(
            seed=seed, iteration=episode.iteration, nees_before=nees_before,
            nees_after=nees(pose_true, mean, cov), heading_nees=float(e_heading**2 / cov[2, 2]),
            local_nees=local_value, local_dof=local_dof, matched=len(pairs), wrong=wrong,
            missed=missed, synthetic_nees=synthetic_nees,
            failed=episode.failure.failed,
        ))
        origin_true = pose_true
    return rows


def fuse_synthetic(back_end, local, lms, x_true, rng, pose_true) -> float:
    """Fuse ``N(x_true, P_L)`` (features with a true landmark) into ``back_end``; its pose NEES."""
    keep = [k for k, lm in enumerate(lms) if lm >= 0]
    idx = np.concatenate([np.arange(3), (3 + 2 * np.array(keep, dtype=np.int64)[:, None]
                                         + np.arange(2)).ravel()])
    P = local.P[np.ix_(idx, idx)]
    x = x_true[idx] + np.linalg.cholesky(P + 1e-12 * np.eye(len(idx))) @ rng.standard_normal(
        len(idx))
    x[2] = wrap_angle(x[2])
    ids = np.asarray(local.ids)[keep]
    back_end.fuse(GaussianMap(x=x, P=P, ids=ids, existence=np.ones(len(ids))))
    return nees(pose_true, back_end.x[:3], back_end.P[:3, :3])


def outside(values, lo, hi) -> float:
    values = np.asarray(values, dtype=float)
    return float(np.mean((values < lo) | (values > hi)))


def summarise(rows: list[dict], label: str) -> None:
    after = np.array([r["nees_after"] for r in rows])
    before = np.array([r["nees_before"] for r in rows])
    synth = np.array([r["synthetic_nees"] for r in rows])
    local_out = [not (chi2.ppf(0.025, r["local_dof"]) <= r["local_nees"]
                      <= chi2.ppf(0.975, r["local_dof"])) for r in rows]
    logger.info(
        "%s: %d fusions; associations %d matched, %d wrong, %d missed | global pose NEES after "
        "fusion: median %.1f, outside the 95 %% band %.2f, heading part median %.1f, rose across "
        "the fusion %.2f | local maps full-state NEES outside the band %.2f | synthetic "
        "consistent local maps: pose NEES median %.1f, outside the band %.2f",
        label, len(rows), sum(r["matched"] for r in rows), sum(r["wrong"] for r in rows),
        sum(r["missed"] for r in rows), np.median(after), outside(after, *BAND_3),
        np.median([r["heading_nees"] for r in rows]), np.mean(after > before),
        np.mean(local_out), np.median(synth), outside(synth, *BAND_3),
    )


def main(argv) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("seeds", help="a count N (seeds 0..N-1) or a range FIRST-LAST")
    parser.add_argument("noise_scale", nargs="?", type=float, default=1.0)
    parser.add_argument("n_steps", nargs="?", type=int, default=None)
    args = parser.parse_args(argv)
    argv = [args.seeds]
    seeds = parse_seeds(args.seeds)
    noise_scale, n_steps = args.noise_scale, args.n_steps
    everything = []
    for seed in seeds:
        rows = run(seed, noise_scale, n_steps)
        first_fail = next((r["iteration"] for r in rows if r["failed"]), None)
        summarise(rows, f"scale {noise_scale} seed {seed} (BB failure by fusion at {first_fail})")
        everything += rows
    summarise(everything, f"scale {noise_scale} seeds {argv[0]}")
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(main(sys.argv[1:]))
