"""Aggregate ``results.jsonl`` rows into ``summary.json``, ``table.md`` and a console table.

One summary group per (system or policy, scenario, clutter level, options) — for one scenario and
fixed options this is the "per group" of docs/ARCHITECTURE.md, "The command line and its output
files". Each group has
``n`` (all recorded runs), ``n_ok``, ``n_errors`` (runs whose ``status`` is ``"error"``),
``n_success``, ``success_rate`` = successes / ``n_ok`` with its 95 % interval ``success_ci95`` =
[lo, hi], Wilson's score interval at the runs' effective number
(:func:`clustered_wilson_interval`, named in ``success_ci95_method``: the draws of one world are
a cluster, Kish's design effect from their intraclass correlation; with one draw a world it is
Wilson's interval itself), and
means over the ok runs of ``anees``, ``nees_in_band_fraction``,
``n_fusions``, ``n_optimisations``, ``wall_time_s``, plus mean and median of ``map_error_m`` and
``final_pose_error_m``. Where the rows carry them (benchmark rows), also the means with a 95 %
interval (``ci95``: mean +- t_{0.975, n-1} s / sqrt(n)) of ``map_error_m``, ``anees``,
``map_completeness``, ``return`` and the CPU seconds ``filter_cpu_s``, ``fusion_cpu_s``,
``optimise_cpu_s``, ``interface_cpu_s`` (fusions + optimisations), ``total_cpu_s``, the map
error of the successful runs (``map_error_m_succeeded``), and the mean return of the failed and
of the successful runs (``return_failed``, ``return_succeeded``). The interval of a quantity that
cannot be negative (:data:`NON_NEGATIVE_KEYS`: errors, ANEES, completeness, CPU seconds) is the
percentile bootstrap interval of the mean (:func:`bootstrap_interval`), which stays within the
runs' range (a symmetric t-interval from 3 runs reached -3 s of CPU and -30 m of map error);
only ``return`` keeps the Student-t interval. ``n_values`` counts the runs behind each
interval. With several filter draws per world (``draw``, issue 46) the draws of a world are
runs of one group, and every interval is taken over worlds: of the per-world means
(:func:`per_world`); the success rate's is the clustered Wilson interval above (issue 56: the
percentile bootstrap of per-world rates used before covered 0.26-0.89 on 3-10 worlds). Errored
runs never count as failures: they
are excluded from every rate and mean and reported in ``n_errors`` (per group and in total), so
a crash cannot pass for a SLAM failure. A null metric (e.g. not computable for that run) is
left out of its mean.
"""

from __future__ import annotations

import json
import math
import os
import statistics
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from filters.validation import require
from slam_gym.evaluation.jobs import JOB_KINDS
from slam_gym.evaluation.results import STATUS_ERROR, STATUS_OK

#: Two-sided 95 % standard-normal quantile, Phi^-1(0.975).
Z95 = 1.959963984540054

SUMMARY_FILENAME = "summary.json"
TABLE_FILENAME = "table.md"

_MEAN_KEYS = ("anees", "nees_in_band_fraction", "n_fusions", "n_optimisations", "wall_time_s")
_MEAN_MEDIAN_KEYS = ("map_error_m", "final_pose_error_m")
CI_KEYS = (
    "map_error_m", "anees", "map_completeness", "return",
    "filter_cpu_s", "fusion_cpu_s", "optimise_cpu_s", "interface_cpu_s", "total_cpu_s",
)
"""Metrics whose mean is reported with a 95 % interval (``ci95``) where rows carry them."""

NON_NEGATIVE_KEYS = frozenset(
    ("map_error_m", "map_error_m_succeeded", "anees", "map_completeness", "filter_cpu_s",
     "fusion_cpu_s", "optimise_cpu_s", "interface_cpu_s", "total_cpu_s"))
"""Metrics that cannot be negative: their ``ci95`` is :func:`bootstrap_interval`'s."""

