"""Nonlinear optimisation of the sub-map back-ends (CM III.C) and the relative back-end.

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

The relative back-end that this optimiser also serves lives in :mod:`filters.back_ends`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from filters.blas import DEFAULT_BLAS_THREADS, check_blas_threads, limited_blas_threads
from filters.geometry import compose, transform_point, wrap_angle
from filters.information import sparse_spd_factor, symmetrise
from filters.optimiser import (
    METHODS,
    POINT,
    POSE,
    GaussianConstraint,
    OptimiserResult,
    RelativeProblem,
    RelativeQuantity,
)
from filters.submap_gauss_newton import gauss_newton, submap_arrays
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

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


def _information_of(submap, min_variance):
    """``P^-1`` of a stored sub-map, kept in its ``cache`` when it has one."""
    cache = getattr(submap, "cache", None)
    if cache is None:
        return gaussian_information(submap.gaussian.P, min_variance)
    key = ("information", min_variance)
    if key not in cache:
        cache[key] = gaussian_information(submap.gaussian.P, min_variance)
    return cache[key]


def _global_ids_of(submap, n: int) -> np.ndarray:
    """The global id of each local feature of stored sub-map number ``n``, in the order of its
    mean (cached like :func:`_information_of`)."""
    cache = getattr(submap, "cache", None)
    if cache is not None and "global_ids" in cache:
        return cache["global_ids"]
    gids = []
    for lid in np.asarray(submap.gaussian.ids, dtype=np.int64):
        gid = submap.id_map.get(int(lid))
        require(gid is not None, f"submaps[{n}].id_map", int(lid), "to map every local id")
        gids.append(int(gid))
    out = np.array(gids, dtype=np.int64)
    if cache is not None:
        cache["global_ids"] = out
    return out


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
        constraints.append(GaussianConstraint(tuple(qs), x, _information_of(s, min_variance)))
    problem = RelativeProblem.from_constraints(
        kinds, constraints, gauge=0, gauge_pose=np.zeros(3) if world else x0
    )
    return SubmapProblem(problem, pose_entity, feature_entity, world)


def joint_covariance(result: OptimiserResult, entities) -> np.ndarray:
    """Joint Gauss-Newton covariance of ``entities``: a block of ``(J^T Lambda J)^-1`` (with a
    robust kernel, ``Lambda`` re-weighted at the optimum: :attr:`OptimiserResult.information`).

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
        H = (J.T @ result.information @ J).tocsc()
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
    redundant: bool = False
    """Nothing was fused since the optimum applied last (or nothing was ever fused): the call
    changed nothing and returned that optimum at once."""
    settings: tuple = ()
    """What the optimum depends on besides the sub-maps (method, options, gauge): a later call
    with other settings is not redundant."""
    warm_start: dict | None = field(default=None, repr=False)
    """The optimum's fusion poses (``"poses"``, (S + 1, 3)) and features (``"features"``, by
    global id): where the next optimisation with the same settings starts."""

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


SOLVERS = ("compiled", "general")
"""``optimise_submaps(solver=...)``: see its docstring."""


def _chain_guess(arrays, x0, known_poses, known_points):
    """Poses and points composed along the sub-maps from ``x0`` (the general optimiser's
    :meth:`~filters.optimiser.RelativeProblem.initial_guess`: each pose from its sub-map's origin,
    each feature from the first sub-map holding it), except where known (a warm start)."""
    poses = np.full((arrays.n_poses, 3), np.nan)
    poses[0] = x0
    for k, pose in known_poses.items():
        if 0 < k < arrays.n_poses:
            poses[k] = pose
    for k in range(len(arrays.origin)):  # origin before end: the chain in order
        e = arrays.end[k]
        if np.isnan(poses[e, 0]):
            r = arrays.means[arrays.mean_start[k]:arrays.mean_start[k] + 3]
            poses[e] = compose(poses[arrays.origin[k]], r)
            poses[e, 2] = poses[arrays.origin[k], 2] + r[2]
    points = np.full((arrays.n_features, 2), np.nan)
    for j, point in known_points.items():
        points[j] = point
    # the first sub-map holding each feature, and where in its mean the feature is
    owner = np.repeat(np.arange(len(arrays.origin)), np.diff(arrays.feature_start))
    offset = (arrays.mean_start[owner] + 3
              + 2 * (np.arange(len(arrays.features)) - arrays.feature_start[owner]))
    _, first = np.unique(arrays.features, return_index=True)
    todo = first[np.isnan(points[arrays.features[first], 0])]
    if len(todo):
        r = np.stack([arrays.means[offset[todo]], arrays.means[offset[todo] + 1]], axis=1)
        points[arrays.features[todo]] = transform_point(poses[arrays.origin[owner[todo]]], r)
    return poses, points


