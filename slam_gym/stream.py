"""The data stream every filter, the env and the evaluation consume (DESIGN section 2).

A :class:`Stream` is a re-iterable, deterministic sequence of :class:`Step` s plus the constants a
filter needs (sensor, clutter and odometry-noise models). Truth is kept apart in
:class:`StepTruth`: the runner hands filters ``odometry``, ``compass_rad`` and ``z`` only.
Simulated worlds (:mod:`slam_gym.world`) and real data sets (:mod:`slam_gym.datasets`) produce
the same type.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from filters.models import ClutterModel, RangeBearingSensor


@dataclass(frozen=True)
class StepTruth:
    """Ground truth for one step: never visible to filters or policies.

    ``pose`` is the true pose (NaN where a real data set has none at this time);
    ``landmark_ids`` (K,) gives for each observation the index of the true landmark in
    ``Stream.landmarks_true``, or -1 for a false alarm (-2 where a data set has no landmark truth).
    ``visible_ids`` lists the true landmarks inside the sensor's field at a scan (None where
    unknown).
    """

    pose: np.ndarray
    landmark_ids: np.ndarray
    visible_ids: np.ndarray | None = None


@dataclass(frozen=True)
class Step:
    """One filter iteration: odometry over ``dt_s`` then the observations at ``t_s``."""

    index: int
    t_s: float
    dt_s: float
    odometry: np.ndarray
    compass_rad: float | None
    z: np.ndarray
    truth: StepTruth


@dataclass
class Stream:
    """A sequence of steps with the models that generated (or describe) it.

    ``make_steps`` is a zero-argument callable returning a fresh iterator over the steps, so the
    stream can be replayed identically for several systems (BB 5.2: "identical worlds, odometry,
    and observations were used for all filters").
    """

    name: str
    sensor: RangeBearingSensor
    clutter: ClutterModel
    odometry_noise: object
    initial_pose: np.ndarray
    landmarks_true: np.ndarray
    n_steps: int
    dt_s: float
    make_steps: Callable[[], Iterator[Step]]
    compass_std_rad: float | None = None
    metadata: dict = field(default_factory=dict)

    def __iter__(self) -> Iterator[Step]:
        return self.make_steps()

    def __len__(self) -> int:
        return self.n_steps


class StepList:
    """A ``make_steps`` for a stream held in memory (picklable, so envs and episodes pickle)."""

    def __init__(self, steps: list[Step]):
        self.steps = steps

    def __call__(self) -> Iterator[Step]:
        return iter(self.steps)


def steps_from_list(steps: list[Step]) -> Callable[[], Iterator[Step]]:
    """A ``make_steps`` for a stream held in memory."""
    return StepList(steps)
