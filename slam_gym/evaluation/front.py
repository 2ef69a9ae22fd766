"""A learned policy's front against the rules: paired comparisons and the goal of issue 29.

The rows are benchmark rows of policies on the same worlds (same scenario, clutter levels and
seeds). A rule's decisions do not depend on the price of compute, so each rule runs once and its
return at another price is recomputed (:func:`return_at_price`); a policy conditioned on the
price runs at every price. :func:`compare` pairs every policy with a reference rule world by
world; :func:`goal` applies the goal declared in docs/RESULTS.md (issue 29 item 5);
:func:`plot_front` draws success and map error against interface CPU.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from filters.validation import require
from slam_gym.evaluation.pairing import paired_worlds
from slam_gym.evaluation.summary import mean_interval, wilson_interval

GOAL_SUCCESS_LOWER_PP = -5.0
"""Goal 1: the pooled paired success difference's lower bound is at least this (points)."""
GOAL_CPU_RATIO = 1.0 / 3.0
"""Goal 3: interface CPU at most this fraction of the reference rule's."""


def return_at_price(row: Mapping[str, Any], price: float) -> float:
    """A run's return at ``price`` (per second) from its return at the price it ran at
    (``w_compute``) and the compute its return charged (``compute_term_s``), same clip."""
    return float(row["return"]) + (float(row["w_compute"]) - price) * float(row["compute_term_s"])


def interface_cpu_s(row: Mapping[str, Any]) -> float:
    return float(row["fusion_cpu_s"]) + float(row["optimise_cpu_s"])


def _world(row: Mapping[str, Any]) -> tuple[str, str, int]:
    """A run's world: scenario (an MRCLAM robot is one), clutter level and seed."""
    return str(row.get("scenario")), str(row["clutter_level"]), int(row["seed"])


def _by_world(rows: Sequence[Mapping[str, Any]], what: str) -> dict[tuple, Mapping]:
    bad = [r for r in rows if r.get("status") != "ok"]
    require(not bad, what, f"{len(bad)} failed runs", "runs that all finished (status ok)")
    out = {}
    for row in rows:
        require(_world(row) not in out, what, _world(row), "one run per world")
        out[_world(row)] = row
    return out


def _interval(values: Sequence[float]) -> list[float] | None:
    ci = mean_interval(list(values))
    return None if ci is None else [float(ci[0]), float(ci[1])]


def compare(rows: Sequence[Mapping[str, Any]], reference: Sequence[Mapping[str, Any]],
            price: float, *, return_reference: Sequence[Mapping[str, Any]] | None = None,
            ) -> dict[str, Any]:
    """One policy's runs against a reference rule's on the same worlds, at ``price``.

    Success (Wilson interval; the paired difference in points with its t interval over all
    worlds), map error of the runs that did not fail (the paired difference over the worlds
    where neither failed: :func:`slam_gym.evaluation.pairing.paired_worlds`, the pairing of
    ``slam-gym compare`` and the headroom report; ``n_map_pairs`` worlds on ``n_map_seeds``
    seeds), mean interface CPU and its ratio to the reference's, mean return at
    ``price`` and, against ``return_reference`` (default ``reference``), the paired difference.
    """
    mine, ref = _by_world(rows, "rows"), _by_world(reference, "reference")
    worlds = sorted(mine)
    require(set(worlds) == set(ref), "rows", len(worlds), "the reference's worlds")
    n = len(worlds)
    successes = sum(bool(mine[w]["success"]) for w in worlds)
    success_diff = [100.0 * (float(mine[w]["success"]) - float(ref[w]["success"]))
                    for w in worlds]
    # the one paired map error (slam_gym.evaluation.pairing): the worlds both survived
    pairs = paired_worlds(reference, rows, "map_error_m")
    map_diff = [float(v) for v in pairs.b - pairs.a]
    survived = [float(mine[w]["map_error_m"]) for w in worlds
                if mine[w]["success"] and mine[w].get("map_error_m") is not None]
    cpu = float(np.mean([interface_cpu_s(mine[w]) for w in worlds]))
    ref_cpu = float(np.mean([interface_cpu_s(ref[w]) for w in worlds]))
    ret = [return_at_price(mine[w], price) for w in worlds]
    other = _by_world(return_reference, "return_reference") if return_reference else ref
    ret_diff = [ret[i] - return_at_price(other[w], price) for i, w in enumerate(worlds)]
    return {
        "n_worlds": n,
        "success_rate": successes / n,
        "success_ci": list(wilson_interval(successes, n)),
        "success_diff_pp": float(np.mean(success_diff)),
        "success_diff_ci_pp": _interval(success_diff),
        "map_error_m": float(np.mean(survived)) if survived else math.nan,
        "map_error_diff_m": float(np.mean(map_diff)) if map_diff else math.nan,
        "map_error_diff_ci_m": _interval(map_diff),
        "n_map_pairs": len(pairs),
        "n_map_seeds": pairs.n_clusters,
        "interface_cpu_s": cpu,
        "interface_cpu_ratio": cpu / ref_cpu if ref_cpu > 0 else math.nan,
        "n_fusions": float(np.mean([mine[w]["n_fusions"] for w in worlds])),
        "n_optimisations": float(np.mean([mine[w]["n_optimisations"] for w in worlds])),
        "mean_return": float(np.mean(ret)),
        "return_diff": float(np.mean(ret_diff)),
        "return_diff_ci": _interval(ret_diff),
    }


