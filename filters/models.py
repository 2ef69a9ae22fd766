"""Motion, odometry-noise and range-bearing observation models with their Jacobians.

* Unicycle velocity model with a mid-point heading: a pose moves by ``v dt`` along the heading
  at the middle of the interval and turns by ``omega dt``. The simulator and every filter use the
  same model, so the only model error a filter sees is linearisation.
* Odometry noise: :class:`ProportionalVelocityNoise` (BB 5.2: std ``0.25 v`` and ``0.35 |omega|``)
  and :class:`ChongKleemanNoise` (CM (14): each wheel's travel has variance ``K |delta rho|``).
  Both give the covariance of the measured ``(v, omega)`` over an interval ``dt``.
* Range-bearing sensor: ``h(pose, m) = (|m - p|, atan2(dy, dx) - theta)`` and its inverse
  ``g(pose, z)``. :class:`RangeBearingSensor` holds its noise, range and field of view;
  :class:`ClutterModel` holds the reliability ``(alpha, beta)`` of BB 5.1.
All functions broadcast over leading axes where noted, so particle filters call them once for all
particles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from filters.geometry import wrap_angle
from filters.validation import check_range


# --------------------------------------------------------------------------- motion model
def motion(pose, u, dt):
    """Unicycle mid-point model: pose (..., 3), u = (v, omega) (..., 2), dt in seconds."""
    pose = np.asarray(pose, dtype=float)
    u = np.asarray(u, dtype=float)
    v, w = u[..., 0], u[..., 1]
    heading = pose[..., 2] + 0.5 * w * dt
    out = np.empty(np.broadcast_shapes(pose.shape, u.shape[:-1] + (3,)))
    out[..., 0] = pose[..., 0] + v * dt * np.cos(heading)
    out[..., 1] = pose[..., 1] + v * dt * np.sin(heading)
    out[..., 2] = wrap_angle(pose[..., 2] + w * dt)
    return out


def motion_jacobians(pose, u, dt):
    """Jacobians of :func:`motion` w.r.t. the pose (..., 3, 3) and the controls (..., 3, 2).

    Broadcasts over leading axes (e.g. one pose per particle).
    """
    pose = np.asarray(pose, dtype=float)
    u = np.asarray(u, dtype=float)
    v, w = u[..., 0], u[..., 1]
    heading = pose[..., 2] + 0.5 * w * dt
    c, s = np.cos(heading), np.sin(heading)
    shape = np.broadcast_shapes(pose.shape[:-1], u.shape[:-1])
    J_pose = np.zeros(shape + (3, 3))
    J_pose[..., 0, 0] = J_pose[..., 1, 1] = J_pose[..., 2, 2] = 1.0
    J_pose[..., 0, 2] = -v * dt * s
    J_pose[..., 1, 2] = v * dt * c
    J_u = np.zeros(shape + (3, 2))
    J_u[..., 0, 0] = dt * c
    J_u[..., 0, 1] = -0.5 * v * dt * dt * s
    J_u[..., 1, 0] = dt * s
    J_u[..., 1, 1] = 0.5 * v * dt * dt * c
    J_u[..., 2, 1] = dt
    return J_pose, J_u


def motion_increment(u, dt):
    """The pose increment of one :func:`motion` step in the robot's own frame (CM (8), (9))."""
    return motion(np.zeros(3), u, dt)


# --------------------------------------------------------------------------- odometry noise
@dataclass(frozen=True)
class ProportionalVelocityNoise:
    """BB 5.2: std of v is ``v_fraction |v|``, std of omega is ``omega_fraction |omega|``.

    ``v_floor_mps`` and ``omega_floor_radps`` add a small constant std so that the covariance is
    never singular when the robot stands still or drives straight (documented deviation; the
    simulator draws its noise from the same model, so the filters stay consistent).
    """

    v_fraction: float = 0.25
    omega_fraction: float = 0.35
    v_floor_mps: float = 0.0
    omega_floor_radps: float = 0.0

    def __post_init__(self):
        check_range("v_fraction", self.v_fraction, 0.0, 5.0)
        check_range("omega_fraction", self.omega_fraction, 0.0, 5.0)
        check_range("v_floor_mps", self.v_floor_mps, 0.0, 10.0)
        check_range("omega_floor_radps", self.omega_floor_radps, 0.0, 10.0)

    def std(self, u):
        """Per-component std (..., 2) of the velocity noise for velocities u (..., 2)."""
        u = np.asarray(u, dtype=float)
        if u.shape == (2,):  # one velocity (the filters' prediction): scalar calls are faster
            return np.array([np.hypot(self.v_fraction * u[0], self.v_floor_mps),
                             np.hypot(self.omega_fraction * u[1], self.omega_floor_radps)])
        out = np.empty(u.shape)
        out[..., 0] = np.hypot(self.v_fraction * u[..., 0], self.v_floor_mps)
        out[..., 1] = np.hypot(self.omega_fraction * u[..., 1], self.omega_floor_radps)
        return out

    def covariance(self, u, dt):
        """Covariance (2, 2) of the measured (v, omega) over an interval of ``dt`` seconds."""
        del dt
        sv, sw = self.std(u)
        return np.array([[sv * sv, 0.0], [0.0, sw * sw]])


