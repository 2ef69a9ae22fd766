"""Nonlinear optimiser over Gaussian relative constraints (CM section III.C).

The input is a Gaussian in information form ``(eta, Lambda)`` over a stacked vector ``r`` of
*relative quantities*, each described by :class:`RelativeQuantity` ``(kind, frame, target)``:

* ``"pose"``: pose ``target`` expressed in the frame of pose ``frame`` (3 numbers,
  ``relative(x_frame, x_target)``); CM's ``d_k^R``, or a sub-map's end pose in its start frame;
* ``"point"``: point ``target`` expressed in the frame of pose ``frame`` (2 numbers); CM's
  ``d_k^{L_j}`` (and its redundant copies made at loop closures), or a sub-map's landmark;
* ``"heading"``: heading of pose ``target`` minus heading of pose ``frame`` (1 number), e.g. a
  compass reading with ``frame`` the gauge.

The unknowns ``tau`` are the global coordinates of all entities (poses: x, y, theta; points: x, y);
the ``gauge`` pose is fixed. ``psi(tau)`` maps ``tau`` to the relative quantities (inverse
compositions) and the cost is CM (13),

    c(tau) = psi(tau)^T Lambda psi(tau) - 2 psi(tau)^T eta,

which equals the weighted least squares CM (12), ``(psi - r_hat)^T Lambda (psi - r_hat)``, minus
the constant ``r_hat^T Lambda r_hat = eta^T r_hat`` (``r_hat = Lambda^-1 eta``). Its gradient is
``J_psi^T (2 Lambda psi - 2 eta)``; neither needs ``Lambda^-1``.

Two minimisers (:meth:`RelativeProblem.optimise`):

* ``"reduced"`` (CM's method): for fixed orientations ``psi`` is affine in the positions,
  ``psi = A(theta) p + b(theta)``, so the optimal positions solve the sparse normal equations
  ``(A^T Lambda A) p = A^T (eta - Lambda b)`` exactly; a quasi-Newton method
  (``scipy.optimize.minimize``, L-BFGS-B) then runs over the orientations only, with the reduced
  gradient given by the envelope theorem: ``d/dtheta c(theta, p*(theta)) = dc/dtheta`` at
  ``p*`` because ``dc/dp = 0`` there.
* ``"gauss-newton"`` / ``"levenberg-marquardt"``: sparse Gauss-Newton on the same cost over all
  of ``tau``, ``(J^T Lambda J + lambda D) delta = -J^T (Lambda psi - eta)``, with Marquardt
  damping switched on only when a step fails to decrease the cost (``"gauss-newton"`` starts
  undamped).

Robust kernels (``robust="huber"`` or ``"cauchy"``, Gauss-Newton / Levenberg-Marquardt only, for
problems stacked by :meth:`RelativeProblem.from_constraints`): CM (12) is a sum of one quadratic
form per constraint, and a constraint with a dense information matrix (a sub-map) cannot be
down-weighted per quantity as it stands. Its Gaussian is therefore factorised exactly into a chain
of conditionals, quantity by quantity in the stacked order (the end pose, then each feature given
the end pose and the features before it): with ``W`` lower triangular and ``W^T W = Lambda_c``
(a Cholesky factor of the constraint's covariance, inverted), ``e^T Lambda_c e = sum_q
||(W e)_q||^2`` where ``(W e)_q``, the rows of quantity ``q``, is its whitened conditional residual.
The robust cost replaces each term ``s_q = ||(W e)_q||^2`` by ``rho(s_q)``,

    c_rho(tau) = sum_q rho(s_q),    Huber: rho(s) = s if s <= d^2 else 2 d sqrt(s) - d^2,
                                    Cauchy: rho(s) = d^2 log(1 + s / d^2),

with ``d^2`` the 95 % chi-square quantile of the quantity's dimension (5.99 for a point, 7.81
for a pose, 3.84 for a heading: the usual SLAM choice, e.g. ORB-SLAM's Huber thresholds), so a
quantity that fits its Gaussian at the 95 % level keeps its least-squares weight and ``rho(s) = s``
gives CM (12) exactly. It is minimised by iteratively re-weighted Gauss-Newton (the weights
``rho'(s_q)`` on the rows of ``W``: ``Lambda_w = W^T diag(rho') W`` in place of ``Lambda``), the
steps accepted on the robust cost; the covariance of the optimum is ``(J^T Lambda_w J)^-1``
(:attr:`OptimiserResult.information`).

``r_hat`` is obtained once by a sparse solve (never a dense inverse). It puts the angle
components of ``psi`` on the 2-pi branch nearest to ``r_hat`` (so the cost is smooth in the
headings), and the minimisers evaluate the cost in the equivalent residual form CM (12) =
CM (13) + ``eta^T r_hat``: near the optimum CM (13) is a difference of two large terms whose
rounding error (``~ 1e-16 eta^T r_hat``) would limit the attainable accuracy of ``tau`` to about
``1e-7``; the residual form is a small ``chi^2`` with full relative precision. Cost and gradient
are the same functions up to the constant; :meth:`RelativeProblem.cost` and
:meth:`RelativeProblem.gradient` evaluate CM (13) and its gradient literally.

Speed note: since SciPy 1.15 L-BFGS-B makes BLAS calls on tiny vectors, and a multi-threaded
OpenBLAS on a busy machine can then dominate the run time (scipy/scipy#22438). On sim-1-sized
problems (35 headings, ~250 positions) ``"reduced"`` took 0.04-0.13 s with
``OPENBLAS_NUM_THREADS=1`` and 0.4-0.6 s without; ``"gauss-newton"`` (0.01-0.04 s) is barely
affected. Worker processes should run with one BLAS thread.

The result carries the optimum, iterations, time and the Gauss-Newton information
``J^T Lambda J`` at the optimum, whose inverse blocks (:meth:`OptimiserResult.marginals`) are the
covariances of the global estimates, obtained by solving for the needed columns only.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from filters.geometry import compose, transform_point, wrap_angle
from filters.information import sparse_spd_factor
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

POSE = "pose"
POINT = "point"
HEADING = "heading"
QUANTITY_DIM = {POSE: 3, POINT: 2, HEADING: 1}
ENTITY_KINDS = (POSE, POINT)
METHODS = ("reduced", "gauss-newton", "levenberg-marquardt")
QUASI_NEWTON = ("L-BFGS-B", "BFGS")
ROBUST_KERNELS = (None, "huber", "cauchy")
ROBUST_PROBABILITY = 0.95
"""Chi-square probability of a quantity's kernel threshold (module docstring)."""


