"""Sub-map fusion (BB section 4) and the sub-mapping system :class:`SubmapSLAM`.

The system keeps a Gaussian **global map** (:class:`GlobalMap`: the global vehicle pose ``v`` and
the global features, jointly Gaussian) and a **local map** built by a front-end (EKF-SLAM or
FastSLAM) in its own frame. The global vehicle pose stored in the global map is the pose at the
previous fusion, ``v-``: the origin of the current local map. Local and global maps are
independent, so between fusions (BB Fig. 3 caption) the current global pose is

    pose = v- (+) x_v^L,   cov = J_a P_v- J_a^T + J_b P_v^L J_b^T

with ``J_a``, ``J_b`` the Jacobians of the composition (:func:`filters.geometry.compose_jacobians`).

Fusion (:meth:`GlobalMap.fuse`), BB section 4:

1. Augmentation: ``x+ = [x-; g(v-, x_L)]`` where ``g`` composes the local pose with ``v-`` and
   carries each local feature into the global frame (:func:`filters.geometry.transform_point`).
   With ``G_v = dg/dv-`` and ``G_L = dg/dx_L``::

       P+ = [[P-,          P-_{:,v} G_v^T                      ],
             [G_v P-_{v,:}, G_v P-_vv G_v^T + G_L P_L G_L^T   ]]

   (BB's displayed matrix, the cross terms running through the Jacobian w.r.t. ``v-`` only because
   the local map is independent of the global one).
2. Association of the local (now global-frame) features with the old global features by JCBB on
   the Cartesian differences under the joint covariance
   (:func:`filters.association.point_difference_candidates`).
3. Each matched pair ``(theta_1, theta_2)`` is fused by the zero-noise observation BB (10)
   ``z_f = theta_1 - theta_2 = 0`` with ``R = 0``: one batch Kalman update in the Cholesky form
   (:func:`filters.ekf_slam.kalman_update`); ``H P H^T`` is the covariance of the difference,
   positive definite because a local feature always carries its own observation noise, and a
   jitter fallback guards round-off. The update leaves the two copies identical (equal means,
   rows and columns of ``P``); the local copy is deleted, which marginalises it out exactly and
   leaves a positive definite covariance without the singular direction ``R = 0`` created.
4. The old global vehicle pose is deleted and the new one (``v- (+) x_v^L``, corrected by the
   fusion through its correlations) takes its place; it is the origin of the next local map.
   Existence probabilities of matched features combine as independent evidence (odds multiply).

The system (:class:`SubmapSLAM`) routes ``predict``/``update``/``update_heading`` to the
front-end, offers ``fuse()`` (any iteration, also with an empty local map), keeps every fused
sub-map in ``self.submaps`` for the optimiser, and computes the interface features of
docs/ARCHITECTURE.md. Compass: a global heading ``theta`` is given to the front-end as the local
heading ``theta - theta(v-)`` with the compass noise; this ignores the uncertainty of the origin's
heading (it is common to every compass reading of one local map, so it cannot be treated as white
noise), which makes the composed heading covariance conservative by up to ``P_v-,theta theta``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from filters.association import (
    DEFAULT_NODE_BUDGET,
    ChiSquareTable,
    Hypothesis,
    individual_compatibility,
    jcbb,
    point_difference_candidates,
    validate_gate_probability,
    validate_node_budget,
)
from filters.ekf_slam import _validate_cov, _validate_pose, kalman_update
from filters.existence import CONFIRMED_PROBABILITY
from filters.geometry import compose, compose_jacobians, transform_point, wrap_angle
from filters.models import innovation, observe, observe_jacobians
from filters.types import FusionReport, GaussianMap, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

INTERFACE_FEATURE_NAMES = (
    "local_map_age_s",
    "local_map_distance_m",
    "ess_ratio",
    "particle_position_spread_m",
    "particle_heading_spread_rad",
    "local_feature_count",
    "local_confirmed_count",
    "vote_margin",
    "innovation_ratio",
    "global_features_in_view",
    "global_position_std_m",
    "global_heading_std_rad",
    "time_since_optimise_s",
    "fusions_since_optimise",
    "clutter_rate",
    "loop_closure_flag",
    "local_map_budget_ratio",
)
"""The interface features of docs/ARCHITECTURE.md, in a fixed order."""


def transform_points_jacobians(pose, points):
    """Batch Jacobians of :func:`transform_point` for points (M, 2): (M, 2, 3) and (2, 2)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    J_pose = np.zeros((len(points), 2, 3))
    J_pose[:, 0, 0] = 1.0
    J_pose[:, 1, 1] = 1.0
    J_pose[:, 0, 2] = -s * points[:, 0] - c * points[:, 1]
    J_pose[:, 1, 2] = c * points[:, 0] - s * points[:, 1]
    return J_pose, np.array([[c, -s], [s, c]])


