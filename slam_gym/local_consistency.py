"""Consistency of a front-end's local maps at fusion (#14): the local-pose NEES.

A sub-map front-end (BB 4) starts every local map at its own origin with zero uncertainty and is
converted to one Gaussian at fusion (BB 3.2). Its *local pose* (the robot's pose in the frame of
the local map's start) then has a known truth: the true pose relative to the true pose at the
local map's start. :func:`local_maps` runs a front-end alone over a stream, restarting it every
``interval_steps`` as the sub-map system does on BB's schedule, and hands every step to the
caller (diagnostics read the local map at the fusions); :func:`local_pose_nees_at_fusion`
returns the NEES of the converted local pose at every restart.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from filters.geometry import relative, wrap_angle


def local_maps(front_end, stream, interval_steps: int = 100,
               known_association: bool = False) -> Iterator[tuple]:
    """Run ``front_end`` over ``stream`` (predict, then update with the true associations if
    ``known_association``), restarting it every ``interval_steps``. Yields ``(step, start_pose,
    at_fusion)`` after every step's update: ``start_pose`` is the true pose at the current local
    map's start, and at a fusion (every ``interval_steps``-th step) the front-end is restarted
    only once the caller has read its local map and asked for the next step."""
    if not isinstance(interval_steps, (int, np.integer)) or interval_steps < 1:
        raise ValueError(f"interval_steps={interval_steps!r} is invalid: must be a positive int")
    return _local_maps(front_end, stream, int(interval_steps), known_association)


def _local_maps(front_end, stream, interval_steps, known_association):
    start = np.asarray(stream.initial_pose, dtype=float).copy()
    for i, step in enumerate(stream):
        front_end.predict(step.odometry, step.dt_s)
        front_end.update(step.z, step.truth.landmark_ids if known_association else None)
        at_fusion = (i + 1) % interval_steps == 0
        yield step, start, at_fusion
        if at_fusion:
            front_end.restart()
            start = np.asarray(step.truth.pose, dtype=float).copy()


def local_pose_nees_at_fusion(front_end, stream, interval_steps: int = 100,
                              known_association: bool = False) -> np.ndarray:
    """NEES (3 dof) of ``front_end.to_gaussian()``'s pose against the true local pose, at every
    ``interval_steps``-th step (after its update), restarting the front-end there."""
    values = []
    for step, start, at_fusion in local_maps(front_end, stream, interval_steps,
                                             known_association):
        if at_fusion:
            local = front_end.to_gaussian()
            error = relative(start, step.truth.pose) - local.x[:3]
            error[2] = wrap_angle(error[2])
            values.append(float(error @ np.linalg.solve(local.P[:3, :3], error)))
    return np.array(values)


def add_fusion_run_arguments(parser) -> None:
    """The positional options of a run of local maps over BB's path at several clutter levels
    and seeds (the local-map diagnostics of scripts/archive/ take them): ``LEVELS`` (e.g.
    ``0,1,2,3``), ``SEEDS`` (a count N: seeds 0..N-1, or a range FIRST-LAST), ``N_STEPS``,
    ``[N_PARTICLES]`` (default 500), ``[known]`` (the true associations). Parsed, they are
    ``levels``, ``seeds`` (a ``range``), ``n_steps``, ``n_particles`` and ``known`` (a bool)."""
    parser.add_argument("levels", type=lambda text: [int(x) for x in text.split(",")],
                        help="clutter levels, e.g. 0,1,2,3")
    parser.add_argument("seeds", type=seed_range,
                        help="a count N (seeds 0..N-1) or a range FIRST-LAST (inclusive)")
    parser.add_argument("n_steps", type=int)
    parser.add_argument("n_particles", nargs="?", type=int, default=500)
    parser.add_argument("known", nargs="?", type=lambda text: text == "known", default=False,
                        choices=[True], help="'known': the true associations")


def seed_range(text: str) -> range:
    """``"N"`` -> seeds 0..N-1; ``"FIRST-LAST"`` -> FIRST..LAST inclusive."""
    first, _, last = text.partition("-")
    return range(int(first), int(last) + 1) if last else range(int(first))
