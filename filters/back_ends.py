"""The sub-map back-ends: BB's EKF global map and CM's relative representation.

Both take fused local maps (:class:`filters.types.GaussianMap`, in the frame of the origin
``v-``) through ``fuse(local, time_s=...)`` and offer the same estimate to
:class:`filters.submap.SubmapSLAM` (``x``, ``P``, ``ids``, ``existence``, ``origin()``,
``landmarks()``, ``feature_cols()``). Each reports the loop closures it detected at a fusion
(:class:`SubmapLoopClosure`, CM Definition 1) in ``FusionReport.loop_closures``. Imports run one
way: :mod:`filters.submap` -> this module -> :mod:`filters.submap_optimise`.

The EKF back-end (:class:`GlobalMap`)
------------------------------------
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

Loop closures (CM Definition 1, second condition; CM III.B): every local feature that re-observes
a global feature not fused for ``loop_closure_unseen_s`` is tested with CM's criterion
``||nu|| > 2 sigma``, ``nu`` the fusion's innovation BB (10) (the Cartesian difference of the two
copies, metres) and ``sigma^2`` the largest eigenvalue of its covariance ``H P+ H^T`` (exact here,
where CM must bound it). The re-observations tested are the pairs JCBB matched *and* those it left
unmatched because they fall outside the association gate: an unmatched local feature is paired
with the nearest old global feature within ``closure_radius_m`` (Euclidean, in the global frame).
These are the inconsistent closures CM's test exists for; they enter the map as new features, and
the event tells the interface that the linearised estimate no longer explains the data. CM's
first condition (an update too slow for real time) has no counterpart: an EKF fusion's cost does
not depend on how long ago a feature was seen.

The relative back-end (:class:`RelativeBackEnd`)
------------------------------------------------
CM's representation at the sub-map level (CM III.B; docs/ARCHITECTURE.md, "Sub-map system"): fused
sub-maps
are kept only in relative coordinates, in information form ``(eta, Lambda)``
(:class:`filters.information.SparseInformation`) over

* ``d_s``: the end pose of sub-map ``s`` in its origin frame (CM's ``d^R``, one per fusion);
* ``l``: each feature's coordinates in the origin frame of the sub-map that first had it (CM's
  ``d^L``), plus redundant coordinates in the frame of a later sub-map at a loop closure.

Fusing sub-map ``b`` (with origin ``x_b``) integrates its Gaussian ``N(r_b, P_b)`` as one
measurement with the EIF update CM (4)-(5): its end pose and its new features are new entities
(``H = I``: exact, constant time); a local feature associated with an existing feature ``j`` whose
latest coordinates ``l`` live in frame ``f`` is the CM (11) analogue
``point_to_frame(d_f (+) ... (+) d_{b-1}, l)``, linearised at the current relative means -- unless
it is a loop closure (CM Definition 1):

1. the chain is long: ``b - f > max_chain`` fusions, or
2. ``||nu|| > innovation_sigmas * sigma`` (CM: 2 sigma), ``sigma^2`` the largest eigenvalue of an
   upper bound of the innovation covariance. The bound: sub-map ``c``'s information term
   ``H^T P_c^-1 H`` is ``I`` on the entities it creates (end pose, new features, redundant
   coordinates; rows ``n``) and a function of older entities on its other rows (``o``); for every
   value of the latter its quadratic form is at least the minimum over them,
   ``x_n^T (P_c[n, n])^-1 x_n``. So ``Lambda >= blockdiag_c (P_c[n_c, n_c])^-1`` (the creating
   entity sets are disjoint and the remaining terms are PSD), the covariance of the relative state
   is at most ``blockdiag_c P_c[n_c, n_c]``, and with the new sub-map independent of the state,

       S = J Cov J^T + P_b[i, i]  <=  S_bar = sum_c J_c P_c[n_c, n_c] J_c^T + P_b[i, i],

   ``J_c`` the Jacobian of the prediction w.r.t. the involved entities created by sub-map ``c``.
   The threshold is therefore conservative (larger than the true 2 sigma), as CM require.

At a loop closure the feature gets redundant coordinates in frame ``b`` (the CM loop-closure
information frozen in a geometric dependency); later re-observations use those. Associations are
decided by JCBB on the global estimate (:func:`filters.association.point_difference_candidates`,
:func:`filters.association.jcbb`, the same test as :meth:`GlobalMap.fuse`).

Between optimisations the global estimate ``(x, P)`` (what :class:`filters.submap.SubmapSLAM`
reads) is the chain: ``x_k = a (+) d_{b0} (+) ... (+) d_{k-1}`` from the anchor pose ``a``
(the initial pose, or the pose of the last optimisation, index ``b0``) and each feature from its
first coordinates, ``m = x_f (+) l``; features covered by the last optimisation keep its optimum.
Its covariance is ``J_A Sigma_A J_A^T + J_R Lambda^-1 J_R^T`` (``Sigma_A`` the anchor's
covariance: the initial pose's, or the Gauss-Newton covariance of the optimum), solved for the
needed columns with a sparse factorisation. Before any optimisation and loop closure this is the
Gaussian posterior of the sub-maps, the same as the EKF back-end's up to linearisation. Treating
the anchor and the relative state as independent after an optimisation is an approximation (both
depend on the sub-maps fused before it), as in :class:`filters.relative_esdf.RelativeESDF`.
``optimise()`` recovers global coordinates with :func:`optimise_submaps` (the stored sub-maps,
unlinearised) and makes the optimum the new anchor.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from filters.association import (
    DEFAULT_NODE_BUDGET,
    ChiSquareTable,
    Hypothesis,
    jcbb,
    point_difference_candidates,
    validate_gate_probability,
    validate_node_budget,
)
from filters.ekf_slam import kalman_update, validate_cov, validate_pose
from filters.geometry import (
    compose,
    compose_jacobians,
    point_to_frame,
    point_to_frame_jacobians,
    transform_point,
    transform_point_jacobians,
    wrap_angle,
)
from filters.information import SparseInformation, symmetrise
from filters.optimiser import POINT, POSE, RelativeQuantity
from filters.relative_esdf import chain_compose
from filters.submap_optimise import (
    DEFAULT_MIN_VARIANCE,
    floored_covariance,
    gaussian_information,
)
from filters.types import FusionReport, GaussianMap, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

BACK_END_KINDS = ("ekf", "relative")

CM_INNOVATION_SIGMAS = 2.0
"""CM III.B: a re-observation whose innovation norm exceeds 2 sigma is a loop closure."""


def cm_innovation_ratio(nu, S, sigmas: float = CM_INNOVATION_SIGMAS) -> float:
    """``||nu|| / (sigmas * sigma)`` with ``sigma^2`` the largest eigenvalue of ``S`` (CM III.B):
    CM's loop-closure test reads ``ratio > 1``. ``nu`` and ``S`` must be in one unit (metres)."""
    sigma = float(np.sqrt(max(np.linalg.eigvalsh(symmetrise(np.asarray(S, dtype=float)))[-1],
                              1e-300)))
    return float(np.linalg.norm(nu) / (sigmas * sigma))


