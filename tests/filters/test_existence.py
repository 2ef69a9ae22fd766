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
