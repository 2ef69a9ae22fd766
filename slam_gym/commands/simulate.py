"""``slam-gym simulate``: one simulated run with dead reckoning only, and a picture of it."""

from __future__ import annotations

import numpy as np

from filters.dead_reckoning import DeadReckoning
from slam_gym.commands.common import add_common_options, emit, out_dir
from slam_gym.scenarios import scenario_names
from slam_gym.world import turning_statistics


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate one run (dead reckoning only) and draw the world",
        description="Simulate one run of a scenario with dead reckoning only; writes world.png.",
    )
    p.add_argument("--scenario", default="brooks-bailey", choices=scenario_names(),
                   help="the world's scenario (slam_gym/scenarios.py; default brooks-bailey)")
    p.add_argument("--clutter-level", type=int, default=None, choices=[0, 1, 2, 3],
                   help="BB's clutter level 0-3 (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="the world's seed")
    p.add_argument("--path-perturbation-m", type=float, default=None,
                   help="the waypoint jitter of the path (m; default: the scenario's), the scalar "
                   "that sets its turning (issue 28)")
    add_common_options(p, default_out="out/simulate")
    p.set_defaults(run=run)


def loop_closed(stream, start_fraction: float = 0.1, end_fraction: float = 0.1) -> bool:
    """Whether the last part of the path re-observes a landmark seen in its first part."""
    scans = [s.truth.visible_ids for s in stream if s.truth.visible_ids is not None]
    n = len(scans)
    head = max(1, int(start_fraction * n))
    tail = max(1, int(end_fraction * n))
    first = set(np.concatenate(scans[:head]).tolist())
    last = set(np.concatenate(scans[-tail:]).tolist())
    return bool(first & last)


def dead_reckon(stream):
    """Means and covariances of dead reckoning at every step (n_steps + 1)."""
    f = DeadReckoning(stream.odometry_noise, stream.initial_pose)
    means, covs = [f.pose()[0]], [f.pose()[1]]
    for step in stream:
        f.predict(step.odometry, step.dt_s)
        if step.compass_rad is not None:
            f.update_heading(step.compass_rad, stream.compass_std_rad)
        m, P = f.pose()
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


def summarise(stream) -> dict:
    poses = np.array([stream.initial_pose] + [s.truth.pose for s in stream])
    n_visible = n_det = n_fa = 0
    for s in stream:
        ids = s.truth.landmark_ids
        n_visible += 0 if s.truth.visible_ids is None else len(s.truth.visible_ids)
        n_det += int(np.count_nonzero(ids >= 0))
        n_fa += int(np.count_nonzero(ids == -1))
    return {
        "scenario": stream.name,
        "seed": stream.metadata.get("seed"),
        "path_perturbation_m": stream.metadata["scenario"].path_perturbation_m,
        "alpha": stream.clutter.alpha,
        "beta": stream.clutter.beta,
        "path_length_m": float(np.sum(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1))),
        "iterations": len(stream),
        "n_landmarks": len(stream.landmarks_true),
        "n_visible": n_visible,
        "n_detections": n_det,
        "n_false_alarms": n_fa,
        "loop_closed": loop_closed(stream),
        **turning_statistics(stream),
    }


def draw(stream, means, covs, path) -> None:
    import matplotlib.pyplot as plt

    from slam_gym.render import draw_map

    true_path = np.array([stream.initial_pose] + [s.truth.pose for s in stream])
    every = max(1, len(means) // 20)
    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    draw_map(
        ax,
        landmarks_true=stream.landmarks_true,
        true_path=true_path,
        est_path=means,
        pose_ellipses=list(zip(means[::every], covs[::every], strict=True)),
        world_size_m=stream.metadata["scenario"].world_size_m,
    )
    ax.plot(*true_path[0, :2], "ko", ms=6, label="start")
    ax.set_title(
        f"{stream.name}, seed {stream.metadata.get('seed')}: truth and dead reckoning "
        "(2-sigma ellipses)"
    )
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(args) -> int:
    from slam_gym.world import make_stream

    overrides = {} if args.clutter_level is None else {"clutter_level": args.clutter_level}
    if args.path_perturbation_m is not None:
        overrides["path_perturbation_m"] = args.path_perturbation_m
    stream = make_stream(args.scenario, seed=args.seed, **overrides)
    means, covs = dead_reckon(stream)
    out = out_dir(args)
    png = out / "world.png"
    draw(stream, means, covs, png)
    summary = summarise(stream)
    final_error = float(np.linalg.norm(means[-1, :2] - stream.metadata["true_poses"][-1, :2]))
    summary["dead_reckoning_final_error_m"] = final_error
    summary["world_png"] = str(png)
    emit(
        args,
        summary,
        [
            f"scenario {summary['scenario']} seed {summary['seed']} "
            f"(alpha={summary['alpha']}, beta={summary['beta']})",
            f"  path {summary['path_length_m']:.1f} m in {summary['iterations']} iterations, "
            f"loop closed: {summary['loop_closed']}, "
            f"waypoint jitter {summary['path_perturbation_m']:g} m, "
            f"turning {summary['total_turning_rad']:.1f} rad, "
            f"{100 * summary['fraction_fast_turning']:.1f} % of steps faster than 0.5 rad/s",
            f"  {summary['n_landmarks']} landmarks, {summary['n_visible']} landmark-in-range "
            f"events, {summary['n_detections']} detections, "
            f"{summary['n_false_alarms']} false alarms",
            f"  dead reckoning final position error {final_error:.2f} m",
            f"  wrote {png}",
        ],
    )
    return 0