@dataclass(frozen=True)
class SubmapLoopClosure:
    """A loop closure found while fusing sub-map ``submap`` (CM Definition 1).

    ``reason``: ``"chain"`` (relative back-end: more than ``max_chain`` fusions between the
    feature's frame and the sub-map) or ``"innovation"`` (``||nu|| > 2 sigma``);
    ``innovation_ratio`` is ``||nu|| / (2 sigma)``; ``chain_length``: fusions since the feature's
    coordinates were made (relative) or since it was last fused (EKF); ``coordinates_entity``: the
    redundant coordinates it created (relative back-end; -1 for the EKF back-end);
    ``unseen_s``: time since the feature was last fused (EKF back-end; NaN for the relative one);
    ``outside_gate``: the re-observation was not matched by the fusion's JCBB (EKF back-end).
    """

    submap: int
    feature_id: int
    chain_length: int
    innovation_ratio: float
    reason: str
    coordinates_entity: int = -1
    unseen_s: float = float("nan")
    outside_gate: bool = False


DEFAULT_LOOP_CLOSURE_UNSEEN_S = 60.0
"""A global feature counts as old (its re-observation may close a loop) when it has not been fused
for this long: in BB's world (1 m/s, 25 m range) a landmark stays in view for at most ~50 s."""

DEFAULT_CLOSURE_RADIUS_M = 5.0
"""Search radius (m) pairing a local feature JCBB left unmatched with an old global feature: a
quarter of the mean landmark spacing of BB's world (35 landmarks in 120 m x 120 m: ~20 m)."""


