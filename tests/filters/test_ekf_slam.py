"""EKF-SLAM with JCBB, clutter and existence probabilities (filters/ekf_slam.py)."""

from __future__ import annotations

from collections import Counter, defaultdict

import numpy as np
import pytest
from scipy.stats import chi2

from filters.association import predict_range_bearing
from filters.ekf_slam import EKFSLAM, EKFSLAMConfig, kalman_update
from filters.existence import (
    detection_update,
    false_alarm_in_gate_probability,
    gate_area,
    miss_update,
)
from filters.geometry import wrap_angle
from filters.models import (
    ClutterModel,
    ProportionalVelocityNoise,
    RangeBearingSensor,
    inverse_observe_jacobians,
    observe,
)
from filters.types import FeatureIds
from slam_gym.world import make_stream

SENSOR = RangeBearingSensor()
NOISE = ProportionalVelocityNoise(v_floor_mps=0.005, omega_floor_radps=0.005)


def _ekf(stream, **options):
    return EKFSLAM(
        stream.sensor, stream.clutter, stream.odometry_noise, initial_pose=stream.initial_pose,
        **options,
    )


def _step(f, stream, step):
    f.predict(step.odometry, step.dt_s)
    if step.compass_rad is not None:
        f.update_heading(step.compass_rad, stream.compass_std_rad)
    f.update(step.z)


def _nees(true_pose, mean, cov):
    e = np.asarray(true_pose) - mean
    e[2] = wrap_angle(e[2])
    return float(e @ np.linalg.solve(cov, e))


def _anees_band(n_runs, dof=3):
    return chi2.ppf([0.025, 0.975], dof * n_runs) / n_runs


# --------------------------------------------------------------------------- numerics
@pytest.mark.parametrize("level", [2, 3])
def test_covariance_symmetric_positive_definite_after_every_update_with_clutter(level):
    stream = make_stream("brooks-bailey", seed=level, n_steps=300, clutter_level=level)
    f = _ekf(stream)
    n_max = 0
    for step in stream:
        _step(f, stream, step)
        P = f.P
        assert np.array_equal(P, P.T)
        if step.index == 0:
            # one step of odometry noise (2-D) into a known pose: PSD, rank-deficient
            ev = np.linalg.eigvalsh(P)
            assert ev[0] >= -1e-12 * ev[-1]
        else:
            np.linalg.cholesky(P)  # raises unless positive definite
        n_max = max(n_max, f.n_features)
    assert n_max > 5


def test_kalman_update_is_the_joseph_form():
    rng = np.random.default_rng(2)
    n = 9
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    x = rng.normal(size=n)
    cols = np.array([0, 1, 2, 5, 6])
    Hc = rng.normal(size=(4, 5))
    R = np.diag([0.1, 0.2, 0.3, 0.4])
    nu = rng.normal(size=4)
    H = np.zeros((4, n))
    H[:, cols] = Hc
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    I_KH = np.eye(n) - K @ H
    P_ref = I_KH @ P @ I_KH.T + K @ R @ K.T
    x_ref = x + K @ nu
    x2, P2 = x.copy(), P.copy()
    kalman_update(x2, P2, cols, Hc, nu, R)
    np.testing.assert_allclose(x2, x_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(P2, P_ref, rtol=1e-9, atol=1e-12)
    assert np.array_equal(P2, P2.T)


def test_update_heading_is_a_scalar_kalman_update():
    f = EKFSLAM(SENSOR, ClutterModel(), NOISE, initial_pose_cov=np.diag([0.1, 0.2, 0.05]))
    f.update(np.array([[10.0, 0.3]]))  # one feature, correlated with the heading
    x0, P0 = f.x.copy(), f.P.copy()
    theta, std = 0.1, 0.02
    f.update_heading(theta, std)
    K = P0[:, 2] / (P0[2, 2] + std**2)
    np.testing.assert_allclose(f.x, x0 + K * (theta - x0[2]), atol=1e-12)
    np.testing.assert_allclose(f.P, P0 - np.outer(K, P0[2, :]), atol=1e-12)


def test_new_feature_is_initialised_through_the_inverse_observation():
    Pv = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.01]])
    pose = np.array([1.0, 2.0, 0.5])
    f = EKFSLAM(SENSOR, ClutterModel(), NOISE, initial_pose=pose, initial_pose_cov=Pv)
    z = np.array([[7.0, -0.4]])
    f.update(z)
    assert f.n_features == 1
    G_p, G_z = inverse_observe_jacobians(pose, z[0])
    np.testing.assert_allclose(f.P[3:, :3], G_p @ Pv, atol=1e-14)
    np.testing.assert_allclose(f.P[3:, 3:], G_p @ Pv @ G_p.T + G_z @ SENSOR.R @ G_z.T, atol=1e-14)
    np.testing.assert_allclose(observe(pose, f.x[3:]), z[0], atol=1e-12)


