"""Issue 16 item 4: why HYBRID's sub-map fusion maps Victoria Park trees twice (docs/RESULTS.md).

Plays a sub-map system (``hybrid`` and/or ``ekf-submap``) over Victoria Park on BB's 10 s fusion
schedule and records, at every fusion, what the back-end's JCBB saw:

* the local map: confirmed features converted (M), features dropped by the existence threshold,
  each converted feature's number of observations in its local map (the front-end's winning ids
  of every scan), its position std (square root of the largest eigenvalue of its local
  covariance) and pairs of converted features closer than ``--near`` metres to each other
  (one tree mapped twice inside one local map);
* against the global map: for every converted feature, the nearest old global feature
  (Euclidean, global frame), its distance, the individual Mahalanobis distance ``d2`` of the
  pair (BB (10)'s difference under the joint covariance) against the gate, and whether JCBB
  paired it. A *miss* is a local feature left unpaired with an old global feature within
  ``--near`` metres;
* the local map's pose and covariance (``local_x``, ``local_P``: both systems fuse at the same
  times, so their local maps are directly comparable) and the global pose after the fusion,
  from which the fusion's heading correction follows;
* the run's path error against GPS after the SE(2) fit, as ``reproduce victoria-park`` does.

``--seed`` picks the particle filter's random stream, ``--option KEY=VALUE`` passes a system
option (``hybrid.front_max_existence=0.999999999`` for one system only), and
``--omega-noise-scale`` multiplies the assumed turn-rate noise of the stream (a sensitivity
check of the odometry assumption of :mod:`slam_gym.datasets.victoria_park`).

Usage: ``python scripts/archive/vp_fusion_diagnosis.py DATA_DIR [--systems hybrid,ekf-submap]
[--seed 0] [--max-steps N] [--particles 200] [--near 1.5] [--option K=V]
[--omega-noise-scale 1] [--json out.json]``.

Supports docs/results/real_data.md, "HYBRID's duplicate trees (issue 16 item 4): fixed by the
lineage term and the small-sample factor".
The command behind it::

    python scripts/archive/vp_fusion_diagnosis.py ../shared/data/victoria_park --seed S \
        --systems hybrid --option hybrid.front_lineage_correction=False
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import logging
from collections import Counter

import numpy as np

from filters.association import point_difference_candidates
from filters.geometry import compose, wrap_angle
from slam_gym.datasets import load_victoria_park, path_error_after_alignment
from slam_gym.datasets.victoria_park import DEFAULT_DT_S, default_odometry_noise
from slam_gym.episode import Episode
from slam_gym.evaluation.core import filter_rng
from slam_gym.systems import make_system

logger = logging.getLogger(__name__)


class FusionRecorder:
    """Wraps a sub-map system's front-end update and back-end fuse to record each fusion."""

    def __init__(self, estimator, near_m: float):
        self.estimator = estimator
        self.near_m = near_m
        self.counts: Counter = Counter()  # observations per local id in the current local map
        self.fusions: list[dict] = []
        front, back = estimator.front_end, estimator.back_end
        update, fuse = front.update, back.fuse

        def counted_update(z, *args, **kwargs):
            update(z, *args, **kwargs)
            self.counts.update(int(i) for i in front.last_associations if i >= 0)

        def recorded_fuse(local, time_s=None):
            record = self._before(local, time_s)
            report = fuse(local, time_s=time_s)
            self._after(record, report)
            self.counts = Counter()
            return report

        front.update = counted_update
        back.fuse = recorded_fuse

    def _before(self, local, time_s):
        back = self.estimator.back_end
        M, N = local.n_features, back.n_features
        n_local_all = len(self.estimator.front_end.landmarks())
        rec = {"t_s": time_s, "M": M, "N": N, "dropped": n_local_all - M}
        covs = local.P[3:, 3:]
        std = np.array([np.sqrt(np.linalg.eigvalsh(covs[2 * i:2 * i + 2, 2 * i:2 * i + 2])[-1])
                        for i in range(M)])
        rec["feature_std_m"] = std.tolist()
        rec["pose_std_m"] = float(np.sqrt(max(local.P[0, 0] + local.P[1, 1], 0.0)))
        rec["heading_std_rad"] = float(np.sqrt(max(local.P[2, 2], 0.0)))
        self._local_pose = local.x[:3].copy()
        rec["local_x"] = local.x.tolist()
        rec["local_P"] = local.P.tolist()
        stats = self.estimator.front_end.local_statistics()
        rec["ess_ratio"] = stats["ess_ratio"]
        rec["n_obs"] = [int(self.counts.get(int(i), 0)) for i in local.ids]
        xy = local.x[3:].reshape(M, 2)
        d_local = np.linalg.norm(xy[:, None] - xy[None], axis=2) if M else np.zeros((0, 0))
        iu = np.triu_indices(M, 1)
        rec["local_near_pairs"] = int(np.sum(d_local[iu] < self.near_m))
        every = self.estimator.front_end.landmarks()
        rec["dropped_existence"] = every.existence[every.existence <= 0.95].tolist()
        rec["dropped_n_obs"] = [int(self.counts.get(int(i), 0))
                                for i in every.ids[every.existence <= 0.95]]
        exy = every.means
        d_every = np.linalg.norm(exy[:, None] - exy[None], axis=2)
        iu2 = np.triu_indices(len(exy), 1)
        rec["all_near_pairs"] = int(np.sum(d_every[iu2] < self.near_m))
        rec["nearest"] = [-1] * M
        rec["nearest_dist_m"] = [float("nan")] * M
        rec["nearest_d2"] = [float("nan")] * M
        if M and N:
            x_aug, P_aug = back.augment(local)
            n = len(back.x)
            local_cols = n + 3 + 2 * np.arange(M)[:, None] + np.arange(2)
            _, d2, _ = point_difference_candidates(
                x_aug, P_aug, local_cols, back.feature_cols(), back._gate
            )
            gxy = x_aug[back.feature_cols()]
            lxy = x_aug[local_cols]
            dist = np.linalg.norm(lxy[:, None] - gxy[None], axis=2)
            j = np.argmin(dist, axis=1)
            rec["nearest"] = j.tolist()
            rec["nearest_dist_m"] = dist[np.arange(M), j].tolist()
            rec["nearest_d2"] = d2[np.arange(M), j].tolist()
            rec["min_d2"] = d2.min(axis=1).tolist()
        rec["gate"] = float(back._gate(1))
        rec["origin_std_m"] = float(np.sqrt(max(back.P[0, 0] + back.P[1, 1], 0.0)))
        rec["origin_heading_std_rad"] = float(np.sqrt(max(back.P[2, 2], 0.0)))
        if M and N:
            cols = back.feature_cols()[rec["nearest"]]
            rec["nearest_global_std_m"] = [
                float(np.sqrt(back.P[c[0], c[0]] + back.P[c[1], c[1]])) for c in cols]
        return rec

    def _after(self, rec, report):
        hyp = self.estimator.back_end.last_hypothesis
        M = rec["M"]
        pairing = hyp.pairing.tolist() if (hyp is not None and M and rec["N"]) else [-1] * M
        rec["pairing"] = pairing
        rec["n_matched"] = report.n_matched
        rec["n_new"] = report.n_new
        rec["global_pose"] = self.estimator.back_end.x[:3].tolist()
        rec["local_pose"] = [float(v) for v in self._local_pose]
        self.fusions.append(rec)


