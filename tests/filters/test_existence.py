"""BB (11) existence updates and the false-alarm-in-gate probability."""

import numpy as np
import pytest

from filters import existence as ex


def test_detection_update_is_bayes_rule():
    p, alpha, p_fa = 0.3, 0.7, 0.05
    # P(exists | detection) by Bayes with P(det | exists) = alpha, P(det | not) = p_fa
    expected = p * alpha / (p * alpha + (1 - p) * p_fa)
    assert ex.detection_update(p, alpha, p_fa) == pytest.approx(expected)
    assert ex.detection_update(p, alpha, p_fa) > p


def test_miss_update_lowers_existence_and_is_bayes_rule():
    p, alpha, p_fa = 0.8, 0.7, 0.05
    expected = p * (1 - alpha) / (p * (1 - alpha) + (1 - p) * (1 - p_fa))
    assert ex.miss_update(p, alpha, p_fa) == pytest.approx(expected)
    assert ex.miss_update(p, alpha, p_fa) < p


def test_perfect_sensor_confirms_in_one_detection_and_kills_on_a_miss():
    assert ex.detection_update(0.5, 1.0, 0.0) == pytest.approx(1.0)
    assert ex.miss_update(0.99, 1.0, 0.0) == pytest.approx(0.0)


def test_gate_area_of_a_diagonal_covariance():
    S = np.diag([0.04, 0.01])
    assert ex.gate_area(S, 9.0) == pytest.approx(np.pi * 9.0 * 0.2 * 0.1)


def test_false_alarm_in_gate_matches_monte_carlo():
    """Drop beta * n_visible uniform false alarms per scan; count scans with one in the gate."""
    rng = np.random.default_rng(3)
    max_range, fov, beta, n_visible = 25.0, 2 * np.pi, 0.06, 5
    S = np.diag([1.0, 0.05]) ** 2
    gamma = 9.21
    centre = np.array([10.0, 0.3])
    scans = 100_000
    counts = rng.binomial(n_visible, beta, size=scans)
    hit = np.zeros(scans, dtype=bool)
    n_total = counts.sum()
    r = rng.uniform(0, max_range, n_total)
    b = rng.uniform(-np.pi, np.pi, n_total)
    d = np.column_stack([r, b]) - centre
    inside = np.einsum("ni,ij,nj->n", d, np.linalg.inv(S), d) <= gamma
    owner = np.repeat(np.arange(scans), counts)
    hit[owner[inside]] = True
    predicted = ex.false_alarm_in_gate_probability(
        beta, n_visible, ex.gate_area(S, gamma), max_range, fov
    )
    assert hit.mean() == pytest.approx(predicted, rel=0.1)


def test_bb_reading_uses_beta_as_written_and_the_gate_reading_the_gate():
    args = (0.06, 5.0, 0.01, 25.0, 2 * np.pi)
    assert ex.false_alarm_probability_one(True, *args) == 0.06
    assert ex.false_alarm_probability_one(False, *args) == pytest.approx(
        ex.false_alarm_in_gate_probability_one(*args)
    )
    assert ex.false_alarm_probability_one(False, *args) < 1e-3


def _detections_to_confirm(filter_name, existence_model):
    """Detections of one landmark, seen from a fixed pose at BB's clutter level 3 (alpha 0.1,
    beta 0.06), before its existence passes 0.95."""
    from filters.ekf_slam import EKFSLAM
    from filters.fastslam import FastSLAM2
    from filters.models import ClutterModel, ProportionalVelocityNoise, RangeBearingSensor

    sensor, clutter = RangeBearingSensor(), ClutterModel(alpha=0.1, beta=0.06)
    noise = ProportionalVelocityNoise(v_floor_mps=0.005, omega_floor_radps=0.005)
    if filter_name == "ekf":
        f = EKFSLAM(sensor, clutter, noise, existence_model=existence_model)
    else:
        f = FastSLAM2(sensor, clutter, noise, np.random.default_rng(0), n_particles=20,
                      existence_model=existence_model)
    for n in range(1, 30):
        f.predict(np.zeros(2), 0.1)
        f.update(np.array([[10.0, 0.3]]))
        if f.landmarks().existence.max(initial=0.0) > ex.CONFIRMED_PROBABILITY:
            return n
    return 30


@pytest.mark.parametrize("filter_name", ["ekf", "fastslam"])
def test_bb_reading_needs_several_detections_in_heavy_clutter(filter_name):
    """Under BB's beta a detection multiplies the odds by alpha / beta = 1.67 at level 3, so
    from p = 0.5 it takes ceil(log 19 / log 1.67) = 6 detections; the gate reading confirms a
    feature whose gate is a few cm wide after 1-2."""
    assert _detections_to_confirm(filter_name, "gate") <= 2
    assert _detections_to_confirm(filter_name, "bb") >= 5


@pytest.mark.parametrize("filter_name", ["ekf", "fastslam"])
def test_unknown_existence_model_raises_naming_it(filter_name):
    with pytest.raises(ValueError, match="existence_model"):
        _detections_to_confirm(filter_name, "literal")
