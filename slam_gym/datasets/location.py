"""Where the real data sets are found when a command or env is not given a directory.

One setting: the environment variable ``SLAM_GYM_DATA`` names a directory holding
``mrclam/MRCLAM_Dataset7`` and ``victoria_park`` (the layout of the project's ``shared/data``).
Without it, ``../shared/data`` beside the repository is used when it exists.
"""

from __future__ import annotations

import os
from pathlib import Path

DATA_ENV_VAR = "SLAM_GYM_DATA"


def data_root() -> Path | None:
    """``$SLAM_GYM_DATA``, else ``../shared/data`` beside the repository, if it is a directory."""
    given = os.environ.get(DATA_ENV_VAR)
    path = Path(given) if given else Path(__file__).resolve().parents[2].parent / "shared" / "data"
    return path if path.is_dir() else None


def default_data_dir(*parts: str) -> Path | None:
    """``<data root>/<parts>`` if it exists (:func:`data_root`)."""
    root = data_root()
    if root is None:
        return None
    path = root.joinpath(*parts)
    return path if path.is_dir() else None
