"""Local-pose NEES of front-ends at BB's fusion points (#14)."""

import numpy as np
import pytest
from scipy.stats import chi2

from filters.dead_reckoning import DeadReckoning
from filters.ekf_slam import EKFSLAM
from slam_gym.local_consistency import local_pose_nees_at_fusion
from slam_gym.scenarios import make_stream

LO, HI = chi2.ppf([0.025, 0.975], 3)


class RestartingDeadReckoning:
    """Dead reckoning with the front-end interface: its local pose is exactly Gaussian-consistent
    (the odometry noise model is the simulator's), so its NEES is chi-square with 3 dof."""

    def __init__(self, noise):
        self.noise = noise
        self.restart()

    def predict(self, u, dt):
        self.f.predict(u, dt)

    def update(self, z, ids=None):
        pass

    def restart(self):
        self.f = DeadReckoning(self.noise, np.zeros(3))

    def to_gaussian(self):
        from types import SimpleNamespace

        mean, cov = self.f.pose()
        return SimpleNamespace(x=mean, P=cov)


def test_local_pose_nees_of_dead_reckoning_is_chi_square():
    """The diagnostic itself: exact local poses give NEES with mean 3 (the true local pose is the
    true pose relative to the true pose at the restart)."""
    values = []
    for seed in range(4):
        stream = make_stream("brooks-bailey", seed=seed, n_steps=1500)
        values.append(local_pose_nees_at_fusion(
            RestartingDeadReckoning(stream.odometry_noise), stream, 100))
    v = np.concatenate(values)
    assert len(v) == 60
    # mean of 60 chi2(3) values: std sqrt(6 / 60) ~ 0.32
    assert abs(np.mean(v) - 3.0) < 1.0
    assert np.mean((v < LO) | (v > HI)) <= 0.15


@pytest.mark.parametrize("level", [0, 3])
def test_ekf_front_end_local_maps_are_consistent_at_fusion(level):
    """EKF local maps at fusion, BB's path (sharp first turn included), seeds 0-3, 1000 steps:
    local-pose NEES inside the 95 % band at >= 85 % of fusions (measured 92.5 % at levels 0, 3)."""
    values = []
    for seed in range(4):
        stream = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=1000)
        front = EKFSLAM(stream.sensor, stream.clutter, stream.odometry_noise)
        values.append(local_pose_nees_at_fusion(front, stream, 100))
    v = np.concatenate(values)
    assert len(v) == 40
    assert np.mean((v >= LO) & (v <= HI)) >= 0.85


def test_interval_must_be_positive():
    stream = make_stream("brooks-bailey", seed=0, n_steps=10)
    with pytest.raises(ValueError, match="interval_steps"):
        local_pose_nees_at_fusion(RestartingDeadReckoning(stream.odometry_noise), stream, 0)
