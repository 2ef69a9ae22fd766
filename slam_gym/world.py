"""The cluttered 2-D world simulator (docs/ARCHITECTURE.md, "The data stream").

:func:`simulate` turns a :class:`slam_gym.scenarios.Scenario` and a seed into a
:class:`slam_gym.stream.Stream`. Randomness comes from three independent generators spawned from
the seed (world and path, odometry noise, sensor), so a given seed yields the same world, path and
odometry at every clutter level (BB 5.2: "identical worlds, odometry, and observations were used
for all filters"), and one seed reproduces the stream bit for bit.

Odometry noise, as each paper states it:
* ``proportional`` (BB 5.2: "vehicle linear and rotational velocity was noisy, perturbed with
  standard deviations equal to 0.25 v and 0.35 omega, where v and omega are commanded"): the
  vehicle truly moves with commanded + N(0, diag((0.25 v)^2, (0.35 omega)^2)) and the odometry the
  filters receive is the commanded (v, omega); the filters' noise covariance is then exact;
* ``chong-kleeman`` (CM (14)): truth moves with the commanded wheel travel; at each encoder tick,
  each wheel's measured travel is the true travel plus N(0, K |travel|); the ticks of a filter
  step are summed and converted to (v, omega). The variance is linear in the travel, so a step's
  summed error has variance K |step travel| at any tick rate (the wheels never reverse within a
  step), which is the covariance the filters use (:class:`filters.models.ChongKleemanNoise`,
  whose tiny floor only keeps it regular at rest).
With ``scan_at_start`` the stream begins with a motionless step (index 0, ``t_s = dt_s = 0``,
zero odometry) holding a scan from the start pose; filters treat ``dt = 0`` as no motion. Step
``i`` is then at ``t_s = i * dt`` and ``metadata["true_poses"][i]`` is its true pose.
The sensor (BB 5.1): each landmark inside range and field of view is detected with probability
alpha (range and bearing with Gaussian noise) and triggers, with probability beta, one false
alarm uniform in range over [0, max range] and in bearing over the field of view; the
observations of a scan are shuffled.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from numba import njit

from filters.geometry import TWO_PI, wrap_angle
from filters.models import (
    ChongKleemanNoise,
    ClutterModel,
    ProportionalVelocityNoise,
    RangeBearingSensor,
    observe,
)
from slam_gym.scenarios import Scenario, get_scenario
from slam_gym.stream import Step, StepTruth, Stream, steps_from_list

WAYPOINT_SWITCH_RADIUS_M = 2.0
WORLD_EDGE_MARGIN_M = 2.0
"""Waypoints stay this far inside the world (the robot drives inside its own world)."""


def sensor_of(scenario: Scenario) -> RangeBearingSensor:
    return RangeBearingSensor(
        range_std_m=scenario.range_std_m,
        bearing_std_rad=scenario.bearing_std_rad,
        max_range_m=scenario.max_range_m,
        fov_rad=scenario.fov_rad,
    )


def odometry_noise_of(scenario: Scenario):
    if scenario.odometry_model == "chong-kleeman":
        return ChongKleemanNoise(k_m=scenario.chong_kleeman_k_m, wheel_base_m=scenario.wheel_base_m)
    return ProportionalVelocityNoise(
        v_fraction=scenario.v_noise_fraction,
        omega_fraction=scenario.omega_noise_fraction,
        v_floor_mps=scenario.v_noise_floor_mps,
        omega_floor_radps=scenario.omega_noise_floor_radps,
    )


def landmark_field(scenario: Scenario, rng: np.random.Generator) -> np.ndarray:
    """Landmarks uniform over the square world [0, W]^2 (BB 5.2)."""
    return rng.uniform(0.0, scenario.world_size_m, size=(scenario.n_landmarks, 2))


def loop_waypoints(scenario: Scenario, rng: np.random.Generator) -> np.ndarray:
    """Perturbed waypoints of one counter-clockwise square loop centred in the world.

    The loop starts in the middle of its bottom edge and runs counter-clockwise; every waypoint
    except the start is moved uniformly by up to ``path_perturbation_m`` in x and y, then kept
    ``WORLD_EDGE_MARGIN_M`` inside the world.
    """
    side = scenario.loop_side_m
    centre = 0.5 * scenario.world_size_m
    lo, hi = centre - 0.5 * side, centre + 0.5 * side
    corners = np.array([[centre, lo], [hi, lo], [hi, hi], [lo, hi], [lo, lo], [centre, lo]])
    points = [corners[0]]
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / scenario.waypoint_spacing_m)))
        for k in range(1, n + 1):
            points.append(a + (b - a) * k / n)
    waypoints = np.array(points[:-1])  # the last point is the start again
    p = scenario.path_perturbation_m
    waypoints[1:] += rng.uniform(-p, p, size=waypoints[1:].shape)
    margin = min(WORLD_EDGE_MARGIN_M, 0.25 * scenario.world_size_m)
    return np.clip(waypoints, margin, scenario.world_size_m - margin)


def route(scenario: Scenario, waypoints: np.ndarray) -> np.ndarray:
    """The loop, then its start again, up to the first waypoint at ``path_length_m`` along it.

    The route always returns to the start (the loop closure), even when the perturbed loop is
    longer than ``path_length_m``. The driven path is a little shorter than this polyline
    (corners are cut) and varies with the perturbation of the waypoints.
    """
    loop = np.vstack([waypoints, waypoints[:1]])
    loop_length = float(np.sum(np.linalg.norm(np.diff(loop, axis=0), axis=1)))
    repeats = 2 + int(scenario.path_length_m // max(loop_length, 1e-9))
    polyline = np.vstack([waypoints] * repeats + [waypoints[:1]])
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(polyline, axis=0), axis=1))])
    last = max(int(np.searchsorted(along, scenario.path_length_m)), len(waypoints))
    return polyline[: min(last, len(polyline) - 1) + 1]


ZONE_KINDS: tuple[str, ...] = ("normal", "corridor", "burst", "patch")
"""What a sector of a zoned world's loop holds (:func:`draw_zones`)."""