@dataclass(frozen=True)
class ChongKleemanNoise:
    """CM (14): each wheel's measured travel is the true travel plus N(0, K |travel|).

    The robot is differential drive with wheel base ``wheel_base_m``. Converting the wheel
    travels (rho_R, rho_L) to (v, omega) = ((rho_R + rho_L) / 2, (rho_R - rho_L) / b) / dt gives
    the covariance below; ``floor_m`` adds a small travel so the covariance stays regular at rest.
    """

    k_m: float = 1e-5
    wheel_base_m: float = 0.5
    floor_m: float = 1e-4

    def __post_init__(self):
        check_range("k_m", self.k_m, 0.0, 1.0)
        check_range("wheel_base_m", self.wheel_base_m, 0.01, 10.0)
        check_range("floor_m", self.floor_m, 0.0, 1.0)

    def wheel_travel(self, u, dt):
        """(right, left) wheel travel (..., 2) in metres for velocities u over dt."""
        u = np.asarray(u, dtype=float)
        half = 0.5 * self.wheel_base_m * u[..., 1]
        return np.stack([(u[..., 0] + half) * dt, (u[..., 0] - half) * dt], axis=-1)

    def velocities(self, wheel_travel, dt):
        """(v, omega) (..., 2) from (right, left) wheel travel over dt."""
        wheel_travel = np.asarray(wheel_travel, dtype=float)
        r, l_ = wheel_travel[..., 0], wheel_travel[..., 1]
        return np.stack([0.5 * (r + l_) / dt, (r - l_) / (self.wheel_base_m * dt)], axis=-1)

    def wheel_variance(self, wheel_travel):
        """Variance (..., 2) of each wheel's measured travel, CM (14)."""
        return self.k_m * (np.abs(np.asarray(wheel_travel, dtype=float)) + self.floor_m)

    def covariance(self, u, dt):
        """Covariance (2, 2) of the measured (v, omega) over an interval of ``dt`` seconds."""
        var_r, var_l = self.wheel_variance(self.wheel_travel(u, dt))
        b = self.wheel_base_m
        A = np.array([[0.5 / dt, 0.5 / dt], [1.0 / (b * dt), -1.0 / (b * dt)]])
        return A @ np.diag([var_r, var_l]) @ A.T


# --------------------------------------------------------------------------- sensor
@dataclass(frozen=True)
class RangeBearingSensor:
    """A range-bearing sensor: noise std, maximum range and field of view (centred ahead)."""

    range_std_m: float = 0.05
    bearing_std_rad: float = float(np.deg2rad(1.0))
    max_range_m: float = 25.0
    fov_rad: float = 2.0 * np.pi

    def __post_init__(self):
        check_range("range_std_m", self.range_std_m, 0.0, 10.0, low_open=True)
        check_range("bearing_std_rad", self.bearing_std_rad, 0.0, 1.0, low_open=True)
        check_range("max_range_m", self.max_range_m, 0.0, 1000.0, low_open=True)
        check_range("fov_rad", self.fov_rad, 0.0, 2.0 * np.pi, low_open=True)

    @property
    def R(self):
        """Observation noise covariance (2, 2) of (range, bearing)."""
        return np.diag([self.range_std_m**2, self.bearing_std_rad**2])

    def in_view(self, z):
        """Whether range-bearing pairs (..., 2) lie inside range and field of view."""
        z = np.asarray(z, dtype=float)
        inside_range = z[..., 0] <= self.max_range_m
        if self.fov_rad >= 2.0 * np.pi:
            return inside_range
        return inside_range & (np.abs(wrap_angle(z[..., 1])) <= 0.5 * self.fov_rad)

    @property
    def field_area_m2(self):
        """Area of the sensor's field of view (a disc sector) in m^2."""
        return 0.5 * self.fov_rad * self.max_range_m**2