def combine_existence(p1, p2):
    """Two independent existence estimates of one feature: odds multiply (even prior)."""
    p1 = np.clip(np.asarray(p1, dtype=float), 0.0, 1.0)
    p2 = np.clip(np.asarray(p2, dtype=float), 0.0, 1.0)
    num = p1 * p2
    den = num + (1.0 - p1) * (1.0 - p2)
    return np.where(den > 0.0, num / np.where(den > 0.0, den, 1.0), 0.5)


# --------------------------------------------------------------------------- back-end
class GlobalMap:
    """BB's global EKF back-end over ``[v (3), m_1 (2), ..., m_N (2)]``.

    ``v`` is the global vehicle pose at the last fusion, i.e. the origin ``v-`` of the current
    local map. ``initial_pose`` / ``initial_pose_cov`` (default: origin, exactly known) anchor the
    map; ``gate_probability`` and ``node_budget`` configure the JCBB of fusion.
    """

    def __init__(
        self,
        initial_pose=None,
        initial_pose_cov=None,
        *,
        gate_probability: float = 0.999,
        node_budget: int = DEFAULT_NODE_BUDGET,
    ):
        validate_gate_probability(gate_probability)
        validate_node_budget(node_budget)
        self.gate_probability = float(gate_probability)
        self.node_budget = int(node_budget)
        self._gate = ChiSquareTable(self.gate_probability, 2)
        pose = np.zeros(3) if initial_pose is None else _validate_pose(initial_pose, "initial_pose")
        self.x = pose
        self.P = _validate_cov(initial_pose_cov, "initial_pose_cov")
        self.initial_pose = pose.copy()  # the anchor of the pose chain (for the optimiser)
        self.initial_pose_cov = self.P.copy()
        self.ids = np.zeros(0, dtype=np.int64)
        self.existence = np.zeros(0)
        self.last_hypothesis: Hypothesis | None = None

    @property
    def n_features(self) -> int:
        return len(self.ids)

    def feature_cols(self) -> np.ndarray:
        return 3 + 2 * np.arange(self.n_features)[:, None] + np.arange(2)

    def origin(self):
        """``v-``: the global pose at the last fusion (mean (3,), cov (3, 3))."""
        return self.x[:3].copy(), self.P[:3, :3].copy()

    def landmarks(self) -> LandmarkEstimate:
        if self.n_features == 0:
            return LandmarkEstimate.empty()
        cols = self.feature_cols()
        return LandmarkEstimate(
            ids=self.ids.copy(),
            means=self.x[cols].copy(),
            covs=self.P[cols[:, :, None], cols[:, None, :]].copy(),
            existence=self.existence.copy(),
        )

    def augment(self, local: GaussianMap):
        """BB section 4: ``x+ = [x-; g(v-, x_L)]`` and ``P+`` (module docstring)."""
        M = local.n_features
        n = len(self.x)
        v = self.x[:3]
        xL = np.asarray(local.x, dtype=float)
        PL = np.asarray(local.P, dtype=float)
        pose_new = compose(v, xL[:3])
        J_a, J_b = compose_jacobians(v, xL[:3])
        f_local = xL[3:].reshape(M, 2)
        f_new = transform_point(v, f_local)
        Jf_v, rot = transform_points_jacobians(v, f_local)
        G_v = np.vstack([J_a, Jf_v.reshape(2 * M, 3)])  # (3 + 2M, 3)
        G_L = np.zeros((3 + 2 * M, 3 + 2 * M))
        G_L[:3, :3] = J_b
        if M:
            G_L[3:, 3:] = np.kron(np.eye(M), rot)
        x_aug = np.concatenate([self.x, pose_new, f_new.ravel()])
        P_aug = np.zeros((n + 3 + 2 * M, n + 3 + 2 * M))
        P_aug[:n, :n] = self.P
        cross = G_v @ self.P[:3, :]
        P_aug[n:, :n] = cross
        P_aug[:n, n:] = cross.T
        new = G_v @ self.P[:3, :3] @ G_v.T + G_L @ PL @ G_L.T
        P_aug[n:, n:] = 0.5 * (new + new.T)
        return x_aug, P_aug

    def fuse(self, local: GaussianMap) -> FusionReport:
        """Fuse a local map (in the frame of ``v-``) into the global map (BB section 4)."""
        M = local.n_features
        n = len(self.x)
        N = self.n_features
        require(
            np.shape(local.x) == (3 + 2 * M,) and np.shape(local.P) == (3 + 2 * M,) * 2,
            "local",
            (np.shape(local.x), np.shape(local.P)),
            "a GaussianMap with x (3 + 2M,) and P (3 + 2M, 3 + 2M)",
        )
        x_aug, P_aug = self.augment(local)
        local_cols = n + 3 + 2 * np.arange(M)[:, None] + np.arange(2)
        pairing = np.full(M, -1, dtype=np.int64)
        if M and N:
            cands, _, _ = point_difference_candidates(
                x_aug, P_aug, local_cols, self.feature_cols(), self._gate
            )
            hyp = jcbb(cands, self._gate, self.node_budget)
            self.last_hypothesis = hyp
            if hyp.exhausted:
                logger.debug("fusion JCBB node budget exhausted (%d nodes)", hyp.n_nodes)
            pairing = hyp.pairing
        matched = np.flatnonzero(pairing >= 0)
        if len(matched):
            k = len(matched)
            a = local_cols[matched]  # (k, 2)
            b = 3 + 2 * pairing[matched][:, None] + np.arange(2)
            cols = np.concatenate([a.ravel(), b.ravel()])
            H = np.zeros((2 * k, 4 * k))
            H[:, : 2 * k] = np.eye(2 * k)
            H[:, 2 * k :] = -np.eye(2 * k)
            nu = -(x_aug[a.ravel()] - x_aug[b.ravel()])  # z_f = 0 minus the predicted difference
            kalman_update(x_aug, P_aug, cols, H, nu, np.zeros((2 * k, 2 * k)))  # BB (10)
        unmatched = np.flatnonzero(pairing < 0)
        keep = np.concatenate(
            [np.arange(n, n + 3), np.arange(3, n), local_cols[unmatched].ravel()]
        ).astype(np.int64)
        self.x = x_aug[keep]
        self.x[2] = wrap_angle(self.x[2])
        P = P_aug[np.ix_(keep, keep)]
        self.P = 0.5 * (P + P.T)
        existence = self.existence.copy()
        if len(matched):
            existence[pairing[matched]] = combine_existence(
                existence[pairing[matched]], local.existence[matched]
            )
        self.existence = np.concatenate([existence, np.asarray(local.existence)[unmatched]])
        self.ids = np.concatenate([self.ids, np.asarray(local.ids, dtype=np.int64)[unmatched]])
        id_map = {int(local.ids[i]): int(local.ids[i]) for i in unmatched}
        id_map.update({int(local.ids[i]): int(self.ids[pairing[i]]) for i in matched})
        return FusionReport(id_map=id_map, n_matched=len(matched), n_new=len(unmatched))


