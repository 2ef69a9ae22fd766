"""``slam-gym benchmark``: interface policies compared in the env, in parallel and resumable."""

from __future__ import annotations

import logging

from slam_gym.commands.common import emit
from slam_gym.commands.envargs import add_env_options, policies_help
from slam_gym.commands.runs import (
    Given,
    add_run_options,
    check_run_options,
    errors_exit_code,
    given,
    name_list,
    print_table,
    run_options,
)

logger = logging.getLogger(__name__)

QUICK = {
    "policies": "fixed-10s,esdf-innovation,fixed-10s-optimise,learned",
    "seeds": 3,
}
"""What ``--quick`` sets: the policies and 3 worlds at each of the env's clutter levels (on the
default env, BB's four at BB's 500 particles: the README's main job)."""

DEFAULT_POLICIES = (
    "never,always,fixed-10s,fixed-10s-optimise,esdf-innovation,innovation-fusion,"
    "adaptive-diversity,imminent-closure"
)
"""The rules of the literature and the adaptive ones (issue 13): every default a reviewer asks."""

def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "benchmark",
        help="compare interface policies in the env",
        description="Run policies x clutter levels x seeds in an env (--env, default "
        "SlamGym/HybridSLAM-v1; a process pool or Ray), write results.jsonl (resumable), "
        "summary.json, table.md and plots. --quick is the README's main job.",
    )
    p.add_argument("--policies", default=DEFAULT_POLICIES, action=Given,
                   help=policies_help("comma-separated policy names"))
    p.add_argument("--baselines", default="dead-reckoning",
                   help="systems run on the same worlds beside the policies, comma-separated "
                   "(dead-reckoning; '' for none): dead reckoning meets BB's success "
                   "criterion without a map, which map completeness shows")
    add_env_options(p)
    p.add_argument("--model", default=None,
                   help="model zip for the learned policy (default: the model shipped for "
                   "--env, else the default model)")
    p.add_argument("--draws", type=int, default=1, metavar="K",
                   help="filter draws per world for every policy (default 1): the same world "
                   "run K times with other draws of the filter's random numbers, draw k the "
                   "same for every policy (common random numbers); rows carry their draw and "
                   "intervals are taken over worlds")
    p.add_argument("--quick", action="store_true",
                   help=f"the quick benchmark: {QUICK['seeds']} seeds at each of the env's "
                   "clutter levels, fixed-10s, esdf-innovation, fixed-10s-optimise, learned "
                   "(an explicit --seeds is kept; --policies cannot be combined with it)")
    p.add_argument("--no-figures", action="store_true",
                   help="write no figures (by default: success rates, two Pareto figures, and "
                   "the uncertainty, NEES, decisions and map of one world)")
    add_run_options(p, default_out="out/benchmark", trials_flag="--seeds")
    p.set_defaults(run=run)


def run(args) -> int:
    from slam_gym.commands.envargs import env_from_args
    from slam_gym.evaluation import benchmark

    if args.quick:
        apply_quick(args)
    check_run_options(args)
    env = env_from_args(args)
    result = benchmark(
        name_list(args.policies),
        env=env,
        seeds=args.trials,
        seed_start=args.seed_start,
        model=args.model,
        draws=args.draws,
        baselines=name_list(args.baselines) if args.baselines else [],
        out=args.out,
        figures=not args.no_figures,
        **run_options(args),
    )
    out, doc, figures = result.out, result.summary, result.figures
    print_table(args, doc, title=f"Policies in {env.describe()}")
    emit(args, {"summary": doc, "figures": figures, "out": str(out), "env_id": env.env_id,
                "env_kwargs": env.kwargs},
         [f"wrote {out / 'results.jsonl'}, summary.json, table.md and {len(figures)} figures"])
    return errors_exit_code(args, result.rows)


def apply_quick(args) -> None:
    """``--quick``: the README's main job. It sets the policies (refusing an explicit
    ``--policies``, which would make it another benchmark) and the seeds the user did not
    give."""
    if given(args, "policies"):
        raise ValueError("--quick is invalid with --policies: --quick sets them (the README's "
                         "main job); leave --quick out to choose them")
    args.policies = QUICK["policies"]
    if not given(args, "trials"):
        args.trials = QUICK["seeds"]
