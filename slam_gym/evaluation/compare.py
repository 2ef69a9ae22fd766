"""``slam-gym compare A B`` as a Python function: two policies on the same worlds and filter
draws, paired by world, with a declared question answered by an anytime-valid sequential test.

>>> from slam_gym.evaluation.compare import compare
>>> result = compare("fixed-10s-optimise", "fixed-10s", metric="success", margin=5,
...                  draws=2, max_worlds=96, out="out/compare")          # doctest: +SKIP
>>> result.decision, result.worlds                                       # doctest: +SKIP

Design (issue 46; the seed as the unit, issue 56). Worlds are (clutter level, seed); each runs
``draws`` filter draws per policy, draw ``k`` the same numbers for both (the env's synchronised
streams: common random numbers). Runs are paired by (level, seed, draw) and averaged per world
(:mod:`slam_gym.evaluation.pairing`, the one pairing: the map error over the draws both policies
survived); the **seed is the independent unit**, its clutter levels and draws nested in it (a
seed's worlds share waypoints, path, landmarks and zones). Fixed-sample intervals are cluster
intervals over seeds; the sequential design looks at per-seed means. Every metric's report
names its interval's method and level (``1 - alpha``), whether it holds at a data-dependent stop
(``anytime_valid``), the seeds behind it, the intraclass correlation of its per-world
differences within seeds and Kish's effective number of independent worlds. Runs go through the
benchmark's machinery (:func:`slam_gym.evaluation.run_jobs`: its executors, lock, error rows,
time limits, and ``results.jsonl`` keyed by job, so a killed comparison resumes without rerunning
a finished run). Statistics: :mod:`slam_gym.evaluation.paired`.

Two designs:

* **sequential** (``max_worlds``): worlds in batches of ``batch_seeds`` seeds at every clutter
  level, a look after each batch (from :data:`slam_gym.evaluation.paired.MIN_SEEDS` seeds on;
  :func:`look`, which runs :func:`slam_gym.evaluation.paired.sequential_decisions`), stopping
  at the first look that decides the question or at ``max_worlds``. After the stop every
  metric's interval is the one valid there: the design's for the declared metric, the
  confidence sequence (on per-seed means, tuned to the planned seeds) for the others.
  ``design`` chooses the interval of a look: ``"confidence-sequence"`` (the default; valid
  under any number of looks and any stopping, ``max_worlds`` only tunes where it is narrowest) or
  ``"group-sequential"`` (repeated confidence intervals of an O'Brien-Fleming-type design planned
  for ``max_worlds``: about half the worlds for the same question when the answer comes near
  ``max_worlds``, but ``max_worlds`` is then a commitment, not to be raised once rows are
  seen; success only). The looks are a function of the rows alone, so a rerun looks at the
  same batches and decides the same.
* **fixed** (``seeds``): that many seeds at every level, the fixed-sample intervals (cluster
  Bonett-Price for success, cluster bootstrap for the rest; ``anytime_valid`` false), the
  question (if any) answered on them.

The question: ``metric`` and ``margin`` (in the metric's reported unit: percentage points for
success and the NEES in-band fraction, metres for the map error, seconds of interface CPU,
points of return): is B *not worse* than A by more than ``margin``? ``better`` (the interval
above 0), ``not worse`` (above ``-margin``), ``worse`` (below ``-margin``) or ``undecided``,
oriented so that "worse" is a lower success or in-band fraction or return, or a higher map error
or CPU (:func:`slam_gym.evaluation.paired.decide`). Margin 0 asks superiority either way.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from filters.validation import check_choice, require

METRICS = ("success", "nees_in_band_fraction", "anees", "map_error_m", "interface_cpu_s",
           "return")
"""What a comparison reports, in this order (consistency and map error are the mission's)."""

UNIT_SCALE = {"success": 100.0, "nees_in_band_fraction": 100.0}
"""Rates are reported (and their margins given) in percentage points."""

UNITS = {"success": "pp", "nees_in_band_fraction": "pp", "anees": "", "map_error_m": "m",
         "interface_cpu_s": "s", "return": ""}

MAX_WORLDS = 100_000
"""The most worlds a comparison accepts (``max_worlds`` or seeds x levels)."""

BOOTSTRAP_SEED = 46
"""The cluster bootstrap's own generator: the same rows give the same intervals."""

SURVIVED_METRICS = frozenset({"map_error_m"})
"""Metrics paired over the draws both policies survived (:mod:`slam_gym.evaluation.pairing`)."""


@dataclass(frozen=True)
class Arm:
    """One side of a comparison: its label, the job's policy name and options, and what a
    worker process needs to build it (:class:`~slam_gym.evaluation.benchmarking.PolicyEntry`)."""

    label: str
    name: str
    options: dict = field(default_factory=dict)
    shipped: Any = None


@dataclass(frozen=True)
class ComparisonResult:
    """What :func:`compare` returns (and ``--json`` prints)."""

    a: str
    b: str
    decision: str | None
    question: dict | None
    worlds: int
    draws: int
    metrics: dict
    looks: list
    rows: list
    out: Path
    n_errors: int
    level: float = 0.95
    """Two-sided level of every interval (``1 - alpha``)."""
    seeds: int | None = None
    """The seeds run (the independent units; each at every clutter level)."""
    env_id: str | None = None
    env_kwargs: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "decision": self.decision, "question": self.question,
                "worlds": self.worlds, "seeds": self.seeds, "draws": self.draws,
                "level": self.level, "metrics": self.metrics, "looks": self.looks,
                "n_errors": self.n_errors, "out": str(self.out), "env_id": self.env_id,
                "env_kwargs": self.env_kwargs}


