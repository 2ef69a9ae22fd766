"""The headroom of a task: its rules, its best threshold rule and the lookahead's bound (and the
lookahead where the bound shows room), paired world by world with the best rule (issue 48; a
command since issue 55: ``slam-gym headroom``, :mod:`slam_gym.commands.headroom`).

Supports docs/RESULTS.md, "Tasks where the interface decision matters (issue 48)". The declared
runs (one worker; resumable: a rerun with the same ``--out`` keeps the finished rows)::

    slam-gym headroom --env SlamGym/HybridSLAM-ZonesStarved-v1 --seeds 10 --seed-start 4800 \
        --threshold-rule out/tr48-starved/chosen.json --out out/headroom48-starved

``--env`` is a registered env id (an issue-48 task: its worlds, particles and clutter levels,
``gym.make(id)``'s env; ``--env-kwargs`` over its own). Policies: ``--policies`` (default the
three rules and ``lookahead-privileged``) and, with ``--threshold-rule`` (the ``chosen.json``
of ``slam-gym threshold-rule`` in the same env, refused from another), the chosen threshold rule
under its own name (``threshold-optimise[FEATURE>=THRESHOLD]``; issue 48's rows call it
``best-threshold``, which a report renames). The **best rule** is the threshold family's rule
chosen there (the family includes its ends ``fixed-10s`` and ``fixed-10s-optimise``; the
chosen one by mean return at ``--price``), else ``--best-rule``.

Statistics: those of ``slam-gym compare`` (issue 56), :func:`paired_difference`. Every run is
paired with the best rule's run on the same world and draw (common random numbers) by the one
pairing, :func:`slam_gym.evaluation.pairing.paired_worlds` (the map error over the draws both
survived); the per-world difference is the mean over the world's draws, and the **seed is the
cluster** (a seed's worlds at the four clutter levels share its waypoints, path, landmarks and
zones). Continuous measures get the cluster bootstrap over seeds
(:func:`~slam_gym.evaluation.paired.cluster_bootstrap_interval`), success the cluster
Bonett-Price interval (:func:`~slam_gym.evaluation.paired.matched_rate_interval`; issue 48
declared Agresti-Min's weight over independent worlds, replaced in issue 56 by compare's
interval, which covers where the seed decides the outcome). Each difference carries its worlds,
seeds, method, the intraclass correlation within seeds and the effective number of independent
worlds (``<metric>_paired`` in ``headroom.json``). Normalised headroom:
``(lookahead - best) / (bound - best)``, reported only where the bound's interval excludes 0
on the better side of the measure. A policy that is neither a rule of the report, a planner
nor the bound (a learner, issue 58) also gets the **gap closed**, ``(policy - best) / (planner
- best)`` for each planner present, with the same interval (:func:`gap_closed`). Writes
``OUT/headroom.json`` and ``OUT/headroom.md``.

``--report-only`` recomputes them from the rows without running anything. ``--rows DIR``
(repeatable) adds the rows of other runs' folders, e.g. the halves of the declared worlds run
in separate processes (a run whose key is already in is kept once); ``--rename-rows OLD=NEW``
reports their policy ``OLD`` as ``NEW`` (issue 48's ``lookahead`` rows are the full planner's,
``lookahead-full`` since issue 57, when the default ``lookahead`` became the fast planner).
The normalised headroom is given for ``lookahead`` and ``lookahead-full`` when present, each
with a 95 % interval (:func:`headroom_interval`). ``--common-worlds``
restricts every policy to the worlds that all of them finished: a partial table, every mean
and difference over the same worlds.
"""

from __future__ import annotations

import logging
import math
from collections import defaultdict
from collections.abc import Mapping, Sequence

import numpy as np

from slam_gym.evaluation.results import row_key

logger = logging.getLogger(__name__)

