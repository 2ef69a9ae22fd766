"""The policy interface for the local-to-global interface decisions (docs/ARCHITECTURE.md,
"Policies").

A policy maps what the environment shows at a decision to the pair of interface decisions::

    act(obs, info) -> np.ndarray, int64, shape (2,) = (fuse now?, optimise now?)

the action of the env's ``MultiDiscrete([2, 2])`` space, and ``reset()`` clears any state kept
between decisions at the start of an episode. ``obs`` is the env's float32 observation vector;
``info["features"]`` holds the same interface features by name (docs/ARCHITECTURE.md, "Interface
features"). Heuristics read only ``info["features"]``, learned policies only ``obs``.

The fusion decision is BB's local-to-global interface (BB section 6: "fusing in a moment of
transient ambiguity can result in an incorrect decision being irreversibly fused into the
back-end"); the optimisation decision is CM's switch from the filter to the nonlinear optimiser
(CM section III.B-C). When both are 1 at one decision the env fuses first and then optimises, so
the optimiser sees the sub-map that was just fused.

This package imports from ``filters`` only (docs/ARCHITECTURE.md, "Layers"): the feature names'
one definition (:mod:`filters.interface_features`) and the option validation every layer shares
(:mod:`filters.validation`).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar

import numpy as np

from filters.interface_features import INTERFACE_FEATURE_NAMES
from filters.validation import require

INTERFACE_FEATURES: tuple[str, ...] = INTERFACE_FEATURE_NAMES
"""The interface-feature names of docs/ARCHITECTURE.md, in table order: the contract between the
env (which fills ``info["features"]``) and the heuristics (which declare the subset they read)."""

N_DISCRETE_ACTIONS = 4
"""Size of the flat action space of the env's ``Discrete(4)`` wrapper (for DQN)."""


# ----------------------------------------------------------------------------------------------
# Actions
# ----------------------------------------------------------------------------------------------
def make_action(fuse: bool, optimise: bool) -> np.ndarray:
    """The env's ``MultiDiscrete([2, 2])`` action ``(fuse, optimise)`` as int64 of shape (2,)."""
    return np.array([1 if fuse else 0, 1 if optimise else 0], dtype=np.int64)


def check_action(action: Any, policy: str | None = None) -> np.ndarray:
    """The env's action from what policy ``policy`` returned (None: what the env's caller
    passed, :meth:`slam_gym.envs.hybrid_slam.HybridSLAMEnv.step`), or ``ValueError`` naming the
    policy, if any, and the value: an array-like of shape (2,), integer (or bool) dtype, each 0
    or 1.

    Floats are refused even when they are whole (``[1.0, 0.0]``), as the env refuses them: a
    float usually means an unrounded score was returned where a decision was meant."""
    arr = np.asarray(action)
    ok = (
        arr.shape == (2,)
        and (np.issubdtype(arr.dtype, np.integer) or arr.dtype == np.bool_)
        and bool(np.all((arr == 0) | (arr == 1)))
    )
    if not ok:
        source = "" if policy is None else f"policy {policy!r} returned "
        raise ValueError(
            f"{source}action={action!r} (dtype {arr.dtype}, shape "
            f"{arr.shape}), which is invalid: must be two integers in {{0, 1}} (fuse, optimise), "
            "e.g. np.array([1, 0], dtype=np.int64), the env's MultiDiscrete([2, 2]) action"
        )
    return arr.astype(np.int64)


