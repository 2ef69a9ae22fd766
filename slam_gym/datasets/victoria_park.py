"""ACFR Victoria Park (Sydney) as a :class:`~slam_gym.stream.Stream` (docs/ARCHITECTURE.md, "The
data stream").

Guivant and Nebot, "Optimization of the simultaneous localization and map-building algorithm for
real-time implementation", IEEE T-RA 17(3), 2001. A directory holds ``inputs.dat`` (t, speed of
the encoder wheel [m/s], steering [rad]; 40 Hz), ``measurements.dat`` (t, range [m], bearing
[rad] in the laser frame 0..pi, tree diameter [m]; trees already extracted from the scans),
``gps.dat`` (t, x, y; intermittent, in its own rotated and shifted frame) and ``info.txt`` (the
car geometry). Times are seconds.

**Vehicle model.** The car is an Ackermann vehicle; the filters know only a unicycle (v, omega)
with the sensor at the robot origin. The robot frame is therefore put at the centre of the rear
axle, which moves exactly as a unicycle: with wheelbase L and steering angle delta the turn rate
is ``omega = v_c tan(delta) / L``. The speed is measured by an encoder on the *left rear* wheel,
at lateral offset H from the centre line; in a turn it runs at ``v_e = v_c (1 - tan(delta) H/L)``,
so ``v_c = v_e / (1 - tan(delta) H / L)`` (:func:`ackermann_to_unicycle`; positive steering turns
left, which makes the left wheel the inner one).

**Laser offset.** info.txt gives a = 0.95 m, b = 0.5 m, H = 0.76 m, L = 2.83 m. ``a`` is measured
from the *front* axle, so the laser sits ``L + a = 3.78`` m ahead of the rear axle and ``b =
0.5`` m to its left (the Guivant-Nebot point-of-interest model, also the 3.78 / 0.50 offsets of
the RFS-SLAM Victoria Park configuration). The laser reports bearings 0..pi from its right to its
left, so its bearing in the vehicle's convention (counter-clockwise from ahead) is
``bearing - pi/2``. We checked all of this on the data: dead-reckoning the first scans' detections
into the plane and comparing each scan with the scans 1-4 s later (detections within 30 m), the
median distance to the nearest detection is 0.18 m with (3.78, +0.5), 0.19 m with (3.78, 0),
0.21 m with (3.78, -0.5), 0.28 m with (0.95, +0.5) and 1.7 m with the bearing mirrored.
:func:`laser_to_vehicle` converts each detection (r_l, b_l) into a range-bearing from the rear
axle: ``p = (x_L + r_l cos(b_l - pi/2), y_L + r_l sin(b_l - pi/2))``,
``z = (|p|, atan2(p_y, p_x))``.

*Effect on the noise.* With laser-frame noise (s_r, s_b) the transformed observation has
covariance ``J diag(s_r^2, s_b^2) J^T``, J the Jacobian of that map: the range std stays about
s_r, the bearing std shrinks by about r_l / r (< 1, since the origin is 3.8 m behind the laser)
and a small range-bearing correlation appears for trees off the axis. The stream keeps the
laser's (s_r, s_b) as a constant, slightly conservative ``RangeBearingSensor`` noise.

**Noise defaults are assumptions** (the data set has no pose or landmark truth to measure them
against): range std 0.5 m and bearing std 1 degree per tree (conservative against the laser's
0.5 degree beam spacing and the tree-centre fit; the dead-reckoned self-consistency above, a
median 0.18 m between sightings, includes two detections' noise and the drift); RFS-SLAM's
configuration uses 0.16 m and 0.005 rad before inflating the variances 40-fold. Odometry noise
(:func:`default_odometry_noise`): over a one-second horizon, a speed std of 3 % plus 0.02 m/s
and a turn-rate std of 5 % plus 0.01 rad/s, converted to the per-step std of a
:class:`ProportionalVelocityNoise` by the white-noise rule (x sqrt(1 s / dt)). Sensor
reliability: a tree in view is detected in a scan with probability 0.9 (RFS-SLAM's value) and
triggers a false alarm with probability 0.1; the scanner delivers a scan about every 0.21 s
(median spacing of the scans, measured) so per filter step alpha and beta are these times
min(1, dt / scan period).

**Stream.** Steps of ``dt_s`` (default 0.025 s, the input rate) from the first input row; a
step's odometry is the time-weighted mean of the rows' (v_c, omega) over it (zero-order hold);
its observations are the detections with time in the step, in file order, those farther than
``max_range_m`` from the rear axle dropped (default 30 m: the laser reports trees up to 75 m,
but 61 % of detections are within 30 m of the rear axle and far detections are the least
reliable; ``max_range_m=None`` keeps all). The sensor field is ``fov = pi`` (the laser's 180
degrees; seen from the rear axle every detection lies within +-1.46 rad). There is no truth:
``truth.pose`` is NaN and every ``truth.landmark_ids`` entry is :data:`UNKNOWN_LANDMARK_ID` (-2,
"unknown", not a false alarm; a known-association filter cannot run here);
``truth.visible_ids`` is None (unknown; every step is still a filter update with the per-step
alpha and beta above); ``landmarks_true`` is empty, so metrics skip the map error.
``metadata["gps"]`` holds the GPS fixes (t in stream seconds, x, y) for
:func:`slam_gym.datasets.align.path_error_after_alignment`.
"""

