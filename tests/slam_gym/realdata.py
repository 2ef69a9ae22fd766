"""Where the real-data tests find their data (issue 17: a clean clone passes its tests).

``SLAM_GYM_DATA`` set (CI sets it to ``../shared/data``): the whole recordings there. Unset: the
excerpts in ``tests/data`` (cut by ``scripts/tools/make_test_excerpts.py``, which says how), and the
tests that need the whole recordings are skipped with :data:`needs_full_data`'s reason.
"""

import os
from pathlib import Path

import pytest

from slam_gym.datasets.location import DATA_ENV_VAR

EXCERPTS = Path(__file__).resolve().parents[1] / "data"
FULL_DATA = Path(os.environ[DATA_ENV_VAR]) if os.environ.get(DATA_ENV_VAR) else None
DATA = FULL_DATA or EXCERPTS
MRCLAM_DIR = DATA / "mrclam" / "MRCLAM_Dataset7"
VP_DIR = DATA / "victoria_park"

needs_full_data = pytest.mark.skipif(
    FULL_DATA is None,
    reason=f"needs the whole recordings: set {DATA_ENV_VAR} to the data directory "
    "(e.g. ../shared/data); the excerpts in tests/data are too short for it",
)