def _apply_optimum(submap_slam, pose_index, x, P) -> None:
    """Write an optimum ``x``, ``P`` over ``[v-, features]`` back: a back-end with
    ``apply_optimum`` (the relative one) takes it as its anchor, the EKF one as its estimate; then
    the system's book-keeping."""
    back = submap_slam.back_end
    if hasattr(back, "apply_optimum"):
        back.apply_optimum(pose_index, x, P)
    else:
        back.x = x
        back.P = P
    submap_slam._optimised()


def _optimise_compiled(submap_slam, submaps, x0, previous, settings, min_variance, t0,
                       max_iterations: int = 200, xtol: float = 1e-10,
                       band: bool = True) -> OptimiseResult:
    """:func:`optimise_submaps` through :mod:`filters.submap_gauss_newton`."""
    back = submap_slam.back_end
    n_poses = 1 + max(int(s.end_index) for s in submaps)
    for n, s in enumerate(submaps):
        require(0 <= s.origin_index < s.end_index < n_poses, f"submaps[{n}].origin_index",
                (s.origin_index, s.end_index), "origin_index < end_index, both >= 0")
    global_ids = [_global_ids_of(s, n) for n, s in enumerate(submaps)]
    order = dict.fromkeys(np.concatenate(global_ids).tolist())  # first appearance
    feature_index = {g: j for j, g in enumerate(order)}
    ids = np.asarray(back.ids, dtype=np.int64)
    missing = [int(g) for g in ids if int(g) not in feature_index]
    require(not missing, "back_end.ids", missing[:5],
            "ids of features that came from fused sub-maps (listed in their id_map)")
    arrays = submap_arrays(submaps, global_ids, feature_index, n_poses,
                           [_information_of(s, min_variance) for s in submaps])
    known_poses, known_points = {}, {}
    warm = previous.warm_start if previous is not None and previous.settings == settings else None
    if warm is not None:
        known_poses = dict(enumerate(warm["poses"]))
        known_points = {feature_index[g]: p for g, p in warm["features"].items()
                        if g in feature_index}
    poses0, points0 = _chain_guess(arrays, x0, known_poses, known_points)
    res = gauss_newton(arrays, x0, poses0, points0, max_iterations=max_iterations, xtol=xtol,
                       band=band)
    pose_index = n_poses - 1
    columns = [feature_index[int(g)] for g in ids]
    x = np.concatenate([res.poses[pose_index], res.points[columns].ravel()])
    x[2] = wrap_angle(x[2])
    P = res.covariance(arrays, pose_index, columns)
    _apply_optimum(submap_slam, pose_index, x, P)
    out = OptimiseResult(
        method="gauss-newton", n_submaps=len(submaps), pose_index=pose_index,
        iterations=res.iterations, converged=res.converged, time_s=time.perf_counter() - t0,
        cost=res.cost, initial_cost=res.initial_cost, x=x.copy(), P=P.copy(), ids=ids.copy(),
        settings=settings,
        warm_start={"poses": res.poses,
                    "features": {g: res.points[j] for g, j in feature_index.items()}},
    )
    if hasattr(submap_slam, "last_optimum"):
        submap_slam.last_optimum = out
    logger.debug("optimise_submaps (compiled): %d sub-maps, %d iterations, cost %.4g -> %.4g, "
                 "%.4f s", len(submaps), res.iterations, res.initial_cost, res.cost, out.time_s)
    return out