def discrete_to_multi(a: Any) -> np.ndarray:
    """Map a ``Discrete(4)`` action to the ``(fuse, optimise)`` pair.

    The mapping is ``a = 2 * fuse + optimise``, i.e.::

        0 -> (0, 0)  keep the local map, no optimisation
        1 -> (0, 1)  optimise only
        2 -> (1, 0)  fuse only
        3 -> (1, 1)  fuse, then optimise

    The env's ``Discrete(4)`` wrapper (for DQN; :class:`slam_gym.envs.wrappers.DiscreteActions`)
    and :mod:`policies.learned` both use it, so a model trained through the wrapper acts
    identically when loaded as a policy.
    """
    arr = np.asarray(a)
    ok = arr.size == 1 and np.issubdtype(arr.dtype, np.integer) and not isinstance(a, bool)
    value = int(arr.reshape(())) if ok else -1
    require(
        0 <= value < N_DISCRETE_ACTIONS,
        "discrete action",
        a,
        f"an integer in [0, {N_DISCRETE_ACTIONS - 1}]",
    )
    return np.array([value // 2, value % 2], dtype=np.int64)


def discrete_action_mask(optimise_redundant: bool) -> np.ndarray:
    """The valid ``Discrete(4)`` actions at a decision: all but ``1`` (optimise only) when the
    env says the optimisation would be redundant (``info["optimise_redundant"]``: nothing fused
    since the last optimum, so optimising alone is a no-op); ``a = 3`` optimises the sub-map it
    has just fused, so it is never a no-op. The env's ``Discrete(4)`` wrapper
    (:class:`slam_gym.envs.wrappers.DiscreteActions`) masks with this function."""
    return np.array([True, not bool(optimise_redundant), True, True])


def multi_to_discrete(pair: Any) -> int:
    """Inverse of :func:`discrete_to_multi`: ``(fuse, optimise) -> 2 * fuse + optimise``."""
    arr = np.asarray(pair)
    ok = (
        arr.shape == (2,)
        and (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.bool_))
        and bool(np.all((arr == 0) | (arr == 1)))
    )
    require(ok, "action pair", pair, "two integers in {0, 1} (fuse, optimise)")
    return int(2 * arr[0] + arr[1])


# ----------------------------------------------------------------------------------------------
# Reading features
# ----------------------------------------------------------------------------------------------
def read_features(info: Any, names: Iterable[str], policy: str) -> dict[str, float]:
    """Return ``{name: float}`` for ``names`` from ``info["features"]``.

    A missing ``info["features"]`` or a missing name raises ``KeyError`` naming what is missing and
    every name the policy needs; a value that is not a real number (or is NaN) raises
    ``ValueError`` naming the feature.
    """
    names = tuple(names)
    needed = ", ".join(names) if names else "(none)"
    if not isinstance(info, Mapping) or "features" not in info:
        raise KeyError(
            f"policy {policy!r} reads info['features'] (a dict of interface features by name) "
            f"but info has no 'features' entry; it needs: {needed}"
        )
    features = info["features"]
    missing = [n for n in names if n not in features]
    if missing:
        raise KeyError(
            f"policy {policy!r} needs interface feature(s) {', '.join(missing)} missing from "
            f"info['features']; it needs: {needed}"
        )
    out: dict[str, float] = {}
    for n in names:
        raw = features[n]
        try:
            v = float(raw)
        except (TypeError, ValueError):
            v = math.nan
        require(not math.isnan(v), f"info['features'][{n!r}]", raw, "a real number (not NaN)")
        out[n] = v
    return out


# ----------------------------------------------------------------------------------------------
# The interface
# ----------------------------------------------------------------------------------------------
class Policy(abc.ABC):
    """A decision rule for the local-to-global interface: ``act(obs, info)`` and ``reset()``.

    Subclasses set the class attribute ``name`` (registry name) and the instance attribute
    ``required_features`` (the names of ``info["features"]`` they read; empty for policies that
    read only ``obs``). ``options`` records the validated constructor options (for logs and
    results files).
    """

    name: ClassVar[str] = "policy"

    def __init__(self) -> None:
        self.required_features: tuple[str, ...] = ()
        self.options: dict[str, Any] = {}

    @abc.abstractmethod
    def act(self, obs: Any, info: Mapping[str, Any]) -> np.ndarray:
        """The action ``(fuse, optimise)``: ``np.ndarray`` of int64, shape (2,)."""

    def reset(self) -> None:  # noqa: B027 - stateless policies need nothing
        """Forget any state kept between decisions (call at the start of every episode)."""

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items())
        return f"{type(self).__name__}({opts})"


class HeuristicPolicy(Policy):
    """A rule on named interface features: reads ``info["features"]``, never ``obs``."""

    def act(self, obs: Any, info: Mapping[str, Any]) -> np.ndarray:
        f = read_features(info, self.required_features, self.name)
        fuse, optimise = self.decide(f)
        return make_action(fuse, optimise)

    @abc.abstractmethod
    def decide(self, f: Mapping[str, float]) -> tuple[bool, bool]:
        """``(fuse, optimise)`` from the required features ``f`` (already read and checked)."""
