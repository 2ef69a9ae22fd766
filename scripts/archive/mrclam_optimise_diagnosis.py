"""Issue 16 item 3: why ``optimise()`` can make the MRCLAM map worse (docs/RESULTS.md).

Plays HYBRID (or EKF sub-mapping) over MRCLAM robots on BB's 10 s schedule without optimising,
keeps the truth of every stored sub-map (the true pose at each fusion, and for each local feature
the landmark most of its observations came from), then solves CM (12) over the stored sub-maps
once at the end and reports:

* **sub-map consistency** against the truth: the NEES of each sub-map's end pose (3 dof) and of
  each of its features (2 dof) under the sub-map's own covariance -- over-confident sub-maps have
  NEES far above the dof;
* **associations**: a local feature whose landmark differs from the landmark of the global
  feature the fusion mapped it to (``StoredSubmap.id_map``) is a *wrong association*, frozen
  into the optimiser's problem;
* **residuals at the optimum**: each feature's and each end pose's Mahalanobis residual
  ``e^T P^-1 e`` (its own marginal), the share of the total cost CM (12) carried by the largest
  ones and by the wrong associations;
* the map error of the optimum with the plain cost and with a robust kernel
  (:mod:`filters.optimiser`, ``robust=``), and with the wrong associations removed (an oracle,
  for the diagnosis only: each wrongly associated local feature marginalised out of its sub-map
  unless it is its global feature's only measurement; ``oracle_dropped`` counts them), and
  after re-associating at the optimum without the truth (:func:`reassociated`, two rounds):
  a local feature moves to another global feature when the move gains 100:1 likelihood odds
  (``map_error_reassociated``), or any gain at all (``..._greedy``).

Usage: ``python scripts/archive/mrclam_optimise_diagnosis.py DATA_DIR [--robots 1,2,3,4,5]
[--system hybrid] [--particles 200] [--seed 0] [--max-steps N]``.

Supports docs/results/history.md, "optimise() on MRCLAM, step by step to the small-sample factor
(issue 16 items 2, 3)".
The command behind it::

    python scripts/archive/mrclam_optimise_diagnosis.py .../MRCLAM_Dataset7 --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from collections import Counter, defaultdict

import numpy as np

from filters.fastslam import GATE_CHI2_999
from filters.geometry import (
    point_to_frame,
    relative,
    transform_point,
    transform_point_jacobians,
    wrap_angle,
)
from filters.submap_optimise import build_submap_problem, floored_covariance
from slam_gym.envs.mrclam import mrclam_stream
from slam_gym.episode import Episode
from slam_gym.evaluation.core import filter_rng
from slam_gym.systems import make_system

logger = logging.getLogger(__name__)

FUSION_INTERVAL_STEPS = 100  # 10 s at 0.1 s steps (BB)
REASSOCIATION_MARGIN = 2.0 * np.log(100.0)  # a move needs 100:1 likelihood odds
REASSOCIATION_ROUNDS = 2


@dataclasses.dataclass
class SubmapTruth:
    pose_index: int  # origin index
    local_landmark: dict  # local id -> true landmark (-1 clutter)


def play(stream, system_name, seed, particles):
    """The run without optimisation; per sub-map the truth of its local features, and the true
    fusion poses (index 0 = the initial pose)."""
    system = make_system(system_name, stream, filter_rng(seed), n_particles=particles)
    episode = Episode(system, stream, record_trace=False)
    votes: dict[int, Counter] = defaultdict(Counter)
    true_poses = [np.asarray(stream.initial_pose, dtype=float)]
    local_truth = []
    while not episode.done:
        for _ in range(FUSION_INTERVAL_STEPS):
            if episode.advance(1) == 0:
                break
            assoc = np.asarray(system.last_associations)
            tids = episode.last_step.truth.landmark_ids
            if len(assoc) == len(tids):
                for f, t in zip(assoc, tids, strict=True):
                    if f >= 0:
                        votes[int(f)][int(t)] += 1
        local = system.front_end.to_gaussian()
        truth = {int(i): (votes[int(i)].most_common(1)[0][0] if votes[int(i)] else -1)
                 for i in np.asarray(local.ids)}
        episode.fuse()
        votes.clear()
        local_truth.append(truth)
        true_poses.append(np.asarray(episode.last_step.truth.pose, dtype=float))
    return episode, np.asarray(true_poses), local_truth


def blocks(g):
    """(slice, kind, local id) of each block of a sub-map Gaussian: the end pose, then features."""
    out = [(slice(0, 3), "pose", -1)]
    for k, lid in enumerate(np.asarray(g.ids, dtype=np.int64)):
        out.append((slice(3 + 2 * k, 5 + 2 * k), "feature", int(lid)))
    return out


def mahalanobis(e, P):
    return float(e @ np.linalg.solve(floored_covariance(P), e))


def analyse(episode, stream, true_poses, local_truth, kernels):
    system = episode.system
    landmarks = stream.landmarks_true
    global_truth = {g: episode.feature_truth.landmark_of(g) for g in system.back_end.ids}
    rows = []  # per block: submap, kind, truth NEES, wrong association, dof
    for s, (sub, truth) in enumerate(zip(system.submaps, local_truth, strict=True)):
        g = sub.gaussian
        x = np.asarray(g.x, dtype=float)
        o, e = sub.origin_index, sub.end_index
        for sl, kind, lid in blocks(g):
            P = np.asarray(g.P)[sl, sl]
            if kind == "pose":
                err = x[sl] - relative(true_poses[o], true_poses[e])
                err[2] = wrap_angle(err[2])
                rows.append((s, kind, lid, -1, False, mahalanobis(err, P)))
                continue
            tid = truth.get(lid, -1)
            gid = sub.id_map[lid]
            gt = global_truth.get(gid, episode.feature_truth.landmark_of(gid))
            wrong = tid >= 0 and gt >= 0 and tid != gt
            nees_f = (mahalanobis(x[sl] - point_to_frame(true_poses[o], landmarks[tid]), P)
                      if tid >= 0 else np.nan)
            rows.append((s, kind, lid, gid, wrong, nees_f))
    pose_nees = np.array([r[5] for r in rows if r[1] == "pose"])
    feat_nees = np.array([r[5] for r in rows if r[1] == "feature" and np.isfinite(r[5])])
    wrong = [r for r in rows if r[4]]
    n_feat = sum(r[1] == "feature" for r in rows)
    report = {
        "submaps": len(system.submaps),
        "pose_nees_median": float(np.median(pose_nees)),
        "pose_nees_mean": float(np.mean(pose_nees)),
        "pose_nees_over_chi2_99": float(np.mean(pose_nees > 11.34)),
        "feature_nees_median": float(np.median(feat_nees)),
        "feature_nees_mean": float(np.mean(feat_nees)),
        "feature_nees_over_chi2_99": float(np.mean(feat_nees > 9.21)),
        "features": n_feat,
        "wrong_associations": len(wrong),
    }
    # residuals at the optimum of the plain cost, per block
    back = system.back_end
    problem = build_submap_problem(system.submaps, back.initial_pose, back.initial_pose_cov)
    p = problem.problem
    res = p.optimise("gauss-newton")
    r = p.psi(res.tau) - p.r_hat
    start = 0
    contrib = []
    for (sub, _), s in zip(zip(system.submaps, local_truth, strict=True),
                           range(len(system.submaps)), strict=True):
        g = sub.gaussian
        n = len(np.asarray(g.x))
        es = r[start:start + n]
        for sl, kind, lid in blocks(g):
            c = mahalanobis(es[sl], np.asarray(g.P)[sl, sl])
            wrong_b = kind == "feature" and any(
                rr[0] == s and rr[2] == lid and rr[4] for rr in rows)
            contrib.append((c, kind, wrong_b, s, lid))
        start += n
    contrib.sort(key=lambda t: -t[0])
    total = sum(c[0] for c in contrib)
    top = contrib[: max(1, len(contrib) // 50)]  # the largest 2 %
    report |= {
        "cost_total": total,
        "cost_share_top2pct": sum(c[0] for c in top) / total,
        "top2pct_wrong": sum(c[2] for c in top),
        "top2pct_pose": sum(c[1] == "pose" for c in top),
        "top2pct_n": len(top),
        "cost_share_wrong": sum(c[0] for c in contrib if c[2]) / total,
        "residual_median": float(np.median([c[0] for c in contrib])),
    }
    report["map_error_never"] = episode.map_score().map_error_m
    for name, opts in kernels.items():
        report[f"map_error_{name}"] = map_error_after(episode, opts)
    oracle, dropped = without_wrong_associations(system.submaps, rows)
    report["oracle_dropped"] = dropped
    report["map_error_oracle"] = map_error_after(episode, {"robust": None}, submaps=oracle)
    for name, margin in (("reassociated", REASSOCIATION_MARGIN), ("reassociated_greedy", 0.0)):
        submaps, switched = system.submaps, 0
        for _ in range(REASSOCIATION_ROUNDS):
            submaps, n = reassociated(submaps, system.back_end, margin)
            switched += n
        report[f"{name}_switched"] = switched
        report[f"map_error_{name}"] = map_error_after(episode, {"robust": None}, submaps=submaps)
    return report, rows


def reassociated(submaps, back, margin):
    """Re-association at the optimum, without the truth: CM (12) is solved over ``submaps``, and
    a stored local feature moves to another global feature when its squared Mahalanobis distance
    to it (the local feature's covariance turned into the world frame plus the global feature's
    Gauss-Newton marginal) is inside the 99.9 % gate and lower than to its current one by more
    than ``margin``; every global feature keeps at least one measurement. Returns (sub-maps,
    number of local features moved)."""
    sp = build_submap_problem(submaps, back.initial_pose, back.initial_pose_cov)
    res = sp.problem.optimise("gauss-newton")
    gids = np.array(sorted(sp.feature_entity), dtype=np.int64)
    entities = [sp.feature_entity[int(g)] for g in gids]
    global_xy = res.means[entities, :2]
    global_cov = np.array(res.marginals(entities))
    count = Counter(gid for sub in submaps for gid in sub.id_map.values())
    out, moved = [], 0
    for sub in submaps:
        x, P = np.asarray(sub.gaussian.x), np.asarray(sub.gaussian.P)
        origin = res.means[sp.pose_entity[sub.origin_index]]
        R = transform_point_jacobians(origin, np.zeros(2))[1]
        id_map = dict(sub.id_map)
        for k, lid in enumerate(np.asarray(sub.gaussian.ids, dtype=np.int64)):
            block = slice(3 + 2 * k, 5 + 2 * k)
            d = global_xy - transform_point(origin, x[block])
            S = global_cov + R @ P[block, block] @ R.T
            d2 = np.einsum("ni,nij,nj->n", d, np.linalg.inv(S), d)
            current = int(id_map[int(lid)])
            best = int(np.argmin(d2))
            d2_current = d2[int(np.searchsorted(gids, current))]
            if (gids[best] != current and d2[best] < GATE_CHI2_999
                    and d2[best] < d2_current - margin and count[current] > 1):
                count[current] -= 1
                count[int(gids[best])] += 1
                id_map[int(lid)] = int(gids[best])
                moved += 1
        out.append(dataclasses.replace(sub, id_map=id_map))
    return out, moved


def without_wrong_associations(submaps, rows):
    """The stored sub-maps with each wrongly associated local feature marginalised out (its rows
    and columns dropped from the sub-map's Gaussian, its entry from ``id_map``), except where it
    is its global feature's only measurement (the optimiser needs one for every global feature).
    Returns (sub-maps, number of local features dropped). An oracle: it uses the truth."""
    wrong = {(r[0], r[2]) for r in rows if r[4]}
    correct_count = Counter()
    for s, sub in enumerate(submaps):
        for lid, gid in sub.id_map.items():
            if (s, lid) not in wrong:
                correct_count[gid] += 1
    out, dropped = [], 0
    for s, sub in enumerate(submaps):
        g = sub.gaussian
        ids = np.asarray(g.ids, dtype=np.int64)
        keep = [k for k, lid in enumerate(ids)
                if (s, int(lid)) not in wrong or correct_count[sub.id_map[int(lid)]] == 0]
        dropped += len(ids) - len(keep)
        cols = np.r_[0:3, [3 + 2 * k + j for k in keep for j in (0, 1)]].astype(np.int64)
        gaussian = dataclasses.replace(
            g, x=np.asarray(g.x)[cols], P=np.asarray(g.P)[np.ix_(cols, cols)], ids=ids[keep],
            existence=np.asarray(g.existence)[keep])
        out.append(dataclasses.replace(
            sub, gaussian=gaussian, id_map={int(ids[k]): sub.id_map[int(ids[k])] for k in keep}))
    return out, dropped


def map_error_after(episode, opts, submaps=None):
    """Map error after one optimise() with ``opts`` on a copy of the back-end's estimate (over
    ``submaps`` instead of the stored ones if given)."""
    estimator = episode.system.estimator
    back = episode.system.back_end
    saved = (np.array(back.x), np.array(back.P), estimator.submaps)
    if submaps is not None:
        estimator.submaps = submaps
    try:
        estimator.optimise(**opts)
        return episode.map_score().map_error_m
    finally:
        back.x, back.P, estimator.submaps = saved


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--system", default="hybrid")
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--seeds", default="0", help="comma-separated filter seeds")
    parser.add_argument("--max-steps", type=int, default=None)
    args = parser.parse_args(argv)
    kernels = {"plain": {"robust": None}, "huber": {"robust": "huber"},
               "cauchy": {"robust": "cauchy"}}
    reports = []
    for robot in [int(r) for r in args.robots.split(",")]:
        stream = mrclam_stream(args.data, robot, max_steps=args.max_steps)
        for seed in [int(s) for s in args.seeds.split(",")]:
            episode, true_poses, local_truth = play(stream, args.system, seed, args.particles)
            report, _ = analyse(episode, stream, true_poses, local_truth, kernels)
            reports.append(report)
            logger.info("robot %d seed %d: %s", robot, seed,
                        ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                  for k, v in report.items()))
    logger.info("mean over %d runs: %s", len(reports), ", ".join(
        f"{k} {np.mean([r[k] for r in reports]):.4g}" for k in reports[0]))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
