"""An independent reference for the sub-map optimiser: CM (12) solved by GTSAM.

The problem of :mod:`filters.submap_optimise` (read its module docstring) is rebuilt as a GTSAM
factor graph: a ``Pose2`` per fusion pose ``x_1 .. x_S`` (``x_0``, the initial pose, is the gauge
and enters the factors of the sub-maps starting there as a constant), a ``Point2`` per global
feature, and one ``gtsam.CustomFactor`` per stored sub-map whose error is
``psi_s(tau) - r_s`` (heading wrapped) under the noise model
``Gaussian.Information(P_s^-1)``, with ``P_s^-1`` the project's floored information
(:func:`filters.submap_optimise.gaussian_information`). The Jacobians are those of
:mod:`filters.geometry` carried into GTSAM's tangent space: a ``Pose2`` is perturbed as
``x.retract(v) = x (+) Exp(v)``, i.e. in its own frame, so ``d x / d v = blockdiag(R(theta), 1)``
at ``v = 0``; a ``Point2`` is perturbed additively. The test
(tests/filters/test_gtsam_reference.py) checks them against finite differences on ``retract``.

The script runs the sub-map system (HYBRID front-end) on Brooks-Bailey's world, fusing every
``--steps-per-fusion`` steps until ``--submaps`` sub-maps are stored, then

* solves the problem with the project's optimiser, ``system.optimise()`` on a fresh deep copy of
  the system each repeat (cold: no warm start, no cached sub-map informations), and
* solves it with GTSAM (Levenberg-Marquardt by default: GTSAM's plain Gauss-Newton overshoots
  from this start and stops; ``--method gauss-newton`` shows it) from the project's starting
  point (the chain of sub-maps, ``RelativeProblem.initial_guess()`` of
  ``build_submap_problem``), with tight tolerances,

and prints the largest differences of the two optima (fusion poses: x, y, heading; features), of
their costs (CM (12), i.e. twice GTSAM's ``graph.error``), and the median process CPU time of
each solver over ``--repeats`` runs (after one untimed warm-up run each). The project's time is
the whole of ``system.optimise()``, its Gauss-Newton covariance and write-back included; GTSAM's
is building the graph (the sub-maps' informations included) and optimising it, nothing else.
BLAS is limited to one thread, as ``slam_gym``'s CLI does (``one_blas_thread_per_process``):
with several, OpenBLAS's spinning threads dominate the process time on busy cores.

Run (from the repository root)::

    .venv/bin/python scripts/performance/gtsam_reference.py --submaps 40 --seed 0 \
        --particles 100 --repeats 7

Supports docs/PERFORMANCE.md, "optimise() (issue 27 item 2)".
The command behind it::

    python scripts/performance/gtsam_reference.py --submaps 40 --seed 0 --particles 100 --repeats 7
"""

from __future__ import annotations

import argparse
import copy
import time
from dataclasses import dataclass

import gtsam
import numpy as np

from filters.geometry import (
    point_to_frame,
    point_to_frame_jacobians,
    relative,
    relative_jacobians,
    wrap_angle,
)
from filters.submap_optimise import (
    DEFAULT_MIN_VARIANCE,
    build_submap_problem,
    gaussian_information,
)
from slam_gym.cli import one_blas_thread_per_process
from slam_gym.systems import make_system
from slam_gym.world import make_stream


# --------------------------------------------------------------------------- the problem
def run_system(n_submaps: int = 40, seed: int = 0, particles: int = 100, *,
               steps_per_fusion: int = 100, clutter_level: int = 2, n_steps: int | None = None):
    """The sub-map system after ``n_submaps`` fusions (one every ``steps_per_fusion`` steps) on
    Brooks-Bailey's world; fewer if the stream (``n_steps`` long when given) ends first."""
    overrides = {"clutter_level": clutter_level}
    if n_steps is not None:
        overrides["n_steps"] = n_steps
    stream = make_stream("brooks-bailey", seed=seed, **overrides)
    system = make_system("hybrid", stream, np.random.default_rng(seed),
                         n_particles=particles).estimator
    for i, step in enumerate(stream):
        system.predict(step.odometry, step.dt_s)
        system.update(step.z)
        if (i + 1) % steps_per_fusion == 0:
            system.fuse()
            if len(system.submaps) >= n_submaps:
                break
    return system


