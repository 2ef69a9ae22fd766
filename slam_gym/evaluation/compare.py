"""``slam-gym compare A B`` as a Python function: two policies on the same worlds and filter
draws, paired by world, with a declared question answered by an anytime-valid sequential test.

>>> from slam_gym.evaluation.compare import compare
>>> result = compare("fixed-10s-optimise", "fixed-10s", metric="success", margin=5,
...                  draws=2, max_worlds=96, out="out/compare")          # doctest: +SKIP
>>> result.decision, result.worlds                                       # doctest: +SKIP

Design (issue 46). Worlds are (clutter level, seed); each runs ``draws`` filter draws per
policy, draw ``k`` the same numbers for both (the env's synchronised streams: common random
numbers). The unit of pairing is the world: per world and policy the mean over its draws (the
success rate, the mean map error, ...), per world the difference B - A. Runs go through the
benchmark's machinery (:func:`slam_gym.evaluation.run_jobs`: its executors, lock, error rows,
time limits, and ``results.jsonl`` keyed by job, so a killed comparison resumes without rerunning
a finished run). Statistics: :mod:`slam_gym.evaluation.paired`.

Two designs:

* **sequential** (``max_worlds``): worlds in batches of ``batch_seeds`` seeds at every clutter
  level, a look after each batch (from :data:`slam_gym.evaluation.paired.MIN_WORLDS` worlds on),
  stopping at the first look that decides the question or at ``max_worlds``. ``design`` chooses
  the interval of a look: ``"confidence-sequence"`` (the default; valid under any number of
  looks and any stopping, ``max_worlds`` only tunes where it is narrowest) or
  ``"group-sequential"`` (repeated confidence intervals of an O'Brien-Fleming-type design planned
  for ``max_worlds``: about half the worlds for the same question when the answer comes near
  ``max_worlds``, but ``max_worlds`` is then a commitment, not to be raised once rows are
  seen; success only). The looks are a function of the rows alone, so a rerun looks at the
  same batches and decides the same.
* **fixed** (``seeds``): that many seeds at every level, the fixed-sample intervals, the
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
"""The stratified bootstrap's own generator: the same rows give the same intervals."""


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
    env_id: str | None = None
    env_kwargs: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "decision": self.decision, "question": self.question,
                "worlds": self.worlds, "draws": self.draws, "metrics": self.metrics,
                "looks": self.looks, "n_errors": self.n_errors, "out": str(self.out),
                "env_id": self.env_id, "env_kwargs": self.env_kwargs}


def resolve_arm(spec: Any) -> Arm:
    """A policy name, a ``package.module:attribute`` reference, a policy object, or the path of
    a learned model (a file ending in ``.zip``: policy ``learned`` with that model)."""
    from slam_gym.evaluation.benchmarking import resolve_policies
    from slam_gym.evaluation.core import learned_options

    if isinstance(spec, (str, os.PathLike)) and str(spec).endswith(".zip"):
        path = str(spec)
        if not Path(path).is_file():
            raise FileNotFoundError(f"model {path!r} is invalid: no such file")
        resolve_policies(["learned"], path)  # loads it: a bad model fails before any run
        return Arm(str(spec), "learned", learned_options(path))
    (entry,) = resolve_policies([spec])
    options = learned_options(None) if entry.name == "learned" else {}
    if entry.digest is not None:
        options["policy_sha256"] = entry.digest
    return Arm(entry.name, entry.name, options, entry.shipped)


def world_table(rows: list[dict], metric: str) -> dict[tuple[int, int], float]:
    """(clutter level, seed) -> the mean over the world's draws of ``metric`` (ok rows with a
    finite value only; a world with none is absent)."""
    from slam_gym.evaluation.summary import metric_values

    by_world: dict[tuple[int, int], list[float]] = {}
    for row in rows:
        if row.get("status") != "ok":
            continue
        values = metric_values([row], metric)
        if values:
            by_world.setdefault((row["clutter_level"], row["seed"]), []).append(values[0])
    return {w: float(np.mean(v)) for w, v in by_world.items()}


def paired_arrays(rows_a: list[dict], rows_b: list[dict], metric: str, worlds: list[tuple]):
    """Per-world aggregates of A and B over ``worlds`` (NaN where missing) and their strata."""
    ta, tb = world_table(rows_a, metric), world_table(rows_b, metric)
    a = np.array([ta.get(w, np.nan) for w in worlds])
    b = np.array([tb.get(w, np.nan) for w in worlds])
    strata = np.array([-1 if w[0] is None else w[0] for w in worlds], dtype=int)  # -1: none
    return a, b, strata


