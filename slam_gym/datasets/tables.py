"""Reading the whitespace-separated text tables of the real data sets, with errors a user can act
on: a bad file is named with the line (1-based, as an editor counts) that is wrong."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from filters.validation import require


def check_max_steps(max_steps) -> None:
    """A loader's ``max_steps``: None (the whole recording) or an integer >= 1, else
    ``ValueError`` naming ``max_steps``."""
    if max_steps is not None:
        require(
            isinstance(max_steps, (int, np.integer)) and not isinstance(max_steps, bool)
            and max_steps >= 1,
            "max_steps",
            max_steps,
            "None or an integer >= 1",
        )


def load_table(path: Path, columns: int, *, sorted_times: bool = False) -> np.ndarray:
    """The numeric rows of ``path`` (``#`` comments and blank lines skipped), ``columns`` wide.

    ``ValueError`` names the directory when the file is missing, and the file and line when a
    row is not ``columns`` finite numbers (a truncated or malformed file), when the file holds no
    row, or (``sorted_times``) when the first column decreases."""
    path = Path(path)
    require(path.is_file(), "directory", str(path.parent), f"a directory containing {path.name}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": below
            table = np.loadtxt(path, comments="#", ndmin=2, dtype=float)
    except ValueError:
        table = None  # find the line below
    if table is not None and table.size == 0:
        raise ValueError(f"{path} holds no data row: must hold rows of {columns} numbers")
    if table is None or table.shape[1] != columns or not np.all(np.isfinite(table)):
        _raise_at_bad_line(path, columns)
    if sorted_times:
        back = np.flatnonzero(np.diff(table[:, 0]) < 0.0)
        if len(back):
            line = _data_line_numbers(path)[back[0] + 1]
            raise ValueError(f"{path} line {line}: time {table[back[0] + 1, 0]!r} is earlier "
                             f"than the row before ({table[back[0], 0]!r}): must be sorted")
    return table


def _data_line_numbers(path: Path) -> list[int]:
    return [n for n, line in enumerate(path.read_text().splitlines(), start=1)
            if line.strip() and not line.lstrip().startswith("#")]


def _raise_at_bad_line(path: Path, columns: int) -> None:
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        fields = text.split()
        try:
            values = [float(f) for f in fields]
        except ValueError:
            values = None
        if values is None or len(values) != columns or not np.all(np.isfinite(values)):
            raise ValueError(f"{path} line {n}: {line.strip()!r} is invalid: must be {columns} "
                             "finite numbers (a truncated or malformed file?)")
    raise ValueError(f"{path}: unreadable as rows of {columns} numbers")
