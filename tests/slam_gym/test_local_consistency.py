"""Local-pose NEES of front-ends at BB's fusion points (#14)."""

import numpy as np
import pytest
from scipy.stats import chi2

from filters.dead_reckoning import DeadReckoning
from filters.ekf_slam import EKFSLAM
from filters.fastslam import FastSLAM2
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


def _fastslam_nees(levels, sample_clutter=False, lineage_correction=True):
    """Local-pose NEES of FastSLAM 2.0 (DAS, 500 particles) at fusion, BB's path, seeds 0-3,
    1000 steps per level: the measurement of scripts/local_pose_nees.py."""
    values = []
    for level in levels:
        for seed in range(4):
            stream = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=1000)
            front = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise,
                              np.random.default_rng([seed, 11]), n_particles=500,
                              sample_clutter=sample_clutter,
                              lineage_correction=lineage_correction)
            values.append(local_pose_nees_at_fusion(front, stream, 100))
    return np.concatenate(values)


@pytest.fixture(scope="module")
def fastslam_nees_levels_0_3():
    return _fastslam_nees(range(4))


def test_fastslam_local_maps_at_fusion_regression(fastslam_nees_levels_0_3):
    """#14 (2), seeded: clutter levels 0-3, 160 fusions. With clutter marginalised by the new
    feature's existence and the lineage term in the conversion, 88 % of the local poses lie
    inside the 95 % band (141 of 160; 9.4 % over-confident). Without the lineage term 86 %
    (138; 11.3 % over); with the earlier clutter rule as well, 76 % (22 % over). The issue's
    90 % is met pooled over the 2080 fusions of seeds 0-27 (90.1 %) and on seeds 4-11 at 2000
    steps (91.7 %), not on these seeds nor on seeds 12-27 (89.5 %) (docs/RESULTS.md)."""
    v = fastslam_nees_levels_0_3
    assert len(v) == 160
    assert np.mean((v >= LO) & (v <= HI)) >= 0.875
    assert np.mean(v > HI) <= 0.10


def test_lineage_term_reduces_over_confidence_at_fusion(fastslam_nees_levels_0_3):
    """The same run converted by BB (7) alone (the filtering is identical, only the Gaussian
    differs): more local poses over the band, every NEES at least as large."""
    v0 = _fastslam_nees(range(4), lineage_correction=False)
    v = fastslam_nees_levels_0_3
    assert np.all(v0 >= v - 1e-9)
    assert np.mean(v0 > HI) > np.mean(v > HI)


def test_sampled_clutter_makes_local_maps_over_confident():
    """The clutter rule alone (both converted by BB (7) without the lineage term): at levels 1-2
    (where clutter and missed detections meet) sampling clutter apart from the new feature leaves
    67.5 % of the local poses inside the band (84 % with the default rule)."""
    v = _fastslam_nees([1, 2], sample_clutter=True, lineage_correction=False)
    assert np.mean((v >= LO) & (v <= HI)) < 0.75


def test_interval_must_be_positive():
    stream = make_stream("brooks-bailey", seed=0, n_steps=10)
    with pytest.raises(ValueError, match="interval_steps"):
        local_pose_nees_at_fusion(RestartingDeadReckoning(stream.odometry_noise), stream, 0)
