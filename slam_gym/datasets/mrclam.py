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

Calibration (:func:`calibrate_mrclam`; the estimators are the generic ones of
:mod:`slam_gym.datasets.estimators`; every estimate is in ``Stream.metadata["calibration"]``, an
explicit keyword overrides it). **What is used:** the
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
  0.029-0.038 m/s over 20-30 s; ``scripts/archive/mrclam_odometry_windows.py``). The default
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

from filters.geometry import wrap_angle
from filters.models import (
    ClutterModel,
    RangeBearingSensor,
    innovation,
    motion,
    observe,
)
from filters.validation import check_range, require
from slam_gym.datasets.align import hold_average, interpolate_poses
from slam_gym.datasets.estimators import (
    DEFAULT_ODOMETRY_WINDOW_S,
    DEFAULT_OUTLIER_GATE_PROBABILITY,
    DetectionRateEstimate,
    OdometryCorrection,
    OdometryNoiseEstimate,
    SensorBiasModel,
    SensorNoiseEstimate,
    correlated_noise_std,
    estimate_detection_rates,
    estimate_field_of_view,
    estimate_measurement_delay,
    estimate_odometry_correction,
    estimate_odometry_noise,
    estimate_sensor_bias,
    estimate_sensor_noise,
    landmarks_in_view,
    odometry_window_fitting,
    sighting_pass_duration,
)
from slam_gym.datasets.tables import check_max_steps, load_table
from slam_gym.stream import ArraySteps, Stream

logger = logging.getLogger(__name__)

ROBOT_SUBJECTS = (1, 2, 3, 4, 5)
DEFAULT_DT_S = 0.1
#: the first seconds of a recording the calibration uses (the rest is held out)
DEFAULT_CALIBRATION_S = 300.0


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