def resolve_arm(spec: Any, env_id: str | None = None) -> Arm:
    """A policy name, a ``package.module:attribute`` reference, a policy object, or the path of
    a learned model (a file ending in ``.zip``: policy ``learned`` with that model). ``env_id``:
    the env the arm runs in; ``learned`` by name runs the model shipped for it
    (:func:`policies.learned.resolve_model_path`)."""
    from slam_gym.evaluation.benchmarking import resolve_policies
    from slam_gym.evaluation.core import learned_options

    if isinstance(spec, (str, os.PathLike)) and str(spec).endswith(".zip"):
        path = str(spec)
        if not Path(path).is_file():
            raise FileNotFoundError(f"model {path!r} is invalid: no such file")
        resolve_policies(["learned"], path)  # loads it: a bad model fails before any run
        return Arm(str(spec), "learned", learned_options(path))
    (entry,) = resolve_policies([spec], env_id=env_id)
    options = learned_options(None, env_id) if entry.name == "learned" else {}
    if entry.digest is not None:
        options["policy_sha256"] = entry.digest
    return Arm(entry.name, entry.name, options, entry.shipped)


def paired_data(rows_a: list[dict], rows_b: list[dict], metric: str,
                worlds: list[tuple] | None = None):
    """The one pairing (:func:`slam_gym.evaluation.pairing.paired_worlds`) of ``metric`` over
    ``worlds`` ((level, seed); default every world either arm ran)."""
    from slam_gym.evaluation.pairing import paired_worlds

    return paired_worlds(rows_a, rows_b, metric, worlds=worlds)


def interval_labels(interval, differences) -> dict:
    """What an interval says about itself: its method, level, whether it holds at a
    data-dependent stop, and the clustering behind it (seeds, intraclass correlation, Kish's
    effective number of independent worlds)."""
    from slam_gym.evaluation import paired

    d = differences.differences
    icc = paired.intraclass_correlation(d, differences.clusters) if len(d) >= 2 else None
    return {"method": interval.method, "level": float(interval.level)
            if math.isfinite(interval.level) else None,
            "anytime_valid": bool(interval.anytime_valid),
            "seeds": int(np.unique(differences.cluster_ids).size),
            "icc": None if icc is None else float(icc),
            "effective_worlds": paired.effective_worlds(len(d), differences.clusters, icc)}


def fixed_interval(differences, metric: str, confidence: float):
    """The fixed-sample interval of one metric's per-world differences (any orientation), the
    seeds the clusters (:mod:`slam_gym.evaluation.pairing`): the cluster Bonett-Price interval
    for success (:func:`~slam_gym.evaluation.paired.matched_rate_interval` with the seeds'
    cluster-robust variance), the cluster bootstrap over seeds otherwise."""
    from slam_gym.evaluation import paired

    if metric in paired.RATE_METRICS:
        return paired.matched_rate_interval(differences.differences,
                                            clusters=differences.cluster_ids,
                                            confidence=confidence)
    return paired.cluster_bootstrap_interval(differences.differences, differences.strata,
                                             differences.cluster_ids, rng=BOOTSTRAP_SEED,
                                             confidence=confidence)