RULES = ("fixed-10s", "fixed-10s-optimise", "esdf-innovation")
BOUND = "lookahead-privileged"
PLANNERS = ("lookahead", "lookahead-full")
"""The planners whose normalised headroom is reported: the default (fast, since issue 57) and
the full planner of issue 39 (what issue 48's rows call ``lookahead``: ``--rename-rows``)."""
METRICS = ("success", "nees_in_band_fraction", "anees", "map_error_m", "interface_cpu_s",
           "return")
"""The paired measures of the table (``return`` at ``--price``)."""

BETTER_IF_HIGHER = {"success": True, "nees_in_band_fraction": True, "anees": False,
                    "map_error_m": False, "interface_cpu_s": False, "return": True}
"""The direction of improvement of each measure: room is where the bound's interval excludes 0
on the better side (a bound that spends more CPU has no "room" in CPU)."""


def value(row: Mapping, metric: str, price: float) -> float | None:
    from slam_gym.evaluation.front import interface_cpu_s, return_at_price

    if metric == "success":
        return float(bool(row["success"]))
    if metric == "interface_cpu_s":
        return interface_cpu_s(row)
    if metric == "return":
        return return_at_price(row, price)
    v = row.get(metric)
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else float(v)


def paired_difference(rows: Sequence[Mapping], reference: Sequence[Mapping], metric: str,
                      price: float) -> dict:
    """``rows`` minus ``reference`` on ``metric``, paired by the one pairing of ``slam-gym
    compare`` (:func:`slam_gym.evaluation.pairing.paired_worlds`: per (level, seed, draw), the
    map error over the draws both survived, the per-world mean over draws, the seed as the
    cluster) with compare's fixed-sample interval (:func:`slam_gym.evaluation.compare.
    fixed_interval`) and its labels: ``{"mean", "lo", "hi", "worlds", "seeds", "method",
    "icc", "effective_worlds"}`` (``mean``, ``lo``, ``hi`` NaN with fewer than 2 seeds)."""
    from slam_gym.evaluation.compare import fixed_interval, interval_labels
    from slam_gym.evaluation.pairing import paired_worlds

    pw = paired_worlds(reference, rows, metric,
                       value=lambda row, m: value(row, m, price))
    d = pw.differences()
    out = {"mean": math.nan, "lo": math.nan, "hi": math.nan, "worlds": len(pw),
           "seeds": pw.n_clusters}
    if pw.n_clusters < 2:
        return out
    interval = fixed_interval(d, metric, 0.95)
    out |= {"mean": float(d.differences.mean()), "lo": float(interval.lo),
            "hi": float(interval.hi)} | interval_labels(interval, d)
    return out


def summarise(rows: Sequence[Mapping], best: str, price: float) -> dict:
    """Per policy: means and paired differences with ``best`` (module docstring)."""
    by_policy: dict[str, list[Mapping]] = defaultdict(list)
    for r in rows:
        if r.get("status") == "ok" and "policy" in r:  # a baseline system's row has none
            by_policy[r["policy"]].append(r)
    reference = by_policy[best]
    out: dict = {"best_rule": best, "price": price, "policies": {}}
    for name, group in by_policy.items():
        entry: dict = {"n_runs": len(group),
                       "n_worlds": len({(r["clutter_level"], r["seed"]) for r in group})}
        for metric in METRICS:
            vals = [value(r, metric, price) for r in group
                    if metric != "map_error_m" or r["success"]]
            vals = [v for v in vals if v is not None]
            entry[metric] = float(np.mean(vals)) if vals else None
            if name == best:
                continue
            paired = paired_difference(group, reference, metric, price)
            entry[f"{metric}_diff"] = (paired["mean"], paired["lo"], paired["hi"])
            entry[f"{metric}_paired"] = paired
        for extra in ("planning_cpu_s", "deviations_from_base", "n_fusions", "n_optimisations"):
            vals = [float(r[extra]) for r in group if r.get(extra) is not None]
            entry[extra] = float(np.mean(vals)) if vals else None
        out["policies"][name] = entry
    bound = out["policies"].get(BOUND)
    out["normalised_headroom"] = {}
    out["normalised_headroom_by_arm"] = {}
    for arm in PLANNERS:
        look = out["policies"].get(arm)
        if not (bound and look) or best in (arm, BOUND):
            continue  # no headroom against itself (e.g. --best-rule lookahead-full)
        point, interval = {}, {}
        for metric in METRICS:
            b, lk = bound[f"{metric}_diff"], look[f"{metric}_diff"]
            room = b[1] > 0.0 if BETTER_IF_HIGHER[metric] else b[2] < 0.0
            point[metric] = (lk[0] / b[0]) if room and b[0] else None
            interval[metric] = (headroom_interval(
                by_policy[arm], by_policy[BOUND], reference, metric, price)
                if point[metric] is not None else None)
        out["normalised_headroom_by_arm"][arm] = {"point": point, "interval": interval}
        if arm == "lookahead":
            out["normalised_headroom"] = point
    out["gap_closed"] = gap_closed(out, by_policy, reference, price)
    return out