def metric_report(rows_a, rows_b, metric: str, worlds: list[tuple], confidence: float = 0.95
                  ) -> dict:
    """``{"a", "b", "difference", "ci", "worlds", "left_out", "method"}`` of one metric in its
    reported unit; ``difference`` and ``ci`` are of B - A (fixed-sample intervals)."""
    from slam_gym.evaluation import paired

    scale = UNIT_SCALE.get(metric, 1.0)
    a, b, strata = paired_arrays(rows_a, rows_b, metric, worlds)
    diffs = paired.world_differences(a, b, strata)
    report = {"a": None, "b": None, "difference": None, "ci": None, "worlds": len(diffs),
              "left_out": diffs.n_left_out, "method": None, "unit": UNITS[metric]}
    keep = np.isfinite(a) & np.isfinite(b)
    if keep.any():
        report["a"] = float(scale * a[keep].mean())
        report["b"] = float(scale * b[keep].mean())
        report["difference"] = report["b"] - report["a"]
    if len(diffs) >= 2:
        if metric in paired.RATE_METRICS:
            interval = paired.matched_rate_interval(diffs.differences, confidence=confidence)
        else:
            interval = paired.stratified_bootstrap_interval(
                diffs.differences, diffs.strata, rng=BOOTSTRAP_SEED, confidence=confidence)
        report["ci"] = [float(scale * interval.lo), float(scale * interval.hi)]
        report["method"] = interval.method
    return report


def oriented(metric: str, a: np.ndarray, b: np.ndarray, strata: np.ndarray):
    """The declared metric's per-world differences with positive = B better."""
    from slam_gym.evaluation import paired

    return paired.world_differences(a, b, strata,
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
    arm_a, arm_b = resolve_arm(a), resolve_arm(b)
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
    look_worlds: list[int] = []  # the worlds with values at each decision look so far
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
        scale = UNIT_SCALE.get(metric, 1.0)
        d = oriented(metric, *paired_arrays(rows_a, rows_b, metric, worlds))
        first_look = paired.MIN_WORLDS if max_worlds is not None else 2
        if len(d) < first_look or (look_worlds and len(d) == look_worlds[-1]):
            # no sequential decision on fewer worlds (paired.MIN_WORLDS), nor a look again at
            # the worlds of the last one (a batch whose runs all failed adds none): it could only
            # repeat that undecided look, and a group-sequential design's looks must add worlds
            looks.append({"worlds": len(worlds), "decision": "undecided", "oriented_ci": None})
            continue
        rate = metric in paired.RATE_METRICS
        if max_worlds is not None:
            look_worlds.append(len(d))
            interval = paired.sequential_interval(d.differences, design=design,
                                                  planned_worlds=max_worlds,
                                                  look_worlds=look_worlds, alpha=alpha,
                                                  rate=rate)
        elif rate:
            interval = paired.matched_rate_interval(d.differences, confidence=1 - alpha)
        else:
            interval = paired.stratified_bootstrap_interval(
                d.differences, d.strata, rng=BOOTSTRAP_SEED, confidence=1 - alpha)
        decision = paired.decide(interval.lo, interval.hi, margin / scale)
        looks.append({"worlds": len(worlds), "decision": decision,
                      "oriented_ci": [scale * interval.lo, scale * interval.hi],
                      "method": interval.method})
        if decision != "undecided":
            break
    metrics = {m: metric_report(rows_a, rows_b, m, worlds, confidence=1 - alpha)
               for m in METRICS}
    question = None
    if metric is not None:
        question = {"metric": metric, "margin": margin, "unit": UNITS[metric],
                    "design": design if max_worlds is not None else "fixed",
                    "max_worlds": max_worlds, "alpha": alpha,
                    "oriented_ci": looks[-1].get("oriented_ci") if looks else None,
                    "higher_is_better": paired.metric_direction(metric) > 0}
    n_errors = sum(r.get("status") == "error" for r in rows_a + rows_b)
    return ComparisonResult(arm_a.label, arm_b.label, decision or ("undecided" if metric else None),
                            question, len(worlds), draws, metrics, looks, rows_a + rows_b, out,
                            n_errors, spec.env_id, spec.kwargs)


def plan(rows_a: list[dict], rows_b: list[dict], metric: str, margin: float, *,
         alpha: float = 0.05, power: float = 0.8, batch_worlds: int = 1) -> dict:
    """Worlds needed for ``metric`` at ``margin`` (reported unit), sequential and fixed, from the
    pilot's rows (:func:`slam_gym.evaluation.paired.plan_worlds`)."""
    from slam_gym.evaluation import paired

    check_question(metric, margin)
    scale = UNIT_SCALE.get(metric, 1.0)
    worlds = sorted({(r["clutter_level"], r["seed"]) for r in rows_a if r.get("status") == "ok"})
    d = oriented(metric, *paired_arrays(rows_a, rows_b, metric, worlds))
    require(len(d) >= 2, "pilot", len(d), "at least 2 worlds with values of both policies")
    rate = metric in paired.RATE_METRICS
    out = {"metric": metric, "margin": margin, "pilot_worlds": len(d),
           "pilot_mean_difference": float(scale * d.differences.mean())}
    if rate:
        out["pilot_discordant_worlds"] = int(np.sum(d.differences != 0))
    for sequential in (True, False):
        p = paired.plan_worlds(d.differences, margin / scale, alpha=alpha, power=power,
                               sequential=sequential, rate=rate, batch_size=batch_worlds)
        out["sequential" if sequential else "fixed"] = {"worlds": p.worlds,
                                                         "sd": float(scale * p.sd)}
    return out
