"""Evaluation metrics (docs/ARCHITECTURE.md, "Evaluation metrics").

* Vehicle NEES ``e^T P^-1 e`` with the heading error wrapped, its 95 % chi-square band for one run
  and for the average of N runs (ANEES: ``chi2(3N)/N``).
* BB's failure criterion (BB 5.2, Table 1): the true pose more than 10 standard deviations from the
  estimate (Mahalanobis distance over the 3-D pose, i.e. NEES > 100) for more than 20 consecutive
  iterations.
* Map error (CM IV.B): the mean distance between estimated features and the true landmarks they
  stand for. A feature stands for the true landmark that most of the observations associated with it
  came from (the simulator's truth ids); :class:`FeatureTruth` keeps those votes, following the
  filters' ``last_associations`` and the ``id_map`` of each fusion. A feature whose votes are mostly
  false alarms is *spurious*; a true landmark that was detected but has no feature is *missed*.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass

import numpy as np

from filters.association import chi_square_quantile
from filters.geometry import wrap_angle
from filters.global_frame import NEES_REGULARISATION, cholesky_nees

POSE_DOF = 3
FAILURE_SIGMA = 10.0
FAILURE_CONSECUTIVE_ITERATIONS = 20


def pose_error(true_pose, est_pose) -> np.ndarray:
    """true - estimate, heading wrapped."""
    e = np.asarray(true_pose, dtype=float) - np.asarray(est_pose, dtype=float)
    e[..., 2] = wrap_angle(e[..., 2])
    return e


def nees(true_pose, est_pose, cov) -> float:
    """Normalised estimation error squared ``e^T P^-1 e`` of a pose (heading error wrapped);
    ``inf`` when the (symmetrised, regularised) covariance is not positive definite."""
    e = pose_error(true_pose, est_pose)
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (len(e), len(e)):
        raise ValueError(f"cov={cov.shape} is invalid: must be ({len(e)}, {len(e)}) like the pose")
    return float(cholesky_nees(e, np.ascontiguousarray(cov), NEES_REGULARISATION))


def nees_band(
    n_runs: int = 1, dof: int = POSE_DOF, confidence: float = 0.95
) -> tuple[float, float]:
    """Two-sided ``confidence`` band for the average NEES of ``n_runs`` independent runs."""
    lo_q, hi_q = (1.0 - confidence) / 2.0, 1.0 - (1.0 - confidence) / 2.0
    return (
        float(chi_square_quantile(lo_q, dof * n_runs) / n_runs),
        float(chi_square_quantile(hi_q, dof * n_runs) / n_runs),
    )


class FailureDetector:
    """BB's criterion: Mahalanobis distance > 10 for more than 20 consecutive iterations."""

    def __init__(
        self,
        sigma: float = FAILURE_SIGMA,
        consecutive: int = FAILURE_CONSECUTIVE_ITERATIONS,
    ):
        self.threshold_nees = sigma**2
        self.consecutive = consecutive
        self.run_length = 0
        self.failed = False
        self.failure_iteration: int | None = None

    def update(self, nees_value: float, iteration: int) -> bool:
        """Feed one iteration's NEES; returns whether the run has failed (so far)."""
        if not (nees_value <= self.threshold_nees):  # NaN and inf count as outside
            self.run_length += 1
        else:
            self.run_length = 0
        if not self.failed and self.run_length > self.consecutive:
            self.failed = True
            self.failure_iteration = iteration
        return self.failed


