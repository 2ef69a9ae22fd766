"""Dead reckoning: the pose predicted from odometry alone, with its covariance.

The mean follows :func:`filters.models.motion`; the covariance follows the usual first-order
propagation ``P <- F P F^T + G Q G^T`` with ``F``, ``G`` the Jacobians of the motion model w.r.t.
pose and controls and ``Q`` the odometry noise covariance of the measured controls. An optional
compass measurement of the heading is fused by a scalar Kalman update. This is the baseline every
SLAM filter must beat, and its consistency on the simulator validates the noise models.
"""

from __future__ import annotations

import numpy as np

from filters.geometry import wrap_angle
from filters.models import motion, motion_jacobians
from filters.types import LandmarkEstimate


class DeadReckoning:
    """Pose-only EKF driven by odometry (and optionally a compass)."""

    def __init__(self, odometry_noise, initial_pose=(0.0, 0.0, 0.0), initial_cov=None):
        self.odometry_noise = odometry_noise
        self.x = np.asarray(initial_pose, dtype=float).copy()
        self.P = np.zeros((3, 3)) if initial_cov is None else np.array(initial_cov, dtype=float)
        self.last_associations = np.zeros(0, dtype=np.int64)

    def predict(self, u, dt):
        """x <- f(x, u); P <- F P F^T + G Q G^T (nothing for ``dt == 0``: no motion)."""
        if float(dt) == 0.0:
            return
        F, G = motion_jacobians(self.x, u, dt)
        Q = self.odometry_noise.covariance(u, dt)
        self.x = motion(self.x, u, dt)
        self.P = F @ self.P @ F.T + G @ Q @ G.T
        self.P = 0.5 * (self.P + self.P.T)

    def update(self, z):
        """Observations carry no information without a map: they are all left unassociated."""
        self.last_associations = np.full(len(z), -1, dtype=np.int64)

    def update_heading(self, theta, std_rad):
        """Scalar Kalman update with a heading measurement ``theta`` of std ``std_rad``."""
        H = np.array([0.0, 0.0, 1.0])
        S = self.P[2, 2] + std_rad**2
        K = self.P @ H / S
        self.x = self.x + K * wrap_angle(theta - self.x[2])
        self.x[2] = wrap_angle(self.x[2])
        I_KH = np.eye(3) - np.outer(K, H)
        self.P = I_KH @ self.P @ I_KH.T + np.outer(K, K) * std_rad**2

    def pose(self):
        return self.x.copy(), self.P.copy()

    def landmarks(self) -> LandmarkEstimate:
        return LandmarkEstimate.empty()
