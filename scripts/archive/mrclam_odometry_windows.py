"""Issue 16: how MRCLAM's odometry error grows with the span it is integrated over.

For each robot, fits :func:`slam_gym.datasets.estimators.estimate_odometry_noise` on the loader's
calibration part (the first ``--calibration-s`` seconds, odometry corrected as the loader does)
with windows of 1, 2, 5, 10, 20 and 30 s, and prints the fitted per-step std at the robot's
typical motion (v = 0.1 m/s, omega = 0.3 rad/s). Errors that were white would give the same std
for every window; errors correlated over seconds give a std that grows with the window until the
window outlasts the correlation. The loader's window (``DEFAULT_ODOMETRY_WINDOW_S``, BB's 10 s
local map) is the span over which a front-end integrates the odometry between fusions.

Usage: ``python scripts/archive/mrclam_odometry_windows.py DATA_DIR [--robots 1,2,3,4,5]
[--calibration-s 300] [--windows 1,2,5,10,20,30]``.

Supports docs/results/real_data.md, "HYBRID, robots 1-5, seeds 0-2, 200 particles, fusion every 10
s, the loader's defaults".
The command behind it::

    python scripts/archive/mrclam_odometry_windows.py .../MRCLAM_Dataset7
"""

from __future__ import annotations

import argparse
import logging

import numpy as np

from slam_gym.datasets import read_mrclam
from slam_gym.datasets.mrclam import DEFAULT_CALIBRATION_S, calibrate_mrclam

logger = logging.getLogger(__name__)

TYPICAL_V_MPS, TYPICAL_OMEGA_RADPS = 0.1, 0.3


def fitted_std(rec, window_s: float, calibration_s: float) -> tuple[float, float]:
    """Per-step (v, omega) std at the typical motion, fitted over windows of ``window_s``."""
    cal = calibrate_mrclam(rec, calibration_s=calibration_s, odometry_window_s=window_s).as_dict()
    v = np.hypot(cal["odometry_v_fraction"] * TYPICAL_V_MPS, cal["odometry_v_floor_mps"])
    omega = np.hypot(cal["odometry_omega_fraction"] * TYPICAL_OMEGA_RADPS,
                     cal["odometry_omega_floor_radps"])
    return float(v), float(omega)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--calibration-s", type=float, default=DEFAULT_CALIBRATION_S)
    parser.add_argument("--windows", default="1,2,5,10,20,30")
    args = parser.parse_args(argv)
    windows = [float(w) for w in args.windows.split(",")]
    logger.info("per-step std at v = %.2f m/s, omega = %.2f rad/s, fitted over windows of %s s",
                TYPICAL_V_MPS, TYPICAL_OMEGA_RADPS, ", ".join(f"{w:g}" for w in windows))
    logger.info("| robot | %s |", " | ".join(f"{w:g} s: v (m/s) / omega (rad/s)" for w in windows))
    logger.info("|---|%s", "---:|" * len(windows))
    for robot in (int(r) for r in args.robots.split(",")):
        rec = read_mrclam(args.data, robot)
        cells = [fitted_std(rec, w, args.calibration_s) for w in windows]
        logger.info("| %d | %s |", robot, " | ".join(f"{v:.3f} / {o:.3f}" for v, o in cells))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