def _warm_start(sp_problem, previous, settings):
    """Entity -> coordinates of the previous optimum (same settings) for the entities this
    problem shares with it: every fusion pose and global feature it had. The sub-maps only grow
    between optimisations, so the previous optimum is the current one's but for the sub-maps
    fused since; starting there, Gauss-Newton needs a few iterations instead of some twenty from
    the chain of sub-maps (:meth:`RelativeProblem.initial_guess`)."""
    if previous is None or previous.settings != settings:
        return None
    warm = getattr(previous, "warm_start", None)
    if warm is None:
        return None
    known = {}
    poses = warm["poses"]
    for k in range(min(len(poses), sp_problem.n_poses)):
        known[int(sp_problem.pose_entity[k])] = poses[k]
    for gid, point in warm["features"].items():
        entity = sp_problem.feature_entity.get(gid)
        if entity is not None:
            known[entity] = point
    return known


def _settings(method, min_variance, options, x0, P0) -> tuple:
    """What an optimum depends on besides the sub-maps (:attr:`OptimiseResult.settings`)."""
    return (method, float(min_variance), repr(sorted(options.items())), x0.tobytes(),
            None if P0 is None else np.asarray(P0, dtype=float).tobytes())


def _redundant(submap_slam, settings: tuple) -> bool:
    """The one test of a redundant optimisation (:func:`optimise_submaps`): nothing fused at
    all, or nothing fused since the optimum applied last with the same ``settings``."""
    if not submap_slam.submaps:
        return True
    previous = getattr(submap_slam, "last_optimum", None)
    return (
        previous is not None and previous.settings == settings
        and previous.n_submaps == len(submap_slam.submaps)
        and getattr(submap_slam, "_fusions_since_optimise", 1) == 0
    )


def optimisation_is_redundant(
    submap_slam,
    method: str = "gauss-newton",
    *,
    initial_pose=None,
    initial_pose_cov=None,
    min_variance: float = DEFAULT_MIN_VARIANCE,
    solver: str = "compiled",
    **options,
) -> bool:
    """Whether :func:`optimise_submaps` with these arguments would be a redundant call now (it
    would change nothing and be charged nothing): the same test, without running anything. An
    action mask built on it is exact (issue 29 item 2)."""
    require(method in METHODS, "method", method, f"one of {METHODS}")
    x0, P0 = _initial_pose_of(submap_slam.back_end, initial_pose, initial_pose_cov)
    return _redundant(submap_slam, _settings(method, min_variance, options, x0, P0))


def optimise_submaps(
    submap_slam,
    method: str = "gauss-newton",
    *,
    initial_pose=None,
    initial_pose_cov=None,
    min_variance: float = DEFAULT_MIN_VARIANCE,
    solver: str = "compiled",
    blas_threads: int | None = DEFAULT_BLAS_THREADS,
    band: bool = True,
    **options,
) -> OptimiseResult:
    """CM III.C: minimise CM (12) over the stored sub-maps and write the optimum back.

    ``submap_slam``: a :class:`filters.submap.SubmapSLAM` (its ``submaps`` and ``back_end``).
    ``method``: ``"gauss-newton"``, ``"levenberg-marquardt"`` or ``"reduced"`` (CM's reduced
    quasi-Newton); ``options`` go to :meth:`RelativeProblem.optimise` (e.g. ``robust="huber"``:
    each sub-map factorised into its end pose and its features, each conditional on the ones
    before it, and every such term given a Huber or Cauchy kernel; :mod:`filters.optimiser`).
    The initial pose (the gauge) and its covariance come from the back-end (``initial_pose``,
    ``initial_pose_cov`` attributes, set by :func:`make_back_end`) unless given. The back-end's
    ``x``/``P`` become the optimum over ``[v-, features]`` and its Gauss-Newton covariance (a
    back-end with ``apply_optimum``, i.e. :class:`RelativeBackEnd`, takes it as its new anchor);
    ids and existence are kept. Calls ``submap_slam._optimised()`` (book-keeping).

    ``solver``: ``"compiled"`` (default) runs Gauss-Newton without a robust kernel and with a
    known initial pose (the env's case) in :mod:`filters.submap_gauss_newton`, the same
    iteration on flat arrays; every other case, and ``solver="general"``, goes through
    :class:`filters.optimiser.RelativeProblem` (whose objects ``problem`` / ``optimiser`` the
    result then carries). Both start from the previous optimum when it had the same settings
    (a warm start: the sub-maps only grow). A **redundant** call -- no sub-map fused since the
    optimum applied last with the same settings, or none fused at all -- changes nothing (no
    book-keeping either) and returns at once with ``redundant=True``.

    ``blas_threads``: the BLAS threads the optimisation runs with (:mod:`filters.blas`; default
    one, restored afterwards; None: the process's own setting). ``band``: the compiled solver
    factorises in a bandwidth-reducing order (:mod:`filters.submap_gauss_newton`; False: dense
    as before issue 40, the same optimum but for rounding). Neither enters the settings.
    """
    require(band in (True, False), "band", band, "True or False")
    require(method in METHODS, "method", method, f"one of {METHODS}")
    return _optimise_submaps(submap_slam, method, initial_pose, initial_pose_cov, min_variance,
                             solver, check_blas_threads(blas_threads), band, options)


