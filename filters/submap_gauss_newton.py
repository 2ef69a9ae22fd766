"""A compiled Gauss-Newton for CM (12) over stored sub-maps (the env's ``optimise()``).

:func:`filters.submap_optimise.optimise_submaps` minimises CM (12),

    c(tau) = sum_s (psi_s(tau) - r_s)^T Lambda_s (psi_s(tau) - r_s),
    psi_s = [relative(x_o, x_e); point_to_frame(x_o, m_j) for the sub-map's features j],

over the chain of fusion poses ``x_1 .. x_S`` (``x_0``, the initial pose, is the gauge) and the
global features. The general optimiser (:class:`filters.optimiser.RelativeProblem`) stacks every
quantity into sparse matrices and re-builds them at every iteration: on BB's world an optimisation
over 40 sub-maps took 30-110 ms, almost all of it in building scipy objects (issue 27). Here the
problem is kept as flat arrays (:class:`SubmapArrays`), and one compiled pass per iteration
(:func:`_normal_equations`) forms each sub-map's residual ``e_s``, its Jacobian ``J_s`` (dense
in the sub-map's own variables: its origin and end poses and its features) and adds
``J_s^T Lambda_s J_s`` and ``J_s^T Lambda_s e_s`` into the normal equations. The iteration
(undamped Gauss-Newton, Marquardt damping only when a step fails to lower the cost, the same
stopping rules) is that of :meth:`RelativeProblem.optimise` with ``"gauss-newton"``, so the
optimum is the same (tested to tolerance against it, and against GTSAM in
``scripts/performance/gtsam_reference.py``).

The factorisation (issue 40). The problem is a chain of sub-maps with a few loop closures: each
sub-map couples its two poses and its features, so ``J^T Lambda J`` is sparse. Ordered by
reverse Cuthill-McKee on the graph of the entities (:class:`BandOrdering`, computed once per
optimisation: the pattern does not change between iterations), it is banded, and LAPACK's band
Cholesky (``dpbtrf``/``dpbtrs``) factorises it in ``n (b + 1)^2`` operations with no fill
outside the band. At the end of a full BB path at clutter level 2 (42 sub-maps, 188 variables)
the bandwidth is 54: a factorisation and solve take ~75 us against ~210-260 us for the dense
Cholesky it replaced, and SuperLU with a fill-reducing order (``splu``, COLAMD or
MMD_AT_PLUS_A) took 300-540 us, its overhead above the operations at this size. The band factor
was the faster one at every size measured up to :data:`DENSE_MAX_VARIABLES` (44 to 300
variables, bandwidths 33 to 54: 9-157 us against 20-933 us); above it, it is used when the band
is at most a third of the matrix, else SuperLU (:attr:`BandOrdering.pays`; on graphs of 652 to
1274 variables from fusing every second, bandwidths 212-372, a whole optimisation took 26-60 ms
against 36-100 ms). The orders differ, so the optimum differs from the dense factorisation's in
rounding: the estimate written back by at most ~1e-6 of its standard deviation on full paths
(tests/filters/test_submap_band_factor.py).

The Jacobians are those of :mod:`filters.geometry` (``relative`` and ``point_to_frame`` w.r.t.
the origin pose, the end pose and the point); the heading residual is wrapped to ``(-pi, pi]``
around the sub-map's heading, as the general optimiser does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.lapack import dpbtrf, dpbtrs

from filters.geometry import wrap_angle_one as _wrap
from filters.information import sparse_spd_factor

DENSE_MAX_VARIABLES = 600
"""Above this many variables the normal equations are factorised sparse (the graph of a
policy that fuses at every decision reaches ~1500); below, a dense Cholesky is faster."""


@dataclass(frozen=True)
class SubmapArrays:
    """The sub-maps of CM (12) as flat arrays.

    ``origin``, ``end`` (S,): pose indices of each sub-map (0 = the gauge); ``feature_start``
    (S + 1,) and ``features``: the global feature index (``0 .. n_features - 1``) of each
    sub-map's features, in the order of its mean; ``mean_start`` (S + 1,) / ``means``: each
    sub-map's mean ``r_s`` (end pose, then 2 per feature; heading wrapped); ``info_start``
    (S + 1,) / ``infos``: each ``Lambda_s`` flattened (row-major).
    """

    n_poses: int
    n_features: int
    origin: np.ndarray
    end: np.ndarray
    feature_start: np.ndarray
    features: np.ndarray
    mean_start: np.ndarray
    means: np.ndarray
    info_start: np.ndarray
    infos: np.ndarray

    @property
    def n_variables(self) -> int:
        return 3 * (self.n_poses - 1) + 2 * self.n_features

    def pose_column(self, k: int) -> int:
        """First column of pose ``k`` (-1 for the gauge)."""
        return 3 * (k - 1) if k > 0 else -1

    def feature_column(self, j: int) -> int:
        return 3 * (self.n_poses - 1) + 2 * j

    def pack(self, poses, points) -> np.ndarray:
        """The variable vector from poses (n_poses, 3) and points (n_features, 2)."""
        return np.concatenate([np.asarray(poses, float)[1:].ravel(),
                               np.asarray(points, float).ravel()])

    def unpack(self, tau, gauge) -> tuple[np.ndarray, np.ndarray]:
        """Poses (n_poses, 3; pose 0 = ``gauge``) and points (n_features, 2) from ``tau``."""
        poses = np.empty((self.n_poses, 3))
        poses[0] = gauge
        poses[1:] = tau[: 3 * (self.n_poses - 1)].reshape(-1, 3)
        return poses, tau[3 * (self.n_poses - 1):].reshape(-1, 2)


def submap_arrays(submaps, global_ids, feature_index: dict, n_poses: int,
                  informations) -> SubmapArrays:
    """Pack stored sub-maps (``gaussian``, ``origin_index``, ``end_index``) with the global ids
    of their features (``global_ids``, one array per sub-map) and their informations
    ``Lambda_s``; ``feature_index`` maps global id -> feature index."""
    origin = np.array([s.origin_index for s in submaps], dtype=np.int64)
    end = np.array([s.end_index for s in submaps], dtype=np.int64)
    means = [np.asarray(s.gaussian.x, dtype=float) for s in submaps]
    infos = [np.asarray(info, dtype=float).ravel() for info in informations]
    lookup = np.vectorize(feature_index.__getitem__, otypes=[np.int64])
    flat_ids = np.concatenate(global_ids)
    starts = [np.concatenate([[0], np.cumsum([len(a) for a in arrays])]).astype(np.int64)
              for arrays in (global_ids, means, infos)]
    flat_means = np.concatenate(means)
    heading = starts[1][:-1] + 2
    flat_means[heading] = (flat_means[heading] + np.pi) % (2.0 * np.pi) - np.pi
    return SubmapArrays(
        n_poses=int(n_poses), n_features=len(feature_index), origin=origin, end=end,
        feature_start=starts[0],
        features=lookup(flat_ids) if len(flat_ids) else np.zeros(0, np.int64),
        mean_start=starts[1], means=flat_means, info_start=starts[2],
        infos=np.concatenate(infos),
    )


@njit(cache=True)
def _submap_terms(poses, points, a_origin, a_end, f0, f1, feats, r, info_flat):
    """Residual ``e`` (d,), Jacobian ``J`` (d, 6 + 2m) w.r.t. [origin, end, features] and
    ``Lambda`` (d, d) of one sub-map."""
    m = f1 - f0
    d = 3 + 2 * m
    xo, xe = poses[a_origin], poses[a_end]
    c, s = np.cos(xo[2]), np.sin(xo[2])
    e = np.empty(d)
    J = np.zeros((d, 6 + 2 * m))
    dx, dy = xe[0] - xo[0], xe[1] - xo[1]
    relx, rely = c * dx + s * dy, -s * dx + c * dy
    e[0], e[1] = relx - r[0], rely - r[1]
    e[2] = _wrap(xe[2] - xo[2] - r[2])
    J[0, 0], J[0, 1], J[0, 2], J[0, 3], J[0, 4] = -c, -s, rely, c, s
    J[1, 0], J[1, 1], J[1, 2], J[1, 3], J[1, 4] = s, -c, -relx, -s, c
    J[2, 2], J[2, 5] = -1.0, 1.0
    for i in range(m):
        row, col = 3 + 2 * i, 6 + 2 * i
        p = points[feats[f0 + i]]
        dx, dy = p[0] - xo[0], p[1] - xo[1]
        px, py = c * dx + s * dy, -s * dx + c * dy
        e[row], e[row + 1] = px - r[row], py - r[row + 1]
        J[row, 0], J[row, 1], J[row, 2], J[row, col], J[row, col + 1] = -c, -s, py, c, s
        J[row + 1, 0], J[row + 1, 1], J[row + 1, 2] = s, -c, -px
        J[row + 1, col], J[row + 1, col + 1] = -s, c
    return e, J, info_flat.reshape(d, d)


@njit(cache=True)
def _columns(n_poses, a_origin, a_end, f0, f1, feats):
    """The variable column of each column of :func:`_submap_terms`'s Jacobian (-1: gauge)."""
    m = f1 - f0
    cols = np.empty(6 + 2 * m, dtype=np.int64)
    for k, pose in ((0, a_origin), (3, a_end)):
        for i in range(3):
            cols[k + i] = 3 * (pose - 1) + i if pose > 0 else -1
    for i in range(m):
        base = 3 * (n_poses - 1) + 2 * feats[f0 + i]
        cols[6 + 2 * i], cols[7 + 2 * i] = base, base + 1
    return cols


