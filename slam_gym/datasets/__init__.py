"""Real data sets as :class:`slam_gym.stream.Stream` s (docs/ARCHITECTURE.md, "The data stream"),
and SE(2) alignment.

* :func:`load_mrclam` — UTIAS MRCLAM, any data set directory, robots 1-5, with ground-truth poses
  and landmarks; sensor, odometry and clutter models estimated from the data
  (:mod:`slam_gym.datasets.mrclam`).
* :func:`load_victoria_park` — ACFR Victoria Park trees, Ackermann odometry reduced to the rear
  axle, laser detections moved to the rear axle; GPS only as truth
  (:mod:`slam_gym.datasets.victoria_park`).
* :func:`fit_se2`, :func:`path_error_after_alignment` — rigid alignment of an estimated path to a
  reference in another frame (:mod:`slam_gym.datasets.align`).
"""

from slam_gym.datasets.align import (
    AlignedPathError,
    fit_se2,
    hold_average,
    interpolate_poses,
    path_error_after_alignment,
)
from slam_gym.datasets.mrclam import MrclamCalibration, calibrate_mrclam, load_mrclam, read_mrclam
from slam_gym.datasets.victoria_park import (
    UNKNOWN_LANDMARK_ID,
    VehicleGeometry,
    load_victoria_park,
    read_victoria_park,
)

__all__ = [
    "UNKNOWN_LANDMARK_ID",
    "AlignedPathError",
    "MrclamCalibration",
    "VehicleGeometry",
    "calibrate_mrclam",
    "fit_se2",
    "hold_average",
    "interpolate_poses",
    "load_mrclam",
    "load_victoria_park",
    "path_error_after_alignment",
    "read_mrclam",
    "read_victoria_park",
]
