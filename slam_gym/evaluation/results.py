"""``results.jsonl``: one JSON object per finished run, a public contract (docs/ARCHITECTURE.md,
"The command line and its output files").

Each row carries the job's fields (``system`` or ``policy``, ``env_id`` and ``env_kwargs``:
the env's id and every resolved keyword argument of ``gym.make``, null for a run outside any env,
``scenario``, ``clutter_level``, ``seed``, ``options``, ``key``), the run function's returned
metrics (at least :data:`RESULT_KEYS`), and ``status`` (``"ok"`` or ``"error"``), ``error``
(``"Type: message"`` or null), ``traceback`` (text or null), ``wall_time_s``, and what made it
(issue 55): ``code`` (``commit``: the git commit of the code that ran, null outside a git
checkout; ``dirty``: whether the tree had uncommitted changes to tracked files; ``version``: the
package's version) and ``finished_at`` (UTC, ISO 8601, when its run finished). The file is
append-only: every row is written as one line, flushed and ``fsync``-ed as soon as its run
finishes, so a killed benchmark loses at most the line being written. A partial last line (no
trailing newline, or not valid JSON) is ignored by :func:`read_results` and cut off by
:class:`ResultsWriter` before it appends.

Values are plain JSON: numpy scalars and arrays become numbers and lists, and non-finite floats
(NaN, inf) are written as ``null`` so that any strict JSON reader accepts the file.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slam_gym.evaluation.jobs import JOB_KINDS, Job

try:  # POSIX advisory lock: two benchmarks must not append to the same file at once
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

logger = logging.getLogger(__name__)

RESULTS_FILENAME = "results.jsonl"

#: Metrics every run function must return (docs/ARCHITECTURE.md, "The command line and its output
#: files"). Null is allowed as a value
#: (e.g. ``failure_iteration`` of a successful run); a missing key makes the run an error row.
RESULT_KEYS = (
    "alpha",
    "beta",
    "success",
    "failure_iteration",
    "anees",
    "nees_in_band_fraction",
    "map_error_m",
    "final_pose_error_m",
    "n_fusions",
    "n_optimisations",
)

#: Keys every row has besides exactly one of ``system`` / ``policy`` (docs/ARCHITECTURE.md, "The
#: command line and its output files").
REQUIRED_ROW_KEYS = ("scenario", "clutter_level", "seed", "status", "error", *RESULT_KEYS,
                     "wall_time_s")

#: Keys the runner owns; a run function's result may not set them.
RESERVED_KEYS = frozenset(
    (*JOB_KINDS, "env_id", "env_kwargs", "scenario", "clutter_level", "seed", "options", "key")
    + ("status", "error", "traceback", "wall_time_s", "code", "finished_at")
)


def code_identity() -> dict[str, Any]:
    """What code runs: ``commit`` (the git commit of this package's checkout, None when it is
    not one or git is missing), ``dirty`` (uncommitted changes to tracked files; None when
    unknown) and ``version`` (the installed package's). Asked once per :func:`run_jobs` call,
    in the process that writes the rows."""
    import subprocess
    from importlib import metadata

    try:
        version = metadata.version("slam-gym")
    except metadata.PackageNotFoundError:
        version = None
    root = Path(__file__).resolve().parents[2]
    commit = dirty = None
    try:
        done = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                              text=True, timeout=10, check=False)
        if done.returncode == 0:
            commit = done.stdout.strip()
            status = subprocess.run(["git", "-C", str(root), "status", "--porcelain",
                                     "--untracked-files=no"], capture_output=True, text=True,
                                    timeout=30, check=False)
            dirty = bool(status.stdout.strip()) if status.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"commit": commit, "dirty": dirty, "version": version}

RUN_TIME_KEYS = ("wall_time_s", "finished_at")
"""Row keys that differ between two runs of the same job by the clock alone."""

STATUS_OK = "ok"
STATUS_ERROR = "error"


class ResultsLockedError(RuntimeError):
    """Another process holds the lock of a ``results.jsonl`` (a benchmark writing into it)."""


class ResultError(ValueError):
    """A run function returned something that cannot be a results row."""


def to_jsonable(value: Any, where: str = "result") -> Any:
    """Convert ``value`` to plain JSON types; non-finite floats become ``None``.

    Raises :class:`ResultError` naming the offending entry for anything else (objects, sets).
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, np.generic):
        value = value.item()
        if isinstance(value, (bool, str)) or value is None:
            return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return [to_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value.tolist())]
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ResultError(f"{where} has a non-str key {k!r}: JSON objects need str keys")
            out[k] = to_jsonable(v, f"{where}[{k!r}]")
        return out
    raise ResultError(
        f"{where} has a value of type {type(value).__name__} ({value!r:.60}): "
        "expected None, bool, int, float, str, list, dict or a numpy number/array"
    )