def sequential_interval(differences, metric: str, *, alpha: float, planned_seeds: int,
                        design: str = "confidence-sequence", look_seeds: list | None = None,
                        worlds_per_seed: int = 1):
    """The interval of one metric at a sequential look, on the per-seed means (the independent
    units): ``design``'s for the declared success metric, else the confidence sequence (valid
    at any stop, whatever metric decided it). Success's pseudo-worlds weigh as one of the
    ``worlds_per_seed`` worlds of a seed."""
    from slam_gym.evaluation import paired

    rate = metric in paired.RATE_METRICS
    units = paired.cluster_means(differences.differences, differences.cluster_ids)
    if design != "confidence-sequence" and not rate:
        design = "confidence-sequence"
    n = units.shape[-1]
    interval = paired.sequential_interval(
        units, design=design, planned_worlds=max(planned_seeds, n), alpha=alpha, rate=rate,
        look_worlds=[t for t in (look_seeds or [n]) if t <= n] or [n],
        pseudo_units=1.0 / max(1, worlds_per_seed))
    return interval


def metric_report(rows_a, rows_b, metric: str, worlds: list[tuple] | None = None,
                  confidence: float = 0.95, *, sequential: dict | None = None) -> dict:
    """One metric in its reported unit: ``a``, ``b`` (means over the paired worlds),
    ``difference`` and ``ci`` of B - A, ``worlds`` and ``seeds`` with values, ``left_out``
    worlds, and :func:`interval_labels`. Fixed-sample intervals (``anytime_valid`` false), or
    with ``sequential`` (``{"planned_seeds", "design", "look_seeds"}``, level ``confidence``)
    the sequential look's (:func:`sequential_interval`, ``anytime_valid`` true)."""
    scale = UNIT_SCALE.get(metric, 1.0)
    pw = paired_data(rows_a, rows_b, metric, worlds)
    diffs = pw.differences()
    report = {"a": None, "b": None, "difference": None, "ci": None, "worlds": len(diffs),
              "seeds": pw.n_clusters, "left_out": diffs.n_left_out, "method": None,
              "level": confidence, "anytime_valid": sequential is not None, "icc": None,
              "effective_worlds": None, "unit": UNITS[metric]}
    if metric in SURVIVED_METRICS:
        report["paired_over"] = "pairs of draws where both policies survived"
    if len(pw):
        report["a"] = float(scale * pw.a.mean())
        report["b"] = float(scale * pw.b.mean())
        report["difference"] = report["b"] - report["a"]
    if pw.n_clusters >= 2:
        if sequential is None:
            interval = fixed_interval(diffs, metric, confidence)
        else:
            interval = sequential_interval(diffs, metric, alpha=1.0 - confidence,
                                           planned_seeds=sequential["planned_seeds"],
                                           design=sequential.get("design",
                                                                 "confidence-sequence"),
                                           look_seeds=sequential.get("look_seeds"),
                                           worlds_per_seed=sequential.get("worlds_per_seed", 1))
        report["ci"] = [float(scale * interval.lo), float(scale * interval.hi)]
        report |= interval_labels(interval, diffs)
        report["level"] = confidence  # a repeated interval's level is over the design's looks
        if sequential is not None:
            report["estimate_per_seed_mean"] = float(scale * interval.estimate)
    return report


def oriented(metric: str, rows_a: list[dict], rows_b: list[dict],
             worlds: list[tuple] | None = None):
    """The declared metric's per-world differences with positive = B better, with their seeds."""
    from slam_gym.evaluation import paired

    return paired_data(rows_a, rows_b, metric, worlds).differences(
        lower_is_better=paired.metric_direction(metric) < 0)


def check_question(metric: str | None, margin: float | None) -> None:
    from slam_gym.evaluation import paired

    require(margin is None or metric is not None, "margin", margin,
            "given with --metric (the metric the margin is a distance in)")
    if metric is None:
        return
    require(metric in METRICS, "metric", metric, f"one of {list(METRICS)}")
    require(paired.metric_direction(metric) != 0, "metric", metric,
            "a metric with a direction (ANEES is reported, not decided: better is closer to 3; "
            "ask about nees_in_band_fraction)")
    require(margin is None or (isinstance(margin, (int, float)) and math.isfinite(margin)
                               and margin >= 0), "margin", margin, "a number >= 0")