# --------------------------------------------------------------------------- the system
@dataclass
class StoredSubmap:
    """A fused local map, kept for the optimiser (DESIGN 3.10).

    ``gaussian``: the local map as fused (local frame, local ids); ``id_map``: local id -> global
    id; ``origin_index``: which pose of the chain of fusion poses is its origin (0 = the initial
    pose, ``s`` = the pose at the ``s``-th fusion); ``end_index = origin_index + 1``: the pose it
    ends at (its vehicle pose); ``time_s``: when it was fused.
    """

    gaussian: GaussianMap
    id_map: dict[int, int]
    origin_index: int
    end_index: int
    time_s: float


@dataclass
class _GlobalObservationStats:
    innovation_ratio: float = 0.0
    loop_closure_flag: float = 0.0
    n_gated: int = 0


class SubmapSLAM:
    """Sub-mapping SLAM (BB section 4): a local-map front-end fused into a global back-end.

    ``front_end``: a filter with ``to_gaussian()``, ``restart()``, ``local_statistics()`` and a
    ``sensor`` attribute (e.g. :class:`filters.ekf_slam.EKFSLAM`); it is restarted here so the
    first local map starts at the origin. ``back_end``: a :class:`GlobalMap` or ``"ekf"`` (a new
    one from ``initial_pose``, ``initial_pose_cov``, ``gate_probability``, ``node_budget``).
    ``loop_closure_unseen_s``: a global feature counts as not seen for a long time
    (``loop_closure_flag``) after this long.
    """

    def __init__(
        self,
        front_end,
        back_end="ekf",
        *,
        initial_pose=None,
        initial_pose_cov=None,
        gate_probability: float = 0.999,
        node_budget: int = DEFAULT_NODE_BUDGET,
        loop_closure_unseen_s: float = 60.0,
    ):
        validate_gate_probability(gate_probability)
        validate_node_budget(node_budget)
        check_range("loop_closure_unseen_s", loop_closure_unseen_s, 0.0, 1e9)
        if isinstance(back_end, str):
            from filters.submap_optimise import make_back_end  # that module imports this one

            back_end = make_back_end(
                back_end,
                initial_pose,
                initial_pose_cov,
                gate_probability=gate_probability,
                node_budget=node_budget,
            )
        else:
            require(
                initial_pose is None and initial_pose_cov is None,
                "initial_pose",
                initial_pose,
                "None when back_end is given as an object (it holds its own initial pose)",
            )
        self.front_end = front_end
        self.back_end = back_end
        self.gate_probability = float(gate_probability)
        self._gate = ChiSquareTable(self.gate_probability, 2)
        self.loop_closure_unseen_s = float(loop_closure_unseen_s)
        self.front_end.restart()
        self.submaps: list[StoredSubmap] = []
        self.n_fusions = 0
        self.n_optimisations = 0
        self._t = 0.0
        self._t_last_optimise = 0.0
        self._fusions_since_optimise = 0
        self._last_seen: dict[int, float] = {}
        self._obs_stats = _GlobalObservationStats()

    # ------------------------------------------------------------------ filter interface
    @property
    def last_associations(self) -> np.ndarray:
        """The front-end's associations of the last update (local ids; -1 = clutter)."""
        return self.front_end.last_associations

    @property
    def time_s(self) -> float:
        return self._t

    def predict(self, u, dt):
        self.front_end.predict(u, dt)
        self._t += float(dt)

    def update(self, z):
        self.front_end.update(z)
        self._obs_stats = self._observe_global(np.asarray(z, dtype=float).reshape(-1, 2))

    def update_heading(self, theta, std_rad):
        """Compass: the local heading ``theta - theta(v-)`` goes to the front-end (module doc)."""
        check_range("theta", theta, -1e6, 1e6)
        v_theta = self.back_end.x[2]
        self.front_end.update_heading(float(wrap_angle(theta - v_theta)), std_rad)

    def _compose_with_origin(self):
        v, P_v = self.back_end.origin()
        xl, Pl = self.front_end.pose()
        J_a, J_b = compose_jacobians(v, xl)
        cov = J_a @ P_v @ J_a.T + J_b @ Pl @ J_b.T
        return compose(v, xl), 0.5 * (cov + cov.T), J_a

    def pose(self):
        """``v- (+) x_v^L`` with covariance ``J_a P_v- J_a^T + J_b P_L J_b^T`` (BB Fig. 3)."""
        mean, cov, _ = self._compose_with_origin()
        return mean, cov

    def landmarks(self) -> LandmarkEstimate:
        """Global features plus the confirmed local features carried into the global frame."""
        glob = self.back_end.landmarks()
        loc = self.front_end.landmarks()
        keep = loc.existence > CONFIRMED_PROBABILITY
        if not keep.any():
            return glob
        v, P_v = self.back_end.origin()
        pts = loc.means[keep]
        J_v, rot = transform_points_jacobians(v, pts)
        means = transform_point(v, pts)
        covs = J_v @ P_v @ np.swapaxes(J_v, 1, 2) + rot @ loc.covs[keep] @ rot.T
        return LandmarkEstimate(
            ids=np.concatenate([glob.ids, loc.ids[keep]]),
            means=np.vstack([glob.means, means]),
            covs=np.concatenate([glob.covs, 0.5 * (covs + np.swapaxes(covs, 1, 2))]),
            existence=np.concatenate([glob.existence, loc.existence[keep]]),
        )

    # ------------------------------------------------------------------ fusion / optimisation
    def fuse(self) -> FusionReport:
        """Fuse the local map into the global map and restart the front-end (BB section 4)."""
        local = self.front_end.to_gaussian()
        n_local = len(self.front_end.landmarks())
        report = self.back_end.fuse(local)
        report.n_dropped = n_local - local.n_features
        self.submaps.append(
            StoredSubmap(
                gaussian=local,
                id_map=dict(report.id_map),
                origin_index=len(self.submaps),
                end_index=len(self.submaps) + 1,
                time_s=self._t,
            )
        )
        self.front_end.restart()
        for gid in report.id_map.values():
            self._last_seen[gid] = self._t
        self.n_fusions += 1
        self._fusions_since_optimise += 1
        return report

    def optimise(self, method: str = "gauss-newton", **options):
        """DESIGN 3.10: minimise CM (12) over the stored sub-maps and replace the global estimate
        by the optimum and its Gauss-Newton covariance (:mod:`filters.submap_optimise`)."""
        from filters.submap_optimise import optimise_submaps

        return optimise_submaps(self, method, **options)

    def _optimised(self):
        """Book-keeping after an optimisation (for the optimiser's implementation)."""
        self.n_optimisations += 1
        self._t_last_optimise = self._t
        self._fusions_since_optimise = 0

    # ------------------------------------------------------------------ interface features
    def _global_prediction(self):
        """Predicted observations of the global features from the composed pose.

        Returns ``(zhat, S, S_upper)`` (N, 2), (N, 2, 2), (N, 2, 2): ``S`` the innovation
        covariance with the cross-covariance between the composed pose and the features
        (``J_a P_v-,m``), ``S_upper = 2 (H_p Sigma H_p^T + H_m P_mm H_m^T) + R`` an upper bound
        of ``S`` (for any joint covariance, ``[[A, B], [B^T, C]] <= 2 diag(A, C)``).
        """
        pose, sigma, J_a = self._compose_with_origin()
        g = self.back_end
        cols = g.feature_cols()
        m = g.x[cols]
        P_mm = g.P[cols[:, :, None], cols[:, None, :]]
        C = np.einsum("ij,jnk->nik", J_a, g.P[:3, cols])  # (N, 3, 2) cov(pose, m_n)
        zhat = observe(pose, m)
        H_p, H_m = observe_jacobians(pose, m)
        R = self.front_end.sensor.R
        A = H_p @ sigma @ np.swapaxes(H_p, 1, 2)
        B = H_m @ P_mm @ np.swapaxes(H_m, 1, 2)
        X = H_p @ C @ np.swapaxes(H_m, 1, 2)
        S = A + B + X + np.swapaxes(X, 1, 2) + R
        S_upper = 2.0 * (A + B) + R
        return zhat, 0.5 * (S + np.swapaxes(S, 1, 2)), S_upper

    def _observe_global(self, z) -> _GlobalObservationStats:
        """Innovation ratio and loop-closure flag of the observations ``z`` of the last update."""
        g = self.back_end
        if g.n_features == 0 or len(z) == 0:
            return _GlobalObservationStats()
        zhat, S, S_upper = self._global_prediction()
        nu = innovation(z[:, None, :], zhat[None])
        d2, mask = individual_compatibility(nu, S[None], self._gate)
        gated = np.flatnonzero(mask.any(axis=1))
        if len(gated) == 0:
            return _GlobalObservationStats()
        nearest = np.argmin(np.where(mask[gated], d2[gated], np.inf), axis=1)
        sigma = np.sqrt(np.linalg.eigvalsh(S_upper[nearest])[:, -1])
        ratio = np.linalg.norm(nu[gated, nearest], axis=1) / (2.0 * sigma)
        flag = 0.0
        for j, r in zip(nearest, ratio, strict=True):
            gid = int(g.ids[j])
            last = self._last_seen.get(gid, 0.0)  # features of a given back-end: seen at start
            if r > 1.0 and self._t - last > self.loop_closure_unseen_s:
                flag = 1.0
            self._last_seen[gid] = self._t
        return _GlobalObservationStats(
            innovation_ratio=float(ratio.max()), loop_closure_flag=flag, n_gated=len(gated)
        )

    def global_features_in_view(self) -> int:
        g = self.back_end
        if g.n_features == 0:
            return 0
        pose, _, _ = self._compose_with_origin()
        zhat = observe(pose, g.x[g.feature_cols()])
        return int(np.count_nonzero(self.front_end.sensor.in_view(zhat)))

    def interface_features(self) -> dict[str, float]:
        """All interface features of docs/ARCHITECTURE.md (names in INTERFACE_FEATURE_NAMES)."""
        out = dict(self.front_end.local_statistics())
        _, cov = self.pose()
        out.update(
            innovation_ratio=float(self._obs_stats.innovation_ratio),
            global_features_in_view=float(self.global_features_in_view()),
            global_position_std_m=float(np.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))),
            global_heading_std_rad=float(np.sqrt(max(cov[2, 2], 0.0))),
            time_since_optimise_s=float(self._t - self._t_last_optimise),
            fusions_since_optimise=float(self._fusions_since_optimise),
            loop_closure_flag=float(self._obs_stats.loop_closure_flag),
        )
        missing = [k for k in INTERFACE_FEATURE_NAMES if k not in out]
        require(not missing, "front_end.local_statistics()", sorted(out), f"to include {missing}")
        return {k: float(out[k]) for k in INTERFACE_FEATURE_NAMES}