BOOTSTRAP_RESAMPLES = 4000
BOOTSTRAP_SEED = 20261127
"""The bootstrap's resamples and the seed of its own generator: the same runs give the same
interval."""

DERIVED_KEYS = {"interface_cpu_s": ("fusion_cpu_s", "optimise_cpu_s")}
"""Row metrics that are sums of others: the CPU time of the interface decisions' work."""

PaperValues = Mapping[str, Mapping[Any, float]]


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (Wilson 1927).

    With p = k/n: centre = (p + z^2/(2n)) / (1 + z^2/n) and half-width
    = z / (1 + z^2/n) * sqrt(p(1-p)/n + z^2/(4n^2)). Exact 0 and 1 at k = 0 and k = n.
    """
    ok_n = isinstance(n, int) and not isinstance(n, bool) and n >= 1
    require(ok_n, "n", n, "an int >= 1")
    ok_k = isinstance(successes, int) and not isinstance(successes, bool) and 0 <= successes <= n
    require(ok_k, "successes", successes, f"an int in [0, {n}]")
    require(isinstance(z, (int, float)) and z > 0 and math.isfinite(z), "z", z, "a number > 0")
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1.0 - p) / n + z2 / (4 * n * n))
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return lo, hi


SUCCESS_CI_METHOD = "wilson-design-effect"
"""The name of ``success_ci95``'s method in the summary (:func:`clustered_wilson_interval`)."""


def world_outcomes(rows: Sequence[Mapping[str, Any]]) -> list[list[bool]]:
    """The judged runs' successes grouped by world (``seed``; a row without one is a world of its
    own), in first-seen order."""
    by_world: dict[Any, list[bool]] = {}
    for i, row in enumerate(rows):
        world = row["seed"] if row.get("seed") is not None else ("run", i)
        by_world.setdefault(world, []).append(bool(row["success"]))
    return list(by_world.values())


def clustered_wilson_interval(worlds: Sequence[Sequence[bool]], z: float = Z95
                              ) -> tuple[float, float]:
    """Wilson's score interval for a success rate whose runs come in clusters (the filter draws
    of one world), at the effective number of runs ``n / deff`` (Kish 1965) and, where the
    draws are correlated (``deff > 1``), Student's quantile at the worlds' degrees of freedom
    ``G - 1`` for ``z`` (the design-effect Wilson interval of Korn & Graubard 1998).

    ``deff = 1 + (m0 - 1) max(icc, 0)``, ``icc`` the one-way ANOVA intraclass correlation of the
    0/1 outcomes within worlds and ``m0`` its average cluster size
    (:func:`slam_gym.evaluation.paired.intraclass_correlation`); with one run a world this is
    :func:`wilson_interval`; with no variation (every run a success, or none) it is Wilson's
    interval over the worlds (the clustering cannot be measured, so the most it can be).
    Written here: scipy has Wilson's interval for independent trials only
    (``binomtest().proportion_ci``), statsmodels (not a dependency) none for clusters. Checked
    by simulation in tests/slam_gym/test_paired.py (5-10 worlds, 2-5 draws: coverage
    0.95-0.97; 0.92 at 3 worlds of 5 draws)."""
    import numpy as np

    from slam_gym.evaluation.paired import effective_worlds, intraclass_correlation

    outcomes = [[bool(v) for v in w] for w in worlds if len(w)]
    n = sum(len(w) for w in outcomes)
    require(n >= 1, "worlds", worlds, "at least one run")
    k = sum(sum(w) for w in outcomes)
    if all(len(w) == 1 for w in outcomes):
        return wilson_interval(k, n, z)
    if k in (0, n):  # no variation to measure the clustering by: count worlds, not runs
        return wilson_interval(len(outcomes) if k else 0, len(outcomes), z)
    values = np.array([float(v) for w in outcomes for v in w])
    clusters = np.repeat(np.arange(len(outcomes)), [len(w) for w in outcomes])
    icc = intraclass_correlation(values, clusters)
    n_eff = effective_worlds(n, clusters, icc)
    if n_eff < n:  # Korn & Graubard's degrees of freedom: the worlds, not the runs
        from scipy.stats import norm, t

        z = float(t.ppf(norm.cdf(z), len(outcomes) - 1))
    p = k / n
    z2 = z * z
    denom = 1.0 + z2 / n_eff
    centre = (p + z2 / (2 * n_eff)) / denom
    half = z / denom * math.sqrt(p * (1.0 - p) / n_eff + z2 / (4 * n_eff * n_eff))
    return max(0.0, centre - half), min(1.0, centre + half)