# --------------------------------------------------------------------------- EKF back-end
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
    map; ``gate_probability`` and ``node_budget`` configure the JCBB of fusion;
    ``loop_closure_unseen_s`` (s) and ``closure_radius_m`` (m) the loop-closure test (module
    docstring).
    """

    def __init__(
        self,
        initial_pose=None,
        initial_pose_cov=None,
        *,
        gate_probability: float = 0.999,
        node_budget: int = DEFAULT_NODE_BUDGET,
        loop_closure_unseen_s: float = DEFAULT_LOOP_CLOSURE_UNSEEN_S,
        closure_radius_m: float = DEFAULT_CLOSURE_RADIUS_M,
    ):
        validate_gate_probability(gate_probability)
        validate_node_budget(node_budget)
        check_range("loop_closure_unseen_s", loop_closure_unseen_s, 0.0, 1e9)
        check_range("closure_radius_m", closure_radius_m, 0.0, 1e6)
        self.loop_closure_unseen_s = float(loop_closure_unseen_s)
        self.closure_radius_m = float(closure_radius_m)
        self.last_fused_s = np.zeros(0)  # per global feature: when it was last fused
        self.n_fusions = 0
        self.loop_closures: list[SubmapLoopClosure] = []
        self.gate_probability = float(gate_probability)
        self.node_budget = int(node_budget)
        self._gate = ChiSquareTable(self.gate_probability, 2)
        pose = np.zeros(3) if initial_pose is None else validate_pose(initial_pose, "initial_pose")
        self.x = pose
        self.P = validate_cov(initial_pose_cov, "initial_pose_cov")
        self.initial_pose = pose.copy()  # the anchor of the pose chain (for the optimiser)
        self.initial_pose_cov = self.P.copy()
        self.ids = np.zeros(0, dtype=np.int64)
        self.existence = np.zeros(0)
        self.last_hypothesis: Hypothesis | None = None
        self._feature_cols = None  # feature_cols() of the last size asked for

    @property
    def n_features(self) -> int:
        return len(self.ids)

    def feature_cols(self) -> np.ndarray:
        """The state columns (n, 2) of each feature's (x, y); read-only, formed once per size."""
        n = self.n_features
        cols = self._feature_cols
        if cols is None or len(cols) != n:
            cols = 3 + 2 * np.arange(n)[:, None] + np.arange(2)
            cols.flags.writeable = False
            self._feature_cols = cols
        return cols

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

    def landmark_means(self):
        """``(ids, means, existence)`` of :meth:`landmarks` without the covariances (the same
        numbers): what map scoring needs, at every decision."""
        if self.n_features == 0:
            empty = LandmarkEstimate.empty()
            return empty.ids, empty.means, empty.existence
        return self.ids.copy(), self.x[self.feature_cols()], self.existence.copy()

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

    @property
    def n_loop_closures(self) -> int:
        return len(self.loop_closures)

    def _last_fused(self) -> np.ndarray:
        """When each global feature was last fused (NaN: not known, e.g. features set by hand)."""
        last = self.last_fused_s[: self.n_features]
        return np.concatenate([last, np.full(self.n_features - len(last), np.nan)])

    def fuse(self, local: GaussianMap, time_s: float | None = None) -> FusionReport:
        """Fuse a local map (in the frame of ``v-``) into the global map (BB section 4).

        ``time_s``: the time of the fusion, for the loop-closure test (None: the test is off)."""
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
        closures = []
        if time_s is not None and M and N:
            closures = self._loop_closures(x_aug, P_aug, local_cols, pairing, local, time_s)
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
        t = np.nan if time_s is None else float(time_s)
        last = self._last_fused()
        if len(matched):
            last[pairing[matched]] = t
        self.last_fused_s = np.concatenate([last, np.full(len(unmatched), t)])
        self.existence = np.concatenate([existence, np.asarray(local.existence)[unmatched]])
        self.ids = np.concatenate([self.ids, np.asarray(local.ids, dtype=np.int64)[unmatched]])
        self.n_fusions += 1
        self.loop_closures.extend(closures)
        id_map = {int(local.ids[i]): int(local.ids[i]) for i in unmatched}
        id_map.update({int(local.ids[i]): int(self.ids[pairing[i]]) for i in matched})
        return FusionReport(
            id_map=id_map, n_matched=len(matched), n_new=len(unmatched), loop_closures=closures
        )

    def _loop_closures(self, x_aug, P_aug, local_cols, pairing, local, time_s):
        """CM Definition 1 on the fusion's re-observations of old features (module docstring)."""
        N = self.n_features
        unseen = time_s - self._last_fused()  # NaN (never timed) compares False: not old
        old = np.flatnonzero(unseen > self.loop_closure_unseen_s)
        if len(old) == 0:
            return []
        global_cols = self.feature_cols()
        old_xy = x_aug[global_cols[old]]  # (n_old, 2)
        taken = set(int(j) for j in pairing[pairing >= 0])
        pairs = []  # (local index, global index, outside the gate?)
        for i in range(len(local_cols)):
            j = int(pairing[i])
            if j >= 0:
                if unseen[j] > self.loop_closure_unseen_s:
                    pairs.append((i, j, False))
                continue
            dist = np.linalg.norm(old_xy - x_aug[local_cols[i]], axis=1)
            k = int(np.argmin(dist))
            if dist[k] <= self.closure_radius_m and int(old[k]) not in taken:
                pairs.append((i, int(old[k]), True))
        out = []
        for i, j, outside in pairs:
            a, b = local_cols[i], global_cols[j]
            nu = x_aug[a] - x_aug[b]
            S = P_aug[np.ix_(a, a)] + P_aug[np.ix_(b, b)]
            S = S - P_aug[np.ix_(a, b)] - P_aug[np.ix_(b, a)]
            ratio = cm_innovation_ratio(nu, S)
            if ratio > 1.0:
                out.append(SubmapLoopClosure(
                    submap=self.n_fusions, feature_id=int(self.ids[j]), chain_length=0,
                    innovation_ratio=ratio, reason="innovation", unseen_s=float(unseen[j]),
                    outside_gate=outside,
                ))
        if out:
            logger.debug("fusion %d: %d loop closure(s) of %d old features (%d global)",
                         self.n_fusions, len(out), len(old), N)
        return out