def validate_result(result: Any) -> dict[str, Any]:
    """Check a run function's return value and convert it to JSON types.

    It must be a mapping with every key of :data:`RESULT_KEYS` and none of
    :data:`RESERVED_KEYS`; extra keys are kept. Raises :class:`ResultError` with a message naming
    what is wrong.
    """
    if not isinstance(result, Mapping):
        raise ResultError(
            f"run function returned {type(result).__name__}, expected a dict with keys "
            f"{', '.join(RESULT_KEYS)}"
        )
    missing = [k for k in RESULT_KEYS if k not in result]
    if missing:
        raise ResultError(f"run function result is missing required keys: {', '.join(missing)}")
    reserved = sorted(k for k in result if k in RESERVED_KEYS)
    if reserved:
        raise ResultError(
            f"run function result sets keys owned by the runner: {', '.join(reserved)}"
        )
    return to_jsonable(dict(result))


def make_row(
    job: Job,
    result: Mapping[str, Any] | None,
    *,
    error: str | None = None,
    traceback_text: str | None = None,
    wall_time_s: float,
    code: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """One ``results.jsonl`` row: job fields, metrics (null for an error), status, timing, the
    code that ran it (``code``: :func:`code_identity`; None asks now) and when it finished.

    ``result`` must already have passed :func:`validate_result` when ``error`` is None.
    """
    import datetime

    row = job.row_fields()
    if error is None:
        if result is None:
            raise ResultError("make_row needs a result when error is None")
        row.update({k: result[k] for k in RESULT_KEYS})
        row.update({k: v for k, v in result.items() if k not in RESULT_KEYS})
        row.update(status=STATUS_OK, error=None, traceback=None)
    else:
        row.update(dict.fromkeys(RESULT_KEYS))
        row.update(status=STATUS_ERROR, error=error, traceback=traceback_text)
    row["wall_time_s"] = to_jsonable(float(wall_time_s))
    row["code"] = dict(code if code is not None else code_identity())
    row["finished_at"] = datetime.datetime.now(datetime.UTC).isoformat(
        timespec="seconds")
    return row


def check_row(row: Mapping[str, Any]) -> None:
    """Raise :class:`ResultError` unless ``row`` has every key of the public contract."""
    kinds = [k for k in JOB_KINDS if k in row]
    if len(kinds) != 1:
        raise ResultError(f"row needs exactly one of {JOB_KINDS}, has {kinds}")
    missing = [k for k in REQUIRED_ROW_KEYS if k not in row]
    if missing:
        raise ResultError(f"row is missing required keys: {', '.join(missing)}")
    if row["status"] not in (STATUS_OK, STATUS_ERROR):
        raise ResultError(f"row status={row['status']!r} is invalid: must be 'ok' or 'error'")


def _parse(data: bytes, path: Path) -> tuple[list[dict[str, Any]], int, int]:
    """Rows of ``data``, the byte length of its valid prefix, and the number of bytes dropped.

    Only the last line may be damaged (a write cut short by a kill): it is dropped if it has no
    trailing newline or is not a JSON object. A damaged line before it raises ``ValueError``.
    """
    rows: list[dict[str, Any]] = []
    lines = data.split(b"\n")
    complete, tail = lines[:-1], lines[-1]
    valid = 0
    for i, line in enumerate(complete):
        end = valid + len(line) + 1
        if line.strip():
            try:
                row = json.loads(line)
                if not isinstance(row, dict):
                    raise ValueError("not a JSON object")
            except ValueError as exc:
                if i == len(complete) - 1 and not tail:
                    return rows, valid, len(data) - valid
                raise ValueError(
                    f"{path}:{i + 1}: line is not a JSON object ({exc}); only the last line of a "
                    "results file may be damaged"
                ) from exc
            rows.append(row)
        valid = end
    return rows, valid, len(data) - valid


def read_results(path: str | os.PathLike) -> list[dict[str, Any]]:
    """All rows of a ``results.jsonl`` file (``[]`` if it does not exist).

    ``path`` may be the file or its directory. A truncated last line is ignored with a warning.
    """
    path = Path(path)
    if path.is_dir():
        path = path / RESULTS_FILENAME
    if not path.exists():
        return []
    rows, _, dropped = _parse(path.read_bytes(), path)
    if dropped:
        logger.warning("%s: ignoring a partial last line (%d bytes)", path, dropped)
    return rows


def row_key(row: Mapping[str, Any]) -> str:
    """The job key of a row (stored under ``key``, or rebuilt from the job fields)."""
    key = row.get("key")
    return key if isinstance(key, str) else Job.from_row(row).key


def finished_keys(rows: Iterable[Mapping[str, Any]]) -> set[str]:
    """Keys of the jobs that have a row (ok or error): a rerun skips these."""
    return {row_key(row) for row in rows}


class ResultsWriter:
    """Append-only, crash-safe writer of ``results.jsonl`` (context manager).

    On entry it takes an exclusive advisory lock (a second writer on the same file fails with
    :class:`ResultsLockedError`, a ``RuntimeError``), cuts off a partial last line left by a
    killed run, and exposes the rows already there as :attr:`existing`. :meth:`write` appends
    one line, flushes and ``fsync`` s.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.existing: list[dict[str, Any]] = []
        self._file = None

    def __enter__(self) -> ResultsWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = self._open_locked()
        try:
            f.seek(0)
            rows, valid, dropped = _parse(f.read(), self.path)
            if dropped:
                logger.warning(
                    "%s: cutting off a partial last line (%d bytes) left by an interrupted run",
                    self.path,
                    dropped,
                )
                f.truncate(valid)
                f.flush()
                os.fsync(f.fileno())
        except BaseException:
            f.close()
            raise
        self.existing = rows
        self._file = f
        return self

    def _open_locked(self):
        f = open(self.path, "a+b")
        if fcntl is not None:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError as exc:
                f.close()
                raise ResultsLockedError(
                    f"{self.path} is being written by another process (another run into the "
                    "same output directory); use another output directory or wait for it to "
                    "finish"
                ) from exc
        return f

    def write(self, row: Mapping[str, Any]) -> None:
        """Validate ``row`` against the contract and append it durably."""
        if self._file is None:
            raise RuntimeError("ResultsWriter.write called outside its 'with' block")
        check_row(row)
        line = json.dumps(row, allow_nan=False, separators=(",", ":")) + "\n"
        self._file.write(line.encode("utf-8"))
        self._file.flush()
        os.fsync(self._file.fileno())

    def rewrite(self, rows: Iterable[Mapping[str, Any]]) -> None:
        """Replace the file's content by ``rows`` atomically (temporary file + ``os.replace``).

        Used to drop error rows before retrying them; the lock moves to the new file.
        """
        if self._file is None:
            raise RuntimeError("ResultsWriter.rewrite called outside its 'with' block")
        rows = [dict(r) for r in rows]
        for row in rows:
            check_row(row)
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "wb") as f:
            for row in rows:
                f.write((json.dumps(row, allow_nan=False, separators=(",", ":")) + "\n").encode())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)
        self._file.close()
        self._file = self._open_locked()
        self.existing = rows

    def __exit__(self, *exc_info: object) -> None:
        if self._file is not None:
            self._file.close()  # closing releases the lock
            self._file = None
