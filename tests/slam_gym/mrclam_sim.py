"""A simulated recording written in MRCLAM's file format, with known noise and known errors.

:func:`write_simulated_mrclam` drives the simulator (:func:`slam_gym.world.simulate`) over a
small arena at MRCLAM-like speed, then writes what a robot of the UTIAS data set would have
logged: ``Barcodes.dat``, ``Landmark_Groundtruth.dat`` and ``Robot1_{Groundtruth, Odometry,
Measurement}.dat``. The systematic errors the loader is meant to find can be put in, each with a
known value: a late odometry (a row stamped ``t`` describes the motion from ``t + delay``), odometry
gains (the true speeds are ``v (v_gain - v_turn |omega|)`` and ``omega_gain omega`` of the logged
``v``, ``omega``: the robot slows down in turns), a time stamp offset of the
measurements and a camera bias (range error ``c0 + c3 b^2``, bearing error ``d0``, ``b`` the
true bearing). ``bias_after_s`` changes the camera bias from that many seconds on, to check
that the calibration never reads past its calibration part.
"""

from __future__ import annotations

from pathlib import Path
from types import MappingProxyType

import numpy as np

from slam_gym.scenarios import get_scenario
from slam_gym.world import simulate

T0 = 1_248_000_000.0
ROBOT_BARCODES = (5, 14, 41, 32, 23)
FIRST_LANDMARK_SUBJECT = 6
FIRST_LANDMARK_BARCODE = 100

#: the simulated arena: a 10 m loop at 0.07 m/s (about 570 s), 15 landmarks, a camera-like
#: field of view; noise known
SCENARIO = MappingProxyType({
    "world_size_m": 12.0,
    "n_landmarks": 15,
    "path_length_m": 40.0,
    "waypoint_spacing_m": 3.0,
    "path_perturbation_m": 0.5,
    "speed_mps": 0.07,
    "max_turn_rate_radps": 0.8,
    "initial_heading_spread_rad": 0.0,
    "range_std_m": 0.08,
    "bearing_std_rad": 0.02,
    "max_range_m": 6.0,
    "fov_rad": 1.2,
    "v_noise_fraction": 0.1,
    "omega_noise_fraction": 0.1,
})


def _write(path: Path, header: str, rows: np.ndarray, formats: str) -> None:
    np.savetxt(path, rows, fmt=formats, delimiter=" \t ", header=header, comments="# ")


def write_simulated_mrclam(
    directory, *, seed: int = 3, odometry_delay_s: float = 0.0, v_gain: float = 1.0,
    omega_gain: float = 1.0, v_turn_s_per_rad: float = 0.0, measurement_delay_s: float = 0.0,
    range_bias: tuple[float, float] = (0.0, 0.0), bearing_bias_rad: float = 0.0,
    bias_after_s: float | None = None, range_bias_after: tuple[float, float] = (0.0, 0.0),
) -> dict:
    """Write robot 1 of a simulated MRCLAM data set into ``directory``; returns the scenario's
    parameters (the true noise) and the number of steps. ``range_bias`` = (c0, c3)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    scenario = get_scenario("brooks-bailey", **SCENARIO)
    stream = simulate(scenario, seed)
    steps = list(stream)
    dt = stream.dt_s
    n_lm = len(stream.landmarks_true)

    subjects = np.arange(FIRST_LANDMARK_SUBJECT, FIRST_LANDMARK_SUBJECT + n_lm)
    barcodes = np.r_[
        np.column_stack([np.arange(1, 6), ROBOT_BARCODES]),
        np.column_stack([subjects, FIRST_LANDMARK_BARCODE + np.arange(n_lm)]),
    ]
    _write(directory / "Barcodes.dat", "Subject #    Barcode #", barcodes, "%d")
    landmarks = np.column_stack([subjects, stream.landmarks_true, np.zeros((n_lm, 2))])
    _write(directory / "Landmark_Groundtruth.dat", "Subject #    x [m]    y [m]    x std-dev [m]"
           "    y std-dev [m]", landmarks, "%d %.8f %.8f %.8f %.8f")

    k = np.arange(len(steps) + 1)
    poses = np.vstack([stream.initial_pose, [s.truth.pose for s in steps]])
    _write(directory / "Robot1_Groundtruth.dat", "Time [s]    x [m]    y [m]    orientation [rad]",
           np.column_stack([T0 + k * dt, poses]), "%.3f %.8f %.8f %.8f")
    u = np.array([s.odometry for s in steps])
    omega = u[:, 1] / omega_gain
    odometry = np.column_stack([T0 + k[:-1] * dt - odometry_delay_s,
                                u[:, 0] / (v_gain - v_turn_s_per_rad * np.abs(omega)), omega])
    _write(directory / "Robot1_Odometry.dat",
           "Time [s]    forward velocity [m/s]    angular velocity[rad/s]", odometry,
           "%.3f %.6f %.6f")

    rows = []
    for j, step in enumerate(steps):
        t_true = T0 + (j + 1) * dt
        late = bias_after_s is not None and (j + 1) * dt > bias_after_s
        c0, c3 = range_bias_after if late else range_bias
        pose = step.truth.pose
        for (r, b), lid in zip(step.z, step.truth.landmark_ids, strict=True):
            if lid < 0:
                continue
            d = stream.landmarks_true[lid] - pose[:2]
            b_true = np.arctan2(d[1], d[0]) - pose[2]
            b_true = (b_true + np.pi) % (2.0 * np.pi) - np.pi
            rows.append([t_true - measurement_delay_s, FIRST_LANDMARK_BARCODE + lid,
                         r + c0 + c3 * b_true**2, b + bearing_bias_rad])
    _write(directory / "Robot1_Measurement.dat",
           "Time [s]    Subject #    range [m]    bearing [rad]", np.array(rows),
           "%.3f %d %.6f %.6f")
    return {**SCENARIO, "n_steps": len(steps), "dt_s": dt}
