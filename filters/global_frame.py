"""The global frame of a sub-map system, compiled: the local pose composed with the local map's
origin (BB Fig. 3), CM's innovation ratio of the observations of global features (CM III.B) and
the pose NEES against the truth.

These are the per-iteration pieces of :class:`filters.submap.SubmapSLAM` and of the episode's
metrics; they live here, apart from both, so that the compiled filter iteration
(:func:`filters.fastslam_kernel.iteration`) runs them in the same call as the scan (issue 47).
"""

from __future__ import annotations

import numpy as np
from numba import njit

NEES_REGULARISATION = 1e-9
"""Added to the covariance's diagonal before NEES (a std of 3e-5 m / rad): keeps numerically
singular covariances (a filter's first iteration, particle sets with one distinct pose) from
producing garbage, far below any uncertainty a filter actually reports."""


@njit(cache=True)
def compose_with_covariance(v, P_v, xl, Pl):
    """``(v (+) xl, J_a P_v J_a^T + J_b Pl J_b^T, J_a)`` (BB Fig. 3; the covariance symmetrised):
    :func:`filters.geometry.compose` and :func:`filters.geometry.compose_jacobians` written out
    for one pair of poses, compiled because the system composes at every iteration."""
    c, s = np.cos(v[2]), np.sin(v[2])
    mean = np.empty(3)
    mean[0] = v[0] + c * xl[0] - s * xl[1]
    mean[1] = v[1] + s * xl[0] + c * xl[1]
    mean[2] = (v[2] + xl[2] + np.pi) % (2.0 * np.pi) - np.pi
    J_a = np.eye(3)
    J_a[0, 2] = -s * xl[0] - c * xl[1]
    J_a[1, 2] = c * xl[0] - s * xl[1]
    J_b = np.zeros((3, 3))
    J_b[0, 0], J_b[0, 1], J_b[1, 0], J_b[1, 1], J_b[2, 2] = c, -s, s, c, 1.0
    cov = J_a @ P_v @ J_a.T + J_b @ Pl @ J_b.T
    return mean, 0.5 * (cov + cov.T), J_a


@njit(cache=True)
def nearest_global_innovations(z, pose, sigma, J_a, x, P, cols, r_var, b_var, radius_m):
    """The global feature each observation is nearest to, and CM's innovation ratio, in metres.

    Predicts each global feature ``m_n`` near an observation from the composed pose ``pose``
    (covariance ``sigma``, ``J_a`` its Jacobian w.r.t. the origin ``v-``): ``S_n = H_p sigma
    H_p^T + H_m P_mm H_m^T + X + X^T + R`` with the pose-feature cross term
    ``X = H_p J_a P[v-, m_n] H_m^T`` (:func:`predict_global_feature`).
    Observation ``k`` is paired with the feature of smallest ``nu^T S_n^-1 nu`` among those whose
    position lies within ``radius_m`` of the observed point -- no chi-square gate, so an
    inconsistent re-observation is still tested (-1: no feature that near). Range and bearing
    innovations are brought to one unit: ``T = diag(1, r_n)`` turns the bearing innovation into
    the cross-range distance at the predicted range, and ``ratio[k] = ||T nu|| / (2 sigma_n)``
    with ``sigma_n^2`` the largest eigenvalue of ``T S_n T``: CM's test ``||nu|| > 2 sigma``
    (CM III.B) reads ``ratio > 1``.
    """
    N, K = cols.shape[0], z.shape[0]
    terms = np.empty((N, 5))  # per feature: range, bearing, S00, S01, S11
    predicted = np.zeros(N, dtype=np.bool_)  # a feature's terms are formed when first needed
    nearest = np.full(K, -1, dtype=np.int64)
    ratio = np.zeros(K)
    for k in range(K):
        px = pose[0] + z[k, 0] * np.cos(z[k, 1] + pose[2])
        py = pose[1] + z[k, 0] * np.sin(z[k, 1] + pose[2])
        best = np.inf
        for n in range(N):
            ex, ey = x[cols[n, 0]] - px, x[cols[n, 1]] - py
            if ex * ex + ey * ey > radius_m * radius_m:
                continue
            if not predicted[n]:
                predict_global_feature(n, pose, sigma, J_a, x, P, cols, r_var, b_var, terms)
                predicted[n] = True
            z_range, z_bearing = terms[n, 0], terms[n, 1]
            S00, S01, S11 = terms[n, 2], terms[n, 3], terms[n, 4]
            nu_r = z[k, 0] - z_range
            nu_b = (z[k, 1] - z_bearing + np.pi) % (2.0 * np.pi) - np.pi
            det = S00 * S11 - S01 * S01
            d2 = (S11 * nu_r * nu_r - 2.0 * S01 * nu_r * nu_b + S00 * nu_b * nu_b) / det
            if d2 < best:
                best = d2
                nearest[k] = n
                rn = z_range
                t00, t01, t11 = S00, rn * S01, rn * rn * S11
                top = 0.5 * (t00 + t11) + np.hypot(0.5 * (t00 - t11), t01)
                ratio[k] = np.hypot(nu_r, rn * nu_b) / (2.0 * np.sqrt(top))
    return nearest, ratio