def gap_closed(doc: Mapping, by_policy: Mapping[str, Sequence[Mapping]],
               reference: Sequence[Mapping], price: float) -> dict:
    """Per policy that is neither a rule (:data:`RULES`, the threshold family), a planner nor
    the bound (a learner): the share
    of the gap from the best rule to each planner it closes, ``mean(arm - best) / mean(planner
    - best)`` with its 95 % cluster-bootstrap interval (:func:`headroom_interval`, the seeds
    resampled), for each measure on which the planner's own interval excludes 0 on the better
    side (issue 58's question 4)."""
    out: dict = {}
    best = doc["best_rule"]
    for arm, entry in doc["policies"].items():
        if arm in (best, BOUND, *PLANNERS, *RULES) or arm.startswith("threshold-"):
            continue
        for planner in PLANNERS:
            look = doc["policies"].get(planner)
            if look is None or planner == best:
                continue
            point, interval = {}, {}
            for metric in METRICS:
                lk, d = look.get(f"{metric}_diff"), entry.get(f"{metric}_diff")
                if lk is None or d is None:
                    continue
                room = lk[1] > 0.0 if BETTER_IF_HIGHER[metric] else lk[2] < 0.0
                if room and lk[0]:
                    point[metric] = d[0] / lk[0]
                    interval[metric] = headroom_interval(by_policy[arm], by_policy[planner],
                                                         reference, metric, price)
            out.setdefault(arm, {})[planner] = {"point": point, "interval": interval}
    return out


def headroom_interval(arm: Sequence[Mapping], bound: Sequence[Mapping],
                      reference: Sequence[Mapping], metric: str, price: float,
                      n_resamples: int = 10_000) -> tuple[float, float] | None:
    """95 % percentile interval of the normalised headroom ``mean(arm - best) / mean(bound -
    best)``, both paired by the one pairing (:func:`slam_gym.evaluation.pairing.paired_worlds`)
    on the worlds both arms have, the seeds (the independent units, issue 56) resampled
    together with every world of theirs (a cluster bootstrap of the ratio; seed 0)."""
    from slam_gym.evaluation.pairing import paired_worlds

    def per_world(rows):
        pw = paired_worlds(reference, rows, metric, value=lambda row, m: value(row, m, price))
        return {(int(lv), int(c)): float(d) for lv, c, d in
                zip(pw.strata, pw.clusters, pw.b - pw.a, strict=True)}

    a, b = per_world(arm), per_world(bound)
    worlds = sorted(set(a) & set(b))
    seeds = sorted({w[1] for w in worlds})
    if len(seeds) < 2:
        return None
    da = np.array([sum(a[w] for w in worlds if w[1] == s) for s in seeds])
    db = np.array([sum(b[w] for w in worlds if w[1] == s) for s in seeds])
    rng = np.random.default_rng(0)
    index = rng.integers(0, len(seeds), size=(n_resamples, len(seeds)))
    num, den = da[index].sum(axis=1), db[index].sum(axis=1)
    ratios = num[den != 0.0] / den[den != 0.0]
    if not len(ratios):
        return None
    lo, hi = np.percentile(ratios, [2.5, 97.5])
    return float(lo), float(hi)