def heading_corrections(fusions):
    """Per fusion after the first, the heading the fusion added to ``v- (+) x_v^L`` (rad), and
    the local map's own heading std: if local maps were consistent, the corrections' RMS could
    not exceed the local heading std's (a correction is a gain < 1 times the innovation)."""
    prev = np.zeros(3)
    out, std = [], []
    for f in fusions:
        g = np.asarray(f["global_pose"])
        predicted = compose(prev, np.asarray(f["local_pose"]))
        out.append(float(wrap_angle(g[2] - predicted[2])))
        std.append(f["heading_std_rad"])
        prev = g
    return np.asarray(out[1:]), np.asarray(std[1:])


def summarise(fusions, near_m):
    """Totals over the fusions of one run (the numbers docs/RESULTS.md quotes)."""
    new = matched = misses = miss_outside = miss_other = 0
    miss_d2, miss_obs, new_obs, matched_obs, miss_std, all_std = [], [], [], [], [], []
    local_dups = dropped = converted = 0
    for f in fusions:
        local_dups += f["local_near_pairs"]
        dropped += f["dropped"]
        converted += f["M"]
        for i in range(f["M"]):
            all_std.append(f["feature_std_m"][i])
            if f["pairing"][i] >= 0:
                matched += 1
                matched_obs.append(f["n_obs"][i])
                continue
            new += 1
            new_obs.append(f["n_obs"][i])
            if f["nearest_dist_m"][i] < near_m:
                misses += 1
                miss_d2.append(f["nearest_d2"][i])
                miss_obs.append(f["n_obs"][i])
                miss_std.append(f["feature_std_m"][i])
                if f["nearest_d2"][i] > f["gate"]:
                    miss_outside += 1
                else:
                    miss_other += 1

    nis = [f["nearest_d2"][i] for f in fusions for i in range(f["M"])
           if f["pairing"][i] >= 0 and f["pairing"][i] == f["nearest"][i]]
    corrections, heading_std = heading_corrections(fusions)

    def pct(a, q):
        return [round(float(v), 3) for v in np.percentile(a, q)] if len(a) else []

    return {
        "fusions": len(fusions),
        "converted": converted,
        "dropped_unconfirmed": dropped,
        "matched": matched,
        "new": new,
        f"new_with_global_within_{near_m:g}m": misses,
        "of_which_outside_gate": miss_outside,
        "of_which_inside_gate_but_unpaired": miss_other,
        "local_pairs_closer_than_near": local_dups,
        "miss_d2_percentiles_10_50_90": pct(miss_d2, [10, 50, 90]),
        "miss_n_obs_percentiles_10_50_90": pct(miss_obs, [10, 50, 90]),
        "new_n_obs_percentiles_10_50_90": pct(new_obs, [10, 50, 90]),
        "matched_n_obs_percentiles_10_50_90": pct(matched_obs, [10, 50, 90]),
        "miss_feature_std_m_percentiles_10_50_90": pct(miss_std, [10, 50, 90]),
        "feature_std_m_percentiles_10_50_90": pct(all_std, [10, 50, 90]),
        "new_with_1_or_2_obs": int(sum(1 for o in new_obs if o <= 2)),
        "matched_nis_mean": float(np.mean(nis)) if nis else None,
        "matched_nis_beyond_99pct": float(np.mean(np.asarray(nis) > 9.21)) if nis else None,
        "heading_correction_mean_deg": float(np.degrees(np.mean(corrections))),
        "heading_correction_rms_deg": float(np.degrees(np.sqrt(np.mean(corrections**2)))),
        "heading_correction_negative_fraction": float(np.mean(corrections < 0)),
        "local_heading_std_rms_deg": float(np.degrees(np.sqrt(np.mean(heading_std**2)))),
        "gate": fusions[0]["gate"] if fusions else None,
    }