def mean_interval(values: Sequence[float], confidence: float = 0.95) -> tuple[float, float] | None:
    """Student-t interval of the mean: ``mean +- t_{(1+c)/2, n-1} s / sqrt(n)`` (None if n < 2)."""
    from scipy.stats import t

    require(0.0 < confidence < 1.0, "confidence", confidence, "in (0, 1)")
    n = len(values)
    if n < 2:
        return None
    mean = statistics.fmean(values)
    half = float(t.ppf(0.5 + confidence / 2.0, n - 1)) * statistics.stdev(values) / math.sqrt(n)
    return mean - half, mean + half


def bootstrap_interval(values: Sequence[float], confidence: float = 0.95
                       ) -> tuple[float, float] | None:
    """Percentile bootstrap interval of the mean (Efron): the ``(1 -+ c) / 2`` quantiles of the
    means of :data:`BOOTSTRAP_RESAMPLES` resamples with replacement (None if n < 2). It lies
    within ``[min(values), max(values)]``, so a non-negative quantity keeps a non-negative
    interval; with few runs it is narrow (3 runs: the interval of 27 equally likely means), so
    read it with the number of runs."""
    import numpy as np

    require(0.0 < confidence < 1.0, "confidence", confidence, "in (0, 1)")
    v = np.asarray(values, dtype=float)
    if len(v) < 2:
        return None
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means = v[rng.integers(0, len(v), size=(BOOTSTRAP_RESAMPLES, len(v)))].mean(axis=1)
    lo, hi = np.quantile(means, [0.5 - confidence / 2.0, 0.5 + confidence / 2.0])
    return float(max(lo, v.min())), float(min(hi, v.max()))


def interval(key: str, values: Sequence[float]) -> list[float] | None:
    """The ``ci95`` of metric ``key``: bootstrap for :data:`NON_NEGATIVE_KEYS`, else Student-t."""
    ci = bootstrap_interval(values) if key in NON_NEGATIVE_KEYS else mean_interval(values)
    return None if ci is None else list(ci)


def _kind_name(row: Mapping[str, Any]) -> tuple[str, str]:
    kinds = [k for k in JOB_KINDS if row.get(k) is not None]
    require(len(kinds) == 1, "row kind", kinds, "exactly one of 'system' or 'policy' set")
    return kinds[0], row[kinds[0]]


def metric_values(rows: Sequence[Mapping[str, Any]], key: str) -> list[float]:
    """The finite values of metric ``key`` over ``rows`` (booleans as 0/1; the
    :data:`DERIVED_KEYS` summed from their parts), rows without it left out."""
    out = []
    for row in rows:
        if key in DERIVED_KEYS and key not in row:
            parts = [row.get(k) for k in DERIVED_KEYS[key]]
            v = sum(parts) if all(isinstance(p, (int, float)) for p in parts) else None
        else:
            v = row.get(key)
        if isinstance(v, bool):
            v = float(v)
        if isinstance(v, (int, float)) and math.isfinite(v):
            out.append(float(v))
    return out


PER_RUN_OPTIONS = ("draw",)
"""Job options that tell runs of one group apart (the draw of a world) rather than groups."""