@njit(cache=True)
def _cost(poses, points, origin, end, feature_start, features, mean_start, means, info_start,
          infos):
    """CM (12) at the given poses and points."""
    total = 0.0
    for k in range(len(origin)):
        e, _, L = _submap_terms(poses, points, origin[k], end[k], feature_start[k],
                                feature_start[k + 1], features,
                                means[mean_start[k]:mean_start[k + 1]],
                                infos[info_start[k]:info_start[k + 1]])
        total += e @ (L @ e)
    return total


@njit(cache=True)
def _add_second_order(H, w, r0, target_col, relx, rely, c, s):
    """Add ``w_x d^2 relx + w_y d^2 rely`` (the second derivatives of one position quantity of
    :func:`_submap_terms`: nonzero only where the origin's heading, column 2, is involved) to
    the local Hessian ``H``; ``w = Lambda e`` and the quantity's rows start at ``r0``."""
    wx, wy = w[r0], w[r0 + 1]
    H[2, 2] += -wx * relx - wy * rely
    for col, value in ((0, wx * s + wy * c), (1, -wx * c + wy * s),
                       (target_col, -wx * s - wy * c), (target_col + 1, wx * c - wy * s)):
        H[2, col] += value
        H[col, 2] += value


@njit(cache=True)
def _normal_equations(poses, points, n_poses, origin, end, feature_start, features, mean_start,
                      means, info_start, infos, n_variables, newton):
    """CM (12), the gradient half ``g = J^T Lambda e`` (n,) and the blocks of ``J^T Lambda J``
    as triplets (rows, columns, values; duplicates to be summed), gauge columns left out. With
    ``newton`` the blocks also carry the residuals' curvature ``sum_i (Lambda e)_i d^2 psi_i``:
    half the exact Hessian of CM (12), Newton's matrix instead of Gauss-Newton's."""
    n_entries = 0
    for k in range(len(origin)):
        v = 6 + 2 * (feature_start[k + 1] - feature_start[k])
        n_entries += v * v
    rows = np.empty(n_entries, dtype=np.int64)
    cols = np.empty(n_entries, dtype=np.int64)
    vals = np.empty(n_entries)
    g = np.zeros(n_variables)
    total = 0.0
    n = 0
    for k in range(len(origin)):
        f0, f1 = feature_start[k], feature_start[k + 1]
        e, J, L = _submap_terms(poses, points, origin[k], end[k], f0, f1, features,
                                means[mean_start[k]:mean_start[k + 1]],
                                infos[info_start[k]:info_start[k + 1]])
        LJ = L @ J
        Le = L @ e
        total += e @ Le
        H = J.T @ LJ
        gk = J.T @ Le
        if newton:
            xo, xe = poses[origin[k]], poses[end[k]]
            c, s = np.cos(xo[2]), np.sin(xo[2])
            dx, dy = xe[0] - xo[0], xe[1] - xo[1]
            _add_second_order(H, Le, 0, 3, c * dx + s * dy, -s * dx + c * dy, c, s)
            for i in range(f1 - f0):
                p = points[features[f0 + i]]
                dx, dy = p[0] - xo[0], p[1] - xo[1]
                _add_second_order(H, Le, 3 + 2 * i, 6 + 2 * i, c * dx + s * dy,
                                  -s * dx + c * dy, c, s)
        index = _columns(n_poses, origin[k], end[k], f0, f1, features)
        for a in range(len(index)):
            if index[a] < 0:
                continue
            g[index[a]] += gk[a]
            for b in range(len(index)):
                if index[b] < 0:
                    continue
                rows[n], cols[n], vals[n] = index[a], index[b], H[a, b]
                n += 1
    return total, g, rows[:n], cols[:n], vals[:n]