ZONE_SAMPLE_SPACING_M = 0.5
"""Spacing of the points that stand for a sector's nominal path in distance tests (a distance
to the path is then exact to within a quarter of it)."""


def nominal_loop(scenario: Scenario) -> np.ndarray:
    """The corners of the unperturbed loop (the square :func:`loop_waypoints` perturbs), from
    its start in the middle of the bottom edge, counter-clockwise, back to the start."""
    side = scenario.loop_side_m
    centre = 0.5 * scenario.world_size_m
    lo, hi = centre - 0.5 * side, centre + 0.5 * side
    return np.array([[centre, lo], [hi, lo], [hi, hi], [lo, hi], [lo, lo], [centre, lo]])


def sector_paths(scenario: Scenario) -> list[np.ndarray]:
    """Points every :data:`ZONE_SAMPLE_SPACING_M` along each of the ``zone_sectors`` sectors of
    equal length of the nominal loop, in the order the robot drives them."""
    corners = nominal_loop(scenario)
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(corners, axis=0), axis=1))])
    n = scenario.zone_sectors
    sectors = []
    for k in range(n):
        a, b = along[-1] * k / n, along[-1] * (k + 1) / n
        s = np.linspace(a, b, max(2, int(math.ceil((b - a) / ZONE_SAMPLE_SPACING_M)) + 1))
        sectors.append(np.column_stack([np.interp(s, along, corners[:, 0]),
                                        np.interp(s, along, corners[:, 1])]))
    return sectors


def draw_zones(scenario: Scenario, rng: np.random.Generator) -> tuple[str, ...]:
    """The kind of each sector (:data:`ZONE_KINDS`): the first and last sectors (the start,
    where the loop closes) are normal; the inner ones get the scenario's corridors, bursts and
    patches in an order drawn from ``rng`` (a uniform permutation), the rest normal."""
    kinds = ["normal"] * scenario.zone_sectors
    if not scenario.has_zones:
        return tuple(kinds)
    inner = 1 + rng.permutation(scenario.zone_sectors - 2)
    drawn = (["corridor"] * scenario.corridor_zones + ["burst"] * scenario.burst_zones
             + ["patch"] * scenario.patch_zones)
    for sector, kind in zip(inner, drawn, strict=False):
        kinds[int(sector)] = kind
    return tuple(kinds)


