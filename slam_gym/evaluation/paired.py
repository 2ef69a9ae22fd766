"""Paired statistics of ``slam-gym compare A B`` (issues 46 and 56): fixed-sample intervals, an
anytime-valid sequential decision and the number of worlds to plan, the seed the independent unit.

The data (docs/ARCHITECTURE.md, "Paired comparison statistics"): policies A and B run on the same
worlds, a world being (clutter level, seed), with K filter draws per world and policy under common
random numbers. Rows are paired once, by :mod:`slam_gym.evaluation.pairing` (per (level, seed,
draw); the map error over the draws both policies survived), and averaged per world: ``d_w``
oriented so that positive = B better (:func:`world_differences`: ``b - a`` where higher is better,
``a - b`` where lower is better). **The seed is the cluster**, its clutter levels and draws nested
in it (issue 56): a seed's worlds at the four levels share its waypoints, true path, landmarks and
zones, so they are not independent, and treating them as such understated the variance where the
seed decides the outcome (the best rule on ZonesStarved-v1 succeeds at all four levels or none on
6 of 10 seeds). Chosen over "every level its own seeds" because the committed rows run every seed
at every level and the seed's shared world then cancels in the pairing. Every interval here is a
cluster interval over seeds (Liang & Zeger 1986); beside each, ``compare`` reports the one-way
ANOVA intraclass correlation of ``d_w`` within seeds (:func:`intraclass_correlation`, Donner
1986) and Kish's effective number of independent worlds ``N / (1 + (m0 - 1) ICC)``
(:func:`effective_worlds`).

What each function computes
---------------------------
- :func:`cluster_bootstrap_interval` (continuous metrics, fixed sample). Estimate: the mean of
  all ``d_w`` (``sum_g T_g / sum_g m_g``, ``T_g`` a seed's total over its ``m_g`` worlds).
  Interval: ``scipy.stats.bootstrap`` resampling whole seeds (the seeds' indices are its samples,
  the statistic the ratio of the resampled totals and sizes), stratified when clusters sit in
  one clutter level each (the design where every level has its own seeds; a seed spanning levels
  is resampled with them), percentile method. Two published small-sample corrections: the seeds'
  totals are first moved to ``r m_g + sqrt(G/(G-1)) (T_g - r m_g)`` (Davison & Hinkley 1997,
  ch. 3, adjusted values, here for a ratio: the resampled variance is the cluster-robust CR1
  one), and the quantiles are taken at Hesterberg's (2015) expanded level ``2 Phi(t_{(1+c)/2,
  G-S}) - 1`` (G seeds, S strata; Cameron & Miller 2015 on t with G - 1 degrees of freedom).
  Percentile rather than BCa because the tests measured it closer to nominal (below).
- :func:`matched_rate_interval` (success, fixed sample). The adjusted Wald interval of Bonett &
  Price (2012) for matched proportions (add 1 to each discordant cell, ``n' = n + 2``; Agresti &
  Min 2005 add 1/2 to all four cells: ``pseudo_weight=0.5``), written as pseudo-worlds at +1 and
  -1 among the per-world differences, with the cluster-robust variance over seeds::

      mean' = sum(d_w) / (n + 2)
      var'  = G / (G - 1) (sum_g (T_g - mean' m_g)^2 + 2 w + 2 mean'^2) / (n + 2)^2
      mean' +- t_{(1+c)/2, G-1} sqrt(var')          (clipped to [-1, 1])

  Every world its own cluster and without the small-sample correction (CR1 factor, t) it is the
  published interval exactly (a test checks both weights against the 2x2 formulas); the cluster
  version is ours. Bonett-Price rather than Agresti-Min because, when B only ever loses at a few
  per cent, Agresti-Min's interval missed the truth too often (measured below).
- :func:`confidence_sequence` (sequential, any metric, on per-seed means). The asymptotic
  confidence sequence of Waudby-Smith, Arbour, Sinha, Kennedy & Ramdas (2021), arXiv:2103.06476,
  with its two-sided normal-mixture boundary (Robbins 1970)::

      mean_t +- sd_t sqrt(2 (t rho^2 + 1) / (t^2 rho^2) log(sqrt(t rho^2 + 1) / alpha))

  ``P(exists t: true mean outside) <= alpha`` asymptotically, so it may be looked at after every
  batch and stopped at any data-dependent time. Its units are the seeds (:func:`cluster_means`:
  the per-seed mean differences, i.i.d. across seeds). ``rho`` makes it narrowest at the planned
  number of seeds ``t*`` (:func:`cs_rho`: ``t* rho^2 = -W_{-1}(-alpha^2 / e) - 1``, Lambert's W
  from ``scipy.special``), where its half-width is ``c(alpha) sd / sqrt(t*)``, ``c(0.05) =
  3.04`` (:func:`cs_multiplier`). For success the moments are those of the units with the
  pseudo-worlds above, each the size of one world (``pseudo_units = 1 / worlds per seed``), so
  zero discordance still gives a finite, shrinking width. It pools the clutter levels: each unit
  already averages its seed's levels, so the levels' differences do not enter its variance.
- :func:`group_sequential_bounds` and :func:`repeated_confidence_interval` (sequential, success
  only: ``design="group-sequential"``). A design planned for ``planned_worlds`` units (seeds), its
  looks at information fractions ``n_k / planned``: each side spends Lan & DeMets' (1983)
  O'Brien-Fleming-type function at ``alpha / 2`` (:func:`obrien_fleming_spending`, gsDesign's
  ``sfLDOF``), bounds ``c_k`` by Armitage, McPherson & Rowe's (1969) recursion, and a look's
  interval the repeated confidence interval ``mean +- c_k sd / sqrt(t)`` (Jennison & Turnbull
  1989) on the units' moments as above. The plan is a commitment (raising ``planned`` after
  seeing rows voids it), and its Wald intervals are tight enough for skew to show, so it is
  offered for success only (:func:`check_design`).
- :func:`decide`: the decision rule below on any ``[lo, hi]``.
- :func:`sequential_decisions`: **the one sequential loop**. ``compare`` calls it after every
  batch on the per-seed means so far with its looks (the seed counts after each batch,
  :func:`slam_gym.evaluation.compare.look`); the calibration tests call it on simulated units.
  No decision before :data:`MIN_SEEDS` = 16 seeds; vectorised over leading axes.
- :func:`plan_worlds`: units (seeds) needed to decide ``not worse`` with probability ``power``
  when the true difference is ``expected_difference``, from a pilot's per-seed means (the
  clustered model: their SD holds the seed effect). Continuous: ``n = ((k + z_power) s /
  (expected_difference + margin))^2`` with ``k = z_{1-alpha/2}`` (fixed) or ``c(alpha)``
  (sequential, tuned to ``t* = n``); success: the same condition with the pseudo-worlds, for
  seeds of ``worlds_per_unit`` worlds; ``compare --plan`` multiplies by the clutter levels.

The decision rule
-----------------
On a two-sided ``1 - alpha`` interval or confidence sequence ``[lo, hi]`` of the oriented mean
difference (positive = B better) and a margin ``m >= 0``, in this order: ``better`` if
``lo > 0``; ``not worse`` if ``lo > -m``; ``worse`` if ``hi < -m``; else ``undecided``. It is a
non-inferiority test, not an equivalence test (that would be two one-sided tests against
``-m`` and ``+m``). Its error: when the true difference is ``-m`` (or lower), a ``better``/``not
worse`` verdict has probability at most ``alpha / 2`` nominally for a fixed interval, and at most
``alpha`` for the sequence over all looks together (the tests check this ``alpha``). Orientation
(:func:`metric_direction`): success, NEES in-band fraction and return, higher is better; map
error and interface CPU, lower is better; ANEES is reported as ``b - a`` without a decision.

Written here, and why
---------------------
From libraries: the bootstrap's resampling and percentile/BCa quantiles
(``scipy.stats.bootstrap``), the quantiles (``scipy.stats.norm``, ``scipy.stats.t``), Lambert's W
(``scipy.special``), root finding (``scipy.optimize.brentq``). Written here, because no installed,
maintained Python library has them: the cluster adjusted-Wald interval (statsmodels, not a
dependency, has McNemar's test and intervals for independent proportions, not this one), the
cluster-robust sums, ICC and Kish's effective size (a few lines each; statsmodels' MixedLM
would be a new dependency for a variance ratio), the small-sample corrections around the
bootstrap call, the asymptotic confidence sequence (its authors publish R code), the
group-sequential bounds (R's gsDesign and rpact have them), the decision rule and the plan.
Each is checked by simulation in ``tests/slam_gym/test_paired.py``; each calibration test names
the mutation it was checked against (it fails under it).

Measured by those tests (seeded; Monte Carlo standard error 0.7 pp at 95 % over 1 000 trials,
0.35 pp over 4 000):
- cluster bootstrap, map errors of 3 draws on 24 seeds x 4 levels (B 20 % lower, 10 % of runs
  without a value, skewness ~1, excess kurtosis ~9): coverage 0.931; on 12 seeds x 4 levels 0.950
  (BCa 0.930); 8 seeds with a strong seed effect 0.952 (0.88 without the small-sample
  correction); 12 seeds, strong seed effect 0.938 (0.72 with the levels as independent worlds);
  every level its own 6 seeds, level means 90x apart: 0.953 (1.000 ignoring the strata);
- success, worlds independent (1 or 3 draws, 40-96 worlds, moderate, rare and one-directional
  discordance, clustered draws): coverage 0.945-1.000; Agresti-Min's weight 0.921 where B only
  loses 7 pp on 80 worlds; with a strong seed effect (10 or 20 seeds x 4 levels x 2 draws)
  0.961 / 0.957, against 0.75 / 0.74 with the levels as independent worlds and 0.60 with the
  draws as independent worlds;
- sequential, true difference exactly -5 pp = -margin: ``not worse`` in 0.000-0.026 of 4 000
  comparisons (sequence) and 0.011-0.052 (group-sequential) on worlds as units; on seeds as
  units with a strong seed effect 0.015 / 0.037; left-skewed continuous differences 0.040 /
  0.034; normal units, margin 0, looks every 2 seeds from 16 to 100: two-sided error 0.025
  (0.050 with the boundary 10 % narrower);
- identical arms (no discordant seed, 4 levels a seed) decide ``not worse`` at 5 pp after 44
  seeds (176 worlds);
- group-sequential bounds equal gsDesign's for five looks (to 1e-3); on 200 000 Brownian paths
  the crossing probability is alpha within 3 MC SE;
- plans: fixed 0.81 power for 0.80 planned (271 seeds; 93 if the levels were independent
  worlds, power 0.31); sequential at least 0.80.
Outside what the tests assert: differences of skewness 6 (lognormal sigma 1) pushed the
sequence's false ``not worse`` to 0.12-0.13 on worlds as units; intervals resting on a central
limit theorem need more seeds than this when a metric has rare huge values.

References: Efron (1987) JASA 82, 171-185; Davison & Hinkley (1997) Bootstrap Methods and their
Application, CUP; Hesterberg (2015) Am. Stat. 69, 371-386; Cameron & Miller (2015) J. Human
Resources 50, 317-372; Donner (1986) Int. Stat. Rev. 54, 67-82; Kish (1965) Survey Sampling,
Wiley; Agresti & Min (2005) Stat. Med. 24, 729-740; Bonett & Price (2012) J. Educ. Behav. Stat.
37, 479-488; Liang & Zeger (1986) Biometrika 73, 13-22; Lan & DeMets (1983) Biometrika 70,
659-663; Armitage, McPherson & Rowe (1969) J. R. Stat. Soc. A 132, 235-244; Jennison & Turnbull
(1989) J. R. Stat. Soc. B 51, 305-361, and (2000) Group Sequential Methods with Applications to
Clinical Trials, CRC; Robbins (1970) Ann. Math. Statist. 41, 1397-1409; Waudby-Smith, Arbour,
Sinha, Kennedy & Ramdas (2021) arXiv:2103.06476.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import special, stats

from filters.validation import check_choice, check_int_range, check_range, require

HIGHER_IS_BETTER = frozenset({"success", "nees_in_band_fraction", "return"})
"""Metrics whose oriented difference is ``b - a``."""

LOWER_IS_BETTER = frozenset({"map_error_m", "interface_cpu_s"})
"""Metrics whose oriented difference is ``a - b``."""

REPORT_ONLY = frozenset({"anees"})
"""Metrics reported as ``b - a`` without a decision (ANEES: better is closer to 3, no direction)."""

RATE_METRICS = frozenset({"success"})
"""0/1 metrics: their intervals are :func:`matched_rate_interval` / ``rate=True``."""

DECISIONS = ("better", "not worse", "worse", "undecided")
"""The outcomes of :func:`decide`, in the order its rule checks them."""

BOOTSTRAP_METHODS = ("percentile", "BCa", "basic")

MIN_SEEDS = 16
"""No sequential decision before this many independent units (seeds;
:func:`sequential_decisions`)."""


@dataclass(frozen=True, eq=False)
class WorldDifferences:
    """Per-world oriented differences of one metric (positive = B better), their strata and
    their clusters (:mod:`slam_gym.evaluation.pairing`: the seed)."""

    differences: np.ndarray
    """``(n,)`` finite ``d_w``."""
    strata: np.ndarray
    """``(n,)`` int stratum (clutter level) of each world."""
    n_left_out: int
    """Worlds dropped because either arm had no (finite) value."""
    clusters: np.ndarray | None = None
    """``(n,)`` int cluster (seed) of each world; None: every world its own cluster."""

    def __len__(self) -> int:
        return int(self.differences.shape[0])

    @property
    def cluster_ids(self) -> np.ndarray:
        """The clusters, every world its own where none were given."""
        return np.arange(len(self)) if self.clusters is None else self.clusters


@dataclass(frozen=True)
class Interval:
    """An estimate of the mean difference with its two-sided interval.

    Fields are floats for one comparison, arrays for a batch (leading axes of the input)."""

    estimate: Any
    lo: Any
    hi: Any
    n_worlds: int
    level: float
    """Two-sided confidence (``1 - alpha`` for a confidence sequence)."""
    method: str
    n_clusters: int | None = None
    """The independent units (seeds) behind it; None: every world its own."""
    anytime_valid: bool = False
    """True for an interval that holds at a data-dependent stopping time (a confidence
    sequence, or a group-sequential design's repeated interval over its looks)."""


@dataclass(frozen=True, eq=False)
class SequentialOutcome:
    """The result of :func:`sequential_decisions`: the first decided look, or the last look."""

    decision: Any
    """A :data:`DECISIONS` string (array of them for a batch)."""
    n_worlds: Any
    """Worlds seen at that look."""
    estimate: Any
    lo: Any
    hi: Any
    looks: tuple[int, ...]
    """The numbers of units (seeds) at which the sequence was looked at."""
    method: str = "asymptotic-cs"
    """The interval of the looks (:data:`SEQUENTIAL_DESIGNS`' ``method`` names)."""


@dataclass(frozen=True)
class WorldPlan:
    """The number of worlds :func:`plan_worlds` asks for, and what it was computed from."""

    worlds: int
    sd: float
    """The pilot's per-world standard deviation of the differences (``ddof=1``)."""
    effect: float
    """``expected_difference + margin``: the distance to the non-inferiority bound."""
    multiplier: float
    """``k``: ``z_{1-alpha/2}`` (fixed) or ``c(alpha)`` (sequential)."""
    pilot_worlds: int
    sequential: bool


def metric_direction(metric: str) -> int:
    """+1 if higher is better, -1 if lower is better, 0 if reported without a decision."""
    known = HIGHER_IS_BETTER | LOWER_IS_BETTER | REPORT_ONLY
    check_choice("metric", metric, sorted(known))
    if metric in HIGHER_IS_BETTER:
        return 1
    return -1 if metric in LOWER_IS_BETTER else 0


def world_differences(a: Any, b: Any, strata: Any = None, *, clusters: Any = None,
                      lower_is_better: bool = False, n_left_out: int = 0) -> WorldDifferences:
    """Oriented per-world differences from per-world aggregates ``a`` and ``b`` (``(n,)`` each).

    ``d_w = b_w - a_w`` (``a_w - b_w`` if ``lower_is_better``); a world where either value is not
    finite is left out and counted in ``n_left_out`` (added to the given ``n_left_out``: worlds
    dropped before). ``strata`` and ``clusters`` (``(n,)`` ints; default all 0, and every world
    its own cluster) follow their worlds."""
    a_ = np.asarray(a, dtype=float)
    b_ = np.asarray(b, dtype=float)
    require(a_.ndim == 1, "a", f"shape {a_.shape}", "a 1-D array")
    require(a_.size >= 1 or n_left_out > 0, "a", f"shape {a_.shape}", "a non-empty 1-D array")
    require(b_.shape == a_.shape, "b", f"shape {b_.shape}", f"the shape of a, {a_.shape}")
    labels = []
    for name, given in (("strata", strata), ("clusters", clusters)):
        if given is None:
            labels.append(None)
            continue
        v = np.asarray(given)
        require(v.shape == a_.shape, name, f"shape {v.shape}", f"the shape of a, {a_.shape}")
        require(v.size == 0 or np.issubdtype(v.dtype, np.integer), name, f"dtype {v.dtype}",
                "integers")
        labels.append(v.astype(int))
    s = np.zeros(a_.shape, dtype=int) if labels[0] is None else labels[0]
    keep = np.isfinite(a_) & np.isfinite(b_)
    d = (a_ - b_) if lower_is_better else (b_ - a_)
    d, s = d[keep], s[keep]
    c = None if labels[1] is None else labels[1][keep]
    for array in (d, s, c):
        if array is not None:
            array.flags.writeable = False
    return WorldDifferences(differences=d, strata=s, clusters=c,
                            n_left_out=int(n_left_out) + int((~keep).sum()))


def cluster_index(clusters: Any, n: int) -> tuple[np.ndarray, int]:
    """``(n,)`` cluster labels (None: every world its own) as indices 0..G-1, and G."""
    if clusters is None:
        return np.arange(n), n
    c = np.asarray(clusters)
    require(c.shape == (n,), "clusters", f"shape {c.shape}", f"one label per world, ({n},)")
    require(np.issubdtype(c.dtype, np.integer), "clusters", f"dtype {c.dtype}", "integers")
    labels, index = np.unique(c, return_inverse=True)
    return index.reshape(-1), int(labels.size)


def cluster_sums(values: np.ndarray, index: np.ndarray, g: int) -> np.ndarray:
    """``(..., G)`` sums over the last axis of ``values`` ``(..., n)`` by cluster ``index``."""
    order = np.argsort(index, kind="stable")
    sorted_index = index[order]
    starts = np.flatnonzero(np.r_[True, sorted_index[1:] != sorted_index[:-1]])
    out = np.zeros(values.shape[:-1] + (g,))
    out[..., sorted_index[starts]] = np.add.reduceat(values[..., order], starts, axis=-1)
    return out


def cluster_means(differences: Any, clusters: Any = None) -> np.ndarray:
    """Per-cluster means ``(..., G)`` of per-world differences ``(..., n)`` (clusters in sorted
    label order): the independent units a sequential look or a plan counts."""
    d = np.asarray(differences, dtype=float)
    index, g = cluster_index(clusters, d.shape[-1])
    return cluster_sums(d, index, g) / np.bincount(index, minlength=g)


def intraclass_correlation(differences: Any, clusters: Any = None) -> float | None:
    """The one-way ANOVA estimate of the intraclass correlation of the per-world differences
    within clusters (seeds), for unequal cluster sizes (Donner 1986): ``(MSB - MSW) / (MSB +
    (m0 - 1) MSW)``, ``m0 = (N - sum m_g^2 / N) / (G - 1)``. None where undefined (fewer than 2
    clusters, no cluster with 2 worlds, or no variance); negative values are returned as they
    are (the clusters vary less than chance), :func:`effective_worlds` reads them as 0."""
    d = np.asarray(differences, dtype=float).ravel()
    index, g = cluster_index(clusters, d.size)
    n = d.size
    if g < 2 or g >= n:
        return None
    m = np.bincount(index, minlength=g).astype(float)
    means = np.bincount(index, weights=d, minlength=g) / m
    msb = float(np.sum(m * (means - d.mean()) ** 2) / (g - 1))
    msw = float(np.sum((d - means[index]) ** 2) / (n - g))
    m0 = (n - float(np.sum(m * m)) / n) / (g - 1)
    denom = msb + (m0 - 1.0) * msw
    if not denom > 0.0:
        return None
    return (msb - msw) / denom


def effective_worlds(n_worlds: int, clusters: Any = None, icc: float | None = None) -> float:
    """Kish's effective number of independent worlds, ``N / (1 + (m0 - 1) max(icc, 0))``, ``m0``
    the ANOVA's average cluster size (:func:`intraclass_correlation`); ``N`` with no ICC."""
    if icc is None or n_worlds < 2:
        return float(n_worlds)
    index, g = cluster_index(clusters, n_worlds)
    m = np.bincount(index, minlength=g).astype(float)
    m0 = (n_worlds - float(np.sum(m * m)) / n_worlds) / max(g - 1, 1)
    return float(n_worlds / (1.0 + (m0 - 1.0) * max(icc, 0.0)))


def _differences(differences: Any, *, min_worlds: int = 2, rate: bool = False,
                 one_d: bool = False, name: str = "differences") -> np.ndarray:
    d = np.asarray(differences, dtype=float)
    if one_d:
        require(d.ndim == 1, name, f"shape {d.shape}", "a 1-D array")
    require(d.ndim >= 1 and d.shape[-1] >= min_worlds, name, f"shape {d.shape}",
            f"an array with at least {min_worlds} worlds on its last axis")
    require(bool(np.isfinite(d).all()), name, "non-finite values",
            "finite (leave such worlds out with world_differences)")
    if rate:
        require(bool((np.abs(d) <= 1.0).all()), name, "values outside [-1, 1]",
                "per-world rate differences in [-1, 1]")
    return d


def _confidence(confidence: float) -> float:
    return check_range("confidence", confidence, 0.0, 1.0, low_open=True, high_open=True)


def _alpha(alpha: float) -> float:
    return check_range("alpha", alpha, 0.0, 1.0, low_open=True, high_open=True)


def _merge_small_strata(strata: np.ndarray) -> np.ndarray:
    """Relabel so that every stratum has >= 2 clusters: a stratum with one joins the next
    clutter level present (the previous one for the highest)."""
    s = strata.copy()
    while True:
        levels, counts = np.unique(s, return_counts=True)
        small = np.flatnonzero(counts < 2)
        if len(levels) < 2 or small.size == 0:
            return s
        i = int(small[0])
        j = i + 1 if i + 1 < len(levels) else i - 1
        s[s == levels[i]] = levels[j]


MIXED_STRATUM = -(2**31)
"""The stratum of a cluster whose worlds span several clutter levels (a seed run at every
level): such clusters are resampled together, the levels nested in them."""


def cluster_strata(strata: np.ndarray, index: np.ndarray, g: int) -> np.ndarray:
    """``(G,)`` the stratum of each cluster: its worlds' clutter level where they share one,
    else :data:`MIXED_STRATUM`."""
    lo = np.full(g, np.iinfo(np.int64).max)
    hi = np.full(g, np.iinfo(np.int64).min)
    np.minimum.at(lo, index, strata)
    np.maximum.at(hi, index, strata)
    return np.where(lo == hi, lo, MIXED_STRATUM)


def cluster_bootstrap_interval(differences: Any, strata: Any = None, clusters: Any = None, *,
                               rng: np.random.Generator | int, confidence: float = 0.95,
                               n_resamples: int = 9999, method: str = "percentile",
                               small_sample_correction: bool = True) -> Interval:
    """Stratified cluster bootstrap interval of the mean per-world difference (fixed sample).

    ``differences`` ``(n,)`` finite per-world differences (draws already averaged), ``strata``
    their clutter levels (default one), ``clusters`` their seeds (default every world its own).
    Estimate: the mean of all ``d_w`` (``sum_g T_g / sum_g m_g``, ``T_g`` a cluster's total over
    its ``m_g`` worlds). Resampled: whole clusters, by ``scipy.stats.bootstrap`` (the clusters'
    indices as its samples), within each cluster stratum (a cluster's clutter level, or one
    stratum for clusters that span levels; a stratum of one cluster joins the next level), the
    estimate over a stratum the ratio of its resampled totals and sizes, weighted by the
    stratum's share of worlds. ``small_sample_correction``: the clusters' totals are first
    moved to ``r_s m_g + sqrt(G_s / (G_s - 1)) (T_g - r_s m_g)`` (Davison & Hinkley's adjusted
    values for a ratio, ``r_s`` the stratum's ratio: the resampled variance is then the
    cluster-robust CR1 one) and the level asked is ``2 Phi(t_{(1+c)/2, G - S}) - 1`` (Hesterberg
    2015; G clusters, S strata: the width of a t-interval with the cluster count's degrees of
    freedom, Cameron & Miller 2015). Differences constant within every stratum give the
    estimate as the interval."""
    d = _differences(differences, one_d=True)
    conf = _confidence(confidence)
    check_int_range("n_resamples", n_resamples, 99)
    check_choice("method", method, BOOTSTRAP_METHODS)
    require(isinstance(rng, (np.random.Generator, int, np.integer)) and not isinstance(rng, bool),
            "rng", rng, "a numpy Generator or an int seed")
    s = np.zeros(d.shape, dtype=int) if strata is None else np.asarray(strata)
    require(s.shape == d.shape, "strata", f"shape {s.shape}",
            f"the shape of differences, {d.shape}")
    require(np.issubdtype(s.dtype, np.integer), "strata", f"dtype {s.dtype}", "integers")
    index, g = cluster_index(clusters, d.size)
    require(g >= 2, "clusters", f"{g} cluster", "at least 2 clusters (seeds)")
    totals = np.bincount(index, weights=d, minlength=g)
    sizes = np.bincount(index, minlength=g).astype(float)
    cs = _merge_small_strata(cluster_strata(s.astype(np.int64), index, g))
    levels = np.unique(cs)
    members = [np.flatnonzero(cs == level) for level in levels]
    weights = np.array([sizes[k].sum() for k in members]) / d.size
    estimate = float(totals.sum() / sizes.sum())
    name = f"cluster-bootstrap-{method}"
    ratios = [totals[k].sum() / sizes[k].sum() for k in members]
    scale_ = max(1.0, float(np.abs(d).max()))
    if all(np.abs(totals[k] - r * sizes[k]).max() <= 1e-12 * scale_ * sizes[k].max()
           for k, r in zip(members, ratios, strict=True)):  # no cluster varies: nothing to resample
        return Interval(estimate, estimate, estimate, int(d.size), conf, name, g)
    level_asked = conf
    if small_sample_correction:
        for k, r in zip(members, ratios, strict=True):
            totals[k] = r * sizes[k] + math.sqrt(k.size / (k.size - 1.0)) * (totals[k]
                                                                            - r * sizes[k])
        q = stats.t.ppf(0.5 + conf / 2.0, g - levels.size)
        level_asked = float(2.0 * stats.norm.cdf(q) - 1.0)
        name += "-corrected"

    def statistic(*groups: np.ndarray, axis: int = -1) -> np.ndarray:
        out = 0.0
        for w, group in zip(weights, groups, strict=True):
            k = group.astype(np.int64)
            out = out + w * totals[k].sum(axis=axis) / sizes[k].sum(axis=axis)
        return out

    samples = tuple(k.astype(float) for k in members)
    res = stats.bootstrap(samples, statistic, n_resamples=n_resamples, vectorized=True,
                          paired=False, confidence_level=level_asked, method=method,
                          rng=np.random.default_rng(rng))
    lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return Interval(estimate, lo, hi, int(d.size), conf, name, g)


def _augmented_moments(d: np.ndarray, pseudo_weight: float, pseudo_units: float = 1.0
                       ) -> tuple[np.ndarray, np.ndarray, float]:
    """Pseudo-worlds of weight ``pseudo_weight`` at +1 and at -1 added (and Agresti-Min's weight 1
    at 0 when ``pseudo_weight`` is 1/2, so the total is 2), each of the size ``pseudo_units`` of
    one unit of ``d`` (1 / its worlds when the units are seeds of several worlds, so that a
    pseudo-world weighs as a world): mean, plug-in variance and total weight over the last
    axis."""
    weight = d.shape[-1] + 2.0 * pseudo_units
    mean = d.sum(axis=-1) / weight
    var = ((d * d).sum(axis=-1) + 2.0 * pseudo_weight * pseudo_units) / weight - mean * mean
    return mean, np.maximum(var, 0.0), weight


def _pseudo_units(pseudo_units: float) -> float:
    return check_range("pseudo_units", pseudo_units, 0.0, 1.0, low_open=True)


def _pseudo_weight(pseudo_weight: float) -> float:
    return check_range("pseudo_weight", pseudo_weight, 0.0, 1.0, low_open=True)


def _out(x: np.ndarray) -> Any:
    return float(x) if np.ndim(x) == 0 else x


def matched_rate_interval(differences: Any, *, clusters: Any = None, confidence: float = 0.95,
                          pseudo_weight: float = 1.0,
                          small_sample_correction: bool = True) -> Interval:
    """Adjusted Wald interval for the difference of matched success rates, cluster version.

    ``differences`` ``(..., n)``: per-world differences of success rates over K draws
    (``b_rate - a_rate``, in [-1, 1]); leading axes are independent comparisons. ``clusters``
    ``(n,)`` the worlds' seeds (default every world its own). Two pseudo-worlds of weight
    ``pseudo_weight`` (1: Bonett & Price 2012; 1/2: Agresti & Min 2005) at +1 and -1, each its
    own cluster, total weight ``W = n + 2``; ``mean' = sum d / W``; the cluster-robust (Liang &
    Zeger 1986) variance ``(sum_g (T_g - mean' m_g)^2 + 2 w + 2 mean'^2) / W^2`` (``T_g`` a
    cluster's total over its ``m_g`` worlds, the last two terms the pseudo-worlds'); ``mean' +-
    q sqrt(var')`` clipped to [-1, 1]. ``small_sample_correction`` (default): the CR1 factor
    ``G / (G - 1)`` on the variance and ``q = t_{(1+c)/2, G-1}`` (Cameron & Miller 2015), G the
    clusters; without it ``q = z`` and, every world its own cluster, this is the published
    interval exactly. Valid with few or no discordant worlds."""
    d = _differences(differences, min_worlds=1, rate=True)
    conf = _confidence(confidence)
    w = _pseudo_weight(pseudo_weight)
    index, g = cluster_index(clusters, d.shape[-1])
    weight = d.shape[-1] + 2.0
    mean = d.sum(axis=-1) / weight
    totals, sizes = cluster_sums(d, index, g), np.bincount(index, minlength=g)
    ss = ((totals - mean[..., None] * sizes) ** 2).sum(axis=-1) + 2.0 * w + 2.0 * mean * mean
    var = ss / (weight * weight)
    if small_sample_correction and g >= 2:
        var = var * g / (g - 1.0)
        q = stats.t.ppf(0.5 + conf / 2.0, g - 1)
    else:
        q = stats.norm.ppf(0.5 + conf / 2.0)
    half = q * np.sqrt(var)
    lo, hi = np.maximum(mean - half, -1.0), np.minimum(mean + half, 1.0)
    method = "bonett-price-cluster" if w == 1.0 else "adjusted-wald-cluster"
    if small_sample_correction:
        method += "-cr1-t"
    return Interval(_out(mean), _out(lo), _out(hi), int(d.shape[-1]), conf, method,
                    None if clusters is None else g)


def _lambert_x(alpha: float) -> float:
    """``x* = t* rho^2`` minimising the boundary's width at ``t*``: ``-W_{-1}(-a^2/e) - 1``."""
    return -float(np.real(special.lambertw(-alpha * alpha / math.e, k=-1))) - 1.0


def _sequential_moments(d: np.ndarray, rate: bool, pseudo_weight: float,
                        pseudo_units: float = 1.0):
    """Mean, standard deviation and weight ``t`` of the differences for a sequential interval:
    for success (``rate``) those of the sample with the pseudo-worlds of
    :func:`matched_rate_interval` (``t = n + 2``), else the sample's (``ddof=1``, ``t = n``)."""
    if rate:
        mean, var, t = _augmented_moments(d, _pseudo_weight(pseudo_weight),
                                          _pseudo_units(pseudo_units))
        return mean, np.sqrt(var), t
    return d.mean(axis=-1), d.std(axis=-1, ddof=1), float(d.shape[-1])


def cs_rho(planned_worlds: int, alpha: float = 0.05) -> float:
    """The ``rho`` that makes :func:`confidence_sequence` narrowest at ``planned_worlds``:
    ``rho^2 = (-W_{-1}(-alpha^2/e) - 1) / planned_worlds``."""
    t_star = check_int_range("planned_worlds", planned_worlds, 1)
    return math.sqrt(_lambert_x(_alpha(alpha)) / t_star)


def cs_multiplier(alpha: float = 0.05) -> float:
    """``c(alpha)``: the confidence sequence's half-width at its planned time is ``c sd/sqrt(t)``
    (3.04 at alpha = 0.05)."""
    a = _alpha(alpha)
    x = _lambert_x(a)
    return math.sqrt(2.0 * (x + 1.0) / x * math.log(math.sqrt(x + 1.0) / a))


def confidence_sequence(differences: Any, *, planned_worlds: int, alpha: float = 0.05,
                        rate: bool = False, pseudo_weight: float = 1.0,
                        pseudo_units: float = 1.0) -> Interval:
    """Asymptotic confidence sequence (Waudby-Smith et al. 2021) of the mean difference, at the
    current number of worlds ``n`` (the last axis of ``differences``, ``(..., n)``, n >= 2).

    Two-sided level ``1 - alpha``, valid at every look at once; ``rho`` from :func:`cs_rho` at
    ``planned_worlds``. ``rate=True`` (success): mean and variance of the sample augmented with
    the pseudo-worlds of :func:`matched_rate_interval` (``t = n + 2``), clipped to [-1, 1], so
    zero discordance gives a finite width."""
    d = _differences(differences, rate=rate)
    a = _alpha(alpha)
    rho = cs_rho(planned_worlds, a)
    mean, sd, t = _sequential_moments(d, rate, pseudo_weight, pseudo_units)
    x = t * rho * rho
    half = sd * math.sqrt(2.0 * (x + 1.0) / (t * x) * math.log(math.sqrt(x + 1.0) / a))
    lo, hi = mean - half, mean + half
    if rate:
        lo, hi = np.maximum(lo, -1.0), np.minimum(hi, 1.0)
    return Interval(_out(mean), _out(lo), _out(hi), int(d.shape[-1]), 1.0 - a, "asymptotic-cs",
                    anytime_valid=True)


SEQUENTIAL_DESIGNS = ("confidence-sequence", "group-sequential")
"""The sequential designs of :func:`sequential_decisions` (module docstring)."""

GSD_GRID_POINTS = 201
"""Points of the numerical integration of :func:`group_sequential_bounds` per look (odd, for
Simpson's rule): five equally spaced looks' bounds agree with gsDesign's published 4.877,
3.357, 2.680, 2.290, 2.031 to 1e-3, and with 401 points to 1e-7."""


def obrien_fleming_spending(fraction: Any, alpha: float = 0.05) -> Any:
    """The two-sided error a group-sequential design may have spent by information fraction
    ``t`` in (0, 1]: each side spends Lan & DeMets' (1983) O'Brien-Fleming-type function at
    ``alpha / 2``, ``2 - 2 Phi(z_{1-alpha/4} / sqrt(t))`` (the symmetric two-sided design of R's
    gsDesign, ``sfLDOF``), so ``4 - 4 Phi(z_{1-alpha/4} / sqrt(t))`` in all: ``alpha`` at
    ``t = 1``, almost nothing early."""
    t = np.asarray(fraction, dtype=float)
    require(bool(np.all((t > 0.0) & (t <= 1.0))), "fraction", fraction, "in (0, 1]")
    z = stats.norm.isf(_alpha(alpha) / 4.0)
    return 4.0 * stats.norm.sf(z / np.sqrt(t))


def group_sequential_bounds(fractions: Any, alpha: float = 0.05,
                            grid_points: int = GSD_GRID_POINTS) -> np.ndarray:
    """Two-sided critical values ``c_k`` of a group-sequential design with Lan-DeMets
    O'Brien-Fleming-type spending (:func:`obrien_fleming_spending`) at the increasing
    information fractions ``fractions`` (t_1 < ... < t_K <= 1): under the null the standardised
    statistics ``Z_k`` (a Brownian motion ``S(t) = Z sqrt(t)`` seen at the ``t_k``) first leave
    ``|Z_k| < c_k`` at look ``k`` with probability ``alpha(t_k) - alpha(t_{k-1})``.

    Computed by Armitage, McPherson & Rowe's (1969) recursion (Jennison & Turnbull 2000, ch. 19):
    the sub-density of ``S(t_k)`` over the paths still inside is carried on a Simpson grid of the
    continuation interval; the probability of leaving at the next look is then a sum of normal
    tail probabilities, solved for ``c`` by ``scipy.optimize.brentq``. Written here: no maintained
    Python library has it (R's gsDesign and rpact do; the test compares with their published
    values). Only the looks so far are needed for the current bound, so looks may come at any
    fractions (the spending function's flexibility)."""
    from scipy.optimize import brentq

    t = np.asarray(fractions, dtype=float).ravel()
    require(t.size >= 1 and bool(np.all(np.diff(t) > 0)), "fractions", fractions,
            "increasing")
    spent = obrien_fleming_spending(t, alpha)
    g = check_int_range("grid_points", grid_points, 11)
    g += 1 - g % 2  # odd for Simpson's rule
    simpson = np.ones(g)
    simpson[1:-1:2], simpson[2:-1:2] = 4.0, 2.0
    bounds = np.empty(t.size)
    grid = weights = None  # the previous look's continuation grid and sub-density x weights
    previous_spent = 0.0
    for k, t_k in enumerate(t):
        target = spent[k] - previous_spent
        if grid is None:
            def leave(c, t_k=t_k):
                return 2.0 * stats.norm.sf(c)
        else:
            sd = math.sqrt(t_k - t[k - 1])

            def leave(c, t_k=t_k, sd=sd, grid=grid, weights=weights):
                edge = c * math.sqrt(t_k)
                return float(np.sum(weights * (stats.norm.cdf((-edge - grid) / sd)
                                               + stats.norm.sf((edge - grid) / sd))))
        # leave() falls from (nearly) all the mass still inside at c = 0 to 0
        bounds[k] = brentq(lambda c, leave=leave, target=target: leave(c) - target, 0.0, 40.0,
                           xtol=1e-10) if target > 0 else np.inf
        edge = min(bounds[k], 40.0) * math.sqrt(t_k)
        new_grid = np.linspace(-edge, edge, g)
        step = new_grid[1] - new_grid[0]
        if grid is None:
            density = stats.norm.pdf(new_grid / math.sqrt(t_k)) / math.sqrt(t_k)
        else:
            density = (weights[None, :] * stats.norm.pdf((new_grid[:, None] - grid[None, :]) / sd)
                       ).sum(axis=1) / sd
        grid, weights = new_grid, density * simpson * step / 3.0
        previous_spent = spent[k]
    return bounds


def repeated_confidence_interval(differences: Any, *, bound: float, rate: bool = False,
                                 pseudo_weight: float = 1.0,
                                 pseudo_units: float = 1.0) -> Interval:
    """Repeated confidence interval (Jennison & Turnbull 1989) of the mean difference at one
    look of a group-sequential design: ``mean +- bound sd / sqrt(t)``, ``bound`` that look's
    :func:`group_sequential_bounds` value; together over the design's looks they cover the
    truth with probability ``1 - alpha``. ``rate=True``: the moments with the pseudo-worlds of
    :func:`matched_rate_interval`, clipped to [-1, 1], as in :func:`confidence_sequence`."""
    d = _differences(differences, rate=rate)
    c = check_range("bound", bound, 0.0, math.inf, low_open=True)
    mean, sd, t = _sequential_moments(d, rate, pseudo_weight, pseudo_units)
    half = c * sd / math.sqrt(t)
    lo, hi = mean - half, mean + half
    if rate:
        lo, hi = np.maximum(lo, -1.0), np.minimum(hi, 1.0)
    level = float("nan")  # simultaneous over the design's looks, not at one look
    return Interval(_out(mean), _out(lo), _out(hi), int(d.shape[-1]), level,
                    "group-sequential-rci", anytime_valid=True)


def check_design(design: str, rate: bool) -> None:
    """``design`` is one of :data:`SEQUENTIAL_DESIGNS` and fits the metric (``rate``: success)."""
    check_choice("design", design, SEQUENTIAL_DESIGNS)
    require(design == "confidence-sequence" or rate, "design", design,
            "'confidence-sequence' for a continuous metric: the group-sequential design's "
            "Wald intervals are checked on success (0/1) only; on skewed continuous differences "
            "at 96 worlds they declared a false 'not worse' 6.4 % of the time against alpha 5 %")


def sequential_interval(differences: Any, *, design: str, planned_worlds: int,
                        look_worlds: Any = None, alpha: float = 0.05, rate: bool = False,
                        pseudo_weight: float = 1.0, pseudo_units: float = 1.0) -> Interval:
    """The interval of the current look (the last axis of ``differences``: the worlds so far)
    under ``design`` (:data:`SEQUENTIAL_DESIGNS`): the :func:`confidence_sequence` tuned to
    ``planned_worlds``, or the :func:`repeated_confidence_interval` with the bound of the
    group-sequential design whose looks so far were at ``look_worlds`` worlds (this look last;
    information fractions ``look_worlds / planned_worlds``)."""
    check_design(design, rate)
    if design == "confidence-sequence":
        return confidence_sequence(differences, planned_worlds=planned_worlds, alpha=alpha,
                                   rate=rate, pseudo_weight=pseudo_weight,
                                   pseudo_units=pseudo_units)
    n = np.shape(differences)[-1]
    looks = [int(v) for v in (look_worlds if look_worlds is not None else [n])]
    require(bool(looks) and looks[-1] == n, "look_worlds", look_worlds,
            f"the looks so far, ending at this one ({n} worlds)")
    planned = check_int_range("planned_worlds", planned_worlds, 1)
    require(looks[-1] <= planned, "planned_worlds", planned_worlds,
            f">= the worlds seen ({looks[-1]})")
    bound = group_sequential_bounds(np.asarray(looks, dtype=float) / planned, alpha)[-1]
    return repeated_confidence_interval(differences, bound=bound, rate=rate,
                                        pseudo_weight=pseudo_weight, pseudo_units=pseudo_units)


def decide(lo: Any, hi: Any, margin: float) -> Any:
    """Non-inferiority decision on an interval of the oriented difference (positive = B better).

    In this order: ``"better"`` if ``lo > 0``; ``"not worse"`` if ``lo > -margin``; ``"worse"``
    if ``hi < -margin``; else ``"undecided"``. Scalars give a str, arrays an array of str."""
    m = check_range("margin", margin, 0.0, math.inf)
    lo_ = np.asarray(lo, dtype=float)
    hi_ = np.asarray(hi, dtype=float)
    require(hi_.shape == lo_.shape, "hi", f"shape {hi_.shape}", f"the shape of lo, {lo_.shape}")
    require(not np.isnan(lo_).any(), "lo", "NaN", "a number")
    require(not np.isnan(hi_).any(), "hi", "NaN", "a number")
    require(bool((lo_ <= hi_).all()), "hi", "below lo", ">= lo")
    out = np.select([lo_ > 0.0, lo_ > -m, hi_ < -m], list(DECISIONS[:3]), default=DECISIONS[3])
    return str(out) if out.ndim == 0 else out


def sequential_decisions(differences: Any, *, margin: float, alpha: float = 0.05,
                         planned_worlds: int | None = None, batch_size: int = 8,
                         rate: bool = False, min_worlds: int = MIN_SEEDS,
                         pseudo_weight: float = 1.0, design: str = "confidence-sequence",
                         looks: Any = None, pseudo_units: float = 1.0) -> SequentialOutcome:
    """Run the sequential non-inferiority decision over independent units in the given order:
    the one sequential loop (``slam-gym compare`` runs it after every batch on the seeds so
    far, the calibration tests on simulated ones).

    ``differences`` ``(..., n)``: per-unit oriented differences in run order (the per-seed means
    of :func:`cluster_means`; leading axes: independent comparisons). Looks after every
    ``batch_size`` units from ``min_worlds`` on (and at ``n``), or at the given ``looks`` (the
    units seen at each look so far, increasing, the last ``n``: ``compare``'s looks, where a
    batch whose runs all failed adds fewer). At each look the interval of ``design``
    (:func:`confidence_sequence`, or the group-sequential design's repeated interval; planned
    for ``planned_worlds`` units, default ``n``) and :func:`decide`; the first look that is not
    ``undecided`` stops. Returns that look's decision and interval, or the last look's
    (``undecided``). ``min_worlds`` (default :data:`MIN_SEEDS`): no decision before, because the
    sequence rests on a central limit theorem and its variance estimate from a few skewed units
    is too small too often."""
    d = _differences(differences, rate=rate)
    check_design(design, rate)
    n = d.shape[-1]
    batch = check_int_range("batch_size", batch_size, 1)
    first = check_int_range("min_worlds", min_worlds, 2)
    planned = n if planned_worlds is None else planned_worlds
    if looks is None:
        looks = [t for t in range(batch, n + 1, batch) if t >= first]
        if not looks or looks[-1] != n:
            looks.append(n)
    else:
        looks = [int(t) for t in looks]
        require(bool(looks) and looks[-1] == n and all(np.diff(looks) > 0) and looks[0] >= 2,
                "looks", looks, f"increasing unit counts >= 2 ending at n = {n}")
        looks = [t for t in looks if t >= first] or [n]
    shape = d.shape[:-1]
    decision = np.full(shape, DECISIONS[3], dtype=object)
    at = np.full(shape, n)
    est, lo, hi = (np.full(shape, np.nan) for _ in range(3))
    open_ = np.ones(shape, dtype=bool)
    if design == "group-sequential":  # a look's bound depends only on the looks before it
        require(n <= planned, "planned_worlds", planned_worlds, f">= the units ({n})")
        bounds = group_sequential_bounds(np.asarray(looks, dtype=float) / planned, alpha)
    for i, t in enumerate(looks):
        if design == "group-sequential":
            cs = repeated_confidence_interval(d[..., :t], bound=bounds[i], rate=rate,
                                              pseudo_weight=pseudo_weight,
                                              pseudo_units=pseudo_units)
        else:
            cs = confidence_sequence(d[..., :t], planned_worlds=planned, alpha=alpha,
                                     rate=rate, pseudo_weight=pseudo_weight,
                                     pseudo_units=pseudo_units)
        now = np.asarray(decide(cs.lo, cs.hi, margin), dtype=object)
        take = open_ & ((now != DECISIONS[3]) | (t == n))
        decision[take] = now[take]
        at[take] = t
        est[take] = np.asarray(cs.estimate)[take]
        lo[take] = np.asarray(cs.lo)[take]
        hi[take] = np.asarray(cs.hi)[take]
        open_ &= ~take
    method = "group-sequential-rci" if design == "group-sequential" else "asymptotic-cs"
    if decision.ndim == 0:
        return SequentialOutcome(str(decision), int(at), float(est), float(lo), float(hi),
                                 tuple(looks), method)
    return SequentialOutcome(decision.astype(str), at, est, lo, hi, tuple(looks), method)


def plan_worlds(pilot_differences: Any, margin: float, *, alpha: float = 0.05,
                power: float = 0.8, expected_difference: float = 0.0, sequential: bool = True,
                rate: bool = False, batch_size: int = 1, pseudo_weight: float = 1.0,
                worlds_per_unit: int = 1) -> WorldPlan:
    """Worlds needed to decide ``not worse`` (``lo > -margin``) with probability ``power`` when the
    true oriented difference is ``expected_difference``.

    From the pilot's per-world standard deviation ``s`` (``ddof=1``) and ``delta =
    expected_difference``: the smallest ``n`` with ``E[est] + margin >= k * half_n + z_power *
    sd(est)``, ``k`` = ``z_{1-alpha/2}`` (fixed sample, the ``1 - alpha`` intervals above) or
    ``c(alpha)`` (sequential, :func:`cs_multiplier`: the sequence tuned to ``planned_worlds = n``
    alone decides with that power at ``n``; earlier looks only add). Continuous: ``est`` the mean,
    ``half_n = sd(est) = s / sqrt(n)``, i.e. ``n = ((k + z_power) s / (delta + margin))^2``.
    Rate: ``est = n delta / W`` and ``half_n = sqrt(v / W)`` with the pseudo-worlds' ``W = n + 2``,
    ``v = (n (s^2 + delta^2) + 2 w) / W - est^2``, ``sd(est) = s sqrt(n) / W`` (so a pilot with
    no discordant world still asks for a finite number). Rounded up to a multiple of
    ``batch_size``, at least 2 (:data:`MIN_SEEDS` for the sequential design)."""
    d = _differences(pilot_differences, one_d=True, rate=rate, name="pilot_differences")
    m = check_range("margin", margin, 0.0, math.inf)
    a = _alpha(alpha)
    p = check_range("power", power, 0.0, 1.0, low_open=True, high_open=True)
    delta = check_range("expected_difference", expected_difference, -math.inf, math.inf)
    batch = check_int_range("batch_size", batch_size, 1)
    w = _pseudo_weight(pseudo_weight)
    per_unit = check_int_range("worlds_per_unit", worlds_per_unit, 1)
    require(delta + m > 0.0, "expected_difference", expected_difference,
            f"> -margin (= {-m}): at or below -margin, not worse cannot be shown")
    sd = float(d.std(ddof=1))
    multiplier = cs_multiplier(a) if sequential else float(stats.norm.ppf(1.0 - a / 2.0))
    z_power = float(stats.norm.ppf(p))

    def slack(n: float) -> float:
        """E[est] + margin - k half_n - z_power sd(est) at n worlds (>= 0: enough)."""
        if not rate:
            return delta + m - (multiplier + z_power) * sd / math.sqrt(n)
        if sequential:  # the moments of sequential_decisions on per-seed means
            units = 1.0 / per_unit
            total = n + 2.0 * units
            est = n * delta / total
            var = max((n * (sd * sd + delta * delta) + 2.0 * w * units) / total - est * est, 0.0)
            return (est + m - multiplier * math.sqrt(var / total)
                    - z_power * sd * math.sqrt(n) / total)
        total = n * per_unit + 2.0  # the cluster interval on the worlds (matched_rate_interval)
        est = n * per_unit * delta / total
        ss = per_unit**2 * n * (sd * sd + (delta - est) ** 2) + 2.0 * w + 2.0 * est * est
        return (est + m - multiplier * math.sqrt(ss) / total
                - z_power * per_unit * sd * math.sqrt(n) / total)

    hi = 2
    while slack(hi) < 0.0:
        hi *= 2
        require(hi < 2**40, "expected_difference", expected_difference,
                "far enough above -margin for a finite plan")
    lo = hi // 2 if hi > 2 else 1
    while hi - lo > 1:  # smallest n with slack >= 0 (slack grows with n beyond the pilot's scale)
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if slack(mid) >= 0.0 else (mid, hi)
    n = max(MIN_SEEDS if sequential else 2, hi)
    n = batch * math.ceil(n / batch)
    return WorldPlan(n, sd, delta + m, multiplier, int(d.size), bool(sequential))