class FeatureTruth:
    """Which true landmark each estimated feature stands for, by majority of its observations."""

    def __init__(self):
        self.votes: dict[int, Counter] = defaultdict(Counter)
        self._landmarks: dict[int, int] = {}
        """:meth:`landmark_of`'s answers, each dropped when its feature's votes change (the map
        is scored at every decision, the votes of a few features change between two)."""

    def __deepcopy__(self, memo):
        """The same votes in new counters (ints need no copying; a generic deep copy of a few
        hundred counters costs milliseconds, this a fraction of one)."""
        copied = FeatureTruth()
        copied.votes.update((fid, Counter(counts)) for fid, counts in self.votes.items())
        copied._landmarks.update(self._answers())
        return copied

    def _answers(self) -> dict[int, int]:
        """The kept answers of :meth:`landmark_of` (a pickle of an older object has none)."""
        answers = self.__dict__.get("_landmarks")
        if answers is None:
            answers = self._landmarks = {}
        return answers

    def record(self, feature_ids: np.ndarray, truth_ids: np.ndarray) -> None:
        """One update: the feature id each observation went to (-1 clutter) and its truth id."""
        feature_ids, truth_ids = np.asarray(feature_ids), np.asarray(truth_ids)
        if len(feature_ids) != len(truth_ids):
            raise ValueError(f"feature_ids={feature_ids!r} is invalid: must have the length of "
                             f"truth_ids ({len(truth_ids)})")
        self.record_lists(feature_ids.astype(np.int64).tolist(),
                          truth_ids.astype(np.int64).tolist())

    def record_lists(self, feature_ids: list[int], truth_ids: list[int]) -> None:
        """:meth:`record` of two equally long lists of Python ints (the episode's every step)."""
        votes, answers = self.votes, self._answers()
        for fid, tid in zip(feature_ids, truth_ids, strict=True):
            if fid >= 0:
                votes[fid][tid] += 1
                answers.pop(fid, None)

    def merge(self, id_map: dict[int, int]) -> None:
        """A fusion renamed features: fold the votes of each local id into its global id."""
        answers = self._answers()
        for local_id, global_id in id_map.items():
            if local_id != global_id and local_id in self.votes:
                self.votes[global_id].update(self.votes.pop(local_id))
                answers.pop(local_id, None)
                answers.pop(global_id, None)

    def landmark_of(self, feature_id: int) -> int:
        """The true landmark index a feature stands for, -1 if mostly clutter or unknown."""
        feature_id = int(feature_id)
        answers = self._answers()
        answer = answers.get(feature_id)
        if answer is None:
            counts = self.votes.get(feature_id)
            answer = int(counts.most_common(1)[0][0]) if counts else -1
            answers[feature_id] = answer
        return answer


@dataclass
class MapScore:
    map_error_m: float
    n_features: int
    n_matched: int
    n_spurious: int
    n_missed: int
    n_detected: int = 0
    best_errors_m: tuple = ()
    """Per matched landmark, the error of the nearest feature standing for it."""

    @property
    def completeness(self) -> float:
        """The fraction of the landmarks the sensor detected that the map holds (NaN if none
        was detected): a map that is accurate because it is empty scores 0 here."""
        if self.n_detected == 0:
            return float("nan")
        return (self.n_detected - self.n_missed) / self.n_detected

    def ospa_m(self, cutoff_m: float) -> float:
        """OSPA distance (order 1, cut-off ``cutoff_m``; Schuhmacher et al. 2008) between the map
        and the detected landmarks: matched landmarks cost their error (at most the cut-off),
        every missed landmark and every spurious or duplicate feature costs the cut-off, averaged
        over ``max(features, detected)``. An empty map scores the cut-off, a perfect one 0."""
        n = max(self.n_features, self.n_detected)
        if n == 0:
            return 0.0
        errors = np.minimum(np.asarray(self.best_errors_m, dtype=float), cutoff_m)
        return float((errors.sum() + cutoff_m * (n - len(errors))) / n)


def score_map(
    feature_ids: np.ndarray,
    feature_means: np.ndarray,
    truth: FeatureTruth,
    landmarks_true: np.ndarray,
    detected_landmarks: set[int] | np.ndarray,
) -> MapScore:
    """CM's map error over the features that stand for a true landmark; spurious and missed.

    A feature's error is the Euclidean distance ``sqrt(dx dx + dy dy)`` to its landmark, formed
    for all matched features at once (the products and the sum rounded apart, as
    ``np.linalg.norm`` of each difference gives them)."""
    feature_ids, feature_means = np.asarray(feature_ids), np.asarray(feature_means)
    if len(feature_ids) != len(feature_means):
        raise ValueError(f"feature_means={feature_means.shape} is invalid: must have one row per "
                         f"feature id ({len(feature_ids)})")
    landmark_of, n_true = truth.landmark_of, len(landmarks_true)
    rows, matched_lms = [], []
    for i, fid in enumerate(feature_ids.tolist()):
        lm = landmark_of(fid)
        if 0 <= lm < n_true:
            rows.append(i)
            matched_lms.append(lm)
    n_spurious = len(feature_ids) - len(rows)
    errors = []
    best: dict[int, float] = {}
    if rows:
        d = feature_means[rows] - np.asarray(landmarks_true)[matched_lms]
        errors = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).tolist()
        for lm, err in zip(matched_lms, errors, strict=True):
            best[lm] = min(err, best.get(lm, np.inf))
    matched = set(best)
    detected = {int(i) for i in detected_landmarks}
    return MapScore(
        map_error_m=float(np.mean(errors)) if errors else float("nan"),
        n_features=len(feature_ids),
        n_matched=len(matched),
        n_spurious=n_spurious,
        n_missed=len(detected - matched),
        n_detected=len(detected),
        best_errors_m=tuple(best.values()),
    )
