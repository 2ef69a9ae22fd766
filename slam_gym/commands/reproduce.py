"""``slam-gym reproduce``: the papers' experiments (BB Table 1 and Figs. 3-4; CM IV)."""

from __future__ import annotations

import numpy as np

from slam_gym.commands.common import emit, out_dir
from slam_gym.commands.runs import (
    add_run_options,
    execute,
    int_list,
    name_list,
    plot_episode_map,
    print_table,
)

#: BB Table 1, success rates per clutter level (BB 5.3)
BB_TABLE1 = {
    "fastslam": {0: 0.0, 1: 0.0, 2: 0.0, 3: 0.0},
    "ekf-submap": {0: 0.79, 1: 0.76, 2: 0.72, 3: 0.30},
    "hybrid": {0: 0.87, 1: 0.89, 2: 0.83, 3: 0.63},
}
#: the names BB uses for its three filters -> our systems
BB_SYSTEMS = {"fastslam": "fastslam", "ekf": "ekf-submap", "hybrid": "hybrid"}


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("reproduce", help="reproduce the papers' experiments")
    targets = p.add_subparsers(dest="target", required=True, metavar="TARGET")
    bb = targets.add_parser(
        "brooks-bailey",
        help="BB Table 1 (FASTSLAM, EKF, HYBRID x clutter levels) and Figs. 3-4",
        description="Success rates of BB Table 1 over random worlds, with Wilson intervals, "
        "and the vehicle-uncertainty traces of BB Figs. 3 and 4.",
    )
    bb.add_argument("--systems", default="fastslam,ekf,hybrid",
                    help="comma-separated among fastslam, ekf, hybrid")
    bb.add_argument("--clutter-levels", default="0,1,2,3")
    bb.add_argument("--particles", type=int, default=500)
    bb.add_argument("--fusion-interval-s", type=float, default=10.0)
    bb.add_argument("--optimise", choices=["never", "at-end", "every-fusion", "after-loop-closure"],
                    default="never",
                    help="optimise() schedule of the sub-map systems (BB: never)")
    bb.add_argument("--no-figures", action="store_true", help="skip the trace figures")
    add_run_options(bb, default_out="out/reproduce-brooks-bailey")
    bb.set_defaults(run=run_brooks_bailey)
    from slam_gym.commands import reproduce_cm, reproduce_real

    reproduce_cm.add_parser(targets)
    reproduce_real.add_parser(targets)


def run_brooks_bailey(args) -> int:
    from slam_gym.evaluation import Job, write_summary

    systems = name_list(args.systems)
    unknown = [s for s in systems if s not in BB_SYSTEMS]
    if unknown:
        raise ValueError(f"systems={unknown} is invalid: must be among {sorted(BB_SYSTEMS)}")
    levels = int_list(args.clutter_levels)
    out = out_dir(args)
    options = {"n_particles": args.particles, "fusion_interval_s": args.fusion_interval_s,
               "optimise": args.optimise}
    jobs = [
        Job("system", BB_SYSTEMS[s], "brooks-bailey", level, seed,
            options if BB_SYSTEMS[s] != "fastslam" else {"n_particles": args.particles})
        for s in systems
        for level in levels
        for seed in range(args.seed_start, args.seed_start + args.trials)
    ]
    rows = execute(args, jobs, out)
    paper = BB_TABLE1
    doc = write_summary(out, rows, paper=paper)
    from slam_gym.evaluation import plot_success_rates

    figures = {"success": str(plot_success_rates(doc, out / "success_rates.png", paper=paper,
                                                 title="BB Table 1: success rate"))}
    if not args.no_figures:
        figures.update(trace_figures(systems, args.seed_start, args.particles, out))
    print_table(args, doc, paper=paper, title="BB Table 1 reproduced (paper in the last column)")
    emit(args, {"summary": doc, "figures": figures, "out": str(out)},
         [f"wrote {out / 'results.jsonl'}, summary.json, table.md and {len(figures)} figures"])
    return 0


def trace_figures(systems, seed, n_particles, out) -> dict:
    """BB Figs. 3 (compass, no clutter) and 4 (no compass): trace of the vehicle covariance."""
    from slam_gym.evaluation import plot_nees, plot_uncertainty_traces
    from slam_gym.evaluation.core import make_job_stream, run_system

    figures = {}
    for scenario, figure in (("brooks-bailey-compass", "fig3"), ("brooks-bailey", "fig4")):
        stream = make_job_stream(scenario, 0, seed)
        traces, nees_traces, episodes = {}, {}, {}
        for s in systems:
            ep = run_system(BB_SYSTEMS[s], stream, seed, n_particles=n_particles,
                            stop_on_failure=False, record_trace=True)
            traces[s.upper()] = np.array(ep.trace.cov_trace)
            nees_traces[s.upper()] = np.array(ep.trace.nees)
            episodes[s] = ep
        name = f"{figure}_uncertainty_{scenario}.png"
        figures[figure] = str(plot_uncertainty_traces(
            traces, out / name, dt_s=stream.dt_s,
            title=f"Vehicle uncertainty, {scenario}, clutter 0, seed {seed}",
        ))
        figures[f"{figure}_nees"] = str(plot_nees(
            nees_traces, out / f"{figure}_nees_{scenario}.png", dt_s=stream.dt_s,
            title=f"Vehicle NEES, {scenario}, seed {seed}",
        ))
        if figure == "fig4" and "hybrid" in episodes:
            figures["map"] = plot_episode_map(
                episodes["hybrid"], out / "map_hybrid.png", f"HYBRID, {scenario}, seed {seed}"
            )
    return figures
