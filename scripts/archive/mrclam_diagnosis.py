"""Issue 16: what leaves EKF-SLAM with known association 0.7 m off on MRCLAM (docs/RESULTS.md).

Prints, for the robots given, (1) what the loader calibrates on the first ``--calibration-s``
seconds of each robot's recording (odometry delay and gains, measurement delay, camera bias,
noise) and (2) EKF-SLAM with known association under each of the loader's corrections alone,
all but one, and with the motion capture's own velocities as odometry (the floor the odometry
leaves). EKF-SLAM is deterministic, so one run per robot.

Usage: ``python scripts/archive/mrclam_diagnosis.py DATA_DIR [--robots 1,2,3,4,5]
[--calibration-s 300]``
(DATA_DIR: an MRCLAM data set directory, e.g. .../MRCLAM_Dataset7).

Supports docs/results/real_data.md, "Why known association left 0.7 m (issue 16 diagnosis)".
The command behind it::

    python scripts/archive/mrclam_diagnosis.py .../MRCLAM_Dataset7
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import logging

import numpy as np

from slam_gym.datasets import load_mrclam, read_mrclam
from slam_gym.datasets.estimators import true_velocities
from slam_gym.evaluation.core import run_system
from slam_gym.evaluation.real_data import mrclam_result

logger = logging.getLogger(__name__)

CORRECTIONS = ("odometry_correction", "timing_correction", "motion_compensation",
               "sensor_bias_correction", "correlated_noise")
CALIBRATION_KEYS = ("odometry_delay_s", "odometry_v_gain", "odometry_v_turn_s_per_rad",
                    "odometry_omega_gain", "measurement_delay_s", "range_bias_c0",
                    "range_bias_c3", "range_std_m", "bearing_std_rad", "noise_window_s",
                    "filter_range_std_m", "filter_bearing_std_rad")


def with_true_odometry(stream, data, robot):
    """``stream`` with each step's odometry replaced by the motion capture's mean (v, omega)."""
    steps = copy.copy(stream.make_steps)
    rec = read_mrclam(data, robot)
    grid = stream.metadata["t0_unix_s"] + steps.t_s[: len(steps) + 1]
    steps.odometry = true_velocities(rec.groundtruth[:, 0], rec.groundtruth[:, 1:4], grid)
    return dataclasses.replace(stream, make_steps=steps)


def run(data, robots, options, after_s, true_odometry=False):
    """Means over ``robots`` of map error, pose RMSE, pose RMSE after ``after_s`` seconds (the
    part the default calibration does not see) and ANEES."""
    rows = []
    for robot in robots:
        stream = load_mrclam(data, robot, **options)
        if true_odometry:
            stream = with_true_odometry(stream, data, robot)
        episode = run_system("ekf-slam", stream, 0, known_association=True,
                             stop_on_failure=False, record_trace=True)
        row = mrclam_result(episode, stream, robot, "known")
        errors = np.asarray(episode.trace.position_error_m, dtype=float)
        late = errors[np.asarray(episode.trace.t_s, dtype=float) > after_s]
        rows.append([row["map_error_m"], row["pose_rmse_m"], np.sqrt(np.mean(late**2)),
                     row["anees"]])
    return np.mean(np.asarray(rows, dtype=float), axis=0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--calibration-s", type=float, default=300.0)
    args = parser.parse_args(argv)
    robots = [int(r) for r in args.robots.split(",")]
    part = {"calibration_s": args.calibration_s}

    logger.info(f"calibration on the first {args.calibration_s:g} s")
    for robot in robots:
        cal = load_mrclam(args.data, robot, max_steps=1, **part).metadata["calibration"]
        logger.info(f"robot {robot}: " + ", ".join(f"{k} {cal[k]:.4g}" for k in CALIBRATION_KEYS))

    configs = [
        ("no corrections, whole recording", {"corrections": False, "calibration_s": None}, False),
        ("no corrections", {"corrections": False, **part}, False),
        *((f"+ {c} only", {"corrections": False, c: True, **part}, False) for c in CORRECTIONS),
        ("all (defaults)", part, False),
        *((f"all but {c}", {c: False, **part}, False) for c in CORRECTIONS),
        ("no corrections, true odometry", {"corrections": False, **part}, True),
        ("all, true odometry", part, True),
    ]
    logger.info("\nEKF-SLAM, known association, mean over robots "
          f"{args.robots}: map error, pose RMSE, pose RMSE after {args.calibration_s:g} s (m), "
          "ANEES")
    for name, options, true_odometry in configs:
        m = run(args.data, robots, options, args.calibration_s, true_odometry)
        logger.info(f"{name:40s} {m[0]:6.3f} {m[1]:6.3f} {m[2]:6.3f} {m[3]:8.1f}")
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
