"""Generic estimators of a recorded data set's models, from residuals against the truth: the
sensor's noise and systematic bias, its field of view, the odometry's noise, delay and gains, the
measurements' time stamp offset, the length of a pass over a landmark and the detection rates.

They know nothing of a file format: :mod:`slam_gym.datasets.mrclam` (whose docstring,
"Calibration", says how they are used) feeds them the rows of a recording.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from filters.geometry import wrap_angle
from filters.models import (
    ProportionalVelocityNoise,
    RangeBearingSensor,
    innovation,
    observe,
)
from filters.validation import check_range, require
from slam_gym.datasets.align import hold_average, interpolate_poses

logger = logging.getLogger(__name__)

DEFAULT_ODOMETRY_WINDOW_S = 10.0
"""Window (s) of the odometry-noise fit: BB's local-map length, the span over which a front-end
integrates the odometry between fusions (:mod:`slam_gym.datasets.mrclam`, "Odometry noise")."""
MIN_ODOMETRY_WINDOWS = 4
"""Fewest windows the odometry-noise fit takes (:func:`estimate_odometry_noise`)."""
ODOMETRY_CORRECTION_WINDOW_S = 1.0
"""Window (s) of the odometry delay and gain fit (:func:`estimate_odometry_correction`)."""
DEFAULT_OUTLIER_GATE_PROBABILITY = 0.9999
FIELD_QUANTILE = 0.995
MIN_ODOMETRY_FLOOR = 1e-3
#: timing offsets searched (+-) and their resolution
MAX_DELAY_S = 0.5
DELAY_STEP_S = 0.01
#: a landmark not seen for longer ends a pass over it (sighting_pass_duration)
PASS_GAP_S = 2.0


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
    from scipy.optimize import nnls  # here: scipy.optimize costs every process ~0.3 s

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