def compare_all_runs(rows: Sequence[Mapping[str, Any]], reference: Sequence[Mapping[str, Any]],
                     metrics: Sequence[str] = ("map_error_m", "pose_rmse_m"),
                     ) -> dict[str, Any]:
    """One policy against a reference on the same runs (on real data: robot and seed), every run
    counted whether or not it met BB's failure rule: per metric the mean and the paired
    difference with its t 95 % interval; interface CPU (mean, paired difference, ratio of the
    means); fusions and optimisations."""
    mine, ref = _by_world(rows, "rows"), _by_world(reference, "reference")
    worlds = sorted(mine)
    require(set(worlds) == set(ref), "rows", len(worlds), "the reference's worlds")
    out: dict[str, Any] = {"n_runs": len(worlds),
                           "success_rate": float(np.mean([bool(mine[w]["success"])
                                                          for w in worlds]))}
    for metric in (*metrics, "interface_cpu_s"):
        def value(row, metric=metric):
            return interface_cpu_s(row) if metric == "interface_cpu_s" else float(row[metric])
        diff = [value(mine[w]) - value(ref[w]) for w in worlds]
        out[metric] = float(np.mean([value(mine[w]) for w in worlds]))
        out[f"{metric}_diff"] = float(np.mean(diff))
        out[f"{metric}_diff_ci"] = _interval(diff)
    ref_cpu = float(np.mean([interface_cpu_s(ref[w]) for w in worlds]))
    out["interface_cpu_ratio"] = out["interface_cpu_s"] / ref_cpu if ref_cpu > 0 else math.nan
    out["n_fusions"] = float(np.mean([mine[w]["n_fusions"] for w in worlds]))
    out["n_optimisations"] = float(np.mean([mine[w]["n_optimisations"] for w in worlds]))
    return out


def goal(against_rule: Mapping[str, Any]) -> dict[str, bool]:
    """The four parts of issue 29's goal from :func:`compare` of a learned policy against
    ``fixed-10s-optimise`` (``return_reference``: the best threshold rule at the price)."""
    s_ci, m_ci = against_rule["success_diff_ci_pp"], against_rule["map_error_diff_ci_m"]
    parts = {
        "success": s_ci is not None and s_ci[0] >= GOAL_SUCCESS_LOWER_PP,
        "map_error": m_ci is not None and m_ci[0] <= 0.0,
        "interface_cpu": against_rule["interface_cpu_ratio"] <= GOAL_CPU_RATIO,
        "return": against_rule["return_diff"] > 0.0,
    }
    parts["reached"] = all(parts.values())
    return parts


def plot_front(points: Sequence[Mapping[str, Any]], path: str | os.PathLike, *,
               title: str = "Success and map error against interface CPU") -> Path:
    """Two panels, success and map error of the runs that did not fail, against mean interface
    CPU (log scale); each point is a policy (``label``; learned ones as stars) with the 95 %
    interval of its paired difference to the reference rule drawn around it (none for the
    reference itself). A panel's CPU axis is linear when some policy spent no interface CPU or
    the panel has no point to draw."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter

    cpu = [p["interface_cpu_s"] for p in points if p["interface_cpu_s"] > 0]
    low, high = (min(cpu), max(cpu)) if cpu else (0.1, 10.0)
    ticks = [m * 10.0 ** e for e in range(-4, 5) for m in (1, 2, 5)
             if low / 1.5 <= m * 10.0 ** e <= high * 1.5]
    fig = Figure(figsize=(11, 4.4), dpi=120)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    for ax, key, diff, ci, ylabel, scale in (
        (axes[0], "success_rate", "success_diff_pp", "success_diff_ci_pp", "success (%)", 100.0),
        (axes[1], "map_error_m", "map_error_diff_m", "map_error_diff_ci_m",
         "map error of the runs that did not fail (m)", 1.0),
    ):
        for i, p in enumerate(points):
            x, y = p["interface_cpu_s"], scale * p[key]
            learned = p.get("learned", False)
            color = f"C{i % 10}"
            interval = p.get(ci)
            if interval is not None and np.isfinite(p[diff]) and np.isfinite(y):
                below, above = p[diff] - interval[0], interval[1] - p[diff]
                ax.errorbar([x], [y], yerr=[[below], [above]], fmt="none", ecolor=color,
                            alpha=0.6, capsize=3)
            ax.scatter([x], [y], s=60 if learned else 40, marker="*" if learned else "o",
                       color=color, label=p["label"], zorder=3)
        # a log axis needs a point to draw and every point above 0 s (a short path can end
        # before any fusion; every run failing leaves the map-error panel without a point)
        log_axis = len(cpu) == len(points) and any(np.isfinite(scale * p[key]) for p in points)
        if log_axis:
            ax.set_xscale("log")
            # plain labels at 1-2-5 steps: matplotlib's minor-tick labels overlap on a short
            # log axis
            ax.set_xticks(ticks, labels=[f"{v:g}" for v in ticks])
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("interface CPU per episode (s, fusions + optimisations"
                      + ("" if log_axis else "; linear: no point or one at 0 s") + ")")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