def gauge_of(system) -> np.ndarray:
    """The initial pose, which must be known exactly (zero covariance: the env's case)."""
    back = system.back_end
    cov = getattr(back, "initial_pose_cov", None)
    if cov is not None and np.any(np.asarray(cov, dtype=float)):
        raise ValueError("an uncertain initial pose (world-frame gauge) is not supported here")
    return np.asarray(back.initial_pose, dtype=float)


def initial_guess(submaps, x0):
    """The project's starting point: fusion poses (S + 1, 3) and ``{global id: (2,)}``."""
    sp_problem = build_submap_problem(copy.deepcopy(submaps), x0)  # leave their caches empty
    means = sp_problem.problem.means(sp_problem.problem.initial_guess())
    poses = means[sp_problem.pose_entity].copy()
    features = {g: means[e, :2].copy() for g, e in sp_problem.feature_entity.items()}
    return poses, features


# --------------------------------------------------------------------------- GTSAM graph
def pose_key(k: int) -> int:
    return gtsam.symbol("x", int(k))


def feature_key(gid: int) -> int:
    return gtsam.symbol("l", int(gid))


def _pose_array(pose: gtsam.Pose2) -> np.ndarray:
    return np.array([pose.x(), pose.y(), pose.theta()])


def _tangent(theta: float) -> np.ndarray:
    """``d x / d v`` of ``x.retract(v)`` at ``v = 0`` for a Pose2 ``x`` with heading ``theta``:
    the local (body-frame) perturbation rotated into the global frame."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def submap_error_function(origin: int, end: int, gids, r, x0):
    """The ``CustomFactor`` error function of one sub-map, and its keys (in that order).

    ``r``: the sub-map's mean ``[end pose, 2 per feature]`` (origin frame), ``gids`` the global
    id of each of its features. Pose 0 (the gauge ``x0``) is a constant, not a key. A global
    feature listed twice in one sub-map gets one key and the sum of its Jacobian blocks."""
    r = np.asarray(r, dtype=float).copy()
    r[2] = wrap_angle(r[2])
    gids = [int(g) for g in gids]
    keys = ([] if origin == 0 else [pose_key(origin)]) + [pose_key(end)]
    dims = [3] * len(keys)
    for g in dict.fromkeys(gids):
        keys.append(feature_key(g))
        dims.append(2)
    column = {k: i for i, k in enumerate(keys)}
    d = 3 + 2 * len(gids)
    x0 = np.asarray(x0, dtype=float)

    def error(this, values, H):
        xo = x0 if origin == 0 else _pose_array(values.atPose2(pose_key(origin)))
        xe = _pose_array(values.atPose2(pose_key(end)))
        e = np.empty(d)
        e[:2] = relative(xo, xe)[:2] - r[:2]
        e[2] = wrap_angle(xe[2] - xo[2] - r[2])
        points = [np.asarray(values.atPoint2(feature_key(g)), dtype=float) for g in gids]
        for i, p in enumerate(points):
            e[3 + 2 * i:5 + 2 * i] = point_to_frame(xo, p) - r[3 + 2 * i:5 + 2 * i]
        if H is not None:
            blocks = [np.zeros((d, dim)) for dim in dims]
            J_o, J_e = relative_jacobians(xo, xe)
            if origin != 0:
                T_o = _tangent(xo[2])
                blocks[column[pose_key(origin)]][:3] += J_o @ T_o
            blocks[column[pose_key(end)]][:3] += J_e @ _tangent(xe[2])
            for i, (g, p) in enumerate(zip(gids, points, strict=True)):
                J_pose, J_p = point_to_frame_jacobians(xo, p)
                rows = slice(3 + 2 * i, 5 + 2 * i)
                if origin != 0:
                    blocks[column[pose_key(origin)]][rows] += J_pose @ T_o
                blocks[column[feature_key(g)]][rows] += J_p
            for i, block in enumerate(blocks):
                H[i] = block
        return e

    return error, keys


def build_graph(submaps, x0, poses0, features0, min_variance: float = DEFAULT_MIN_VARIANCE):
    """The factor graph of CM (12) and its initial values (``poses0`` (S + 1, 3): row 0, the
    gauge, is not a variable; ``features0``: ``{global id: (2,)}``)."""
    graph = gtsam.NonlinearFactorGraph()
    for s in submaps:
        g = s.gaussian
        gids = [s.id_map[int(lid)] for lid in np.asarray(g.ids, dtype=np.int64)]
        error, keys = submap_error_function(int(s.origin_index), int(s.end_index), gids, g.x, x0)
        noise = gtsam.noiseModel.Gaussian.Information(gaussian_information(g.P, min_variance))
        graph.add(gtsam.CustomFactor(noise, keys, error))
    values = gtsam.Values()
    for k in range(1, len(poses0)):
        values.insert(pose_key(k), gtsam.Pose2(*np.asarray(poses0[k], dtype=float)))
    for gid, p in features0.items():
        values.insert(feature_key(gid), np.asarray(p, dtype=float))
    return graph, values


METHODS = ("levenberg-marquardt", "gauss-newton")
"""GTSAM optimisers :func:`optimise_graph` offers (``--method``)."""


def optimise_graph(graph, values, method: str = "levenberg-marquardt", *,
                   tolerance: float = 1e-15, max_iterations: int = 100):
    """GTSAM's Levenberg-Marquardt (or undamped Gauss-Newton) until the cost stops decreasing
    (relative and absolute ``tolerance``): ``(optimum values, iterations)``."""
    if method == "gauss-newton":
        params = gtsam.GaussNewtonParams()
    elif method == "levenberg-marquardt":
        params = gtsam.LevenbergMarquardtParams()
    else:
        raise ValueError(f"method {method!r}: one of {METHODS}")
    params.setRelativeErrorTol(tolerance)
    params.setAbsoluteErrorTol(tolerance)
    params.setMaxIterations(max_iterations)
    if method == "gauss-newton":
        optimizer = gtsam.GaussNewtonOptimizer(graph, values, params)
    else:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    return result, optimizer.iterations()


def values_of(poses, features) -> gtsam.Values:
    """Values holding fusion poses 1 .. S of ``poses`` and the ``features``."""
    values = gtsam.Values()
    for k in range(1, len(poses)):
        values.insert(pose_key(k), gtsam.Pose2(*np.asarray(poses[k], dtype=float)))
    for gid, p in features.items():
        values.insert(feature_key(gid), np.asarray(p, dtype=float))
    return values


def optimum_of(values, x0, n_poses: int, gids):
    """Fusion poses (n_poses, 3; row 0 the gauge) and ``{gid: (2,)}`` read from GTSAM values."""
    poses = np.empty((n_poses, 3))
    poses[0] = x0
    for k in range(1, n_poses):
        poses[k] = _pose_array(values.atPose2(pose_key(k)))
    return poses, {g: np.asarray(values.atPoint2(feature_key(g)), dtype=float) for g in gids}


def project_optimum(result):
    """Fusion poses (S + 1, 3) and ``{gid: (2,)}`` of an :class:`OptimiseResult`: from its
    general optimiser's entity coordinates when it has them, else from its warm-start record."""
    if result.problem is not None and result.optimiser is not None:
        means = result.optimiser.means
        sp_problem = result.problem
        return (means[sp_problem.pose_entity].copy(),
                {g: means[e, :2].copy() for g, e in sp_problem.feature_entity.items()})
    warm = result.warm_start
    return (np.asarray(warm["poses"], dtype=float).copy(),
            {g: np.asarray(p, dtype=float).copy() for g, p in warm["features"].items()})


