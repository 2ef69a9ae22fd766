"""Tests of filters/optimiser.py: CM (13), its gradient, the reduced problem and Gauss-Newton."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from filters.geometry import compose, relative, wrap_angle
from filters.optimiser import (
    HEADING,
    POINT,
    POSE,
    GaussianConstraint,
    RelativeProblem,
    RelativeQuantity,
)


def _truth(rng, n_poses=8, n_points=10):
    """Poses on a rough circle (gauge first) and points around it."""
    ang = np.linspace(0.0, 2.0 * np.pi, n_poses, endpoint=False)
    poses = np.column_stack([10 * np.cos(ang), 10 * np.sin(ang), wrap_angle(ang + np.pi / 2)])
    poses += rng.normal(0.0, [0.5, 0.5, 0.05], poses.shape)
    pts = rng.uniform(-14.0, 14.0, (n_points, 2))
    return poses, pts


def _quantities(rng, n_poses, n_points, *, loop=True, heading=True):
    """Relative quantities over entities [poses..., points...]: a chain, first sightings,
    redundant re-sightings (loop closures), optionally a heading."""
    qs = [RelativeQuantity(POSE, k - 1, k) for k in range(1, n_poses)]
    for j in range(n_points):
        qs.append(RelativeQuantity(POINT, int(rng.integers(n_poses)), n_poses + j))
    if loop:
        for j in range(0, n_points, 2):
            qs.append(RelativeQuantity(POINT, int(rng.integers(n_poses)), n_poses + j))
        qs.append(RelativeQuantity(POSE, n_poses - 1, 0))
    if heading:
        qs.append(RelativeQuantity(HEADING, 0, n_poses // 2))
    return qs


def _psi_truth(qs, poses, pts, n_poses):
    out = []
    for q in qs:
        f = poses[q.frame]
        if q.kind == POSE:
            out.append(relative(f, poses[q.target]))
        elif q.kind == POINT:
            p = pts[q.target - n_poses]
            c, s = np.cos(f[2]), np.sin(f[2])
            d = p - f[:2]
            out.append([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
        else:
            out.append([wrap_angle(poses[q.target, 2] - f[2])])
    return np.concatenate([np.atleast_1d(o) for o in out])


def _random_spd(rng, d, scale):
    A = rng.normal(size=(d, d))
    return scale * (A @ A.T / d + 0.5 * np.eye(d))


def _problem(seed=0, *, noise=True, loop=True, heading=True, n_poses=8, n_points=10):
    """A problem stacked from a few correlated Gaussian constraints (sub-map style)."""
    rng = np.random.default_rng(seed)
    poses, pts = _truth(rng, n_poses, n_points)
    qs = _quantities(rng, n_poses, n_points, loop=loop, heading=heading)
    r_true = _psi_truth(qs, poses, pts, n_poses)
    kinds = [POSE] * n_poses + [POINT] * n_points
    # split the quantities into groups, each a Gaussian with a dense information block
    groups = np.array_split(np.arange(len(qs)), 4)
    constraints = []
    for g in groups:
        sub = [qs[i] for i in g]
        d = sum(q.dim for q in sub)
        L = _random_spd(rng, d, 50.0)
        starts = np.concatenate([[0], np.cumsum([q.dim for q in qs])])
        mean = np.concatenate([r_true[starts[i] : starts[i + 1]] for i in g])
        if noise:
            mean = mean + rng.multivariate_normal(np.zeros(d), np.linalg.inv(L))
        constraints.append(GaussianConstraint(tuple(sub), mean, L))
    prob = RelativeProblem.from_constraints(kinds, constraints, gauge=0, gauge_pose=poses[0])
    tau_true = prob.pack(
        np.vstack([poses[:, :2], pts]), np.concatenate([poses[:, 2], np.zeros(n_points)])
    )
    return prob, tau_true


def _assert_tau_close(prob, a, b, atol):
    """Positions equal, headings equal modulo 2 pi."""
    d = np.asarray(a) - np.asarray(b)
    d[prob.n_positions :] = wrap_angle(d[prob.n_positions :])
    np.testing.assert_allclose(d, 0.0, atol=atol)


def _fd_grad(f, x, h=1e-6):
    g = np.empty_like(x)
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (f(x + e) - f(x - e)) / (2 * h)
    return g


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradient_matches_finite_differences(seed):
    prob, tau_true = _problem(seed)
    rng = np.random.default_rng(100 + seed)
    tau = tau_true + rng.normal(0.0, 0.3, tau_true.shape)
    g = prob.gradient(tau)
    g_fd = _fd_grad(prob.cost, tau)
    np.testing.assert_allclose(g, g_fd, rtol=1e-5, atol=1e-4 * np.max(np.abs(g_fd)))


def test_psi_jacobian_matches_finite_differences():
    prob, tau_true = _problem(3)
    tau = tau_true + np.random.default_rng(7).normal(0.0, 0.2, tau_true.shape)
    J = prob.psi_jacobian(tau).toarray()
    J_fd = np.column_stack(
        [(prob.psi(tau + e) - prob.psi(tau - e)) / 2e-6 for e in 1e-6 * np.eye(prob.n_variables)]
    )
    np.testing.assert_allclose(J, J_fd, atol=1e-6)


def test_cost_is_weighted_least_squares_up_to_a_constant():
    """CM (13) + eta^T r_hat equals CM (12) at any tau."""
    prob, tau_true = _problem(4)
    rng = np.random.default_rng(5)
    const = float(prob.eta @ prob.r_hat)
    for _ in range(3):
        tau = tau_true + rng.normal(0.0, 0.5, tau_true.shape)
        c13 = prob.cost(tau)
        c12 = prob.weighted_residual_cost(tau)
        assert c13 + const == pytest.approx(c12, rel=1e-9, abs=1e-6 * abs(const))


def test_reduced_gradient_envelope_matches_finite_differences():
    prob, tau_true = _problem(6)
    theta = tau_true[prob.n_positions :] + np.random.default_rng(8).normal(
        0.0, 0.05, prob.n_variables - prob.n_positions
    )
    _, g, _ = prob.reduced_cost_and_gradient(theta)
    g_fd = _fd_grad(lambda th: prob.reduced_cost_and_gradient(th)[0], theta)
    np.testing.assert_allclose(g, g_fd, rtol=1e-5, atol=1e-5 * np.max(np.abs(g_fd)))


def test_optimal_positions_zero_the_position_gradient():
    prob, tau_true = _problem(9)
    theta = tau_true[prob.n_positions :] + 0.03
    p = prob.optimal_positions(theta)
    g = prob.gradient(np.concatenate([p, theta]))
    scale = np.max(np.abs(prob.gradient(tau_true + 0.1)))
    assert np.max(np.abs(g[: prob.n_positions])) < 1e-8 * scale


@pytest.mark.parametrize(
    ("method", "quasi_newton"),
    [
        ("reduced", "L-BFGS-B"),
        ("reduced", "BFGS"),
        ("gauss-newton", "L-BFGS-B"),
        ("levenberg-marquardt", "L-BFGS-B"),
    ],
)
def test_noise_free_optimum_is_the_truth(method, quasi_newton):
    prob, tau_true = _problem(10, noise=False)
    res = prob.optimise(method, quasi_newton=quasi_newton)
    assert res.converged
    _assert_tau_close(prob, res.tau, tau_true, 1e-7)
    # the start guess composes r_hat, which is already the truth: perturb it as well
    start = tau_true + np.random.default_rng(1).normal(0.0, 0.2, tau_true.shape)
    res2 = prob.optimise(method, tau0=start, quasi_newton=quasi_newton)
    assert res2.converged and res2.iterations > 0
    _assert_tau_close(prob, res2.tau, tau_true, 1e-7)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_reduced_and_gauss_newton_reach_the_same_optimum(seed):
    prob, tau_true = _problem(seed)
    red = prob.optimise("reduced")
    gn = prob.optimise("gauss-newton")
    assert red.converged and gn.converged
    _assert_tau_close(prob, red.tau, gn.tau, 1e-6)
    assert red.cost == pytest.approx(gn.cost, abs=1e-6 * max(1.0, abs(gn.cost)))
    # it is a minimum: the gradient vanishes and no perturbation lowers the cost
    scale = np.max(np.abs(prob.gradient(tau_true + 0.1)))
    assert np.max(np.abs(prob.gradient(gn.tau))) < 1e-7 * scale
    rng = np.random.default_rng(seed)
    for _ in range(5):
        assert prob.cost(gn.tau + rng.normal(0.0, 1e-3, gn.tau.shape)) > gn.cost


def test_without_redundancy_the_optimum_composes_the_relative_mean_and_its_covariance():
    """A tree of quantities: tau = compose(r_hat) exactly, GN covariance = J Lambda^-1 J^T."""
    prob, _ = _problem(14, loop=False, heading=False, n_poses=5, n_points=4)
    res = prob.optimise("gauss-newton")
    _assert_tau_close(prob, res.tau, prob.initial_guess(), 1e-9)
    np.testing.assert_allclose(prob.psi(res.tau), prob.r_hat, atol=1e-9)
    # covariance of tau by linear propagation: tau = phi(r), d tau / d r = J_psi^-1 (square here)
    J = prob.psi_jacobian(res.tau).toarray()
    P_r = np.linalg.inv(prob.Lambda.toarray())
    Jinv = np.linalg.inv(J)
    P_tau = Jinv @ P_r @ Jinv.T
    for e in range(1, len(prob.entity_kinds)):
        cols = prob.variable_columns(e)
        np.testing.assert_allclose(
            res.covariance(e), P_tau[np.ix_(cols, cols)], rtol=1e-7, atol=1e-12
        )
    assert np.all(res.covariance(0) == 0.0)


def test_gauss_newton_covariance_is_spd_and_matches_dense_inverse():
    prob, _ = _problem(15)
    res = prob.optimise("reduced")
    J = prob.psi_jacobian(res.tau).toarray()
    P = np.linalg.inv(J.T @ prob.Lambda.toarray() @ J)
    ents = list(range(1, len(prob.entity_kinds)))
    for e, C in zip(ents, res.marginals(ents), strict=True):
        cols = prob.variable_columns(e)
        np.testing.assert_allclose(C, P[np.ix_(cols, cols)], rtol=1e-7, atol=1e-14)
        assert np.allclose(C, C.T)
        assert np.all(np.linalg.eigvalsh(C) > 0)


def test_angle_branches_far_from_zero():
    """Headings near +-pi: wrapped relative angles keep the cost smooth and the optimum exact."""
    rng = np.random.default_rng(16)
    poses = np.array([[0.0, 0.0, 3.1], [1.0, 0.1, -3.1], [2.0, 0.3, 3.05], [3.0, 0.2, -3.0]])
    pts = np.array([[1.5, 2.0], [2.5, -1.0]])
    qs = [RelativeQuantity(POSE, k - 1, k) for k in range(1, 4)]
    qs += [
        RelativeQuantity(POINT, 0, 4),
        RelativeQuantity(POINT, 3, 4),
        RelativeQuantity(POINT, 2, 5),
    ]
    qs += [RelativeQuantity(POSE, 0, 3)]
    r = _psi_truth(qs, poses, pts, 4)
    L = sp.diags(rng.uniform(10.0, 100.0, len(r)))
    prob = RelativeProblem([POSE] * 4 + [POINT] * 2, qs, L @ r, L, gauge_pose=poses[0])
    for method in ("reduced", "gauss-newton"):
        res = prob.optimise(method)
        np.testing.assert_allclose(res.means[:4, :2], poses[:, :2], atol=1e-8)
        np.testing.assert_allclose(wrap_angle(res.means[:4, 2] - poses[:, 2]), 0.0, atol=1e-8)
        np.testing.assert_allclose(res.means[4:, :2], pts, atol=1e-8)
        assert np.all(np.isnan(res.means[4:, 2]))


def test_initial_guess_composes_chain():
    prob, tau_true = _problem(17, noise=False)
    _assert_tau_close(prob, prob.initial_guess(), tau_true, 1e-9)
    P, Th = prob.unpack(tau_true)
    np.testing.assert_allclose(compose(P[0].tolist() + [Th[0]], [0, 0, 0]), prob.gauge_pose)


# ------------------------------------------------------------------------ validation
def _tiny():
    kinds = [POSE, POSE, POINT]
    qs = [RelativeQuantity(POSE, 0, 1), RelativeQuantity(POINT, 1, 2)]
    return kinds, qs, np.zeros(5), sp.eye(5)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda k, q, e, L: ([POSE, "line", POINT], q, e, L), "entity_kinds"),
        (lambda k, q, e, L: (k, [RelativeQuantity("circle", 0, 1)], e, L), "quantities.kind"),
        (lambda k, q, e, L: (k, [RelativeQuantity(POINT, 2, 1)], e, L), "quantities.frame"),
        (lambda k, q, e, L: (k, [RelativeQuantity(POSE, 0, 2)], e, L), "quantities.target"),
        (lambda k, q, e, L: (k, q, np.zeros(4), L), "eta"),
        (lambda k, q, e, L: (k, q, e, sp.eye(4)), "Lambda"),
        (lambda k, q, e, L: (k, q[:1], e[:3], sp.eye(3)), "quantities"),
    ],
)
def test_bad_problem_raises_value_error_naming_field(change, field):
    kinds, qs, eta, L = change(*_tiny())
    with pytest.raises(ValueError, match=field):
        RelativeProblem(kinds, qs, eta, L)


def test_bad_gauge_and_options_raise_value_error():
    kinds, qs, eta, L = _tiny()
    with pytest.raises(ValueError, match="gauge"):
        RelativeProblem(kinds, qs, eta, L, gauge=2)
    with pytest.raises(ValueError, match="gauge_pose"):
        RelativeProblem(kinds, qs, eta, L, gauge_pose=[0.0, np.nan, 0.0])
    prob = RelativeProblem(kinds, qs, eta, L)
    with pytest.raises(ValueError, match="method"):
        prob.optimise("newton-raphson")
    with pytest.raises(ValueError, match="max_iterations"):
        prob.optimise("reduced", max_iterations=0)
    with pytest.raises(ValueError, match="quasi_newton"):
        prob.optimise("reduced", quasi_newton="newton-cg")
    with pytest.raises(ValueError, match="gtol"):
        prob.optimise("reduced", gtol=-1.0)
    with pytest.raises(ValueError, match="tau0"):
        prob.optimise("reduced", tau0=np.zeros(2))
    with pytest.raises(ValueError, match=r"constraints\.information"):
        RelativeProblem.from_constraints(
            kinds, [GaussianConstraint(tuple(qs), np.zeros(5), np.eye(4))]
        )


def test_no_descent_step_tells_a_minimum_to_working_precision_from_a_slope():
    from filters.optimiser import _no_descent_step

    def fun(x):
        return float(x @ x), 2.0 * x

    at_minimum = np.array([1e-9, -1e-9])
    assert _no_descent_step(fun, at_minimum, *fun(at_minimum))
    away = np.array([0.3, -0.2])
    assert not _no_descent_step(fun, away, *fun(away))


# --------------------------------------------------------------------------- robust kernels
def _outlier_problem(offset=(8.0, -6.0)):
    """A small noise-free map (odometry chain, every point seen from two poses) plus one point
    constraint ``offset`` metres off, as confident as the rest: a wrong association."""
    rng = np.random.default_rng(0)
    n_poses, n_points = 6, 6
    poses, pts = _truth(rng, n_poses, n_points)
    kinds = [POSE] * n_poses + [POINT] * n_points
    cons = [
        GaussianConstraint((RelativeQuantity(POSE, k - 1, k),), relative(poses[k - 1], poses[k]),
                           np.diag([100.0, 100.0, 1000.0]))
        for k in range(1, n_poses)
    ]

    def seen_from(f, p):
        c, s = np.cos(f[2]), np.sin(f[2])
        d = p - f[:2]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])

    for j in range(n_points):
        for k in (j % n_poses, (j + 2) % n_poses):
            cons.append(GaussianConstraint((RelativeQuantity(POINT, k, n_poses + j),),
                                           seen_from(poses[k], pts[j]), 100.0 * np.eye(2)))
    bad = seen_from(poses[3], pts[0]) + np.asarray(offset)
    cons.append(GaussianConstraint((RelativeQuantity(POINT, 3, n_poses),), bad, 100.0 * np.eye(2)))
    prob = RelativeProblem.from_constraints(kinds, cons, gauge=0, gauge_pose=poses[0])
    return prob, np.vstack([poses[:, :2], pts])


@pytest.mark.parametrize(("robust", "tolerance_m"), [("cauchy", 0.01), ("huber", 0.25)])
def test_robust_kernel_recovers_the_truth_that_one_outlier_ruins(robust, tolerance_m):
    prob, truth = _outlier_problem()
    plain = prob.optimise("gauss-newton")
    assert plain.converged
    assert np.max(np.linalg.norm(plain.means[:, :2] - truth, axis=1)) > 1.0
    res = prob.optimise("gauss-newton", robust=robust)
    assert res.converged and res.robust == robust
    errors = np.linalg.norm(res.means[:, :2] - truth, axis=1)
    assert np.max(errors) < tolerance_m
    # the outlier (the last quantity) is the one down-weighted, the rest keep weight ~1
    assert res.weights[-1] < 0.05 and np.min(res.weights[:-1]) > 0.5
    # Huber keeps a bounded pull (not re-descending), Cauchy almost none
    if robust == "huber":
        assert np.max(errors) > 0.01


@pytest.mark.parametrize("robust", [None, "huber", "cauchy"])
def test_robust_cost_and_gradient_match_finite_differences(robust):
    prob, tau_true = _problem(1)
    tau = tau_true + np.random.default_rng(3).normal(0.0, 0.05, tau_true.shape)
    # the factor terms split CM (12) exactly
    assert prob.factor_residuals(tau).sum() == pytest.approx(prob.weighted_residual_cost(tau),
                                                              rel=1e-10)
    g = prob.robust_gradient(tau, robust)
    fd = _fd_grad(lambda t: prob.robust_cost(t, robust), tau)
    np.testing.assert_allclose(g, fd, atol=1e-6 * np.max(np.abs(fd)))
    if robust is None:  # CM (12) and CM (13) differ by a constant: the same gradient
        np.testing.assert_allclose(g, prob.gradient(tau), rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("robust", ["huber", "cauchy"])
def test_kernels_are_least_squares_inside_and_bounded_in_slope(robust):
    from filters.optimiser import robust_rho

    d2 = 5.99
    s = np.array([0.0, 1.0, 3.0, 20.0, 400.0])
    rho, slope = robust_rho(robust, s, d2)
    h = 1e-6
    fd = (robust_rho(robust, s + h, d2)[0] - robust_rho(robust, np.maximum(s - h, 0), d2)[0]) / (
        s + h - np.maximum(s - h, 0))
    np.testing.assert_allclose(slope, fd, rtol=1e-5)
    assert np.all(rho <= s + 1e-12) and np.all(np.diff(slope) <= 0)  # never above LS, concave
    if robust == "huber":
        np.testing.assert_array_equal(rho[:3], s[:3])  # quadratic below the threshold
    else:
        np.testing.assert_allclose(rho[:2], s[:2], rtol=0.1)


def test_robust_options_are_validated():
    prob, _ = _problem(0)
    with pytest.raises(ValueError, match="robust"):
        prob.optimise("gauss-newton", robust="tukey")
    with pytest.raises(ValueError, match="robust"):
        prob.optimise("reduced", robust="huber")
    direct = RelativeProblem(prob.entity_kinds, prob.quantities, prob.eta, prob.Lambda,
                             gauge=0, gauge_pose=prob.gauge_pose)
    with pytest.raises(ValueError, match="robust"):
        direct.optimise("gauss-newton", robust="cauchy")
    # without a kernel the weighted information is Lambda itself
    res = prob.optimise("gauss-newton")
    assert res.information is prob.Lambda
    np.testing.assert_allclose(
        prob.weighted_information(np.ones(len(prob.quantities))).toarray(),
        prob.Lambda.toarray(), atol=1e-9 * abs(prob.Lambda).max())