def per_world(rows: Sequence[Mapping[str, Any]], key: str) -> list[float]:
    """``key``'s values as one value per world (``seed``): the mean over the world's draws, so
    that an interval over worlds treats the draws of one world as the one observation they are
    (a cluster); with one draw per world, the values themselves."""
    by_world: dict[Any, list[float]] = {}
    for i, row in enumerate(rows):
        values = metric_values([row], key)
        if values:  # a row that names no world is a world of its own
            world = row["seed"] if row.get("seed") is not None else ("run", i)
            by_world.setdefault(world, []).append(values[0])
    return [sum(v) / len(v) for v in by_world.values()]


def draw_discordance(rows: Sequence[Mapping[str, Any]]) -> tuple[int, int]:
    """(worlds run with more than one draw, those of them whose success differs between their
    draws): how often the filter's random numbers alone change a world's outcome."""
    outcomes: dict[Any, list[bool]] = {}
    for i, row in enumerate(rows):
        if row.get("success") is not None:
            world = row["seed"] if row.get("seed") is not None else ("run", i)
            outcomes.setdefault(world, []).append(bool(row["success"]))
    several = [v for v in outcomes.values() if len(v) > 1]
    return len(several), sum(len(set(v)) > 1 for v in several)


def _mean(values: list[float]) -> float | None:
    return statistics.fmean(values) if values else None


def _median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


def paper_rate(paper: PaperValues | None, name: str, clutter_level: Any) -> float | None:
    """Look up a reference success rate (fraction) by name and clutter level (int or str keys)."""
    if not paper or name not in paper:
        return None
    by_level = paper[name]
    for key in (clutter_level, str(clutter_level)):
        if key in by_level:
            return float(by_level[key])
    return None