def diff_cell(entry: Mapping, metric: str, scale: float = 1.0, digits: int = 2) -> str:
    """``entry``'s paired difference on ``metric`` as ``mean [lo, hi]`` (``-`` if undefined)."""
    d = entry.get(f"{metric}_diff")
    if d is None or any(math.isnan(x) for x in d):
        return "-"
    m, lo, hi = (x * scale for x in d)
    return f"{m:+.{digits}f} [{lo:+.{digits}f}, {hi:+.{digits}f}]"


def markdown(doc: Mapping) -> str:
    head = ["policy", "worlds", "success", "vs best (pp)", "NEES in band", "vs best (pp)",
            "ANEES", "vs best", "map error (m)", "vs best (m)", "interface CPU (s)",
            "vs best (s)", f"return @ {doc['price']:g} /s", "vs best", "planning CPU (s/ep)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def cell(entry, metric, scale=1.0, digits=2):
        mean = entry.get(metric)
        return "-" if mean is None else f"{mean * scale:.{digits}f}"

    for name, e in doc["policies"].items():
        label = f"**{name}** (best rule)" if name == doc["best_rule"] else name
        lines.append("| " + " | ".join([
            label, str(e["n_worlds"]),
            cell(e, "success", 100, 0) + " %", diff_cell(e, "success", 100, 0),
            cell(e, "nees_in_band_fraction", 100, 0) + " %",
            diff_cell(e, "nees_in_band_fraction", 100, 0),
            cell(e, "anees"), diff_cell(e, "anees"),
            cell(e, "map_error_m"), diff_cell(e, "map_error_m"),
            cell(e, "interface_cpu_s", 1, 3), diff_cell(e, "interface_cpu_s", 1, 3),
            cell(e, "return", 1, 0), diff_cell(e, "return", 1, 0),
            "-" if e.get("planning_cpu_s") is None else f"{e['planning_cpu_s']:.0f}",
        ]) + " |")
    by_arm = doc.get("normalised_headroom_by_arm") or (
        {"lookahead": {"point": doc["normalised_headroom"], "interval": {}}}
        if doc.get("normalised_headroom") else {})
    for arm, h in by_arm.items():
        lines.append("")
        lines.append(f"Normalised headroom ({arm} - best) / (bound - best), where the bound's "
                     "interval excludes 0 on the better side: " + (", ".join(
                         f"{m} {v:.2f}" + _interval_text((h.get("interval") or {}).get(m))
                         for m, v in h["point"].items() if v is not None) or "none"))
    for arm, planners in (doc.get("gap_closed") or {}).items():
        for planner, g in planners.items():
            lines.append("")
            lines.append(f"Gap closed ({arm} - best) / ({planner} - best), where the planner's "
                         "interval excludes 0 on the better side: " + (", ".join(
                             f"{m} {v:.2f}" + _interval_text(g["interval"].get(m))
                             for m, v in g["point"].items()) or "none"))
    return "\n".join(lines) + "\n"


def _interval_text(interval) -> str:
    return "" if not interval else f" [{interval[0]:.2f}, {interval[1]:.2f}]"


def common_worlds(rows: Sequence[Mapping]) -> list[Mapping]:
    """``rows`` restricted to the (level, seed) worlds on which every policy has a finished
    (``ok``) run."""
    worlds_by_policy: dict[str, set] = defaultdict(set)
    for r in rows:
        if r.get("status") == "ok":
            worlds_by_policy[r["policy"]].add((int(r["clutter_level"]), int(r["seed"])))
    if not worlds_by_policy:
        return []
    shared = set.intersection(*worlds_by_policy.values())
    return [r for r in rows if (int(r["clutter_level"]), int(r["seed"])) in shared]


def join_rows(*groups: Sequence[Mapping]) -> list[dict]:
    """The union of several runs' rows, each run (its job key, :func:`results.row_key`) once: the
    first group's row wins."""
    seen, out = set(), []
    for group in groups:
        for r in group:
            key = row_key(r)
            if key not in seen:
                seen.add(key)
                out.append(dict(r))
    return out


def rename_policies(rows: Sequence[Mapping], renames: Mapping[str, str]) -> list[dict]:
    """``rows`` with the policy names in ``renames`` replaced (their keys too, so that a row
    renamed is never taken for a run of the new name's policy)."""
    out = []
    for r in rows:
        r = dict(r)
        if r.get("policy") in renames:
            r["key"] = f"renamed:{r['policy']}:{row_key(r)}"
            r["policy"] = renames[r["policy"]]
        out.append(r)
    return out


def headroom_table(docs: Sequence[Mapping]) -> str:
    """The headroom table of README and RESULTS (issue 48 item 4): per task (one ``headroom.json``
    each) the best rule's success, then the bound's and the lookahead's paired differences with
    the best rule, and the lookahead's normalised headroom."""
    names = {"nees_in_band_fraction": "NEES in band", "map_error_m": "map error",
             "interface_cpu_s": "interface CPU"}
    lines = ["| task | best rule | its success | arm | success (pp) | NEES in band (pp) | ANEES "
             "| map error (m) | interface CPU (s) | return | normalised headroom | worlds |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    for doc in docs:
        best = doc["policies"][doc["best_rule"]]
        arms = (BOUND, "lookahead", *(["lookahead-full"]
                                      if "lookahead-full" in doc["policies"] else []))
        for arm in arms:
            entry = doc["policies"].get(arm)
            first = arm == BOUND
            task = [f"`{doc['task']}`", f"`{doc.get('best_rule_label', doc['best_rule'])}`",
                    f"{best['success'] * 100:.0f} %"] if first else ["", "", ""]
            label = "bound" if first else arm
            if entry is None:
                lines.append("| " + " | ".join([*task, label, "not run", *["-"] * 6, "0"]) + " |")
                continue
            point = (doc.get("normalised_headroom_by_arm", {}).get(arm, {}).get("point")
                     or (doc["normalised_headroom"] if arm == "lookahead" else {}))
            headroom = "-" if first else ", ".join(
                f"{names.get(m, m)} {v:.2f}" for m, v in point.items() if v is not None) or "-"
            map_worlds = (entry.get("map_error_m_paired") or {}).get("worlds")
            lines.append("| " + " | ".join([
                *task, label, diff_cell(entry, "success", 100, 0),
                diff_cell(entry, "nees_in_band_fraction", 100, 0), diff_cell(entry, "anees", 1, 1),
                diff_cell(entry, "map_error_m") + ("" if map_worlds is None
                                                   else f" ({map_worlds} worlds)"),
                diff_cell(entry, "interface_cpu_s", 1, 3),
                diff_cell(entry, "return", 1, 0), headroom, str(entry["n_worlds"])]) + " |")
    clustering = []
    for doc in docs:
        for arm in (BOUND, "lookahead"):
            paired = (doc["policies"].get(arm) or {}).get("success_paired")
            if paired and paired.get("icc") is not None:
                clustering.append(f"`{doc['task']}` {'bound' if arm == BOUND else arm} "
                                  f"{paired['icc']:.2f} ({paired['effective_worlds']:.0f} of "
                                  f"{paired['worlds']} worlds, {paired['seeds']} seeds)")
    if clustering:
        lines.append("")
        lines.append("Success: the intraclass correlation of the paired differences within seeds "
                     "and the effective number of independent worlds: " + "; ".join(clustering)
                     + ".")
    return "\n".join(lines) + "\n"