def compare(
    a: Any,
    b: Any,
    *,
    metric: str | None = None,
    margin: float | None = None,
    env: Any = None,
    env_kwargs: Any = None,
    clutter_levels: Iterable[int] | None = None,
    draws: int = 2,
    seeds: int | None = None,
    max_worlds: int | None = None,
    design: str = "confidence-sequence",
    batch_seeds: int = 2,
    seed_start: int = 0,
    alpha: float = 0.05,
    out: str | os.PathLike = "out/compare",
    workers: int | None = None,
    executor: str = "process",
    ray_address: str | None = None,
    progress: bool = False,
    retry_errors: bool = False,
    rerun_changed: bool = False,
    run_timeout_s: float | None = None,
) -> ComparisonResult:
    """Compare policies ``a`` and ``b`` (module docstring) in ``env`` (a registered id, default
    ``SlamGym/HybridSLAM-v1``, or a :class:`~slam_gym.envs.spec.ResolvedEnv`) with
    ``env_kwargs`` over the id's own, at ``clutter_levels`` (None: the env's own). Every option
    is checked before any run, here and only here (``ValueError`` naming it; the command shows
    these messages)."""
    from slam_gym.evaluation import paired
    from slam_gym.evaluation.benchmarking import (
        check_draws,
        check_picklable,
        env_of,
        make_out_dir,
    )
    from slam_gym.evaluation.core import run_job
    from slam_gym.evaluation.executors import run_jobs
    from slam_gym.evaluation.jobs import Job

    check_question(metric, margin)
    check_choice("design", design, paired.SEQUENTIAL_DESIGNS)
    if design != "confidence-sequence":
        require(max_worlds is not None, "design", design,
                "'confidence-sequence' without max_worlds (a group-sequential design is planned "
                "for max_worlds worlds)")
    if max_worlds is not None and metric is not None:
        paired.check_design(design, metric in paired.RATE_METRICS)
    if metric is not None and margin is None:
        margin = 0.0
    spec = env_of(env, env_kwargs, clutter_levels)
    levels = list(spec.levels)
    draws = check_draws(draws)
    require(isinstance(batch_seeds, int) and not isinstance(batch_seeds, bool)
            and batch_seeds >= 1, "batch_seeds", batch_seeds, "an integer >= 1")
    batch_worlds = batch_seeds * len(levels)
    require(0 < alpha < 1, "alpha", alpha, "in (0, 1)")
    if max_worlds is not None:
        require(seeds is None, "seeds", seeds, "left out with max_worlds (the sequential design "
                "chooses how many worlds it runs)")
        require(metric is not None, "max_worlds", max_worlds,
                "given with a metric (the sequential design stops when its question is decided)")
        require(isinstance(max_worlds, int) and batch_worlds <= max_worlds <= MAX_WORLDS,
                "max_worlds", max_worlds,
                f"an integer in [{batch_worlds}, {MAX_WORLDS}] (at least one batch: "
                f"{batch_seeds} seeds x {len(levels)} clutter levels)")
        n_batches = max_worlds // batch_worlds
    else:
        seeds = 10 if seeds is None else seeds
        require(isinstance(seeds, int) and 2 <= seeds and seeds * len(levels) <= MAX_WORLDS,
                "seeds", seeds, f"an integer >= 2 with seeds x levels <= {MAX_WORLDS}")
        n_batches = 1
        batch_seeds = seeds
    require(isinstance(seed_start, int) and 0 <= seed_start
            and seed_start + n_batches * batch_seeds < 2**31, "seed_start", seed_start,
            "an integer >= 0 with every seed below 2**31")
    arm_a, arm_b = resolve_arm(a, spec.env_id), resolve_arm(b, spec.env_id)
    if executor != "serial":
        check_picklable((arm_a, arm_b), executor)
    out = make_out_dir(out)
    shipped = {arm.name: arm.shipped for arm in (arm_a, arm_b) if arm.shipped is not None}
    run_fn = functools.partial(run_job, policy_factories=shipped) if shipped else run_job

    def jobs_of(arm: Arm, seed_list: list[int]) -> list:
        return [Job.in_env("policy", arm.name, spec, level, seed, arm.options | {"draw": k})
                for seed in seed_list for level in levels for k in range(draws)]

    rows_a: list[dict] = []
    rows_b: list[dict] = []
    worlds: list[tuple[int, int]] = []
    looks: list[dict] = []
    look_seeds: list[int] = []  # the seeds with values at each decision look so far
    decision = None
    for batch in range(n_batches):
        first = seed_start + batch * batch_seeds
        seed_list = list(range(first, first + batch_seeds))
        ja, jb = jobs_of(arm_a, seed_list), jobs_of(arm_b, seed_list)
        same = [j.key for j in ja] == [j.key for j in jb]  # A against itself: run once
        rows = run_jobs(ja if same else ja + jb, run_fn, out, workers=workers,
                        executor=executor, ray_address=ray_address, progress=progress,
                        retry_errors=retry_errors, rerun_changed=rerun_changed,
                        run_timeout_s=run_timeout_s)
        rows_a += rows[:len(ja)]
        rows_b += rows[:len(ja)] if same else rows[len(ja):]
        worlds += [(level, seed) for seed in seed_list for level in levels]
        if metric is None:
            continue
        entry, look_seeds = look(rows_a, rows_b, worlds, metric, margin, alpha=alpha,
                                 planned_seeds=n_batches * batch_seeds if max_worlds else None,
                                 design=design, look_seeds=look_seeds)
        looks.append(entry)
        decision = entry["decision"]
        if decision != "undecided":
            break
    metrics, question = report(rows_a, rows_b, worlds, metric, margin, alpha=alpha,
                               planned_seeds=n_batches * batch_seeds if max_worlds else None,
                               design=design, look_seeds=look_seeds, looks=looks,
                               max_worlds=max_worlds)
    n_errors = sum(r.get("status") == "error" for r in rows_a + rows_b)
    return ComparisonResult(arm_a.label, arm_b.label, decision or ("undecided" if metric else None),
                            question, len(worlds), draws, metrics, looks, rows_a + rows_b, out,
                            n_errors, level=1.0 - alpha,
                            seeds=len({w[1] for w in worlds}), env_id=spec.env_id,
                            env_kwargs=spec.kwargs)


