"""``slam-gym compare A B``: is B better than, not worse than, or worse than A? Paired by world
on common random numbers, with a sequential test (:mod:`slam_gym.evaluation.compare`)."""

from __future__ import annotations

import json

from slam_gym.commands.common import emit, to_jsonable
from slam_gym.commands.envargs import add_env_options, env_from_args, policies_help
from slam_gym.commands.runs import (
    add_run_options,
    check_run_options,
    errors_exit_code,
    run_options,
)

EPILOG = """examples:
  slam-gym compare fixed-10s-optimise fixed-10s --metric success --margin 5 --max-worlds 96
  slam-gym compare fixed-10s-optimise my_rules:Rule --metric map_error_m --margin 0.15 \\
      --max-worlds 200 --seed-start 5000
  slam-gym compare fixed-10s-optimise out/train/model.zip --seeds 10        (fixed design)
  slam-gym compare fixed-10s-optimise fixed-10s --metric success --margin 5 --plan
"""


def add_parser(subparsers) -> None:
    import argparse

    p = subparsers.add_parser(
        "compare",
        help="a paired, sequential comparison of two policies",
        description="Run policies A and B on the same worlds and filter draws (common random "
        "numbers) and compare them world by world: success, the fraction of pose NEES inside "
        "its 95 %% band, ANEES, map error (over the draws both survived), interface CPU and "
        "return, each with a paired interval at level 1 - --alpha, the seed the independent "
        "unit (its clutter levels and draws nested in it; the report names each interval's "
        "method, the seeds, the intraclass correlation and the effective worlds). With --metric "
        "and --margin it answers whether B is better, not worse (by more than the margin) or "
        "worse than A; with --max-worlds it runs worlds in batches until that is decided, "
        "under an anytime-valid confidence sequence.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("a", metavar="A", help=policies_help(
                   "the reference policy: a learned model's .zip, or a name")
                   .replace("%", "%%"))
    p.add_argument("b", metavar="B", help="the policy compared with A (same forms)")
    p.add_argument("--metric", default=None,
                   choices=["success", "nees_in_band_fraction", "map_error_m", "interface_cpu_s",
                            "return"],
                   help="the metric of the question (needs --margin or asks superiority)")
    p.add_argument("--margin", type=float, default=None,
                   help="non-inferiority margin in the metric's unit: percentage points for "
                   "success and nees_in_band_fraction, metres for map_error_m, seconds for "
                   "interface_cpu_s (0: superiority either way)")
    p.add_argument("--max-worlds", type=int, default=None, metavar="N",
                   help="sequential design: batches of worlds until decided or N worlds")
    p.add_argument("--design", default="confidence-sequence",
                   choices=["confidence-sequence", "group-sequential"],
                   help="the sequential design's interval: an anytime-valid confidence sequence "
                   "(default; any stopping, --max-worlds may be raised later) or an "
                   "O'Brien-Fleming-type group-sequential design planned for --max-worlds "
                   "(narrower near its end; --max-worlds fixed in advance)")
    p.add_argument("--batch-seeds", type=int, default=2, metavar="S",
                   help="seeds per batch of the sequential design, each at every clutter level "
                   "(default 2: 8 worlds a batch over levels 0-3)")
    p.add_argument("--seeds", dest="trials", type=int, default=None, metavar="N",
                   help="fixed design: N seeds at every clutter level (default 10; the pilot "
                   "of --plan: default one batch)")
    p.add_argument("--seed-start", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--draws", type=int, default=2, metavar="K",
                   help="filter draws per world for both policies (default 2)")
    p.add_argument("--alpha", type=float, default=0.05,
                   help="error rate of the intervals and the decision (default 0.05)")
    p.add_argument("--plan", action="store_true",
                   help="run a pilot (--seeds, default one batch) and print the worlds needed "
                   "to decide --metric at --margin with 80 %% power, sequential and fixed "
                   "(the seed the unit: planned in seeds, each at every clutter level)")
    add_env_options(p)
    add_run_options(p, default_out="out/compare", trials_flag=None)
    p.set_defaults(run=run)


def _num(value, digits=2, signed=False) -> str:
    if value is None:
        return "-"
    return f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"


def _level(level) -> str:
    return f"{100 * level:g} %"


