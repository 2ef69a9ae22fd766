"""Tests of filters/relative_esdf.py: CM III.B relative ESDF, loop closures, optimiser hand-off."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from filters.geometry import wrap_angle
from filters.models import ProportionalVelocityNoise, RangeBearingSensor, motion, observe
from filters.optimiser import HEADING, POINT, POSE
from filters.relative_esdf import RelativeESDF, chain_compose

DT = 0.1
NOISE = ProportionalVelocityNoise(
    v_fraction=0.0, omega_fraction=0.0, v_floor_mps=0.05, omega_floor_radps=0.02
)
SENSOR = RangeBearingSensor(range_std_m=0.05, bearing_std_rad=np.deg2rad(1.0), max_range_m=8.0)
RADIUS = 10.0


def simulate(seed, kind="loop", *, n_steps=800, noisy=True, omega_scale_error=0.0, compass=False):
    """A robot on a circle (``"loop"``, landmarks near it) or a straight line (``"line"``).

    ``noisy``: odometry and sensor noise drawn from the filter's models (consistent data).
    ``omega_scale_error``: a systematic turn-rate error (a miscalibrated wheel base), which the
    filter's noise model does not describe; it has no effect on a straight line (omega = 0).
    Scans every 50 steps (5 s). Returns (start pose, landmarks, steps) with steps of
    (u_measured, z, ids, true pose, compass or None).
    """
    rng = np.random.default_rng(seed)
    if kind == "loop":
        ang = rng.uniform(0.0, 2.0 * np.pi, 40)
        rad = RADIUS + rng.uniform(-4.0, 4.0, 40)
        lms = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
        x0 = np.array([RADIUS, 0.0, np.pi / 2])
        u_true = np.array([1.0, 1.0 / RADIUS])
    else:
        lms = np.column_stack([rng.uniform(-5.0, 80.0, 60), rng.uniform(-6.0, 6.0, 60)])
        x0 = np.zeros(3)
        u_true = np.array([1.0, 0.0])
    pose = x0.copy()
    steps = []
    for k in range(n_steps):
        u = u_true * np.array([1.0, 1.0 + omega_scale_error])
        if noisy:
            u = u + rng.multivariate_normal(np.zeros(2), NOISE.covariance(u_true, DT))
        pose = motion(pose, u_true, DT)
        z, ids, heading = np.zeros((0, 2)), np.zeros(0, dtype=np.int64), None
        if (k + 1) % 50 == 0:
            zz = observe(pose, lms)
            ids = rng.permutation(np.flatnonzero(zz[:, 0] <= SENSOR.max_range_m))
            z = zz[ids]
            if noisy:
                z = z + rng.normal(0.0, [SENSOR.range_std_m, SENSOR.bearing_std_rad], z.shape)
            if compass:
                heading = float(pose[2])
        steps.append((u, z, ids.astype(np.int64), pose.copy(), heading))
    return x0, lms, steps


def run(filt, steps):
    for u, z, ids, _, heading in steps:
        filt.predict(u, DT)
        filt.update(z, ids)
        if heading is not None:
            filt.update_heading(heading, 1e-3)
    return filt


def map_error(est, ids, lms):
    return float(np.mean(np.linalg.norm(est.means - lms[ids], axis=1)))


# ------------------------------------------------------------------------ Jacobians
def test_chain_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    start = np.array([1.0, -2.0, 0.7])
    ds = rng.normal([4.0, 0.5, 0.3], [1.0, 1.0, 0.2], (5, 3))
    G, J_ds, J_start = chain_compose(start, ds)
    h = 1e-6
    for i in range(len(ds)):
        for c in range(3):
            dp, dm = ds.copy(), ds.copy()
            dp[i, c] += h
            dm[i, c] -= h
            fd = (chain_compose(start, dp)[0][-1] - chain_compose(start, dm)[0][-1]) / (2 * h)
            np.testing.assert_allclose(J_ds[i][:, c], fd, atol=1e-6)
    for c in range(3):
        e = np.zeros(3)
        e[c] = h
        fd = (chain_compose(start + e, ds)[0][-1] - chain_compose(start - e, ds)[0][-1]) / (2 * h)
        np.testing.assert_allclose(J_start[:, c], fd, atol=1e-6)


def test_cm11_observation_jacobian_matches_finite_differences():
    """h(d_{k+1} (+) ... (+) d_l, d^L) and its Jacobian as the filter builds it."""
    from filters.models import observe_jacobians

    rng = np.random.default_rng(1)
    ds = rng.normal([3.0, 0.2, 0.2], [0.5, 0.5, 0.1], (4, 3))
    m = np.array([12.0, 5.0])

    def h(ds_, m_):
        return observe(chain_compose(np.zeros(3), ds_)[0][-1], m_)

    G, J_ds, _ = chain_compose(np.zeros(3), ds)
    H_T, H_m = observe_jacobians(G[-1], m)
    H_ds = H_T @ J_ds
    eps = 1e-6
    for i in range(len(ds)):
        for c in range(3):
            dp, dm = ds.copy(), ds.copy()
            dp[i, c] += eps
            dm[i, c] -= eps
            fd = (h(dp, m) - h(dm, m)) / (2 * eps)
            np.testing.assert_allclose(H_ds[i][:, c], fd, atol=1e-6)
    for c in range(2):
        e = np.zeros(2)
        e[c] = eps
        np.testing.assert_allclose(H_m[:, c], (h(ds, m + e) - h(ds, m - e)) / (2 * eps), atol=1e-6)


# ------------------------------------------------------------------------ loop closures
def test_innovation_test_declares_loop_closure_on_a_loop_not_on_a_straight_run():
    """A turn-rate calibration error makes the loop's accumulated error inconsistent with the
    relative covariance: the innovation test fires when the start is re-observed, and only then;
    on a straight run the same error does nothing and no loop closure is declared."""
    x0, _, steps = simulate(0, "loop", noisy=False, omega_scale_error=0.1)
    loop = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=1000), steps)
    assert loop.n_loop_closures > 0
    assert all(lc.reason == "innovation" for lc in loop.loop_closures)
    assert all(lc.innovation_ratio > 1.0 for lc in loop.loop_closures)
    loop_epoch = int(2 * np.pi * RADIUS / 5.0)  # ~12.6 epochs of 5 s per lap
    first = min(lc.epoch for lc in loop.loop_closures)
    assert loop_epoch - 3 <= first <= loop_epoch + 1
    assert min(lc.chain_length for lc in loop.loop_closures) >= loop_epoch - 4
    assert loop.redundancies  # the landmarks now have coordinates in two frames

    x0, _, steps = simulate(0, "line", noisy=False, omega_scale_error=0.1)
    line = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=1000), steps)
    assert line.n_loop_closures == 0
    assert not line.redundancies


def test_last_update_flag_and_ratio():
    x0, _, steps = simulate(0, "loop", noisy=False, omega_scale_error=0.1)
    f = RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=1000)
    flags = []
    for u, z, ids, _, _ in steps:
        f.predict(u, DT)
        n_before = f.n_loop_closures
        f.update(z, ids)
        if len(z):
            flags.append(f.last_loop_closure)
            assert f.last_loop_closure == (f.n_loop_closures > n_before)
            assert (f.last_innovation_ratio > 1.0) == f.last_loop_closure
    assert any(flags) and not all(flags)


def test_chain_length_declares_loop_closure():
    x0, _, steps = simulate(1, "loop", noisy=True)
    f = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=5), steps)
    chain = [lc for lc in f.loop_closures if lc.reason == "chain"]
    assert chain and all(lc.chain_length > 5 for lc in chain)
    assert all(np.isnan(lc.innovation_ratio) for lc in chain)


def test_innovation_bound_false_alarm_rate_on_consistent_data():
    """||nu|| > k sigma_max(S_bar) with S_bar >= S implies nu^T S^-1 nu > k^2, so on consistent
    data the rate of declared closures is at most P(chi2_2 > k^2) = exp(-k^2 / 2)."""
    n_obs = n_closures = 0
    for seed in range(4):
        for kind in ("loop", "line"):
            x0, _, steps = simulate(10 + seed, kind, noisy=True, n_steps=600)
            f = RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=1000)
            seen = set()
            for u, z, ids, _, _ in steps:
                f.predict(u, DT)
                n_obs += sum(int(j) in seen for j in ids)
                seen.update(int(j) for j in ids)
                f.update(z, ids)
            n_closures += f.n_loop_closures
    assert n_obs > 400
    rate = n_closures / n_obs
    assert rate <= np.exp(-2.0)


# ------------------------------------------------------------------------ filter properties
def test_information_symmetric_and_covariances_spd():
    x0, _, steps = simulate(2, "loop", noisy=True, n_steps=700)
    f = RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=4)
    for u, z, ids, _, _ in steps:
        f.predict(u, DT)
        f.update(z, ids)
        if len(z) == 0:
            continue
        _, L = f.information()
        assert abs(L - L.T).max() == 0.0
        _, P = f.pose()
        assert np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
    assert np.all(np.linalg.eigvalsh(f.landmarks().covs) > 0)
    assert np.all(np.linalg.eigvalsh(np.linalg.inv(f.information()[1].toarray())) > 0)


def test_pose_nees_within_chi_square_bounds():
    n_runs = 30
    nees = []
    for seed in range(n_runs):
        x0, _, steps = simulate(200 + seed, "loop", noisy=True, n_steps=200)
        f = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0), steps)
        m, P = f.pose()
        e = m - steps[-1][3]
        e[2] = wrap_angle(e[2])
        nees.append(e @ np.linalg.solve(P, e))
    lo, hi = chi2.ppf([0.005, 0.995], 3 * n_runs) / n_runs
    assert lo < np.mean(nees) < hi


def test_seeded_determinism():
    x0, _, steps = simulate(3, "loop", noisy=True)
    a = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0), steps)
    b = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0), steps)
    np.testing.assert_array_equal(a.pose()[0], b.pose()[0])
    np.testing.assert_array_equal(a.landmarks().means, b.landmarks().means)
    assert repr(a.loop_closures) == repr(b.loop_closures)  # NaN ratios compare by repr


# ------------------------------------------------------------------------ optimiser hand-off
@pytest.mark.parametrize("method", ["reduced", "gauss-newton"])
def test_noise_free_loop_optimum_is_the_truth(method):
    x0, lms, steps = simulate(4, "loop", noisy=False, n_steps=900, compass=True)
    f = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=3), steps)
    prob = f.relative_problem()
    assert f.n_loop_closures > 0
    kinds = [q.kind for q in prob.quantities]
    assert kinds.count(POINT) > f.n_landmarks and kinds.count(HEADING) > 0
    assert kinds.count(POSE) == f.n_delayed_poses - 1
    res = f.optimise(method)
    assert res.converged
    truth = np.array([s[3] for s in steps if len(s[1])])
    traj = f.trajectory()
    np.testing.assert_allclose(traj[1:, :2], truth[:, :2], atol=1e-7)
    np.testing.assert_allclose(wrap_angle(traj[1:, 2] - truth[:, 2]), 0.0, atol=1e-9)
    est = f.landmarks()
    np.testing.assert_allclose(est.means, lms[f.landmark_ids()], atol=1e-7)
    np.testing.assert_allclose(f.pose()[0][:2], steps[-1][3][:2], atol=1e-7)


def test_optimisation_after_loop_closure_reduces_map_error():
    x0, lms, steps = simulate(5, "loop", noisy=True, omega_scale_error=0.1, n_steps=900)
    f = run(RelativeESDF(SENSOR, None, NOISE, initial_pose=x0), steps)
    assert f.n_loop_closures > 0
    before = map_error(f.landmarks(), f.landmark_ids(), lms)
    pose_before = np.linalg.norm(f.pose()[0][:2] - steps[-1][3][:2])
    red = f.optimise("reduced")
    after_red = map_error(f.landmarks(), f.landmark_ids(), lms)
    gn = f.optimise("gauss-newton")
    after_gn = map_error(f.landmarks(), f.landmark_ids(), lms)
    assert after_gn < 0.5 * before
    assert after_red == pytest.approx(after_gn, abs=1e-6)
    assert np.linalg.norm(f.pose()[0][:2] - steps[-1][3][:2]) < pose_before
    np.testing.assert_allclose(red.means[:, :2], gn.means[:, :2], atol=1e-6)
    # after optimising, reported covariances come from Gauss-Newton and are SPD
    assert np.all(np.linalg.eigvalsh(f.landmarks().covs) > 0)
    assert np.all(np.linalg.eigvalsh(f.pose()[1]) > 0)


def test_without_redundancy_optimum_equals_the_filter_chain():
    """No loop closure: the optimum is the composed relative mean, with the same covariance."""
    x0, _, steps = simulate(6, "line", noisy=True, n_steps=500)
    f = RelativeESDF(SENSOR, None, NOISE, initial_pose=x0, max_chain=1000, innovation_sigmas=100.0)
    run(f, steps)
    assert f.n_loop_closures == 0
    traj0, lm0, pose0 = f.trajectory(), f.landmarks(), f.pose()
    f.optimise("gauss-newton")
    traj1, lm1, pose1 = f.trajectory(), f.landmarks(), f.pose()
    np.testing.assert_allclose(traj1, traj0, atol=1e-8)
    np.testing.assert_allclose(lm1.means, lm0.means, atol=1e-8)
    np.testing.assert_allclose(lm1.covs, lm0.covs, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(pose1[0], pose0[0], atol=1e-8)
    np.testing.assert_allclose(pose1[1], pose0[1], rtol=1e-6, atol=1e-12)


def test_entities_added_after_optimisation_chain_onto_the_optimum():
    x0, lms, steps = simulate(7, "loop", noisy=True, omega_scale_error=0.1, n_steps=900)
    f = RelativeESDF(SENSOR, None, NOISE, initial_pose=x0)
    run(f, steps[:300])
    res = f.optimise("gauss-newton")
    n_opt = f.n_delayed_poses
    n_lm = f.n_landmarks
    run(f, steps[300:])
    assert f.n_delayed_poses > n_opt and f.n_landmarks > n_lm
    traj = f.trajectory()
    pose_entities = [g for g, k in enumerate(res.problem.entity_kinds) if k == POSE]
    np.testing.assert_allclose(traj[:n_opt], res.means[pose_entities], atol=1e-12)
    # later poses: the optimised anchor composed with the relative means
    mu = f.info.mean()
    anchor = traj[n_opt - 1]
    d = f.info.mean_of(f._pose_rel[n_opt], mu)
    np.testing.assert_allclose(traj[n_opt], wrap_pose(chain_compose(anchor, d)[0][-1]), atol=1e-9)
    # landmarks covered by the optimisation keep the optimum; new ones are chained too
    est = f.landmarks()
    old = [n for n, j in enumerate(f.landmark_ids()) if f._lm_g[int(j)] < len(res.means)]
    np.testing.assert_allclose(
        est.means[old], res.means[[f._lm_g[int(j)] for j in f.landmark_ids()[old]], :2]
    )
    assert np.all(np.linalg.eigvalsh(f.pose()[1]) > 0)
    assert np.all(np.linalg.eigvalsh(est.covs) > 0)
    # the anchored pose covariance grows along the new chain from the optimum's covariance
    assert np.trace(f.pose()[1][:2, :2]) > np.trace(res.covariance(pose_entities[-1])[:2, :2])


def wrap_pose(p):
    p = np.array(p, dtype=float)
    p[2] = wrap_angle(p[2])
    return p


# ------------------------------------------------------------------------ validation
@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"max_chain": 0}, "max_chain"),
        ({"max_chain": 2.5}, "max_chain"),
        ({"innovation_sigmas": 0.0}, "innovation_sigmas"),
        ({"innovation_sigmas": float("nan")}, "innovation_sigmas"),
        ({"recovery_window": 0}, "recovery_window"),
        ({"min_odometry_var": 0.0}, "min_odometry_var"),
        ({"initial_pose": (1.0, 2.0)}, "initial_pose"),
    ],
)
def test_bad_options_raise_value_error_naming_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        RelativeESDF(SENSOR, None, NOISE, **kwargs)


def test_bad_calls_raise_value_error_naming_field():
    f = RelativeESDF(SENSOR, None, NOISE)
    with pytest.raises(ValueError, match="ids"):
        f.update(np.array([[1.0, 0.0]]))
    with pytest.raises(ValueError, match="dt"):
        f.predict(np.array([1.0, 0.0]), float("inf"))
    with pytest.raises(ValueError, match="method"):
        f.predict(np.array([1.0, 0.0]), 0.5)
        f.update(np.array([[2.0, 0.1]]), np.array([3]))
        f.optimise("simplex")