def look(rows_a: list[dict], rows_b: list[dict], worlds: list[tuple], metric: str,
         margin: float, *, alpha: float, planned_seeds: int | None,
         design: str = "confidence-sequence", look_seeds: list[int] | None = None
         ) -> tuple[dict, list[int]]:
    """One look at the question on the rows so far: ``(entry, look_seeds)``, the entry of
    ``looks`` (``worlds``, ``seeds``, ``decision``, ``oriented_ci``, ``method``) and the seed
    counts of the sequential looks so far.

    Fixed design (``planned_seeds`` None): the fixed-sample interval on all worlds. Sequential:
    :func:`slam_gym.evaluation.paired.sequential_decisions`, the loop the calibration tests
    check, on the per-seed means of the oriented differences (the seeds the independent units),
    its looks the seed counts so far; no look before :data:`~slam_gym.evaluation.paired.
    MIN_SEEDS` seeds, nor again at the seeds of the last one (a batch whose runs all failed
    adds none: it could only repeat that undecided look, and a group-sequential design's looks
    must add units)."""
    from slam_gym.evaluation import paired

    scale = UNIT_SCALE.get(metric, 1.0)
    seen = list(look_seeds or [])
    d = oriented(metric, rows_a, rows_b, worlds)
    n_seeds = int(np.unique(d.cluster_ids).size) if len(d) else 0
    entry = {"worlds": len(worlds), "seeds": len({w[1] for w in worlds}),
             "decision": "undecided", "oriented_ci": None}
    rate = metric in paired.RATE_METRICS
    if planned_seeds is None:
        if n_seeds < 2:
            return entry, seen
        interval = fixed_interval(d, metric, 1.0 - alpha)
        decision, lo, hi, method = (paired.decide(interval.lo, interval.hi, margin / scale),
                                    interval.lo, interval.hi, interval.method)
    else:
        if n_seeds < paired.MIN_SEEDS or (seen and n_seeds == seen[-1]):
            return entry, seen
        seen.append(n_seeds)
        units = paired.cluster_means(d.differences, d.cluster_ids)
        out = paired.sequential_decisions(
            units, margin=margin / scale, alpha=alpha, planned_worlds=max(planned_seeds, n_seeds),
            rate=rate, design=design, looks=seen,
            pseudo_units=1.0 / max(1, len({w[0] for w in worlds})))
        decision, lo, hi, method = out.decision, out.lo, out.hi, out.method
    entry |= {"decision": decision, "oriented_ci": [scale * lo, scale * hi], "method": method,
              "anytime_valid": planned_seeds is not None}
    return entry, seen


