"""Bad real-data files: ValueError naming the file and the line (issue 16)."""

import numpy as np
import pytest
from realdata import MRCLAM_DIR, VP_DIR

from slam_gym.datasets import load_mrclam, load_victoria_park
from slam_gym.datasets.tables import load_table


def _copy(src, dst):
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def _replace_line(path, n, text):
    lines = path.read_text().splitlines(keepends=True)
    lines[n - 1] = text + "\n"
    path.write_text("".join(lines))


def test_a_good_table_loads_and_comments_are_skipped(tmp_path):
    path = tmp_path / "t.dat"
    path.write_text("# time x\n1.0 2.0\n\n2.0 3.5  # note\n")
    np.testing.assert_array_equal(load_table(path, 2), [[1.0, 2.0], [2.0, 3.5]])


@pytest.mark.parametrize(
    "line, why", [("1.0 abc", "not a number"), ("1.0", "truncated row"), ("1.0 2.0 3.0", "extra"),
                  ("1.0 nan", "not finite")],
)
def test_a_malformed_line_is_named_by_file_and_line(tmp_path, line, why):
    path = tmp_path / "t.dat"
    path.write_text(f"# header\n1.0 2.0\n{line}\n3.0 4.0\n")
    with pytest.raises(ValueError, match=r"t\.dat line 3"):
        load_table(path, 2)


def test_empty_files_unsorted_times_and_missing_files(tmp_path):
    empty = tmp_path / "e.dat"
    empty.write_text("# only a header\n")
    with pytest.raises(ValueError, match="e.dat"):
        load_table(empty, 2)
    unsorted = tmp_path / "u.dat"
    unsorted.write_text("1.0 0\n3.0 0\n# comment\n2.0 0\n")
    with pytest.raises(ValueError, match=r"u\.dat line 4"):
        load_table(unsorted, 2, sorted_times=True)
    with pytest.raises(ValueError, match="directory"):
        load_table(tmp_path / "missing.dat", 2)


def test_loaders_name_the_bad_file_and_line(tmp_path):
    mrclam = _copy(MRCLAM_DIR, tmp_path / "mrclam")
    _replace_line(mrclam / "Robot2_Odometry.dat", 12, "1248446190.0  0.1")  # truncated row
    with pytest.raises(ValueError, match=r"Robot2_Odometry\.dat line 12"):
        load_mrclam(mrclam, 2)
    vp = _copy(VP_DIR, tmp_path / "vp")
    _replace_line(vp / "measurements.dat", 7, "0.9 20.0 x 0.3")
    with pytest.raises(ValueError, match=r"measurements\.dat line 7"):
        load_victoria_park(vp)
