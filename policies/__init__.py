"""Decision rules for the local-to-global interface (see DESIGN section 5).

A policy is ``act(obs, info) -> np.ndarray`` (int64, shape (2,): fuse now?, optimise now?, the
env's ``MultiDiscrete([2, 2])`` action) plus ``reset()``; see :mod:`policies.base`. Heuristics
(:mod:`policies.heuristics`) read ``info["features"]`` by name, learned policies
(:mod:`policies.learned`) the observation vector. This package imports nothing else of the project.

>>> import policies
>>> policy = policies.make("fixed-10s")
>>> policy.reset()
>>> policy.act(None, {"features": {"local_map_age_s": 10.0}}).tolist()
[1, 0]

Names (``policies.available()``):

* ``fixed-interval`` (``interval_s``, ``optimise``), ``fixed-10s`` = BB's rule (interval 10 s),
  ``fixed-10s-optimise`` = the same with the optimiser after every fusion;
* ``esdf-innovation`` -- CM's rule: fuse on BB's interval (or the budget), optimise once per loop
  closure found by CM's test (CM III.B-C); ``innovation-fusion`` -- CM's test used as a fusion
  trigger instead;
* ``never`` (pure FastSLAM), ``always`` (fuse at every decision, EKF-like);
* ``adaptive-diversity`` and ``imminent-closure`` -- adaptive rules of BB sections 6 and 5.4;
* ``learned`` -- a stable-baselines3 model zip (``path``, ``algo``).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

from policies.base import (
    INTERFACE_FEATURES,
    HeuristicPolicy,
    Policy,
    discrete_to_multi,
    multi_to_discrete,
)
from policies.heuristics import HEURISTICS
from policies.learned import LearnedPolicy

_CLASSES: Mapping[str, type[Policy]] = MappingProxyType({**HEURISTICS, "learned": LearnedPolicy})

_ALIASES: Mapping[str, tuple[str, Mapping[str, Any]]] = MappingProxyType(
    {
        "fixed-10s": ("fixed-interval", MappingProxyType({"interval_s": 10.0})),
        "fixed-10s-optimise": (
            "fixed-interval",
            MappingProxyType({"interval_s": 10.0, "optimise": "every-fusion"}),
        ),
    }
)
"""Alias -> (policy name, options it fixes). ``fixed-10s`` is BB's rule (BB section 6);
``fixed-10s-optimise`` runs CM's optimiser after every one of its fusions."""


def available() -> list[str]:
    """Every name :func:`make` accepts (policies and aliases), sorted."""
    return sorted({*_CLASSES, *_ALIASES})


def _option_names(factory: Callable[..., Any]) -> list[str]:
    params = inspect.signature(factory).parameters.values()
    return [p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]


def make(name: str, **options: Any) -> Policy:
    """Build the policy registered as ``name`` with keyword ``options``.

    An unknown name raises ``ValueError`` listing :func:`available`; an unknown option raises
    ``ValueError`` listing the policy's options; a bad option value raises ``ValueError`` naming
    the option, the value and the allowed range. An alias fixes some options (``fixed-10s``:
    ``interval_s=10``); passing a different value for one of them raises ``ValueError``.
    """
    if not isinstance(name, str) or (name not in _CLASSES and name not in _ALIASES):
        raise ValueError(
            f"policy name={name!r} is invalid: must be one of {', '.join(available())}"
        )
    fixed: Mapping[str, Any] = {}
    target = name
    if name in _ALIASES:
        target, fixed = _ALIASES[name]
        for key, value in fixed.items():
            if key in options and options[key] != value:
                raise ValueError(
                    f"{key}={options[key]!r} is invalid: must be {value!r} for {name!r} "
                    f"(use {target!r} to choose {key})"
                )
    cls = _CLASSES[target]
    allowed = _option_names(cls.__init__)
    allowed = [a for a in allowed if a != "self"]
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ValueError(
            f"option(s) {', '.join(unknown)} invalid for policy {name!r}: must be among "
            f"{', '.join(allowed) if allowed else '(no options)'}"
        )
    return cls(**{**fixed, **options})


__all__ = [
    "INTERFACE_FEATURES",
    "HeuristicPolicy",
    "LearnedPolicy",
    "Policy",
    "available",
    "discrete_to_multi",
    "make",
    "multi_to_discrete",
]