@njit(cache=True)
def _dense(n_variables, rows, cols, vals):
    H = np.zeros((n_variables, n_variables))
    for i in range(len(rows)):
        H[rows[i], cols[i]] += vals[i]
    return H


@njit(cache=True)
def _band(n_variables, bandwidth, position, rows, cols, vals):
    """The lower band of the permuted matrix in LAPACK's storage (``ab[i - j, j] = H[i, j]``
    for ``0 <= i - j <= bandwidth``, in the order ``position``: old column -> new)."""
    ab = np.zeros((bandwidth + 1, n_variables))
    for k in range(len(rows)):
        i, j = position[rows[k]], position[cols[k]]
        if i >= j:
            ab[i - j, j] += vals[k]
    return ab


@njit(cache=True)
def _entity_graph(n_poses, n_features, origin, end, feature_start, features):
    """The graph of the entities (pose ``k >= 1`` -> ``k - 1``, feature ``j`` ->
    ``n_poses - 1 + j``), joined where one sub-map holds both: the pattern of ``J^T Lambda J``
    by blocks, as adjacency lists (indptr, indices; each entity its own neighbour)."""
    n = n_poses - 1 + n_features
    n_pairs = 0
    for k in range(len(origin)):
        m = 2 + feature_start[k + 1] - feature_start[k]
        n_pairs += m * m
    keys = np.empty(n_pairs, dtype=np.int64)
    count = 0
    ents = np.empty(2 + np.max(np.diff(feature_start)) if len(origin) else 2, dtype=np.int64)
    for k in range(len(origin)):
        m = 0
        for pose in (origin[k], end[k]):
            if pose > 0:
                ents[m] = pose - 1
                m += 1
        for i in range(feature_start[k], feature_start[k + 1]):
            ents[m] = n_poses - 1 + features[i]
            m += 1
        for i in range(m):
            for j in range(m):
                keys[count] = ents[i] * n + ents[j]
                count += 1
    keys = np.unique(keys[:count])
    indptr = np.zeros(n + 1, dtype=np.int64)
    for key in keys:
        indptr[key // n + 1] += 1
    indptr = np.cumsum(indptr)
    return indptr, keys % n


@njit(cache=True)
def _reverse_cuthill_mckee(indptr, indices):
    """Reverse Cuthill-McKee: breadth first from a least-connected entity of each component,
    the neighbours of each in order of their degree, the whole order reversed."""
    n = len(indptr) - 1
    degree = np.diff(indptr)
    visited = np.zeros(n, dtype=np.bool_)
    order = np.empty(n, dtype=np.int64)
    by_degree = np.argsort(degree, kind="mergesort")
    filled = 0
    for start in by_degree:
        if visited[start]:
            continue
        visited[start] = True
        order[filled] = start
        head, filled = filled, filled + 1
        while head < filled:
            node = order[head]
            head += 1
            first = filled
            for i in range(indptr[node], indptr[node + 1]):
                other = indices[i]
                if not visited[other]:
                    visited[other] = True
                    order[filled] = other
                    filled += 1
            if filled - first > 1:
                new = order[first:filled].copy()
                order[first:filled] = new[np.argsort(degree[new], kind="mergesort")]
    return order[::-1].copy()


@njit(cache=True)
def _band_order(n_poses, n_features, origin, end, feature_start, features):
    """The variable order of :class:`BandOrdering` and the bandwidth of its block pattern (an
    upper bound of the matrix's own: every block two entities share is counted full)."""
    indptr, indices = _entity_graph(n_poses, n_features, origin, end, feature_start, features)
    entities = _reverse_cuthill_mckee(indptr, indices)
    n_entities = len(entities)
    size = np.empty(n_entities, dtype=np.int64)
    column = np.empty(n_entities, dtype=np.int64)  # the entity's first variable column
    for e in range(n_entities):
        if e < n_poses - 1:
            size[e], column[e] = 3, 3 * e
        else:
            size[e], column[e] = 2, 3 * (n_poses - 1) + 2 * (e - (n_poses - 1))
    first = np.empty(n_entities, dtype=np.int64)  # the entity's first row in the new order
    order = np.empty(size.sum(), dtype=np.int64)
    filled = 0
    for e in entities:
        first[e] = filled
        for i in range(size[e]):
            order[filled] = column[e] + i
            filled += 1
    bandwidth = 0
    for a in range(n_entities):
        for i in range(indptr[a], indptr[a + 1]):
            b = indices[i]
            if first[a] >= first[b]:
                bandwidth = max(bandwidth, first[a] + size[a] - 1 - first[b])
    return order, bandwidth


@dataclass(frozen=True)
class BandOrdering:
    """A bandwidth-reducing order of the variables: reverse Cuthill-McKee on the graph of the
    entities (fusion poses and features, joined where a sub-map holds both), each entity's
    columns kept together. ``order[new] = old``, ``position[old] = new``; ``bandwidth``: of the
    permuted ``J^T Lambda J``'s block pattern, which holds every nonzero. A Cholesky factor has
    no fill outside the band (module docstring)."""

    order: np.ndarray
    position: np.ndarray
    bandwidth: int

    @classmethod
    def of(cls, arrays: SubmapArrays) -> BandOrdering:
        a = arrays
        order, bandwidth = _band_order(a.n_poses, a.n_features, a.origin, a.end,
                                       a.feature_start, a.features)
        position = np.empty(len(order), dtype=np.int64)
        position[order] = np.arange(len(order))
        return cls(order, position, int(bandwidth))

    @property
    def pays(self) -> bool:
        """Whether the band factor is the one to use: up to :data:`DENSE_MAX_VARIABLES`
        always (LAPACK's band Cholesky was faster than the dense one at every size measured,
        even at 44 variables with a bandwidth of 33: 9 against 20 us), above it when the band
        is at most a third of the matrix (else SuperLU's fill-reducing order)."""
        n = len(self.order)
        return n <= DENSE_MAX_VARIABLES or 3 * (self.bandwidth + 1) <= n


class _Normal:
    """``J^T Lambda J`` at one point, factorised on demand: banded in a bandwidth-reducing order
    (``ordering``, when it pays), else dense up to :data:`DENSE_MAX_VARIABLES` variables, else
    sparse (module docstring)."""

    def __init__(self, n, rows, cols, vals, ordering: BandOrdering | None = None):
        self.n = n
        self.ordering = ordering if ordering is not None and ordering.pays else None
        if self.ordering is not None:
            self.matrix = _band(n, self.ordering.bandwidth, self.ordering.position, rows, cols,
                                vals)
            self.diagonal = self.matrix[0].copy()  # in the band's order
        elif n <= DENSE_MAX_VARIABLES:
            self.matrix = _dense(n, rows, cols, vals)
            self.diagonal = np.diag(self.matrix).copy()
        else:
            self.matrix = sp.csc_matrix((vals, (rows, cols)), shape=(n, n))
            self.diagonal = self.matrix.diagonal()

    def factor(self, damping: float = 0.0):
        """A solver of ``(H + damping diag(H)) x = b``; None if not positive definite."""
        if self.ordering is not None:
            ab = self.matrix
            if damping > 0:
                ab = ab.copy()
                ab[0] += damping * self.diagonal
            factor, info = dpbtrf(ab, lower=1)
            if info != 0:
                return None
            order = self.ordering.order

            def solve(b):
                x_band, info = dpbtrs(factor, b[order], lower=1)
                if info != 0:
                    raise ValueError(f"dpbtrs: argument {-info} is invalid")
                x = np.empty_like(x_band)
                x[order] = x_band
                return x

            return solve
        if isinstance(self.matrix, np.ndarray):
            H = self.matrix + np.diag(damping * self.diagonal) if damping > 0 else self.matrix
            try:
                factor = cho_factor(H, lower=True, check_finite=False)
            except np.linalg.LinAlgError:
                return None
            return lambda b: cho_solve(factor, b, check_finite=False)
        H = self.matrix + sp.diags(damping * self.diagonal) if damping > 0 else self.matrix
        try:
            return sparse_spd_factor(H).solve
        except RuntimeError:
            return None


@dataclass
class GaussNewtonResult:
    poses: np.ndarray
    points: np.ndarray
    cost: float
    initial_cost: float
    iterations: int
    converged: bool
    message: str
    normal: _Normal

    def covariance(self, arrays: SubmapArrays, pose_index: int, feature_indices) -> np.ndarray:
        """Joint Gauss-Newton covariance of pose ``pose_index`` and the listed features: the
        block of ``(J^T Lambda J)^-1`` at the optimum, solved for those columns only."""
        cols = [arrays.pose_column(pose_index) + i for i in range(3)] if pose_index > 0 else []
        out_idx = list(range(3)) if pose_index > 0 else []
        for n, j in enumerate(feature_indices):
            base = arrays.feature_column(int(j))
            cols += [base, base + 1]
            out_idx += [3 + 2 * n, 4 + 2 * n]
        dim = 3 + 2 * len(feature_indices)
        C = np.zeros((dim, dim))
        if cols:
            E = np.zeros((arrays.n_variables, len(cols)))
            E[np.asarray(cols), np.arange(len(cols))] = 1.0
            solve = self.normal.factor()
            if solve is None:
                raise RuntimeError("J^T Lambda J is singular at the optimum")
            X = solve(E)
            oi = np.asarray(out_idx)
            C[np.ix_(oi, oi)] = X[np.asarray(cols)]
        return 0.5 * (C + C.T)


def gauss_newton(arrays: SubmapArrays, gauge, poses0, points0, *, max_iterations: int = 200,
                 xtol: float = 1e-10, band: bool = True) -> GaussNewtonResult:
    """Minimise CM (12) from ``poses0`` (n_poses, 3) / ``points0`` (n_features, 2).

    The iteration of :meth:`filters.optimiser.RelativeProblem.optimise` (``"gauss-newton"``:
    undamped steps, Marquardt damping only when a step fails to lower the cost; it stops at a
    step below ``xtol`` relative, a decrease below 1e-15 relative, or when no descent step is
    left), with two changes. Where Newton's matrix (Gauss-Newton's plus the residuals'
    curvature, :func:`_normal_equations`) is positive definite, the step is Newton's: Gauss-Newton
    alone converges only linearly here (the headings' curvature: ~18 iterations on BB's world,
    each shrinking the step by a factor of about 0.4); Newton converges quadratically to the same
    stationary point. A Newton step that does not lower the cost is replaced by Gauss-Newton's,
    and one of those by its halves (up to 1/64) before damping: with sub-maps of one second
    each, damping alone crawled along a valley for 200 iterations. It stops when the model's
    decrease ``g^T H^-1 g`` is below 1e-10 of the cost (rounding). The covariance is
    Gauss-Newton's, ``(J^T Lambda J)^-1`` at the optimum. ``band=False`` factorises as before
    issue 40 (dense, or sparse above :data:`DENSE_MAX_VARIABLES`): the same optimum but for
    rounding (module docstring)."""
    a = arrays
    static = (a.origin, a.end, a.feature_start, a.features, a.mean_start, a.means, a.info_start,
              a.infos)
    gauge = np.asarray(gauge, dtype=float)
    tau = a.pack(poses0, points0)
    n = a.n_variables

    ordering = []  # the pattern is the same at every point: ordered once

    def evaluate(t, newton):
        poses, points = a.unpack(t, gauge)
        cost, g, rows, cols, vals = _normal_equations(poses, points, a.n_poses, *static, n,
                                                      newton)
        if not ordering:
            ordering.append(BandOrdering.of(a) if band else None)
        return cost, g, _Normal(n, rows, cols, vals, ordering[0])

    def cost_at(t):
        poses, points = a.unpack(t, gauge)
        return _cost(poses, points, *static)

    cost, g, normal = evaluate(tau, True)
    initial_cost = cost
    lam, it = 0.0, 0
    converged, message = False, "maximum iterations reached"
    while it < max_iterations and not converged:
        it += 1
        newton = True
        undamped = normal.factor()
        if undamped is None:  # Newton's matrix indefinite here: Gauss-Newton's
            _, _, normal = evaluate(tau, False)
            newton, undamped = False, normal.factor()
        accepted = tiny = False
        while not accepted and lam <= 1e12:
            solve = undamped if lam == 0.0 else normal.factor(lam)
            if solve is None:
                lam = max(1e-6, 10.0 * lam)
                continue
            step = -solve(g)
            # the model's decrease g^T H^-1 g: below 1e-10 of the cost, what is left is rounding
            # (ill-conditioned sub-maps, e.g. of one second each, never resolve it further)
            flat = float(-(g @ step)) <= 1e-10 * max(1.0, cost)
            tiny = np.max(np.abs(step)) <= xtol * (1.0 + np.max(np.abs(tau)))
            new_cost = cost_at(tau + step)
            accepted = bool(new_cost <= cost)
            if not accepted:
                if tiny or flat:
                    break
                if newton:  # a Newton step that does not descend: Gauss-Newton's first
                    _, _, normal = evaluate(tau, False)
                    newton, undamped = False, normal.factor()
                    continue
                if lam == 0.0:  # Gauss-Newton's direction overshoots: halve it a few times
                    for _ in range(6):
                        step = 0.5 * step
                        new_cost = cost_at(tau + step)
                        if new_cost <= cost:
                            accepted = True
                            break
                    if accepted:
                        break
                lam = max(1e-6, 10.0 * lam)
        if not accepted:
            converged, message = True, "no further decrease"
            break
        decrease = cost - new_cost
        tau = tau + step
        lam = 0.0 if lam <= 1e-6 else lam / 10.0
        if tiny or flat or decrease <= 1e-15 * max(1.0, cost):
            converged, message = True, "step below tolerance"
            break
        cost, g, normal = evaluate(tau, True)
    cost, _, normal = evaluate(tau, False)  # the covariance: Gauss-Newton's at the optimum
    poses, points = a.unpack(tau, gauge)
    return GaussNewtonResult(poses.copy(), points.copy(), float(cost), float(initial_cost), it,
                             converged, message, normal)