def test_growing_capacity_gives_the_same_estimates():
    stream = make_stream("brooks-bailey", seed=4, n_steps=150, clutter_level=2)
    small = _ekf(stream, initial_feature_capacity=1)
    large = _ekf(stream, initial_feature_capacity=64)
    for step in stream:
        _step(small, stream, step)
        _step(large, stream, step)
    assert small.n_features > 4
    np.testing.assert_array_equal(small.feature_ids(), large.feature_ids())
    np.testing.assert_allclose(small.x, large.x, atol=1e-9)
    np.testing.assert_allclose(small.P, large.P, atol=1e-9)


def test_same_stream_gives_the_same_run_bit_for_bit():
    stream = make_stream("brooks-bailey", seed=5, n_steps=120, clutter_level=1)
    a, b = _ekf(stream, ids=FeatureIds()), _ekf(stream, ids=FeatureIds())
    for step in stream:
        _step(a, stream, step)
        _step(b, stream, step)
        np.testing.assert_array_equal(a.last_associations, b.last_associations)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)


# --------------------------------------------------------------------------- consistency
def test_anees_in_band_without_clutter_with_compass():
    """40 runs x 300 iterations of brooks-bailey-compass: the final ANEES lies inside the 95 %
    chi-square band chi2(3N)/N (runs are independent worlds, paths and noise)."""
    n_runs = 40
    finals = []
    for seed in range(n_runs):
        stream = make_stream("brooks-bailey-compass", seed=seed, n_steps=300)
        f = _ekf(stream)
        for step in stream:
            _step(f, stream, step)
        mean, cov = f.pose()
        finals.append(_nees(step.truth.pose, mean, cov))
    lo, hi = _anees_band(n_runs)
    assert lo <= np.mean(finals) <= hi, (np.mean(finals), lo, hi)


def test_confirmed_features_are_real_landmarks_in_clutter():
    """Clutter level 2: features started by false alarms are culled; what is confirmed stands
    for a true landmark (majority of its associated observations) in all but rare cases."""
    stream = make_stream("brooks-bailey", seed=11, n_steps=400, clutter_level=2)
    f = _ekf(stream)
    votes: dict[int, Counter] = defaultdict(Counter)
    n_clutter_obs = 0
    for step in stream:
        _step(f, stream, step)
        for fid, truth in zip(f.last_associations, step.truth.landmark_ids, strict=True):
            if fid >= 0:
                votes[int(fid)][int(truth)] += 1
        n_clutter_obs += int(np.count_nonzero(step.truth.landmark_ids < 0))
    assert n_clutter_obs > 20
    lm = f.landmarks()
    confirmed = lm.ids[lm.existence > 0.95]
    assert len(confirmed) >= 5
    real = [votes[int(i)].most_common(1)[0][0] >= 0 for i in confirmed]
    assert np.mean(real) >= 0.9
    spurious_started = sum(1 for c in votes.values() if c.most_common(1)[0][0] < 0)
    assert spurious_started > 0  # clutter did start features ...
    assert f.n_features < len(votes)  # ... and they were culled
    assert 0.0 < f.clutter_rate() < 1.0


# --------------------------------------------------------------------------- existence / culling
def _static_filter(**options):
    clutter = ClutterModel(alpha=0.7, beta=0.02)
    return EKFSLAM(SENSOR, clutter, NOISE, **options), clutter


def test_existence_detection_miss_and_cull():
    f, clutter = _static_filter()
    z = np.array([[10.0, 0.2]])
    f.update(z)
    assert f.n_features == 1
    assert f.existence()[0] == pytest.approx(0.5)  # initial_existence
    (fid,) = f.feature_ids()
    np.testing.assert_array_equal(f.last_associations, [fid])
    # detection: BB (11) with the false-alarm-in-gate probability of this gate
    pred = predict_range_bearing(f.x, f.P, np.arange(3), np.array([[3, 4]]), SENSOR.R)
    area = gate_area(pred.S, chi2.ppf(f.config.gate_probability, 2))
    p_fa = false_alarm_in_gate_probability(
        clutter.beta, 1.0, area, SENSOR.max_range_m, SENSOR.fov_rad
    )
    f.update(z)
    expected = detection_update(0.5, clutter.alpha, p_fa)[0]
    assert f.existence()[0] == pytest.approx(expected, rel=1e-9)
    np.testing.assert_array_equal(f.last_associations, [fid])
    # a miss: predicted in view, not detected
    pred = predict_range_bearing(f.x, f.P, np.arange(3), np.array([[3, 4]]), SENSOR.R)
    area = gate_area(pred.S, chi2.ppf(f.config.gate_probability, 2))
    p_fa = false_alarm_in_gate_probability(
        clutter.beta, max(1.0, expected), area, SENSOR.max_range_m, SENSOR.fov_rad
    )
    f.update(np.zeros((0, 2)))
    assert f.existence()[0] == pytest.approx(miss_update(expected, clutter.alpha, p_fa)[0])
    # repeated misses cull the feature and its rows/columns
    for _ in range(60):
        f.update(np.zeros((0, 2)))
    assert f.n_features == 0 and f.state_dim == 3


