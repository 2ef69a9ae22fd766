"""One row pairing: two policies' result rows as paired per-world data, the seed as the cluster
(issue 56 item 1 and 3; issue 55 item 6). ``compare``, ``front``, the headroom report
(``scripts/results/task_headroom.py``) and the result scripts pair their rows here and nowhere
else.

The data. A run is one (scenario, clutter level, seed, filter draw) of one policy. Two runs of A
and B with the same key ran on the same world with the same filter numbers (common random
numbers): they are a *pair*. A *world* is (scenario, clutter level, seed); its draws are nested in
it. A *cluster* is (scenario, seed): the worlds of one seed at every clutter level share the
seed's waypoints, true path, landmarks and zones (only the clutter differs), so they are not
independent; the seeds are. Chosen over "every level its own seeds" because the committed rows
(issue 46's decided comparisons, issue 48's headroom) already run each seed at every level, and
the seed's shared world is then part of the pairing instead of noise between levels; the
statistics (:mod:`slam_gym.evaluation.paired`) resample and sum by cluster, with the clutter
levels and the draws nested in it.

Which pairs enter a metric (:func:`paired_value`): both runs finished (status ``ok``) and both have
a finite value. **The map error is defined for a run that survived** (``success`` true): a
failed run's map is not a map, so the *paired map error* is over the pairs of draws where both
policies survived, a world entering with the mean over those draws and leaving out (counted in
``n_left_out``) when no draw of it has both alive. With one draw this is "the worlds both
survived"; with K draws it keeps the draws where both survived rather than asking every draw of
both to survive (which, on issue 46's ``fixed-10s`` against ``fixed-10s-optimise``, keeps 42 of
96 worlds instead of 65). Every report gives the number of worlds and seeds beside it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from filters.validation import require

SURVIVED_ONLY = frozenset({"map_error_m"})
"""Metrics defined only for a run that survived (``success`` true)."""

ValueFn = Callable[[Mapping[str, Any], str], "float | None"]


def run_value(row: Mapping[str, Any], metric: str) -> float | None:
    """A run's raw value of ``metric`` (booleans as 0/1, ``interface_cpu_s`` as fusions +
    optimisations), or None where it has none or it is not finite."""
    from slam_gym.evaluation.summary import metric_values

    values = metric_values([row], metric)
    return values[0] if values else None


def paired_value(row: Mapping[str, Any], metric: str, value: ValueFn | None = None
                 ) -> float | None:
    """The value a run brings to a pair: None unless it finished (status ``ok``), None for a
    :data:`SURVIVED_ONLY` metric of a run that failed, else ``value(row, metric)`` (default
    :func:`run_value`) if finite."""
    if row.get("status", "ok") != "ok":
        return None
    if metric in SURVIVED_ONLY and row.get("success") is not True:
        return None
    v = (run_value if value is None else value)(row, metric)
    return None if v is None or not math.isfinite(float(v)) else float(v)


def run_key(row: Mapping[str, Any]) -> tuple:
    """(scenario, clutter level, seed, draw): what makes two policies' runs a pair."""
    draw = row.get("draw")
    if draw is None:
        draw = (row.get("options") or {}).get("draw", 0)
    return (str(row.get("scenario")), str(row.get("clutter_level")), int(row["seed"]),
            int(draw or 0))


@dataclass(frozen=True, eq=False)
class PairedRuns:
    """Pairs of runs of one metric: one entry per pair where both values are finite."""

    scenarios: np.ndarray
    levels: np.ndarray
    """``(p,)`` clutter levels as ints (the strata)."""
    seeds: np.ndarray
    draws: np.ndarray
    a: np.ndarray
    b: np.ndarray
    worlds: tuple
    """Every world (scenario, level, seed) either arm ran, in order: the denominator of
    ``n_left_out``."""

    def __len__(self) -> int:
        return int(self.a.shape[0])


def _level_int(level: str) -> int:
    try:
        return int(level)
    except ValueError:
        return -1  # a run without clutter levels (a real recording): one stratum


def pair_rows(rows_a: Sequence[Mapping[str, Any]], rows_b: Sequence[Mapping[str, Any]],
              metric: str, *, value: ValueFn | None = None,
              worlds: Sequence[tuple] | None = None) -> PairedRuns:
    """The pairs of ``rows_a`` and ``rows_b`` (module docstring) with their values of ``metric``
    (:func:`paired_value`: ``value(row, metric)``, default :func:`run_value`, of the finished
    runs, the survived ones for the map error). ``worlds`` restricts to these
    (scenario, level, seed) or (level, seed) worlds (default every world either arm has a row
    for). Two rows of one arm with the same key: ``ValueError`` (``rows_a``/``rows_b``)."""
    tables = []
    for name, rows in (("rows_a", rows_a), ("rows_b", rows_b)):
        table: dict[tuple, float | None] = {}
        for row in rows:
            key = run_key(row)
            require(key not in table, name, key, "one row per (scenario, level, seed, draw)")
            table[key] = paired_value(row, metric, value)
        tables.append(table)
    ta, tb = tables
    all_worlds = list(dict.fromkeys(k[:3] for k in (*ta, *tb)))
    if worlds is not None:
        wanted = {(str(w[0]), str(w[1]), int(w[2])) if len(w) == 3 else (str(w[0]), int(w[1]))
                  for w in worlds}
        all_worlds = [w for w in all_worlds if w in wanted or (w[1], w[2]) in wanted]
    keep_world = set(all_worlds)
    keys = [k for k in ta if k[:3] in keep_world and k in tb
            and ta[k] is not None and tb[k] is not None]
    return PairedRuns(
        scenarios=np.array([k[0] for k in keys], dtype=object),
        levels=np.array([_level_int(k[1]) for k in keys], dtype=int),
        seeds=np.array([k[2] for k in keys], dtype=np.int64),
        draws=np.array([k[3] for k in keys], dtype=np.int64),
        a=np.array([ta[k] for k in keys], dtype=float),
        b=np.array([tb[k] for k in keys], dtype=float),
        worlds=tuple(all_worlds))


