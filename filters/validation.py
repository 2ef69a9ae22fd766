"""Validation helpers: a bad value raises ``ValueError`` naming field, value and allowed range."""

from __future__ import annotations

import math


def require(condition: bool, field: str, value, allowed: str) -> None:
    """Raise ``ValueError("<field>=<value> is invalid: must be <allowed>")`` unless true."""
    if not condition:
        raise ValueError(f"{field}={value!r} is invalid: must be {allowed}")


def check_range(
    field: str, value, low: float, high: float, *, low_open: bool = False, high_open: bool = False
) -> None:
    """Require a finite number in the interval from ``low`` to ``high`` (open ends by flag)."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (value > low if low_open else value >= low) and (
            value < high if high_open else value <= high
        )
    interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    require(ok, field, value, f"a number in {interval}")
