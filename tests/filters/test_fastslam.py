"""FastSLAM 2.0 with Data Association Sampling (filters/fastslam.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from filters import fastslam_kernel as kernel
from filters.conversion import CLUTTER_VOTE, NEW_VOTE, pose_moments
from filters.fastslam import LOCAL_MAP_MAX_EXISTENCE, FastSLAM2
from filters.geometry import wrap_angle
from filters.models import (
    ClutterModel,
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
from slam_gym.scenarios import SQUARE_LOOP_OVERRIDES
from slam_gym.world import make_stream

LOCAL_KEYS = {
    "local_map_age_s", "local_map_distance_m", "ess_ratio", "particle_position_spread_m",
    "particle_heading_spread_rad", "local_feature_count", "local_confirmed_count", "vote_margin",
    "clutter_rate", "local_map_budget_ratio",
}


def make_filter(stream=None, seed=0, **options):
    if stream is None:
        sensor, clutter = RangeBearingSensor(), ClutterModel()
        noise = ProportionalVelocityNoise(v_floor_mps=0.005, omega_floor_radps=0.005)
        pose = np.zeros(3)
    else:
        sensor, clutter, noise = stream.sensor, stream.clutter, stream.odometry_noise
        pose = stream.initial_pose
    options.setdefault("initial_pose", pose)
    return FastSLAM2(sensor, clutter, noise, np.random.default_rng(seed), **options)


def assert_spd(C, floor=0.0):
    np.testing.assert_allclose(C, np.swapaxes(C, -1, -2), atol=1e-12)
    assert np.linalg.eigvalsh(C).min() > floor


def feature_covs_spd(f):
    covs = f.covs[f.active]
    if len(covs):
        assert np.all(np.abs(covs[:, 0, 1] - covs[:, 1, 0]) == 0.0)
        det = covs[:, 0, 0] * covs[:, 1, 1] - covs[:, 0, 1] ** 2
        assert np.all(covs[:, 0, 0] > 0) and np.all(det > 0)


def run(f, stream, known=False, every=None):
    for step in stream:
        f.predict(step.odometry, step.dt_s)
        f.update(step.z, step.truth.landmark_ids if known else None)
        if every is not None:
            every(step)
    return f


# --------------------------------------------------------------------------- building blocks
def test_terms_and_refine_match_matrix_kalman_form():
    rng = np.random.default_rng(1)
    sensor = RangeBearingSensor()
    R = sensor.R
    zk = np.array([4.0, 0.3])
    for _ in range(4):
        pose = rng.normal(size=3)
        A = rng.normal(size=(3, 2))  # rank-2 proposal covariance, as from the motion model
        Pc = A @ A.T * 0.01
        m = pose[:2] + rng.normal(size=2) * 5
        B = rng.normal(size=(2, 2))
        sig = B @ B.T * 0.1
        t = kernel._observation_terms(zk[0], zk[1], pose, Pc, m[0], m[1], sig[0, 0], sig[0, 1],
                                      sig[1, 1], R[0, 0], R[1, 1])
        nu_r, nu_b, S00, S01, S11, det, d2, h00, h01, h10, h11 = t
        G, Hm = observe_jacobians(pose, m)
        S = G @ Pc @ G.T + Hm @ sig @ Hm.T + R
        np.testing.assert_allclose([[S00, S01], [S01, S11]], S, atol=1e-12)
        np.testing.assert_allclose(det, np.linalg.det(S), rtol=1e-9)
        np.testing.assert_allclose([[h00, h01], [h10, h11]], Hm, atol=1e-12)
        nu = innovation(zk, observe(pose, m))
        np.testing.assert_allclose([nu_r, nu_b], nu, atol=1e-12)
        np.testing.assert_allclose(d2, nu @ np.linalg.solve(S, nu), rtol=1e-9)

        x, P = pose.copy(), Pc.copy()
        scratch = np.full((4, 3), np.nan)  # work space: its contents must not matter
        kernel._refine(x, P, np.array(t), scratch)
        K = Pc @ G.T @ np.linalg.inv(S)
        np.testing.assert_allclose(wrap_angle(x - (pose + K @ nu)), 0.0, atol=1e-12)
        np.testing.assert_allclose(P, Pc - K @ G @ Pc, atol=1e-12)
        assert np.linalg.eigvalsh(0.5 * (P + P.T)).min() > -1e-12


def test_feature_ekf_matches_matrix_ekf():
    rng = np.random.default_rng(2)
    R = np.diag([0.05**2, 0.02**2])
    for _ in range(6):
        pose = rng.normal(size=3)
        m = pose[:2] + rng.normal(size=2) * 8
        B = rng.normal(size=(2, 2))
        sig = B @ B.T * 0.2
        z = observe(pose, m) + rng.normal(size=2) * 0.05
        mx, my, sxx, sxy, syy = kernel._feature_ekf(
            pose, m[0], m[1], sig[0, 0], sig[0, 1], sig[1, 1], z[0], z[1], R[0, 0], R[1, 1]
        )
        _, H = observe_jacobians(pose, m)
        S = H @ sig @ H.T + R
        K = sig @ H.T @ np.linalg.inv(S)
        m_new = m + K @ innovation(z, observe(pose, m))
        sig_new = (np.eye(2) - K @ H) @ sig
        np.testing.assert_allclose([mx, my], m_new, atol=1e-10)
        np.testing.assert_allclose([[sxx, sxy], [sxy, syy]], sig_new, atol=1e-12)


def test_new_feature_is_the_inverse_observation_with_its_covariance():
    f = make_filter(n_particles=3, initial_pose=(1.0, -2.0, 0.4))
    f.predict([0.0, 0.0], 0.1)  # zero motion: the proposal stays at the initial pose
    z = np.array([[7.0, -0.6], [3.0, 1.2]])
    f.update(z, associations=[0, 1])
    pose = f.poses[0]
    m_expected = inverse_observe(pose, z)
    _, Gz = inverse_observe_jacobians(pose, z)
    cov_expected = Gz @ f.sensor.R @ np.swapaxes(Gz, 1, 2)
    np.testing.assert_allclose(f.means[0, :2], m_expected, atol=1e-12)
    np.testing.assert_allclose(f.covs[0, :2], cov_expected, atol=1e-15)
    assert f.active[:, :2].all() and f._state.count.tolist() == [2, 2, 2]

def test_propagate_matches_the_motion_model_and_its_jacobian():
    rng = np.random.default_rng(3)
    poses = rng.normal(size=(5, 3)) * [3.0, 3.0, 3.0]
    u, dt = np.array([1.3, -0.7]), 0.1
    Q = np.array([[0.04, 0.01], [0.01, 0.09]])
    state = kernel.new_state(5, 1, np.zeros(3))._replace(poses=poses.copy())
    kernel.propagate(state, u[0], u[1], dt, Q)
    moved, covs = state.poses, state.prop_cov
    np.testing.assert_allclose(moved, motion(poses, u, dt), atol=1e-14)
    for p in range(5):
        _, J = motion_jacobians(poses[p], u, dt)
        np.testing.assert_allclose(covs[p], J @ Q @ J.T, atol=1e-15)


@pytest.mark.parametrize("rank", [1, 2, 3])
def test_pose_draw_reproduces_singular_covariances(rank):
    rng = np.random.default_rng(rank)
    J = rng.normal(size=(3, rank))
    C = J @ J.T * 0.003  # heading std well below pi: the draw wraps the heading
    n = 100_000
    x = np.zeros((n, 3))
    covs = np.ascontiguousarray(np.broadcast_to(C, (n, 3, 3)))
    state = kernel.new_state(n, 1, np.zeros(3))._replace(prop_cov=covs.copy())
    kernel.draw_poses(state, rng.standard_normal((n, 3)))
    x = state.poses
    assert not state.prop_cov.any()  # the pose is drawn: no proposal left
    # each entry of the sample covariance is within ~6 standard errors
    tol = 6.0 * np.sqrt((np.outer(np.diag(C), np.diag(C)) + C**2) / n) + 1e-12
    assert np.abs(x[:, 2]).max() < np.pi
    assert np.all(np.abs(np.cov(x.T) - C) < tol)
    if rank < 3:  # the samples stay in the covariance's range
        null = np.linalg.svd(J)[0][:, rank:]
        assert np.abs(x @ null).max() < 1e-9


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "option, value",
    [
        ("n_particles", 0),
        ("resample_threshold", 1.5),
        ("gate_chi2", -1.0),
        ("new_landmark_density_per_m2", 0.0),
        ("max_existence", 2.0),
        ("cull_threshold", 0.9),
        ("cull_interval_steps", 0),
        ("feature_budget", 0),
        ("initial_capacity", 0),
        ("initial_pose", (0.0, 1.0)),
        ("lineage_correction", 1),
        ("small_sample_correction", "yes"),
    ],
)
def test_constructor_rejects_bad_options(option, value):
    with pytest.raises(ValueError, match=option):
        make_filter(**{option: value})


def test_constructor_rejects_bad_models():
    with pytest.raises(ValueError, match="rng"):
        FastSLAM2(RangeBearingSensor(), ClutterModel(), ProportionalVelocityNoise(), rng=0)
    with pytest.raises(ValueError, match="sensor"):
        FastSLAM2(None, ClutterModel(), ProportionalVelocityNoise(), np.random.default_rng())


def test_methods_reject_bad_input():
    f = make_filter(n_particles=3)
    with pytest.raises(ValueError, match="dt"):
        f.predict([1.0, 0.0], -0.1)
    poses = f.poses
    f.predict([1.0, 0.0], 0.0)  # no time elapsed: no motion (a scan at the start pose)
    np.testing.assert_array_equal(f.poses, poses)
    with pytest.raises(ValueError, match="u"):
        f.predict([1.0, np.nan], 0.1)
    with pytest.raises(ValueError, match="z"):
        f.update([[np.nan, 0.0]])
    with pytest.raises(ValueError, match="associations"):
        f.update([[5.0, 0.0]], associations=[1, 2])
    with pytest.raises(ValueError, match="std_rad"):
        f.update_heading(0.0, 0.0)


# --------------------------------------------------------------------------- behaviour
def test_das_picks_the_right_association_for_nearly_all_particles():
    stream = make_stream("brooks-bailey", seed=0, n_steps=150, clutter_level=0)
    f = make_filter(stream, seed=0, n_particles=100)
    common_id: dict[int, int] = {}
    fractions, wrong_winners = [], 0

    def check(step):
        nonlocal wrong_winners
        assert len(f.last_associations) == len(step.z)
        for k, label in enumerate(step.truth.landmark_ids):
            label = int(label)
            if label not in common_id:
                common_id[label] = int(f.last_associations[k])
                continue
            fractions.append(np.mean(f.last_votes[k] == common_id[label]))
            wrong_winners += int(f.last_associations[k] != common_id[label])

    run(f, stream, every=check)
    assert len(fractions) > 300
    assert np.mean(fractions) > 0.95
    assert wrong_winners == 0
    assert len(set(common_id.values())) == len(common_id)  # one common id per landmark
    lm = f.landmarks()
    assert set(lm.ids[lm.existence > 0.95]) == set(common_id.values())


def test_clutter_does_not_create_confirmed_features():
    # the start of the square loop (no sharp first turn): the robot's own uncertainty stays
    # small, so a confirmed feature far from every landmark can only come from clutter
    stream = make_stream("brooks-bailey", seed=1, n_steps=200, clutter_level=3,
                         **SQUARE_LOOP_OVERRIDES)
    f = make_filter(stream, seed=1, n_particles=100)
    run(f, stream, every=lambda step: feature_covs_spd(f))
    lm = f.landmarks()
    confirmed = lm.existence > 0.95
    seen = {int(i) for step in stream for i in step.truth.landmark_ids if i >= 0}
    assert confirmed.sum() == len(seen)
    distance = np.linalg.norm(lm.means[:, None] - stream.landmarks_true[None], axis=2).min(1)
    assert distance[confirmed].max() < 1.0
    stats = f.local_statistics()
    assert 0.0 < stats["clutter_rate"] < 1.0
    assert stats["local_feature_count"] >= stats["local_confirmed_count"] == len(seen)


def test_known_association_fastslam2_is_consistent_on_short_runs():
    """ANEES over 20 runs of 100 iterations within the 95 % chi-square bound (known data
    association, 1000 particles, NEES from iteration 10 on: before that the particle cloud is
    degenerate because the robot starts with zero uncertainty and drives straight)."""
    runs, n_steps, skip = 20, 100, 10
    nees = np.zeros((runs, n_steps - skip))
    for seed in range(runs):
        stream = make_stream("brooks-bailey", seed=seed, n_steps=n_steps, clutter_level=0)
        f = make_filter(stream, seed=100 + seed, n_particles=1000)
        for step in stream:
            f.predict(step.odometry, step.dt_s)
            f.update(step.z, step.truth.landmark_ids)
            if step.index >= skip:
                mean, cov = f.pose()
                e = step.truth.pose - mean
                e[2] = wrap_angle(e[2])
                nees[seed, step.index - skip] = e @ np.linalg.solve(cov, e)
    bound = chi2.ppf(0.975, 3 * runs) / runs
    assert nees.mean() <= bound
    assert nees.mean() > chi2.ppf(0.025, 3 * runs) / runs  # not grossly pessimistic either


def test_seeded_determinism_bit_for_bit():
    stream = make_stream("brooks-bailey", seed=2, n_steps=60, clutter_level=2)

    slots_before_restart, slots_after_restart = [], []

    def episode(seed, capacity=16):
        f = make_filter(stream, seed=seed, n_particles=200, initial_capacity=capacity)
        out = []
        for step in stream:
            f.predict(step.odometry, step.dt_s)
            f.update(step.z)
            out.append(f.last_associations.copy())
            if step.index == 29:
                out.append(f.to_gaussian().P)
                slots_before_restart.append(f.capacity)
                f.restart()
                slots_after_restart.append(f.capacity)
        out += [f.poses, f.weights, f.means, f.covs, f.existence, f.correspondence_ids]
        return out

    a, b, c = episode(7), episode(7), episode(8)
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    # the capacity doubling, and its return at the restart, do not change the result
    d = episode(7, capacity=1)
    # (seeds 7, 7, 8 at 16 slots, then 7 at 1 slot): the slots grew, a restart gave them back
    assert slots_after_restart == [16, 16, 16, 1]
    assert slots_before_restart[3] > 1
    for x, y in zip(a[:-6], d[:-6], strict=True):  # every scan's associations, the fused map
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a[-6], d[-6])  # poses
    np.testing.assert_array_equal(a[-5], d[-5])  # weights
    assert not np.array_equal(a[-6], c[-6])


def test_to_gaussian_restart_and_local_statistics():
    stream = make_stream("brooks-bailey", seed=3, n_steps=80, clutter_level=1)
    ids = FeatureIds()
    f = make_filter(stream, seed=3, n_particles=150, ids=ids, feature_budget=40)
    run(f, stream)
    g = f.to_gaussian()
    assert_spd(g.P)
    lm = f.landmarks()
    assert set(g.ids) == set(lm.ids[lm.existence > 0.95]) and len(g.ids) > 0
    assert np.all(g.existence > 0.95)
    mean, cov = f.pose()
    np.testing.assert_allclose(g.x[:3], mean)
    np.testing.assert_allclose(g.P[:3, :3], cov, atol=1e-9)
    for i, fid in enumerate(g.ids):
        n = int(np.flatnonzero(lm.ids == fid)[0])
        np.testing.assert_allclose(g.x[3 + 2 * i: 5 + 2 * i], lm.means[n])
    stats = f.local_statistics()
    assert set(stats) == LOCAL_KEYS
    assert all(isinstance(v, float) and np.isfinite(v) for v in stats.values())
    assert stats["local_map_age_s"] == pytest.approx(8.0)
    assert stats["local_map_distance_m"] == pytest.approx(8.0, rel=0.05)
    assert 0.0 < stats["ess_ratio"] <= 1.0
    assert 0.0 <= stats["vote_margin"] <= 1.0
    assert stats["local_feature_count"] == len(lm)
    assert stats["local_map_budget_ratio"] == pytest.approx(len(lm) / 40)
    _, cloud_cov = pose_moments(f.poses, f.weights)  # the spreads are the cloud's own
    assert stats["particle_position_spread_m"] == pytest.approx(
        np.sqrt(cloud_cov[0, 0] + cloud_cov[1, 1]))

    f.restart()
    mean, cov = f.pose()
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(cov, 0.0)
    assert len(f.landmarks()) == 0 and not f.active.any()
    g = f.to_gaussian()
    assert g.x.shape == (3,) and g.n_features == 0
    assert_spd(g.P)  # the zero pose block is lifted to the eigenvalue floor
    stats = f.local_statistics()
    assert stats["local_map_age_s"] == 0.0 and stats["local_feature_count"] == 0.0
    # ids keep coming from the shared source after a restart
    before = int(ids.new(1)[0])
    step = next(iter(stream))
    f.predict(step.odometry, step.dt_s)
    f.update(step.z)
    assert np.all(f.last_associations[f.last_associations >= 0] > before)


def test_landmark_count_is_the_number_of_landmarks_at_every_step():
    """landmark_count (what a fusion reports without forming the moments) equals
    len(landmarks()) through a cluttered run, before and after updates, and at zero."""
    stream = make_stream("brooks-bailey", seed=4, n_steps=60, clutter_level=3)
    f = make_filter(stream, seed=4, n_particles=60)
    assert f.landmark_count() == len(f.landmarks()) == 0
    counts = []

    def check(_step):
        counts.append(f.landmark_count())
        assert counts[-1] == len(f.landmarks())

    run(f, stream, every=check)
    assert max(counts) > 0 and len(set(counts)) > 1


def test_pending_proposal_is_part_of_pose_and_conversion():
    f = make_filter(n_particles=50)
    f.predict([1.0, 0.5], 0.1)
    mean, cov = f.pose()  # all particles share the proposal: cov = J Q J^T
    Q = f.odometry_noise.covariance(np.array([1.0, 0.5]), 0.1)
    _, J = motion_jacobians(np.zeros(3), [1.0, 0.5], 0.1)
    np.testing.assert_allclose(cov, J @ Q @ J.T, atol=1e-15)
    np.testing.assert_allclose(f.to_gaussian().P, cov, atol=2e-10)  # + eigenvalue floor
    f.update(np.zeros((0, 2)))  # no observations: the pose is drawn from the motion model
    _, cov_sampled = f.pose()
    assert np.trace(cov_sampled) > 0.0
    assert f.last_associations.shape == (0,)


def test_compass_before_update_refines_the_proposal():
    sensor, clutter = RangeBearingSensor(), ClutterModel()
    noise = ProportionalVelocityNoise()
    f = FastSLAM2(sensor, clutter, noise, np.random.default_rng(5), n_particles=2000)
    g = FastSLAM2(sensor, clutter, noise, np.random.default_rng(5), n_particles=2000)
    u = np.array([1.0, 1.5])  # heading std of the motion noise: 0.35 * 1.5 * 0.1 = 0.0525
    for filt in (f, g):
        filt.predict(u, 0.1)
    f.update_heading(0.2, 0.005)  # compass during the pending proposal: proposal correction
    f.update(np.zeros((0, 2)))
    g.update(np.zeros((0, 2)))
    g.update_heading(0.2, 0.005)  # after sampling: weights only
    mean_f, cov_f = f.pose()
    _, cov_g = g.pose()
    heading_std = np.sqrt(0.0525**2 * 0.005**2 / (0.0525**2 + 0.005**2))
    assert np.sqrt(cov_f[2, 2]) == pytest.approx(heading_std, rel=0.1)
    expected_mean = 0.15 + (0.2 - 0.15) * 0.0525**2 / (0.0525**2 + 0.005**2)
    assert mean_f[2] == pytest.approx(expected_mean, abs=3 * heading_std / np.sqrt(2000) + 1e-3)
    assert f.local_statistics()["ess_ratio"] > 0.99  # the proposal leaves the weights even
    assert g.local_statistics()["ess_ratio"] < 0.5  # reweighting alone degenerates
    assert np.sqrt(cov_g[2, 2]) < 0.02


def test_unconfirmed_feature_decays_and_is_culled():
    # alpha = 0.5, beta = 0.3: a new feature at 5 m starts at L_new / (L_new + L_clutter) ~ 0.7
    # and every miss halves its odds.
    sensor = RangeBearingSensor()
    clutter = ClutterModel(alpha=0.5, beta=0.3)
    f = FastSLAM2(sensor, clutter, ProportionalVelocityNoise(0.0, 0.0, 1e-3, 1e-3),
                  np.random.default_rng(0), n_particles=20, cull_interval_steps=1)
    f.predict([0.0, 0.0], 0.1)
    f.update([[5.0, 0.3]])
    assert f.active.sum(axis=1).max() == 1  # created (as a new feature) or taken for clutter
    p0 = f.existence[f.active]
    assert len(p0) > 0 and np.all(p0 < 0.95)
    history = []
    for _ in range(12):
        f.predict([0.0, 0.0], 0.1)
        f.update(np.zeros((0, 2)))
        history.append(f.existence[f.active].max() if f.active.any() else 0.0)
    assert all(b <= a for a, b in zip(history, history[1:], strict=False))
    assert not f.active.any()  # culled
    assert len(f.landmarks()) == 0


def test_repeated_detection_confirms_and_votes_agree():
    sensor = RangeBearingSensor()
    clutter = ClutterModel(alpha=0.9, beta=0.05)
    f = FastSLAM2(sensor, clutter, ProportionalVelocityNoise(0.0, 0.0, 1e-3, 1e-3),
                  np.random.default_rng(1), n_particles=50)
    rng = np.random.default_rng(2)
    winners = []
    for _ in range(5):
        f.predict([0.0, 0.0], 0.1)
        z = observe(np.zeros(3), np.array([[8.0, 3.0], [-4.0, 9.0]]))
        f.update(z + rng.normal(size=z.shape) * [0.05, 0.017])
        winners.append(f.last_associations.copy())
        assert np.all(np.isin(f.last_votes, [CLUTTER_VOTE, NEW_VOTE]) | (f.last_votes >= 0))
    assert np.all(winners[-1] >= 0) and np.array_equal(winners[-1], winners[-2])
    lm = f.landmarks()
    confirmed = lm.ids[lm.existence > 0.95]
    assert set(confirmed) == set(winners[-1])
    assert f.local_statistics()["vote_margin"] > 0.9
    feature_covs_spd(f)


def _place_features(f, positions, cids, existence=0.999, var=0.01):
    """Give every particle the features ``positions`` (list per particle) by hand."""
    f._grow(max(len(p) for p in positions))
    s = f._state
    for p, feats in enumerate(positions):
        for slot, (x, y) in enumerate(feats):
            s.mx[p, slot], s.my[p, slot] = x, y
            s.sxx[p, slot], s.sxy[p, slot], s.syy[p, slot] = var, 0.0, var
            s.ex[p, slot], s.active[p, slot], s.cid[p, slot] = existence, True, cids[p][slot]
        s.count[p] = len(feats)


def test_duplicate_features_are_not_rewarded():
    # Particle 0 maps the landmark once, particle 1 twice (a duplicate). One observation of
    # it: particle 1 fails to detect one of its two features, and the missed-detection term
    # (1 - alpha e p_vis ~ 0.011) must outweigh the second feature's extra likelihood.
    f = make_filter(n_particles=2, resample_threshold=0.0)
    _place_features(f, [[(10.0, 0.0)], [(10.0, 0.0), (10.0, 0.0)]], [[0], [0, 0]])
    f.update([[10.0, 0.0]])
    w = f.weights
    assert w[1] < 0.05 * w[0]
    assert f.existence[1, :2].min() < 0.95  # the undetected duplicate is no longer confirmed


def _duplicate_ids(f):
    """(particle, id) pairs held by more than one active feature of the particle."""
    cids, active = f.correspondence_ids, f.active
    out = []
    for p in range(f.n_particles):
        values, counts = np.unique(cids[p][active[p] & (cids[p] >= 0)], return_counts=True)
        out += [(p, int(v)) for v in values[counts > 1]]
    return out


def test_minority_particle_does_not_get_a_second_feature_with_the_winning_id():
    # Particles 0-2 map the landmark at (10, 0) as id 0. Particle 3 holds id 0 at (10, 4) (its
    # own, different, hypothesis) and nothing at (10, 0), so it starts a new feature for the
    # observation. The vote goes to id 0; BB's rule taken literally would give particle 3 two
    # features called 0 (and the common map would drop one of them).
    f = make_filter(n_particles=4, resample_threshold=0.0)
    _place_features(f, [[(10.0, 0.0)]] * 3 + [[(10.0, 4.0)]], [[0]] * 4)
    f.update([[10.0, 0.0]])
    assert f.last_associations[0] == 0
    assert f.correspondence_ids[3, :2].tolist() == [0, -1]
    assert f.active[3, :2].all()
    assert _duplicate_ids(f) == []


def test_correspondence_ids_stay_unique_within_every_particle_in_dense_clutter():
    # Dense landmarks, a poor sensor and clutter: many ambiguous associations and split votes.
    stream = make_stream(
        "brooks-bailey", seed=4, n_steps=150, clutter_level=2, world_size_m=40.0,
        path_length_m=100.0, waypoint_spacing_m=8.0, path_perturbation_m=1.0,
        n_landmarks=200, range_std_m=0.4, bearing_std_rad=np.deg2rad(4.0), max_range_m=8.0,
    )
    f = make_filter(stream, seed=4, n_particles=100)
    split_votes = 0

    def check(step):
        nonlocal split_votes
        assert _duplicate_ids(f) == []
        split_votes += int(sum(len(np.unique(v)) > 1 for v in f.last_votes))

    run(f, stream, every=check)
    assert split_votes > 50  # the votes really were contested


def test_visibility_is_soft_at_the_range_limit():
    f = make_filter(n_particles=1)
    _place_features(f, [[(24.9, 0.0), (25.0, 0.0), (25.1, 0.0), (5.0, 0.0), (40.0, 0.0)]],
                    [[0, 1, 2, 3, 4]], var=0.01)
    Pc = np.zeros((3, 3))
    s = f._state
    p_vis = [
        kernel._visibility(s.mx[0, j], s.my[0, j], 0.0, s.sxx[0, j] + Pc[0, 0],
                           s.sxy[0, j] + Pc[0, 1], s.syy[0, j] + Pc[1, 1], f.sensor.max_range_m,
                           f.sensor.fov_rad)
        for j in range(5)
    ]
    sigma = 0.1  # radial std of a feature with covariance 0.01 I, pose known
    np.testing.assert_allclose(
        p_vis[:3], [0.5 * (1 + math.erf(d / sigma / np.sqrt(2))) for d in (0.1, 0.0, -0.1)]
    )
    assert p_vis[3] == 1.0 and p_vis[4] == 0.0


def test_existence_model_bb_uses_beta_literally():
    """BB (11) as written (P_fa = beta): a detection at alpha 0.3, beta 0.2 multiplies the odds
    of existence by 1.5 in every particle; the gate model confirms faster."""
    sensor = RangeBearingSensor()
    clutter = ClutterModel(alpha=0.3, beta=0.2)
    noise = ProportionalVelocityNoise(0.0, 0.0, 1e-3, 1e-3)
    existence = {}
    for model in ("bb", "gate"):
        f = FastSLAM2(sensor, clutter, noise, np.random.default_rng(1), n_particles=20,
                      existence_model=model)
        z = observe(np.zeros(3), np.array([[8.0, 3.0]]))
        f.predict([0.0, 0.0], 0.1)
        f.update(z)
        first = f.existence[:, 0]
        f.predict([0.0, 0.0], 0.1)
        f.update(z)
        existence[model] = (first, f.existence[:, 0])
    first_bb, second_bb = existence["bb"]
    # the first detection creates the feature; the second updates it by BB (11) with beta
    from filters.existence import detection_update

    held = first_bb > 0.0  # particles that started the feature at the first scan
    assert held.sum() >= 10 and np.all(first_bb < 0.9)
    np.testing.assert_allclose(
        second_bb[held], detection_update(first_bb[held], 0.3, 0.2), rtol=1e-9
    )
    first_gate, second_gate = existence["gate"]
    both = held & (first_gate > 0.0)
    assert both.any() and np.all(second_gate[both] > second_bb[both] + 0.05)
    with pytest.raises(ValueError, match="existence_model"):
        FastSLAM2(sensor, clutter, noise, np.random.default_rng(1), existence_model="x")


def test_unexplained_observation_is_a_new_feature_whose_existence_carries_clutter():
    """#14 (2): no particle draws *clutter* for an unexplained observation; every one starts the
    feature with existence L_new / (L_new + L_clutter), so the weights stay even and the clutter
    share is 1 - that existence. ``sample_clutter=True`` keeps the earlier draw."""
    sensor = RangeBearingSensor()
    clutter = ClutterModel(alpha=0.5, beta=0.3)
    noise = ProportionalVelocityNoise(0.0, 0.0, 1e-3, 1e-3)
    f = FastSLAM2(sensor, clutter, noise, np.random.default_rng(0), n_particles=200)
    f.predict([0.0, 0.0], 0.1)
    f.update([[5.0, 0.3]])
    assert np.all(f.active.sum(axis=1) == 1)
    e = f.existence[f.active]
    assert np.all(e < 0.95) and np.ptp(e) == 0.0
    assert np.ptp(f.weights) < 1e-12
    assert np.all(f.last_votes == NEW_VOTE)
    assert f.local_statistics()["clutter_rate"] == pytest.approx(1.0 - e[0])
    g = FastSLAM2(sensor, clutter, noise, np.random.default_rng(0), n_particles=200,
                  sample_clutter=True)
    g.predict([0.0, 0.0], 0.1)
    g.update([[5.0, 0.3]])
    taken = g.active.sum(axis=1)
    assert 0 < taken.sum() < 200  # some particles drew clutter
    assert np.all(g.last_votes[0, taken == 0] == CLUTTER_VOTE)
    with pytest.raises(ValueError, match="sample_clutter"):
        FastSLAM2(sensor, clutter, noise, np.random.default_rng(0), sample_clutter="yes")


def test_lineage_correction_only_adds_uncertainty_and_restarts_with_the_local_map():
    """#14 (2): the lineage term widens the pose and map Gaussians of a cloud that resampled
    (same particles, same means); after a restart every particle is its own lineage again."""
    stream = make_stream("brooks-bailey", seed=2, n_steps=150, clutter_level=1)
    with_term = run(make_filter(stream, seed=2, n_particles=200), stream)
    without = run(make_filter(stream, seed=2, n_particles=200, lineage_correction=False), stream)
    np.testing.assert_array_equal(with_term.poses, without.poses)  # filtering is unchanged
    assert len(np.unique(with_term.lineages)) < 100  # resampled: shared ancestors
    g1, g0 = with_term.to_gaussian(), without.to_gaussian()
    np.testing.assert_array_equal(g1.x, g0.x)
    extra = g1.P - g0.P
    assert np.linalg.eigvalsh(extra).min() > -1e-12 and np.trace(extra[:3, :3]) > 0.0
    assert_spd(g1.P)
    np.testing.assert_allclose(g1.P[:3, :3], with_term.pose()[1], atol=1e-9)
    # pose() is cached per step, but not across a change of the flags
    with_term.small_sample_correction = False
    lineage_only = pose_moments(with_term.poses, with_term.weights,
                                lineages=with_term.lineages)[1]
    np.testing.assert_allclose(with_term.pose()[1], lineage_only, atol=1e-12)
    assert np.trace(lineage_only) < np.trace(g1.P[:3, :3])
    with_term.small_sample_correction = True
    assert with_term.local_statistics() == without.local_statistics()

    with_term.restart()
    np.testing.assert_array_equal(with_term.lineages, np.arange(200))
    with_term.predict([1.0, 0.2], 0.1)
    with_term.update(np.zeros((0, 2)))
    _, spread = pose_moments(with_term.poses, with_term.weights)
    # independent, equally weighted particles: the term is 2 / (P - 1) of the spread, and the
    # small-sample factor nu / (nu - p - 1) has nu = P - 1; one step after the restart the
    # poses lie on a curve (rank p = 2): 199 / 196
    assert np.linalg.matrix_rank(spread, hermitian=True) == 2
    np.testing.assert_allclose(with_term.pose()[1], spread * (1 + 2 / 199) * 199 / 196,
                               rtol=1e-9)


@pytest.mark.parametrize("max_existence", [0.999, LOCAL_MAP_MAX_EXISTENCE])
def test_existence_clip_is_a_memory_limit_and_the_front_end_guard_still_decays(max_existence):
    """A landmark detected in 20 steps at alpha = 0.1 (Victoria Park's per-step rate), then in
    view but missed: at the 0.999 clip it is un-confirmed after about 36 misses (evidence of the
    20 detections forgotten); at the front-end's float guard it stays confirmed for 100 misses,
    and it is still un-confirmable: enough misses take it below 0.95."""
    sensor = RangeBearingSensor()
    clutter = ClutterModel(alpha=0.1, beta=0.01)
    f = FastSLAM2(sensor, clutter, ProportionalVelocityNoise(0.0, 0.0, 1e-4, 1e-4),
                  np.random.default_rng(4), n_particles=20, max_existence=max_existence)
    landmark = np.array([[8.0, 2.0]])
    for _ in range(20):
        f.predict([0.0, 0.0], 0.1)
        f.update(observe(f.pose()[0], landmark))
    assert f.existence[f.active].min() > 0.95
    misses_to_unconfirm = None
    for k in range(1, 2001):
        f.predict([0.0, 0.0], 0.1)
        f.update(np.zeros((0, 2)))
        if f.landmarks().existence.max(initial=0.0) < 0.95:
            misses_to_unconfirm = k
            break
    assert misses_to_unconfirm is not None  # never stuck at 1
    if max_existence == 0.999:
        assert 30 <= misses_to_unconfirm <= 45
    else:
        assert misses_to_unconfirm > 100