@njit(cache=True)
def predict_global_feature(n, pose, sigma, J_a, x, P, cols, r_var, b_var, predicted):
    """The predicted observation of global feature ``n`` and its innovation covariance ``S_n``,
    written into row ``n`` of ``predicted`` (range, bearing, ``S00``, ``S01``, ``S11``), for
    :func:`nearest_global_innovations`, which forms them only for the features near an
    observation (each feature's terms depend on that feature alone)."""
    Hp = np.empty((2, 3))
    Hm = np.empty((2, 2))
    cross = np.empty((3, 2))  # J_a P[v-, m_n]: cov(pose, m_n)
    c0, c1 = cols[n, 0], cols[n, 1]
    dx, dy = x[c0] - pose[0], x[c1] - pose[1]
    q = max(dx * dx + dy * dy, 1e-12)
    r = np.sqrt(q)
    predicted[n, 0] = r
    predicted[n, 1] = (np.arctan2(dy, dx) - pose[2] + np.pi) % (2.0 * np.pi) - np.pi
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
    predicted[n, 2] = A[0, 0] + B[0, 0] + 2.0 * X[0, 0] + r_var
    predicted[n, 3] = 0.5 * (A[0, 1] + A[1, 0] + B[0, 1] + B[1, 0]) + X[0, 1] + X[1, 0]
    predicted[n, 4] = A[1, 1] + B[1, 1] + 2.0 * X[1, 1] + b_var


@njit(cache=True)
def cholesky_nees(e, cov, regularisation):
    """``|L^-1 e|^2`` with ``L L^T = (cov + cov^T) / 2 + regularisation I`` (Cholesky-Banachiewicz,
    forward substitution): the episode takes a NEES at every iteration, and numpy's cholesky and
    solve cost some microseconds each on a 3 x 3."""
    n = len(e)
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            total = 0.5 * (cov[i, j] + cov[j, i]) + (regularisation if i == j else 0.0)
            for k in range(j):
                total -= L[i, k] * L[j, k]
            if i == j:
                if not total > 0.0:  # not positive definite (or NaN)
                    return np.inf
                L[i, i] = np.sqrt(total)
            else:
                L[i, j] = total / L[j, j]
    result = 0.0
    y = np.zeros(n)
    for i in range(n):
        total = e[i]
        for k in range(i):
            total -= L[i, k] * y[k]
        y[i] = total / L[i, i]
        result += y[i] * y[i]
    return result


@njit(cache=True)
def pose_metrics(true_pose, mean, cov):
    """The pose NEES ``e^T P^-1 e`` (heading error wrapped; :func:`cholesky_nees` with
    :data:`NEES_REGULARISATION`) and the position error ``|e_xy|`` of the estimate ``N(mean,
    cov)`` against ``true_pose``; NaN for both when the truth is not finite (no truth at this
    iteration)."""
    e = np.empty(3)
    for i in range(3):
        e[i] = true_pose[i] - mean[i]
        if not np.isfinite(true_pose[i]):
            return np.nan, np.nan
    e[2] = (e[2] + np.pi) % (2.0 * np.pi) - np.pi
    return cholesky_nees(e, cov, NEES_REGULARISATION), np.sqrt(e[0] * e[0] + e[1] * e[1])


_NO_TRUTH = np.full(3, np.nan)


def stepwise_iteration(system, u, dt, z=None, heading=None, truth_pose=None, **update_options):
    """One filter iteration of any estimator through its separate calls: ``predict(u, dt)``,
    ``update_heading(*heading)`` (None: no compass), ``update(z, **update_options)`` (None: no
    scan) and ``pose()``, then the pose's NEES and position error against ``truth_pose`` (None:
    NaN) by :func:`pose_metrics`. Returns ``(mean, cov, nees, position_error_m)``, what
    :meth:`filters.submap.SubmapSLAM.iterate` returns from one compiled call where the
    front-end has one."""
    system.predict(u, dt)
    if heading is not None:
        system.update_heading(*heading)
    if z is not None:
        system.update(z, **update_options)
    mean, cov = system.pose()
    mean = np.asarray(mean, dtype=float)
    cov = np.ascontiguousarray(cov, dtype=float)
    truth = _NO_TRUTH if truth_pose is None else np.asarray(truth_pose, dtype=float)
    value, error = pose_metrics(truth, mean, cov)
    return mean, cov, float(value), float(error)
