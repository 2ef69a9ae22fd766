"""Play a :class:`~slam_gym.stream.Stream` through a SLAM system and measure it.

:class:`Episode` is the one place where filters meet truth: it hands each step's odometry,
compass and observations to the system, keeps the truth apart, and tracks the metrics of
docs/ARCHITECTURE.md, "Evaluation metrics" (NEES against the chi-square band, BB's failure
criterion, pose error, map error through
:class:`~slam_gym.metrics.FeatureTruth`). The fixed-schedule runner, the evaluation and the
Gymnasium env all drive systems through it, so the env adds no behaviour of its own.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from filters.existence import CONFIRMED_PROBABILITY
from filters.global_frame import stepwise_iteration
from filters.types import LandmarkEstimate
from slam_gym.metrics import FailureDetector, FeatureTruth, nees_band, score_map
from slam_gym.world import RedrawnFuture


@dataclass
class Trace:
    """Per-iteration records of a run (for plots): time, NEES, pose error, covariance trace."""

    t_s: list = field(default_factory=list)
    nees: list = field(default_factory=list)
    position_error_m: list = field(default_factory=list)
    cov_trace: list = field(default_factory=list)
    est_poses: list = field(default_factory=list)
    true_poses: list = field(default_factory=list)

    def __deepcopy__(self, memo):
        """A copy whose lists are new but whose entries are shared: entries are never changed
        after they are appended (floats and arrays made for the trace), so a copy of an episode
        (:meth:`slam_gym.envs.hybrid_slam.HybridSLAMEnv.clone`) need not copy them."""
        return Trace(*(list(getattr(self, f.name)) for f in dataclasses.fields(self)))


class Episode:
    """One run of ``system`` over ``stream``.

    ``known_association``: hand the truth landmark ids to systems that accept them (CM's setting,
    and the comparison mode on real data). ``record_trace``: keep per-iteration arrays.
    ``draws``: the system's source of random numbers when it is keyed by iteration
    (:class:`filters.draws.SynchronisedDraws`): the episode sets its ``iteration`` before each
    filter iteration, the one place that counts them.
    """

    def __init__(self, system, stream, *, known_association: bool = False, record_trace=True,
                 draws=None):
        self.system = system
        self.draws = draws
        self.stream = stream
        self.known_association = known_association
        self._steps = iter(stream)
        self.iteration = 0
        self.t_s = 0.0
        self.done = False
        self.feature_truth = FeatureTruth()
        self.failure = FailureDetector()
        self.detected_landmarks: set[int] = set()
        self.n_fusions = 0
        self.n_optimisations = 0
        self.compute_time_s = 0.0
        self.band = nees_band(1)
        self._nees_sum = 0.0
        self._nees_count = 0
        self._in_band = 0
        self._pos_err_sum = 0.0
        self.last_nees = float("nan")
        self.last_position_error_m = float("nan")
        self.last_step = None
        self.trace = Trace() if record_trace else None

    # ------------------------------------------------------------------ stepping
    def advance(self, n_iterations: int = 1) -> int:
        """Process up to ``n_iterations`` steps; returns how many were processed."""
        done = 0
        while done < n_iterations:
            step = next(self._steps, None)
            if step is None:
                self.done = True
                break
            self._process(step)
            done += 1
        if self.iteration >= len(self.stream):
            self.done = True
        return done

    def _process(self, step) -> None:
        """One filter iteration and its metrics. A system with a compiled iteration
        (:meth:`filters.submap.SubmapSLAM.iterate`) runs the prediction, the compass, the scan,
        the pose and the pose's NEES and position error against the truth in one call; the
        others (and known association) run the separate calls
        (:func:`filters.global_frame.stepwise_iteration`). ``filter_time_s`` counts either,
        the pose's moments included."""
        system = self.system
        if self.draws is not None:
            self.draws.iteration = self.iteration
        heading = None
        if step.compass_rad is not None and self.stream.compass_std_rad is not None:
            heading = (step.compass_rad, self.stream.compass_std_rad)
        z = step.z if step.scanned else None  # a step without a scan is no evidence
        truth = step.truth
        truth_ids = truth.landmark_ids
        iterate = None if self.known_association else getattr(system, "iterate", None)
        start = time.perf_counter()
        if iterate is not None:
            mean, cov, value, error = iterate(step.odometry, step.dt_s, z, heading=heading,
                                              truth_pose=truth.pose)
        else:
            options = {"known_ids": truth_ids} if self.known_association and z is not None else {}
            mean, cov, value, error = stepwise_iteration(system, step.odometry, step.dt_s, z,
                                                         heading, truth.pose, **options)
        self.compute_time_s += time.perf_counter() - start
        if len(truth_ids):
            # the truth's association votes and the detected landmarks, over a few observations:
            # Python ints, not numpy scalars
            truth_list = truth_ids.tolist()
            associations = system.last_associations
            if len(associations) == len(truth_list):
                self.feature_truth.record_lists(np.asarray(associations).tolist(), truth_list)
            self.detected_landmarks.update([t for t in truth_list if t >= 0])
        self.iteration += 1
        self.t_s = step.t_s
        self.last_step = step
        self._measure(step, mean, cov, value, error)

    def _measure(self, step, mean, cov, value, error) -> None:
        """The iteration's pose metrics (``value`` its NEES, ``error`` its position error, from
        the system's iteration) into the run's sums, the failure test and the trace."""
        true_pose = step.truth.pose
        x, y, heading = np.asarray(true_pose, dtype=float).tolist()
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(heading)):
            return
        self.last_nees = value
        self.failure.update(value, self.iteration)
        self._nees_sum += value
        self._nees_count += 1
        self._in_band += int(self.band[0] <= value <= self.band[1])
        self.last_position_error_m = error
        self._pos_err_sum += error
        if self.trace is not None:
            self.trace.t_s.append(step.t_s)
            self.trace.nees.append(value)
            self.trace.position_error_m.append(error)
            self.trace.cov_trace.append(float(cov[0, 0] + cov[1, 1] + cov[2, 2]))  # np.trace's
            self.trace.est_poses.append(np.array(mean))
            self.trace.true_poses.append(np.array(true_pose))

    def redraw_future(self, seed: int) -> None:
        """Replace the rest of the stream with the same world's steps with their measurement
        noise drawn anew from ``seed`` (:class:`slam_gym.world.RedrawnFuture`): the path, the
        landmarks and what was already processed stay; the scans to come are another draw."""
        self._steps = RedrawnFuture(self.stream, self.iteration, seed)

    # ------------------------------------------------------------------ interface decisions
    def fuse(self):
        start = time.perf_counter()
        report = self.system.fuse()
        self.compute_time_s += time.perf_counter() - start
        if report is not None:
            self.feature_truth.merge(report.id_map)
        self.n_fusions += 1
        return report

    def optimise(self):
        start = time.perf_counter()
        result = self.system.optimise()
        self.compute_time_s += time.perf_counter() - start
        if not getattr(result, "redundant", False):  # a redundant call changed nothing
            self.n_optimisations += 1
        return result

    # ------------------------------------------------------------------ metrics
    def confirmed_landmarks(self, min_existence: float = CONFIRMED_PROBABILITY):
        """The system's map without the features not (yet) believed to exist (BB 5.1)."""
        lm = self.system.landmarks()
        keep = np.asarray(lm.existence) >= min_existence
        return LandmarkEstimate(
            ids=np.asarray(lm.ids)[keep],
            means=np.asarray(lm.means)[keep],
            covs=np.asarray(lm.covs)[keep],
            existence=np.asarray(lm.existence)[keep],
        )

    def map_score(self, min_existence: float = CONFIRMED_PROBABILITY):
        ids, means = self._confirmed_means(min_existence)
        return score_map(
            ids,
            means,
            self.feature_truth,
            self.stream.landmarks_true,
            self.detected_landmarks,
        )

    def _confirmed_means(self, min_existence: float):
        """Ids and means of :meth:`confirmed_landmarks`, without computing covariances where the
        system can skip them (``landmark_means``): the score needs none, and the env scores
        the map at every decision."""
        system = self.system
        if hasattr(system, "landmark_means"):
            ids, means, existence = system.landmark_means()
        else:
            lm = system.landmarks()
            ids, means, existence = lm.ids, lm.means, lm.existence
        keep = np.asarray(existence) >= min_existence
        return np.asarray(ids)[keep], np.asarray(means)[keep]

    def metrics(self) -> dict:
        """The metrics (docs/ARCHITECTURE.md, "Evaluation metrics") of the run so far."""
        score = self.map_score()
        n = max(self._nees_count, 1)
        return {
            "iterations": self.iteration,
            "success": not self.failure.failed,
            "failure_iteration": self.failure.failure_iteration,
            "anees": self._nees_sum / n if self._nees_count else float("nan"),
            "nees_in_band_fraction": self._in_band / n if self._nees_count else float("nan"),
            "final_pose_error_m": self.last_position_error_m,
            "mean_pose_error_m": self._pos_err_sum / n if self._nees_count else float("nan"),
            "map_error_m": score.map_error_m,
            "n_features": score.n_features,
            "n_matched_landmarks": score.n_matched,
            "n_spurious": score.n_spurious,
            "n_missed": score.n_missed,
            "map_completeness": score.completeness,
            "n_fusions": self.n_fusions,
            "n_optimisations": self.n_optimisations,
            "filter_time_s": self.compute_time_s,
        }
