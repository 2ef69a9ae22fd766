"""The speed record of ``slam-gym speed --quick``: a few figures that catch a regression.

A record is one JSON object: where and when it was measured (machine, Python, date, commit) and
``figures``, each ``{"value", "unit", "higher_is_better"}``. :func:`compare` sets a record
against a baseline: every figure's *speed ratio* (new / baseline for a rate, baseline / new for a
time, so below 1 is always slower) and whether any falls below :data:`REGRESSION_RATIO`. The
figures are CPU times of one process, so another job on the machine moves them much less than
wall-clock times; on this project's machines repeated runs differ by 10-20 %, and a halving is
beyond that noise (issue 27: the loss it was made to catch was threefold).

The machines themselves differ more than that: the same code ran 2.5-3 times as fast on one
machine of this project's kind as on another a day earlier (docs/PERFORMANCE.md), so a raw ratio
would let a threefold loss pass on a fast machine and fail unchanged code on a slow one. A record
therefore also holds ``machine_reference_s``, the CPU time of a fixed workload that involves
none of the project's code (:func:`machine_reference`: an interpreted loop, small numpy
operations and a compiled loop, the three kinds of work an env step is made of), measured before
and after the figures. Where both records have it, :func:`compare` judges each figure by its
ratio *for the machine*: the raw ratio times ``reference now / reference then`` (a machine twice
as fast halves the reference and doubles the raw ratio of unchanged code).
"""

from __future__ import annotations

import datetime
import json
import math
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
from numba import njit

REGRESSION_RATIO = 0.5
"""A figure whose speed ratio to the baseline falls below this fails the comparison."""


REFERENCE_REPEATS = 5
"""Each part of the reference workload runs this many times; its fastest run counts."""


def _interpreted_work(n: int) -> float:
    acc, recent = 0.0, {}
    for i in range(n):
        acc += (i % 7) * 0.5
        recent[i % 64] = acc
    return acc + len(recent)


def _array_work(n: int) -> float:
    cloud = np.random.default_rng(0).random((500, 3))
    positions = (np.arange(500) + 0.5) / 500
    for _ in range(n):
        w = np.exp(cloud[:, 0] - cloud[:, 0].max())
        cdf = np.cumsum(w / w.sum())
        idx = np.minimum(np.searchsorted(cdf, positions, side="right"), 499)
        cloud = np.take(cloud, idx, axis=0) + 1e-3 * cloud[::-1]
    return float(cloud.sum())


@njit(cache=True)
def _compiled_work(n):
    acc = 0.0
    for i in range(n):
        x = 1e-3 * (i % 1000)
        acc += math.sqrt(x + 1.0) * math.atan2(x, 1.0 + 1e-9 * acc) + math.exp(-x)
    return acc


def machine_reference() -> float:
    """CPU seconds of a fixed workload that runs none of the project's code (module doc): the
    sum over its three parts (~10 ms each here) of each part's fastest of
    :data:`REFERENCE_REPEATS` runs. The compiled part is loaded (or compiled) before it is
    timed."""
    _compiled_work(10)
    total = 0.0
    for work, n in ((_interpreted_work, 200_000), (_array_work, 600), (_compiled_work, 400_000)):
        best = math.inf
        for _ in range(REFERENCE_REPEATS):
            start = time.process_time()
            work(n)
            best = min(best, time.process_time() - start)
        total += best
    return total


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


def make_record(figures: dict, root: Path, machine_reference_s: float | None = None) -> dict:
    record = {
        "kind": "slam-gym speed record",
        "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "commit": commit_of(root),
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "python": platform.python_version()},
        "figures": figures,
    }
    if machine_reference_s is not None:
        record["machine_reference_s"] = float(machine_reference_s)
    return record


def machine_factor(record: dict, baseline: dict) -> float:
    """How many times as fast the baseline's machine was as this record's, by their
    ``machine_reference_s`` (this record's over the baseline's), or NaN when either lacks it."""
    try:
        now, then = float(record["machine_reference_s"]), float(baseline["machine_reference_s"])
    except (KeyError, TypeError, ValueError):
        return math.nan
    return now / then if now > 0 and then > 0 else math.nan


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
    and none has a speed ratio below ``threshold``. Where both records carry a machine
    reference the ratio is the one for the machine (raw ratio x :func:`machine_factor`, module
    doc); otherwise the raw ratio."""
    rows, ok = [], True
    factor = machine_factor(record, baseline)
    factor = 1.0 if math.isnan(factor) else factor
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
        ratio = speed_ratio(new, old) * factor
        slow = not ratio >= threshold  # NaN (a zero or broken figure) fails too
        ok &= not slow
        rows.append((name, old["value"], new["value"], new["unit"], ratio,
                     "SLOWER" if slow else "ok"))
    return rows, ok


def comparison_lines(rows, record: dict, baseline: dict,
                     threshold: float = REGRESSION_RATIO) -> list[str]:
    width = max([len(row[0]) for row in rows] + [6]) + 2
    lines = [f"against the baseline of {baseline.get('date_utc', '?')} (commit "
             f"{str(baseline.get('commit', '?'))[:12]}); speed ratio = how many times as fast, "
             f"failing below {threshold:g}"]
    factor = machine_factor(record, baseline)
    if math.isnan(factor):
        lines.append("ratios as measured: a record lacks the machine reference "
                     "(machine_reference_s), so the machines' speeds are not compared")
    else:
        lines.append(f"machine reference {1e3 * record['machine_reference_s']:.1f} ms against "
                     f"{1e3 * baseline['machine_reference_s']:.1f} ms: this machine "
                     f"{1 / factor:.2f} times as fast as the baseline's; each ratio below is "
                     "the measured one divided by that")
    lines.append(
        f"{'figure':<{width}}{'baseline':>12}{'now':>12}  {'unit':<14}{'ratio':>7}  verdict")

    def fmt(value):
        return "-" if value is None else f"{value:.4g}"

    for name, old, new, unit, ratio, verdict in rows:
        lines.append(f"{name:<{width}}{fmt(old):>12}{fmt(new):>12}  {unit:<14}"
                     f"{('-' if math.isnan(ratio) else f'{ratio:.2f}'):>7}  {verdict}")
    return lines
