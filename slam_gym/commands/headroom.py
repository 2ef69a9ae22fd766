"""``slam-gym headroom``: the headroom of a task (issue 48; a command since issue 55).

The best rule, the lookahead and its privileged bound on the task's worlds, each paired world by
world with the best rule by the one pairing of ``slam-gym compare`` (:mod:`slam_gym.evaluation.
headroom` holds the report; :mod:`slam_gym.evaluation.pairing` the pairing), and the
normalised headroom ``(lookahead - best) / (bound - best)``. The runs go through the benchmark
(resumable); ``--report-only`` recomputes the report from the rows, ``--table`` prints the
headroom table of README and RESULTS from several reports.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from slam_gym.commands.common import emit
from slam_gym.commands.runs import add_run_options, check_run_options, errors_exit_code, run_options

logger = logging.getLogger(__name__)

EPILOG = """examples:
  slam-gym headroom --env SlamGym/HybridSLAM-Zones-v1 --seeds 10 --seed-start 4800 \\
      --threshold-rule out/tr48-zones/chosen.json --policies lookahead,lookahead-privileged \\
      --out out/headroom-zones
  slam-gym headroom --table docs/results/issue48/zones_40_worlds_lookahead.json
"""


def add_parser(subparsers) -> None:
    import argparse

    from slam_gym.commands.envargs import add_env_options, policies_help
    from slam_gym.evaluation.headroom import BOUND, RULES

    p = subparsers.add_parser(
        "headroom", help="a task's headroom: the best rule, the lookahead and its bound, paired",
        description=(__doc__ or "").split("\n\n")[1].replace("\n", " "), epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", dest="trials", type=int, default=10, metavar="N",
                   help="seeds (each at every clutter level; default 10)")
    p.add_argument("--seed-start", type=int, default=4800, metavar="S",
                   help="the first seed (default 4800, issue 48's reported worlds)")
    p.add_argument("--draws", type=int, default=1, metavar="K", help="filter draws per world")
    p.add_argument("--price", type=float, default=10.0,
                   help="the price of compute the runs are scored at (w_compute, /s)")
    p.add_argument("--compute-clip-s", dest="env_compute_clip_s", type=float, default=0.2,
                   help="the reward's compute clip (s; default 0.2, issue 48's)")
    p.add_argument("--policies", default=",".join((*RULES, BOUND)),
                   help=policies_help("comma-separated policy names"))
    p.add_argument("--threshold-rule", default=None, metavar="CHOSEN_JSON",
                   help="chosen.json of slam-gym threshold-rule in the same env: its rule at "
                   "--price joins the policies and is the best rule")
    p.add_argument("--best-rule", default=None,
                   help="the best rule's name (else --threshold-rule's choice, else "
                   "fixed-10s-optimise)")
    p.add_argument("--report-only", action="store_true",
                   help="recompute the report from --out's rows; run nothing")
    p.add_argument("--rows", action="append", default=[], metavar="DIR",
                   help="also report the rows of DIR/results.jsonl (repeatable)")
    p.add_argument("--rename-rows", action="append", default=[], metavar="OLD=NEW",
                   help="report the --rows folders' policy OLD as NEW (repeatable), e.g. "
                   "lookahead=lookahead-full for issue 48's rows of the full planner")
    p.add_argument("--common-worlds", action="store_true",
                   help="report every policy on the worlds all policies finished")
    p.add_argument("--table", action="extend", nargs="+", default=[], metavar="HEADROOM_JSON",
                   help="print the headroom table of these reports' headroom.json, nothing else")
    add_env_options(p, ("scenario", "n_particles", "n_steps"))
    add_run_options(p, default_out="out/headroom", trials_flag=None)
    p.set_defaults(run=run)


def run(args) -> int:
    import policies
    from filters.validation import require
    from slam_gym.commands.envargs import env_from_args
    from slam_gym.commands.threshold_rule import read_chosen
    from slam_gym.evaluation import benchmark
    from slam_gym.evaluation.headroom import (
        common_worlds,
        headroom_table,
        join_rows,
        markdown,
        rename_policies,
        summarise,
    )
    from slam_gym.evaluation.results import read_results

    if args.table:
        try:
            docs = [json.loads(Path(f).read_text()) for f in args.table]
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"table={args.table!r} is invalid: {exc}") from exc
        print(headroom_table(docs), end="")
        return 0
    check_run_options(args)
    require(args.env is not None, "env", None, "a registered env id (the task), e.g. "
            "SlamGym/HybridSLAM-Zones-v1")
    require(args.trials >= 2, "trials", args.trials, "a number of seeds >= 2")
    renames = dict(r.split("=", 1) for r in args.rename_rows if "=" in r)
    require(len(renames) == len(args.rename_rows), "rename_rows", args.rename_rows,
            "OLD=NEW pairs")
    env = env_from_args(args).replace(w_compute=args.price)
    names = [n.strip() for n in args.policies.split(",") if n.strip()]
    specs: dict = {n: policies.make(n, **({"env_id": env.env_id} if n == "learned" else {}))
                   for n in names}  # learned: the model shipped for the task
    best = args.best_rule or "fixed-10s-optimise"
    chosen = read_chosen(args.threshold_rule, env).get(f"{args.price:g}")
    if args.threshold_rule and chosen is None:
        raise ValueError(f"threshold_rule={args.threshold_rule!r} is invalid: it chose no rule "
                         f"at price {args.price:g}")
    if chosen is not None:  # its printed name is its name (ThresholdOptimise.format_name)
        specs.setdefault(chosen["rule"], policies.make(chosen["rule"]))
        best = args.best_rule or chosen["rule"]
        renames.setdefault("best-threshold", chosen["rule"])  # issue 48's rows' name for it
    if args.best_rule:
        policies.make(args.best_rule)  # a name that cannot be typed back fails here
    for folder in args.rows:
        require((Path(folder) / "results.jsonl").is_file(), "rows", folder,
                "folders with a results.jsonl")
    out = Path(args.out)
    if args.report_only:
        rows = read_results(out)
    else:
        rows = benchmark(specs, env=env, seeds=args.trials, seed_start=args.seed_start,
                         draws=args.draws, baselines=[], out=out, figures=False,
                         **run_options(args)).rows
    # --rename-rows is for the --rows folders (the help's word); --out's rows keep their names
    # but issue 48's name of the chosen rule
    own = {k: v for k, v in renames.items() if k == "best-threshold"}
    rows = join_rows(rename_policies(rows, own),
                     *(rename_policies(read_results(folder), renames) for folder in args.rows))
    if args.common_worlds:
        rows = common_worlds(rows)
    require(bool(rows), "out", str(out), "a folder with rows to report (or give --rows)")
    require(any(r.get("policy") == best for r in rows), "best_rule", best,
            "a policy with rows here")
    out.mkdir(parents=True, exist_ok=True)
    doc = summarise([r for r in rows if r.get("status") == "ok"], best, args.price) | {
        "task": env.env_id, "env_kwargs": env.kwargs, "seeds": args.trials,
        "seed_start": args.seed_start, "draws": args.draws,
        "clutter_levels": list(env.levels),
        "worlds": len({(r["clutter_level"], r["seed"]) for r in rows}),
        "common_worlds": args.common_worlds, "best_rule_label": best}
    (out / "headroom.json").write_text(json.dumps(doc, indent=2) + "\n")
    text = markdown(doc)
    (out / "headroom.md").write_text(text)
    emit(args, doc, [text.rstrip(), f"wrote {out / 'headroom.json'} and headroom.md"])
    return errors_exit_code(args, rows)
