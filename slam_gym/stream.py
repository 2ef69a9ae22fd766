"""The data stream every filter, the env and the evaluation consume (docs/ARCHITECTURE.md, "The
data stream").

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
    """One filter iteration: odometry over ``dt_s`` then the observations at ``t_s``.

    ``scanned``: whether the step carries a sensor scan. A scan that detected nothing (``z``
    empty, ``scanned`` True) is evidence against the features in view (BB (11), FastSLAM's
    missed-detection weight); a step without a scan (``scanned`` False) is no evidence at all,
    and filters must not be updated with it.
    """

    index: int
    t_s: float
    dt_s: float
    odometry: np.ndarray
    compass_rad: float | None
    z: np.ndarray
    truth: StepTruth
    scanned: bool = True


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


class ArraySteps:
    """A ``make_steps`` for recorded data held as arrays (picklable, and so are its iterators).

    Step ``k`` covers ``(t_s[k], t_s[k + 1]]`` with odometry ``odometry[k]`` and the observation
    rows ``bounds[k]:bounds[k + 1]`` of ``z`` / ``landmark_ids``; ``poses[k]`` is its true pose
    (NaN where unknown) and ``visible[k]`` (optional, boolean over the true landmarks) marks the
    landmarks in view. Every step counts as a scan (``Step.scanned``): a recording's sensor runs
    continuously, so a step with no detection is a frame in which nothing was seen.
    """

    def __init__(self, t_s, dt_s, odometry, z, landmark_ids, bounds, poses, visible=None):
        self.t_s = np.asarray(t_s, dtype=float)
        self.dt_s = float(dt_s)
        self.odometry = np.asarray(odometry, dtype=float)
        self.z = np.asarray(z, dtype=float).reshape(-1, 2)
        self.landmark_ids = np.asarray(landmark_ids, dtype=np.int64)
        self.bounds = np.asarray(bounds, dtype=np.int64)
        self.poses = np.asarray(poses, dtype=float)
        self.visible = None if visible is None else np.asarray(visible, dtype=bool)

    def __len__(self) -> int:
        return len(self.odometry)

    def step(self, k: int) -> Step:
        s, e = self.bounds[k], self.bounds[k + 1]
        visible = None if self.visible is None else np.flatnonzero(self.visible[k])
        return Step(
            index=k,
            t_s=float(self.t_s[k + 1]),
            dt_s=self.dt_s,
            odometry=self.odometry[k].copy(),
            compass_rad=None,
            z=self.z[s:e].copy(),
            truth=StepTruth(
                pose=self.poses[k].copy(),
                landmark_ids=self.landmark_ids[s:e].copy(),
                visible_ids=None if visible is None else visible.astype(np.int64),
            ),
        )

    def __call__(self) -> Iterator[Step]:
        return _ArrayStepIterator(self)


class _ArrayStepIterator:
    def __init__(self, steps: ArraySteps):
        self.steps = steps
        self.k = 0

    def __iter__(self):
        return self

    def __next__(self) -> Step:
        if self.k >= len(self.steps):
            raise StopIteration
        self.k += 1
        return self.steps.step(self.k - 1)