def _optimise_submaps(submap_slam, method, initial_pose, initial_pose_cov, min_variance, solver,
                      threads, band, options) -> OptimiseResult:
    t0 = time.perf_counter()
    back = submap_slam.back_end
    submaps = list(submap_slam.submaps)
    x0, P0 = _initial_pose_of(back, initial_pose, initial_pose_cov)
    settings = _settings(method, min_variance, options, x0, P0)
    previous = getattr(submap_slam, "last_optimum", None)
    if _redundant(submap_slam, settings):
        # redundant: the state stays as it is, to the bit (module docstring)
        if previous is None or not submaps:
            x, P, ids = back.x, back.P, back.ids
        else:
            x, P, ids = previous.x, previous.P, previous.ids
        return OptimiseResult(
            method, len(submaps), 0 if previous is None else previous.pose_index, 0, True,
            time.perf_counter() - t0, 0.0 if previous is None else previous.cost,
            0.0 if previous is None else previous.cost, np.asarray(x).copy(),
            np.asarray(P).copy(), np.asarray(ids).copy(), redundant=True, settings=settings,
        )
    require(solver in SOLVERS, "solver", solver, f"one of {SOLVERS}")
    with limited_blas_threads(threads):  # not around a redundant call: it has no algebra
        return _solve_submaps(submap_slam, method, min_variance, solver, band, options, t0,
                              submaps, x0, P0, settings, previous)


def _solve_submaps(submap_slam, method, min_variance, solver, band, options, t0, submaps, x0,
                   P0, settings, previous) -> OptimiseResult:
    back = submap_slam.back_end
    if (
        solver == "compiled" and method == "gauss-newton" and options.get("robust") is None
        and _is_zero(P0) and set(options) <= {"robust", "max_iterations", "xtol"}
    ):
        return _optimise_compiled(submap_slam, submaps, x0, previous, settings, min_variance,
                                  t0, band=band,
                                  **{k: v for k, v in options.items() if k != "robust"})
    sp_problem = build_submap_problem(submaps, x0, P0, min_variance=min_variance)
    problem = sp_problem.problem
    tau0 = problem.initial_guess(known=_warm_start(sp_problem, previous, settings))
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
    _apply_optimum(submap_slam, pose_index, x, P)
    warm = {"poses": res.means[sp_problem.pose_entity],
            "features": {g: res.means[e, :2] for g, e in sp_problem.feature_entity.items()}}
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
        settings=settings,
        warm_start=warm,
    )
    if hasattr(submap_slam, "last_optimum"):
        submap_slam.last_optimum = out
    logger.debug(
        "optimise_submaps: %d sub-maps, %s, %d iterations, cost %.4g -> %.4g, %.3f s",
        len(submaps), method, res.iterations, initial_cost, out.cost, out.time_s,
    )
    return out