from __future__ import annotations

import logging
import re
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from filters.models import ClutterModel, ProportionalVelocityNoise, RangeBearingSensor
from filters.validation import check_range, require
from slam_gym.datasets.align import hold_average
from slam_gym.datasets.tables import check_max_steps, load_table
from slam_gym.stream import ArraySteps, Stream

logger = logging.getLogger(__name__)

UNKNOWN_LANDMARK_ID = -2
DEFAULT_DT_S = 0.025
DEFAULT_MAX_RANGE_M = 30.0
DEFAULT_RANGE_STD_M = 0.5
DEFAULT_BEARING_STD_RAD = float(np.deg2rad(1.0))
DEFAULT_DETECTION_PROBABILITY = 0.9
DEFAULT_FALSE_ALARM_PROBABILITY = 0.1
# One-second-horizon odometry stds (assumed): fraction of |u| and floor, for v and omega.
ODOMETRY_STD_1S = {"v_fraction": 0.03, "v_floor": 0.02, "omega_fraction": 0.05, "omega_floor": 0.01}


@dataclass(frozen=True)
class VehicleGeometry:
    """Car geometry of info.txt: laser ``a_m`` ahead of the front axle and ``b_m`` left of the
    centre line, encoder wheel ``h_m`` left of the centre line, wheelbase ``l_m``."""

    a_m: float = 0.95
    b_m: float = 0.5
    h_m: float = 0.76
    l_m: float = 2.83

    def __post_init__(self):
        check_range("a_m", self.a_m, -10.0, 10.0)
        check_range("b_m", self.b_m, -10.0, 10.0)
        check_range("h_m", self.h_m, 0.0, 10.0)
        check_range("l_m", self.l_m, 0.1, 20.0)

    @property
    def laser_xy(self) -> np.ndarray:
        """Laser position in the rear-axle frame (x ahead, y left)."""
        return np.array([self.l_m + self.a_m, self.b_m])


def read_geometry(info_path) -> VehicleGeometry:
    """The car parameters ``a``, ``b``, ``H``, ``L`` from info.txt (defaults for missing ones)."""
    text = Path(info_path).read_text(errors="replace")
    found = {}
    for key, value in re.findall(r"^\s*([abHL])\s*:\s*([-+0-9.eE]+)\s*m\b", text, re.MULTILINE):
        found[key] = float(value)
    names = {"a": "a_m", "b": "b_m", "H": "h_m", "L": "l_m"}
    missing = sorted(set(names) - set(found))
    if missing:
        logger.warning("%s: no value for %s, using the published defaults", info_path, missing)
    return VehicleGeometry(**{names[k]: v for k, v in found.items()})


def ackermann_to_unicycle(speed, steering, geometry: VehicleGeometry):
    """(v_c, omega) of the rear-axle centre from the encoder speed and the steering angle."""
    speed = np.asarray(speed, dtype=float)
    tan_delta = np.tan(np.asarray(steering, dtype=float))
    scale = 1.0 - tan_delta * geometry.h_m / geometry.l_m
    require(bool(np.all(scale > 0.1)), "steering", "too large", "|tan(steering)| H / L < 0.9")
    v_c = speed / scale
    return v_c, v_c * tan_delta / geometry.l_m


