"""Local-pose NEES of front-ends at BB's fusion points (#14)."""

import numpy as np
import pytest
from scipy.stats import chi2

from filters.dead_reckoning import DeadReckoning
from filters.ekf_slam import EKFSLAM
from filters.fastslam import LOCAL_MAP_MAX_EXISTENCE, FastSLAM2
from slam_gym.local_consistency import local_pose_nees_at_fusion
from slam_gym.world import make_stream

# its module-scoped fixtures are built once: every test of this file on one worker (pytest -n)
pytestmark = pytest.mark.xdist_group("test_local_consistency")

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


def _fastslam_nees(levels, seeds=range(4), n_steps=1000, sample_clutter=False,
                   lineage_correction=True, small_sample_correction=True):
    """Local-pose NEES of FastSLAM 2.0 (DAS, 500 particles, built as HYBRID's front-end: the
    existence clip is the float guard) at fusion, BB's path, per level and seed: the measurement
    of scripts/archive/local_pose_nees.py."""
    values = []
    for level in levels:
        for seed in seeds:
            stream = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=n_steps)
            front = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise,
                              np.random.default_rng([seed, 11]), n_particles=500,
                              sample_clutter=sample_clutter,
                              lineage_correction=lineage_correction,
                              small_sample_correction=small_sample_correction,
                              max_existence=LOCAL_MAP_MAX_EXISTENCE)
            values.append(local_pose_nees_at_fusion(front, stream, 100))
    return np.concatenate(values)


def test_fastslam_local_maps_at_fusion_are_inside_the_band_at_90_percent():
    """#14 (2), seeded: clutter levels 0-3, seeds 28-43 (declared before their result was seen;
    never used to design the conversion), 2000 steps, 1280 fusions. With the lineage term and
    the small-sample factor the local pose lies inside the two-sided 95 % band at >= 90 % of
    fusions and over it at <= 5 % (nominal 2.5 %). Measured here 93.3 % / 2.6 % with the
    front-end's float-guard existence clip (over seeds 28-59 the same; docs/RESULTS.md, "Local
    maps at fusion", re-measured 2026-11-25); with FastSLAM's 0.999 clip, the front-end before
    issue 16 item 4, 91.2 % / 3.5 % (with the lineage term alone 88.8 % / 8.3 %), and over seeds
    28-59 (2560 fusions) 92.2 % / 3.2 % (89.7 % / 8.1 %) (docs/results/history.md)."""
    v = _fastslam_nees(range(4), seeds=range(28, 44), n_steps=2000)
    assert len(v) == 1280
    assert np.mean((v >= LO) & (v <= HI)) >= 0.90
    assert np.mean(v > HI) <= 0.05


@pytest.fixture(scope="module")
def fastslam_nees_levels_0_3():
    return _fastslam_nees(range(4))


@pytest.fixture(scope="module")
def fastslam_nees_lineage_term_alone():
    return _fastslam_nees(range(4), small_sample_correction=False)


def test_lineage_term_reduces_over_confidence_at_fusion(fastslam_nees_lineage_term_alone):
    """Seeds 0-3, 1000 steps, 160 fusions, converted by BB (7) alone and with the lineage term,
    both without the small-sample factor (the filtering is identical, only the Gaussian
    differs): BB (7) alone puts more local poses over the band, every NEES at least as large
    (measured 15.6 % vs 10.6 % over)."""
    v0 = _fastslam_nees(range(4), lineage_correction=False)
    v1 = fastslam_nees_lineage_term_alone
    assert np.all(v0 >= v1 - 1e-9)
    assert np.mean(v0 > HI) > np.mean(v1 > HI)


def test_small_sample_factor_reduces_over_confidence_at_fusion(
        fastslam_nees_levels_0_3, fastslam_nees_lineage_term_alone):
    """The same 160 fusions with and without the small-sample factor (it only scales the pose
    block up): every NEES at most as large, over the band 17 -> 4 of 160; the price is more
    local poses under the band (6 -> 11 of 160 on these seeds)."""
    without = fastslam_nees_lineage_term_alone
    v = fastslam_nees_levels_0_3
    assert len(v) == len(without) == 160
    assert np.all(v <= without + 1e-9)
    assert np.mean(v > HI) <= 0.05 < np.mean(without > HI)


def test_sampled_clutter_makes_local_maps_over_confident():
    """The clutter rule alone (both converted by BB (7) without the lineage term): at levels 1-2
    (where clutter and missed detections meet) sampling clutter apart from the new feature leaves
    72.5 % of the local poses inside the band (80 % with the default rule)."""
    v = _fastslam_nees([1, 2], sample_clutter=True, lineage_correction=False)
    assert np.mean((v >= LO) & (v <= HI)) < 0.75


def test_interval_must_be_positive():
    stream = make_stream("brooks-bailey", seed=0, n_steps=10)
    with pytest.raises(ValueError, match="interval_steps"):
        local_pose_nees_at_fusion(RestartingDeadReckoning(stream.odometry_noise), stream, 0)
