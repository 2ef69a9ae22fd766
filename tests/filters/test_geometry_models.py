"""Every Jacobian of filters.geometry and filters.models against central finite differences."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from filters import geometry as g
from filters import models as m

coord = st.floats(-50.0, 50.0, allow_nan=False)
angle = st.floats(-np.pi + 1e-3, np.pi - 1e-3, allow_nan=False)
pose_st = st.tuples(coord, coord, angle).map(np.array)
point_st = st.tuples(coord, coord).map(np.array)


def numeric_jacobian(f, x, eps=1e-6, wrap_rows=()):
    x = np.asarray(x, dtype=float)
    f0 = np.asarray(f(x))
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        diff = np.asarray(f(x + dx)) - np.asarray(f(x - dx))
        for r in wrap_rows:
            diff[r] = g.wrap_angle(diff[r])
        J[:, i] = diff / (2 * eps)
    return J


def assert_jacobian(analytic, f, x, wrap_rows=(), atol=1e-5):
    numeric = numeric_jacobian(f, x, wrap_rows=wrap_rows)
    np.testing.assert_allclose(analytic, numeric, atol=atol, rtol=1e-5)


@settings(max_examples=60, deadline=None)
@given(pose_st, pose_st)
def test_compose_jacobians(a, b):
    J_a, J_b = g.compose_jacobians(a, b)
    assert_jacobian(J_a, lambda x: g.compose(x, b), a, wrap_rows=(2,))
    assert_jacobian(J_b, lambda x: g.compose(a, x), b, wrap_rows=(2,))


@settings(max_examples=60, deadline=None)
@given(pose_st)
def test_inverse_jacobian_and_identity(a):
    assert_jacobian(g.inverse_jacobian(a), g.inverse, a, wrap_rows=(2,))
    np.testing.assert_allclose(g.compose(a, g.inverse(a)), np.zeros(3), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(pose_st, pose_st)
def test_relative_jacobians_and_consistency(a, b):
    J_a, J_b = g.relative_jacobians(a, b)
    assert_jacobian(J_a, lambda x: g.relative(x, b), a, wrap_rows=(2,))
    assert_jacobian(J_b, lambda x: g.relative(a, x), b, wrap_rows=(2,))
    back = g.compose(a, g.relative(a, b))
    np.testing.assert_allclose(back[:2], b[:2], atol=1e-9)
    assert abs(g.wrap_angle(back[2] - b[2])) < 1e-9


@settings(max_examples=60, deadline=None)
@given(pose_st, point_st)
def test_point_transforms(pose, p):
    J_pose, J_p = g.transform_point_jacobians(pose, p)
    assert_jacobian(J_pose, lambda x: g.transform_point(x, p), pose)
    assert_jacobian(J_p, lambda x: g.transform_point(pose, x), p)
    J_pose, J_p = g.point_to_frame_jacobians(pose, p)
    assert_jacobian(J_pose, lambda x: g.point_to_frame(x, p), pose)
    assert_jacobian(J_p, lambda x: g.point_to_frame(pose, x), p)
    np.testing.assert_allclose(g.point_to_frame(pose, g.transform_point(pose, p)), p, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(pose_st, st.floats(0.0, 3.0), st.floats(-1.8, 1.8), st.floats(0.01, 0.5))
def test_motion_jacobians(pose, v, w, dt):
    u = np.array([v, w])
    J_pose, J_u = m.motion_jacobians(pose, u, dt)
    assert_jacobian(J_pose, lambda x: m.motion(x, u, dt), pose, wrap_rows=(2,))
    assert_jacobian(J_u, lambda x: m.motion(pose, x, dt), u, wrap_rows=(2,))
    np.testing.assert_allclose(
        m.motion(pose, u, dt), g.compose(pose, m.motion_increment(u, dt)), atol=1e-9
    )


@settings(max_examples=60, deadline=None)
@given(pose_st, st.floats(0.5, 30.0), angle)
def test_observation_jacobians_and_inverse(pose, rng_m, bearing):
    z = np.array([rng_m, bearing])
    point = m.inverse_observe(pose, z)
    np.testing.assert_allclose(m.innovation(m.observe(pose, point), z), 0.0, atol=1e-9)
    H_pose, H_m = m.observe_jacobians(pose, point)
    assert_jacobian(H_pose, lambda x: m.observe(x, point), pose, wrap_rows=(1,))
    assert_jacobian(H_m, lambda x: m.observe(pose, x), point, wrap_rows=(1,))
    G_pose, G_z = m.inverse_observe_jacobians(pose, z)
    assert_jacobian(G_pose, lambda x: m.inverse_observe(x, z), pose)
    assert_jacobian(G_z, lambda x: m.inverse_observe(pose, x), z)


def test_observation_broadcasts_over_particles():
    rng = np.random.default_rng(0)
    poses = rng.normal(size=(7, 3))
    points = rng.normal(size=(7, 5, 2)) * 10
    z = m.observe(poses[:, None, :], points)
    H_pose, H_m = m.observe_jacobians(poses[:, None, :], points)
    assert z.shape == (7, 5, 2) and H_pose.shape == (7, 5, 2, 3) and H_m.shape == (7, 5, 2, 2)
    np.testing.assert_allclose(z[3, 2], m.observe(poses[3], points[3, 2]))
    np.testing.assert_allclose(H_m[3, 2], m.observe_jacobians(poses[3], points[3, 2])[1])


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 1001)
    w = g.wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    assert g.wrap_angle(np.pi) == pytest.approx(-np.pi)


def test_compiled_wrap_equals_wrap_angle_to_the_bit():
    """wrap_angle_one's shortcuts around fmod give wrap_angle's bits, at the branch edges too."""
    two_pi = 2.0 * np.pi
    edges = [0.0, -0.0, np.pi, -np.pi, two_pi, -two_pi, 3 * np.pi, -3 * np.pi, 2 * two_pi, 1e-300,
             -1e-300, 5e-324, np.pi + 1e-15, -np.pi - 1e-15, 3 * np.pi - 1e-15, 1e6, -1e6]
    near = [np.nextafter(e, d) for e in edges for d in (-np.inf, np.inf)]
    rng = np.random.default_rng(0)
    angles = np.concatenate([edges, near, rng.uniform(-4 * np.pi, 4 * np.pi, 20_000),
                             rng.uniform(-1e4, 1e4, 2_000), [np.inf, -np.inf, np.nan]])
    compiled = np.array([g.wrap_angle_one(float(a)) for a in angles])
    reference = g.wrap_angle(angles)
    finite = np.isfinite(angles)
    assert np.array_equal(compiled[finite].view(np.int64), reference[finite].view(np.int64))
    assert np.all(np.isnan(compiled[~finite])) and np.all(np.isnan(reference[~finite]))


def test_chong_kleeman_covariance_matches_wheel_sampling():
    """CM (14): the (v, omega) covariance equals the sample covariance of noisy wheel travels."""
    noise = m.ChongKleemanNoise(k_m=1e-3, wheel_base_m=0.5)
    u, dt = np.array([1.0, 0.4]), 0.1
    travel = noise.wheel_travel(u, dt)
    rng = np.random.default_rng(1)
    samples = travel + rng.standard_normal((200_000, 2)) * np.sqrt(noise.wheel_variance(travel))
    vel = noise.velocities(samples, dt)
    np.testing.assert_allclose(vel.mean(axis=0), u, atol=2e-3)
    np.testing.assert_allclose(np.cov(vel.T), noise.covariance(u, dt), rtol=0.02)


def test_proportional_noise_std():
    noise = m.ProportionalVelocityNoise(0.25, 0.35)
    np.testing.assert_allclose(
        noise.covariance(np.array([2.0, -1.0]), 0.1), np.diag([0.25, 0.35**2])
    )


@pytest.mark.parametrize(
    "factory, field",
    [
        (lambda: m.ClutterModel(alpha=0.0), "alpha"),
        (lambda: m.ClutterModel(beta=1.0), "beta"),
        (lambda: m.RangeBearingSensor(max_range_m=-1.0), "max_range_m"),
        (lambda: m.RangeBearingSensor(fov_rad=7.0), "fov_rad"),
        (lambda: m.ProportionalVelocityNoise(v_fraction=-0.1), "v_fraction"),
        (lambda: m.ChongKleemanNoise(wheel_base_m=0.0), "wheel_base_m"),
        (lambda: m.ClutterModel(alpha=float("nan")), "alpha"),
    ],
)
def test_bad_model_values_name_the_field(factory, field):
    with pytest.raises(ValueError, match=field):
        factory()


def test_motion_jacobians_broadcast_over_particles():
    rng = np.random.default_rng(2)
    poses = rng.normal(size=(6, 3))
    u, dt = np.array([1.2, 0.4]), 0.1
    J_pose, J_u = m.motion_jacobians(poses, u, dt)
    assert J_pose.shape == (6, 3, 3) and J_u.shape == (6, 3, 2)
    for p in range(6):
        single_pose, single_u = m.motion_jacobians(poses[p], u, dt)
        assert_jacobian(single_pose, lambda x, p=p: m.motion(x, u, dt), poses[p], wrap_rows=(2,))
        np.testing.assert_array_equal(J_pose[p], single_pose)
        np.testing.assert_array_equal(J_u[p], single_u)