# --------------------------------------------------------------------------- relative back-end
@dataclass
class _Anchor:
    index: int  # fusion-pose index of the anchor pose
    pose: np.ndarray  # (3,)
    ids: np.ndarray  # features covered by the anchor (global ids)
    means: np.ndarray  # (Na, 2)
    cov: np.ndarray  # (3 + 2 Na, 3 + 2 Na) over [pose, features]


class RelativeBackEnd(GlobalMap):
    """CM's relative representation as a sub-map back-end (module docstring).

    Offers :class:`GlobalMap`'s interface to :class:`filters.submap.SubmapSLAM` (``x``, ``P``,
    ``ids``, ``existence``, ``origin()``, ``landmarks()``, ``feature_cols()``, ``fuse(local)``,
    ``last_hypothesis``), with ``x``/``P`` the chain estimate. Options beyond GlobalMap's:
    ``innovation_sigmas`` (CM: 2, in (0, 100]), ``max_chain`` (fusions, 1..10^6),
    ``min_variance`` (floor on sub-map covariance eigenvalues).
    """

    def __init__(
        self,
        initial_pose=None,
        initial_pose_cov=None,
        *,
        gate_probability: float = 0.999,
        node_budget: int = DEFAULT_NODE_BUDGET,
        innovation_sigmas: float = 2.0,
        max_chain: int = 10,
        min_variance: float = DEFAULT_MIN_VARIANCE,
    ):
        super().__init__(
            initial_pose,
            initial_pose_cov,
            gate_probability=gate_probability,
            node_budget=node_budget,
        )
        check_range("innovation_sigmas", innovation_sigmas, 0.0, 100.0, low_open=True)
        require(
            isinstance(max_chain, (int, np.integer))
            and not isinstance(max_chain, bool)
            and 1 <= max_chain <= 10**6,
            "max_chain",
            max_chain,
            "an integer in [1, 1000000]",
        )
        check_range("min_variance", min_variance, 0.0, 1.0, low_open=True)
        self.innovation_sigmas = float(innovation_sigmas)
        self.max_chain = int(max_chain)
        self.min_variance = float(min_variance)
        self.initial_pose = self.x.copy()
        self.initial_pose_cov = self.P.copy()
        self.info = SparseInformation()
        self.quantities: list[RelativeQuantity] = []  # per relative entity (pose index / gid)
        self._creator: list[tuple[int, int]] = []  # per entity: (sub-map, offset in its block)
        self._creator_cov: list[np.ndarray] = []  # per sub-map: cov of the entities it created
        self._d: list[int] = []  # per sub-map: entity of its end pose d_s
        self._coords: dict[int, list[tuple[int, int]]] = {}  # gid -> [(entity, frame index)]
        self.last_loop_closure = False
        self.last_innovation_ratio = 0.0
        self._anchor = _Anchor(
            0, self.x.copy(), np.zeros(0, dtype=np.int64), np.zeros((0, 2)), self.P.copy()
        )

    # ------------------------------------------------------------------ book-keeping
    @property
    def n_submaps(self) -> int:
        return len(self._d)

    @property
    def redundancies(self) -> dict[int, int]:
        """Global id -> number of coordinate sets, for features with more than one."""
        return {g: len(c) for g, c in self._coords.items() if len(c) > 1}

    def _mean_of(self, e, mu) -> np.ndarray:
        o = self.info.offset(e)
        return mu[o : o + self.info.size(e)]

    def _new_entity(self, size, quantity, submap, offset) -> int:
        e = self.info.add_entity(size)
        self.quantities.append(quantity)
        self._creator.append((submap, offset))
        return e

    def _chain_prediction(self, gid: int, b: int, mu):
        """CM (11) analogue: feature ``gid`` (latest coordinates) seen from fusion pose ``b``.

        Returns the predicted coordinates ``point_to_frame(d_f (+) ... (+) d_{b-1}, l)`` (2,), the
        entities it depends on (``d_f, ..., d_{b-1}, l``) and its Jacobians w.r.t. them.
        """
        ent, f = self._coords[int(gid)][-1]
        d_ents = self._d[f:b]
        ds = np.array([self._mean_of(e, mu) for e in d_ents]).reshape(-1, 3)
        G, J_ds, _ = chain_compose(np.zeros(3), ds)
        lm = self._mean_of(ent, mu)
        H_T, H_l = point_to_frame_jacobians(G[-1], lm)
        return point_to_frame(G[-1], lm), [*d_ents, ent], [*(H_T @ J for J in J_ds), H_l]

    def predict_coordinates(self, gid: int):
        """Prediction of feature ``gid`` in the frame of the current fusion pose ``v-``.

        ``(mean (2,), entities, Jacobians)`` at the current relative means: what the next sub-map's
        copy of the feature is tested against (module docstring).
        """
        require(int(gid) in self._coords, "gid", gid, "the id of a fused feature")
        mu = self.info.mean()
        return self._chain_prediction(int(gid), len(self._d), mu)

    def innovation_bound(self, ents, Hs) -> np.ndarray:
        """``sum_c J_c P_c[n_c, n_c] J_c^T`` over the creators of ``ents`` (module docstring).

        An upper bound of the covariance ``J Lambda^-1 J^T`` of a prediction with Jacobians ``Hs``
        w.r.t. the relative entities ``ents``.
        """
        groups: dict[int, list[tuple[int, np.ndarray]]] = {}
        for e, H in zip(ents, Hs, strict=True):
            c, off = self._creator[e]
            groups.setdefault(c, []).append((off, H))
        out = np.zeros((2, 2))
        for c, members in groups.items():
            idx = np.concatenate([np.arange(off, off + H.shape[1]) for off, H in members])
            J = np.hstack([H for _, H in members])
            out += J @ self._creator_cov[c][np.ix_(idx, idx)] @ J.T
        return out

    # ------------------------------------------------------------------ fusion
    def fuse(self, local: GaussianMap, time_s: float | None = None) -> FusionReport:
        """Associate (JCBB), test for loop closures and integrate a sub-map (module docstring).

        ``time_s`` is accepted for the interface of :meth:`GlobalMap.fuse` (the relative test
        counts fusions, not time)."""
        M = local.n_features
        require(
            np.shape(local.x) == (3 + 2 * M,) and np.shape(local.P) == (3 + 2 * M,) * 2,
            "local",
            (np.shape(local.x), np.shape(local.P)),
            "a GaussianMap with x (3 + 2M,) and P (3 + 2M, 3 + 2M)",
        )
        b = len(self._d)  # this sub-map starts at fusion pose b
        N = self.n_features
        pairing = np.full(M, -1, dtype=np.int64)
        if M and N:
            x_aug, P_aug = self.augment(local)  # the chain estimate augmented, as BB section 4
            n = len(self.x)
            local_cols = n + 3 + 2 * np.arange(M)[:, None] + np.arange(2)
            cands, _, _ = point_difference_candidates(
                x_aug, P_aug, local_cols, self.feature_cols(), self._gate
            )
            hyp = jcbb(cands, self._gate, self.node_budget)
            self.last_hypothesis = hyp
            pairing = hyp.pairing
        xL = np.asarray(local.x, dtype=float).copy()
        xL[2] = wrap_angle(xL[2])
        PL = floored_covariance(local.P, self.min_variance)
        W = gaussian_information(PL, self.min_variance)
        mu = self.info.mean() if self.info.n_entities else np.zeros(0)
        dim = 3 + 2 * M
        h = xL.copy()  # h(mu) per row; rows of new entities measure them directly
        blocks: dict[int, np.ndarray] = {}
        lin: dict[int, np.ndarray] = {}  # linearisation point per entity
        new_rows: list[int] = []
        self.last_loop_closure = False
        self.last_innovation_ratio = 0.0
        n_closures_before = len(self.loop_closures)

        def new_entity(rows, size, quantity):
            e = self._new_entity(size, quantity, b, len(new_rows))
            new_rows.extend(rows)
            B = np.zeros((dim, size))
            B[rows, np.arange(size)] = 1.0
            blocks[e] = B
            lin[e] = xL[rows]
            return e

        self._d.append(new_entity([0, 1, 2], 3, RelativeQuantity(POSE, b, b + 1)))
        for i in range(M):
            rows = [3 + 2 * i, 4 + 2 * i]
            if pairing[i] < 0:
                gid = int(local.ids[i])
                self._coords[gid] = [(new_entity(rows, 2, RelativeQuantity(POINT, b, gid)), b)]
                continue
            gid = int(self.ids[pairing[i]])
            pred, p_ents, p_H = self._chain_prediction(gid, b, mu)
            chain = b - self._coords[gid][-1][1]
            nu = xL[rows] - pred
            S_bar = PL[np.ix_(rows, rows)] + self.innovation_bound(p_ents, p_H)
            sigma = float(np.sqrt(np.linalg.eigvalsh(symmetrise(S_bar))[-1]))
            ratio = float(np.linalg.norm(nu) / (self.innovation_sigmas * sigma))
            self.last_innovation_ratio = max(self.last_innovation_ratio, ratio)
            reason = "chain" if chain > self.max_chain else ("innovation" if ratio > 1 else "")
            if reason:
                e = new_entity(rows, 2, RelativeQuantity(POINT, b, gid))
                self._coords[gid].append((e, b))
                self.loop_closures.append(SubmapLoopClosure(b, gid, chain, ratio, reason, e))
                self.last_loop_closure = True
                logger.debug("loop closure on feature %d (%s, chain %d)", gid, reason, chain)
                continue
            h[rows] = pred  # CM (11) analogue, linearised at the relative means
            for e, H in zip(p_ents, p_H, strict=True):
                if e not in blocks:
                    blocks[e] = np.zeros((dim, self.info.size(e)))
                    lin[e] = self._mean_of(e, mu).copy()
                blocks[e][rows] += H
        self._creator_cov.append(PL[np.ix_(new_rows, new_rows)].copy())
        ents = list(blocks)
        rhs = xL - h + sum(blocks[e] @ lin[e] for e in ents)
        self.info.add_information(ents, [blocks[e] for e in ents], W, rhs)  # CM (4)-(5)

        matched = np.flatnonzero(pairing >= 0)
        unmatched = np.flatnonzero(pairing < 0)
        existence = self.existence.copy()
        if len(matched):
            existence[pairing[matched]] = combine_existence(
                existence[pairing[matched]], np.asarray(local.existence)[matched]
            )
        self.existence = np.concatenate([existence, np.asarray(local.existence)[unmatched]])
        old_ids = self.ids
        self.ids = np.concatenate([old_ids, np.asarray(local.ids, dtype=np.int64)[unmatched]])
        id_map = {int(local.ids[i]): int(local.ids[i]) for i in unmatched}
        id_map.update({int(local.ids[i]): int(old_ids[pairing[i]]) for i in matched})
        self._refresh()
        return FusionReport(
            id_map=id_map, n_matched=len(matched), n_new=len(unmatched),
            loop_closures=self.loop_closures[n_closures_before:],
        )

    # ------------------------------------------------------------------ global estimate
    def _refresh(self) -> None:
        """``x``, ``P``: the chain from the anchor (module docstring)."""
        A = self._anchor
        mu = self.info.mean() if self.info.n_entities else np.zeros(0)
        N = self.n_features
        n_g = 3 + 2 * N
        n_A = len(A.cov)
        x = np.empty(n_g)
        J_A = np.zeros((n_g, n_A))
        J_R = np.zeros((n_g, self.info.dim))
        anchored = {int(g): k for k, g in enumerate(A.ids)}
        poses: dict[int, tuple] = {}

        def pose_at(k):
            if k not in poses:
                require(k >= A.index, "feature frame", k, f">= the anchor index {A.index}")
                d_ents = self._d[A.index : k]
                ds = np.array([self._mean_of(e, mu) for e in d_ents]).reshape(-1, 3)
                G, J_ds, J_start = chain_compose(A.pose, ds)
                poses[k] = (G[-1], J_start, list(zip(d_ents, J_ds, strict=True)))
            return poses[k]

        def add_chain(rows, J_out, J_start, chain):
            J_A[rows, :3] += J_out @ J_start
            for e, J in chain:
                o = self.info.offset(e)
                J_R[rows, o : o + 3] += J_out @ J

        v, J_start, chain = pose_at(len(self._d))
        x[:3] = v
        x[2] = wrap_angle(x[2])
        add_chain(slice(0, 3), np.eye(3), J_start, chain)
        for n, gid in enumerate(self.ids):
            rows = slice(3 + 2 * n, 5 + 2 * n)
            k = anchored.get(int(gid))
            if k is not None:
                x[rows] = A.means[k]
                J_A[rows, 3 + 2 * k : 5 + 2 * k] = np.eye(2)
                continue
            ent, f = self._coords[int(gid)][0]
            pose_f, J_start, chain = pose_at(f)
            lm = self._mean_of(ent, mu)
            x[rows] = transform_point(pose_f, lm)
            J_p, J_l = transform_point_jacobians(pose_f, lm)
            add_chain(rows, J_p, J_start, chain)
            o = self.info.offset(ent)
            J_R[rows, o : o + 2] += J_l
        P = J_A @ A.cov @ J_A.T
        if self.info.dim:
            P = P + J_R @ self.info.factor().solve(J_R.T)
        self.x = x
        self.P = symmetrise(P)

    def apply_optimum(self, pose_index: int, x, P) -> None:
        """Make an optimum over ``[v-, features in id order]`` the anchor (optimise_submaps)."""
        require(
            pose_index == len(self._d),
            "pose_index",
            pose_index,
            f"the current fusion pose {len(self._d)} (optimise after the last fusion)",
        )
        n = 3 + 2 * self.n_features
        x = np.asarray(x, dtype=float)
        P = np.asarray(P, dtype=float)
        require(x.shape == (n,) and P.shape == (n, n), "x, P", (x.shape, P.shape), f"({n},), "
                f"({n}, {n})")
        self._anchor = _Anchor(
            pose_index, x[:3].copy(), self.ids.copy(), x[3:].reshape(-1, 2).copy(), symmetrise(P)
        )
        self._refresh()


# --------------------------------------------------------------------------- factory
def make_back_end(kind: str, initial_pose=None, initial_pose_cov=None, **options):
    """A sub-map back-end by name: ``"ekf"`` (BB's :class:`GlobalMap`) or ``"relative"``.

    ``options`` go to the constructor (``gate_probability``, ``node_budget``; for ``"relative"``
    also ``innovation_sigmas``, ``max_chain``, ``min_variance``). The initial pose and covariance
    are recorded on the back-end (``initial_pose``, ``initial_pose_cov``): the gauge of
    :func:`optimise_submaps`.
    """
    require(kind in BACK_END_KINDS, "back_end", kind, f"one of {BACK_END_KINDS}")
    if kind == "relative":
        return RelativeBackEnd(initial_pose, initial_pose_cov, **options)
    back = GlobalMap(initial_pose, initial_pose_cov, **options)
    if not hasattr(back, "initial_pose"):
        back.initial_pose = back.x[:3].copy()
    if not hasattr(back, "initial_pose_cov"):
        back.initial_pose_cov = back.P[:3, :3].copy()
    return back
