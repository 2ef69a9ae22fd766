"""The speed record of ``slam-gym speed --quick``: a few figures that catch a regression.

A record is one JSON object: where and when it was measured (machine, Python, date, commit) and
``figures``, each ``{"value", "unit", "higher_is_better"}``. :func:`compare` sets a record
against a baseline: every figure's *speed ratio* (new / baseline for a rate, baseline / new for a
time, so below 1 is always slower) and whether any falls below :data:`REGRESSION_RATIO`. The
figures are CPU times of one process, so another job on the machine moves them much less than
wall-clock times; on this project's machines repeated runs differ by 10-20 %, and a halving is
beyond that noise (issue 27: the loss it was made to catch was threefold).
"""

from __future__ import annotations

import datetime
import json
import math
import platform
import subprocess
from pathlib import Path

REGRESSION_RATIO = 0.5
"""A figure whose speed ratio to the baseline falls below this fails the comparison."""


def figure(value: float, unit: str, higher_is_better: bool) -> dict:
    return {"value": float(value), "unit": unit, "higher_is_better": bool(higher_is_better)}


def commit_of(path: Path) -> str:
    """The git commit of the checkout holding ``path`` (with ``+dirty`` for uncommitted
    changes), or ``"unknown"`` outside a git checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=path, capture_output=True,
                              text=True, check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=path, capture_output=True, text=True, check=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def make_record(figures: dict, root: Path) -> dict:
    return {
        "kind": "slam-gym speed record",
        "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "commit": commit_of(root),
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "python": platform.python_version()},
        "figures": figures,
    }


def load_record(path) -> dict:
    """A record from ``path``; ``ValueError`` naming the file if it is not one."""
    path = Path(path)
    try:
        record = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(
            f"baseline={str(path)!r} is invalid: cannot be read as JSON ({exc})") from exc
    if not isinstance(record, dict) or not isinstance(record.get("figures"), dict):
        raise ValueError(f"baseline={str(path)!r} is invalid: must be a speed record with "
                         "'figures' (written by slam-gym speed --quick)")
    return record


def speed_ratio(new: dict, old: dict) -> float:
    """``new`` against ``old`` (two figures of one name): above 1 faster, below 1 slower."""
    a, b = float(new["value"]), float(old["value"])
    if not (a > 0 and b > 0 and math.isfinite(a) and math.isfinite(b)):
        return math.nan
    return a / b if old.get("higher_is_better", True) else b / a


def compare(record: dict, baseline: dict, threshold: float = REGRESSION_RATIO):
    """Rows ``(name, baseline value, new value, unit, ratio, verdict)`` for every figure of
    either record, and whether the comparison passes: every baseline figure is measured again
    and none has a speed ratio below ``threshold``."""
    rows, ok = [], True
    new_figures, old_figures = record["figures"], baseline["figures"]
    for name in sorted(set(new_figures) | set(old_figures)):
        new, old = new_figures.get(name), old_figures.get(name)
        if old is None:
            rows.append((name, None, new["value"], new["unit"], math.nan, "new"))
            continue
        if new is None:
            rows.append((name, old["value"], None, old["unit"], math.nan, "MISSING"))
            ok = False
            continue
        ratio = speed_ratio(new, old)
        slow = not ratio >= threshold  # NaN (a zero or broken figure) fails too
        ok &= not slow
        rows.append((name, old["value"], new["value"], new["unit"], ratio,
                     "SLOWER" if slow else "ok"))
    return rows, ok


def comparison_lines(rows, baseline: dict, threshold: float = REGRESSION_RATIO) -> list[str]:
    width = max([len(row[0]) for row in rows] + [6]) + 2
    lines = [f"against the baseline of {baseline.get('date_utc', '?')} (commit "
             f"{str(baseline.get('commit', '?'))[:12]}); speed ratio = how many times as fast, "
             f"failing below {threshold:g}",
             f"{'figure':<{width}}{'baseline':>12}{'now':>12}  {'unit':<14}{'ratio':>7}  verdict"]
    def fmt(value):
        return "-" if value is None else f"{value:.4g}"

    for name, old, new, unit, ratio, verdict in rows:
        lines.append(f"{name:<{width}}{fmt(old):>12}{fmt(new):>12}  {unit:<14}"
                     f"{('-' if math.isnan(ratio) else f'{ratio:.2f}'):>7}  {verdict}")
    return lines
