"""UTIAS MRCLAM data sets as a :class:`~slam_gym.stream.Stream` (docs/ARCHITECTURE.md, "The data
stream").

Leung, Halpern, Barfoot, Liu, "The UTIAS Multi-Robot Cooperative Localization and Mapping
Dataset", IJRR 30(8), 2011. A data set directory holds ``Barcodes.dat``,
``Landmark_Groundtruth.dat`` and, per robot N = 1..5, ``RobotN_Odometry.dat`` (t, v, omega),
``RobotN_Measurement.dat`` (t, barcode, range, bearing) and ``RobotN_Groundtruth.dat``
(t, x, y, theta; motion capture). Files are parsed with numpy ('#' comment headers).

How the stream is built (all deterministic: the same directory and options give the same stream
bit for bit):

* **Time grid.** The stream starts at ``t0`` = the later of the first odometry row and the first
  ground-truth row; ``initial_pose`` is the ground truth interpolated at ``t0``. Step ``k`` covers
  the interval ``(t0 + k dt, t0 + (k + 1) dt]`` with ``dt = dt_s`` (default 0.1 s, the 10 Hz filter
  rate of BB 5.2); ``Step.t_s`` is the end of the interval in seconds since ``t0``. The stream ends
  at the last full step before the earlier of the last odometry row and the last ground-truth
  row.
* **Odometry.** The logged (v, omega) rows are a zero-order-hold signal (a row holds until the
  next; rows sharing a time stamp: the last wins). A step's odometry is its time-weighted mean over
  the step (:func:`slam_gym.datasets.align.hold_average`).
* **Observations.** The measurement rows whose (corrected, below) time falls in the step, in
  file order, as (range, bearing). A measurement taken up to ``dt`` before the step's end is used
  at the end; by default it is first moved there with the odometry (motion compensation, below);
  without that, at MRCLAM's speeds (< 0.09 m/s, < 0.6 rad/s) and dt = 0.1 s it is off by < 1 cm
  and < 0.06 rad, which the noise estimate (against the true pose at the *step's end*) then
  includes. At dt = 0.1 s no landmark is seen twice within one step in Dataset 7.
* **Barcodes.** A row's barcode is mapped to a subject through ``Barcodes.dat`` (barcode and
  subject numbers overlap). Landmarks are the subjects listed in ``Landmark_Groundtruth.dat``
  (``Stream.landmarks_true`` holds them in subject order; ``truth.landmark_ids`` indexes it).
  **Decision:** sightings of other robots (subjects 1-5, about 21 % of the rows) and barcodes in
  no table are not landmarks and are *dropped* by default: they never reach a filter. With
  ``robot_sightings_as_clutter=True`` they are kept as clutter (truth id -1): a moving target is
  then a realistic false alarm for the existence logic (BB (11)).
* **Outliers.** A landmark row whose residual against the ground truth lies outside the
  ``outlier_gate_probability`` (default 0.9999) chi-square gate of the estimated noise is labelled
  a false alarm (truth id -1), since it does not measure its landmark (misread barcodes; e.g.
  range errors of 3-6 m in Robots 3 and 5). It stays in ``z``: a filter must reject it.
* **Visibility.** ``truth.visible_ids`` of every step lists the landmarks inside the stream's
  sensor field (range and fov) from the true pose: every step counts as a scan, consistent with
  alpha being a per-step rate (below).
* **Known association.** ``known_association=True`` only sets ``metadata["known_association"]``:
  it means the runner passes ``step.truth.landmark_ids`` to a known-association filter
  (-1 = clutter, to be ignored). The observations are the same in both modes.

Calibration (:func:`calibrate_mrclam`; every estimate is in
``Stream.metadata["calibration"]``, an explicit keyword overrides it). **What is used:** the
first ``calibration_s`` seconds (default 300 s, :data:`DEFAULT_CALIBRATION_S`) after the raw
start of the robot's *own* recording: its ground truth, odometry and landmark measurements up to
``t0 + calibration_s`` and nothing after (tested: a recording changed after 300 s gives the same
calibration). **Why:** the collection's nine recordings share arena, robots and sensors but not
their errors, so no number is carried from one recording to another and none is set by hand;
the first minutes are what a user of a new recording can calibrate on, and the rest of the run
stays held out (``reproduce mrclam`` reports the pose error over it). ``calibration_s=None``
uses the whole recording (the behaviour before issue 16). The outlier labels (truth ids -1) of
rows after the calibration part use the gate of the calibrated noise; they are truth for the
evaluation, never filter input.

With ``corrections=True`` (the default) the systematic errors measured on MRCLAM Dataset 7
(issue 16; docs/RESULTS.md) are estimated there and removed from the whole stream:

* **Odometry delay and gains** (:func:`estimate_odometry_correction`): the robots follow their
  logged (v, omega) about 0.2-0.3 s late and slow down in turns (true v = v (1.02-1.07 -
  1.1-1.2 s/rad |omega|), true omega = 0.92-0.97 omega on Dataset 7); the rows are shifted in
  time and corrected. Of all corrections this one lowers the map error of EKF-SLAM with known
  association the most on Dataset 7 (1.05 -> 0.59 m alone).
* **Measurement time stamps** (:func:`estimate_measurement_delay`): sightings are stamped
  0.02-0.04 s after they were taken; the stamps are moved back.
* **Motion compensation** (:func:`compensate_motion`): a measurement taken before its step's
  end is moved there with the (corrected) odometry.
* **Camera bias** (:func:`estimate_sensor_bias`): ranges read 0.1-0.25 m long at the image
  centre and 0.2-0.3 m short at its edges (range error ~ c0 - 1.6..2.1 b^2); fitted on the
  calibration part's inliers and subtracted from every measurement (held out, the range residual
  falls from 0.10-0.20 m to 0.04-0.09 m).
* **Correlated noise** (:func:`correlated_noise_std`): the std the filters assume is the
  white-noise rule over one pass over a landmark (:func:`sighting_pass_duration`, the median
  run of sightings of one landmark with gaps under 2 s; 2-3 s on Dataset 7), since a filter
  fuses a whole pass and the camera's errors stay correlated over it.

Each can be switched alone (``odometry_correction``, ``timing_correction``,
``motion_compensation``, ``sensor_bias_correction``, ``correlated_noise``);
``corrections=False`` gives the plain stream (the file's rows, noise = root mean square).

The models then estimated on the (corrected) calibration part:

* **Sensor noise** (:func:`estimate_sensor_noise`): residuals z - h(x_true, m_true) of the
  landmark rows, the true pose interpolated at the step's end; the std of range and bearing is
  the root mean square *about zero* (so a remaining bias counts as noise: the filters assume
  zero mean) of the inliers of an iterated chi-square gate.
* **Field of view** (:func:`estimate_field_of_view`): max range = 99.5 % quantile of the inlier
  ranges; fov = twice the 99.5 % quantile of |bearing| (the camera sees about +-0.6 rad).
* **Odometry noise** (:func:`estimate_odometry_noise`): a :class:`ProportionalVelocityNoise`
  (BB 5.2 form, std = hypot(fraction |u|, floor)). The true (v, omega) over windows of
  ``odometry_window_s`` come from the differentiated ground truth (summed over 0.1 s parts of
  each window, :func:`true_velocities`); the error of the window means is converted to a
  per-step std by the white-noise rule (variance x window / dt) — i.e. the per-step noise that
  reproduces the dead-reckoning error growth over one window. The errors are correlated over
  seconds, so that noise grows with the window until the window outlasts the correlation (on
  Dataset 7 the speed's, at v = 0.1 m/s: 0.015-0.021 m/s over 1 s, 0.024-0.035 m/s over 10 s,
  0.029-0.038 m/s over 20-30 s; ``scripts/results/mrclam_odometry_windows.py``). The default
  window is BB's local-map length, 10 s (:data:`DEFAULT_ODOMETRY_WINDOW_S`): the span over which a
  front-end integrates the odometry between fusions, so a local map's odometry covariance is
  not under-stated (the earlier 1 s window gave 57-68 % of the 10 s std for the speed). The
  fractions and floors are fitted by non-negative least squares to the squared errors; floors
  are at least 1e-3 so the covariance stays regular at rest.
* **Clutter** (:func:`estimate_detection_rates`, over the calibration part's steps): alpha =
  (steps in which an in-view landmark is detected) / (landmark-in-view events), per *filter step*
  (the camera delivers a frame about every 0.24 s and rows only for frames with a detection, so
  alpha per 0.1 s step is well below the per-frame rate); beta = false alarms (outliers, plus
  robot sightings and unknown barcodes when kept) / in-view events.

Not derived here: FastSLAM's new-landmark density and association gate (filter options; the
filters' defaults apply unless ``reproduce mrclam`` is given ``--landmark-density`` /
``--gate-chi2``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import InitVar, asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
from scipy.optimize import nnls

from filters.geometry import wrap_angle
from filters.models import (
    ClutterModel,
    ProportionalVelocityNoise,
    RangeBearingSensor,
    innovation,
    motion,
    observe,
)
from filters.validation import check_range, require
from slam_gym.datasets.align import hold_average, interpolate_poses
from slam_gym.datasets.tables import check_max_steps, load_table
from slam_gym.stream import ArraySteps, Stream

logger = logging.getLogger(__name__)

ROBOT_SUBJECTS = (1, 2, 3, 4, 5)
DEFAULT_DT_S = 0.1
DEFAULT_ODOMETRY_WINDOW_S = 10.0
"""Window (s) of the odometry-noise fit: BB's local-map length, the span over which a front-end
integrates the odometry between fusions (module doc, "Odometry noise")."""
MIN_ODOMETRY_WINDOWS = 4
"""Fewest windows the odometry-noise fit takes (:func:`estimate_odometry_noise`)."""
ODOMETRY_CORRECTION_WINDOW_S = 1.0
"""Window (s) of the odometry delay and gain fit (:func:`estimate_odometry_correction`)."""
DEFAULT_OUTLIER_GATE_PROBABILITY = 0.9999
FIELD_QUANTILE = 0.995
MIN_ODOMETRY_FLOOR = 1e-3
#: the first seconds of a recording the calibration uses (the rest is held out)
DEFAULT_CALIBRATION_S = 300.0
#: timing offsets searched (+-) and their resolution
MAX_DELAY_S = 0.5
DELAY_STEP_S = 0.01
#: a landmark not seen for longer ends a pass over it (sighting_pass_duration)
PASS_GAP_S = 2.0


# --------------------------------------------------------------------------- raw files
@dataclass(frozen=True)
class MrclamRecording:
    """The raw tables of one robot of one MRCLAM data set (times in Unix seconds).

    ``barcode_subjects`` (B, 2) rows (subject, barcode); ``landmark_subjects`` (N,) and
    ``landmarks_xy`` (N, 2) in subject order; ``odometry`` (R, 3) t, v, omega;
    ``groundtruth`` (G, 4) t, x, y, theta with strictly increasing t; ``measurements`` (M, 4)
    t, barcode, range, bearing in file order.
    """

    directory: Path
    robot: int
    barcode_subjects: np.ndarray
    landmark_subjects: np.ndarray
    landmarks_xy: np.ndarray
    odometry: np.ndarray
    groundtruth: np.ndarray
    measurements: np.ndarray

    def measurement_subjects(self) -> np.ndarray:
        """Subject number of each measurement row through ``Barcodes.dat``; -1 = unknown."""
        barcodes = self.measurements[:, 1].astype(np.int64)
        table = self.barcode_subjects
        order = np.argsort(table[:, 1], kind="stable")
        sorted_codes = table[order, 1]
        pos = np.clip(np.searchsorted(sorted_codes, barcodes), 0, sorted_codes.size - 1)
        found = sorted_codes[pos] == barcodes
        return np.where(found, table[order, 0][pos], -1).astype(np.int64)

    def measurement_landmark_index(self) -> np.ndarray:
        """Index into ``landmarks_xy`` of each measurement row; -1 = not a landmark."""
        subjects = self.measurement_subjects()
        pos = np.clip(
            np.searchsorted(self.landmark_subjects, subjects), 0, self.landmark_subjects.size - 1
        )
        found = self.landmark_subjects[pos] == subjects
        return np.where(found, pos, -1).astype(np.int64)


def read_mrclam(directory, robot: int = 1) -> MrclamRecording:
    """Parse the tables of ``robot`` (1-5) in an MRCLAM data set ``directory``."""
    require(
        isinstance(robot, (int, np.integer)) and not isinstance(robot, bool) and 1 <= robot <= 5,
        "robot",
        robot,
        "an integer in [1, 5]",
    )
    directory = Path(directory)
    require(directory.is_dir(), "directory", str(directory), "an existing MRCLAM directory")
    barcodes = load_table(directory / "Barcodes.dat", 2).astype(np.int64)
    landmarks = load_table(directory / "Landmark_Groundtruth.dat", 5)
    landmarks = landmarks[np.argsort(landmarks[:, 0], kind="stable")]
    odometry = load_table(directory / f"Robot{robot}_Odometry.dat", 3)
    groundtruth = load_table(directory / f"Robot{robot}_Groundtruth.dat", 4)
    measurements = load_table(directory / f"Robot{robot}_Measurement.dat", 4)
    require(
        bool(np.all(np.diff(odometry[:, 0]) >= 0.0)),
        f"Robot{robot}_Odometry.dat",
        "decreasing times",
        "non-decreasing times",
    )
    require(
        bool(np.all(np.diff(measurements[:, 0]) >= 0.0)),
        f"Robot{robot}_Measurement.dat",
        "decreasing times",
        "non-decreasing times",
    )
    order = np.argsort(groundtruth[:, 0], kind="stable")
    groundtruth = groundtruth[order]
    _, first = np.unique(groundtruth[:, 0], return_index=True)
    groundtruth = groundtruth[first]
    return MrclamRecording(
        directory=directory,
        robot=int(robot),
        barcode_subjects=barcodes,
        landmark_subjects=landmarks[:, 0].astype(np.int64),
        landmarks_xy=landmarks[:, 1:3].copy(),
        odometry=odometry,
        groundtruth=groundtruth,
        measurements=measurements,
    )


# --------------------------------------------------------------------------- estimators
@dataclass(frozen=True)
class SensorNoiseEstimate:
    """Range-bearing noise from residuals against the truth (see :func:`estimate_sensor_noise`)."""

    range_std_m: float
    bearing_std_rad: float
    range_bias_m: float
    bearing_bias_rad: float
    n_inliers: int
    n_outliers: int
    inlier: np.ndarray


def estimate_sensor_noise(
    residuals, *, gate_probability: float = DEFAULT_OUTLIER_GATE_PROBABILITY, max_iterations=100
) -> SensorNoiseEstimate:
    """Noise std of (range, bearing) from residuals (K, 2) (bearing wrapped), outliers excluded.

    Start from sigma = 1.4826 median|e| (robust), then iterate: inliers are the rows with
    (e_r / sigma_r)^2 + (e_b / sigma_b)^2 inside the chi-square(2) quantile
    ``-2 ln(1 - gate_probability)``; sigma = root mean square about zero of the inliers; stop when
    the inlier set no longer changes. The root mean square about zero includes any bias (reported
    separately as the inlier mean) because the filters model zero-mean noise.
    """
    e = np.asarray(residuals, dtype=float)
    require(e.ndim == 2 and e.shape[1] == 2, "residuals", e.shape, "a (K, 2) array")
    require(e.shape[0] >= 3, "residuals", e.shape[0], "at least 3 rows")
    require(bool(np.all(np.isfinite(e))), "residuals", "non-finite values", "finite numbers")
    check_range("gate_probability", gate_probability, 0.5, 1.0, high_open=True)
    gate2 = -2.0 * np.log1p(-gate_probability)
    sigma = 1.4826 * np.median(np.abs(e), axis=0)
    sigma = np.where(sigma > 0.0, sigma, np.sqrt(np.mean(e**2, axis=0)))
    require(bool(np.all(sigma > 0.0)), "residuals", "all zero", "some spread in each column")
    inlier = np.ones(e.shape[0], dtype=bool)
    for _ in range(max_iterations):
        new = np.sum((e / sigma) ** 2, axis=1) <= gate2
        if new.sum() < 3:
            break
        sigma = np.sqrt(np.mean(e[new] ** 2, axis=0))
        if np.array_equal(new, inlier):
            break
        inlier = new
    bias = e[inlier].mean(axis=0)
    return SensorNoiseEstimate(
        range_std_m=float(sigma[0]),
        bearing_std_rad=float(sigma[1]),
        range_bias_m=float(bias[0]),
        bearing_bias_rad=float(bias[1]),
        n_inliers=int(inlier.sum()),
        n_outliers=int((~inlier).sum()),
        inlier=inlier,
    )


@dataclass(frozen=True)
class SensorBiasModel:
    """Systematic (repeatable) camera errors, as functions of the measurement itself.

    Range error ``c0 + c1 r + c2 b + c3 b^2`` and bearing error ``d0 + d1 b`` of a measurement
    ``(r, b)``; :meth:`correct` subtracts them. On MRCLAM Dataset 7 the range error is
    dominated by the ``b^2`` term (about -1.5 to -1.9 m/rad^2: ranges read ~0.2 m long at the
    image centre and short at its edges, the camera's distortion), see
    :func:`estimate_sensor_bias`.
    """

    range_coef: tuple[float, float, float, float]
    bearing_coef: tuple[float, float]
    n_rows: int

    def bias(self, z) -> np.ndarray:
        z = np.asarray(z, dtype=float).reshape(-1, 2)
        c, d = self.range_coef, self.bearing_coef
        r, b = z[:, 0], z[:, 1]
        return np.column_stack([c[0] + c[1] * r + c[2] * b + c[3] * b * b, d[0] + d[1] * b])

    def correct(self, z) -> np.ndarray:
        """``z`` (K, 2) minus its bias (bearing wrapped, range kept >= 0)."""
        out = np.asarray(z, dtype=float).reshape(-1, 2) - self.bias(z)
        out[:, 0] = np.maximum(out[:, 0], 0.0)
        out[:, 1] = wrap_angle(out[:, 1])
        return out


def estimate_sensor_bias(z, residuals) -> SensorBiasModel:
    """Least-squares fit of :class:`SensorBiasModel` to ``residuals`` (K, 2) = z - h(x_true,
    m_true) of the measurements ``z`` (K, 2) (inliers only: pass the rows
    :func:`estimate_sensor_noise` kept). The regressors are the *measured* range and bearing, so
    the correction can be applied to new measurements without any truth."""
    z = np.asarray(z, dtype=float)
    e = np.asarray(residuals, dtype=float)
    require(z.ndim == 2 and z.shape[1] == 2, "z", z.shape, "a (K, 2) array")
    require(e.shape == z.shape, "residuals", e.shape, f"{z.shape} like z")
    require(z.shape[0] >= 8, "z", z.shape[0], "at least 8 rows")
    require(bool(np.all(np.isfinite(z)) and np.all(np.isfinite(e))), "residuals",
            "non-finite values", "finite numbers")
    r, b = z[:, 0], z[:, 1]
    A = np.column_stack([np.ones_like(r), r, b, b * b])
    c, *_ = np.linalg.lstsq(A, e[:, 0], rcond=None)
    d, *_ = np.linalg.lstsq(A[:, [0, 2]], e[:, 1], rcond=None)
    return SensorBiasModel(
        range_coef=tuple(float(x) for x in c), bearing_coef=tuple(float(x) for x in d),
        n_rows=int(z.shape[0]),
    )


def correlated_noise_std(residuals, times, groups, window_s: float) -> tuple[float, float]:
    """Per-measurement (range, bearing) std that a white-noise filter should assume when the
    errors are correlated in time: the white-noise rule of :func:`estimate_odometry_noise`
    applied to the sensor.

    The rows of each group (landmark) are cut into consecutive windows of ``window_s``; with
    ``n`` rows and mean residual ``m`` in a window, ``n m^2`` estimates ``sigma^2`` if the errors
    were white (the variance of a mean of n white errors is sigma^2 / n), and exceeds it by the
    correlation of the errors otherwise. Returns the root of the average of ``n m^2`` over all
    windows: the std whose white-noise average over a window matches the observed one. With
    ``window_s`` shorter than the gap between rows it is the root mean square of the residuals.
    """
    e = np.asarray(residuals, dtype=float)
    t = np.asarray(times, dtype=float).reshape(-1)
    g = np.asarray(groups).reshape(-1)
    require(e.ndim == 2 and e.shape[1] == 2, "residuals", e.shape, "a (K, 2) array")
    require(len(t) == len(g) == len(e) and len(e) >= 1, "times", t.shape,
            f"({len(e)},) like groups and residuals")
    check_range("window_s", window_s, 0.0, 1e6, low_open=True)
    total, n_windows = np.zeros(2), 0
    for group in np.unique(g):
        rows = g == group
        tg, eg = t[rows], e[rows]
        window = np.floor((tg - tg.min()) / window_s).astype(np.int64)
        _, inverse, counts = np.unique(window, return_inverse=True, return_counts=True)
        sums = np.zeros((len(counts), 2))
        np.add.at(sums, inverse, eg)
        total += np.sum(sums**2 / counts[:, None], axis=0)
        n_windows += len(counts)
    std = np.sqrt(total / n_windows)
    return float(std[0]), float(std[1])


def estimate_field_of_view(z, *, quantile: float = FIELD_QUANTILE) -> tuple[float, float]:
    """(max range, fov) from observations z (K, 2): the ``quantile`` of the ranges and twice the
    ``quantile`` of |bearing| (the sensor model's field is symmetric about the heading)."""
    z = np.asarray(z, dtype=float)
    require(z.ndim == 2 and z.shape[1] == 2 and z.shape[0] >= 1, "z", z.shape, "a (K, 2) array")
    check_range("quantile", quantile, 0.5, 1.0)
    max_range = float(np.quantile(z[:, 0], quantile))
    fov = float(min(2.0 * np.quantile(np.abs(wrap_angle(z[:, 1])), quantile), 2.0 * np.pi))
    return max_range, fov


@dataclass(frozen=True)
class OdometryNoiseEstimate:
    """A fitted :class:`ProportionalVelocityNoise` (see :func:`estimate_odometry_noise`)."""

    v_fraction: float
    omega_fraction: float
    v_floor_mps: float
    omega_floor_radps: float
    v_bias_mps: float
    omega_bias_radps: float
    window_s: float
    n_windows: int

    def model(self) -> ProportionalVelocityNoise:
        return ProportionalVelocityNoise(
            v_fraction=self.v_fraction,
            omega_fraction=self.omega_fraction,
            v_floor_mps=self.v_floor_mps,
            omega_floor_radps=self.omega_floor_radps,
        )


def true_velocities(row_t, poses, grid_t, sub_steps: int = 1) -> np.ndarray:
    """Mean true (v, omega) (M, 2) over each interval of ``grid_t`` (M + 1,) from a pose track.

    omega = wrapped heading change / interval; v = arc length / interval, the arc being the
    chord projected on the mid heading divided by sinc(dtheta / 2) (exact for a constant turn
    rate, the unicycle of :func:`filters.models.motion`). With ``sub_steps`` = k > 1 each
    interval is cut into k equal parts and the parts' arcs and heading changes are summed: over
    windows of several seconds the turn rate is not constant and the heading may change by more
    than pi, so one arc per window would take the chord for the path (on MRCLAM a 10 s window
    read that way shows up to twice the speed error there is).
    """
    check_range("sub_steps", sub_steps, 1, 1e6)
    require(int(sub_steps) == sub_steps, "sub_steps", sub_steps, "a whole number")
    if sub_steps > 1:
        grid_t = np.asarray(grid_t, dtype=float)
        parts = np.linspace(0.0, 1.0, int(sub_steps) + 1)[:-1]
        fine = np.append((grid_t[:-1, None] + np.diff(grid_t)[:, None] * parts).ravel(),
                         grid_t[-1])
        return true_velocities(row_t, poses, fine).reshape(-1, int(sub_steps), 2).mean(axis=1)
    p = interpolate_poses(row_t, poses, grid_t)
    dt = np.diff(np.asarray(grid_t, dtype=float))
    dtheta = wrap_angle(np.diff(p[:, 2]))
    mid = p[:-1, 2] + 0.5 * dtheta
    chord = np.diff(p[:, 0]) * np.cos(mid) + np.diff(p[:, 1]) * np.sin(mid)
    arc = chord / np.sinc(0.5 * dtheta / np.pi)
    return np.column_stack([arc / dt, dtheta / dt])


def odometry_window_fitting(window_s: float, span_s: float, dt_s: float) -> float:
    """``window_s``, shortened (to a whole number of steps, at least one) if the calibration part
    of ``span_s`` seconds holds fewer than :data:`MIN_ODOMETRY_WINDOWS` such windows; a
    shortened window is logged, since a shorter window under-states correlated errors (module
    doc, "Odometry noise")."""
    if span_s >= MIN_ODOMETRY_WINDOWS * window_s:
        return float(window_s)
    steps = max(1, int(np.floor(span_s / MIN_ODOMETRY_WINDOWS / dt_s + 1e-9)))
    shorter = round(steps * dt_s, 9)
    logger.warning("calibration part of %.1f s holds fewer than %d odometry windows of %g s: "
                   "odometry noise fitted over %g s windows", span_s, MIN_ODOMETRY_WINDOWS,
                   window_s, shorter)
    return float(shorter)


def estimate_odometry_noise(
    odometry_rows,
    groundtruth_rows,
    t_start: float,
    t_end: float,
    *,
    dt_s: float,
    window_s: float = DEFAULT_ODOMETRY_WINDOW_S,
    min_floor: float = MIN_ODOMETRY_FLOOR,
) -> OdometryNoiseEstimate:
    """Fit a per-step :class:`ProportionalVelocityNoise` to odometry against ground truth.

    ``odometry_rows`` (R, 3) t, v, omega (zero-order hold); ``groundtruth_rows`` (G, 4)
    t, x, y, theta. Over consecutive windows of ``window_s`` in [t_start, t_end] the error e of
    the window-mean odometry against :func:`true_velocities` is computed; with n = window_s / dt_s
    steps per window, a per-step white noise of variance s^2 gives a window-mean variance
    s^2 / n, so s^2 = n e^2 is fitted per component as ``fraction^2 u^2 + floor^2`` (u the
    measured window mean) by non-negative least squares. Floors are raised to ``min_floor``.
    """
    check_range("dt_s", dt_s, 0.0, 10.0, low_open=True)
    check_range("window_s", window_s, dt_s, 1000.0)
    check_range("min_floor", min_floor, 0.0, 1.0)
    odometry_rows = np.asarray(odometry_rows, dtype=float)
    groundtruth_rows = np.asarray(groundtruth_rows, dtype=float)
    n = int(np.floor((t_end - t_start) / window_s + 1e-9))
    require(n >= MIN_ODOMETRY_WINDOWS, "t_end", t_end,
            f"at least {MIN_ODOMETRY_WINDOWS} windows of {window_s} s after t_start={t_start}")
    grid = t_start + window_s * np.arange(n + 1)
    measured = hold_average(odometry_rows[:, 0], odometry_rows[:, 1:3], grid)
    truth = true_velocities(groundtruth_rows[:, 0], groundtruth_rows[:, 1:4], grid,
                            sub_steps=max(1, round(window_s / dt_s)))
    ok = np.all(np.isfinite(truth), axis=1)
    require(int(ok.sum()) >= MIN_ODOMETRY_WINDOWS, "groundtruth_rows", "too short",
            f"covering at least {MIN_ODOMETRY_WINDOWS} windows")
    u, err = measured[ok], measured[ok] - truth[ok]
    steps_per_window = window_s / dt_s
    fractions, floors = [], []
    for c in range(2):
        A = np.column_stack([u[:, c] ** 2, np.ones(u.shape[0])])
        coef, _ = nnls(A, steps_per_window * err[:, c] ** 2)
        fractions.append(float(min(np.sqrt(coef[0]), 5.0)))
        floors.append(float(min(max(np.sqrt(coef[1]), min_floor), 10.0)))
    bias = err.mean(axis=0)
    return OdometryNoiseEstimate(
        v_fraction=fractions[0],
        omega_fraction=fractions[1],
        v_floor_mps=floors[0],
        omega_floor_radps=floors[1],
        v_bias_mps=float(bias[0]),
        omega_bias_radps=float(bias[1]),
        window_s=float(window_s),
        n_windows=int(ok.sum()),
    )


# --------------------------------------------------------------------------- timing and scale
@dataclass(frozen=True)
class OdometryCorrection:
    """Systematic odometry errors: a logged (v, omega) row stamped ``t`` describes the motion
    from ``t + delay_s`` (the robot answers its commands late), the true speed is
    ``v (v_gain - v_turn_s_per_rad |omega|)`` (the robot slows down in turns; the factor is
    kept >= 0) and the true turn rate ``omega_gain omega`` (see
    :func:`estimate_odometry_correction`)."""

    delay_s: float
    v_gain: float
    v_turn_s_per_rad: float
    omega_gain: float
    n_windows: int

    def apply(self, odometry_rows) -> np.ndarray:
        """Rows (R, 3) t, v, omega with the times shifted and the speeds corrected."""
        out = np.array(odometry_rows, dtype=float, copy=True)
        factor = np.maximum(self.v_gain - self.v_turn_s_per_rad * np.abs(out[:, 2]), 0.0)
        out[:, 0] += self.delay_s
        out[:, 1] *= factor
        out[:, 2] *= self.omega_gain
        return out


def estimate_odometry_correction(
    odometry_rows, groundtruth_rows, t_start: float, t_end: float, *,
    window_s: float = ODOMETRY_CORRECTION_WINDOW_S, max_delay_s: float = MAX_DELAY_S,
    delay_step_s: float = DELAY_STEP_S,
) -> OdometryCorrection:
    """Delay and gains of the odometry against the ground truth over [t_start, t_end].

    The truth (v, omega) over consecutive windows of ``window_s`` (:func:`true_velocities`) is
    compared with the window means of the odometry rows shifted by each delay on a grid of
    ``delay_step_s`` in [-max_delay_s, max_delay_s]; the delay is the one with the smallest
    squared omega error (the turn rate changes often and fast, the speed hardly: omega carries
    the timing). With that delay, the true speed is fitted by least squares as
    ``v_gain mean(v) - v_turn_s_per_rad mean(v |omega|)`` over each window (means of the rows'
    zero-order hold, so the model applies row by row) and ``omega_gain`` is the least-squares
    factor of the true on the logged turn rate. On MRCLAM Dataset 7 the robots cover their
    logged speed in straight lines (v_gain about 1.0) and about 1.1 s/rad x |omega| less of it
    in turns; a single distance ratio fitted on a part with more turning than the rest would
    under-predict the rest by 6-8 %.
    """
    check_range("window_s", window_s, 0.01, 1000.0)
    check_range("max_delay_s", max_delay_s, 0.0, 10.0)
    check_range("delay_step_s", delay_step_s, 1e-4, 10.0)
    odo = np.asarray(odometry_rows, dtype=float)
    gt = np.asarray(groundtruth_rows, dtype=float)
    start = max(t_start, odo[0, 0] + max_delay_s)
    n = int(np.floor((t_end - start) / window_s + 1e-9))
    require(n >= 4, "t_end", t_end,
            f"at least 4 windows of {window_s} s after {start} (odometry start + max delay)")
    grid = start + window_s * np.arange(n + 1)
    truth = true_velocities(gt[:, 0], gt[:, 1:4], grid)
    ok = np.all(np.isfinite(truth), axis=1)
    require(int(ok.sum()) >= 4, "groundtruth_rows", "too short", "covering at least 4 windows")
    truth = truth[ok]
    delays = delay_step_s * np.arange(-round(max_delay_s / delay_step_s),
                                      round(max_delay_s / delay_step_s) + 1)
    cost = [np.sum((hold_average(odo[:, 0] + d, odo[:, 1:3], grid)[ok, 1] - truth[:, 1]) ** 2)
            for d in delays]
    delay = float(delays[int(np.argmin(cost))])
    columns = np.column_stack([odo[:, 1:3], odo[:, 1] * np.abs(odo[:, 2])])
    measured = hold_average(odo[:, 0] + delay, columns, grid)[ok]
    A = np.column_stack([measured[:, 0], -measured[:, 2]])
    if np.linalg.matrix_rank(A) == 2:
        (v_gain, v_turn), *_ = np.linalg.lstsq(A, truth[:, 0], rcond=None)
    else:  # no motion, or no turning while moving: nothing to fit the turn term on
        distance = float(np.sum(measured[:, 0]))
        v_gain, v_turn = (float(np.sum(truth[:, 0]) / distance) if distance else 1.0), 0.0
    turn = float(np.sum(measured[:, 1] ** 2))
    omega_gain = float(np.sum(truth[:, 1] * measured[:, 1]) / turn) if turn > 0.0 else 1.0
    return OdometryCorrection(delay, float(v_gain), float(v_turn), omega_gain, int(ok.sum()))


def estimate_measurement_delay(
    times, z, landmarks_xy, groundtruth_rows, *, max_delay_s: float = MAX_DELAY_S,
    delay_step_s: float = DELAY_STEP_S,
) -> float:
    """Delay ``d`` such that a measurement stamped ``t`` was taken at ``t + d``: the value on a
    grid of ``delay_step_s`` in [-max_delay_s, max_delay_s] with the smallest squared bearing
    residual against the truth at ``t + d`` (a late or early stamp turns every bearing by the
    robot's rotation in between; the range hardly changes at MRCLAM's speeds). Rows whose
    residual exceeds 5 robust std (1.4826 median |e|) at zero delay are left out. ``times``
    (K,), ``z`` (K, 2), ``landmarks_xy`` (K, 2) the true position of each row's landmark."""
    t = np.asarray(times, dtype=float).reshape(-1)
    z = np.asarray(z, dtype=float)
    m = np.asarray(landmarks_xy, dtype=float)
    gt = np.asarray(groundtruth_rows, dtype=float)
    require(z.shape == (t.size, 2) and m.shape == (t.size, 2), "z", z.shape,
            f"({t.size}, 2) like landmarks_xy, one row per time")
    check_range("max_delay_s", max_delay_s, 0.0, 10.0)
    check_range("delay_step_s", delay_step_s, 1e-4, 10.0)
    inside = (t - max_delay_s >= gt[0, 0]) & (t + max_delay_s <= gt[-1, 0])
    t, z, m = t[inside], z[inside], m[inside]
    require(t.size >= 8, "times", t.size, "at least 8 measurements inside the ground truth")

    def bearing_error(d):
        return innovation(z, observe(interpolate_poses(gt[:, 0], gt[:, 1:4], t + d), m))[:, 1]

    e0 = bearing_error(0.0)
    keep = np.abs(e0) <= 5.0 * 1.4826 * np.median(np.abs(e0))
    delays = delay_step_s * np.arange(-round(max_delay_s / delay_step_s),
                                      round(max_delay_s / delay_step_s) + 1)
    cost = [np.sum(bearing_error(d)[keep] ** 2) for d in delays]
    return float(delays[int(np.argmin(cost))])


def sighting_pass_duration(times, groups, *, max_gap_s: float = PASS_GAP_S) -> float:
    """Median duration of the passes over a landmark: runs of sightings of one group with no
    gap longer than ``max_gap_s`` (passes of a single sighting last 0 s and are left out;
    0.0 when there is none). Used as the window of :func:`correlated_noise_std`: a filter fuses
    a whole pass, over which the camera's errors stay correlated."""
    t = np.asarray(times, dtype=float).reshape(-1)
    g = np.asarray(groups).reshape(-1)
    require(t.size == g.size, "groups", g.shape, f"({t.size},) like times")
    durations = []
    for group in np.unique(g):
        tg = np.sort(t[g == group])
        cuts = np.flatnonzero(np.diff(tg) > max_gap_s)
        starts = np.r_[0, cuts + 1]
        ends = np.r_[cuts, tg.size - 1]
        durations.extend(tg[ends] - tg[starts])
    durations = np.asarray(durations)
    durations = durations[durations > 0.0]
    return float(np.median(durations)) if durations.size else 0.0


def landmarks_in_view(step_poses, landmarks_xy, sensor: RangeBearingSensor) -> np.ndarray:
    """(S, N) bool: landmark n inside the sensor field (range and fov) from true pose s."""
    step_poses = np.asarray(step_poses, dtype=float)
    landmarks_xy = np.asarray(landmarks_xy, dtype=float)
    z = observe(step_poses[:, None, :], landmarks_xy[None, :, :])
    return sensor.in_view(z) & np.all(np.isfinite(z), axis=-1)


@dataclass(frozen=True)
class DetectionRateEstimate:
    """Per-step sensor reliability (BB 5.1) measured against the truth."""

    alpha: float
    beta: float
    n_in_view: int
    n_detected_in_view: int
    n_detected_out_of_view: int
    n_false_alarms: int


def estimate_detection_rates(
    step_poses, landmarks_xy, sensor: RangeBearingSensor, det_steps, det_landmarks, n_false_alarms
) -> DetectionRateEstimate:
    """alpha = detected in-view (step, landmark) pairs / in-view pairs; beta = false alarms /
    in-view pairs.

    ``step_poses`` (S, 3) true poses at the steps; a landmark is in view when
    ``sensor.in_view(observe(pose, m))``; ``det_steps``, ``det_landmarks`` (D,) the step and
    landmark index of each true detection (several in one step count once).
    """
    in_view = landmarks_in_view(step_poses, landmarks_xy, sensor)
    detected = np.zeros(in_view.shape, dtype=bool)
    rows = np.asarray(det_steps, dtype=np.int64)
    detected[rows, np.asarray(det_landmarks, dtype=np.int64)] = True
    n_in_view = int(in_view.sum())
    n_hit = int((detected & in_view).sum())
    require(n_in_view > 0, "sensor", sensor, "a field in which some landmark is in view")
    require(n_hit > 0, "det_steps", "no detection in view", "at least one in-view detection")
    return DetectionRateEstimate(
        alpha=n_hit / n_in_view,
        beta=min(n_false_alarms / n_in_view, 0.999),
        n_in_view=n_in_view,
        n_detected_in_view=n_hit,
        n_detected_out_of_view=int((detected & ~in_view).sum()),
        n_false_alarms=int(n_false_alarms),
    )


# --------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class MrclamCalibration:
    """Every model parameter estimated from one robot's data (see the module docstring)."""

    sensor_noise: SensorNoiseEstimate
    odometry: OdometryNoiseEstimate
    detection: DetectionRateEstimate
    max_range_m: float
    fov_rad: float
    sensor_bias: SensorBiasModel | None = None
    noise_window_s: float | None = None
    filter_range_std_m: float | None = None
    filter_bearing_std_rad: float | None = None
    calibration_s: float | None = None
    odometry_correction: OdometryCorrection | None = None
    measurement_delay_s: float | None = None

    def as_dict(self) -> dict:
        """Flat numbers (no arrays), for ``Stream.metadata`` and reports."""
        noise = {k: v for k, v in asdict(self.sensor_noise).items() if k != "inlier"}
        bias = {}
        if self.sensor_bias is not None:
            bias = {f"range_bias_c{i}": c for i, c in enumerate(self.sensor_bias.range_coef)}
            bias |= {f"bearing_bias_d{i}": d for i, d in enumerate(self.sensor_bias.bearing_coef)}
        correction = {}
        if self.odometry_correction is not None:
            correction = {
                "odometry_delay_s": self.odometry_correction.delay_s,
                "odometry_v_gain": self.odometry_correction.v_gain,
                "odometry_v_turn_s_per_rad": self.odometry_correction.v_turn_s_per_rad,
                "odometry_omega_gain": self.odometry_correction.omega_gain,
            }
        return {
            **noise,
            **bias,
            **correction,
            "calibration_s": self.calibration_s,
            "measurement_delay_s": self.measurement_delay_s,
            "noise_window_s": self.noise_window_s,
            "filter_range_std_m": self.filter_range_std_m,
            "filter_bearing_std_rad": self.filter_bearing_std_rad,
            "max_range_m": self.max_range_m,
            "fov_rad": self.fov_rad,
            **{f"odometry_{k}": v for k, v in asdict(self.odometry).items()},
            **asdict(self.detection),
        }


@dataclass(frozen=True)
class _Layout:
    """The time grid and the classification of the measurement rows of one recording."""

    t0: float
    n_steps: int
    rel_t: np.ndarray  # (n + 1,) boundaries in seconds since t0
    row_step: np.ndarray  # (M,) step of each measurement row, -1 outside the grid
    row_landmark: np.ndarray  # (M,) landmark index, -1 = not a landmark
    row_is_robot: np.ndarray  # (M,) sighting of a robot subject
    residuals: np.ndarray  # (M, 2) z - h(x_true(step end), m_true) for landmark rows in the grid
    step_poses: np.ndarray  # (n, 3) true poses at the step ends
    row_z: np.ndarray  # (M, 2) the (range, bearing) each row hands the filter at its step's end


def compensate_motion(z, u, tau):
    """Observations ``z`` (K, 2) taken ``tau`` (K,) seconds before the end of their step, moved
    into the robot frame at the step's end with the step's odometry ``u`` (K, 2) = (v, omega):
    the point ``p`` seen at the measurement time is ``inverse(d) (+) p`` at the end, ``d`` the
    unicycle increment :func:`filters.models.motion` over ``tau``. Uses odometry only (no
    truth): it is what a filter stepping at ``dt_s`` would do with a time-stamped measurement.
    """
    z = np.asarray(z, dtype=float).reshape(-1, 2)
    u = np.asarray(u, dtype=float).reshape(-1, 2)
    tau = np.asarray(tau, dtype=float).reshape(-1)
    require(len(u) == len(tau) == len(z), "u", u.shape, f"({len(z)}, 2) like z, tau ({len(z)},)")
    d = motion(np.zeros((len(z), 3)), u, tau)
    px = z[:, 0] * np.cos(z[:, 1]) - d[:, 0]
    py = z[:, 0] * np.sin(z[:, 1]) - d[:, 1]
    c, s = np.cos(d[:, 2]), np.sin(d[:, 2])
    x, y = c * px + s * py, -s * px + c * py
    return np.column_stack([np.hypot(x, y), wrap_angle(np.arctan2(y, x))])


def _layout(rec: MrclamRecording, dt_s: float, motion_compensation: bool = False) -> _Layout:
    odo_t, gt_t = rec.odometry[:, 0], rec.groundtruth[:, 0]
    t0 = float(max(odo_t[0], gt_t[0]))
    t_end = float(min(odo_t[-1], gt_t[-1]))
    n = int(np.floor((t_end - t0) / dt_s + 1e-9))
    while n > 0 and t0 + dt_s * n > t_end:
        n -= 1
    require(n >= 1, "dt_s", dt_s, f"shorter than the recording ({t_end - t0:.3f} s)")
    rel_t = dt_s * np.arange(n + 1)
    boundaries = t0 + rel_t
    m_t = rec.measurements[:, 0]
    row_step = np.searchsorted(boundaries, m_t, side="left") - 1
    row_step = np.where((row_step >= 0) & (row_step < n), row_step, -1)
    row_landmark = rec.measurement_landmark_index()
    subjects = rec.measurement_subjects()
    row_is_robot = np.isin(subjects, ROBOT_SUBJECTS) & (row_landmark < 0)
    step_poses = interpolate_poses(gt_t, rec.groundtruth[:, 1:4], boundaries[1:])
    row_z = rec.measurements[:, 2:4].copy()
    if motion_compensation:
        inside = row_step >= 0
        u = hold_average(odo_t, rec.odometry[:, 1:3], boundaries)[row_step[inside]]
        tau = boundaries[row_step[inside] + 1] - m_t[inside]
        row_z[inside] = compensate_motion(row_z[inside], u, tau)
    residuals = np.full((m_t.size, 2), np.nan)
    lm = (row_landmark >= 0) & (row_step >= 0)
    predicted = observe(step_poses[row_step[lm]], rec.landmarks_xy[row_landmark[lm]])
    residuals[lm] = innovation(row_z[lm], predicted)
    return _Layout(
        t0, n, rel_t, row_step, row_landmark, row_is_robot, residuals, step_poses, row_z
    )


def _corrected(rec: MrclamRecording, calibration_s, odometry_correction: bool,
               timing_correction: bool):
    """``rec`` with its odometry and measurement times corrected, the corrections estimated on
    the first ``calibration_s`` seconds (None: all) after the raw start ``t0``; returns
    (recording, OdometryCorrection or None, measurement delay or None, end of the calibration
    part in Unix seconds)."""
    odo_t, gt_t = rec.odometry[:, 0], rec.groundtruth[:, 0]
    t0 = float(max(odo_t[0], gt_t[0]))
    t_end = float(min(odo_t[-1], gt_t[-1]))
    cal_end = t_end if calibration_s is None else min(t_end, t0 + float(calibration_s))
    correction, delay = None, None
    odometry, measurements = rec.odometry, rec.measurements
    if odometry_correction:
        correction = estimate_odometry_correction(rec.odometry, rec.groundtruth, t0, cal_end)
        odometry = correction.apply(rec.odometry)
    if timing_correction:
        index = rec.measurement_landmark_index()
        rows = (index >= 0) & (rec.measurements[:, 0] >= t0) & (rec.measurements[:, 0] <= cal_end)
        delay = estimate_measurement_delay(
            rec.measurements[rows, 0], rec.measurements[rows, 2:4],
            rec.landmarks_xy[index[rows]], rec.groundtruth,
        )
        measurements = rec.measurements.copy()
        measurements[:, 0] += delay
    rec = replace(rec, odometry=odometry, measurements=measurements)
    return rec, correction, delay, cal_end


def calibrate_mrclam(
    rec: MrclamRecording,
    *,
    dt_s: float = DEFAULT_DT_S,
    calibration_s: float | None = DEFAULT_CALIBRATION_S,
    odometry_window_s: float = DEFAULT_ODOMETRY_WINDOW_S,
    outlier_gate_probability: float = DEFAULT_OUTLIER_GATE_PROBABILITY,
    robot_sightings_as_clutter: bool = False,
    sensor: RangeBearingSensor | None = None,
    corrections: bool = True,
    motion_compensation: bool | None = None,
    sensor_bias_correction: bool | None = None,
    odometry_correction: bool | None = None,
    timing_correction: bool | None = None,
    correlated_noise: bool | None = None,
    noise_window_s: float | None = None,
) -> MrclamCalibration:
    """Estimate the models of one robot from the first ``calibration_s`` seconds of its
    recording (module docstring, "Calibration"); the options as in :func:`load_mrclam`.
    ``sensor``, when given, replaces the estimated sensor for the in-view test of the clutter
    rates."""
    options = MrclamOptions(calibration_s, corrections, motion_compensation,
                            sensor_bias_correction, odometry_correction, timing_correction,
                            correlated_noise, noise_window_s)
    return _calibrated(rec, options, dt_s=dt_s, odometry_window_s=odometry_window_s,
                       outlier_gate_probability=outlier_gate_probability,
                       robot_sightings_as_clutter=robot_sightings_as_clutter,
                       sensor=sensor)[3]


def _calibrated(rec, options: MrclamOptions, *, dt_s, **calibration_options):
    """The recording corrected as ``options`` say (odometry gains and delay, measurement time
    stamps), its step layout, the end of the calibration part, and :func:`_calibrate`'s
    calibration, outlier mask, sensor and observations: ``(rec, layout, cal_end, calibration,
    outlier, sensor, row_z)``."""
    flags = options.switches()
    rec, correction, delay, cal_end = _corrected(
        rec, options.calibration_s, flags["odometry_correction"], flags["timing_correction"]
    )
    lay = _layout(rec, dt_s, flags["motion_compensation"])
    return (rec, lay, cal_end, *_calibrate(
        rec,
        lay,
        dt_s=dt_s,
        cal_end=cal_end,
        calibration_s=options.calibration_s,
        sensor_bias_correction=flags["sensor_bias_correction"],
        correlated_noise=flags["correlated_noise"],
        noise_window_s=options.noise_window_s,
        odometry_correction=correction,
        measurement_delay_s=delay,
        **calibration_options,
    ))


CORRECTION_SWITCHES = ("motion_compensation", "sensor_bias_correction", "odometry_correction",
                       "timing_correction", "correlated_noise")
"""The corrections :class:`MrclamOptions` switches one by one (None: as ``corrections``)."""


@dataclass(frozen=True)
class MrclamOptions:
    """The calibration options of an MRCLAM recording, validated once: the loader
    (:func:`load_mrclam`), the calibration (:func:`calibrate_mrclam`), the env
    (:class:`slam_gym.envs.mrclam.MRCLAMEnv`) and ``slam-gym reproduce mrclam`` all build one.

    ``calibration_s``: the seconds every estimate uses (None: the whole recording; else in
    [10, 1e7]); ``corrections``: every correction on or off together; each of
    :data:`CORRECTION_SWITCHES`, when a bool, overrides ``corrections`` for its correction;
    ``noise_window_s``: the window of the white-noise rule (None: the measured pass duration;
    else > 0, and the rule is on). Meanings in :func:`load_mrclam`. A bad value raises
    ``ValueError`` naming the field; ``names`` maps a field to the name the caller's user gave it
    (the env's ``sensor_noise_window_s``), so the message names what the user wrote.
    """

    calibration_s: float | None = DEFAULT_CALIBRATION_S
    corrections: bool = True
    motion_compensation: bool | None = None
    sensor_bias_correction: bool | None = None
    odometry_correction: bool | None = None
    timing_correction: bool | None = None
    correlated_noise: bool | None = None
    noise_window_s: float | None = None
    names: InitVar[Mapping[str, str] | None] = None

    def __post_init__(self, names: Mapping[str, str] | None) -> None:
        def name(field: str) -> str:
            return (names or {}).get(field, field)

        require(isinstance(self.corrections, bool), name("corrections"), self.corrections,
                "a bool")
        for field in CORRECTION_SWITCHES:
            flag = getattr(self, field)
            require(flag is None or isinstance(flag, bool), name(field), flag, "None or a bool")
        if self.calibration_s is not None:
            check_range(name("calibration_s"), self.calibration_s, 10.0, 1e7)
        if self.noise_window_s is not None:
            check_range(name("noise_window_s"), self.noise_window_s, 0.0, 1e6, low_open=True)

    def switches(self) -> dict[str, bool]:
        """Each correction of :data:`CORRECTION_SWITCHES` on or off (None follows
        ``corrections``)."""
        return {field: self.corrections if getattr(self, field) is None else getattr(self, field)
                for field in CORRECTION_SWITCHES}

    def as_kwargs(self) -> dict:
        """The options as keyword arguments of :func:`load_mrclam`."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _calibrate(
    rec, lay, *, dt_s, cal_end, calibration_s, odometry_window_s, outlier_gate_probability,
    robot_sightings_as_clutter, sensor=None, range_std_m=None, bearing_std_rad=None,
    max_range_m=None, fov_rad=None, sensor_bias_correction=False, correlated_noise=False,
    noise_window_s=None, odometry_correction=None, measurement_delay_s=None,
):
    """Calibration (on the rows and steps up to ``cal_end``) plus the outlier mask over all
    rows, the stream's sensor and the rows' observations (bias-corrected if asked)."""
    usable_all = np.all(np.isfinite(lay.residuals), axis=1)
    part = rec.measurements[:, 0] <= cal_end
    usable = usable_all & part
    residuals, row_z = lay.residuals, lay.row_z
    noise = estimate_sensor_noise(residuals[usable], gate_probability=outlier_gate_probability)
    bias = None
    if sensor_bias_correction:
        rows = np.flatnonzero(usable)[noise.inlier]
        bias = estimate_sensor_bias(row_z[rows], residuals[rows])
        shift = bias.bias(row_z)
        row_z = bias.correct(row_z)
        residuals = residuals - shift
        residuals[:, 1] = wrap_angle(residuals[:, 1])
        noise = estimate_sensor_noise(
            residuals[usable], gate_probability=outlier_gate_probability
        )
    inliers = np.flatnonzero(usable)[noise.inlier]
    filter_std = (noise.range_std_m, noise.bearing_std_rad)
    if correlated_noise or noise_window_s is not None:
        if noise_window_s is None:
            noise_window_s = sighting_pass_duration(
                rec.measurements[inliers, 0], lay.row_landmark[inliers]
            )
        if noise_window_s > 0.0:
            filter_std = correlated_noise_std(
                residuals[inliers], rec.measurements[inliers, 0], lay.row_landmark[inliers],
                noise_window_s,
            )
    # outliers of every row (the labels of the truth ids) by the gate of the calibrated noise
    sigma = np.array([noise.range_std_m, noise.bearing_std_rad])
    gate2 = -2.0 * np.log1p(-outlier_gate_probability)
    outlier = np.zeros(lay.row_step.size, dtype=bool)
    rows = np.flatnonzero(usable_all)
    outlier[rows] = np.sum((residuals[rows] / sigma) ** 2, axis=1) > gate2
    outlier[np.flatnonzero(usable)] = ~noise.inlier
    good_z = rec.measurements[inliers, 2:4]
    est_range, est_fov = estimate_field_of_view(good_z)
    if sensor is None:
        sensor = RangeBearingSensor(
            range_std_m=filter_std[0] if range_std_m is None else range_std_m,
            bearing_std_rad=filter_std[1] if bearing_std_rad is None else bearing_std_rad,
            max_range_m=est_range if max_range_m is None else max_range_m,
            fov_rad=est_fov if fov_rad is None else fov_rad,
        )
    odometry_end = min(lay.t0 + lay.rel_t[-1], cal_end)
    window_s = odometry_window_fitting(odometry_window_s, odometry_end - lay.t0, dt_s)
    odometry = estimate_odometry_noise(
        rec.odometry,
        rec.groundtruth,
        lay.t0,
        odometry_end,
        dt_s=dt_s,
        window_s=window_s,
    )
    n_cal = int(np.searchsorted(lay.t0 + lay.rel_t[1:], cal_end, side="right"))
    n_cal = max(n_cal, 1)
    in_grid = (lay.row_step >= 0) & (lay.row_step < n_cal)
    hit = in_grid & (lay.row_landmark >= 0) & ~outlier
    false_alarm = in_grid & (lay.row_landmark >= 0) & outlier
    if robot_sightings_as_clutter:
        false_alarm |= in_grid & (lay.row_landmark < 0)
    detection = estimate_detection_rates(
        lay.step_poses[:n_cal],
        rec.landmarks_xy,
        sensor,
        lay.row_step[hit],
        lay.row_landmark[hit],
        int(false_alarm.sum()),
    )
    calibration = MrclamCalibration(
        noise, odometry, detection, est_range, est_fov, sensor_bias=bias,
        noise_window_s=noise_window_s, filter_range_std_m=sensor.range_std_m,
        filter_bearing_std_rad=sensor.bearing_std_rad, calibration_s=calibration_s,
        odometry_correction=odometry_correction, measurement_delay_s=measurement_delay_s,
    )
    return calibration, outlier, sensor, row_z


# --------------------------------------------------------------------------- the stream
def load_mrclam(
    directory,
    robot: int = 1,
    *,
    dt_s: float = DEFAULT_DT_S,
    known_association: bool = False,
    robot_sightings_as_clutter: bool = False,
    odometry_window_s: float = DEFAULT_ODOMETRY_WINDOW_S,
    outlier_gate_probability: float = DEFAULT_OUTLIER_GATE_PROBABILITY,
    range_std_m: float | None = None,
    bearing_std_rad: float | None = None,
    max_range_m: float | None = None,
    fov_rad: float | None = None,
    odometry_noise=None,
    clutter: ClutterModel | None = None,
    max_steps: int | None = None,
    calibration_s: float | None = DEFAULT_CALIBRATION_S,
    corrections: bool = True,
    motion_compensation: bool | None = None,
    sensor_bias_correction: bool | None = None,
    odometry_correction: bool | None = None,
    timing_correction: bool | None = None,
    correlated_noise: bool | None = None,
    noise_window_s: float | None = None,
) -> Stream:
    """The stream of one robot of an MRCLAM data set (see the module docstring).

    ``dt_s`` the filter period (default 0.1 s); ``known_association`` marks the stream for
    known-association filters (the runner passes ``truth.landmark_ids``);
    ``robot_sightings_as_clutter`` keeps robot sightings and unknown barcodes as clutter instead
    of dropping them. ``range_std_m``, ``bearing_std_rad``, ``max_range_m``, ``fov_rad``,
    ``odometry_noise`` and ``clutter`` override the estimates (None = estimated from the data);
    ``max_steps`` truncates the stream (the estimates do not depend on it).

    Calibration (module docstring, "Calibration"): every estimate uses the first
    ``calibration_s`` seconds (default 300; None = the whole recording) and nothing after them.
    ``corrections`` (default True) switches on, together, the corrections estimated there:
    ``odometry_correction`` (delay and gains of the odometry, :func:`estimate_odometry_correction`),
    ``timing_correction`` (the measurements' time stamp offset,
    :func:`estimate_measurement_delay`), ``motion_compensation`` (each measurement moved to its
    step's end with the odometry, :func:`compensate_motion`), ``sensor_bias_correction`` (the
    camera's systematic errors, :func:`estimate_sensor_bias`, subtracted from every
    measurement) and ``correlated_noise`` (the filters' std by the white-noise rule over one
    pass over a landmark, :func:`correlated_noise_std`, :func:`sighting_pass_duration`); each of
    them, when given as a bool, overrides ``corrections``. ``noise_window_s`` sets the window of
    the white-noise rule instead of the measured pass duration (and switches the rule on).
    """
    options = MrclamOptions(calibration_s, corrections, motion_compensation,
                            sensor_bias_correction, odometry_correction, timing_correction,
                            correlated_noise, noise_window_s)
    check_range("dt_s", dt_s, 0.001, 10.0)
    require(isinstance(known_association, bool), "known_association", known_association, "a bool")
    require(
        isinstance(robot_sightings_as_clutter, bool),
        "robot_sightings_as_clutter",
        robot_sightings_as_clutter,
        "a bool",
    )
    check_max_steps(max_steps)
    rec, lay, cal_end, calibration, outlier, sensor, row_z = _calibrated(
        read_mrclam(directory, robot), options, dt_s=dt_s, odometry_window_s=odometry_window_s,
        outlier_gate_probability=outlier_gate_probability,
        robot_sightings_as_clutter=robot_sightings_as_clutter, range_std_m=range_std_m,
        bearing_std_rad=bearing_std_rad, max_range_m=max_range_m, fov_rad=fov_rad,
    )
    if odometry_noise is None:
        odometry_noise = calibration.odometry.model()
    if clutter is None:
        clutter = ClutterModel(alpha=calibration.detection.alpha, beta=calibration.detection.beta)

    n = lay.n_steps if max_steps is None else min(lay.n_steps, int(max_steps))
    boundaries = lay.t0 + lay.rel_t[: n + 1]
    odometry = hold_average(rec.odometry[:, 0], rec.odometry[:, 1:3], boundaries)
    poses = lay.step_poses[:n].copy()
    visible = landmarks_in_view(poses, rec.landmarks_xy, sensor)
    initial_pose = interpolate_poses(rec.groundtruth[:, 0], rec.groundtruth[:, 1:4], [lay.t0])[0]

    is_landmark = lay.row_landmark >= 0
    keep = (lay.row_step >= 0) & (lay.row_step < n)
    if not robot_sightings_as_clutter:
        keep &= is_landmark
    rows = np.flatnonzero(keep)
    rows = rows[np.argsort(lay.row_step[rows], kind="stable")]
    z_all = row_z[rows].copy()
    ids_all = np.where(is_landmark[rows] & ~outlier[rows], lay.row_landmark[rows], -1)
    ids_all = ids_all.astype(np.int64)
    bounds = np.searchsorted(lay.row_step[rows], np.arange(n + 1), side="left")
    rel_t = lay.rel_t

    make_steps = ArraySteps(rel_t, dt_s, odometry, z_all, ids_all, bounds, poses, visible)

    in_grid = lay.row_step >= 0
    counts = {
        "measurement_rows": int(lay.row_step.size),
        "landmark_rows": int(is_landmark.sum()),
        "robot_sighting_rows": int(lay.row_is_robot.sum()),
        "unknown_barcode_rows": int((~is_landmark & ~lay.row_is_robot).sum()),
        "rows_outside_time_grid": int((~in_grid).sum()),
        "outlier_rows_in_grid": int((outlier & in_grid).sum()),
        "observations_in_stream": int(rows.size),
        "false_alarms_in_stream": int((ids_all < 0).sum()),
    }
    metadata = {
        "dataset": "MRCLAM",
        "directory": str(rec.directory),
        "robot": rec.robot,
        "t0_unix_s": lay.t0,
        "known_association": known_association,
        "robot_sightings": "clutter" if robot_sightings_as_clutter else "dropped",
        "corrections": corrections,
        **options.switches(),
        "calibration_end_s": cal_end - lay.t0,
        "landmark_subjects": tuple(int(s) for s in rec.landmark_subjects),
        "calibration": calibration.as_dict(),
        "counts": counts,
    }
    logger.info(
        "MRCLAM %s robot %d: %d steps, %d observations, sensor %s, clutter %s",
        rec.directory.name, rec.robot, n, rows.size, sensor, clutter,
    )
    return Stream(
        name=f"mrclam-{rec.directory.name}-robot{rec.robot}",
        sensor=sensor,
        clutter=clutter,
        odometry_noise=odometry_noise,
        initial_pose=initial_pose,
        landmarks_true=rec.landmarks_xy.copy(),
        n_steps=n,
        dt_s=float(dt_s),
        make_steps=make_steps,
        metadata=metadata,
    )
