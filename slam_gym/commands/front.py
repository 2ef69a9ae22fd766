"""``slam-gym front``: a learned policy at several prices of compute against the rules.

Runs, on the same worlds (``--seeds`` from ``--seed-start`` at each clutter level; by default
400-419, worlds no policy ran on before issue 29), the rules ``--rules`` once (at the price
``--run-price``: their decisions do not depend on it) and the learned model ``--model`` at every
price of ``--prices`` (a policy conditioned on the price acts on it). The threshold rules chosen
per price by ``slam-gym threshold-rule`` (``--threshold-rules OUT/chosen.json``) join the rules.

At each price, every policy is paired world by world with ``fixed-10s-optimise`` (success, map
error, interface CPU) and its return with the best threshold rule's; the learned policy gets the
verdict of issue 29's goal (:func:`slam_gym.evaluation.front.goal`). Writes ``OUT/front.json``,
``OUT/front.md`` (one table per price) and ``OUT/front.png`` (success and map error against
interface CPU), with the benchmark's rows under ``OUT/rules`` and ``OUT/learned-<price>``.

``--compare-model OTHER.zip`` runs a second learned model at every price too (rows under
``OUT/compared-<price>``; e.g. a feed-forward PPO beside a recurrent one): it joins the tables
and the figure, and per price the first model is paired with it world by world (success, map
error, interface CPU, return: ``by_price[p]["against_compared"]`` and a table in ``front.md``).

The run options are ``slam-gym benchmark``'s (``--workers``, ``--executor``, ``--retry-errors``,
``--run-timeout-s``, ...), checked before any run (exit 2). A policy with error rows is left out of
the comparisons (``by_price[p]["not_compared"]``; every policy when the reference has any), the
tables still print, and the command exits 3 unless ``--allow-errors`` is given.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from slam_gym.commands.common import emit, out_dir
from slam_gym.commands.envargs import add_env_options
from slam_gym.commands.runs import (
    add_run_options,
    check_run_options,
    errors_exit_code,
    float_list,
    name_list,
    run_options,
)

REFERENCE = "fixed-10s-optimise"
DEFAULT_RULES = "fixed-10s,fixed-10s-optimise,esdf-innovation"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "front", help="a learned policy at several prices of compute against the rules, paired")
    p.add_argument("--model", required=True, help="the learned model zip")
    p.add_argument("--compare-model", default=None,
                   help="a second learned model zip, run at every price and paired with --model")
    p.add_argument("--label", default="learned", help="the name of --model in tables and plot")
    p.add_argument("--compare-label", default="compared",
                   help="the name of --compare-model in tables and plot")
    p.add_argument("--prices", default="1,10,100", help="prices of compute (w_compute, /s)")
    p.add_argument("--run-price", type=float, default=10.0,
                   help="the price the rules run at (their returns at the others are recomputed)")
    p.add_argument("--compute-clip-s", type=float, default=0.2, metavar="S",
                   help="the reward's per-decision clip of compute (s; default 0.2)")
    p.add_argument("--rules", default=DEFAULT_RULES, help="rule names (must include "
                   f"{REFERENCE}, the reference)")
    p.add_argument("--threshold-rules", default=None,
                   help="chosen.json of `slam-gym threshold-rule` (the best rule per price)")
    add_env_options(p, ("scenario", "n_particles", "n_steps"))
    add_run_options(p, default_out="out/front", trials_flag="--seeds")
    p.set_defaults(seed_start=400)
    p.set_defaults(run=run)


def run(args) -> int:
    import policies
    from filters.validation import require
    from slam_gym.commands.envargs import env_from_args
    from slam_gym.commands.threshold_rule import read_chosen
    from slam_gym.evaluation import benchmark
    from slam_gym.evaluation.benchmarking import resolve_policies
    from slam_gym.evaluation.front import compare, goal, plot_front
    from slam_gym.evaluation.summary import group_provenance, provenance_footnote

    prices = float_list(args.prices, "prices")
    require(bool(prices) and all(p >= 0 for p in prices) and len(set(prices)) == len(prices),
            "prices", args.prices, "distinct comma-separated numbers >= 0 (at least one)")
    rule_names = name_list(args.rules)
    require(REFERENCE in rule_names, "rules", args.rules, f"a list including {REFERENCE}")
    check_run_options(args)
    env = env_from_args(args)
    chosen = read_chosen(args.threshold_rules, env, "threshold_rules")
    rules: dict[str, Any] = {name: policies.make(name) for name in rule_names}
    for c in chosen.values():
        if c["rule"] not in rules:  # its printed name is its name (ThresholdOptimise)
            rules[c["rule"]] = policies.make(c["rule"])
    model = str(Path(args.model).expanduser().resolve())
    other = (None if args.compare_model is None
             else str(Path(args.compare_model).expanduser().resolve()))
    for field, path in (("model", model), ("compare_model", other)):
        if path is not None:  # a missing or broken model fails before the rules run
            try:
                resolve_policies(["learned"], path)
            except FileNotFoundError as exc:
                raise ValueError(f"{field}={path!r} is invalid: {exc}") from exc
    out = out_dir(args)
    common = dict(seeds=args.trials, seed_start=args.seed_start, baselines=[], figures=False,
                  **run_options(args))

    def at_price(price: float):
        """The env at one price of compute (the clip ``--compute-clip-s``)."""
        return env.replace(w_compute=price, compute_clip_s=args.compute_clip_s)

    rule_rows = benchmark(rules, env=at_price(args.run_price), out=out / "rules", **common).rows
    by_rule = {name: [r for r in rule_rows if r["policy"] == name] for name in rules}

    def rows_at_every_price(model_path: str, prefix: str) -> dict[float, list]:
        return {price: benchmark(["learned"], model=model_path, env=at_price(price),
                                 out=out / f"{prefix}-{price:g}", **common).rows
                for price in prices}

    learned_rows = rows_at_every_price(model, "learned")
    compared_rows = {} if other is None else rows_at_every_price(other, "compared")

    reference = by_rule[REFERENCE]
    def provenance_of(rows_by_price) -> dict[str, Any]:
        return group_provenance([r for rows in rows_by_price.values() for r in rows
                                 if r.get("status") == "ok"])

    provenance, compared_provenance = provenance_of(learned_rows), provenance_of(compared_rows)
    stale = provenance.get("model_matches_code") is False
    compared_stale = compared_provenance.get("model_matches_code") is False
    doc: dict[str, Any] = {"model": model, "compared_model": other, "prices": prices,
                           "env_id": env.env_id, "env_kwargs": env.kwargs,
                           "seeds": args.trials,
                           "seed_start": args.seed_start, "compute_clip_s": args.compute_clip_s,
                           **provenance, "by_price": {}}
    if other is not None:
        doc["compared_provenance"] = compared_provenance
    lines = []
    points = []
    for price in prices:
        best = chosen.get(f"{price:g}", {}).get("rule")
        best_rows = by_rule.get(best) if best else None
        if best_rows is not None and not _finished(best_rows):
            best = best_rows = None  # no return differences against a rule with failed runs
        table = {}
        learned_name = f"{args.label} @ {price:g}/s"
        compared_name = f"{args.compare_label} @ {price:g}/s"
        runs = [*by_rule.items(), (learned_name, learned_rows[price])]
        if other is not None:
            runs.append((compared_name, compared_rows[price]))
        not_compared = []  # every policy when the reference itself has failed runs
        for name, rows in runs:
            if _finished(rows) and _finished(reference):
                table[name] = compare(rows, reference, price, return_reference=best_rows)
            else:
                not_compared.append(name)
        learned = table.get(learned_name)
        verdict = goal(learned) if best_rows is not None and learned is not None else None
        doc["by_price"][f"{price:g}"] = {"best_threshold_rule": best, "policies": table,
                                         "goal": verdict, "not_compared": not_compared}
        marked = {learned_name} if stale else set()
        marked |= {compared_name} if compared_stale else set()
        lines += [f"\n### Price {price:g} /s (return differences against {best or 'n/a'})\n",
                  _markdown(table, marked=marked), f"goal: {verdict}"]
        if not_compared:
            lines.append(f"not compared (some of their runs, or {REFERENCE}'s, are error rows): "
                         f"{', '.join(not_compared)}")
        if learned is not None:
            points.append({"label": learned_name, "learned": True, **learned})
        if learned is not None and compared_name in table:
            against = compare(learned_rows[price], compared_rows[price], price)
            doc["by_price"][f"{price:g}"]["against_compared"] = against
            lines += [f"\n{args.label} - {args.compare_label} @ {price:g}/s (paired, 95 %): "
                      "success "
                      f"{against['success_diff_pp']:+.0f} pp"
                      f"{_fmt_ci(against['success_diff_ci_pp'])}, map error "
                      f"{against['map_error_diff_m']:+.2f} m"
                      f"{_fmt_ci(against['map_error_diff_ci_m'], 2)}, interface CPU x "
                      f"{against['interface_cpu_ratio']:.2f}, return "
                      f"{against['return_diff']:+.0f}{_fmt_ci(against['return_diff_ci'])}"]
            points.append({"label": compared_name, "learned": True, **table[compared_name]})
    footnote = provenance_footnote([provenance, compared_provenance])
    lines += ["", footnote] if footnote else []
    ref_at = doc["by_price"][f"{prices[0]:g}"]["policies"]
    points = [{"label": name, **ref_at[name]} for name in rules if name in ref_at] + points
    written = ["front.json", "front.md"]
    if points:
        written.append(plot_front(points, out / "front.png", title=(
            f"Learned policy at prices {', '.join(f'{p:g}' for p in prices)} /s and the rules: "
            f"{args.trials} worlds per level from seed {args.seed_start} "
            f"(bars: paired 95 % interval against {REFERENCE})")).name)
    (out / "front.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    (out / "front.md").write_text("\n".join(lines).lstrip() + "\n")
    emit(args, doc, [*lines, f"wrote {out}/{', '.join(written)}"])
    every_row = [*rule_rows, *(r for rows in (*learned_rows.values(), *compared_rows.values())
                               for r in rows)]
    return errors_exit_code(args, every_row, where=f"{out}/*/results.jsonl")


def _finished(rows) -> bool:
    """Whether every run of a policy finished (no error row): only such runs are paired."""
    return all(r.get("status") == "ok" for r in rows)


def _fmt_ci(ci, digits=0) -> str:
    return "" if ci is None else f" [{ci[0]:+.{digits}f}, {ci[1]:+.{digits}f}]"


def _markdown(table: dict[str, dict[str, Any]], marked=()) -> str:
    """The table of one price; the names in ``marked`` (a model that does not match the code)
    get :data:`~slam_gym.evaluation.summary.MISMATCH_MARK`."""
    from slam_gym.evaluation.summary import MISMATCH_MARK

    head = ["policy", "success", f"vs {REFERENCE} (pp)", "map error (m)", "paired diff (m)",
            "interface CPU (s)", "CPU ratio", "optimisations", "return", "return diff"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in table.items():
        lines.append("| " + " | ".join([
            f"{name} {MISMATCH_MARK}" if name in marked else name, f"{r['success_rate']:.0%}",
            f"{r['success_diff_pp']:+.0f}{_fmt_ci(r['success_diff_ci_pp'])}",
            f"{r['map_error_m']:.2f}",
            f"{r['map_error_diff_m']:+.2f}{_fmt_ci(r['map_error_diff_ci_m'], 2)}",
            f"{r['interface_cpu_s']:.2f}", f"{r['interface_cpu_ratio']:.2f}",
            f"{r['n_optimisations']:.1f}", f"{r['mean_return']:.0f}",
            f"{r['return_diff']:+.0f}{_fmt_ci(r['return_diff_ci'])}",
        ]) + " |")
    return "\n".join(lines)
