"""Result types and the interface every filter offers (docs/ARCHITECTURE.md, "Filter interface").

Feature identity: every feature a filter creates gets a persistent integer id from a
:class:`FeatureIds` counter. A system that owns several maps (local and global) shares one counter
between them, so an id names one feature across the whole system. After each ``update(z)`` a
filter exposes ``last_associations``: for each observation of ``z`` the id of the feature it was
associated with (a new feature's id when it created one), or -1 when it took it for clutter. The
evaluation layer uses these ids with the simulator's truth to match features to true landmarks;
filters never see truth. Sub-map fusion reports which local ids became which global ids.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


class FeatureIds:
    """A source of fresh, never repeated feature ids (owned by one system, shared by its maps)."""

    def __init__(self, start: int = 0):
        self._next = int(start)

    @property
    def next_id(self) -> int:
        """The id the next call of :meth:`new` returns first (a compiled caller may hand out
        ``next_id, next_id + 1, ...`` and then take them with ``new``)."""
        return self._next

    def new(self, n: int = 1) -> np.ndarray:
        ids = np.arange(self._next, self._next + n, dtype=np.int64)
        self._next += n
        return ids


@dataclass
class LandmarkEstimate:
    """A map as filters report it: ids (N,), means (N, 2), covs (N, 2, 2), existence (N,)."""

    ids: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    existence: np.ndarray

    @classmethod
    def empty(cls) -> LandmarkEstimate:
        return cls(
            np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0)
        )

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class GaussianMap:
    """A joint Gaussian over ``[pose (3), feature_1 (2), ..., feature_N (2)]`` in one frame.

    This is what a local map hands to sub-map fusion (BB section 4): the mean ``x`` (3 + 2N,),
    covariance ``P`` (3 + 2N, 3 + 2N), and per feature its id and existence probability.
    """

    x: np.ndarray
    P: np.ndarray
    ids: np.ndarray
    existence: np.ndarray

    @property
    def n_features(self) -> int:
        return len(self.ids)


@dataclass
class FusionReport:
    """What one sub-map fusion did: which local ids now live under which global ids."""

    id_map: dict[int, int] = field(default_factory=dict)
    n_matched: int = 0
    n_new: int = 0
    n_dropped: int = 0
    loop_closures: list = field(default_factory=list)
    """The loop closures the back-end detected in this fusion (CM Definition 1;
    :class:`filters.back_ends.SubmapLoopClosure`)."""


class SlamFilter(Protocol):
    """The interface of docs/ARCHITECTURE.md, "Filter interface". Sub-map systems add ``fuse()``
    and ``optimise()``."""

    last_associations: np.ndarray

    def predict(self, u: np.ndarray, dt: float) -> None: ...

    def update(self, z: np.ndarray) -> None: ...

    def pose(self) -> tuple[np.ndarray, np.ndarray]: ...

    def landmarks(self) -> LandmarkEstimate: ...
