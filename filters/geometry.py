"""SE(2) geometry: angle wrapping, pose composition and inversion, point transforms.

Poses are ``(x, y, theta)`` arrays with ``theta`` wrapped to [-pi, pi). Every function that a
filter linearises comes with its Jacobians, named ``J_<argument>``; tests check each one against
finite differences.

Notation follows Smith, Self and Cheeseman: ``compose(a, b) = a (+) b`` is the pose ``b`` expressed
in the frame of ``a`` carried into the frame ``a`` is expressed in; ``inverse(a) = (-) a``;
``relative(a, b) = (-) a (+) b`` is ``b`` seen from ``a`` (CM (8): ``x_k = x_{k-1} (+) d_k``).
All functions broadcast over leading axes (e.g. over particles).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * np.pi


def wrap_angle(angle):
    """Wrap an angle (or array of angles) in radians to [-pi, pi)."""
    return (np.asarray(angle, dtype=float) + np.pi) % TWO_PI - np.pi


@njit(cache=True, inline="always")
def wrap_angle_one(angle):
    """:func:`wrap_angle` of one float, compiled, to the bit.

    Python's (and numba's) float ``%`` calls ``fmod``, the costliest part of a compiled filter
    step's many wraps. For ``x = angle + pi`` within two turns of [0, 2 pi) the remainder is
    one exact subtraction or the same rounded addition ``%`` makes: ``fmod`` returns ``x`` for
    ``|x| < 2 pi`` (a negative one then gets ``+ 2 pi``, as here), and ``x - 2 pi`` is exact for
    ``2 pi < x < 4 pi`` (Sterbenz). Zero and everything else take ``%`` itself.
    """
    x = angle + math.pi
    if 0.0 < x < TWO_PI:
        return x - math.pi
    if TWO_PI < x < 2.0 * TWO_PI:
        return (x - TWO_PI) - math.pi
    if -TWO_PI < x < 0.0:
        return (x + TWO_PI) - math.pi
    return x % TWO_PI - math.pi


def compose(a, b):
    """Pose composition ``a (+) b`` for poses of shape (..., 3)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    out[..., 1] = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    out[..., 2] = wrap_angle(a[..., 2] + b[..., 2])
    return out


def compose_jacobians(a, b):
    """Jacobians of ``compose(a, b)`` w.r.t. ``a`` and ``b`` (single poses), each (3, 3)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[2]), np.sin(a[2])
    J_a = np.array(
        [
            [1.0, 0.0, -s * b[0] - c * b[1]],
            [0.0, 1.0, c * b[0] - s * b[1]],
            [0.0, 0.0, 1.0],
        ]
    )
    J_b = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return J_a, J_b


def inverse(a):
    """Pose inversion ``(-) a`` for poses of shape (..., 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty(a.shape)
    out[..., 0] = -c * a[..., 0] - s * a[..., 1]
    out[..., 1] = s * a[..., 0] - c * a[..., 1]
    out[..., 2] = wrap_angle(-a[..., 2])
    return out


def inverse_jacobian(a):
    """Jacobian of ``inverse(a)`` with respect to ``a`` (single pose), (3, 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array(
        [
            [-c, -s, s * a[0] - c * a[1]],
            [s, -c, c * a[0] + s * a[1]],
            [0.0, 0.0, -1.0],
        ]
    )


def relative(a, b):
    """``b`` expressed in the frame of ``a``: ``(-) a (+) b`` (poses of shape (..., 3))."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 2] = wrap_angle(b[..., 2] - a[..., 2])
    return out


def relative_jacobians(a, b):
    """Jacobians of ``relative(a, b)`` w.r.t. ``a`` and ``b`` (single poses), each (3, 3)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    J_a = np.array(
        [
            [-c, -s, -s * dx + c * dy],
            [s, -c, -c * dx - s * dy],
            [0.0, 0.0, -1.0],
        ]
    )
    J_b = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return J_a, J_b


def transform_point(pose, p):
    """A point ``p`` (..., 2) in the frame of ``pose`` (..., 3), expressed in the outer frame."""
    pose = np.asarray(pose, dtype=float)
    p = np.asarray(p, dtype=float)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    out = np.empty(np.broadcast_shapes(pose.shape[:-1], p.shape[:-1]) + (2,))
    out[..., 0] = pose[..., 0] + c * p[..., 0] - s * p[..., 1]
    out[..., 1] = pose[..., 1] + s * p[..., 0] + c * p[..., 1]
    return out


def transform_point_jacobians(pose, p):
    """Jacobians of ``transform_point(pose, p)`` w.r.t. ``pose`` (2, 3) and ``p`` (2, 2)."""
    pose = np.asarray(pose, dtype=float)
    p = np.asarray(p, dtype=float)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    J_pose = np.array(
        [[1.0, 0.0, -s * p[0] - c * p[1]], [0.0, 1.0, c * p[0] - s * p[1]]]
    )
    J_p = np.array([[c, -s], [s, c]])
    return J_pose, J_p


def point_to_frame(pose, p):
    """A point ``p`` (..., 2) in the outer frame, expressed in the frame of ``pose`` (..., 3)."""
    pose = np.asarray(pose, dtype=float)
    p = np.asarray(p, dtype=float)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    dx = p[..., 0] - pose[..., 0]
    dy = p[..., 1] - pose[..., 1]
    out = np.empty(np.broadcast_shapes(pose.shape[:-1], p.shape[:-1]) + (2,))
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    return out


def point_to_frame_jacobians(pose, p):
    """Jacobians of ``point_to_frame(pose, p)`` w.r.t. ``pose`` (2, 3) and ``p`` (2, 2)."""
    pose = np.asarray(pose, dtype=float)
    p = np.asarray(p, dtype=float)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dx, dy = p[0] - pose[0], p[1] - pose[1]
    J_pose = np.array([[-c, -s, -s * dx + c * dy], [s, -c, -c * dx - s * dy]])
    J_p = np.array([[c, s], [-s, c]])
    return J_pose, J_p