def _distance_to(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance of each of ``points`` (n, 2) to the nearest point of ``path`` (m, 2)."""
    if len(points) == 0:
        return np.zeros(0)
    d2 = ((points[:, None, :2] - path[None, :, :]) ** 2).sum(axis=-1)
    return np.sqrt(d2.min(axis=1))


def zoned_landmarks(scenario: Scenario, kinds, landmarks: np.ndarray,
                    rng: np.random.Generator) -> np.ndarray:
    """``landmarks`` with each patch sector's ``patch_landmarks`` added (uniform in a disc of
    ``patch_radius_m`` on the sector's midpoint, drawn from ``rng``), then every landmark within
    ``corridor_clearance_m`` of a corridor sector's nominal path removed."""
    sectors = sector_paths(scenario)
    added = []
    for kind, path in zip(kinds, sectors, strict=True):
        if kind == "patch":
            centre = path[len(path) // 2]
            radius = scenario.patch_radius_m * np.sqrt(rng.random(scenario.patch_landmarks))
            angle = rng.uniform(-np.pi, np.pi, scenario.patch_landmarks)
            added.append(centre + np.column_stack([radius * np.cos(angle),
                                                   radius * np.sin(angle)]))
    out = np.vstack([landmarks, *added]) if added else landmarks
    keep = np.ones(len(out), dtype=bool)
    for kind, path in zip(kinds, sectors, strict=True):
        if kind == "corridor":
            keep &= _distance_to(out, path) > scenario.corridor_clearance_m
    return out[keep]


def scan_clutter(scenario: Scenario, kinds, poses: np.ndarray) -> np.ndarray:
    """(n, 2): the (alpha, beta) of a scan from each true pose of ``poses`` (n, 3): the
    scenario's, with beta raised to ``burst_beta`` within ``burst_radius_m`` of a burst sector's
    nominal path."""
    out = np.tile(np.array([scenario.alpha, scenario.beta], dtype=float), (len(poses), 1))
    for kind, path in zip(kinds, sector_paths(scenario), strict=True):
        if kind == "burst":
            inside = _distance_to(np.asarray(poses)[:, :2], path) <= scenario.burst_radius_m
            out[inside, 1] = max(scenario.beta, scenario.burst_beta)
    return out


def drive(
    scenario: Scenario, waypoints: np.ndarray, rng: np.random.Generator,
    heading_offset_rad: float = 0.0,
):
    """Drive through the waypoints in order until the last one is reached.

    The robot starts at the first waypoint facing the second, turned by ``heading_offset_rad``.

    Returns the true poses at every filter step (n_steps + 1, 3), the commanded velocities of
    every odometry tick (n_steps, ticks_per_step, 2) and the true velocities of every tick (the
    commanded ones, perturbed with the ``proportional`` noise model when that is the scenario's).
    The integration is the scalar form of :func:`filters.models.motion` (the same mid-point model
    the filters use), inlined because this loop runs at the encoder rate.
    """
    dt_tick = 1.0 / scenario.odometry_rate_hz
    ticks = scenario.ticks_per_step
    noise = odometry_noise_of(scenario)
    perturb = isinstance(noise, ProportionalVelocityNoise)
    x, y = float(waypoints[0, 0]), float(waypoints[0, 1])
    theta = math.atan2(waypoints[1, 1] - y, waypoints[1, 0] - x) + heading_offset_rad
    target = 1
    v = scenario.speed_mps
    w_max = scenario.max_turn_rate_radps
    gain = scenario.heading_gain
    max_steps = int(3 * scenario.path_length_m / (v * scenario.dt_s))
    poses = [(x, y, theta)]
    commands, true_velocities = [], []
    while target < len(waypoints) and len(commands) < max_steps:
        step_commands = np.empty((ticks, 2))
        step_true = np.empty((ticks, 2))
        for tick in range(ticks):
            tx, ty = waypoints[min(target, len(waypoints) - 1)]
            if math.hypot(tx - x, ty - y) < WAYPOINT_SWITCH_RADIUS_M:
                target += 1
                tx, ty = waypoints[min(target, len(waypoints) - 1)]
            err = (math.atan2(ty - y, tx - x) - theta + math.pi) % (2.0 * math.pi) - math.pi
            w = max(-w_max, min(w_max, gain * err))
            step_commands[tick] = (v, w)
            vt, wt = v, w
            if perturb:
                # per-tick std scaled by sqrt(ticks): the step's mean velocity has the model's std
                sv, sw = noise.std(step_commands[tick]) * math.sqrt(ticks)
                vt, wt = v + sv * rng.standard_normal(), w + sw * rng.standard_normal()
            step_true[tick] = (vt, wt)
            heading = theta + 0.5 * wt * dt_tick
            x += vt * dt_tick * math.cos(heading)
            y += vt * dt_tick * math.sin(heading)
            theta = (theta + wt * dt_tick + math.pi) % (2.0 * math.pi) - math.pi
        poses.append((x, y, theta))
        commands.append(step_commands)
        true_velocities.append(step_true)
    return np.array(poses), np.array(commands), np.array(true_velocities)


def measured_odometry(
    scenario: Scenario, commands: np.ndarray, true_velocities: np.ndarray, rng
) -> np.ndarray:
    """The (v, omega) each filter step reports (see the module docstring for the two models)."""
    noise = odometry_noise_of(scenario)
    if isinstance(noise, ChongKleemanNoise):
        dt_tick = 1.0 / scenario.odometry_rate_hz
        travel = noise.wheel_travel(true_velocities, dt_tick)  # (n, ticks, 2)
        # CM (14) exactly: variance K |travel| per tick, so a step's summed error has variance
        # K |step travel| whatever the tick rate (the filters' model adds a tiny floor for rest)
        measured = travel + rng.standard_normal(travel.shape) * np.sqrt(
            noise.k_m * np.abs(travel)
        )
        return noise.velocities(measured.sum(axis=1), scenario.dt_s)
    return commands.mean(axis=1)


def scan(
    pose: np.ndarray,
    landmarks: np.ndarray,
    sensor: RangeBearingSensor,
    clutter: ClutterModel,
    rng: np.random.Generator,
):
    """One scan from ``pose``: shuffled observations (K, 2), their truth ids, visible ids."""
    z_true = observe(pose, landmarks) if len(landmarks) else np.zeros((0, 2))
    return _detect(z_true, np.flatnonzero(sensor.in_view(z_true)), sensor, clutter, rng)


def _detect(z_true, visible, sensor, clutter, rng):
    """The scan of :func:`scan` given the true observations of every landmark (L, 2) and the
    indices of the visible ones: detections, false alarms, shuffled (the random draws)."""
    detected = visible[rng.random(len(visible)) < clutter.alpha]
    n_det = len(detected)
    noise_std = np.array([sensor.range_std_m, sensor.bearing_std_rad])
    z_det = z_true[detected] + rng.standard_normal((n_det, 2)) * noise_std
    n_false = int(np.count_nonzero(rng.random(len(visible)) < clutter.beta))
    # detections first, then the false alarms (range, then bearing), in one array
    z = np.empty((n_det + n_false, 2))
    z[:n_det] = z_det
    z[n_det:, 0] = rng.uniform(0.0, sensor.max_range_m, n_false)
    z[n_det:, 1] = rng.uniform(-0.5 * sensor.fov_rad, 0.5 * sensor.fov_rad, n_false)
    z[:, 0] = np.maximum(z[:, 0], 0.0)  # a range sensor reports no negative range
    z[:, 1] = wrap_angle(z[:, 1])
    ids = np.full(n_det + n_false, -1, dtype=np.int64)
    ids[:n_det] = detected
    order = rng.permutation(len(z))
    return z[order], ids[order], visible.astype(np.int64)


@njit(cache=True)
def _detect_block(z_true, in_view, alpha, beta, range_std_m, bearing_std_rad, max_range_m,
                  fov_rad, rng):
    """:func:`_detect` for the scans of a block of poses in turn, compiled: the same random
    draws from ``rng`` in the same order and the same arithmetic, element by element.

    ``z_true`` (S, L, 2) and ``in_view`` (S, L): the true observations of every landmark and
    which are visible, per scan; ``alpha`` and ``beta`` (S,): each scan's reliability (the
    same value for every scan but where a world has clutter bursts, :func:`scan_clutter`).
    Returns the scans' observations (N, 2), truth ids (N,) and visible ids (V,) one after the
    other, and the offsets (S + 1,) of each scan in the first two
    and in the third (:func:`_detect_scans` splits them). numba's ``Generator`` methods draw from
    the caller's bit generator exactly as numpy's do (``tests/slam_gym/test_world.py`` compares
    the two paths array for array).
    """
    n_scans, n_landmarks = in_view.shape
    n_seen = 0
    for i in range(n_scans):
        for j in range(n_landmarks):
            n_seen += in_view[i, j]
    visible_all = np.empty(n_seen, dtype=np.int64)
    # at most one detection and one false alarm per visible landmark
    z_all = np.empty((2 * n_seen, 2))
    ids_all = np.empty(2 * n_seen, dtype=np.int64)
    z_start = np.zeros(n_scans + 1, dtype=np.int64)
    visible_start = np.zeros(n_scans + 1, dtype=np.int64)
    visible = np.empty(n_landmarks, dtype=np.int64)
    detected = np.empty(n_landmarks, dtype=np.int64)
    z = np.empty((2 * n_landmarks, 2))
    ids = np.empty(2 * n_landmarks, dtype=np.int64)
    half_fov = 0.5 * fov_rad
    for i in range(n_scans):
        n_visible = 0
        for j in range(n_landmarks):
            if in_view[i, j]:
                visible[n_visible] = j
                n_visible += 1
        u = rng.random(n_visible)
        n_det = 0
        for v in range(n_visible):
            if u[v] < alpha[i]:
                detected[n_det] = visible[v]
                n_det += 1
        noise = rng.standard_normal((n_det, 2))
        for d in range(n_det):
            z[d, 0] = z_true[i, detected[d], 0] + noise[d, 0] * range_std_m
            z[d, 1] = z_true[i, detected[d], 1] + noise[d, 1] * bearing_std_rad
            ids[d] = detected[d]
        u = rng.random(n_visible)
        n_false = 0
        for v in range(n_visible):
            if u[v] < beta[i]:
                n_false += 1
        ranges = rng.uniform(0.0, max_range_m, n_false)
        bearings = rng.uniform(-half_fov, half_fov, n_false)
        for f in range(n_false):
            z[n_det + f, 0] = ranges[f]
            z[n_det + f, 1] = bearings[f]
            ids[n_det + f] = -1
        n = n_det + n_false
        for k in range(n):
            r = z[k, 0]
            z[k, 0] = r if (r >= 0.0 or np.isnan(r)) else 0.0  # np.maximum(r, 0.0)
            z[k, 1] = (z[k, 1] + np.pi) % TWO_PI - np.pi  # wrap_angle
        order = rng.permutation(n)
        start = z_start[i]
        for k in range(n):
            z_all[start + k, 0] = z[order[k], 0]
            z_all[start + k, 1] = z[order[k], 1]
            ids_all[start + k] = ids[order[k]]
        z_start[i + 1] = start + n
        start = visible_start[i]
        for v in range(n_visible):
            visible_all[start + v] = visible[v]
        visible_start[i + 1] = start + n_visible
    n_total = z_start[n_scans]
    return z_all[:n_total].copy(), ids_all[:n_total].copy(), visible_all, z_start, visible_start


def _detect_scans(poses: np.ndarray, landmarks: np.ndarray, sensor: RangeBearingSensor,
                  clutter: ClutterModel, rng: np.random.Generator, reliability=None):
    """The scans (z, truth ids, visible ids) from each pose of ``poses`` (n, 3), drawn one after
    the other from ``rng``: what :func:`_detect` called once per pose in turn returns, bit for
    bit, in compiled blocks (:func:`_detect_block`; the simulator's costliest loop).
    ``reliability`` (n, 2): each scan's (alpha, beta) where they vary along the path (None:
    ``clutter``'s for every scan)."""
    reliability = _reliability(clutter, len(poses), reliability)
    scans = []
    if len(landmarks) == 0:
        for a, b in reliability:
            scans.append(_detect(np.zeros((0, 2)), np.zeros(0, dtype=np.int64), sensor,
                                 ClutterModel(alpha=float(a), beta=float(b)), rng))
        return scans
    block = max(1, OBSERVED_BLOCK_ELEMENTS // len(landmarks))
    for begin in range(0, len(poses), block):
        z_true = observe(poses[begin:begin + block, None, :], landmarks[None, :, :])
        here = reliability[begin:begin + block]
        z, ids, visible, z_start, visible_start = _detect_block(
            z_true, sensor.in_view(z_true), np.ascontiguousarray(here[:, 0]),
            np.ascontiguousarray(here[:, 1]),
            float(sensor.range_std_m), float(sensor.bearing_std_rad), float(sensor.max_range_m),
            float(sensor.fov_rad), rng,
        )
        for i in range(len(z_start) - 1):
            a, b = z_start[i], z_start[i + 1]
            scans.append((z[a:b], ids[a:b], visible[visible_start[i]:visible_start[i + 1]]))
    return scans


def _reliability(clutter: ClutterModel, n: int, reliability=None) -> np.ndarray:
    """(n, 2) float array of each scan's (alpha, beta): ``reliability``, or ``clutter``'s."""
    if reliability is None:
        return np.tile(np.array([clutter.alpha, clutter.beta], dtype=float), (n, 1))
    reliability = np.asarray(reliability, dtype=float).reshape(-1, 2)
    if len(reliability) != n:
        raise ValueError(f"reliability has {len(reliability)} rows: must have one per scan ({n})")
    return reliability


OBSERVED_BLOCK_ELEMENTS = 1 << 16
"""Pose-landmark pairs :func:`_true_views` observes at once (bounds its memory to a few MB)."""


def _true_views(poses: np.ndarray, landmarks: np.ndarray, sensor: RangeBearingSensor):
    """For each pose of ``poses`` (n, 3), in order: the true observations of every landmark
    (L, 2) and the indices of the visible ones, as :func:`scan` computes them, for blocks of
    poses at once (element-wise arithmetic on the same values, so the same numbers)."""
    if len(landmarks) == 0:
        for _ in range(len(poses)):
            yield np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
        return
    block = max(1, OBSERVED_BLOCK_ELEMENTS // len(landmarks))
    for start in range(0, len(poses), block):
        z_true = observe(poses[start:start + block, None, :], landmarks[None, :, :])
        seen = sensor.in_view(z_true)
        for z, in_view in zip(z_true, seen, strict=True):
            yield z, np.flatnonzero(in_view)


FAST_TURN_RADPS = 0.5
"""A step turns fast when its commanded turn rate exceeds this (rad/s)."""


def turning_statistics(stream, fast_radps: float = FAST_TURN_RADPS) -> dict:
    """Total turning (rad, from the odometry's turn rates) and the fraction of moving steps
    whose turn rate exceeds ``fast_radps``."""
    steps = [s for s in stream if s.dt_s > 0.0]
    omega = np.array([s.odometry[1] for s in steps]) if steps else np.zeros(0)
    dt = np.array([s.dt_s for s in steps]) if steps else np.zeros(0)
    return {
        "total_turning_rad": float(np.sum(np.abs(omega) * dt)),
        "fraction_fast_turning": float(np.mean(np.abs(omega) > fast_radps)) if len(omega) else 0.0,
    }


WORLD_CACHE_SIZE = 8
"""Worlds :func:`simulate_cached` keeps per process (a ``brooks-bailey`` world is about 5 MB)."""


def _check_seed(seed) -> None:
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed={seed!r} is invalid: must be a non-negative integer")


def _read_only(array):
    if isinstance(array, np.ndarray):
        array.flags.writeable = False
    return array


def _frozen(stream: Stream) -> Stream:
    """``stream`` with every array read-only and its steps in a tuple: a world that can be
    shared, since no holder can change it (its steps and truths are frozen dataclasses)."""
    steps = tuple(stream)
    for step in steps:
        for array in (step.odometry, step.z, step.truth.pose, step.truth.landmark_ids,
                      step.truth.visible_ids):
            _read_only(array)
    for array in (stream.initial_pose, stream.landmarks_true, *stream.metadata.values()):
        _read_only(array)
    return dataclasses.replace(stream, make_steps=steps_from_list(steps))


@functools.lru_cache(maxsize=WORLD_CACHE_SIZE)
def _remembered_world(scenario: Scenario, seed: int) -> Stream:
    """The read-only world of ``(scenario, seed)`` (:func:`simulate_cached`)."""
    return _frozen(simulate(scenario, seed))


def simulate_cached(scenario: Scenario, seed: int) -> Stream:
    """:func:`simulate`, remembering the last :data:`WORLD_CACHE_SIZE` worlds of this process.

    A world is a pure function of the scenario and the seed, so a remembered one is the world
    :func:`simulate` would return, bit for bit. Remembered worlds are shared read-only: their
    arrays cannot be written (a write raises), their steps are frozen and held in a tuple, and
    each call gets its own :class:`~slam_gym.stream.Stream` and ``metadata`` dict, so no caller
    can change another's world. Each process (e.g. a spawned worker) keeps its own cache.
    """
    _check_seed(seed)
    world = _remembered_world(scenario, int(seed))
    return dataclasses.replace(world, metadata=dict(world.metadata))


def make_stream(name: str | Scenario, seed: int, **overrides) -> Stream:
    """Simulate the scenario ``name`` (a preset name or a :class:`Scenario`, with fields
    overridden by keyword) for ``seed``, as a ``Stream`` (a world simulated recently in this
    process is shared read-only, not simulated again: :func:`simulate_cached`)."""
    return simulate_cached(get_scenario(name, **overrides), seed)


def simulate(scenario: Scenario, seed: int) -> Stream:
    """Simulate ``scenario`` for ``seed`` (a non-negative integer)."""
    _check_seed(seed)
    # a fourth child for the zones: the first three are the children spawn(3) gives, so a
    # zoned world's base (landmarks before its zones, path, odometry) is its unzoned world's
    world_rng, odometry_rng, sensor_rng, zone_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(4)
    )
    landmarks = landmark_field(scenario, world_rng)
    waypoints = loop_waypoints(scenario, world_rng)
    spread = scenario.initial_heading_spread_rad
    offset = float(world_rng.uniform(-spread, spread)) if spread > 0.0 else 0.0
    poses, commands, true_velocities = drive(
        scenario, route(scenario, waypoints), odometry_rng, heading_offset_rad=offset
    )
    zones = draw_zones(scenario, zone_rng) if scenario.has_zones else None
    if zones is not None:
        landmarks = zoned_landmarks(scenario, zones, landmarks, zone_rng)
    odometry = measured_odometry(scenario, commands, true_velocities, odometry_rng)
    sensor = sensor_of(scenario)
    clutter = ClutterModel(alpha=scenario.alpha, beta=scenario.beta)
    first = 1 if scenario.scan_at_start else 0  # the motionless scan at the start pose
    n_moving = len(commands)
    if scenario.n_steps is not None:
        n_moving = min(scenario.n_steps - first, n_moving)
    n_steps = first + n_moving
    dt = scenario.dt_s
    every = scenario.steps_per_scan
    empty_z, empty_ids = np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    steps = []
    scan_indices = [0] * first + [k + 1 for k in range(n_moving) if (k + 1) % every == 0]
    # each step's (alpha, beta): the scenario's, but in a clutter burst
    # (step j's true pose is poses[j + 1 - first]; a redrawn future reads them per step)
    step_reliability = (scan_clutter(scenario, zones, poses[1 - first:1 - first + n_steps])
                        if zones is not None else None)
    reliability = (scan_clutter(scenario, zones, poses[scan_indices])
                   if zones is not None else None)
    if scenario.compass_std_rad is None:
        # no compass draws between the scans: every scan's draws in one compiled pass
        scans = iter(_detect_scans(poses[scan_indices], landmarks, sensor, clutter, sensor_rng,
                                   reliability))

        def scan_at_next_pose():
            return next(scans)
    else:
        views = _true_views(poses[scan_indices], landmarks, sensor)
        reliabilities = iter(_reliability(clutter, len(scan_indices), reliability))

        def scan_at_next_pose():
            z_true, visible = next(views)
            a, b = next(reliabilities)
            return _detect(z_true, visible, sensor, ClutterModel(alpha=float(a), beta=float(b)),
                           sensor_rng)

    def compass_at(pose):
        if scenario.compass_std_rad is None:
            return None
        return float(wrap_angle(pose[2] + scenario.compass_std_rad * sensor_rng.normal()))

    if first:
        z, ids, visible = scan_at_next_pose()
        steps.append(
            Step(
                index=0,
                t_s=0.0,
                dt_s=0.0,
                odometry=np.zeros(2),
                compass_rad=compass_at(poses[0]),
                z=z,
                truth=StepTruth(pose=poses[0].copy(), landmark_ids=ids, visible_ids=visible),
            )
        )
    for k in range(n_moving):
        pose = poses[k + 1]
        scanned = (k + 1) % every == 0
        if scanned:
            z, ids, visible = scan_at_next_pose()
        else:
            z, ids, visible = empty_z, empty_ids, None
        steps.append(
            Step(
                index=first + k,
                t_s=(k + 1) * dt,
                dt_s=dt,
                odometry=odometry[k],
                compass_rad=compass_at(pose),
                z=z,
                truth=StepTruth(pose=pose, landmark_ids=ids, visible_ids=visible),
                scanned=scanned,
            )
        )
    return Stream(
        name=scenario.name,
        sensor=sensor,
        clutter=clutter,
        odometry_noise=odometry_noise_of(scenario),
        initial_pose=poses[0].copy(),
        landmarks_true=landmarks,
        n_steps=n_steps,
        dt_s=dt,
        make_steps=steps_from_list(steps),
        compass_std_rad=scenario.compass_std_rad,
        metadata={
            "scenario": scenario,
            "seed": int(seed),
            "waypoints": waypoints,
            "true_poses": poses[: n_moving + 1],
            **({"zones": zones, "step_reliability": step_reliability}
               if zones is not None else {}),
        },
    )


FUTURE_BLOCK_STEPS = 64
"""Steps :class:`RedrawnFuture` redraws at once (a lookahead rarely needs more than a few
hundred steps of a future, so the rest of the path is drawn only if it is reached)."""


class RedrawnFuture:
    """The steps of a simulated world from index ``start`` on, with their measurement noise drawn
    anew from ``seed``: an iterator that can stand in for the rest of an episode's stream.

    What is kept: the true path (poses), the landmarks, which steps scan, the odometry, the
    sensor and clutter models. What is redrawn, in the order :func:`simulate` draws it: each
    scan's detections, their range-bearing noise and its false alarms (and the compass reading
    where the scenario has a compass). The odometry is kept as recorded: under BB's model
    (``odometry_noise="proportional"``) it is the commanded velocity and the noise lives in the
    true path, which a re-seeded future must keep; under CM's model (``"chong-kleeman"``) the
    recorded odometry errors stay those of the episode (a documented limit: they cannot be
    redrawn without the path's true velocities). Steps are drawn lazily in blocks of
    :data:`FUTURE_BLOCK_STEPS`, so a short lookahead pays only for the steps it plays.

    ``stream`` must be a simulated world (its ``metadata`` names the scenario); a recording has
    no model to redraw from and raises ``ValueError``. The object deep-copies and pickles (its
    source steps are shared read-only by :meth:`slam_gym.envs.hybrid_slam.HybridSLAMEnv.clone`).
    """

    def __init__(self, stream: Stream, start: int, seed: int):
        if not isinstance(stream.metadata.get("scenario"), Scenario):
            raise ValueError(
                f"stream={stream.name!r} is invalid for a redrawn future: must be a simulated "
                "world (a recording has no sensor model to redraw its noise from)"
            )
        _check_seed(seed)
        if not isinstance(start, (int, np.integer)) or not 0 <= start <= len(stream):
            raise ValueError(f"start={start!r} is invalid: must be an integer in "
                             f"[0, {len(stream)}]")
        steps = stream.make_steps
        self.source = steps.steps if hasattr(steps, "steps") else tuple(stream)
        self.landmarks = stream.landmarks_true
        self.sensor = stream.sensor
        self.clutter = stream.clutter
        self.compass_std_rad = stream.compass_std_rad
        #: each step's (alpha, beta) in a world with clutter bursts (None: the stream's clutter)
        self.step_reliability = stream.metadata.get("step_reliability")
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(start)]))
        self.next_index = int(start)
        self._buffer: list[Step] = []

    def __iter__(self):
        return self

    def __next__(self) -> Step:
        if not self._buffer:
            if self.next_index >= len(self.source):
                raise StopIteration
            self._buffer = self._draw(self.next_index,
                                      min(self.next_index + FUTURE_BLOCK_STEPS, len(self.source)))
            self._buffer.reverse()  # pop() from the end
        self.next_index += 1
        return self._buffer.pop()

    def _draw(self, begin: int, end: int) -> list[Step]:
        block = self.source[begin:end]
        scanned = [s for s in block if s.scanned]
        reliability = None
        if self.step_reliability is not None:
            reliability = np.asarray(self.step_reliability[begin:end])[
                [s.scanned for s in block]]
        if self.compass_std_rad is None:
            poses = np.array([s.truth.pose for s in scanned]).reshape(-1, 3)
            scans = iter(_detect_scans(poses, self.landmarks, self.sensor, self.clutter,
                                       self.rng, reliability))
        out = []
        for position, step in enumerate(block, start=begin):
            compass = step.compass_rad
            z, ids, visible = step.z, step.truth.landmark_ids, step.truth.visible_ids
            if step.scanned:
                if self.compass_std_rad is None:
                    z, ids, visible = next(scans)
                else:
                    clutter = self.clutter
                    if self.step_reliability is not None:
                        a, b = self.step_reliability[position]
                        clutter = ClutterModel(alpha=float(a), beta=float(b))
                    z, ids, visible = scan(step.truth.pose, self.landmarks, self.sensor,
                                           clutter, self.rng)
            if compass is not None and self.compass_std_rad is not None:
                compass = float(wrap_angle(step.truth.pose[2]
                                           + self.compass_std_rad * self.rng.normal()))
            out.append(dataclasses.replace(
                step, z=z, compass_rad=compass,
                truth=StepTruth(pose=step.truth.pose, landmark_ids=ids, visible_ids=visible),
            ))
        return out