def laser_to_vehicle(range_m, bearing_laser_rad, geometry: VehicleGeometry) -> np.ndarray:
    """Range-bearing (K, 2) from the rear-axle origin of laser detections (laser bearing 0..pi,
    right to left; pi/2 straight ahead)."""
    r = np.asarray(range_m, dtype=float)
    b = np.asarray(bearing_laser_rad, dtype=float) - 0.5 * np.pi
    x = geometry.laser_xy[0] + r * np.cos(b)
    y = geometry.laser_xy[1] + r * np.sin(b)
    return np.stack([np.hypot(x, y), np.arctan2(y, x)], axis=-1)


def default_odometry_noise(dt_s: float) -> ProportionalVelocityNoise:
    """Per-step odometry noise equal to the assumed one-second stds (:data:`ODOMETRY_STD_1S`)
    under the white-noise rule: per-step std = one-second std x sqrt(1 s / dt_s)."""
    check_range("dt_s", dt_s, 0.0, 10.0, low_open=True)
    k = np.sqrt(1.0 / dt_s)
    return ProportionalVelocityNoise(
        v_fraction=float(min(ODOMETRY_STD_1S["v_fraction"] * k, 5.0)),
        omega_fraction=float(min(ODOMETRY_STD_1S["omega_fraction"] * k, 5.0)),
        v_floor_mps=float(min(ODOMETRY_STD_1S["v_floor"] * k, 10.0)),
        omega_floor_radps=float(min(ODOMETRY_STD_1S["omega_floor"] * k, 10.0)),
    )


@dataclass(frozen=True)
class VictoriaParkRecording:
    """The raw tables: ``inputs`` (N, 3) t, speed, steering; ``measurements`` (M, 4) t, range,
    laser bearing, diameter; ``gps`` (G, 3) t, x, y; the car ``geometry``."""

    directory: Path
    inputs: np.ndarray
    measurements: np.ndarray
    gps: np.ndarray
    geometry: VehicleGeometry


def read_victoria_park(directory, geometry: VehicleGeometry | None = None) -> VictoriaParkRecording:
    """Parse a Victoria Park directory (geometry from info.txt unless given)."""
    directory = Path(directory)
    require(directory.is_dir(), "directory", str(directory), "an existing Victoria Park directory")
    if geometry is None:
        info = directory / "info.txt"
        geometry = read_geometry(info) if info.is_file() else VehicleGeometry()
    return VictoriaParkRecording(
        directory=directory,
        inputs=load_table(directory / "inputs.dat", 3, sorted_times=True),
        measurements=load_table(directory / "measurements.dat", 4, sorted_times=True),
        gps=load_table(directory / "gps.dat", 3, sorted_times=True),
        geometry=geometry,
    )