# --------------------------------------------------------------------------- comparison
@dataclass
class Comparison:
    """Largest absolute differences of two optima and their costs (CM (12))."""

    position_m: float
    heading_rad: float
    feature_m: float
    project_cost: float
    gtsam_cost: float
    project_cost_on_graph: float
    gtsam_iterations: int
    initial_cost: float

    @property
    def cost_difference(self) -> float:
        return abs(self.project_cost - self.gtsam_cost)


def solve_with_gtsam(system, method: str = "levenberg-marquardt",
                     min_variance: float = DEFAULT_MIN_VARIANCE):
    """Build and solve the graph of ``system``'s sub-maps from the project's starting point:
    ``(graph, optimum values, iterations, initial cost)``."""
    x0 = gauge_of(system)
    poses0, features0 = initial_guess(system.submaps, x0)
    graph, values = build_graph(system.submaps, x0, poses0, features0, min_variance)
    initial_cost = 2.0 * graph.error(values)
    optimum, iterations = optimise_graph(graph, values, method)
    return graph, optimum, iterations, initial_cost


def compare(system, method: str = "levenberg-marquardt") -> Comparison:
    """Solve ``system``'s problem with both optimisers (the project's on a deep copy) and compare
    the optima."""
    graph, optimum, iterations, initial_cost = solve_with_gtsam(system, method)
    result = copy.deepcopy(system).optimise()
    poses_p, features_p = project_optimum(result)
    graph_ids = {int(s.id_map[int(lid)]) for s in system.submaps for lid in s.gaussian.ids}
    if graph_ids != {int(g) for g in features_p} or len(poses_p) != len(system.submaps) + 1:
        raise AssertionError("the two problems do not have the same variables")
    poses_g, features_g = optimum_of(optimum, gauge_of(system), len(poses_p), features_p)
    d_pose = poses_p - poses_g
    d_pose[:, 2] = wrap_angle(d_pose[:, 2])
    d_feat = np.array([features_p[g] - features_g[g] for g in features_p])
    return Comparison(
        position_m=float(np.abs(d_pose[:, :2]).max()),
        heading_rad=float(np.abs(d_pose[:, 2]).max()),
        feature_m=float(np.abs(d_feat).max()) if len(d_feat) else 0.0,
        project_cost=float(result.cost),
        gtsam_cost=2.0 * graph.error(optimum),
        project_cost_on_graph=2.0 * graph.error(values_of(poses_p, features_p)),
        gtsam_iterations=iterations,
        initial_cost=initial_cost,
    )