def robust_rho(kernel, s, threshold2):
    """``(rho(s), rho'(s))`` of ``kernel`` (None, ``"huber"``, ``"cauchy"``) for squared whitened
    residuals ``s`` (>= 0) with squared thresholds ``threshold2`` (module docstring)."""
    s = np.asarray(s, dtype=float)
    d2 = np.asarray(threshold2, dtype=float)
    if kernel is None:
        return s.copy(), np.ones_like(s)
    if kernel == "huber":
        root = np.sqrt(np.maximum(s, d2))
        inside = s <= d2
        d = np.sqrt(d2)
        return np.where(inside, s, 2.0 * d * root - d2), np.where(inside, 1.0, d / root)
    if kernel == "cauchy":
        return d2 * np.log1p(s / d2), 1.0 / (1.0 + s / d2)
    raise ValueError(f"robust={kernel!r} is invalid: must be one of {ROBUST_KERNELS}")


@dataclass(frozen=True)
class RelativeQuantity:
    """One relative quantity of the stacked vector: ``kind`` of ``target`` in pose ``frame``."""

    kind: str
    frame: int
    target: int

    @property
    def dim(self) -> int:
        return QUANTITY_DIM[self.kind]


@dataclass(frozen=True)
class GaussianConstraint:
    """A Gaussian over several relative quantities: mean (d,) and information (d, d).

    E.g. one fused sub-map: its end pose and landmarks in its start frame with the inverse of their
    joint covariance.
    """

    quantities: tuple
    mean: np.ndarray
    information: np.ndarray


@dataclass
class OptimiserResult:
    """Outcome of :meth:`RelativeProblem.optimise`.

    ``means`` (n_entities, 3): global coordinates of every entity (points have NaN heading),
    headings wrapped. ``tau`` the variable vector. ``cost`` CM (13) at the optimum.
    """

    means: np.ndarray
    tau: np.ndarray
    cost: float
    iterations: int
    evaluations: int
    time_s: float
    converged: bool
    method: str
    message: str = ""
    problem: RelativeProblem | None = field(default=None, repr=False)
    robust: str | None = None
    robust_cost: float | None = None
    weights: np.ndarray | None = field(default=None, repr=False)
    _factor: object = field(default=None, repr=False)

    @property
    def information(self):
        """The information of the relative quantities the optimum was weighted with: ``Lambda``,
        or with a robust kernel ``W^T diag(rho') W`` at the optimum (module docstring)."""
        p = self.problem
        if self.robust is None or self.weights is None:
            return p.Lambda
        return p.weighted_information(self.weights)

    def _gn_factor(self):
        if self._factor is None:
            p = self.problem
            J = p.psi_jacobian(self.tau)
            H = (J.T @ self.information @ J).tocsc()
            self._factor = sparse_spd_factor(H)
        return self._factor

    def marginals(self, entities) -> list[np.ndarray]:
        """Gauss-Newton covariance blocks ``(J^T Lambda J)^-1`` of the listed entities.

        Poses get (3, 3), points (2, 2); the gauge has zero covariance. Only the needed columns
        are solved for.
        """
        p = self.problem
        entities = [int(e) for e in entities]
        cols = [p.variable_columns(e) for e in entities]
        n_rhs = sum(len(c) for c in cols)
        E = np.zeros((p.n_variables, n_rhs))
        j = 0
        for c in cols:
            for col in c:
                E[col, j] = 1.0
                j += 1
        X = self._gn_factor().solve(E) if n_rhs else E
        out, j = [], 0
        for e, c in zip(entities, cols, strict=True):
            d = QUANTITY_DIM[p.entity_kinds[e]]
            if len(c) == 0:
                out.append(np.zeros((d, d)))
                continue
            B = X[np.asarray(c)][:, j : j + len(c)]
            out.append(0.5 * (B + B.T))
            j += len(c)
        return out

    def covariance(self, entity: int) -> np.ndarray:
        return self.marginals([entity])[0]


