"""Gating, nearest neighbour and JCBB (filters/association.py)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.stats import chi2

from filters.association import (
    Candidates,
    ChiSquareTable,
    build_candidates,
    individual_compatibility,
    innovation_covariances,
    jcbb,
    joint_covariance,
    joint_distance,
    mahalanobis_squared,
    nearest_neighbour,
    point_difference_candidates,
    predict_range_bearing,
    range_bearing_candidates,
)
from filters.models import RangeBearingSensor, observe

GATE = 0.99


def _chosen(cands: Candidates, pairing):
    """Candidate indices of a pairing (obs -> feature)."""
    out = []
    for o, f in enumerate(pairing):
        if f >= 0:
            out.append(int(np.flatnonzero((cands.obs == o) & (cands.feat == f))[0]))
    return out


def _brute_force(cands: Candidates, table: ChiSquareTable):
    """Most pairings, then lowest joint distance, over every jointly compatible hypothesis."""
    per_obs = [np.flatnonzero(cands.obs == o) for o in range(cands.n_obs)]
    best = (0, 0.0, ())
    for choice in itertools.product(*[[-1, *list(c)] for c in per_obs]):
        chosen = [c for c in choice if c >= 0]
        feats = [int(cands.feat[c]) for c in chosen]
        if len(set(feats)) < len(feats) or not chosen:
            continue
        d2 = joint_distance(cands, chosen)
        if d2 > table(len(chosen)):
            continue
        if len(chosen) > best[0] or (len(chosen) == best[0] and d2 < best[1]):
            best = (len(chosen), d2, tuple(chosen))
    return best


def _shifted_points_case(shift):
    """Global points on a line, local copies sharing a large common offset uncertainty.

    State: [global points (N x 2), local points (K x 2)]. Local points all carry a common
    translation uncertainty (std 1 m), like features seen from an uncertain pose.
    """
    glob = np.array([[10.0, 0.0], [10.0, 1.5]])
    loc = glob + np.array([0.0, shift])
    N, K = len(glob), len(loc)
    x = np.concatenate([glob.ravel(), loc.ravel()])
    n = len(x)
    P = np.eye(n) * 0.01**2
    common = np.kron(np.ones((K, K)), np.eye(2)) * 1.0**2
    P[2 * N :, 2 * N :] += common
    cols_b = np.arange(2 * N).reshape(N, 2)
    cols_a = 2 * N + np.arange(2 * K).reshape(K, 2)
    return x, P, cols_a, cols_b


# --------------------------------------------------------------------------- gating
def test_bearing_innovation_is_wrapped_across_pi():
    """A feature just behind the robot: predicted at -pi + eps, observed at +pi - eps."""
    x = np.array([0.0, 0.0, 0.0, -10.0, -0.05])
    P = np.diag([0.01, 0.01, 0.001, 0.01, 0.01])
    sensor = RangeBearingSensor()
    pred = predict_range_bearing(x, P, np.arange(3), np.array([[3, 4]]), sensor.R)
    assert pred.zhat[0, 1] < -np.pi + 0.01  # the prediction is just above -pi
    z = np.array([[10.0, np.pi - 0.003]])
    cands, d2, mask = range_bearing_candidates(z, x, P, pred, sensor.R, GATE)
    assert mask[0, 0] and len(cands) == 1
    assert d2[0, 0] < 1.0
    assert abs(cands.nu[0, 1]) < 0.01  # a small innovation, not ~2 pi


def test_individual_gate_matches_per_pair_mahalanobis():
    rng = np.random.default_rng(0)
    K, N = 5, 7
    nu = rng.normal(size=(K, N, 2)) * 2.0
    A = rng.normal(size=(N, 2, 2))
    S = A @ np.swapaxes(A, 1, 2) + 0.5 * np.eye(2)
    d2, mask = individual_compatibility(nu, S[None], GATE)
    for i in range(K):
        for j in range(N):
            ref = nu[i, j] @ np.linalg.inv(S[j]) @ nu[i, j]
            assert d2[i, j] == pytest.approx(ref, rel=1e-10)
            assert mask[i, j] == (ref <= chi2.ppf(GATE, 2))


def test_joint_covariance_equals_dense_jacobian_product():
    rng = np.random.default_rng(1)
    n = 11
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    R = np.diag([0.3, 0.02])
    cols = np.array([[0, 1, 2, 3, 4], [0, 1, 2, 5, 6], [0, 1, 2, 7, 8], [0, 1, 2, 5, 6]])
    J = rng.normal(size=(4, 2, 5))
    groups = np.array([0, 0, 1, 2])
    M = joint_covariance(P, cols, J, R, groups)
    H = np.zeros((8, n))
    for c in range(4):
        H[2 * c : 2 * c + 2, cols[c]] = J[c]
    noise = np.kron((groups[:, None] == groups[None, :]).astype(float), R)
    np.testing.assert_allclose(M, H @ P @ H.T + noise, rtol=1e-12, atol=1e-12)
    S = innovation_covariances(P, cols, J, R)
    for c in range(4):
        np.testing.assert_allclose(S[c], M[2 * c : 2 * c + 2, 2 * c : 2 * c + 2], atol=1e-12)


def test_mahalanobis_squared_broadcasts():
    S = np.array([[2.0, 0.5], [0.5, 1.0]])
    nu = np.array([[1.0, 2.0], [0.0, -1.0]])
    out = mahalanobis_squared(nu, S)
    np.testing.assert_allclose(out, [v @ np.linalg.solve(S, v) for v in nu])


# --------------------------------------------------------------------------- NN / JCBB
def test_jcbb_rejects_a_pairing_nearest_neighbour_accepts():
    """Two points 1.5 m apart seen with a common offset of -0.9 m (std 1 m): NN pairs the second
    observation with the first point (0.6 m away rather than 0.9 m) and then the first observation
    with the second point, an individually compatible but jointly incompatible hypothesis. JCBB
    finds the consistent shift."""
    x, P, cols_a, cols_b = _shifted_points_case(-0.9)
    cands, d2, mask = point_difference_candidates(x, P, cols_a, cols_b, GATE)
    assert mask.all()  # every pairing is individually compatible: an ambiguous case
    nn = nearest_neighbour(d2, mask)
    np.testing.assert_array_equal(nn, [1, 0])
    table = ChiSquareTable(GATE, 2)
    assert joint_distance(cands, _chosen(cands, nn)) > table(2)  # NN is jointly incompatible
    hyp = jcbb(cands, table)
    np.testing.assert_array_equal(hyp.pairing, [0, 1])
    assert hyp.n_pairs == 2 and not hyp.exhausted
    assert hyp.d2 == pytest.approx(joint_distance(cands, _chosen(cands, hyp.pairing)))
    assert hyp.d2 <= table(2)


def test_jcbb_range_bearing_with_uncertain_pose():
    """Range-bearing version: the robot is really 1.2 m to the left of its estimate (y std 1 m);
    three features 2 m apart. NN takes the shifted neighbour, JCBB the consistent triple."""
    feats = np.array([[10.0, 0.0], [10.0, 2.0], [10.0, 4.0]])
    x = np.concatenate([[0.0, 0.0, 0.0], feats.ravel()])
    P = np.diag([0.01**2, 1.0**2, 1e-6] + [1e-4] * 6)
    true_pose = np.array([0.0, 1.2, 0.0])
    z = observe(true_pose, feats)  # noise-free, in order of the features
    sensor = RangeBearingSensor()
    pred = predict_range_bearing(x, P, np.arange(3), 3 + np.arange(6).reshape(3, 2), sensor.R)
    cands, d2, mask = range_bearing_candidates(z, x, P, pred, sensor.R, GATE)
    nn = nearest_neighbour(d2, mask)
    assert not np.array_equal(nn, [0, 1, 2])
    hyp = jcbb(cands, ChiSquareTable(GATE, 2))
    np.testing.assert_array_equal(hyp.pairing, [0, 1, 2])
    assert hyp.n_pairs == 3


def test_jcbb_matches_brute_force_on_random_problems():
    """Most pairings, ties by lowest joint distance: JCBB equals exhaustive enumeration."""
    rng = np.random.default_rng(7)
    table = ChiSquareTable(GATE, 2)
    n_nontrivial = 0
    for _ in range(25):
        N, K = rng.integers(2, 5), rng.integers(2, 5)
        n = 3 + 2 * N
        A = rng.normal(size=(n, n)) * 0.3
        P = A @ A.T + np.eye(n) * 0.05
        x = np.concatenate([[0.0, 0.0, 0.0], rng.uniform(-6, 6, size=2 * N)])
        feats = x[3:].reshape(N, 2)
        # observations near random features (some clutter), random order
        idx = rng.integers(0, N, size=K)
        pts = feats[idx] + rng.normal(size=(K, 2)) * 0.5
        z = observe(np.zeros(3), pts)
        R = np.diag([0.05**2, 0.02**2])
        pred = predict_range_bearing(x, P, np.arange(3), 3 + np.arange(2 * N).reshape(N, 2), R)
        cands, _, _ = range_bearing_candidates(z, x, P, pred, R, GATE)
        hyp = jcbb(cands, table)
        n_best, d2_best, _ = _brute_force(cands, table)
        assert hyp.n_pairs == n_best
        if n_best:
            assert hyp.d2 == pytest.approx(d2_best, rel=1e-9, abs=1e-9)
            n_nontrivial += 1
        used = hyp.pairing[hyp.pairing >= 0]
        assert len(np.unique(used)) == len(used)
    assert n_nontrivial >= 10


def test_incremental_joint_distance_equals_direct_computation():
    x, P, cols_a, cols_b = _shifted_points_case(-0.5)
    cands, _, _ = point_difference_candidates(x, P, cols_a, cols_b, GATE)
    hyp = jcbb(cands, ChiSquareTable(GATE, 2))
    assert hyp.n_pairs == 2
    assert hyp.d2 == pytest.approx(joint_distance(cands, _chosen(cands, hyp.pairing)), rel=1e-10)


def test_node_budget_stops_the_search_with_a_compatible_answer():
    rng = np.random.default_rng(3)
    # many observations in many gates: a large tree
    N = K = 8
    glob = np.column_stack([np.full(N, 10.0), np.arange(N) * 0.3])
    loc = glob + rng.normal(size=glob.shape) * 0.05
    x = np.concatenate([glob.ravel(), loc.ravel()])
    P = np.eye(len(x)) * 0.2**2
    cols_b = np.arange(2 * N).reshape(N, 2)
    cols_a = 2 * N + np.arange(2 * K).reshape(K, 2)
    cands, _, _ = point_difference_candidates(x, P, cols_a, cols_b, GATE)
    table = ChiSquareTable(GATE, 2)
    small = jcbb(cands, table, node_budget=5)
    assert small.exhausted and small.n_nodes == 5
    if small.n_pairs:
        assert joint_distance(cands, _chosen(cands, small.pairing)) <= table(small.n_pairs)
    full = jcbb(cands, table, node_budget=200_000)
    assert full.n_pairs >= small.n_pairs
    assert full.n_pairs == K


def test_empty_inputs():
    nu = np.zeros((0, 3, 2))
    d2 = np.zeros((0, 3))
    mask = np.zeros((0, 3), dtype=bool)
    cols, J = np.zeros((1, 3, 5), dtype=int), np.zeros((1, 3, 2, 5))
    cands = build_candidates(nu, d2, mask, np.eye(9), cols, J)
    hyp = jcbb(cands, ChiSquareTable(GATE, 2))
    assert hyp.n_pairs == 0 and len(hyp.pairing) == 0
    assert len(nearest_neighbour(d2, mask)) == 0


def test_chi_square_table_extends():
    table = ChiSquareTable(0.95, 2)
    assert table(40) == pytest.approx(chi2.ppf(0.95, 80))
    assert table(1) == pytest.approx(chi2.ppf(0.95, 2))


@pytest.mark.parametrize("bad", [0.0, 1.0, 1.5, -0.1, float("nan")])
def test_bad_gate_probability_names_the_field(bad):
    with pytest.raises(ValueError, match="gate_probability"):
        ChiSquareTable(bad, 2)
    with pytest.raises(ValueError, match="gate_probability"):
        individual_compatibility(np.zeros((1, 1, 2)), np.eye(2)[None, None], bad)


@pytest.mark.parametrize("bad", [0, -3, 2.5, True])
def test_bad_node_budget_names_the_field(bad):
    x, P, cols_a, cols_b = _shifted_points_case(-1.2)
    cands, _, _ = point_difference_candidates(x, P, cols_a, cols_b, GATE)
    with pytest.raises(ValueError, match="node_budget"):
        jcbb(cands, ChiSquareTable(GATE, 2), node_budget=bad)


def test_chi_square_quantile_is_scipy_stats_chi2_ppf_to_the_bit():
    """The gates and the NEES band take their chi-square quantiles without scipy.stats (a third
    of a second or more of every process's imports): the same numbers, to the bit."""
    from filters.association import chi_square_quantile

    rng = np.random.default_rng(0)
    probabilities = np.concatenate([[0.0, 0.001, 0.025, 0.5, 0.95, 0.975, 0.999, 0.99999, 1.0],
                                    rng.random(40)])
    for dof in [*range(1, 200), 0.5, 2.5, 1000]:
        np.testing.assert_array_equal(chi_square_quantile(probabilities, dof),
                                      chi2.ppf(probabilities, dof))
        assert chi_square_quantile(0.999, dof) == chi2.ppf(0.999, dof)
    dofs = 2 * np.arange(1, 40)
    np.testing.assert_array_equal(chi_square_quantile(0.999, dofs), chi2.ppf(0.999, dofs))
