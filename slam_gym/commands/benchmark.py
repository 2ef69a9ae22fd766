"""``slam-gym benchmark``: interface policies compared in the env, in parallel and resumable."""

from __future__ import annotations

import logging

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

logger = logging.getLogger(__name__)

QUICK = {
    "policies": "fixed-10s,esdf-innovation,fixed-10s-optimise,learned",
    "clutter_levels": "0,1,2,3",
    "seeds": 3,
    "particles": 500,
}

DEFAULT_POLICIES = (
    "never,always,fixed-10s,fixed-10s-optimise,esdf-innovation,innovation-fusion,"
    "adaptive-diversity,imminent-closure"
)
"""The rules of the literature and the adaptive ones (issue 13): every default a reviewer asks."""

BASELINE_SYSTEMS = ("dead-reckoning",)
"""Systems that can run beside the policies on the same worlds (``--baselines``)."""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "benchmark",
        help="compare interface policies in the env",
        description="Run policies x clutter levels x seeds through SlamGym/HybridSLAM-v0 (a "
        "process pool or Ray), write results.jsonl (resumable), summary.json, table.md and "
        "plots. --quick is the README's main job.",
    )
    p.add_argument("--policies", default=DEFAULT_POLICIES)
    p.add_argument("--env", default=None, metavar="ID",
                   help="a registered simulated env id whose front-end and back-end to use "
                   "(e.g. SlamGym/HybridSLAM-Relative-v0); --front-end/--back-end otherwise")
    p.add_argument("--baselines", default="dead-reckoning",
                   help="systems run on the same worlds beside the policies, comma-separated "
                   f"from {','.join(BASELINE_SYSTEMS)} ('' for none): dead reckoning meets BB's "
                   "success criterion without a map, which map completeness shows")
    p.add_argument("--clutter-levels", default="0,1,2,3")
    p.add_argument("--scenario", default="brooks-bailey")
    p.add_argument("--particles", type=int, default=500)
    p.add_argument("--decision-interval", type=int, default=10)
    p.add_argument("--front-end", choices=["fastslam", "ekf"], default="fastslam")
    p.add_argument("--back-end", choices=["ekf", "relative"], default="ekf")
    p.add_argument("--model", default=None, help="model zip for the learned policy")
    p.add_argument("--quick", action="store_true",
                   help=f"the quick benchmark: {QUICK['seeds']} seeds, {QUICK['particles']} "
                   "particles, all clutter levels, fixed-10s, esdf-innovation, learned")
    p.add_argument("--no-figures", action="store_true")
    add_run_options(p, default_out="out/benchmark", trials_flag="--seeds")
    p.set_defaults(run=run)