def summarise(
    rows: Iterable[Mapping[str, Any]], *, paper: PaperValues | None = None
) -> list[dict[str, Any]]:
    """One dict per (system or policy, scenario, clutter level, options), in first-seen order
    of names and scenarios and ascending clutter level. ``paper`` (name -> {level: rate}) adds
    ``paper_success_rate`` to the matching groups.
    """
    groups: dict[tuple, list[Mapping[str, Any]]] = {}
    name_order: dict[tuple[str, str], int] = {}
    scenario_order: dict[str, int] = {}
    for row in rows:
        kind, name = _kind_name(row)
        status = row.get("status")
        require(status in (STATUS_OK, STATUS_ERROR), "row status", status, "'ok' or 'error'")
        # the draws of a world are one group's runs, not groups of their own
        options = json.dumps({k: v for k, v in (row.get("options") or {}).items()
                              if k not in PER_RUN_OPTIONS}, sort_keys=True)
        name_order.setdefault((kind, name), len(name_order))
        scenario_order.setdefault(row.get("scenario"), len(scenario_order))
        gkey = (kind, name, row.get("scenario"), row.get("clutter_level"), options)
        groups.setdefault(gkey, []).append(row)

    def order(gkey: tuple) -> tuple:
        kind, name, scenario, level, _ = gkey
        level_key = (1, 0) if level is None else (0, level)
        return name_order[(kind, name)], scenario_order[scenario], level_key

    summary = []
    for gkey in sorted(groups, key=order):
        kind, name, scenario, level, options = gkey
        members = groups[gkey]
        ok = [r for r in members if r.get("status") == STATUS_OK]
        # success is undefined (null) where there is no pose truth, e.g. Victoria Park
        judged = [r for r in ok if r.get("success") is not None]
        n_success = sum(1 for r in judged if r.get("success") is True)
        ci = list(wilson_interval(n_success, len(judged))) if judged else None
        n_worlds = len({r["seed"] if r.get("seed") is not None else ("run", i)
                        for i, r in enumerate(members)})
        several, varies = draw_discordance(judged)
        if judged:
            # one method, draws or not: Wilson's interval at the effective number of runs
            # (the draws of a world are one cluster; with one draw a world, Wilson's own)
            ci = list(clustered_wilson_interval(world_outcomes(judged)))
        first = next((r for r in ok if r.get("alpha") is not None), {})
        group: dict[str, Any] = {
            kind: name,
            "scenario": scenario,
            "clutter_level": level,
            "options": json.loads(options),
            "alpha": first.get("alpha"),
            "beta": first.get("beta"),
            "n": len(members),
            "n_worlds": n_worlds,
            "n_ok": len(ok),
            "n_errors": len(members) - len(ok),
            "n_success": n_success,
            "success_rate": n_success / len(judged) if judged else None,
            "success_ci95": ci,
            "success_ci95_method": SUCCESS_CI_METHOD if ci is not None else None,
        }
        if several:
            # the noise floor of a success comparison: worlds whose outcome the filter's draws
            # alone change (issue 46; formerly the script filter_noise.py)
            group["worlds_with_draws"] = several
            group["worlds_outcome_varies"] = varies
        for key in _MEAN_KEYS:
            group[key] = _mean(metric_values(ok, key))
        for key in _MEAN_MEDIAN_KEYS:
            values = metric_values(ok, key)
            group[key] = {"mean": _mean(values), "median": _median(values)}
        intervals, counts = {}, {}
        for key in CI_KEYS:
            values = metric_values(ok, key)
            if values:
                group.setdefault(key, _mean(values))
                intervals[key] = interval(key, per_world(ok, key))
                counts[key] = len(values)
        succeeded = [r for r in judged if r["success"]]
        values = metric_values(succeeded, "map_error_m")
        if values and intervals:
            # the map error of the runs that did not fail: a rule that fails early keeps a small
            # map with small errors, which the mean over all runs would reward
            group["map_error_m_succeeded"] = _mean(values)
            intervals["map_error_m_succeeded"] = interval("map_error_m_succeeded",
                                                          per_world(succeeded, "map_error_m"))
            counts["map_error_m_succeeded"] = len(values)
        if intervals:
            group["ci95"] = intervals
            group["n_values"] = counts
        if any(r.get("return") is not None for r in ok):
            group["return_failed"] = _mean(metric_values([r for r in judged if not r["success"]],
                                                    "return"))
            group["return_succeeded"] = _mean(metric_values([r for r in judged if r["success"]],
                                                       "return"))
        group.update(group_provenance(ok))
        if paper is not None:
            group["paper_success_rate"] = paper_rate(paper, name, level)
        summary.append(group)
    return summary


MISMATCH_MARK = "†"
"""Marks a learned policy's row whose model does not match the code (its fingerprint differs)."""


