"""Cut the small excerpts of the real data sets that the tests run on (tests/data/).

The tests must pass in a clone with nothing beside it, so the loaders and the real-data commands
are tested on excerpts kept in the repository; tests that need the whole recordings read them
from the directory in ``SLAM_GYM_DATA`` (CI points it at ``../shared/data``).

How the excerpts are cut (every kept line is copied byte for byte, header comments included):

* MRCLAM Dataset 7 (``mrclam/MRCLAM_Dataset7``): ``Barcodes.dat`` and
  ``Landmark_Groundtruth.dat`` whole; for each robot 1-5 the rows of ``RobotN_Odometry.dat``
  and ``RobotN_Measurement.dat`` with time in ``[t0, t0 + 60 s]``, ``t0`` the robot's first
  odometry time, and the ``RobotN_Groundtruth.dat`` rows in ``[t0 - 5 s, t0 + 61 s]`` (ground
  truth starts a few seconds before odometry in the recording, as the loader expects).
* Victoria Park (``victoria_park``): ``info.txt`` whole; the rows of ``inputs.dat``,
  ``measurements.dat`` and ``gps.dat`` with time below 120 s (the car starts moving after ~20 s).

Usage: ``python scripts/tools/make_test_excerpts.py SOURCE_DATA_DIR [OUT_DIR]`` (default OUT_DIR:
tests/data beside this script's repository).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

MRCLAM_SECONDS = 60.0
MRCLAM_TRUTH_MARGIN_S = (5.0, 1.0)
VP_SECONDS = 120.0


def _rows(path: Path) -> tuple[list[str], list[tuple[float, str]]]:
    """Header comment lines and (time, line) of the data lines of a text data file."""
    header, rows = [], []
    for line in path.read_text().splitlines(keepends=True):
        if line.lstrip().startswith("#") or not line.strip():
            header.append(line)
        else:
            rows.append((float(line.split()[0]), line))
    return header, rows


def _write(path: Path, header: list[str], rows: list[tuple[float, str]], lo: float, hi: float):
    path.parent.mkdir(parents=True, exist_ok=True)
    kept = [line for t, line in rows if lo <= t <= hi]
    path.write_text("".join(header) + "".join(kept))
    return len(kept)


def cut_mrclam(source: Path, out: Path) -> None:
    for name in ("Barcodes.dat", "Landmark_Groundtruth.dat"):
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text((source / name).read_text())
    for robot in range(1, 6):
        odo_header, odo = _rows(source / f"Robot{robot}_Odometry.dat")
        t0 = odo[0][0]
        t1 = t0 + MRCLAM_SECONDS
        _write(out / f"Robot{robot}_Odometry.dat", odo_header, odo, t0, t1)
        header, rows = _rows(source / f"Robot{robot}_Measurement.dat")
        _write(out / f"Robot{robot}_Measurement.dat", header, rows, t0, t1)
        header, rows = _rows(source / f"Robot{robot}_Groundtruth.dat")
        before, after = MRCLAM_TRUTH_MARGIN_S
        _write(out / f"Robot{robot}_Groundtruth.dat", header, rows, t0 - before, t1 + after)


def cut_victoria_park(source: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "info.txt").write_text((source / "info.txt").read_text())
    for name in ("inputs.dat", "measurements.dat", "gps.dat"):
        header, rows = _rows(source / name)
        _write(out / name, header, rows, -1e9, VP_SECONDS)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("source", type=Path, help="the data directory (mrclam/, victoria_park/)")
    parser.add_argument("out", type=Path, nargs="?",
                        default=Path(__file__).resolve().parents[2] / "tests/data",
                        help="where to write the excerpts (default: tests/data)")
    args = parser.parse_args(argv)
    source, out = args.source, args.out
    cut_mrclam(source / "mrclam" / "MRCLAM_Dataset7", out / "mrclam" / "MRCLAM_Dataset7")
    cut_victoria_park(source / "victoria_park", out / "victoria_park")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