def report(rows_a: list[dict], rows_b: list[dict], worlds: list[tuple], metric: str | None,
           margin: float | None, *, alpha: float, planned_seeds: int | None,
           design: str = "confidence-sequence", look_seeds: list[int] | None = None,
           looks: list[dict] | None = None, max_worlds: int | None = None
           ) -> tuple[dict, dict | None]:
    """Every metric's report (:func:`metric_report` at level ``1 - alpha``: the fixed-sample
    intervals, or after a sequential run the intervals valid at its stop) and the question."""
    from slam_gym.evaluation import paired

    sequential = None if planned_seeds is None else {
        "planned_seeds": planned_seeds, "look_seeds": look_seeds,
        "worlds_per_seed": len({w[0] for w in worlds}),
        "design": design if metric in paired.RATE_METRICS else "confidence-sequence"}
    metrics = {}
    for m in METRICS:
        seq = None if sequential is None else (
            sequential if m == metric else sequential | {"design": "confidence-sequence"})
        metrics[m] = metric_report(rows_a, rows_b, m, worlds, confidence=1.0 - alpha,
                                   sequential=seq)
    question = None
    if metric is not None:
        last = (looks or [{}])[-1]
        question = {"metric": metric, "margin": margin, "unit": UNITS[metric],
                    "design": design if planned_seeds is not None else "fixed",
                    "max_worlds": max_worlds, "alpha": alpha,
                    "oriented_ci": last.get("oriented_ci"), "method": last.get("method"),
                    "anytime_valid": planned_seeds is not None,
                    "unit_of_decision": "seed" if planned_seeds is not None else "world "
                    "(intervals clustered by seed)",
                    "higher_is_better": paired.metric_direction(metric) > 0}
    return metrics, question


def plan(rows_a: list[dict], rows_b: list[dict], metric: str, margin: float, *,
         alpha: float = 0.05, power: float = 0.8, batch_worlds: int = 1) -> dict:
    """Worlds needed for ``metric`` at ``margin`` (reported unit), sequential and fixed, from the
    pilot's rows, under the clustered model: the pilot's per-seed means of the oriented
    differences are the independent units (:func:`slam_gym.evaluation.paired.plan_worlds` in
    seeds), and a seed brings the pilot's worlds per seed (its clutter levels). ``batch_worlds``
    (a batch's worlds) rounds the seeds up to whole batches."""
    from slam_gym.evaluation import paired

    check_question(metric, margin)
    scale = UNIT_SCALE.get(metric, 1.0)
    worlds = sorted({(r["clutter_level"], r["seed"]) for r in rows_a if r.get("status") == "ok"})
    d = oriented(metric, rows_a, rows_b, worlds)
    units = paired.cluster_means(d.differences, d.cluster_ids) if len(d) else np.zeros(0)
    require(units.size >= 2, "pilot", f"{units.size} seeds",
            "at least 2 seeds with values of both policies")
    per_seed = max(1, len({w[0] for w in worlds}))  # the clutter levels: worlds a seed brings
    batch_seeds = max(1, math.ceil(batch_worlds / per_seed))
    rate = metric in paired.RATE_METRICS
    icc = paired.intraclass_correlation(d.differences, d.cluster_ids)
    out = {"metric": metric, "margin": margin, "pilot_worlds": len(d),
           "pilot_seeds": int(units.size), "worlds_per_seed": per_seed,
           "pilot_icc": None if icc is None else float(icc),
           "pilot_mean_difference": float(scale * d.differences.mean()),
           "unit": "seed (its clutter levels and draws nested)"}
    if rate:
        out["pilot_discordant_worlds"] = int(np.sum(d.differences != 0))
    for sequential in (True, False):
        p = paired.plan_worlds(units, margin / scale, alpha=alpha, power=power,
                               sequential=sequential, rate=rate, batch_size=batch_seeds,
                               worlds_per_unit=1 if sequential else per_seed)
        out["sequential" if sequential else "fixed"] = {
            "worlds": p.worlds * per_seed, "seeds": p.worlds, "sd": float(scale * p.sd)}
    return out
