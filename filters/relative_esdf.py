"""Relative-coordinate ESDF (CM section III.B) with loop-closure detection and the optimiser.

State (CM (6)-(7)): every delayed pose relative to the previous one, ``d_k^R`` with
``x_k = x_{k-1} (+) d_k^R``, and every landmark relative to the delayed pose that first saw it,
``d_k^{L_j}``. The start pose ``x_0`` is known and is the gauge.

* Odometry (CM (9)): the odometry compounded between epochs, ``u_k``, is a *linear* observation of
  the new relative pose, ``u_k = d_k^R + w_k`` with ``w_k ~ N(0, Q_k)`` (``Q_k`` the compounded
  covariance, :class:`filters.esdf.OdometryAccumulator`); integrated with CM (4)-(5) it touches one
  diagonal block, so it is exact and constant time.
* First observation of landmark ``j`` at epoch ``k``: ``z = h(0, d_k^{L_j})`` depends on the new
  coordinates only (the frame is the observing pose itself).
* Re-observation at epoch ``l`` of a landmark whose current coordinates live in frame ``k``
  (CM (11)): ``z_l = h(d_{k+1}^R (+) ... (+) d_l^R, d_k^{L_j})``, linearised at the current
  relative means and integrated with CM (4)-(5); it touches the ``l - k`` relative poses of the
  chain and the landmark.

Loop closure (CM Definition 1). A re-observation is a loop closure when

1. the chain is long: ``l - k > max_chain`` (CM bound the filter's time per re-observation; the
   time is proportional to the chain length, so we bound the length), or
2. the innovation is too large: ``||nu|| > innovation_sigmas * sigma`` (CM: 2 sigma), with
   ``sigma^2`` the largest eigenvalue of an *upper bound* of the innovation covariance built from
   the measurement covariances only. The bound: each relative quantity's information contains the
   single measurement that created it -- ``Q_i^-1`` for ``d_i^R`` (CM (9)), and
   ``H_m^T R^-1 H_m`` for a landmark's coordinates (its first observation, which involves those
   coordinates alone) -- plus other, positive semi-definite terms. Hence the joint information of
   the involved quantities dominates ``blockdiag(Q_i^-1, (G_z R G_z^T)^-1)`` (the Schur
   complement of a sum of PSD terms dominates that of the creating terms, which touch the
   involved block only), so their covariance is bounded by ``blockdiag(Q_i, G_z R G_z^T)`` and

       S = H P H^T + R  <=  S_bar = sum_i H_i Q_i H_i^T + H_m (G_z R G_z^T) H_m^T + R,

   whose largest eigenvalue bounds that of ``S``. The threshold is therefore conservative
   (larger than the true 2 sigma), as CM require.

At a loop closure the observation is *not* integrated through the chain; the landmark gets new,
redundant coordinates in the current frame (initialised from this observation), which later
re-observations use, so the filter never linearises a long chain. The redundancy -- the same
landmark expressed in two frames -- is what :meth:`RelativeESDF.optimise` exploits
(:mod:`filters.optimiser`, CM III.C). Optimising does not change the filter; its result replaces
the global estimates of the entities it covers until the next optimisation, and entities added
later are chained onto it.

A compass reading (:meth:`RelativeESDF.update_heading`) is a redundant quantity of the same kind:
a ``"heading"`` quantity of the current pose relative to the gauge, stored with its own
information and used by the optimiser only (integrating it through the whole chain would fill
``Lambda``).

Mean recovery: a window solve as in :class:`filters.esdf.ESDF` (block Gauss-Seidel on the
entities this update touched plus the last ``recovery_window`` relative poses). Relative
coordinates move little once estimated, so the window is accurate; reported estimates use the
exact sparse solve.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from filters.esdf import (
    DelayedStateFilter,
    check_initial_pose,
    check_observations,
)
from filters.geometry import compose, transform_point_jacobians, wrap_angle
from filters.information import symmetrise
from filters.models import (
    innovation,
    inverse_observe,
    inverse_observe_jacobians,
    observe,
    observe_jacobians,
)
from filters.optimiser import (
    HEADING,
    POINT,
    POSE,
    OptimiserResult,
    RelativeProblem,
    RelativeQuantity,
)
from filters.types import FeatureIds, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopClosure:
    """One declared loop closure (CM Definition 1).

    ``reason`` is ``"chain"`` (chain longer than ``max_chain``) or ``"innovation"``
    (``||nu|| > innovation_sigmas * sigma``); ``innovation_ratio`` is ``||nu|| / (k sigma)``
    (NaN when the chain test fired first and the long chain was not evaluated).
    """

    epoch: int
    landmark_id: int
    feature_id: int
    chain_length: int
    innovation_ratio: float
    reason: str
    coordinates_entity: int


def chain_compose(start, ds):
    """Compose ``start (+) d_1 (+) ... (+) d_c`` with the Jacobians of the end pose.

    Returns ``(G, J_ds, J_start)``: ``G`` (c + 1, 3) the partial compositions (``G[0] = start``),
    ``J_ds`` (c, 3, 3) the Jacobians of ``G[c]`` w.r.t. each ``d_i`` and ``J_start`` (3, 3) w.r.t.
    ``start``. With ``G_c = G_i (+) S``: ``dG_c/dd_i = J_a(G_i, S) R(theta_{i-1})``, where
    ``J_a(G_i, S)`` depends on ``G_c - G_i`` only. Headings are left unwrapped.
    """
    ds = np.asarray(ds, dtype=float).reshape(-1, 3)
    G = np.empty((len(ds) + 1, 3))
    G[0] = start
    for i, d in enumerate(ds):
        G[i + 1] = compose(G[i], d)
        G[i + 1, 2] = G[i, 2] + d[2]
    end = G[-1]

    def ja(p):  # d (p (+) S) / dp at fixed S, for every row p of G
        out = np.zeros((len(p), 3, 3))
        out[:, 0, 0] = out[:, 1, 1] = out[:, 2, 2] = 1.0
        out[:, 0, 2] = -(end[1] - p[:, 1])
        out[:, 1, 2] = end[0] - p[:, 0]
        return out

    Ja = ja(G)
    c, s = np.cos(G[:-1, 2]), np.sin(G[:-1, 2])
    Rb = np.zeros((len(ds), 3, 3))
    Rb[:, 0, 0], Rb[:, 0, 1], Rb[:, 1, 0], Rb[:, 1, 1] = c, -s, s, c
    Rb[:, 2, 2] = 1.0
    return G, Ja[1:] @ Rb, Ja[0]


class RelativeESDF(DelayedStateFilter):
    """CM's relative-coordinate ESDF with known data association.

    Parameters (beyond those of :class:`filters.esdf.ESDF`)
    ----------
    max_chain : a re-observation through more than this many relative poses is a loop closure
        (1..100000).
    innovation_sigmas : the innovation threshold in sigmas (CM: 2), in (0, 100].
    recovery_window : relative poses in the recovery window (1..1000).
    """

    def __init__(
        self,
        sensor,
        clutter=None,
        odometry_noise=None,
        ids: FeatureIds | None = None,
        *,
        initial_pose=None,
        max_chain: int = 10,
        innovation_sigmas: float = 2.0,
        recovery_window: int = 4,
        min_odometry_var: float = 1e-10,
    ):
        super().__init__(sensor, clutter, odometry_noise, ids, recovery_window, min_odometry_var)
        require(
            isinstance(max_chain, int) and 1 <= max_chain <= 100000,
            "max_chain",
            max_chain,
            "an integer in [1, 100000]",
        )
        check_range("innovation_sigmas", innovation_sigmas, 0.0, 100.0, low_open=True)
        self.initial_pose = check_initial_pose(initial_pose)
        self.max_chain = max_chain
        self.innovation_sigmas = float(innovation_sigmas)
        self._quantity: list[RelativeQuantity] = []  # per relative entity
        self._bound: list[np.ndarray] = []  # per relative entity: measurement-only covariance
        self._entity_kinds: list[str] = [POSE]  # global entities (optimiser structure)
        self._pose_g: list[int] = [0]  # pose number -> global entity
        self._pose_rel: list[int] = [-1]  # pose number -> relative entity of d_k (none for x_0)
        self._lm_g: dict[int, int] = {}
        self._lm_fid: dict[int, int] = {}
        self._lm_coords: dict[int, list[tuple[int, int]]] = {}  # id -> [(rel entity, frame pose)]
        self.loop_closures: list[LoopClosure] = []
        self.last_loop_closure = False
        self.last_innovation_ratio = 0.0
        self.last_optimisation: OptimiserResult | None = None
        self._opt_poses = 0  # poses covered by the last optimisation
        self._opt_version = 0
        self._anchor_cov: dict[int, np.ndarray] = {}

    # ----------------------------------------------------------------- bookkeeping
    @property
    def n_delayed_poses(self) -> int:
        return len(self._pose_g)

    @property
    def n_landmarks(self) -> int:
        return len(self._lm_g)

    @property
    def n_loop_closures(self) -> int:
        return len(self.loop_closures)

    @property
    def redundancies(self) -> dict[int, list[int]]:
        """Landmark id -> its relative-coordinate entities, for landmarks with more than one."""
        return {j: [e for e, _ in c] for j, c in self._lm_coords.items() if len(c) > 1}

    def _new_relative(self, size, mean, quantity, bound) -> int:
        e = self.info.add_entity(size)
        self._mu.append(np.asarray(mean, dtype=float).copy())
        self._quantity.append(quantity)
        self._bound.append(np.asarray(bound, dtype=float))
        return e

    # ----------------------------------------------------------------- filter steps
    def _epoch_pose(self) -> int:
        """Pose number of this epoch; a new ``d_k^R`` integrated with CM (9) if the robot moved."""
        if self._odo.steps == 0:
            return len(self._pose_g) - 1
        k = len(self._pose_g)
        g = len(self._entity_kinds)
        self._entity_kinds.append(POSE)
        Q = self._odo.cov
        W = self._odo.information(self.min_odometry_var)
        delta = self._odo.delta.copy()
        e = self._new_relative(3, delta, RelativeQuantity(POSE, self._pose_g[-1], g), Q)
        self.info.add_information([e], [np.eye(3)], W, delta)  # CM (9): H = I, exact
        self._pose_g.append(g)
        self._pose_rel.append(e)
        self._odo.reset()
        return k

    def _add_coordinates(self, j: int, k: int, z) -> int:
        """New coordinates of landmark ``j`` in the frame of pose ``k`` from observation ``z``."""
        m = inverse_observe(np.zeros(3), z)
        _, G_z = inverse_observe_jacobians(np.zeros(3), z)
        e = self._new_relative(
            2, m, RelativeQuantity(POINT, self._pose_g[k], self._lm_g[j]), G_z @ self._R @ G_z.T
        )
        _, H_m = observe_jacobians(np.zeros(3), m)
        rhs = innovation(z, observe(np.zeros(3), m)) + H_m @ m
        self.info.add_information([e], [H_m], self._R_inv, rhs)
        self._lm_coords[j].append((e, k))
        return e

    def update(self, z, ids=None) -> None:
        """Integrate observations ``z`` (K, 2) of landmarks ``ids`` (K,), -1 for false alarms.

        New landmarks get coordinates in this epoch's frame; re-observations are tested for a
        loop closure (module docstring) and otherwise integrated through CM (11), all linearised
        at the relative means before this update.
        """
        z, ids = check_observations(z, ids)
        self.last_associations = np.full(len(z), -1, dtype=np.int64)
        self.last_loop_closure = False
        self.last_innovation_ratio = 0.0
        valid = np.flatnonzero(ids >= 0)
        if valid.size == 0:
            return
        k = self._epoch_pose()
        touched = [self._pose_rel[k]] if k > 0 else []
        pending = []
        for i in valid:
            j = int(ids[i])
            if j not in self._lm_g:
                self._lm_g[j] = len(self._entity_kinds)
                self._entity_kinds.append(POINT)
                self._lm_fid[j] = int(self.ids.new(1)[0])
                self._lm_coords[j] = []
                touched.append(self._add_coordinates(j, k, z[i]))
            else:
                factor = self._reobservation(i, j, k, z[i])
                if factor is not None:
                    pending.append(factor)
            self.last_associations[i] = self._lm_fid[j]
        for ents, Hs, rhs in pending:
            self.info.add_information(ents, Hs, self._R_inv, rhs)
            touched.extend(ents)
        self._recover(touched)

    def _reobservation(self, i, j, k, z):
        """CM (11) for one re-observation, or a loop closure (returns None)."""
        ent, f = self._lm_coords[j][-1]
        chain = k - f
        if chain > self.max_chain:
            self._close_loop(j, k, z, chain, float("nan"), "chain")
            return None
        d_ents = [self._pose_rel[n] for n in range(f + 1, k + 1)]
        ds = np.array([self._mu[e] for e in d_ents]).reshape(-1, 3)
        G, J_ds, _ = chain_compose(np.zeros(3), ds)
        T = G[-1]
        m = self._mu[ent]
        H_T, H_m = observe_jacobians(T, m)
        nu = innovation(z, observe(T, m))
        H_ds = H_T @ J_ds  # (c, 2, 3)
        S_bar = self._R + H_m @ self._bound[ent] @ H_m.T
        for H, e in zip(H_ds, d_ents, strict=True):
            S_bar = S_bar + H @ self._bound[e] @ H.T
        sigma = np.sqrt(np.linalg.eigvalsh(symmetrise(S_bar))[-1])
        ratio = float(np.linalg.norm(nu) / (self.innovation_sigmas * sigma))
        self.last_innovation_ratio = max(self.last_innovation_ratio, ratio)
        if ratio > 1.0:
            self._close_loop(j, k, z, chain, ratio, "innovation")
            return None
        ents = [*d_ents, ent]
        Hs = [*H_ds, H_m]
        rhs = nu + sum(H @ self._mu[e] for H, e in zip(Hs, ents, strict=True))
        return ents, Hs, rhs

    def _close_loop(self, j, k, z, chain, ratio, reason):
        e = self._add_coordinates(j, k, z)
        self.loop_closures.append(
            LoopClosure(len(self._pose_g) - 1, j, self._lm_fid[j], chain, ratio, reason, e)
        )
        self.last_loop_closure = True
        logger.debug("loop closure on landmark %d (%s, chain %d)", j, reason, chain)

    def update_heading(self, theta, std_rad) -> None:
        """A compass reading: a redundant ``"heading"`` quantity for the optimiser (no chain)."""
        self._check_heading(theta, std_rad)
        k = self._epoch_pose()
        if k == 0:
            return  # the start pose is the gauge: known
        chain_heading = sum(self._mu[self._pose_rel[n]][2] for n in range(1, k + 1))
        value = chain_heading + wrap_angle(theta - self.initial_pose[2] - chain_heading)
        var = float(std_rad) ** 2
        e = self._new_relative(
            1, [value], RelativeQuantity(HEADING, 0, self._pose_g[k]), np.array([[var]])
        )
        self.info.add_information([e], [np.eye(1)], np.array([[1.0 / var]]), np.array([value]))

    def _recover(self, touched) -> None:
        active = list(touched)
        k = len(self._pose_g) - 1
        active.extend(self._pose_rel[n] for n in range(max(1, k - self.recovery_window + 1), k + 1))
        if active:
            for e, m in self.info.solve_window(active, self._mu).items():
                self._mu[e] = m

    # ----------------------------------------------------------------- optimiser
    def relative_problem(self) -> RelativeProblem:
        """The optimiser's input: global entities, relative quantities, ``(eta, Lambda)``."""
        eta, Lambda = self.information()
        return RelativeProblem(
            self._entity_kinds, self._quantity, eta, Lambda, gauge=0, gauge_pose=self.initial_pose
        )

    def optimise(self, method: str = "reduced", **options) -> OptimiserResult:
        """CM III.C: global coordinates of every pose and landmark from the relative state."""
        require(self.info.n_entities > 0, "state", "empty", "at least one relative quantity")
        result = self.relative_problem().optimise(method, **options)
        self.last_optimisation = result
        self._opt_poses = len(self._pose_g)
        self._opt_version += 1
        self._anchor_cov = {}
        return result

    # ----------------------------------------------------------------- estimates
    def _cache_stamp(self):
        return (self.info.version, self._opt_version)

    def _base(self, k):
        """The global anchor for pose ``k``: (pose number b <= k, mean, covariance)."""
        if self.last_optimisation is not None and self._opt_poses > 0:
            b = min(k, self._opt_poses - 1)
            g = self._pose_g[b]
            res = self.last_optimisation
            if g not in self._anchor_cov:
                self._anchor_cov[g] = res.covariance(g)
            return b, res.means[g].copy(), self._anchor_cov[g]
        return 0, self.initial_pose.copy(), np.zeros((3, 3))

    def _global_functional(self, f, mu):
        """Global pose of delayed pose ``f``: mean, base covariance term, chain functional."""
        b, base_mean, base_cov = self._base(f)
        d_ents = [self._pose_rel[n] for n in range(b + 1, f + 1)]
        ds = np.array([self.info.mean_of(e, mu) for e in d_ents]).reshape(-1, 3)
        G, J_ds, J_start = chain_compose(base_mean, ds)
        return G[-1], J_start @ base_cov @ J_start.T, list(zip(d_ents, J_ds, strict=True))

    def _delayed_pose(self):
        """Global last delayed pose: (optimised anchor) (+) relative chain (:meth:`pose` adds
        the pending odometry).

        Before any optimisation the anchor is the known start pose and the covariance is exact
        for the linearised chain (``J Lambda^-1 J^T``). After an optimisation the anchor is the
        optimum with its Gauss-Newton covariance, and the chain added since is taken as
        independent of it (an approximation: both depend on shared landmark observations).
        """

        def fn():
            k = len(self._pose_g) - 1
            mean, base_term, functional = self._global_functional(k, self.info.mean())
            chain = self.info.covariance_blocks([functional])[0] if functional else 0.0
            return mean, symmetrise(base_term + chain)

        return self._cached("pose", fn)

    def trajectory(self) -> np.ndarray:
        """Global means of all delayed poses (K, 3), headings wrapped."""
        mu = self.info.mean()
        out = np.empty((len(self._pose_g), 3))
        for k in range(len(self._pose_g)):
            out[k] = self._global_functional(k, mu)[0]
        out[:, 2] = wrap_angle(out[:, 2])
        return out

    def landmarks(self) -> LandmarkEstimate:
        """Landmarks in global coordinates (one per id, from its first coordinates).

        Landmarks covered by the last optimisation take its optimum and Gauss-Newton covariance;
        the others are their first frame's global pose (+) their relative coordinates, with
        covariance ``J Lambda^-1 J^T`` plus the anchor's term.
        """

        def fn():
            if not self._lm_g:
                return LandmarkEstimate.empty()
            mu = self.info.mean()
            res = self.last_optimisation
            n_opt_entities = 0 if res is None else len(res.means)
            ext = list(self._lm_g)
            means = np.empty((len(ext), 2))
            covs = np.empty((len(ext), 2, 2))
            functionals, extra, rows = [], [], []
            opt_rows, opt_ents = [], []
            for n, j in enumerate(ext):
                g = self._lm_g[j]
                if g < n_opt_entities:
                    opt_rows.append(n)
                    opt_ents.append(g)
                    continue
                ent, f = self._lm_coords[j][0]
                pose_mean, base_term, chain = self._global_functional(f, mu)
                d = self.info.mean_of(ent, mu)
                Jp, Jd = transform_point_jacobians(pose_mean, d)
                c, s = np.cos(pose_mean[2]), np.sin(pose_mean[2])
                means[n] = pose_mean[:2] + np.array([c * d[0] - s * d[1], s * d[0] + c * d[1]])
                functionals.append([(e, Jp @ J) for e, J in chain] + [(ent, Jd)])
                extra.append(Jp @ base_term @ Jp.T)
                rows.append(n)
            if functionals:
                for n, C, X in zip(
                    rows, self.info.covariance_blocks(functionals), extra, strict=True
                ):
                    covs[n] = symmetrise(C + X)
            if opt_rows:
                means[opt_rows] = res.means[opt_ents, :2]
                covs[opt_rows] = np.array(res.marginals(opt_ents))
            fids = np.array([self._lm_fid[j] for j in ext], dtype=np.int64)
            return LandmarkEstimate(fids, means, covs, np.ones(len(ext)))

        return self._cached("landmarks", fn)

    def landmark_ids(self) -> np.ndarray:
        """The external (association) ids of the landmarks, in :meth:`landmarks` order."""
        return np.array(list(self._lm_g), dtype=np.int64)
