"""Nonlinear optimisation of the sub-map back-ends (DESIGN 3.10) and the relative back-end.

Sub-maps as relative constraints
--------------------------------
Every fused sub-map ``s`` (:class:`filters.submap.StoredSubmap`) is a Gaussian
``N(r_s, P_s)`` over *relative* quantities: its end pose (the local vehicle pose at the fusion)
and its features, all in the frame of its origin pose. Its origin is the global vehicle pose at the
previous fusion -- the end pose of sub-map ``s - 1`` -- and sub-map 0 starts at the initial pose,
the gauge. In the notation of CM III.C the sub-maps are independent measurements of
``r = psi(tau)``, where the unknowns ``tau`` are the global coordinates of

* the chain of fusion poses ``x_0 (gauge), x_1, ..., x_S`` (``x_{s+1}`` = end of sub-map ``s``),
* every global feature; a local feature enters through ``StoredSubmap.id_map`` (local id ->
  global id), so several sub-maps observing one global feature are exactly the loop-closure
  redundancy that CM's optimiser exploits (CM Fig. 1),

and ``psi_s(tau) = [relative(x_s, x_{s+1}); point_to_frame(x_s, m_j) ...]`` (inverse
compositions). The cost is CM (12) summed over sub-maps,

    c(tau) = sum_s (r_s - psi_s(tau))^T P_s^-1 (r_s - psi_s(tau)),

i.e. CM (12)/(13) with the block-diagonal information ``Lambda = blockdiag(P_s^-1)``. It is
minimised by :class:`filters.optimiser.RelativeProblem` (one optimiser for the relative ESDF and for
the sub-maps): Gauss-Newton / Levenberg-Marquardt, or CM's reduced quasi-Newton method. Each
``P_s^-1`` is obtained from a Cholesky factor of the (small) sub-map covariance ``P_s``; no
inverse of the stacked system is ever formed. A sub-map covariance with an eigenvalue below
``min_variance`` (the EKF front-end's pose block is exactly zero right after a restart, so a fusion
with no motion gives a singular ``P_s``) is floored there first (an eigen-decomposition of that
block alone).

With an uncertain initial pose (``initial_pose_cov`` not zero) a fixed world frame becomes the
gauge and the initial pose an unknown with the prior ``N(x_0, P_0)`` as one more constraint.

Write-back (:func:`optimise_submaps`): the global estimate ``(x, P)`` of the back-end -- vehicle
pose ``v-`` (the origin of the current, unfused local map, which is the end pose ``x_S`` of the
last fused sub-map) and the features by id -- is replaced by the optimum and its Gauss-Newton
covariance: the ``[x_S, m_1, ..., m_N]`` block of ``(J^T Lambda J)^-1`` at the optimum, solved for
those columns only with a sparse factorisation. Ids and existence probabilities are kept, so
:meth:`SubmapSLAM.pose` (``v- (+)`` local pose) stays consistent. Optimising twice in a row gives
the same result: the problem depends on the stored sub-maps only.

The relative back-end (:class:`RelativeBackEnd`)
------------------------------------------------
CM's representation at the sub-map level (CM III.B, DESIGN "The hybrid system"): fused sub-maps
are kept only in relative coordinates, in information form ``(eta, Lambda)``
(:class:`filters.esdf.SparseInformation`) over

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
import time
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from filters.association import DEFAULT_NODE_BUDGET, jcbb, point_difference_candidates
from filters.esdf import SparseInformation, sparse_spd_factor, symmetrise
from filters.geometry import (
    point_to_frame,
    point_to_frame_jacobians,
    transform_point,
    transform_point_jacobians,
    wrap_angle,
)
from filters.optimiser import (
    METHODS,
    POINT,
    POSE,
    GaussianConstraint,
    OptimiserResult,
    RelativeProblem,
    RelativeQuantity,
)
from filters.relative_esdf import chain_compose
from filters.submap import GlobalMap, combine_existence
from filters.types import FusionReport, GaussianMap
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

BACK_END_KINDS = ("ekf", "relative")
DEFAULT_MIN_VARIANCE = 1e-10
"""Floor (m^2, rad^2) on the eigenvalues of a sub-map covariance (a std of 1e-5)."""


# --------------------------------------------------------------------------- sub-map Gaussians
def floored_covariance(P, min_variance: float = DEFAULT_MIN_VARIANCE) -> np.ndarray:
    """``P`` symmetrised, with eigenvalues below ``min_variance`` raised to it (else unchanged)."""
    P = symmetrise(np.asarray(P, dtype=float))
    if P.size == 0:
        return P
    w, V = np.linalg.eigh(P)
    if w[0] >= min_variance:
        return P
    return symmetrise((V * np.maximum(w, min_variance)) @ V.T)


def gaussian_information(P, min_variance: float = DEFAULT_MIN_VARIANCE) -> np.ndarray:
    """``P^-1`` of one (small) sub-map covariance through its Cholesky factor (floored first)."""
    P = floored_covariance(P, min_variance)
    if P.size == 0:
        return P
    return symmetrise(cho_solve(cho_factor(P), np.eye(len(P))))


def _is_zero(P) -> bool:
    return P is None or not np.any(np.asarray(P, dtype=float))


@dataclass
class SubmapProblem:
    """The optimiser's problem built from stored sub-maps, with the entity book-keeping.

    ``pose_entity[k]``: entity of fusion pose ``k`` (0 = initial pose); ``feature_entity[gid]``:
    entity of global feature ``gid``; ``world``: a fixed world frame is the gauge (entity 0)
    because the initial pose is uncertain.
    """

    problem: RelativeProblem
    pose_entity: np.ndarray
    feature_entity: dict
    world: bool

    @property
    def n_poses(self) -> int:
        return len(self.pose_entity)

    def tau_of(self, poses, features: dict) -> np.ndarray:
        """``tau`` from global poses (n_poses, 3) and feature positions ``{gid: (2,)}``."""
        p = self.problem
        n = len(p.entity_kinds)
        P = np.zeros((n, 2))
        Th = np.zeros(n)
        poses = np.asarray(poses, dtype=float)
        require(
            poses.shape == (self.n_poses, 3), "poses", poses.shape, f"({self.n_poses}, 3)"
        )
        P[self.pose_entity] = poses[:, :2]
        Th[self.pose_entity] = poses[:, 2]
        missing = [g for g in self.feature_entity if g not in features]
        require(not missing, "features", f"missing ids {missing[:5]}", "every optimised feature")
        for gid, e in self.feature_entity.items():
            P[e] = np.asarray(features[gid], dtype=float)
        return p.pack(P, Th)

    def cost(self, tau) -> float:
        """CM (12) at ``tau``: ``sum_s (psi_s - r_s)^T P_s^-1 (psi_s - r_s)``."""
        return self.problem.weighted_residual_cost(tau)


def build_submap_problem(
    submaps,
    initial_pose,
    initial_pose_cov=None,
    *,
    min_variance: float = DEFAULT_MIN_VARIANCE,
) -> SubmapProblem:
    """CM (12) over the stored sub-maps (module docstring): one constraint per sub-map."""
    submaps = list(submaps)
    require(len(submaps) > 0, "submaps", submaps, "at least one fused sub-map")
    check_range("min_variance", min_variance, 0.0, 1.0, low_open=True)
    x0 = np.asarray(initial_pose, dtype=float)
    require(
        x0.shape == (3,) and bool(np.all(np.isfinite(x0))),
        "initial_pose",
        initial_pose,
        "a finite (x, y, theta)",
    )
    world = not _is_zero(initial_pose_cov)
    n_poses = 1 + max(int(s.end_index) for s in submaps)
    kinds = [POSE] if world else []
    pose_entity = np.arange(n_poses) + len(kinds)
    kinds += [POSE] * n_poses
    feature_entity: dict[int, int] = {}
    constraints = []
    if world:
        P0 = np.asarray(initial_pose_cov, dtype=float)
        require(P0.shape == (3, 3), "initial_pose_cov", P0.shape, "a (3, 3) matrix")
        constraints.append(
            GaussianConstraint(
                (RelativeQuantity(POSE, 0, int(pose_entity[0])),),
                x0,
                gaussian_information(P0, min_variance),
            )
        )
    for n, s in enumerate(submaps):
        g = s.gaussian
        o, e = int(s.origin_index), int(s.end_index)
        require(
            0 <= o < e < n_poses,
            f"submaps[{n}].origin_index",
            (o, e),
            "origin_index < end_index, both >= 0",
        )
        qs = [RelativeQuantity(POSE, int(pose_entity[o]), int(pose_entity[e]))]
        for lid in np.asarray(g.ids, dtype=np.int64):
            gid = s.id_map.get(int(lid))
            require(gid is not None, f"submaps[{n}].id_map", int(lid), "to map every local id")
            ent = feature_entity.get(int(gid))
            if ent is None:
                ent = len(kinds)
                kinds.append(POINT)
                feature_entity[int(gid)] = ent
            qs.append(RelativeQuantity(POINT, int(pose_entity[o]), ent))
        x = np.asarray(g.x, dtype=float).copy()
        x[2] = wrap_angle(x[2])
        constraints.append(
            GaussianConstraint(tuple(qs), x, gaussian_information(g.P, min_variance))
        )
    problem = RelativeProblem.from_constraints(
        kinds, constraints, gauge=0, gauge_pose=np.zeros(3) if world else x0
    )
    return SubmapProblem(problem, pose_entity, feature_entity, world)


def joint_covariance(result: OptimiserResult, entities) -> np.ndarray:
    """Joint Gauss-Newton covariance of ``entities``: a block of ``(J^T Lambda J)^-1``.

    Solves for the listed entities' columns only (sparse factorisation, no inverse); the gauge
    contributes zero rows and columns. Poses take 3 rows, points 2.
    """
    p = result.problem
    entities = [int(e) for e in entities]
    dims = [3 if p.entity_kinds[e] == POSE else 2 for e in entities]
    starts = np.concatenate([[0], np.cumsum(dims)]).astype(int)
    out_idx, var_idx = [], []
    for e, s0 in zip(entities, starts[:-1], strict=True):
        cols = p.variable_columns(e)
        out_idx.extend(range(s0, s0 + len(cols)))
        var_idx.extend(cols)
    C = np.zeros((starts[-1], starts[-1]))
    if var_idx:
        J = p.psi_jacobian(result.tau)
        H = (J.T @ p.Lambda @ J).tocsc()
        E = np.zeros((p.n_variables, len(var_idx)))
        E[np.asarray(var_idx), np.arange(len(var_idx))] = 1.0
        X = sparse_spd_factor(H).solve(E)
        oi = np.asarray(out_idx)
        C[np.ix_(oi, oi)] = X[np.asarray(var_idx)]
    return symmetrise(C)


# --------------------------------------------------------------------------- optimise()
@dataclass
class OptimiseResult:
    """Outcome of :func:`optimise_submaps`.

    ``x``, ``P``, ``ids``: the global estimate written back (``[v-, m_1, ..., m_N]``, features in
    the back-end's id order). ``cost`` and ``initial_cost``: CM (12) at the optimum and at the
    optimiser's start (the chain of sub-maps). ``time_s`` covers optimisation, covariance and
    write-back. ``optimiser`` / ``problem`` are None when there was no sub-map to optimise.
    """

    method: str
    n_submaps: int
    pose_index: int
    iterations: int
    converged: bool
    time_s: float
    cost: float
    initial_cost: float
    x: np.ndarray
    P: np.ndarray
    ids: np.ndarray
    optimiser: OptimiserResult | None = None
    problem: SubmapProblem | None = None

    @property
    def optimiser_time_s(self) -> float:
        return 0.0 if self.optimiser is None else self.optimiser.time_s


def _initial_pose_of(back_end, initial_pose, initial_pose_cov):
    if initial_pose is None:
        initial_pose = getattr(back_end, "initial_pose", None)
    require(
        initial_pose is not None,
        "initial_pose",
        None,
        "given, or stored by the back-end (make_back_end records it as back_end.initial_pose)",
    )
    if initial_pose_cov is None:
        initial_pose_cov = getattr(back_end, "initial_pose_cov", None)
    return np.asarray(initial_pose, dtype=float), initial_pose_cov


def optimise_submaps(
    submap_slam,
    method: str = "gauss-newton",
    *,
    initial_pose=None,
    initial_pose_cov=None,
    min_variance: float = DEFAULT_MIN_VARIANCE,
    **options,
) -> OptimiseResult:
    """DESIGN 3.10: minimise CM (12) over the stored sub-maps and write the optimum back.

    ``submap_slam``: a :class:`filters.submap.SubmapSLAM` (its ``submaps`` and ``back_end``).
    ``method``: ``"gauss-newton"``, ``"levenberg-marquardt"`` or ``"reduced"`` (CM's reduced
    quasi-Newton); ``options`` go to :meth:`RelativeProblem.optimise`. The initial pose (the
    gauge) and its covariance come from the back-end (``initial_pose``, ``initial_pose_cov``
    attributes, set by :func:`make_back_end`) unless given. The back-end's ``x``/``P`` become the
    optimum over ``[v-, features]`` and its Gauss-Newton covariance (a back-end with
    ``apply_optimum``, i.e. :class:`RelativeBackEnd`, takes it as its new anchor); ids and
    existence are kept. Calls ``submap_slam._optimised()`` (book-keeping) in every case; with no
    fused sub-map nothing else changes.
    """
    require(method in METHODS, "method", method, f"one of {METHODS}")
    t0 = time.perf_counter()
    back = submap_slam.back_end
    submaps = list(submap_slam.submaps)
    x0, P0 = _initial_pose_of(back, initial_pose, initial_pose_cov)
    if not submaps:
        submap_slam._optimised()
        return OptimiseResult(
            method, 0, 0, 0, True, time.perf_counter() - t0, 0.0, 0.0,
            np.asarray(back.x).copy(), np.asarray(back.P).copy(), np.asarray(back.ids).copy(),
        )
    sp_problem = build_submap_problem(submaps, x0, P0, min_variance=min_variance)
    problem = sp_problem.problem
    tau0 = problem.initial_guess()
    initial_cost = problem.weighted_residual_cost(tau0)
    res = problem.optimise(method, tau0, **options)
    pose_index = sp_problem.n_poses - 1
    ids = np.asarray(back.ids, dtype=np.int64)
    missing = [int(g) for g in ids if int(g) not in sp_problem.feature_entity]
    require(
        not missing,
        "back_end.ids",
        missing[:5],
        "ids of features that came from fused sub-maps (listed in their id_map)",
    )
    v_ent = int(sp_problem.pose_entity[pose_index])
    f_ents = [sp_problem.feature_entity[int(g)] for g in ids]
    x = np.concatenate([res.means[v_ent], res.means[f_ents, :2].ravel()])
    x[2] = wrap_angle(x[2])
    P = joint_covariance(res, [v_ent, *f_ents])
    if hasattr(back, "apply_optimum"):
        back.apply_optimum(pose_index, x, P)
    else:
        back.x = x
        back.P = P
    submap_slam._optimised()
    out = OptimiseResult(
        method=method,
        n_submaps=len(submaps),
        pose_index=pose_index,
        iterations=res.iterations,
        converged=res.converged,
        time_s=time.perf_counter() - t0,
        cost=problem.weighted_residual_cost(res.tau),
        initial_cost=initial_cost,
        x=x.copy(),
        P=P.copy(),
        ids=ids.copy(),
        optimiser=res,
        problem=sp_problem,
    )
    logger.debug(
        "optimise_submaps: %d sub-maps, %s, %d iterations, cost %.4g -> %.4g, %.3f s",
        len(submaps), method, res.iterations, initial_cost, out.cost, out.time_s,
    )
    return out


# --------------------------------------------------------------------------- relative back-end
@dataclass(frozen=True)
class SubmapLoopClosure:
    """A loop closure found while fusing sub-map ``submap`` (CM Definition 1).

    ``reason``: ``"chain"`` (more than ``max_chain`` fusions between the feature's frame and the
    sub-map) or ``"innovation"`` (``||nu|| > innovation_sigmas * sigma``); ``innovation_ratio`` is
    ``||nu|| / (innovation_sigmas * sigma)``.
    """

    submap: int
    feature_id: int
    chain_length: int
    innovation_ratio: float
    reason: str
    coordinates_entity: int


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
        self.loop_closures: list[SubmapLoopClosure] = []
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
    def n_loop_closures(self) -> int:
        return len(self.loop_closures)

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
    def fuse(self, local: GaussianMap) -> FusionReport:
        """Associate (JCBB), test for loop closures and integrate a sub-map (module docstring)."""
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
                self.loop_closures.append(
                    SubmapLoopClosure(b, gid, chain, ratio, reason, e)
                )
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
        return FusionReport(id_map=id_map, n_matched=len(matched), n_new=len(unmatched))

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