def load_victoria_park(
    directory,
    *,
    dt_s: float = DEFAULT_DT_S,
    max_range_m: float | None = DEFAULT_MAX_RANGE_M,
    range_std_m: float = DEFAULT_RANGE_STD_M,
    bearing_std_rad: float = DEFAULT_BEARING_STD_RAD,
    detection_probability: float = DEFAULT_DETECTION_PROBABILITY,
    false_alarm_probability: float = DEFAULT_FALSE_ALARM_PROBABILITY,
    odometry_noise=None,
    geometry: VehicleGeometry | None = None,
    max_steps: int | None = None,
) -> Stream:
    """The Victoria Park run as a stream (see the module docstring).

    ``dt_s`` the filter period; ``max_range_m`` drops detections farther from the rear axle
    (None keeps all, and the sensor range is then the farthest detection); ``range_std_m`` and
    ``bearing_std_rad`` the assumed sensor noise; ``detection_probability`` and
    ``false_alarm_probability`` the assumed per-scan reliability, scaled to per-step alpha and
    beta; ``odometry_noise`` defaults to :func:`default_odometry_noise`; ``geometry`` defaults to
    info.txt; ``max_steps`` truncates the stream.
    """
    check_range("dt_s", dt_s, 0.001, 10.0)
    if max_range_m is not None:
        check_range("max_range_m", max_range_m, 0.0, 1000.0, low_open=True)
    check_range("detection_probability", detection_probability, 0.0, 1.0, low_open=True)
    check_range("false_alarm_probability", false_alarm_probability, 0.0, 1.0, high_open=True)
    check_max_steps(max_steps)
    rec = read_victoria_park(directory, geometry)
    geometry = rec.geometry
    t_in = rec.inputs[:, 0]
    t0 = float(t_in[0])
    n_total = int(np.floor((t_in[-1] - t0) / dt_s + 1e-9))
    require(n_total >= 1, "dt_s", dt_s, f"shorter than the recording ({t_in[-1] - t0:.3f} s)")
    n = n_total if max_steps is None else min(n_total, int(max_steps))
    rel_t = dt_s * np.arange(n + 1)
    boundaries = t0 + rel_t

    v_c, omega = ackermann_to_unicycle(rec.inputs[:, 1], rec.inputs[:, 2], geometry)
    odometry = hold_average(t_in, np.column_stack([v_c, omega]), boundaries)

    m = rec.measurements
    z_vehicle = laser_to_vehicle(m[:, 1], m[:, 2], geometry)
    row_step = np.searchsorted(boundaries, m[:, 0], side="left") - 1
    in_grid = (row_step >= 0) & (row_step < n)
    in_range = np.ones(m.shape[0], dtype=bool) if max_range_m is None else (
        z_vehicle[:, 0] <= max_range_m
    )
    rows = np.flatnonzero(in_grid & in_range)
    z_all = z_vehicle[rows]
    bounds = np.searchsorted(row_step[rows], np.arange(n + 1), side="left")

    scan_times = np.unique(m[:, 0])
    scan_period = float(np.median(np.diff(scan_times))) if scan_times.size > 1 else dt_s
    frames_per_step = min(1.0, dt_s / scan_period)
    clutter = ClutterModel(
        alpha=detection_probability * frames_per_step,
        beta=false_alarm_probability * frames_per_step,
    )
    sensor = RangeBearingSensor(
        range_std_m=range_std_m,
        bearing_std_rad=bearing_std_rad,
        max_range_m=float(z_vehicle[:, 0].max()) if max_range_m is None else float(max_range_m),
        fov_rad=float(np.pi),
    )
    if odometry_noise is None:
        odometry_noise = default_odometry_noise(dt_s)

    make_steps = ArraySteps(
        rel_t, dt_s, odometry, z_all, np.full(len(z_all), UNKNOWN_LANDMARK_ID, dtype=np.int64),
        bounds, np.full((n, 3), np.nan),
    )

    gps = rec.gps.copy()
    gps[:, 0] -= t0
    metadata = {
        "dataset": "Victoria Park",
        "directory": str(rec.directory),
        "t0_s": t0,
        "gps": gps,
        "geometry": {**asdict(geometry), "laser_x_m": float(geometry.laser_xy[0]),
                     "laser_y_m": float(geometry.laser_xy[1])},
        "scan_period_s": scan_period,
        "frames_per_step": frames_per_step,
        "assumptions": {
            "range_std_m": range_std_m,
            "bearing_std_rad": bearing_std_rad,
            "detection_probability_per_scan": detection_probability,
            "false_alarm_probability_per_scan": false_alarm_probability,
            "odometry_std_1s": dict(ODOMETRY_STD_1S),
        },
        "counts": {
            "input_rows": int(t_in.size),
            "detection_rows": int(m.shape[0]),
            "rows_outside_time_grid": int((~in_grid).sum()),
            "rows_beyond_max_range": int((in_grid & ~in_range).sum()),
            "observations_in_stream": int(rows.size),
            "scans": int(scan_times.size),
            "gps_fixes": int(gps.shape[0]),
        },
        "duration_s": float(rel_t[-1]),
        "known_association": False,
    }
    logger.info(
        "Victoria Park: %d steps (%.1f s), %d observations, clutter %s",
        n, rel_t[-1], rows.size, clutter,
    )
    return Stream(
        name="victoria-park",
        sensor=sensor,
        clutter=clutter,
        odometry_noise=odometry_noise,
        initial_pose=np.zeros(3),
        landmarks_true=np.empty((0, 2)),
        n_steps=n,
        dt_s=float(dt_s),
        make_steps=make_steps,
        metadata=metadata,
    )