def text_report(result) -> list[str]:
    """The human summary: one line per metric (its interval's method, seeds, intraclass
    correlation and effective worlds; whether it holds at a sequential stop) and the answer."""
    level = getattr(result, "level", 0.95)
    seeds = getattr(result, "seeds", None)
    sequential = result.question is not None and result.question["design"] != "fixed"
    kind = ("intervals valid at the sequential stop" if sequential
            else "fixed-sample intervals")
    lines = [f"{result.b} against {result.a} in {result.env_id}: {result.worlds} worlds"
             + (f" ({seeds} seeds)" if seeds else "") + f" x {result.draws} draws "
             f"(paired by world, the seed the unit; {_level(level)} {kind} of B - A)"]
    width = max(len(m) for m in result.metrics)
    for name, m in result.metrics.items():
        unit = f" {m['unit']}" if m["unit"] else ""
        ci = "-" if m["ci"] is None else f"[{m['ci'][0]:+.2f}, {m['ci'][1]:+.2f}]"
        left = f", {m['left_out']} worlds left out" if m["left_out"] else ""
        over = " (draws both survived)" if m.get("paired_over") else ""
        labels = ""
        if m.get("method"):
            icc = "-" if m.get("icc") is None else f"{m['icc']:.2f}"
            eff = m.get("effective_worlds")
            labels = (f"; {m['method']}, {m['worlds']} worlds / {m['seeds']} seeds, ICC {icc}"
                      + ("" if eff is None else f", effective worlds {eff:.0f}")
                      + (", anytime-valid" if m.get("anytime_valid") else ""))
        lines.append(f"  {name:<{width}}  A {_num(m['a'])}  B {_num(m['b'])}  "
                     f"B - A {_num(m['difference'], signed=True)}{unit} {ci}{over}{left}"
                     f"{labels}")
    q = result.question
    if q is not None:
        ci = q["oriented_ci"]
        better = "higher" if q["higher_is_better"] else "lower"
        where = ("" if ci is None else f"; {_level(level)} interval of the gain ({better} is "
                 f"better) [{ci[0]:+.2f}, {ci[1]:+.2f}] {q['unit']}"
                 + (f", {q['method']}" if q.get("method") else ""))
        design = (f"{q['design']}, stopped at {result.worlds} of at most {q['max_worlds']} "
                  "worlds" if q["design"] != "fixed" else "fixed design")
        lines.append(f"question: is {result.b} not worse than {result.a} by {q['margin']:g} "
                     f"{q['unit']} on {q['metric']}? {result.decision} ({design}{where})")
    return lines


def run(args) -> int:
    from slam_gym.evaluation.compare import compare, plan

    check_run_options(args)
    if args.plan and (args.metric is None or args.max_worlds is not None):
        raise ValueError("--plan is invalid without --metric or with --max-worlds: it plans "
                         "the worlds of a question from a pilot")
    env = env_from_args(args)
    common = dict(env=env, draws=args.draws, seed_start=args.seed_start, alpha=args.alpha,
                  out=args.out, **run_options(args))
    if args.plan:
        pilot_seeds = args.trials or max(args.batch_seeds, 2)
        result = compare(args.a, args.b, seeds=pilot_seeds, **common)
        half = len(result.rows) // 2
        rows_a, rows_b = result.rows[:half], result.rows[half:]
        levels = len(env.levels)
        planned = plan(rows_a, rows_b, args.metric, args.margin or 0.0, alpha=args.alpha,
                       batch_worlds=args.batch_seeds * levels)
        emit(args, {"plan": planned, "pilot": result.as_dict()},
             text_report(result) + [
                 f"plan for {args.metric} at margin {args.margin or 0:g}: "
                 f"{planned['sequential']['worlds']} worlds sequential (--max-worlds), "
                 f"{planned['fixed']['worlds']} fixed ({planned['sequential']['seeds']} and "
                 f"{planned['fixed']['seeds']} seeds at every clutter level), for 80 % power if "
                 f"the true difference is 0 (pilot: {planned['pilot_worlds']} worlds on "
                 f"{planned['pilot_seeds']} seeds, per-seed SD "
                 f"{planned['sequential']['sd']:.3g})"])
        return errors_exit_code(args, result.rows)
    result = compare(args.a, args.b, metric=args.metric, margin=args.margin,
                     seeds=args.trials, max_worlds=args.max_worlds, design=args.design,
                     batch_seeds=args.batch_seeds, **common)
    doc = to_jsonable(result.as_dict())
    (result.out / "compare.json").write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    lines = text_report(result)
    (result.out / "compare.md").write_text("\n".join(lines) + "\n")
    emit(args, doc, lines + [f"wrote {result.out / 'compare.json'} and compare.md"])
    return errors_exit_code(args, result.rows)