def run(args) -> int:
    import policies
    from slam_gym.evaluation import Job, plot_pareto, plot_success_rates, write_summary
    from slam_gym.evaluation.core import learned_options

    if args.quick:
        args.policies, args.clutter_levels = QUICK["policies"], QUICK["clutter_levels"]
        args.trials, args.particles = QUICK["seeds"], QUICK["particles"]
    if args.env is not None:
        apply_env_id(args)
    baselines = name_list(args.baselines) if args.baselines else []
    bad = [b for b in baselines if b not in BASELINE_SYSTEMS]
    if bad:
        raise ValueError(f"baselines={bad} is invalid: must be among {list(BASELINE_SYSTEMS)}")
    names = name_list(args.policies)
    unknown = [n for n in names if n not in policies.available()]
    if unknown:
        raise ValueError(f"policies={unknown} is invalid: must be among {policies.available()}")
    if "learned" in names:
        policies.make("learned", **({"path": args.model} if args.model else {}))  # fail early
    levels = int_list(args.clutter_levels)
    out = out_dir(args)
    options = {
        "n_particles": args.particles,
        "decision_interval": args.decision_interval,
        "front_end": args.front_end,
        "back_end": args.back_end,
    }
    jobs = []
    for name in names:
        opts = options | (learned_options(args.model) if name == "learned" else {})
        seeds = range(args.seed_start, args.seed_start + args.trials)
        jobs += [Job("policy", name, args.scenario, level, seed, opts)
                 for level in levels for seed in seeds]
    seeds = range(args.seed_start, args.seed_start + args.trials)
    jobs += [Job("system", name, args.scenario, level, seed, {})
             for name in baselines for level in levels for seed in seeds]
    rows = execute(args, jobs, out)
    doc = write_summary(out, rows)
    figures = {}
    if not args.no_figures:
        figures["success"] = str(plot_success_rates(doc, out / "success_rates.png",
                                                    title="Success rate per clutter level"))
        env_name = args.env or f"{args.front_end} front-end, {args.back_end} back-end"
        if any(g.get("map_error_m_succeeded") is not None for g in doc["groups"]):
            figures["pareto"] = str(plot_pareto(
                doc, out / "pareto.png",
                title=f"Map error against all compute ({env_name}, {args.particles} particles)",
            ))
            figures["pareto_interface"] = str(plot_pareto(
                doc, out / "pareto_interface.png", x="interface_cpu_s",
                title=f"Map error against the compute of fusions and optimisations "
                f"({env_name}, {args.particles} particles)",
            ))
        else:
            logger.warning("no policy succeeded in any world: no map error to plot against "
                           "compute (the Pareto figures are left out)")
        figures.update(episode_figures(names, args, levels[-1], out))
    print_table(args, doc, title=f"Policies on {args.scenario} ({args.particles} particles)")
    emit(args, {"summary": doc, "figures": figures, "out": str(out)},
         [f"wrote {out / 'results.jsonl'}, summary.json, table.md and {len(figures)} figures"])
    return 0


def apply_env_id(args) -> None:
    """Take the front-end and back-end of a registered simulated env id (``--env``)."""
    import slam_gym

    variants = slam_gym.ENV_VARIANTS
    if args.env not in variants:
        raise ValueError(f"env={args.env!r} is invalid: must be one of {sorted(variants)}")
    kwargs = variants[args.env]
    args.front_end = kwargs.get("front_end", "fastslam")
    args.back_end = kwargs.get("back_end", "ekf")


def episode_figures(names, args, level, out) -> dict:
    """Uncertainty and NEES traces of every policy on one seed, that seed's map, and when each
    policy fused and optimised against the loop closure."""
    from slam_gym.evaluation import plot_nees, plot_uncertainty_traces
    from slam_gym.evaluation.core import make_policy
    from slam_gym.evaluation.timeline import decision_timeline, plot_decision_timelines

    traces, nees, runs, timelines = {}, {}, [], {}
    for name in names:
        timeline, episode, env = decision_timeline(
            make_policy(name, model_path=args.model), args.scenario, level, args.seed_start,
            n_particles=args.particles, decision_interval=args.decision_interval,
            front_end=args.front_end, back_end=args.back_end,
        )
        traces[name] = np.array(episode.trace.cov_trace)
        nees[name] = np.array(episode.trace.nees)
        timelines[name] = timeline
        runs.append((name, episode, env))
    dt = runs[0][2].stream.dt_s
    figures = {
        "uncertainty": str(plot_uncertainty_traces(
            traces, out / "uncertainty_traces.png", dt_s=dt,
            title=f"Vehicle uncertainty, clutter level {level}, seed {args.seed_start}")),
        "nees": str(plot_nees(
            nees, out / "nees.png", dt_s=dt,
            title=f"Vehicle NEES, clutter level {level}, seed {args.seed_start}")),
    }
    figures["decisions"] = str(plot_decision_timelines(
        timelines, out / "decisions.png",
        title=f"Fusions and optimisations, clutter level {level}, seed {args.seed_start}"))
    name, episode, _ = runs[0]  # the map of the first policy named
    figures["map"] = plot_episode_map(
        episode, out / "map.png", f"{name}, clutter level {level}, seed {args.seed_start}"
    )
    return figures