def group_provenance(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``model_matches_code`` (False if any run's model did not match the code, True if every run's
    did, None if unchecked) and the distinct ``model_differences``, for rows that carry them (a
    learned policy's); {} for the others."""
    marked = [r for r in rows if "model_matches_code" in r]
    if not marked:
        return {}
    values = [r.get("model_matches_code") for r in marked]
    matches = False if False in values else (True if all(v is True for v in values) else None)
    differences: list[str] = []
    for r in marked:
        differences += [d for d in r.get("model_differences") or [] if d not in differences]
    return {"model_matches_code": matches, "model_differences": differences}


def provenance_footnote(groups: Sequence[Mapping[str, Any]]) -> str | None:
    """The footnote of :data:`MISMATCH_MARK` when a group's model does not match the code."""
    stale = [g for g in groups if g.get("model_matches_code") is False]
    if not stale:
        return None
    differences: list[str] = []
    for g in stale:
        differences += [d for d in g.get("model_differences") or [] if d not in differences]
    shown = "; ".join(differences[:3]) + ("; ..." if len(differences) > 3 else "")
    return (f"{MISMATCH_MARK} the model was trained on a different system: its fingerprint does "
            f"not match this code ({shown}); its rows do not show what the policy learned on "
            "this system (`slam-gym fingerprint MODEL`).")


def summary_document(
    rows: Iterable[Mapping[str, Any]], *, paper: PaperValues | None = None
) -> dict[str, Any]:
    """The content of ``summary.json``: totals, the interval used and the groups."""
    rows = list(rows)
    groups = summarise(rows, paper=paper)
    n_errors = sum(g["n_errors"] for g in groups)
    return {
        "n_runs": len(rows),
        "n_ok": len(rows) - n_errors,
        "n_errors": n_errors,
        "interval": "Wilson score interval, 95 % (z = 1.96)",
        "note": (
            "success_rate and all means are over runs with status 'ok'; runs with status "
            "'error' are counted in n_errors and excluded"
        ),
        "groups": groups,
    }


# ---------------------------------------------------------------------------------------------
# Formatting


def _groups(summary: Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    if isinstance(summary, Mapping):
        return list(summary["groups"])
    return list(summary)


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.0f} %"


def _num(x: float | None, digits: int = 2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def format_success(group: Mapping[str, Any]) -> str:
    """``"87 % [80, 92]"``: success rate with its Wilson 95 % interval, in percent."""
    rate, ci = group.get("success_rate"), group.get("success_ci95")
    if rate is None or ci is None:
        return "–"
    return f"{100 * rate:.0f} % [{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]"


def options_distinguish(groups: Sequence[Mapping[str, Any]]) -> bool:
    """True if two groups share name, scenario and clutter level and differ only by options."""
    seen = set()
    for g in groups:
        ident = (_kind_name(g), g.get("scenario"), g.get("clutter_level"))
        if ident in seen:
            return True
        seen.add(ident)
    return False


def table_cells(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]], *, paper: PaperValues | None = None
) -> tuple[list[str], list[list[str]]]:
    """Header and rows of strings shared by the markdown, rich and plain-text tables.

    The ``scenario`` column appears only when scenarios vary, ``options`` only when rows of the
    same name, scenario and clutter level differ by options; ``paper`` only when reference values
    are given (argument, or ``paper_success_rate`` in the groups).
    """
    groups = _groups(summary)
    kinds = {k for g in groups for k in JOB_KINDS if k in g}
    name_header = "/".join(k for k in JOB_KINDS if k in kinds) or "system"
    show_scenario = len({g.get("scenario") for g in groups}) > 1
    show_options = options_distinguish(groups)

    def ref(g: Mapping[str, Any]) -> float | None:
        if paper is not None:
            return paper_rate(paper, _kind_name(g)[1], g.get("clutter_level"))
        return g.get("paper_success_rate")

    show_paper = any(ref(g) is not None for g in groups)
    show_compute = any("total_cpu_s" in g for g in groups)
    show_return = any("return" in g for g in groups)
    header = [name_header]
    header += ["scenario"] if show_scenario else []
    header += ["options"] if show_options else []
    # consistency and map error first: the mission's measures (issue 46); success after them
    header += ["clutter", "n", "errors", "NEES in band", "ANEES", "map error (m) mean / median",
               "success [95 % CI]"]
    header += ["paper"] if show_paper else []
    header += ["fusions", "optimisations", "time (s)"]
    header += ["completeness", "CPU fusion / optimise / total (s)"] if show_compute else []
    header += ["return (failed / succeeded)"] if show_return else []
    body = []
    for g in groups:
        level = g.get("clutter_level")
        cells = [_kind_name(g)[1] + (f" {MISMATCH_MARK}" if g.get("model_matches_code") is False
                                     else "")]
        cells += [str(g.get("scenario"))] if show_scenario else []
        if show_options:
            cells.append(", ".join(f"{k}={v}" for k, v in (g.get("options") or {}).items()))
        cells += ["–" if level is None else str(level), str(g["n"]), str(g["n_errors"])]
        map_err = g.get("map_error_m") or {}
        cells += [
            _pct(g.get("nees_in_band_fraction")),
            _num(g.get("anees")),
            f"{_num(map_err.get('mean'))} / {_num(map_err.get('median'))}",
            format_success(g),
        ]
        cells += [_pct(ref(g))] if show_paper else []
        cells += [
            _num(g.get("n_fusions"), 1),
            _num(g.get("n_optimisations"), 1),
            _num(g.get("wall_time_s"), 1),
        ]
        if show_compute:
            cells += [
                _pct(g.get("map_completeness")),
                " / ".join(_num(g.get(k)) for k in ("fusion_cpu_s", "optimise_cpu_s",
                                                       "total_cpu_s")),
            ]
        if show_return:
            cells.append(f"{_num(g.get('return'), 0)} ({_num(g.get('return_failed'), 0)} / "
                         f"{_num(g.get('return_succeeded'), 0)})")
        body.append(cells)
    return header, body


def markdown_table(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]], *, paper: PaperValues | None = None
) -> str:
    """The summary as a GitHub-flavoured markdown table (the content of ``table.md``)."""
    header, body = table_cells(summary, paper=paper)

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"

    align = ["---"] + ["---:"] * (len(header) - 1)
    notes = [n for n in (provenance_footnote(_groups(summary)),
                         draws_footnote(_groups(summary))) if n]
    return "\n".join([line(header), "|" + "|".join(align) + "|", *map(line, body)]
                     + [x for n in notes for x in ("", n)]) + "\n"


