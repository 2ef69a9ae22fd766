"""Map scoring: error over matched features, spurious and missed landmarks, completeness."""

import math

import numpy as np

from slam_gym.metrics import FeatureTruth, score_map

LANDMARKS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])


def _truth(pairs):
    truth = FeatureTruth()
    ids = np.array([f for f, _ in pairs])
    lms = np.array([t for _, t in pairs])
    truth.record(ids, lms)
    return truth


def test_completeness_counts_detected_landmarks_the_map_holds():
    truth = _truth([(7, 0), (8, 1), (9, -1)])
    means = np.array([[0.1, 0.0], [10.0, 0.3], [5.0, 5.0]])
    score = score_map(np.array([7, 8, 9]), means, truth, LANDMARKS, {0, 1, 2})
    assert score.n_matched == 2 and score.n_spurious == 1 and score.n_missed == 1
    assert score.n_detected == 3
    assert math.isclose(score.completeness, 2 / 3)
    assert math.isclose(score.map_error_m, (0.1 + 0.3) / 2)


def test_an_empty_map_is_accurate_by_default_but_has_completeness_zero():
    score = score_map(np.zeros(0, int), np.zeros((0, 2)), FeatureTruth(), LANDMARKS, {0, 3})
    assert math.isnan(score.map_error_m)
    assert score.completeness == 0.0 and score.n_missed == 2


def test_completeness_is_undefined_when_nothing_was_detected():
    score = score_map(np.zeros(0, int), np.zeros((0, 2)), FeatureTruth(), LANDMARKS, set())
    assert math.isnan(score.completeness)


def test_ospa_charges_the_cutoff_for_missed_spurious_and_duplicate_features():
    truth = _truth([(7, 0), (8, 1), (9, -1), (10, 1)])
    means = np.array([[0.1, 0.0], [10.0, 0.3], [5.0, 5.0], [10.0, 9.0]])
    score = score_map(np.array([7, 8, 9, 10]), means, truth, LANDMARKS, {0, 1, 2})
    # 4 features, 3 detected: landmarks 0 and 1 matched (0.1, 0.3); the rest cost the cut-off
    assert math.isclose(score.ospa_m(5.0), (0.1 + 0.3 + 2 * 5.0) / 4)
    assert math.isclose(score.ospa_m(0.2), (0.1 + 0.2 + 2 * 0.2) / 4)  # errors capped too
    empty = score_map(np.zeros(0, int), np.zeros((0, 2)), FeatureTruth(), LANDMARKS, {0, 3})
    assert empty.ospa_m(5.0) == 5.0
    perfect = score_map(np.array([7]), LANDMARKS[:1], _truth([(7, 0)]), LANDMARKS, {0})
    assert perfect.ospa_m(5.0) == 0.0


def test_compiled_nees_equals_the_cholesky_solve_and_is_inf_when_not_positive_definite():
    """Issue 27: the compiled NEES (filters.global_frame.cholesky_nees) against numpy's Cholesky
    and triangular solve of the symmetrised, regularised covariance; a covariance that is not
    positive definite (or NaN) gives inf, as numpy's LinAlgError did."""
    import pytest

    from slam_gym.metrics import NEES_REGULARISATION, nees

    rng = np.random.default_rng(5)
    for _ in range(200):
        A = rng.normal(size=(3, 3)) * rng.uniform(0.01, 3.0)
        cov = A @ A.T + rng.uniform(0, 1e-3) * np.eye(3)
        cov[0, 1] += 1e-12  # slightly asymmetric, as filters' round-off leaves it
        truth, est = rng.normal(size=3) * 5, rng.normal(size=3) * 5
        e = truth - est
        e[2] = (e[2] + np.pi) % (2 * np.pi) - np.pi
        L = np.linalg.cholesky(0.5 * (cov + cov.T) + NEES_REGULARISATION * np.eye(3))
        w = np.linalg.solve(L, e)
        assert nees(truth, est, cov) == pytest.approx(float(w @ w), rel=1e-10)
    assert nees(np.zeros(3), np.ones(3), -np.eye(3)) == math.inf
    assert nees(np.zeros(3), np.ones(3), np.diag([1.0, 1.0, np.nan])) == math.inf
    with pytest.raises(ValueError, match="cov"):
        nees(np.zeros(3), np.ones(3), np.eye(2))


def test_map_score_equals_the_feature_by_feature_reference():
    """score_map's matched errors (one array expression) against the distance of each feature to
    its landmark by np.linalg.norm, and FeatureTruth's kept answers against the votes counted
    afresh after records and merges. The distances agree to 1e-12 relative (the same products and
    sum; the tolerance allows a BLAS that fuses np.linalg.norm's dot product)."""
    from collections import Counter

    from slam_gym.metrics import FeatureTruth, score_map

    rng = np.random.default_rng(3)
    landmarks = rng.uniform(-50.0, 50.0, (30, 2))
    truth = FeatureTruth()
    for step in range(300):
        ids = rng.integers(-1, 25, rng.integers(0, 4))
        truth.record(ids, rng.integers(-1, 32, len(ids)))
        if step % 40 == 39:  # a fusion renames a few features
            old = rng.choice(25, 3, replace=False)
            truth.merge({int(o): int(100 + step + i) for i, o in enumerate(old)})
        feature_ids = np.array(sorted(truth.votes)[:20], dtype=np.int64)
        means = landmarks[rng.integers(0, 30, len(feature_ids))] + rng.normal(0, 2, (len(
            feature_ids), 2))
        score = score_map(feature_ids, means, truth, landmarks, {1, 2, 3, 40})
        expected_errors = []
        for fid, mean in zip(feature_ids, means, strict=True):
            counts = Counter(truth.votes[int(fid)])
            lm = counts.most_common(1)[0][0] if counts else -1
            assert truth.landmark_of(fid) == lm
            if 0 <= lm < len(landmarks):
                expected_errors.append(np.linalg.norm(mean - landmarks[lm]))
        assert score.n_spurious == len(feature_ids) - len(expected_errors)
        if expected_errors:
            np.testing.assert_allclose(score.map_error_m, np.mean(expected_errors), rtol=1e-12)
