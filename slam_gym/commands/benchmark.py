"""``slam-gym benchmark``: interface policies compared in the env, in parallel and resumable."""

from __future__ import annotations

import logging

from slam_gym.commands.common import emit
from slam_gym.commands.runs import (
    Given,
    add_run_options,
    check_run_options,
    errors_exit_code,
    given,
    int_list,
    name_list,
    print_table,
    run_options,
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

def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "benchmark",
        help="compare interface policies in the env",
        description="Run policies x clutter levels x seeds through SlamGym/HybridSLAM-v1 (a "
        "process pool or Ray), write results.jsonl (resumable), summary.json, table.md and "
        "plots. --quick is the README's main job.",
    )
    p.add_argument("--policies", default=DEFAULT_POLICIES, action=Given,
                   help="comma-separated policy names (policies.available(): the project's, "
                   "installed plug-ins' of entry-point group slam_gym.policies) or "
                   "package.module:attribute references to a policy class, factory or object")
    p.add_argument("--env", default=None, metavar="ID",
                   help="a registered simulated env id whose front-end and back-end to use "
                   "(e.g. SlamGym/HybridSLAM-Relative-v1); --front-end/--back-end otherwise")
    p.add_argument("--baselines", default="dead-reckoning",
                   help="systems run on the same worlds beside the policies, comma-separated "
                   "(dead-reckoning; '' for none): dead reckoning meets BB's success "
                   "criterion without a map, which map completeness shows")
    p.add_argument("--clutter-levels", default="0,1,2,3", action=Given, metavar="L,...",
                   help="comma-separated clutter levels 0-3, distinct (default 0,1,2,3)")
    p.add_argument("--scenario", default="brooks-bailey",
                   help="the worlds' scenario (slam_gym/scenarios.py; default brooks-bailey)")
    p.add_argument("--particles", type=int, default=500, action=Given, metavar="P",
                   help="FastSLAM particles of the front-end (default 500, BB's)")
    p.add_argument("--decision-interval", type=int, default=10, metavar="K",
                   help="simulation steps between decisions (default 10: one a second)")
    p.add_argument("--front-end", choices=["fastslam", "ekf"], default=None,
                   help="default fastslam (or --env's)")
    p.add_argument("--back-end", choices=["ekf", "relative"], default=None,
                   help="default ekf (or --env's)")
    p.add_argument("--n-steps", type=int, default=None, metavar="N",
                   help="cut every path to N simulation steps (quick looks, tests)")
    p.add_argument("--model", default=None, help="model zip for the learned policy")
    p.add_argument("--draws", type=int, default=1, metavar="K",
                   help="filter draws per world for every policy (default 1): the same world "
                   "run K times with other draws of the filter's random numbers, draw k the "
                   "same for every policy (common random numbers); rows carry their draw and "
                   "intervals are taken over worlds")
    p.add_argument("--quick", action="store_true",
                   help=f"the quick benchmark: {QUICK['seeds']} seeds, {QUICK['particles']} "
                   "particles, all clutter levels, fixed-10s, esdf-innovation, "
                   "fixed-10s-optimise, learned (an explicit --seeds or --particles is kept; "
                   "--policies and --clutter-levels cannot be combined with it)")
    p.add_argument("--no-figures", action="store_true",
                   help="write no figures (by default: success rates, two Pareto figures, and "
                   "the uncertainty, NEES, decisions and map of one world)")
    add_run_options(p, default_out="out/benchmark", trials_flag="--seeds")
    p.set_defaults(run=run)


def run(args) -> int:
    from slam_gym.evaluation import benchmark

    if args.quick:
        apply_quick(args)
    check_run_options(args)
    if args.draws < 1:
        raise ValueError(f"--draws {args.draws} is invalid: must be >= 1")
    result = benchmark(
        name_list(args.policies),
        clutter_levels=int_list(args.clutter_levels, "clutter_levels"),
        seeds=args.trials,
        seed_start=args.seed_start,
        scenario=args.scenario,
        env=args.env,
        n_particles=args.particles,
        decision_interval=args.decision_interval,
        front_end=args.front_end,
        back_end=args.back_end,
        n_steps=args.n_steps,
        model=args.model,
        draws=args.draws,
        baselines=name_list(args.baselines) if args.baselines else [],
        out=args.out,
        figures=not args.no_figures,
        **run_options(args),
    )
    out, doc, figures = result.out, result.summary, result.figures
    print_table(args, doc, title=f"Policies on {args.scenario} ({args.particles} particles)")
    emit(args, {"summary": doc, "figures": figures, "out": str(out)},
         [f"wrote {out / 'results.jsonl'}, summary.json, table.md and {len(figures)} figures"])
    return errors_exit_code(args, result.rows)


def apply_quick(args) -> None:
    """``--quick``: the README's main job. It sets the policies and clutter levels (refusing an
    explicit ``--policies`` or ``--clutter-levels``, which would make it another benchmark) and
    the seeds and particles the user did not give."""
    clash = [flag for flag, dest in (("--policies", "policies"),
                                     ("--clutter-levels", "clutter_levels")) if given(args, dest)]
    if clash:
        raise ValueError(f"--quick is invalid with {' and '.join(clash)}: --quick sets them "
                         "(the README's main job); leave --quick out to choose them")
    args.policies, args.clutter_levels = QUICK["policies"], QUICK["clutter_levels"]
    if not given(args, "trials"):
        args.trials = QUICK["seeds"]
    if not given(args, "particles"):
        args.particles = QUICK["particles"]