def draws_footnote(groups: Sequence[Mapping[str, Any]]) -> str | None:
    """With several filter draws per world: per group, the worlds whose success differed
    between draws, out of those run with several (None without draws)."""
    parts = [f"{g.get('policy') or g.get('system')} at clutter {g.get('clutter_level')}: "
             f"{g['worlds_outcome_varies']} of {g['worlds_with_draws']}"
             for g in groups if g.get("worlds_with_draws")]
    if not parts:
        return None
    return ("Worlds whose success differs between filter draws (the noise floor of a paired "
            "success comparison): " + "; ".join(parts) + ".")


def format_table(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    *,
    paper: PaperValues | None = None,
    rich: bool = True,
    title: str | None = "Benchmark summary (success: Wilson 95 % interval)",
) -> Any:
    """A ``rich.table.Table`` for the console, or aligned plain text with ``rich=False``."""
    header, body = table_cells(summary, paper=paper)
    footnote = provenance_footnote(_groups(summary))
    if rich:
        from rich.table import Table

        table = Table(title=title, caption=footnote)
        # the names are never cut short (two names with one prefix would read the same): the
        # first column is as wide as its longest name, the others fold rather than truncate
        longest = max((len(r[0]) for r in body), default=0)
        for i, name in enumerate(header):
            table.add_column(name, justify="left" if i == 0 else "right", overflow="fold",
                             min_width=longest if i == 0 else None)
        for cells in body:
            table.add_row(*cells)
        return table
    widths = [max(len(r[i]) for r in [header, *body]) for i in range(len(header))]

    def line(cells: list[str]) -> str:
        pairs = enumerate(zip(cells, widths, strict=True))
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in pairs).rstrip()

    out = [title] if title else []
    out += [line(header), "  ".join("-" * w for w in widths), *map(line, body)]
    out += [footnote] if footnote else []
    return "\n".join(out)


KEY_COLUMNS = frozenset(("scenario", "options", "clutter"))
"""Columns (besides the first, the name) repeated in every part of a split console table."""

_BOX_COST = 3
"""Characters a column of a rich table costs besides its text: a border and two of padding."""


def _longest_word(text: str) -> int:
    return max((len(word) for word in text.split()), default=0)