def run(data, name, *, max_steps, particles, near_m, seed=0, fusion_interval_s=10.0,
        system_options=None, omega_noise_scale=1.0):
    noise = default_odometry_noise(DEFAULT_DT_S)
    noise = dataclasses.replace(
        noise, omega_fraction=noise.omega_fraction * omega_noise_scale,
        omega_floor_radps=noise.omega_floor_radps * omega_noise_scale,
    )
    stream = load_victoria_park(data, max_steps=max_steps, odometry_noise=noise)
    system = make_system(name, stream, filter_rng(seed), n_particles=particles,
                         **(system_options or {}))
    recorder = FusionRecorder(system.estimator, near_m)
    episode = Episode(system, stream, record_trace=False)
    every = max(1, round(fusion_interval_s / stream.dt_s))
    t, xy = [], []
    while not episode.done:
        for _ in range(every):
            if episode.advance(1) == 0:
                break
            t.append(episode.t_s)
            xy.append(system.pose()[0][:2])
        episode.fuse()
    lm = system.landmarks()
    summary = summarise(recorder.fusions, near_m)
    gps = np.asarray(stream.metadata["gps"], dtype=float)
    fit = path_error_after_alignment(np.array(t), np.array(xy), gps[:, 0], gps[:, 1:3])
    summary["gps_rmse_m"] = float(fit.rmse_m)
    summary["gps_median_m"] = float(np.median(fit.errors_m))
    summary["trees"] = int(np.sum(np.asarray(lm.existence) >= 0.95))
    return summary, recorder.fusions


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data")
    parser.add_argument("--systems", default="hybrid,ekf-submap")
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--near", type=float, default=1.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--omega-noise-scale", type=float, default=1.0,
                        help="factor on the assumed turn-rate noise (std)")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="a system option (front_/back_ prefixed; SYSTEM.KEY for one "
                        "system only), value read as Python")
    parser.add_argument("--json", default=None, help="write every fusion's record here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    options = {}
    for item in args.option:
        key, _, value = item.partition("=")
        options[key] = ast.literal_eval(value)
    out = {}
    for name in [s for s in args.systems.split(",") if s]:
        mine = {k: v for k, v in options.items() if "." not in k or k.startswith(name + ".")}
        mine = {k.split(".", 1)[-1]: v for k, v in mine.items()}
        summary, fusions = run(args.data, name, max_steps=args.max_steps,
                               particles=args.particles, near_m=args.near, seed=args.seed,
                               system_options=mine,
                               omega_noise_scale=args.omega_noise_scale)
        logger.info("%s: %s", name, json.dumps(summary, indent=1))
        out[name] = {"summary": summary, "fusions": fusions}
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
