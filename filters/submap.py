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
from numba import njit

from filters.association import (
    DEFAULT_NODE_BUDGET,
    ChiSquareTable,
    Hypothesis,
    jcbb,
    point_difference_candidates,
    validate_gate_probability,
    validate_node_budget,
)
from filters.ekf_slam import _validate_cov, _validate_pose, kalman_update
from filters.existence import CONFIRMED_PROBABILITY
from filters.geometry import compose, compose_jacobians, transform_point, wrap_angle
from filters.interface_features import INTERFACE_FEATURE_NAMES
from filters.models import observe
from filters.types import FusionReport, GaussianMap, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)



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
        self._composed = None  # the composed pose of the current state (_compose_with_origin)

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
        self._composed = None

    def update(self, z):
        self.front_end.update(z)
        self._composed = None
        self._obs_stats = self._observe_global(np.asarray(z, dtype=float).reshape(-1, 2))

    def update_heading(self, theta, std_rad):
        """Compass: the local heading ``theta - theta(v-)`` goes to the front-end (module doc)."""
        check_range("theta", theta, -1e6, 1e6)
        v_theta = self.back_end.x[2]
        self.front_end.update_heading(float(wrap_angle(theta - v_theta)), std_rad)
        self._composed = None

    def _compose_with_origin(self):
        """``(v- (+) x_v^L, its covariance, J_a)``; computed once per state (every method that
        changes the front-end or the back-end resets it)."""
        if self._composed is None:
            v, P_v = self.back_end.origin()
            xl, Pl = self.front_end.pose()
            J_a, J_b = compose_jacobians(v, xl)
            cov = J_a @ P_v @ J_a.T + J_b @ Pl @ J_b.T
            self._composed = (compose(v, xl), 0.5 * (cov + cov.T), J_a)
        return tuple(a.copy() for a in self._composed)

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
        self._composed = None
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
        self._composed = None
        self._t_last_optimise = self._t
        self._fusions_since_optimise = 0

    # ------------------------------------------------------------------ interface features
    def _observe_global(self, z) -> _GlobalObservationStats:
        """Innovation ratio and loop-closure flag of the observations ``z`` of the last update
        (:func:`_nearest_global_innovations`)."""
        g = self.back_end
        if g.n_features == 0 or len(z) == 0:
            return _GlobalObservationStats()
        pose, sigma, J_a = self._compose_with_origin()
        R = self.front_end.sensor.R
        nearest, ratio = _nearest_global_innovations(
            z, pose, sigma, J_a, np.asarray(g.x, dtype=float), np.asarray(g.P, dtype=float),
            g.feature_cols(), float(R[0, 0]), float(R[1, 1]), self._gate(1),
        )
        gated = np.flatnonzero(nearest >= 0)
        if len(gated) == 0:
            return _GlobalObservationStats()
        flag = 0.0
        for j, r in zip(nearest[gated], ratio[gated], strict=True):
            gid = int(g.ids[j])
            last = self._last_seen.get(gid, 0.0)  # features of a given back-end: seen at start
            if r > 1.0 and self._t - last > self.loop_closure_unseen_s:
                flag = 1.0
            self._last_seen[gid] = self._t
        return _GlobalObservationStats(
            innovation_ratio=float(ratio[gated].max()), loop_closure_flag=flag, n_gated=len(gated)
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


@njit(cache=True)
def _nearest_global_innovations(z, pose, sigma, J_a, x, P, cols, r_var, b_var, gate_chi2):
    """The global feature each observation is nearest to, and its innovation ratio.

    Predicts every global feature ``m_n`` from the composed pose ``pose`` (covariance
    ``sigma``, ``J_a`` its Jacobian w.r.t. the origin ``v-``): ``S_n = H_p sigma H_p^T + H_m P_mm
    H_m^T + X + X^T + R`` with the pose-feature cross term ``X = H_p J_a P[v-, m_n] H_m^T``.
    For observation ``k``, ``nearest[k]`` is the feature with the smallest ``nu^T S_n^-1 nu``
    inside the gate ``gate_chi2`` (-1: none) and ``ratio[k] = ||nu|| / (2 sigma_n)``, with
    ``sigma_n^2`` the largest eigenvalue of the upper bound ``2 (H_p sigma H_p^T + H_m P_mm
    H_m^T) + R`` of ``S_n`` (for any joint covariance ``[[A, B], [B^T, C]] <= 2 diag(A, C)``):
    CM's innovation test ``||nu|| > 2 sigma`` (CM III.B) reads ``ratio > 1``.
    """
    N, K = cols.shape[0], z.shape[0]
    z_range, z_bearing = np.empty(N), np.empty(N)
    S00, S01, S11, upper_eig = np.empty(N), np.empty(N), np.empty(N), np.empty(N)
    Hp = np.empty((2, 3))
    Hm = np.empty((2, 2))
    cross = np.empty((3, 2))  # J_a P[v-, m_n]: cov(pose, m_n)
    for n in range(N):
        c0, c1 = cols[n, 0], cols[n, 1]
        dx, dy = x[c0] - pose[0], x[c1] - pose[1]
        q = max(dx * dx + dy * dy, 1e-12)
        r = np.sqrt(q)
        z_range[n] = r
        z_bearing[n] = (np.arctan2(dy, dx) - pose[2] + np.pi) % (2.0 * np.pi) - np.pi
        Hm[0, 0], Hm[0, 1], Hm[1, 0], Hm[1, 1] = dx / r, dy / r, -dy / q, dx / q
        Hp[0, 0], Hp[0, 1], Hp[0, 2] = -Hm[0, 0], -Hm[0, 1], 0.0
        Hp[1, 0], Hp[1, 1], Hp[1, 2] = -Hm[1, 0], -Hm[1, 1], -1.0
        for i in range(3):
            for a in range(2):
                cross[i, a] = J_a[i, 0] * P[0, cols[n, a]] + J_a[i, 1] * P[1, cols[n, a]] + (
                    J_a[i, 2] * P[2, cols[n, a]]
                )
        A = Hp @ sigma @ Hp.T
        pmm = np.empty((2, 2))
        for a in range(2):
            for b in range(2):
                pmm[a, b] = P[cols[n, a], cols[n, b]]
        B = Hm @ pmm @ Hm.T
        X = Hp @ cross @ Hm.T
        S00[n] = A[0, 0] + B[0, 0] + 2.0 * X[0, 0] + r_var
        S01[n] = 0.5 * (A[0, 1] + A[1, 0] + B[0, 1] + B[1, 0]) + X[0, 1] + X[1, 0]
        S11[n] = A[1, 1] + B[1, 1] + 2.0 * X[1, 1] + b_var
        u00 = 2.0 * (A[0, 0] + B[0, 0]) + r_var
        u01 = (A[0, 1] + A[1, 0]) + (B[0, 1] + B[1, 0])
        u11 = 2.0 * (A[1, 1] + B[1, 1]) + b_var
        upper_eig[n] = 0.5 * (u00 + u11) + np.hypot(0.5 * (u00 - u11), u01)
    nearest = np.full(K, -1, dtype=np.int64)
    ratio = np.zeros(K)
    for k in range(K):
        best = np.inf
        for n in range(N):
            nu_r = z[k, 0] - z_range[n]
            nu_b = (z[k, 1] - z_bearing[n] + np.pi) % (2.0 * np.pi) - np.pi
            det = S00[n] * S11[n] - S01[n] * S01[n]
            d2 = (S11[n] * nu_r * nu_r - 2.0 * S01[n] * nu_r * nu_b + S00[n] * nu_b * nu_b) / det
            if d2 <= gate_chi2 and d2 < best:
                best = d2
                nearest[k] = n
                ratio[k] = np.hypot(nu_r, nu_b) / (2.0 * np.sqrt(upper_eig[n]))
    return nearest, ratio
