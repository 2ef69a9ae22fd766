"""Validation helpers: a bad value raises ``ValueError`` naming field, value and allowed range.

Every layer validates its options with these (filters, policies, slam_gym), so every message has
one format: ``"<field>=<value> is invalid: must be <allowed>"``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np


def require(condition: bool, field: str, value: Any, allowed: str) -> None:
    """Raise ``ValueError("<field>=<value> is invalid: must be <allowed>")`` unless true."""
    if not condition:
        raise ValueError(f"{field}={value!r} is invalid: must be {allowed}")


def check_range(
    field: str,
    value: Any,
    low: float,
    high: float,
    *,
    low_open: bool = False,
    high_open: bool = False,
    why: str = "",
) -> float:
    """Require a finite number (not bool) in [low, high] (open ends by flag); return it as float.

    An infinite bound is shown open in the message (``[0.0, inf)``); the value must be finite.
    ``why`` is appended to the message (e.g. which other option sets a bound).
    """
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )
    if ok:
        v = float(value)
        ok = (
            math.isfinite(v)
            and (v > low if low_open else v >= low)
            and (v < high if high_open else v <= high)
        )
    if not ok:  # the message is formed only when it is raised (filters check every step)
        lo = "(" if (low_open or math.isinf(low)) else "["
        hi = ")" if (high_open or math.isinf(high)) else "]"
        suffix = f" ({why})" if why else ""
        require(ok, field, value, f"a number in {lo}{low}, {high}{hi}{suffix}")
    return float(value)


def check_int_range(field: str, value: Any, low: int, high: int | None = None) -> int:
    """Require an integer (not bool) in [low, high] (``high=None``: no upper bound); return it."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if ok:
        ok = value >= low and (high is None or value <= high)
    upper = "inf)" if high is None else f"{high}]"
    require(ok, field, value, f"an integer in [{low}, {upper}")
    return int(value)


def check_choice(field: str, value: Any, choices: Iterable[str]) -> str:
    """Require ``value`` to be one of the strings ``choices``; return it."""
    choices = tuple(choices)
    require(
        isinstance(value, str) and value in choices,
        field,
        value,
        "one of " + ", ".join(repr(c) for c in choices),
    )
    return value