def test_feature_out_of_view_is_not_missed():
    f, _ = _static_filter()
    f.update(np.array([[24.99, 0.0]]))  # at the edge of the range: not surely in view
    f.update(np.zeros((0, 2)))
    assert f.existence()[0] == pytest.approx(0.5)


def test_removing_features_deletes_their_rows_and_columns():
    f, _ = _static_filter(initial_pose_cov=np.diag([0.1, 0.1, 0.01]))
    f.update(np.array([[10.0, 0.2], [12.0, -1.0], [8.0, 2.0], [15.0, 3.0]]))
    x0, P0, ids0 = f.x.copy(), f.P.copy(), f.feature_ids()
    keep = np.array([True, False, True, False])
    f._remove_features(keep)
    idx = np.r_[0:3, 3:5, 7:9]
    np.testing.assert_array_equal(f.x, x0[idx])
    np.testing.assert_array_equal(f.P, P0[np.ix_(idx, idx)])
    np.testing.assert_array_equal(f.feature_ids(), ids0[keep])


def test_ambiguous_unpaired_observation_is_clutter_not_a_new_feature():
    f, _ = _static_filter()
    f.update(np.array([[10.0, 0.0]]))
    f.update(np.array([[10.0, 0.0]]))
    n = f.n_features
    # two observations in the gate of the one feature: one pairs, the other is clutter
    f.update(np.array([[10.01, 0.0], [10.0, 0.003]]))
    assert f.n_features == n
    assert sorted(f.last_associations.tolist())[0] == -1
    assert np.count_nonzero(f.last_associations >= 0) == 1


def test_known_association_follows_the_labels_even_against_the_geometry():
    f, _ = _static_filter(initial_pose_cov=np.diag([0.01, 0.01, 0.001]))
    f.update(np.array([[10.0, 0.0], [10.0, 0.5]]), associations=[4, 9])
    fid4, fid9 = f.feature_ids()
    np.testing.assert_array_equal(f.last_associations, [fid4, fid9])
    # label 9 observed where feature 4 is (JCBB would pair it with 4); label -1 is ignored
    # (no new feature); label 2 is new; label 9 twice in one scan pairs its first only
    x_before = f.x.copy()
    f.update(np.array([[10.0, 0.0], [7.0, 1.0], [12.0, -1.0], [10.0, 0.5]]),
             associations=[9, -1, 2, 9])
    assert f.n_features == 3
    fid2 = f.feature_ids()[2]
    np.testing.assert_array_equal(f.last_associations, [fid9, -1, fid2, -1])
    assert f.x[6] < x_before[6]  # feature 9 (state 5:7) pulled towards bearing 0
    # unknown association again pairs by geometry
    f.update(np.array([[10.0, 0.0]]))
    assert f.last_associations[0] in (fid4, fid9)


def test_known_association_recreates_a_culled_label():
    f, _ = _static_filter()
    f.update(np.array([[10.0, 0.0]]), associations=[3])
    (first,) = f.feature_ids()
    for _ in range(60):
        f.update(np.zeros((0, 2)), associations=[])
    assert f.n_features == 0
    f.update(np.array([[10.0, 0.0]]), associations=[3])
    (second,) = f.feature_ids()
    assert second != first and f.last_associations.tolist() == [second]
    with pytest.raises(ValueError, match="associations"):
        f.update(np.array([[10.0, 0.0]]), associations=[3, 4])


