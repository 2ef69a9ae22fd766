"""Decision rules for the local-to-global interface (docs/ARCHITECTURE.md, "Policies").

A policy is ``act(obs, info) -> np.ndarray`` (int64, shape (2,): fuse now?, optimise now?, the
env's ``MultiDiscrete([2, 2])`` action) plus ``reset()``; see :mod:`policies.base`. Heuristics
(:mod:`policies.heuristics`) read ``info["features"]`` by name, learned policies
(:mod:`policies.learned`) the observation vector. This package imports only ``filters`` of the
project (docs/ARCHITECTURE.md, "Layers").

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
* ``learned`` -- a stable-baselines3 model zip (``path``, ``algo``; ``env_id``: the model
  shipped for that env, else the default one, :func:`policies.learned.resolve_model_path`).

Policies of your own (:mod:`policies.registry`): ``policies.register("my-rule", MyRule)`` for
this process; the entry-point group ``slam_gym.policies`` for an installed package (its names
appear in :func:`available` and in every command); or the reference ``package.module:attribute``
wherever a name is accepted (``policies.make("my_package.rules:MyRule")``, ``slam-gym benchmark
--policies fixed-10s,my_package.rules:MyRule``).
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
    discrete_action_mask,
    discrete_to_multi,
    multi_to_discrete,
)
from policies.heuristics import HEURISTICS
from policies.learned import LearnedPolicy
from policies.registry import ENTRY_POINT_GROUP, PolicyRegistry

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


def _builtin_names() -> list[str]:
    return sorted({*_CLASSES, *_ALIASES})


def _option_names(factory: Callable[..., Any]) -> list[str]:
    params = inspect.signature(factory).parameters.values()
    return [p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]


def _make_builtin(name: str, **options: Any) -> Policy:
    """Build the project's policy ``name`` with keyword ``options`` (see :func:`make`)."""
    if not isinstance(name, str) or (name not in _CLASSES and name not in _ALIASES):
        raise ValueError(
            f"policy name={name!r} is invalid: must be one of {', '.join(_builtin_names())}"
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


class _BuiltinFactory:
    """The registry's factory of the project's policy ``name``: :func:`_make_builtin`, and the
    class's reading of a name with parameters (``threshold-optimise[...]``,
    :data:`policies.registry.PARAMETERISED`) when it has one."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __call__(self, **options: Any) -> Policy:
        return _make_builtin(self.name, **options)

    @property
    def parse_parameters(self) -> Callable[[str], dict] | None:
        target = _ALIASES[self.name][0] if self.name in _ALIASES else self.name
        return getattr(_CLASSES[target], "parse_parameters", None)


REGISTRY = PolicyRegistry(
    {name: _BuiltinFactory(name) for name in _builtin_names()},
    group=ENTRY_POINT_GROUP,
)
"""The default registry: the project's policies, the entry points of group
``slam_gym.policies`` (read on first use) and what :func:`register` adds in this process."""


def available() -> list[str]:
    """Every name :func:`make` accepts (the project's policies and aliases, installed plug-ins,
    names registered in this process), sorted."""
    return REGISTRY.available()


def make(name: str, **options: Any) -> Policy:
    """Build the policy ``name`` (a name of :func:`available` or a ``package.module:attribute``
    reference) with keyword ``options``.

    An unknown name raises ``ValueError`` listing :func:`available`; an unknown option raises
    ``ValueError`` listing the policy's options; a bad option value raises ``ValueError`` naming
    the option, the value and the allowed range. An alias fixes some options (``fixed-10s``:
    ``interval_s=10``); passing a different value for one of them raises ``ValueError``.
    """
    return REGISTRY.make(name, **options)


def register(name: str, factory: Callable[..., Any]) -> None:
    """Register ``factory`` (a policy class, a function returning a policy, or a policy object)
    as ``name`` in this process (:meth:`policies.registry.PolicyRegistry.register`)."""
    REGISTRY.register(name, factory)


def unregister(name: str) -> None:
    """Forget a name :func:`register` added."""
    REGISTRY.unregister(name)


__all__ = [
    "ENTRY_POINT_GROUP",
    "INTERFACE_FEATURES",
    "REGISTRY",
    "HeuristicPolicy",
    "LearnedPolicy",
    "Policy",
    "PolicyRegistry",
    "available",
    "discrete_action_mask",
    "discrete_to_multi",
    "make",
    "multi_to_discrete",
    "register",
    "unregister",
]