class RelativeProblem:
    """Minimise CM (13) over global coordinates given ``(eta, Lambda)`` of relative quantities.

    Parameters
    ----------
    entity_kinds : sequence of ``"pose"`` / ``"point"``, one per global entity.
    quantities : sequence of :class:`RelativeQuantity` (or ``(kind, frame, target)`` tuples) in
        the order of the stacked vector; ``frame`` must be a pose; ``target`` a pose for
        ``"pose"``/``"heading"``, a point for ``"point"``.
    eta, Lambda : information vector and (sparse) symmetric positive definite matrix over the
        stacked vector.
    gauge : index of the pose held fixed at ``gauge_pose``.
    """

    def __init__(self, entity_kinds, quantities, eta, Lambda, *, gauge=0, gauge_pose=None,
                 _r_hat=None):
        kinds = list(entity_kinds)
        require(len(kinds) > 0, "entity_kinds", entity_kinds, "a non-empty sequence")
        bad = [k for k in kinds if k not in ENTITY_KINDS]
        require(not bad, "entity_kinds", bad[:3], f"each one of {ENTITY_KINDS}")
        self.entity_kinds = kinds
        n_ent = len(kinds)
        require(
            isinstance(gauge, (int, np.integer)) and 0 <= gauge < n_ent and kinds[gauge] == POSE,
            "gauge",
            gauge,
            "the index of a pose entity",
        )
        self.gauge = int(gauge)
        g = np.zeros(3) if gauge_pose is None else np.asarray(gauge_pose, dtype=float)
        require(
            g.shape == (3,) and bool(np.all(np.isfinite(g))),
            "gauge_pose",
            gauge_pose,
            "a finite (x, y, theta)",
        )
        self.gauge_pose = g
        qs = [q if isinstance(q, RelativeQuantity) else RelativeQuantity(*q) for q in quantities]
        require(len(qs) > 0, "quantities", quantities, "a non-empty sequence")
        for q in qs:
            require(
                q.kind in QUANTITY_DIM, "quantities.kind", q.kind, f"one of {tuple(QUANTITY_DIM)}"
            )
            ok_f = 0 <= q.frame < n_ent and kinds[q.frame] == POSE
            require(ok_f, "quantities.frame", q, "the index of a pose entity")
            want = POINT if q.kind == POINT else POSE
            ok_t = 0 <= q.target < n_ent and kinds[q.target] == want and q.target != q.frame
            require(ok_t, "quantities.target", q, f"the index of a {want} entity other than frame")
        self.quantities = qs
        dims = np.array([q.dim for q in qs])
        self.n_r = int(dims.sum())
        eta = np.asarray(eta, dtype=float)
        require(eta.shape == (self.n_r,), "eta", eta.shape, f"a vector of length {self.n_r}")
        Lambda = sp.csc_matrix(Lambda, dtype=float)
        require(
            Lambda.shape == (self.n_r, self.n_r),
            "Lambda",
            Lambda.shape,
            f"a ({self.n_r}, {self.n_r}) matrix",
        )
        self.eta = eta
        self.Lambda = Lambda
        self._constraint_information = None  # the dense blocks, when stacked from constraints
        self._robust_cache = None

        # Variable layout: [x, y of every non-gauge entity ; theta of every non-gauge pose].
        free = [e for e in range(n_ent) if e != self.gauge]
        self._pcol = np.full(n_ent, -1)
        self._pcol[free] = 2 * np.arange(len(free))
        self.n_positions = 2 * len(free)
        free_poses = [e for e in free if kinds[e] == POSE]
        self._tcol = np.full(n_ent, -1)
        self._tcol[free_poses] = self.n_positions + np.arange(len(free_poses))
        self.n_variables = self.n_positions + len(free_poses)
        self._is_pose = np.array([k == POSE for k in kinds])

        starts = np.concatenate([[0], np.cumsum(dims)[:-1]])
        kind_arr = np.array([q.kind for q in qs])
        fr = np.array([q.frame for q in qs])
        tg = np.array([q.target for q in qs])
        has_pos = kind_arr != HEADING
        has_ang = kind_arr != POINT
        self._pf, self._pt = fr[has_pos], tg[has_pos]
        self._rx = starts[has_pos]
        self._ry = starts[has_pos] + 1
        self._af, self._at = fr[has_ang], tg[has_ang]
        self._ra = np.where(kind_arr[has_ang] == POSE, starts[has_ang] + 2, starts[has_ang])

        if _r_hat is not None:  # from_constraints: Lambda^-1 eta is the stacked means
            self.r_hat = np.asarray(_r_hat, dtype=float)
        else:
            try:
                self.r_hat = sparse_spd_factor(self.Lambda).solve(self.eta)
            except RuntimeError as exc:  # singular factor
                raise ValueError(f"Lambda is invalid: must be positive definite ({exc})") from exc
        require(
            bool(np.all(np.isfinite(self.r_hat))),
            "Lambda",
            "singular",
            "a positive definite matrix",
        )
        self._check_connected()

    # ----------------------------------------------------------------- construction helpers
    @classmethod
    def from_constraints(cls, entity_kinds, constraints, *, gauge=0, gauge_pose=None):
        """Stack independent :class:`GaussianConstraint` s into one block-diagonal problem.

        Each information matrix must be positive definite (checked by its Cholesky factor); the
        stacked ``Lambda^-1 eta`` is then the stacked means, so no factorisation of the whole
        ``Lambda`` is needed."""
        require(len(constraints) > 0, "constraints", constraints, "a non-empty sequence")
        quantities, etas, blocks, means = [], [], [], []
        for c in constraints:
            qs = [
                q if isinstance(q, RelativeQuantity) else RelativeQuantity(*q) for q in c.quantities
            ]
            d = sum(q.dim for q in qs)
            m = np.asarray(c.mean, dtype=float)
            L = np.asarray(c.information, dtype=float)
            require(m.shape == (d,), "constraints.mean", m.shape, f"a vector of length {d}")
            require(L.shape == (d, d), "constraints.information", L.shape, f"a ({d}, {d}) matrix")
            L = 0.5 * (L + L.T)
            try:
                np.linalg.cholesky(L)
            except np.linalg.LinAlgError as exc:
                raise ValueError("constraints.information is invalid: must be positive "
                                 f"definite ({exc})") from exc
            quantities.extend(qs)
            etas.append(L @ m)
            blocks.append(L)
            means.append(m)
        problem = cls(
            entity_kinds,
            quantities,
            np.concatenate(etas),
            sp.block_diag(blocks, format="csc"),
            gauge=gauge,
            gauge_pose=gauge_pose,
            _r_hat=np.concatenate(means),
        )
        problem._constraint_information = blocks
        return problem

    # ----------------------------------------------------------------- robust kernels
    def _robust_structure(self):
        """``(W, rows of each quantity's factor, its squared threshold)`` (module docstring);
        built once, for problems stacked from constraints."""
        if self._robust_cache is None:
            from scipy.stats import chi2

            infos = self._constraint_information
            require(
                infos is not None, "robust", "a kernel",
                "None for a problem not stacked from constraints (from_constraints)",
            )
            Ws = []
            for L in infos:
                # W lower triangular with W^T W = L: the Cholesky factor of the reversed matrix
                rev = np.linalg.cholesky(L[::-1, ::-1])
                Ws.append(sp.csr_matrix(rev.T[::-1, ::-1]))
            dims = np.array([q.dim for q in self.quantities])
            factor = np.repeat(np.arange(len(dims)), dims)
            thresholds = chi2.ppf(ROBUST_PROBABILITY, dims)
            self._robust_cache = (sp.block_diag(Ws, format="csr"), factor, thresholds)
        return self._robust_cache

    def factor_residuals(self, tau) -> np.ndarray:
        """``s_q = ||(W e)_q||^2`` of every quantity at ``tau`` (``e = psi - r_hat``): its
        whitened conditional residual; they sum to CM (12)."""
        W, factor, _ = self._robust_structure()
        w = W @ (self.psi(tau) - self.r_hat)
        return np.bincount(factor, weights=w * w, minlength=len(self.quantities))

    def robust_cost(self, tau, robust) -> float:
        """``sum_q rho(s_q)`` (module docstring); CM (12) for ``robust=None``."""
        require(robust in ROBUST_KERNELS, "robust", robust, f"one of {ROBUST_KERNELS}")
        _, _, thresholds = self._robust_structure()
        return float(robust_rho(robust, self.factor_residuals(tau), thresholds)[0].sum())

    def robust_gradient(self, tau, robust) -> np.ndarray:
        """Gradient of :meth:`robust_cost`: ``2 J^T W^T diag(rho'(s)) W e``."""
        _, _, thresholds = self._robust_structure()
        weights = robust_rho(robust, self.factor_residuals(tau), thresholds)[1]
        P, Th = self.unpack(tau)
        e = self._psi(P, Th) - self.r_hat
        return 2.0 * (self._jacobian(P, Th).T @ (self.weighted_information(weights) @ e))

    def weighted_information(self, weights) -> sp.csc_matrix:
        """``W^T diag(w) W`` with one weight per quantity (``w = 1``: ``Lambda``)."""
        W, factor, _ = self._robust_structure()
        return (W.T @ sp.diags(np.asarray(weights, dtype=float)[factor]) @ W).tocsc()

    def _check_connected(self):
        reach = self._spanning_order()
        missing = [e for e in range(len(self.entity_kinds)) if e not in reach]
        require(
            not missing,
            "quantities",
            f"entities {missing[:5]} unreachable",
            "a structure linking every entity to the gauge by pose/point quantities",
        )

    def _spanning_order(self) -> dict[int, tuple[int, int]]:
        """Breadth-first tree from the gauge: entity -> (quantity index, direction)."""
        out_q: dict[int, list[int]] = {}
        in_q: dict[int, list[int]] = {}
        for i, q in enumerate(self.quantities):
            if q.kind == HEADING:
                continue
            out_q.setdefault(q.frame, []).append(i)
            if q.kind == POSE:
                in_q.setdefault(q.target, []).append(i)
        tree = {self.gauge: (-1, 0)}
        queue = deque([self.gauge])
        while queue:
            e = queue.popleft()
            for i in out_q.get(e, ()):
                t = self.quantities[i].target
                if t not in tree:
                    tree[t] = (i, +1)
                    queue.append(t)
            for i in in_q.get(e, ()):
                f = self.quantities[i].frame
                if f not in tree:
                    tree[f] = (i, -1)
                    queue.append(f)
        return tree

    # ----------------------------------------------------------------- variables
    def variable_columns(self, e: int) -> list[int]:
        """Columns of ``tau`` holding entity ``e`` (x, y[, theta]); empty for the gauge."""
        if e == self.gauge:
            return []
        cols = [int(self._pcol[e]), int(self._pcol[e]) + 1]
        if self._is_pose[e]:
            cols.append(int(self._tcol[e]))
        return cols

    def unpack(self, tau):
        """Entity positions (n, 2) and headings (n,) (points: 0) from ``tau``."""
        tau = np.asarray(tau, dtype=float)
        n = len(self.entity_kinds)
        P = np.empty((n, 2))
        free = self._pcol >= 0
        P[free, 0] = tau[self._pcol[free]]
        P[free, 1] = tau[self._pcol[free] + 1]
        P[self.gauge] = self.gauge_pose[:2]
        Th = np.zeros(n)
        tf = self._tcol >= 0
        Th[tf] = tau[self._tcol[tf]]
        Th[self.gauge] = self.gauge_pose[2]
        return P, Th

    def pack(self, P, Th) -> np.ndarray:
        tau = np.empty(self.n_variables)
        free = self._pcol >= 0
        tau[self._pcol[free]] = P[free, 0]
        tau[self._pcol[free] + 1] = P[free, 1]
        tf = self._tcol >= 0
        tau[self._tcol[tf]] = Th[tf]
        return tau

    def means(self, tau) -> np.ndarray:
        """Entity coordinates (n, 3) from ``tau``: headings wrapped, NaN for points."""
        P, Th = self.unpack(tau)
        out = np.column_stack([P, wrap_angle(Th)])
        out[~self._is_pose, 2] = np.nan
        return out

    def initial_guess(self, known=None) -> np.ndarray:
        """``tau`` from composing ``r_hat`` along a breadth-first spanning tree from the gauge.

        ``known`` (optional) maps entities to coordinates to start from instead (a warm start:
        e.g. the previous optimum of a problem this one extends; a pose (3,), a point (2,)); the
        other entities are composed from their parents in the tree as usual."""
        n = len(self.entity_kinds)
        poses = np.zeros((n, 3))
        poses[self.gauge] = self.gauge_pose
        known = {} if known is None else known
        starts = np.concatenate([[0], np.cumsum([q.dim for q in self.quantities])])
        tree = self._spanning_order()  # insertion order: parents before children
        for e in tree:
            i, direction = tree[e]
            if e in known and e != self.gauge:
                value = np.asarray(known[e], dtype=float)
                dim = 3 if self._is_pose[e] else 2
                require(value.shape == (dim,) and bool(np.all(np.isfinite(value))),
                        f"known[{e}]", value, f"finite coordinates of shape ({dim},)")
                poses[e, :dim] = value
                continue
            if i < 0:
                continue
            q = self.quantities[i]
            r = self.r_hat[starts[i] : starts[i + 1]]
            if q.kind == POINT:
                poses[e, :2] = transform_point(poses[q.frame], r)
            elif direction > 0:
                poses[e] = compose(poses[q.frame], r)
                poses[e, 2] = poses[q.frame, 2] + r[2]
            else:  # frame from target: x_f = x_t (+) (-) r
                c, s = np.cos(r[2]), np.sin(r[2])
                inv = np.array([-c * r[0] - s * r[1], s * r[0] - c * r[1], -r[2]])
                poses[e] = compose(poses[q.target], inv)
                poses[e, 2] = poses[q.target, 2] - r[2]
        return self.pack(poses[:, :2], poses[:, 2])

    # ----------------------------------------------------------------- psi and cost
    def psi(self, tau) -> np.ndarray:
        """Relative quantities ``psi(tau)`` (inverse compositions); angles near ``r_hat``."""
        P, Th = self.unpack(tau)
        return self._psi(P, Th)

    def _psi(self, P, Th):
        r = np.empty(self.n_r)
        d = P[self._pt] - P[self._pf]
        c, s = np.cos(Th[self._pf]), np.sin(Th[self._pf])
        r[self._rx] = c * d[:, 0] + s * d[:, 1]
        r[self._ry] = -s * d[:, 0] + c * d[:, 1]
        ref = self.r_hat[self._ra]
        r[self._ra] = ref + wrap_angle(Th[self._at] - Th[self._af] - ref)
        return r

    def psi_jacobian(self, tau) -> sp.csr_matrix:
        """Sparse ``d psi / d tau`` (n_r, n_variables)."""
        P, Th = self.unpack(tau)
        return self._jacobian(P, Th)

    def _jacobian(self, P, Th, positions_only=False):
        d = P[self._pt] - P[self._pf]
        c, s = np.cos(Th[self._pf]), np.sin(Th[self._pf])
        relx = c * d[:, 0] + s * d[:, 1]
        rely = -s * d[:, 0] + c * d[:, 1]
        pt, pf = self._pcol[self._pt], self._pcol[self._pf]
        rx, ry = self._rx, self._ry
        rows = [rx, rx, ry, ry, rx, rx, ry, ry]
        cols = [pt, pt + 1, pt, pt + 1, pf, pf + 1, pf, pf + 1]
        vals = [c, s, -s, c, -c, -s, s, -c]
        valid = [pt >= 0] * 4 + [pf >= 0] * 4
        if not positions_only:
            tf = self._tcol[self._pf]
            rows += [rx, ry]
            cols += [tf, tf]
            vals += [rely, -relx]
            valid += [tf >= 0, tf >= 0]
            at, af = self._tcol[self._at], self._tcol[self._af]
            ones = np.ones(len(self._ra))
            rows += [self._ra, self._ra]
            cols += [at, af]
            vals += [ones, -ones]
            valid += [at >= 0, af >= 0]
        mask = np.concatenate(valid)
        ncols = self.n_positions if positions_only else self.n_variables
        return sp.csr_matrix(
            (
                np.concatenate(vals)[mask],
                (np.concatenate(rows)[mask], np.concatenate(cols)[mask]),
            ),
            shape=(self.n_r, ncols),
        )

    def cost(self, tau) -> float:
        """CM (13): ``psi^T Lambda psi - 2 psi^T eta`` (no inverse of Lambda)."""
        r = self.psi(tau)
        return float(r @ (self.Lambda @ r) - 2.0 * r @ self.eta)

    def gradient(self, tau) -> np.ndarray:
        """``J_psi^T (2 Lambda psi - 2 eta)``."""
        P, Th = self.unpack(tau)
        r = self._psi(P, Th)
        return self._jacobian(P, Th).T @ (2.0 * (self.Lambda @ r) - 2.0 * self.eta)

    def weighted_residual_cost(self, tau) -> float:
        """CM (12): ``(psi - r_hat)^T Lambda (psi - r_hat)`` = CM (13) + ``eta^T r_hat``."""
        e = self.psi(tau) - self.r_hat
        return float(e @ (self.Lambda @ e))

    # ----------------------------------------------------------------- reduced problem
    def optimal_positions(self, theta) -> np.ndarray:
        """Exact minimiser over positions for fixed free headings ``theta`` (sparse solve)."""
        P, Th = self._with_theta(theta)
        P[self._pcol >= 0] = 0.0
        b = self._psi(P, Th)  # psi at p = 0: the affine offset
        A = self._jacobian(P, Th, positions_only=True)
        lhs = (A.T @ self.Lambda @ A).tocsc()
        rhs = A.T @ (self.Lambda @ (self.r_hat - b))  # = A^T (eta - Lambda b)
        return sparse_spd_factor(lhs).solve(rhs)

    def _with_theta(self, theta):
        n = len(self.entity_kinds)
        P = np.zeros((n, 2))
        P[self.gauge] = self.gauge_pose[:2]
        Th = np.zeros(n)
        tf = self._tcol >= 0
        Th[tf] = np.asarray(theta, dtype=float)[self._tcol[tf] - self.n_positions]
        Th[self.gauge] = self.gauge_pose[2]
        return P, Th

    def reduced_cost_and_gradient(self, theta):
        """Cost with positions eliminated, and its gradient in ``theta``; also the full ``tau``.

        The cost is CM (13) + ``eta^T r_hat``, evaluated in the residual form CM (12) (see the
        module docstring); the gradient is ``dc/dtheta`` at the optimal positions (envelope
        theorem), ``J_theta^T 2 Lambda (psi - r_hat) = J_theta^T (2 Lambda psi - 2 eta)``.
        """
        p = self.optimal_positions(theta)
        tau = np.concatenate([p, theta])
        P, Th = self.unpack(tau)
        e = self._psi(P, Th) - self.r_hat
        Le = self.Lambda @ e
        g = self._jacobian(P, Th).T @ (2.0 * Le)
        return float(e @ Le), g[self.n_positions :], tau

    # ----------------------------------------------------------------- minimisers
    def optimise(
        self,
        method: str = "reduced",
        tau0=None,
        *,
        max_iterations: int = 200,
        gtol: float = 1e-8,
        xtol: float = 1e-10,
        quasi_newton: str = "L-BFGS-B",
        robust: str | None = None,
    ) -> OptimiserResult:
        """Minimise CM (13); see the module docstring for the methods.

        ``tau0``: start (default :meth:`initial_guess`). ``gtol``: gradient tolerance of the
        quasi-Newton method on the cost per coordinate of ``r`` (``"reduced"``); ``xtol``: relative
        step tolerance of Gauss-Newton; ``quasi_newton``: ``"L-BFGS-B"`` or ``"BFGS"``.
        ``robust``: None (CM (12)), ``"huber"`` or ``"cauchy"`` (module docstring; Gauss-Newton
        and Levenberg-Marquardt, problems stacked from constraints).
        """
        require(method in METHODS, "method", method, f"one of {METHODS}")
        require(robust in ROBUST_KERNELS, "robust", robust, f"one of {ROBUST_KERNELS}")
        require(
            robust is None or method != "reduced", "robust", robust,
            "None with method='reduced' (robust kernels use Gauss-Newton)",
        )
        if robust is not None:
            self._robust_structure()  # ValueError naming robust if the blocks are unknown
        require(
            quasi_newton in QUASI_NEWTON, "quasi_newton", quasi_newton, f"one of {QUASI_NEWTON}"
        )
        require(
            isinstance(max_iterations, int) and 1 <= max_iterations <= 100000,
            "max_iterations",
            max_iterations,
            "an integer in [1, 100000]",
        )
        check_range("gtol", gtol, 0.0, 1.0, low_open=True)
        check_range("xtol", xtol, 0.0, 1.0, low_open=True)
        tau0 = self.initial_guess() if tau0 is None else np.asarray(tau0, dtype=float)
        require(
            tau0.shape == (self.n_variables,),
            "tau0",
            tau0.shape,
            f"a vector of length {self.n_variables}",
        )
        t0 = time.perf_counter()
        if method == "reduced":
            res = self._optimise_reduced(tau0, max_iterations, gtol, quasi_newton)
        else:
            lam0 = 0.0 if method == "gauss-newton" else 1e-3
            res = self._optimise_lm(tau0, max_iterations, xtol, lam0, robust)
        tau, iters, evals, converged, msg = res
        weights = rcost = None
        if robust is not None:
            _, _, thresholds = self._robust_structure()
            rho, weights = robust_rho(robust, self.factor_residuals(tau), thresholds)
            rcost = float(rho.sum())
        out = OptimiserResult(
            means=self.means(tau),
            tau=tau,
            cost=self.cost(tau),
            iterations=iters,
            evaluations=evals,
            time_s=time.perf_counter() - t0,
            converged=converged,
            method=method,
            message=msg,
            problem=self,
            robust=robust,
            robust_cost=rcost,
            weights=weights,
        )
        logger.debug("optimise %s: %d iterations, %.3f s, %s", method, iters, out.time_s, msg)
        return out

    def _optimise_reduced(self, tau0, max_iterations, gtol, quasi_newton):
        theta0 = tau0[self.n_positions :]
        if theta0.size == 0:  # only the gauge has a heading: one linear solve
            tau = np.concatenate([self.optimal_positions(theta0), theta0])
            return tau, 0, 1, True, "positions only"
        scale = float(self.n_r)  # cost per coordinate: O(1) at the optimum
        first_gradient = []

        def fun(theta):
            f, g, _ = self.reduced_cost_and_gradient(theta)
            if not first_gradient:
                first_gradient.append(np.max(np.abs(g)) / scale)
            return f / scale, g / scale

        options = {"maxiter": max_iterations, "gtol": gtol}
        if quasi_newton == "L-BFGS-B":
            options |= {"ftol": 1e-15, "maxcor": 30}
        from scipy.optimize import minimize  # here: scipy.optimize costs every process ~0.3 s

        res = minimize(fun, theta0, jac=True, method=quasi_newton, options=options)
        theta = res.x
        # a line-search stop at the precision limit counts as converged if the gradient vanished
        # or if no step along steepest descent lowers the cost any more (the LM branch's "no
        # further decrease"): on nearly noise-free data the gradient at the limit of float64
        # need not fall by the fixed factor
        small = np.max(np.abs(res.jac)) <= 1e-6 * max(1.0, first_gradient[0])
        if not (res.success or small):
            small = _no_descent_step(fun, theta, res.fun, res.jac)
        tau = np.concatenate([self.optimal_positions(theta), theta])
        return tau, int(res.nit), int(res.nfev), bool(res.success or small), str(res.message)

    def _optimise_lm(self, tau, max_iterations, xtol, lam0, robust=None):
        if robust is None:
            def residual_cost(t):
                P, Th = self.unpack(t)
                e = self._psi(P, Th) - self.r_hat
                return float(e @ (self.Lambda @ e)), P, Th
        else:  # iteratively re-weighted: the weights at the current iterate (module docstring)
            W, factor, thresholds = self._robust_structure()
            n_q = len(self.quantities)

            def residual_cost(t):
                P, Th = self.unpack(t)
                w = W @ (self._psi(P, Th) - self.r_hat)
                s = np.bincount(factor, weights=w * w, minlength=n_q)
                return float(robust_rho(robust, s, thresholds)[0].sum()), P, Th

        def information(P, Th):
            if robust is None:
                return self.Lambda
            w = W @ (self._psi(P, Th) - self.r_hat)
            s = np.bincount(factor, weights=w * w, minlength=n_q)
            return self.weighted_information(robust_rho(robust, s, thresholds)[1])

        cost, P, Th = residual_cost(tau)
        lam, evals, it = lam0, 1, 0
        converged, msg = False, "maximum iterations reached"
        while it < max_iterations:
            it += 1
            J = self._jacobian(P, Th)
            Lam = information(P, Th)
            g = J.T @ (Lam @ (self._psi(P, Th) - self.r_hat))
            H = (J.T @ Lam @ J).tocsc()
            diag = sp.diags(H.diagonal())
            accepted = False
            tiny = False
            while not accepted and lam <= 1e12:
                step = -sparse_spd_factor(H + lam * diag if lam > 0 else H).solve(g)
                tiny = np.max(np.abs(step)) <= xtol * (1.0 + np.max(np.abs(tau)))
                new_cost, nP, nTh = residual_cost(tau + step)
                evals += 1
                accepted = bool(new_cost <= cost)
                if not accepted:
                    if tiny:  # rounding noise: the cost cannot be resolved any further
                        break
                    lam = max(1e-6, 10.0 * lam)
            if not accepted:  # no descent step left: at the minimum to working precision
                converged, msg = True, "no further decrease"
                break
            decrease = cost - new_cost
            tau, cost, P, Th = tau + step, new_cost, nP, nTh
            lam = 0.0 if (lam0 == 0.0 and lam <= 1e-6) else lam / 10.0
            if tiny or decrease <= 1e-15 * max(1.0, cost):
                converged, msg = True, "step below tolerance"
                break
        return tau, it, evals, converged, msg


def _no_descent_step(fun, theta, f0: float, g) -> bool:
    """Whether no step along ``-g`` (lengths from 1e-12 to 1 of ``max(1, |theta|)``) lowers
    ``fun`` below ``f0`` by more than rounding (1e-14 relative): a minimum to working precision."""
    norm = float(np.linalg.norm(g))
    if norm == 0.0:
        return True
    direction = -np.asarray(g) / norm
    scale = max(1.0, float(np.linalg.norm(theta)))
    for t in np.geomspace(1e-12, 1.0, 13) * scale:
        if fun(theta + t * direction)[0] < f0 - 1e-14 * max(1.0, abs(f0)):
            return False
    return True
