"""The compiled filter iteration (issue 47): each of its new compiled pieces against a plain
numpy reference, and the whole iteration against the separate calls it replaces, from the same
state and the same draws at every step of seeded runs (captured scans), to rounding."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from filters.geometry import compose, compose_jacobians, wrap_angle

# its module-scoped fixtures are built once: every test of this file on one worker (pytest -n)
pytestmark = pytest.mark.xdist_group("test_fastslam_iteration")


def _numpy_heading_update(state, theta, var, pending):
    """The compass update as FastSLAM2.update_heading wrote it in numpy before issue 47."""
    poses, logw = state.poses.copy(), state.logw.copy()
    prop_cov = state.prop_cov.copy()
    nu = wrap_angle(theta - poses[:, 2])
    if pending:
        Pc = prop_cov
        s = Pc[:, 2, 2] + var
        k = Pc[:, :, 2] / s[:, None]
        poses += k * nu[:, None]
        poses[:, 2] = wrap_angle(poses[:, 2])
        Pc = Pc - k[:, :, None] * Pc[:, None, 2, :]
        prop_cov = 0.5 * (Pc + np.swapaxes(Pc, 1, 2))
    else:
        s = np.full(len(poses), var)
    logw += -0.5 * nu * nu / s - 0.5 * np.log(2.0 * np.pi * s)
    return poses, prop_cov, logw - logw.max()


@pytest.mark.parametrize("pending", [True, False])
def test_heading_update_equals_the_numpy_reference(pending):
    from filters.fastslam_kernel import call_heading_update, new_state

    rng = np.random.default_rng(4)
    for P in (1, 3, 200):
        state = new_state(P, 2, np.zeros(3))
        state.poses[:] = rng.normal(size=(P, 3)) * [5.0, 5.0, 3.0]
        A = rng.normal(size=(P, 3, 3)) * 0.1
        state.prop_cov[:] = A @ np.swapaxes(A, 1, 2)
        state.logw[:] = rng.normal(size=P)
        theta, var = float(rng.uniform(-np.pi, np.pi)), 0.01**2
        poses, prop_cov, logw = _numpy_heading_update(state, theta, var, pending)
        call_heading_update(state, theta, var, pending)
        np.testing.assert_allclose(state.poses, poses, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(state.prop_cov, prop_cov, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(state.logw, logw, rtol=1e-12, atol=1e-12)


def test_pose_metrics_equal_numpys_cholesky_and_norm():
    """The iteration's NEES (with the heading error wrapped and the regularisation of
    slam_gym.metrics) and position error against numpy; NaN without truth."""
    from filters.global_frame import NEES_REGULARISATION, pose_metrics

    rng = np.random.default_rng(9)
    for _ in range(200):
        truth, mean = rng.normal(size=3) * [10, 10, 3], rng.normal(size=3) * [10, 10, 3]
        A = rng.normal(size=(3, 3))
        cov = A @ A.T + 1e-3 * np.eye(3)
        e = truth - mean
        e[2] = wrap_angle(e[2])
        L = np.linalg.cholesky(0.5 * (cov + cov.T) + NEES_REGULARISATION * np.eye(3))
        y = np.linalg.solve(L, e)
        value, error = pose_metrics(truth, mean, cov)
        assert value == pytest.approx(float(y @ y), rel=1e-10)
        assert error == pytest.approx(float(np.linalg.norm(e[:2])), rel=1e-12)
    assert all(np.isnan(pose_metrics(np.full(3, np.nan), mean, cov)))
    assert pose_metrics(np.zeros(3), np.zeros(3), -np.eye(3))[0] == np.inf


def _reference_iteration(system, step, heading):
    """What the compiled iteration replaces, from the separate calls: predict, the compass, CM's
    innovation ratio against the prior (the separately compiled and separately tested
    SubmapSLAM.observation_innovation_ratio), the scan and the pose moments; the composition
    with the origin and the NEES in numpy. Returns (mean, cov, nees, error, ratio)."""
    from slam_gym.metrics import nees

    system.predict(step.odometry, step.dt_s)
    if heading is not None:
        system.update_heading(*heading)
    ratio = None
    if step.scanned:
        z = np.asarray(step.z, dtype=float).reshape(-1, 2)
        ratio = system.observation_innovation_ratio(z)
        system.front_end.update(z)
    xl, Pl = system.front_end.pose()
    v, P_v = system.back_end.origin()
    J_a, J_b = compose_jacobians(v, xl)
    cov = J_a @ P_v @ J_a.T + J_b @ Pl @ J_b.T
    mean, cov = compose(v, xl), 0.5 * (cov + cov.T)
    return (mean, cov, nees(step.truth.pose, mean, cov),
            float(np.linalg.norm(step.truth.pose[:2] - mean[:2])), ratio)


@pytest.mark.parametrize("scenario, sensor_rate_hz", [("brooks-bailey", 5.0),
                                                      ("brooks-bailey-compass", 10.0)])
def test_iteration_equals_the_separate_calls_on_captured_scans(scenario, sensor_rate_hz):
    """SubmapSLAM.iterate (one compiled call) against the separate calls from the same state
    with the same synchronised draws at every step of a seeded run with fusions every 20 steps
    (so the innovation ratio sees global features), iterations without a scan (a pending
    proposal drawn at the next prediction) or a compass: the poses, NEES, position errors,
    innovation ratios and every array of the particle state to rounding, the associations
    equal."""
    from filters.draws import SynchronisedDraws
    from filters.fastslam_kernel import ParticleState
    from slam_gym.systems import make_system
    from slam_gym.world import make_stream

    stream = make_stream(scenario, seed=3, n_steps=120, clutter_level=2,
                         sensor_rate_hz=sensor_rate_hz)
    draws = SynchronisedDraws((3, 0))
    system = make_system("hybrid", stream, draws, n_particles=60).estimator
    n_ratio = n_resampled = 0
    for i, step in enumerate(stream):
        if i and i % 20 == 0:
            system.fuse()
        heading = None
        if step.compass_rad is not None:
            heading = (step.compass_rad, stream.compass_std_rad)
        reference = copy.deepcopy(system)
        reference.front_end.draws.iteration = draws.iteration = i
        reference.start_interval()
        system.start_interval()
        expected = _reference_iteration(reference, step, heading)
        got = system.iterate(step.odometry, step.dt_s, step.z if step.scanned else None,
                             heading=heading, truth_pose=step.truth.pose)
        np.testing.assert_allclose(got[0], expected[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(got[1], expected[1], rtol=1e-8, atol=1e-14)
        assert got[2] == pytest.approx(expected[2], rel=1e-7)
        assert got[3] == pytest.approx(expected[3], rel=1e-9, abs=1e-12)
        if expected[4] is not None:
            assert system.interval_innovation_ratio == pytest.approx(expected[4], rel=1e-9)
            n_ratio += expected[4] > 0.0
        front, ref_front = system.front_end, reference.front_end
        n_resampled += ref_front._ess_ratio < front.resample_threshold
        for name in ParticleState._fields:
            a, b = getattr(front._state, name), getattr(ref_front._state, name)
            if a.dtype.kind == "f":
                np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12, err_msg=name)
            else:
                np.testing.assert_array_equal(a, b, err_msg=name)
        np.testing.assert_array_equal(front.last_associations, ref_front.last_associations)
        assert front._pending == ref_front._pending
        assert front._ess_ratio == pytest.approx(ref_front._ess_ratio, rel=1e-12)
        np.testing.assert_allclose(front.weights, ref_front.weights, rtol=1e-12, atol=1e-300)
    assert n_ratio > 5 and n_resampled > 5  # the ratio and the resampling were exercised


def test_run_iteration_with_known_association_equals_the_separate_calls():
    """The filter alone (its own frame) with known association: run_iteration against
    predict, update(z, associations) and pose from the same state and draws."""
    from filters.draws import SynchronisedDraws
    from filters.fastslam import FastSLAM2
    from slam_gym.world import make_stream

    stream = make_stream("brooks-bailey", seed=5, n_steps=60, clutter_level=1)
    draws = SynchronisedDraws((5, 1))
    f = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise, draws, n_particles=40,
                  initial_pose=stream.initial_pose)
    for i, step in enumerate(stream):
        reference = copy.deepcopy(f)
        reference.draws.iteration = draws.iteration = i
        reference.predict(step.odometry, step.dt_s)
        reference.update(step.z, step.truth.landmark_ids)
        mean, cov = reference.pose()
        result = f.run_iteration(step.odometry, step.dt_s, step.z,
                                 associations=step.truth.landmark_ids)
        np.testing.assert_allclose(result.local_mean, mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(result.local_cov, cov, rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(result.mean, mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(f.last_associations, reference.last_associations)
        np.testing.assert_allclose(f._state.poses, reference._state.poses, rtol=1e-12,
                                   atol=1e-12)
        assert np.isnan(result.nees)
