"""Tests of filters/esdf.py: the ESDF against a dense EKF, sparsity, SPD, recovery, validation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from filters.esdf import ESDF
from filters.geometry import compose, compose_jacobians, wrap_angle
from filters.information import SparseInformation
from filters.models import (
    ProportionalVelocityNoise,
    RangeBearingSensor,
    innovation,
    inverse_observe,
    inverse_observe_jacobians,
    motion,
    motion_jacobians,
    observe,
    observe_jacobians,
)
from filters.types import FeatureIds

DT = 0.1
NOISE = ProportionalVelocityNoise(
    v_fraction=0.0, omega_fraction=0.0, v_floor_mps=0.05, omega_floor_radps=0.02
)
SENSOR = RangeBearingSensor(range_std_m=0.05, bearing_std_rad=np.deg2rad(1.0), max_range_m=10.0)
X0 = np.array([8.0, 0.0, np.pi / 2])


def simulate(seed, n_steps=300, scan_every=50, n_landmarks=30, radius=8.0, v=1.0):
    """A robot on a circle of ``radius`` (centred at the origin) among uniform landmarks.

    Odometry noise is drawn from NOISE (constant covariance, so the filter's model is exact),
    observations of every landmark in range every ``scan_every`` steps. Returns the landmarks
    and a list of (u_measured, z, ids, true pose) per step (z empty between scans).
    """
    rng = np.random.default_rng(seed)
    lms = rng.uniform(-15.0, 15.0, (n_landmarks, 2))
    pose = X0.copy()
    u_true = np.array([v, v / radius])
    steps = []
    for k in range(n_steps):
        u = u_true + rng.multivariate_normal(np.zeros(2), NOISE.covariance(u_true, DT))
        pose = motion(pose, u_true, DT)
        z, ids = np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
        if (k + 1) % scan_every == 0:
            zz = observe(pose, lms)
            ids = np.flatnonzero(zz[:, 0] <= SENSOR.max_range_m)
            ids = rng.permutation(ids)
            z = zz[ids] + rng.normal(
                0.0, [SENSOR.range_std_m, SENSOR.bearing_std_rad], (len(ids), 2)
            )
        steps.append((u, z, ids.astype(np.int64), pose.copy()))
    return lms, steps


class DenseDelayedEKF:
    """Reference: a dense EKF over the same delayed state [x_0, x_1, ..., landmarks]."""

    def __init__(self, x0, P0, R):
        self.x = x0.copy()
        self.P = P0.copy()
        self.R = R
        self.poses = [0]
        self.lm = {}
        self.delta = np.zeros(3)
        self.Q = np.zeros((3, 3))
        self.steps = 0

    def predict(self, u, dt):
        Jp, Ju = motion_jacobians(self.delta, u, dt)
        self.delta = motion(self.delta, u, dt)
        self.Q = Jp @ self.Q @ Jp.T + Ju @ NOISE.covariance(u, dt) @ Ju.T
        self.steps += 1

    def _augment(self, mean, A, Q_add):
        """Append mean with covariance A P A^T + Q_add and cross covariance A P."""
        n = len(self.x)
        cross = A @ self.P
        new = cross @ A.T + Q_add
        self.x = np.concatenate([self.x, mean])
        self.P = np.block([[self.P, cross.T], [cross, new]])
        return n

    def _pose_slot(self):
        if self.steps == 0:
            return self.poses[-1]
        i = self.poses[-1]
        xp = self.x[i : i + 3]
        Ja, Jb = compose_jacobians(xp, self.delta)
        mean = compose(xp, self.delta)
        mean[2] = xp[2] + wrap_angle(self.delta[2])
        A = np.zeros((3, len(self.x)))
        A[:, i : i + 3] = Ja
        k = self._augment(mean, A, Jb @ self.Q @ Jb.T)
        self.poses.append(k)
        self.delta, self.Q, self.steps = np.zeros(3), np.zeros((3, 3)), 0
        return k

    def update(self, z, ids):
        if len(z) == 0:
            return
        k = self._pose_slot()
        xk = self.x[k : k + 3].copy()
        known = []
        for zi, j in zip(z, ids, strict=True):
            if j in self.lm:
                known.append((zi, j))
                continue
            G_pose, G_z = inverse_observe_jacobians(xk, zi)
            A = np.zeros((2, len(self.x)))
            A[:, k : k + 3] = G_pose
            self.lm[j] = self._augment(inverse_observe(xk, zi), A, G_z @ self.R @ G_z.T)
        if not known:
            return
        n = len(self.x)
        H = np.zeros((2 * len(known), n))
        nu = np.zeros(2 * len(known))
        for r, (zi, j) in enumerate(known):
            o = self.lm[j]
            Hp, Hm = observe_jacobians(self.x[k : k + 3], self.x[o : o + 2])
            H[2 * r : 2 * r + 2, k : k + 3] = Hp
            H[2 * r : 2 * r + 2, o : o + 2] = Hm
            nu[2 * r : 2 * r + 2] = innovation(zi, observe(self.x[k : k + 3], self.x[o : o + 2]))
        Rb = np.kron(np.eye(len(known)), self.R)
        S = H @ self.P @ H.T + Rb
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ nu
        IKH = np.eye(n) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ Rb @ K.T

    def pose(self):
        i = self.poses[-1]
        xp, Pp = self.x[i : i + 3], self.P[i : i + 3, i : i + 3]
        Ja, Jb = compose_jacobians(xp, self.delta)
        return compose(xp, self.delta), Ja @ Pp @ Ja.T + Jb @ self.Q @ Jb.T


def _make_esdf(**kw):
    opts = {"initial_pose": X0, "recovery": "full", "min_odometry_var": 1e-16} | kw
    return ESDF(SENSOR, None, NOISE, **opts)


@pytest.mark.parametrize("seed", [0, 1])
def test_esdf_equals_dense_ekf_on_the_same_problem(seed):
    """Same linearisation points (full recovery) -> identical Gaussian, epoch by epoch."""
    _, steps = simulate(seed, n_steps=600)
    f = _make_esdf()
    std0 = np.array([1e-3, 1e-3, 1e-4])
    ekf = DenseDelayedEKF(X0, np.diag(std0**2), SENSOR.R)
    for u, z, ids, _ in steps:
        f.predict(u, DT)
        ekf.predict(u, DT)
        f.update(z, ids)
        ekf.update(z, ids)
        m, P = f.pose()
        m_ref, P_ref = ekf.pose()
        np.testing.assert_allclose(m, m_ref, atol=1e-9)
        np.testing.assert_allclose(P, P_ref, rtol=1e-6, atol=1e-12)
    # the whole state: delayed poses and landmarks, means and marginals
    traj = f.trajectory()
    ref = np.array([ekf.x[i : i + 3] for i in ekf.poses])
    np.testing.assert_allclose(traj[:, :2], ref[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(traj[:, 2] - ref[:, 2]), 0.0, atol=1e-10)
    est = f.landmarks()
    for j, mean, cov in zip(f.landmark_ids(), est.means, est.covs, strict=True):
        o = ekf.lm[int(j)]
        np.testing.assert_allclose(mean, ekf.x[o : o + 2], atol=1e-9)
        np.testing.assert_allclose(cov, ekf.P[o : o + 2, o : o + 2], rtol=1e-6, atol=1e-12)
    # and the full covariance is the inverse of Lambda
    P_full = np.linalg.inv(f.information()[1].toarray())
    assert len(ekf.x) == f.state_size
    scale = np.max(np.abs(ekf.P))
    np.testing.assert_allclose(P_full[:6, :6], ekf.P[:6, :6], atol=1e-7 * scale)


def test_information_symmetric_and_covariances_spd_after_every_update():
    _, steps = simulate(2, n_steps=700, scan_every=25)
    f = ESDF(SENSOR, None, NOISE, initial_pose=X0)
    n_updates = 0
    for u, z, ids, _ in steps:
        f.predict(u, DT)
        f.update(z, ids)
        if len(z) == 0:
            continue
        n_updates += 1
        eta, L = f.information()
        assert abs(L - L.T).max() == 0.0
        assert eta.shape == (f.state_size,)
        _, P = f.pose()
        assert np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
        est = f.landmarks()
        assert np.all(np.linalg.eigvalsh(est.covs) > 0)
    assert n_updates == 28
    w = np.linalg.eigvalsh(np.linalg.inv(f.information()[1].toarray()))
    assert np.all(w > 0)


def test_information_is_exactly_sparse():
    """Off-diagonal blocks: consecutive delayed poses and (pose, landmark it observed) only."""
    _, steps = simulate(3, n_steps=600)
    f = ESDF(SENSOR, None, NOISE, initial_pose=X0)
    expected = set()
    for u, z, ids, _ in steps:
        f.predict(u, DT)
        before = f.n_delayed_poses
        f.update(z, ids)
        if len(z) == 0:
            continue
        k = f._poses[-1]
        if f.n_delayed_poses > before:
            expected.add((f._poses[-2], k))
        for j in ids:
            e = f._lm_entity[int(j)]
            expected.add((min(k, e), max(k, e)))
    got = {key for key in f.info._blocks if key[0] != key[1]}
    assert got == expected


def test_window_recovery_stays_close_to_full_recovery():
    """Partial (window) recovery vs exact recovery on a loop: same estimate to a few mm."""
    _, steps = simulate(4, n_steps=900, scan_every=50)
    fw = ESDF(
        SENSOR,
        None,
        NOISE,
        initial_pose=X0,
        recovery="window",
        recovery_window=2,
        loop_gap_epochs=4,
    )
    ff = ESDF(SENSOR, None, NOISE, initial_pose=X0, recovery="full")
    for u, z, ids, _ in steps:
        for f in (fw, ff):
            f.predict(u, DT)
            f.update(z, ids)
    assert fw.n_full_recoveries >= 1  # the loop closure triggered a full solve
    assert fw.n_full_recoveries < ff.n_full_recoveries
    np.testing.assert_allclose(fw.trajectory()[:, :2], ff.trajectory()[:, :2], atol=5e-3)
    np.testing.assert_allclose(fw.landmarks().means, ff.landmarks().means, atol=5e-3)
    # window means (the filter's linearisation points) are close to the exact solve as well
    mu_exact = fw.info.mean()
    for e in fw._poses[-2:]:
        np.testing.assert_allclose(fw._mu[e], fw.info.mean_of(e, mu_exact), atol=1e-6)


def test_window_solve_is_block_gauss_seidel():
    """SparseInformation.solve_window with every entity active equals the full solve."""
    rng = np.random.default_rng(5)
    info = SparseInformation()
    ents = [info.add_entity(s) for s in (3, 2, 3, 2, 2)]
    for _ in range(12):
        a, b = rng.choice(len(ents), 2, replace=False)
        Ha = rng.normal(size=(2, info.size(a)))
        Hb = rng.normal(size=(2, info.size(b)))
        info.add_information([a, b], [Ha, Hb], np.eye(2), rng.normal(size=2))
    for e in ents:
        info.add_information(
            [e], [np.eye(info.size(e))], 0.1 * np.eye(info.size(e)), np.zeros(info.size(e))
        )
    means = [np.zeros(info.size(e)) for e in ents]
    sol = info.solve_window(ents, means)
    np.testing.assert_allclose(np.concatenate([sol[e] for e in ents]), info.mean(), atol=1e-10)
    # a partial window holds the rest fixed: with the rest at the exact mean it is exact too
    exact = [info.mean_of(e).copy() for e in ents]
    sol = info.solve_window([1, 3], exact)
    np.testing.assert_allclose(sol[1], exact[1], atol=1e-10)
    np.testing.assert_allclose(sol[3], exact[3], atol=1e-10)


def test_pose_nees_within_chi_square_bounds():
    n_runs = 30
    nees = []
    for seed in range(n_runs):
        _, steps = simulate(100 + seed, n_steps=200, scan_every=50)
        f = ESDF(SENSOR, None, NOISE, initial_pose=X0)
        for u, z, ids, _ in steps:
            f.predict(u, DT)
            f.update(z, ids)
        m, P = f.pose()
        e = m - steps[-1][3]
        e[2] = wrap_angle(e[2])
        nees.append(e @ np.linalg.solve(P, e))
    lo, hi = chi2.ppf([0.005, 0.995], 3 * n_runs) / n_runs
    assert lo < np.mean(nees) < hi


def test_compass_reduces_heading_uncertainty():
    _, steps = simulate(6, n_steps=120)
    f = ESDF(SENSOR, None, NOISE, initial_pose=X0)
    for u, z, ids, _ in steps:
        f.predict(u, DT)
        f.update(z, ids)
    var_before = f.pose()[1][2, 2]
    f.update_heading(steps[-1][3][2], 0.001)
    m, P = f.pose()
    assert P[2, 2] < var_before
    assert P[2, 2] <= 0.001**2 * (1 + 1e-6)
    assert abs(wrap_angle(m[2] - steps[-1][3][2])) < 0.01


def test_seeded_determinism_and_associations():
    _, steps = simulate(7, n_steps=300)
    ids_counter = FeatureIds(start=100)
    runs = []
    for counter in (ids_counter, FeatureIds(start=100)):
        f = ESDF(SENSOR, None, NOISE, counter, initial_pose=X0)
        assocs = []
        for u, z, ids, _ in steps:
            f.predict(u, DT)
            zz = np.vstack([z, [[3.0, 0.1]]]) if len(z) else z
            ii = np.concatenate([ids, [-1]]) if len(z) else ids
            f.update(zz, ii)
            if len(z):
                assocs.append(f.last_associations.copy())
        runs.append((f.pose(), f.landmarks(), assocs))
    (p1, l1, a1), (p2, l2, a2) = runs
    np.testing.assert_array_equal(p1[0], p2[0])
    np.testing.assert_array_equal(p1[1], p2[1])
    np.testing.assert_array_equal(l1.means, l2.means)
    for x, y in zip(a1, a2, strict=True):
        np.testing.assert_array_equal(x, y)
        assert x[-1] == -1 and np.all(x[:-1] >= 100)
    assert len(set(l1.ids.tolist())) == len(l1.ids)


def test_empty_update_is_a_no_op():
    f = ESDF(SENSOR, None, NOISE, initial_pose=X0)
    f.predict(np.array([1.0, 0.0]), DT)
    f.update(np.zeros((0, 2)), np.zeros(0, dtype=int))
    assert f.n_delayed_poses == 1 and f.last_associations.shape == (0,)
    m, _ = f.pose()
    np.testing.assert_allclose(m, motion(X0, [1.0, 0.0], DT))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"recovery": "sometimes"}, "recovery"),
        ({"recovery_window": 0}, "recovery_window"),
        ({"loop_gap_epochs": 0}, "loop_gap_epochs"),
        ({"min_odometry_var": -1.0}, "min_odometry_var"),
        ({"initial_pose_std": (0.1, -0.1, 0.1)}, "initial_pose_std"),
        ({"initial_pose": (0.0, 1.0)}, "initial_pose"),
    ],
)
def test_bad_options_raise_value_error_naming_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        ESDF(SENSOR, None, NOISE, **kwargs)


def test_bad_calls_raise_value_error_naming_field():
    with pytest.raises(ValueError, match="odometry_noise"):
        ESDF(SENSOR, None, None)
    f = ESDF(SENSOR, None, NOISE)
    with pytest.raises(ValueError, match="ids"):
        f.update(np.array([[1.0, 0.0]]))
    with pytest.raises(ValueError, match="ids"):
        f.update(np.array([[1.0, 0.0]]), np.array([1, 2]))
    with pytest.raises(ValueError, match="dt"):
        f.predict(np.array([1.0, 0.0]), -0.1)
    with pytest.raises(ValueError, match="u"):
        f.predict(np.array([1.0, np.nan]), 0.1)
    with pytest.raises(ValueError, match="std_rad"):
        f.update_heading(0.0, 0.0)


def test_covariance_blocks_match_dense_inverse_in_any_chunking():
    _, steps = simulate(8, n_steps=300)
    f = ESDF(SENSOR, None, NOISE, initial_pose=X0)
    for u, z, ids, _ in steps:
        f.predict(u, DT)
        f.update(z, ids)
    P = np.linalg.inv(f.information()[1].toarray())
    rng = np.random.default_rng(0)
    ents = list(range(f.info.n_entities))
    functionals = [
        [(e, rng.normal(size=(2, f.info.size(e)))) for e in rng.choice(ents, 3, replace=False)]
        for _ in range(7)
    ]
    whole = f.info.covariance_blocks(functionals)
    chunked = f.info.covariance_blocks(functionals, chunk_columns=3)
    for fn, C, D in zip(functionals, whole, chunked, strict=True):
        J = np.zeros((2, f.state_size))
        for e, Jb in fn:
            o = f.info.offset(e)
            J[:, o : o + f.info.size(e)] += Jb
        np.testing.assert_allclose(C, J @ P @ J.T, rtol=1e-8, atol=1e-14)
        np.testing.assert_allclose(D, C, rtol=1e-12, atol=1e-16)
