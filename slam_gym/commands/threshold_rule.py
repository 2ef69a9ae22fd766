"""``slam-gym threshold-rule``: choose the best threshold rule for the optimise decision.

The family (issue 29 item 3, :class:`policies.heuristics.ThresholdOptimise`): BB's fusion every
10 s and, at a fusion, the optimiser when one feature reaches a threshold; its two ends are
``fixed-10s`` (never optimise) and ``fixed-10s-optimise`` (at every fusion). Every rule of the
grid runs once on the training-time worlds (by default the training evaluation worlds
900000-900004 at each clutter level: never the reported worlds) at the price ``--run-price``; a
rule's decisions do not depend on the price, so its return at every price of ``--prices`` is
recomputed from the compute its return charged (``compute_term_s``,
:class:`slam_gym.envs.hybrid_slam.HybridSLAMEnv`). The rule with the highest mean return at each
price is chosen.

Writes ``OUT/results.jsonl`` (the benchmark's rows, resumable), ``OUT/candidates.md`` (every rule's
mean return per price, success, map error, optimisations, interface CPU) and ``OUT/chosen.json``
(per price: the chosen rule's feature, threshold and mean return).

The run options are ``slam-gym benchmark``'s (``--workers``, ``--executor``, ``--retry-errors``,
``--run-timeout-s``, ...), checked before any run (exit 2). A rule with error rows is neither
scored nor chosen (``chosen.json``'s ``not_scored``; no rule is chosen at a price when none
finished all its runs), and the command exits 3 unless ``--allow-errors`` is given.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slam_gym.commands.common import emit, out_dir
from slam_gym.commands.envargs import add_env_options
from slam_gym.commands.runs import (
    add_run_options,
    check_run_options,
    errors_exit_code,
    float_list,
    int_list,
    run_options,
)
from slam_gym.evaluation.front import interface_cpu_s, return_at_price

DEFAULT_GRID: Mapping[str, tuple[float, ...]] = {
    "global_heading_std_rad": (0.005, 0.01, 0.02, 0.04),
    "time_since_optimise_s": (20.0, 40.0, 80.0, 160.0),
    "global_position_std_m": (0.5, 1.0, 2.0, 4.0),
}
"""The grid declared in docs/RESULTS.md (issue 29) before any run."""

DEFAULT_PRICES = "1,10,100"


def add_parser(subparsers) -> None:
    from slam_gym.training.evaluation import DEFAULT_EVAL_SEEDS

    p = subparsers.add_parser(
        "threshold-rule",
        help="choose the best threshold rule for the optimise decision on training-time worlds")
    p.add_argument("--prices", default=DEFAULT_PRICES,
                   help="prices of compute (w_compute, per second) to choose a rule at")
    p.add_argument("--run-price", type=float, default=10.0,
                   help="the price the runs are scored at (the others are recomputed)")
    p.add_argument("--compute-clip-s", type=float, default=0.2,
                   help="the reward's per-decision clip of compute (s)")
    p.add_argument("--seeds", default=",".join(str(s) for s in DEFAULT_EVAL_SEEDS),
                   help="worlds per level (default: the training-time evaluation worlds)")
    add_env_options(p, ("scenario", "n_particles", "n_steps"))
    add_run_options(p, default_out="out/threshold-rule", trials_flag=None)
    p.set_defaults(run=run)


def candidates(grid: Mapping[str, Sequence[float]] = DEFAULT_GRID) -> dict[str, Any]:
    """Rule name -> policy object: the grid's rules and the family's two ends."""
    import policies

    rules: dict[str, Any] = {"fixed-10s": policies.make("fixed-10s"),
                             "fixed-10s-optimise": policies.make("fixed-10s-optimise")}
    for feature, thresholds in grid.items():
        for threshold in thresholds:
            rules[rule_name(feature, threshold)] = policies.make(
                "threshold-optimise", feature=feature, threshold=float(threshold))
    return rules


def rule_name(feature: str, threshold: float) -> str:
    """The rule's name as every command accepts it back
    (:meth:`policies.heuristics.ThresholdOptimise.format_name`)."""
    from policies.heuristics import ThresholdOptimise

    return ThresholdOptimise.format_name(feature, threshold)


def score(rows: Sequence[Mapping[str, Any]], prices: Sequence[float]) -> list[dict[str, Any]]:
    """Per rule whose runs all finished (a rule with error rows is left out, see
    :func:`not_scored`): mean return at every price and the benchmark's other means."""
    by_rule: dict[str, list[Mapping[str, Any]]] = {}
    for row in rows:
        by_rule.setdefault(row["policy"], []).append(row)
    table = []
    for name, group in by_rule.items():
        if any(r.get("status") != "ok" for r in group):
            continue
        survived = [r["map_error_m"] for r in group
                    if r["success"] and r.get("map_error_m") is not None]
        table.append({
            "rule": name,
            "n_episodes": len(group),
            **{f"mean_return_at_{p:g}": float(np.mean([return_at_price(r, p) for r in group]))
               for p in prices},
            "success_rate": float(np.mean([r["success"] for r in group])),
            "map_error_m": float(np.mean(survived)) if survived else math.nan,
            "n_optimisations": float(np.mean([r["n_optimisations"] for r in group])),
            "interface_cpu_s": float(np.mean([interface_cpu_s(r) for r in group])),
        })
    return table