def split_columns(header: Sequence[str], body: Sequence[Sequence[str]], width: int
                  ) -> list[list[tuple[int, int]]]:
    """How a table of ``header`` and ``body`` fits ``width`` characters of a rich table with
    borders: its parts, each a list of (column index, column width). The first column and
    :data:`KEY_COLUMNS` are in every part, the others in order, as many per part as fit. A cell
    is never cut: a column is as wide as its widest cell, and a header folds at spaces (a column
    as wide as the header's longest word) only in a part that does not fit at the headers' full
    widths. Only a column too wide to fit beside the key columns even alone wraps its cells, at
    spaces (never narrower than its longest word; the key columns never wrap, so such a part
    may be wider than ``width``)."""
    n = len(header)

    def widths_of(head_width, cell_width) -> list[int]:
        return [max([head_width(header[i]), *(cell_width(row[i]) for row in body)])
                for i in range(n)]

    def cost(columns, widths) -> int:
        return sum(widths[i] + _BOX_COST for i in columns) + 1

    keys = [0] + [i for i in range(1, n) if header[i] in KEY_COLUMNS]
    others = [i for i in range(n) if i not in keys]
    full = widths_of(len, len)
    compact = widths_of(_longest_word, len)
    narrowest = widths_of(_longest_word, _longest_word)
    parts: list[list[int]] = []
    current: list[int] = []
    for i in others:
        if current and cost(keys + current + [i], compact) > width:
            parts.append(current)
            current = []
        current.append(i)
    parts.append(current)
    out = []
    for part in parts:
        columns = sorted(keys + part)
        widths = list(full if cost(columns, full) <= width else compact)
        if len(part) == 1 and cost(columns, widths) > width:  # wrap its cells at spaces
            i = part[0]
            widths[i] = max(narrowest[i], width - cost(keys, widths) - _BOX_COST)
        out.append([(i, widths[i]) for i in columns])
    return out


def parts_width(part: Sequence[tuple[int, int]]) -> int:
    """The characters a part of :func:`split_columns` takes."""
    return sum(w + _BOX_COST for _, w in part) + 1


def format_tables(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    *,
    width: int,
    paper: PaperValues | None = None,
    title: str | None = "Benchmark summary (success: Wilson 95 % interval)",
) -> list[Any]:
    """The console table as ``rich.table.Table`` parts that fit ``width`` characters
    (:func:`split_columns`): one table when it fits, else the columns spread over several,
    each repeating the names (and clutter level). The title heads the first part, the footnote
    closes the last. A part's ``min_width`` is its width: print it at least that wide (a part
    can be wider than ``width`` only when its names alone are)."""
    from rich.table import Table

    header, body = table_cells(summary, paper=paper)
    footnote = provenance_footnote(_groups(summary))
    parts = split_columns(header, body, width)
    tables = []
    for k, columns in enumerate(parts):
        part_title = title if k == 0 else None
        if title and len(parts) > 1:
            part_title = f"{title} ({k + 1}/{len(parts)})" if k == 0 else f"({k + 1}/{len(parts)})"
        table = Table(title=part_title, caption=footnote if k == len(parts) - 1 else None,
                      min_width=max(parts_width(columns), 1))
        for i, w in columns:
            table.add_column(header[i], justify="left" if i == 0 else "right",
                             overflow="fold", min_width=w, max_width=w)
        for cells in body:
            table.add_row(*(cells[i] for i, _ in columns))
        tables.append(table)
    return tables


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_summary(
    out_dir: str | os.PathLike,
    rows: Iterable[Mapping[str, Any]],
    *,
    paper: PaperValues | None = None,
) -> dict[str, Any]:
    """Write ``summary.json`` (see :func:`summary_document`) and ``table.md``; return the doc."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = summary_document(rows, paper=paper)
    _write_atomic(out / SUMMARY_FILENAME, json.dumps(doc, indent=2, allow_nan=False) + "\n")
    table = markdown_table(doc, paper=paper)
    note = (
        f"\n{doc['n_runs']} runs, {doc['n_errors']} errored (excluded from rates and means). "
        "Success: rate over ok runs with its Wilson 95 % interval.\n"
    )
    _write_atomic(out / TABLE_FILENAME, table + note)
    return doc