# --------------------------------------------------------------------------- front-end interface
def test_to_gaussian_restart_and_local_statistics():
    stream = make_stream("brooks-bailey", seed=2, n_steps=80)
    f = _ekf(stream)
    for step in stream:
        _step(f, stream, step)
    g = f.to_gaussian()
    conf = f.confirmed_mask()
    assert g.n_features == np.count_nonzero(conf) > 0
    np.testing.assert_array_equal(g.ids, f.feature_ids()[conf])
    assert np.all(g.existence > 0.95)
    assert g.P.shape == (3 + 2 * g.n_features,) * 2 and np.array_equal(g.P, g.P.T)
    np.linalg.cholesky(g.P)
    np.testing.assert_array_equal(g.x[:3], f.x[:3])
    stats = f.local_statistics()
    P = f.P
    assert stats["ess_ratio"] == 1.0 and stats["vote_margin"] == 1.0
    assert stats["particle_position_spread_m"] == pytest.approx(np.sqrt(P[0, 0] + P[1, 1]))
    assert stats["particle_heading_spread_rad"] == pytest.approx(np.sqrt(P[2, 2]))
    assert stats["local_feature_count"] == f.n_features
    assert stats["local_confirmed_count"] == g.n_features
    assert stats["local_map_age_s"] == pytest.approx(80 * stream.dt_s)
    assert stats["local_map_distance_m"] == pytest.approx(
        sum(abs(s.odometry[0]) * s.dt_s for s in stream)
    )
    assert stats["local_map_budget_ratio"] == pytest.approx(f.n_features / 100)
    f.restart()
    mean, cov = f.pose()
    assert np.array_equal(mean, np.zeros(3)) and np.array_equal(cov, np.zeros((3, 3)))
    assert f.n_features == 0 and len(f.landmarks()) == 0
    after = f.local_statistics()
    assert after["local_map_age_s"] == 0.0 and after["local_map_distance_m"] == 0.0
    assert after["clutter_rate"] == stats["clutter_rate"]
    g0 = f.to_gaussian()
    assert g0.n_features == 0 and g0.x.shape == (3,)


def test_landmarks_report_every_feature_with_marginal_covariances():
    f, _ = _static_filter(initial_pose_cov=np.diag([0.1, 0.1, 0.01]))
    f.update(np.array([[10.0, 0.2], [12.0, -1.0]]))
    lm = f.landmarks()
    assert len(lm) == 2
    np.testing.assert_array_equal(lm.means, f.x[3:].reshape(2, 2))
    np.testing.assert_array_equal(lm.covs[1], f.P[5:7, 5:7])
    np.testing.assert_array_equal(lm.existence, [0.5, 0.5])


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "option, value",
    [
        ("gate_probability", 1.0),
        ("gate_probability", 0.0),
        ("initial_existence", 0.0),
        ("initial_existence", 1.0),
        ("cull_probability", 0.96),
        ("max_detection_probability", 0.0),
        ("node_budget", 0),
        ("feature_budget", 0),
        ("clutter_rate_forgetting", 1.5),
        ("in_view_margin_sigma", -1.0),
    ],
)
def test_bad_option_raises_value_error_naming_the_field(option, value):
    with pytest.raises(ValueError, match=option):
        EKFSLAM(SENSOR, ClutterModel(), NOISE, **{option: value})
    with pytest.raises(ValueError, match=option):
        EKFSLAMConfig(**{option: value})


def test_initial_existence_must_exceed_cull_probability():
    with pytest.raises(ValueError, match="initial_existence=0.04"):
        EKFSLAM(SENSOR, ClutterModel(), NOISE, initial_existence=0.04, cull_probability=0.05)


def test_unknown_option_and_bad_inputs():
    with pytest.raises(ValueError, match="gate_prob"):
        EKFSLAM(SENSOR, ClutterModel(), NOISE, gate_prob=0.9)
    f = EKFSLAM(SENSOR, ClutterModel(), NOISE)
    with pytest.raises(ValueError, match="z"):
        f.update(np.array([1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match="std_rad"):
        f.update_heading(0.0, 0.0)
    with pytest.raises(ValueError, match="dt"):
        f.predict(np.array([1.0, 0.0]), -0.1)
    with pytest.raises(ValueError, match="initial_pose_cov"):
        EKFSLAM(SENSOR, ClutterModel(), NOISE, initial_pose_cov=-np.eye(3))


def test_existence_model_bb_uses_beta_literally():
    """BB (11) as written: P_fa = beta, so a detection multiplies the odds by alpha / beta."""
    f, clutter = _static_filter(existence_model="bb")
    z = np.array([[10.0, 0.2]])
    f.update(z)
    f.update(z)
    expected = float(detection_update(0.5, clutter.alpha, clutter.beta))
    assert f.existence()[0] == pytest.approx(expected, rel=1e-9)
    gate, _ = _static_filter()
    gate.update(z)
    gate.update(z)
    assert gate.existence()[0] > expected  # clutter in a small gate is far rarer than beta
    with pytest.raises(ValueError, match="existence_model"):
        _static_filter(existence_model="literal")