@dataclass(frozen=True)
class ClutterModel:
    """Sensor reliability of BB 5.1.

    ``alpha``: probability of detecting a visible landmark. ``beta``: probability that a visible
    landmark triggers one false alarm, uniform in range [0, max range] and in bearing over the
    field of view.
    """

    alpha: float = 1.0
    beta: float = 0.0

    def __post_init__(self):
        check_range("alpha", self.alpha, 0.0, 1.0, low_open=True)
        check_range("beta", self.beta, 0.0, 1.0, high_open=True)


def observe(pose, m):
    """Range-bearing observation of points m (..., 2) from poses (..., 3): (..., 2)."""
    pose = np.asarray(pose, dtype=float)
    m = np.asarray(m, dtype=float)
    dx = m[..., 0] - pose[..., 0]
    dy = m[..., 1] - pose[..., 1]
    out = np.empty(dx.shape + (2,))  # the broadcast shape of the poses and the points
    out[..., 0] = np.hypot(dx, dy)
    out[..., 1] = wrap_angle(np.arctan2(dy, dx) - pose[..., 2])
    return out


def observe_jacobians(pose, m):
    """Jacobians of :func:`observe` w.r.t. pose (..., 2, 3) and point (..., 2, 2); broadcasts."""
    pose = np.asarray(pose, dtype=float)
    m = np.asarray(m, dtype=float)
    dx = m[..., 0] - pose[..., 0]
    dy = m[..., 1] - pose[..., 1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    shape = dx.shape  # the broadcast shape of the poses and the points
    H_m = np.empty(shape + (2, 2))
    H_m[..., 0, 0] = dx / r
    H_m[..., 0, 1] = dy / r
    H_m[..., 1, 0] = -dy / q
    H_m[..., 1, 1] = dx / q
    H_pose = np.empty(shape + (2, 3))
    H_pose[..., :, :2] = -H_m
    H_pose[..., 0, 2] = 0.0
    H_pose[..., 1, 2] = -1.0
    return H_pose, H_m


def inverse_observe(pose, z):
    """Point (..., 2) seen at range-bearing z (..., 2) from pose (..., 3)."""
    pose = np.asarray(pose, dtype=float)
    z = np.asarray(z, dtype=float)
    angle = pose[..., 2] + z[..., 1]
    out = np.empty(angle.shape + (2,))  # the broadcast shape of the poses and the observations
    out[..., 0] = pose[..., 0] + z[..., 0] * np.cos(angle)
    out[..., 1] = pose[..., 1] + z[..., 0] * np.sin(angle)
    return out


def inverse_observe_jacobians(pose, z):
    """Jacobians of :func:`inverse_observe` w.r.t. pose (..., 2, 3) and z (..., 2, 2)."""
    pose = np.asarray(pose, dtype=float)
    z = np.asarray(z, dtype=float)
    angle = pose[..., 2] + z[..., 1]
    c, s = np.cos(angle), np.sin(angle)
    rng = z[..., 0]
    shape = np.broadcast_shapes(pose.shape[:-1], z.shape[:-1])
    G_pose = np.zeros(shape + (2, 3))
    G_pose[..., 0, 0] = 1.0
    G_pose[..., 1, 1] = 1.0
    G_pose[..., 0, 2] = -rng * s
    G_pose[..., 1, 2] = rng * c
    G_z = np.empty(shape + (2, 2))
    G_z[..., 0, 0] = c
    G_z[..., 0, 1] = -rng * s
    G_z[..., 1, 0] = s
    G_z[..., 1, 1] = rng * c
    return G_pose, G_z


def innovation(z, z_pred):
    """Observation residual with the bearing wrapped to [-pi, pi)."""
    nu = np.asarray(z, dtype=float) - np.asarray(z_pred, dtype=float)
    nu[..., 1] = wrap_angle(nu[..., 1])
    return nu