def not_scored(rows: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """Rule -> its number of error rows, for the rules :func:`score` leaves out."""
    failed: dict[str, int] = {}
    for row in rows:
        if row.get("status") != "ok":
            failed[row["policy"]] = failed.get(row["policy"], 0) + 1
    return failed


def choose(table: Sequence[Mapping[str, Any]], prices: Sequence[float],
           rules: Mapping[str, Any]) -> dict[str, Any]:
    """Per price, the rule with the highest mean return (ties: the first in grid order); none
    from an empty table."""
    order = list(rules)
    chosen: dict[str, Any] = {}
    for p in prices if table else ():
        key = f"mean_return_at_{p:g}"
        best = max(table, key=lambda r: (r[key], -order.index(r["rule"])))
        options = getattr(rules[best["rule"]], "options", {})
        chosen[f"{p:g}"] = {"rule": best["rule"], "mean_return": best[key],
                            "feature": options.get("feature"),
                            "threshold": options.get("threshold")}
    return chosen


def markdown(table: Sequence[Mapping[str, Any]], prices: Sequence[float]) -> str:
    head = ["rule", *[f"return at {p:g} /s" for p in prices], "success", "map error (m)",
            "optimisations", "interface CPU (s)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table:
        cells = [r["rule"], *[f"{r[f'mean_return_at_{p:g}']:.0f}" for p in prices],
                 f"{r['success_rate']:.0%}", f"{r['map_error_m']:.2f}",
                 f"{r['n_optimisations']:.1f}", f"{r['interface_cpu_s']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(args) -> int:
    from filters.validation import require
    from slam_gym.commands.envargs import env_from_args
    from slam_gym.envs.wrappers import TRAINING_WORLD_SEED_OFFSET
    from slam_gym.evaluation import benchmark

    prices = float_list(args.prices, "prices")
    require(bool(prices) and all(p >= 0 for p in prices), "prices", args.prices,
            "comma-separated non-negative numbers")
    seeds = int_list(args.seeds, "seeds")
    require(bool(seeds) and all(0 <= s < TRAINING_WORLD_SEED_OFFSET for s in seeds), "seeds",
            args.seeds, f"seeds in [0, {TRAINING_WORLD_SEED_OFFSET})")
    check_run_options(args)
    env = env_from_args(args)
    env = env.replace(w_compute=args.run_price, compute_clip_s=args.compute_clip_s)
    out = out_dir(args)
    rules = candidates()
    levels = list(env.levels)
    result = benchmark(rules, env=env, seeds=seeds, baselines=[], figures=False, out=out,
                       **run_options(args))
    table = score(result.rows, prices)
    failed = not_scored(result.rows)
    table.sort(key=lambda r: list(rules).index(r["rule"]))
    chosen = choose(table, prices, rules)
    (Path(out) / "candidates.md").write_text(markdown(table, prices))
    doc = {"env_id": env.env_id, "env_kwargs": env.kwargs, "scenario": env.scenario,
           "particles": env.get("n_particles"),
           "prices": prices, "run_price": args.run_price, "compute_clip_s": args.compute_clip_s,
           "seeds": seeds, "clutter_levels": levels, "chosen": chosen,
           "candidates": table, "not_scored": failed}
    (Path(out) / "chosen.json").write_text(json.dumps(doc, indent=2) + "\n")
    emit(args, doc, [markdown(table, prices).rstrip(),
                     *[f"price {p}: {c['rule']} (mean return {c['mean_return']:.0f})"
                       for p, c in chosen.items()],
                     *([f"not scored (rules with error rows): "
                        f"{', '.join(f'{r} ({n})' for r, n in failed.items())}"]
                       if failed else []),
                     f"wrote {out}/candidates.md, chosen.json"])
    return errors_exit_code(args, result.rows)


def read_chosen(path: str | None, env, field: str = "threshold_rule"
                ) -> dict[str, dict[str, Any]]:
    """Price -> the chosen threshold rule's name and options (from ``chosen.json``), chosen in
    ``env`` (a :class:`~slam_gym.envs.spec.ResolvedEnv`): a file of another env is refused,
    since its rule was chosen on other worlds (``ValueError`` naming both)."""
    if path is None:
        return {}
    doc = json.loads(Path(path).read_text())
    chose_in = chosen_env(doc)
    mine = {"env_id": env.env_id, "scenario": env.scenario, "n_particles": env.get("n_particles")}
    differ = {k: (v, mine[k]) for k, v in chose_in.items() if v is not None and v != mine[k]}
    if differ:
        raise ValueError(
            f"{field}={path!r} is invalid: its rules were chosen in another env ("
            + ", ".join(f"{k} {a!r} there, {b!r} here" for k, (a, b) in differ.items())
            + f"): run in that env (--env {chose_in.get('env_id') or '...'}) or choose "
            "the rules in this one (slam-gym threshold-rule --env ...)")
    return {price: c for price, c in doc["chosen"].items()}


def chosen_env(doc: Mapping[str, Any]) -> dict[str, Any]:
    """What env a ``chosen.json`` was made in: its ``env_id``, scenario and particles (files
    before issue 55 name only ``scenario`` and ``particles``)."""
    kwargs = doc.get("env_kwargs") or {}
    return {"env_id": doc.get("env_id"),
            "scenario": kwargs.get("scenario", doc.get("scenario")),
            "n_particles": kwargs.get("n_particles", doc.get("particles"))}