@dataclass(frozen=True, eq=False)
class PairedWorlds:
    """Per-world means over the paired draws, with each world's stratum and cluster."""

    a: np.ndarray
    b: np.ndarray
    strata: np.ndarray
    """``(n,)`` clutter level of each world."""
    clusters: np.ndarray
    """``(n,)`` int cluster (seed) of each world."""
    draws: np.ndarray
    """``(n,)`` paired draws behind each world's means."""
    n_left_out: int
    """Worlds either arm ran that have no pair with both values."""

    def __len__(self) -> int:
        return int(self.a.shape[0])

    @property
    def n_clusters(self) -> int:
        return int(np.unique(self.clusters).size)

    def differences(self, *, lower_is_better: bool = False):
        """The oriented :class:`~slam_gym.evaluation.paired.WorldDifferences` (``b - a``, or
        ``a - b`` when lower is better) carrying strata and clusters."""
        from slam_gym.evaluation.paired import world_differences

        return world_differences(self.a, self.b, self.strata, clusters=self.clusters,
                                 lower_is_better=lower_is_better, n_left_out=self.n_left_out)


def world_means(levels: Any, seeds: Any, a: Any, b: Any, *, draws: Any = None,
                scenarios: Any = None, n_worlds: int | None = None) -> PairedWorlds:
    """Pairs (one per run) to worlds: per (scenario, level, seed) the mean of A and of B over its
    pairs (its ``draws``: nested in the world, never worlds of their own); the cluster is
    (scenario, seed), the levels nested in it. ``n_worlds`` (default the worlds found) counts
    the worlds that had to be there, for ``n_left_out``."""
    lv = np.asarray(levels, dtype=int)
    sd = np.asarray(seeds, dtype=np.int64)
    av, bv = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    require(lv.shape == sd.shape == av.shape == bv.shape and lv.ndim == 1, "a",
            f"shape {av.shape}", "one value per pair, like levels and seeds")
    dr = np.zeros(lv.shape, dtype=np.int64) if draws is None else np.asarray(draws, np.int64)
    require(dr.shape == lv.shape, "draws", f"shape {dr.shape}", "one draw per pair")
    sc = np.zeros(lv.shape, dtype=np.int64) if scenarios is None else np.unique(
        np.asarray(scenarios, dtype=str), return_inverse=True)[1].reshape(lv.shape)
    if lv.size == 0:
        empty = np.zeros(0)
        return PairedWorlds(empty, empty, empty.astype(int), empty.astype(int), empty.astype(int),
                            int(n_worlds or 0))
    world_keys = np.stack([sc, lv.astype(np.int64), sd], axis=1)  # the draw is not in the key
    worlds, world_of, counts = np.unique(world_keys, axis=0, return_inverse=True,
                                         return_counts=True)
    world_of = world_of.reshape(-1)
    mean_a = np.bincount(world_of, weights=av) / counts
    mean_b = np.bincount(world_of, weights=bv) / counts
    clusters = np.unique(worlds[:, [0, 2]], axis=0, return_inverse=True)[1].reshape(-1)
    found = int(worlds.shape[0])
    total = found if n_worlds is None else int(n_worlds)
    require(total >= found, "n_worlds", n_worlds, f">= the worlds with pairs ({found})")
    return PairedWorlds(mean_a, mean_b, worlds[:, 1].astype(int), clusters.astype(int),
                        counts.astype(int), total - found)


def paired_worlds(rows_a: Sequence[Mapping[str, Any]], rows_b: Sequence[Mapping[str, Any]],
                  metric: str, *, value: ValueFn | None = None,
                  worlds: Sequence[tuple] | None = None) -> PairedWorlds:
    """:func:`pair_rows` then :func:`world_means`: the one pairing of two policies' rows."""
    runs = pair_rows(rows_a, rows_b, metric, value=value, worlds=worlds)
    return world_means(runs.levels, runs.seeds, runs.a, runs.b, draws=runs.draws,
                       scenarios=runs.scenarios, n_worlds=len(runs.worlds))
