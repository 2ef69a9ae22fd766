"""``slam-gym distil``: the distilled planner of a task (issue 58), DAgger from ``lookahead``.

Behaviour cloning of the task's best rule, then rounds of DAgger labelled by the planner on the
states the learner visits, each snapshot selected on training-time worlds
(:mod:`slam_gym.training.dagger`). Resumable: run the same command again to continue.
"""

from __future__ import annotations

import json
import shlex
import sys

EPILOG = """examples:
  slam-gym distil --env SlamGym/HybridSLAM-Zones-v1 --env-kwargs w_compute:10 compute_clip_s:0.2 \\
      --best-rule 'threshold-optimise[global_position_std_m>=2]' --seed 0 --out out/distil-zones-0
  slam-gym distil --reweigh out/distil-zones-0 --departure-weight 5 --out out/weighted-zones-0
  slam-gym compare 'threshold-optimise[global_position_std_m>=2]' \\
      learned:model_path=out/distil-zones-0/model.zip --env SlamGym/HybridSLAM-Zones-v1 ...
"""


def add_parser(subparsers) -> None:
    import argparse

    from slam_gym.commands.envargs import add_env_options
    from slam_gym.training.dagger import DistillSetup

    defaults = DistillSetup.__dataclass_fields__
    p = subparsers.add_parser(
        "distil", help="a task's distilled planner: DAgger from lookahead, started at a rule",
        description=(__doc__ or "").split("\n\n")[1].replace("\n", " "), epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--best-rule", default=None,
                   help="the task's best rule: cloned first, and the labels where the teacher "
                   "does not plan")
    p.add_argument("--teacher", default="lookahead", help="the planner (default lookahead)")
    p.add_argument("--seed", type=int, default=0, help="the run's seed (default 0)")
    for name, help_text in (
            ("frame_stack", "decisions the learner sees at once"),
            ("cloning_decisions", "decisions of the rule cloned in round 0"),
            ("rounds", "DAgger rounds after the cloning"),
            ("episodes_per_round", "episodes of each DAgger round"),
            ("max_episodes", "the learner's episodes in all rounds, at most"),
            ("max_planner_labels", "the planner's labels in all rounds, at most"),
            ("selection_workers", "processes for the selection runs")):
        p.add_argument("--" + name.replace("_", "-"), type=int, default=defaults[name].default,
                       help=f"{help_text} (default {defaults[name].default})")
    p.add_argument("--beta", type=float, default=0.5,
                   help="round i executes the teacher's label with probability beta**i "
                   "(default 0.5)")
    p.add_argument("--selection-seeds", type=int, default=10, metavar="N",
                   help="training-time worlds the snapshots are selected on (default 10)")
    p.add_argument("--selection-seed-start", type=int, default=900000, metavar="S",
                   help="the first of them (default 900000)")
    p.add_argument("--select-from", nargs="+", default=None, metavar="RUN",
                   help="run nothing: copy the best snapshot of these finished runs (the "
                   "seeds of a learner; selection success, ties return) to --out")
    p.add_argument("--reweigh", default=None, metavar="RUN",
                   help="run no planner: refit RUN's round-0 learner on RUN's DAgger labels with "
                   "the planner's departures from its base rule weighted --departure-weight "
                   "(the cost-weighted learner), select it, write it to --out")
    p.add_argument("--departure-weight", type=float, default=None, metavar="W",
                   help="with --reweigh: the weight of a departure (every other label 1)")
    p.add_argument("--out", required=True, help="the run's folder (resumable)")
    add_env_options(p, (), levels=False)
    p.set_defaults(run=run)


def run(args) -> int:
    from filters.validation import require
    from slam_gym.commands.envargs import env_shorthands
    from slam_gym.envs.spec import parse_env_kwargs
    from slam_gym.training.dagger import DistillSetup, distil, select_runs

    if args.reweigh:
        from slam_gym.training.dagger import reweigh

        require(args.departure_weight is not None, "departure_weight", None,
                "a positive number (with --reweigh)")
        config = reweigh(args.reweigh, args.departure_weight, args.out,
                         command=shlex.join(["slam-gym", *sys.argv[1:]]))
        print(json.dumps({"model": f"{args.out}/model.zip", "reweighted": config["reweighted"],
                          "selection": config["selection"]}, indent=2))
        return 0
    require(args.departure_weight is None, "departure_weight", args.departure_weight,
            "given only with --reweigh")
    if args.select_from:
        config = select_runs(args.select_from, args.out)
        print(json.dumps({"model": f"{args.out}/model.zip", "selected_from":
                          config["selected_from"], "selected_round": config["selected_round"],
                          "selection": config["selection"]}, indent=2))
        return 0
    require(args.best_rule is not None, "best_rule", None, "the task's best rule's name")
    require(args.env is not None, "env", None, "a registered env id (the task), e.g. "
            "SlamGym/HybridSLAM-Zones-v1")
    require(args.selection_seeds >= 1, "selection_seeds", args.selection_seeds,
            "a positive number of seeds")
    setup = DistillSetup(
        env_id=args.env, env_kwargs={**parse_env_kwargs(args.env_kwargs), **env_shorthands(args)},
        best_rule=args.best_rule, seed=args.seed, teacher=args.teacher,
        frame_stack=args.frame_stack, cloning_decisions=args.cloning_decisions,
        rounds=args.rounds, episodes_per_round=args.episodes_per_round, beta=args.beta,
        max_episodes=args.max_episodes, max_planner_labels=args.max_planner_labels,
        selection_seeds=tuple(range(args.selection_seed_start,
                                    args.selection_seed_start + args.selection_seeds)),
        selection_workers=args.selection_workers,
        command=shlex.join(["slam-gym", *sys.argv[1:]]))
    config = distil(setup, args.out)
    print(json.dumps({"model": f"{args.out}/model.zip", "selected_round": config["selected_round"],
                      "selection": config["selection"]}, indent=2))
    return 0