def time_project(system, repeats: int) -> list[float]:
    """Process CPU seconds of ``system.optimise()`` on a fresh deep copy each repeat (copying
    untimed), after one untimed warm-up."""
    out = []
    for i in range(repeats + 1):
        cold = copy.deepcopy(system)
        t = time.process_time()
        cold.optimise()
        if i:
            out.append(time.process_time() - t)
    return out


def time_gtsam(system, repeats: int, method: str = "levenberg-marquardt") -> list[float]:
    """Process CPU seconds of building the graph and optimising it (the starting point computed
    untimed), after one untimed warm-up."""
    x0 = gauge_of(system)
    poses0, features0 = initial_guess(system.submaps, x0)
    out = []
    for i in range(repeats + 1):
        t = time.process_time()
        graph, values = build_graph(system.submaps, x0, poses0, features0)
        optimise_graph(graph, values, method)
        if i:
            out.append(time.process_time() - t)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--submaps", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--steps-per-fusion", type=int, default=100)
    parser.add_argument("--clutter-level", type=int, default=2)
    parser.add_argument("--method", choices=METHODS, default=METHODS[0],
                        help="GTSAM's optimiser (undamped Gauss-Newton can diverge from the "
                        "chain of sub-maps)")
    args = parser.parse_args(argv)
    one_blas_thread_per_process()  # as the CLI runs: multi-threaded BLAS spins on busy cores

    system = run_system(args.submaps, args.seed, args.particles,
                        steps_per_fusion=args.steps_per_fusion, clutter_level=args.clutter_level)
    pristine = copy.deepcopy(system)  # never optimised: empty sub-map caches
    c = compare(pristine, args.method)
    n_features = len({g for s in system.submaps for g in s.id_map.values()})
    print(f"problem: {len(system.submaps)} sub-maps, {n_features} global features, "
          f"seed {args.seed}, {args.particles} particles")
    print(f"max |difference| of the optima: fusion poses x, y {c.position_m:.3g} m, "
          f"heading {c.heading_rad:.3g} rad; features {c.feature_m:.3g} m")
    print(f"cost (CM (12)): start {c.initial_cost:.10g}; project {c.project_cost:.12g}, "
          f"GTSAM {c.gtsam_cost:.12g} ({c.gtsam_iterations} {args.method} iterations); "
          f"|difference| {c.cost_difference:.3g} "
          f"(relative {c.cost_difference / max(abs(c.gtsam_cost), 1e-300):.3g}); "
          f"GTSAM's graph at the project's optimum {c.project_cost_on_graph:.12g}")
    t_project = float(np.median(time_project(pristine, args.repeats))) * 1e3
    t_gtsam = float(np.median(time_gtsam(pristine, args.repeats, args.method))) * 1e3
    print(f"median process CPU time over {args.repeats} repeats: project system.optimise() "
          f"(cold; covariance and write-back included) {t_project:.2f} ms; GTSAM (graph "
          f"construction + {args.method}) {t_gtsam:.2f} ms; GTSAM / project "
          f"{t_gtsam / t_project:.2f}")


if __name__ == "__main__":
    main()
