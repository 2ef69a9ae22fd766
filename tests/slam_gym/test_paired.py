"""Calibration tests of slam_gym/evaluation/paired.py: coverage of the fixed intervals, error rate
of the sequential decision under repeated looks, the decision rule, the plan, bad input.

Every simulation is seeded; the synthetic comparisons follow the data model of ``slam-gym
compare``: seeds, each at four clutter levels (the strata), K filter draws per world and policy
with common random numbers (the same uniform decides both arms' draw unless a share of the draws
is made independent), per-world means, left-out worlds. The tests that matter most go through
the code ``compare`` runs: :func:`slam_gym.evaluation.pairing.world_means` (runs to worlds, the
seed as the cluster), :func:`slam_gym.evaluation.compare.fixed_interval` and
:func:`~slam_gym.evaluation.paired.sequential_decisions` (compare's one loop). Monte Carlo
standard errors are quoted where a threshold is set from them.

Mutations each calibration test was checked against by hand (issue 56 item 5; the test fails
under it, and passes without it), named in the test's docstring:
- ignore strata: ``cluster_bootstrap_interval`` with every cluster in one stratum;
- drop the small-sample correction: ``small_sample_correction=False`` as the default;
- narrow the sequential boundary by 10 %: ``confidence_sequence``'s half-width x 0.9, and
  ``group_sequential_bounds`` x 0.9;
- draws as independent worlds: ``pairing.world_means`` keying worlds and clusters by draw too;
- levels as independent worlds: ``pairing.world_means``' cluster (scenario, level, seed).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from scipy import stats

from slam_gym.evaluation import paired, pairing
from slam_gym.evaluation.compare import fixed_interval
from slam_gym.evaluation.paired import (
    cluster_bootstrap_interval,
    cs_multiplier,
    cs_rho,
    decide,
    matched_rate_interval,
    metric_direction,
    plan_worlds,
    sequential_decisions,
    world_differences,
)
from slam_gym.evaluation.summary import clustered_wilson_interval

ALPHA = 0.05


def mc_se(p: float, trials: int) -> float:
    """Monte Carlo standard error of a rate ``p`` estimated from ``trials`` trials."""
    return math.sqrt(p * (1.0 - p) / trials)


# --- synthetic comparisons ---------------------------------------------------------------------


def rate_worlds(rng: np.random.Generator, trials: int, n: int, k: int, catalogue, probs,
                independent: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-world success rates of A and B over ``k`` draws, ``trials`` comparisons of ``n`` worlds.

    Each world is a type from ``catalogue`` (success probabilities ``(p_a, p_b)``) drawn with
    ``probs``; draw j of both arms uses the same uniform (common random numbers) except a share
    ``independent`` of B's draws, which get their own. Returns the rates and the true difference
    ``sum probs (p_b - p_a)``."""
    cat = np.asarray(catalogue, dtype=float)
    kind = rng.choice(len(cat), p=probs, size=(trials, n))
    p_a, p_b = cat[kind, 0][..., None], cat[kind, 1][..., None]
    u = rng.random((trials, n, k))
    v = np.where(rng.random((trials, n, k)) < independent, rng.random((trials, n, k)), u)
    truth = float(np.dot(probs, cat[:, 1] - cat[:, 0]))
    return (u < p_a).mean(axis=-1), (v < p_b).mean(axis=-1), truth


MAP_SIGMA_DRAW, MAP_SIGMA_ARM = 0.5, 0.4


def map_error_worlds(rng: np.random.Generator, n: int, k: int, ratio: float, sigma_world: float,
                     missing: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map errors ``(n, k)`` of A and B: world scale ``exp(0.5 level + sigma_world N(0,1))`` (four
    clutter levels, balanced) x a draw factor shared by both arms (lognormal 0.5, common random
    numbers) x each arm's own factor (lognormal 0.4); B's errors are ``ratio`` times A's. A share
    ``missing`` of the runs has no map error (NaN)."""
    strata = np.arange(n) % 4
    scale = np.exp(0.5 * strata + sigma_world * rng.standard_normal(n))[:, None]
    draw = rng.lognormal(0.0, MAP_SIGMA_DRAW, (n, k))
    a = scale * draw * rng.lognormal(0.0, MAP_SIGMA_ARM, (n, k))
    b = ratio * scale * draw * rng.lognormal(0.0, MAP_SIGMA_ARM, (n, k))
    a[rng.random((n, k)) < missing] = np.nan
    b[rng.random((n, k)) < missing] = np.nan
    return a, b, strata


def map_error_truth(n: int, ratio: float, sigma_world: float) -> float:
    """E[a_w - b_w] (lower is better, so positive = B better), strata weighted as in the sample."""
    level = np.arange(n) % 4
    world = np.exp(0.5 * level + sigma_world**2 / 2.0).mean()
    return (1.0 - ratio) * world * math.exp(MAP_SIGMA_DRAW**2 / 2.0 + MAP_SIGMA_ARM**2 / 2.0)


def left_skewed(rng: np.random.Generator, trials: int, n: int, mean: float, sd: float,
                sigma: float = 0.5) -> np.ndarray:
    """Per-world differences with the given mean and sd, left-skewed (a lognormal's mirror: B's
    occasional large losses), the hard case for a sequence built on a central limit theorem."""
    ln = rng.lognormal(0.0, sigma, (trials, n))
    mu = math.exp(sigma**2 / 2.0)
    sigma_ln = math.sqrt((math.exp(sigma**2) - 1.0) * math.exp(sigma**2))
    return mean - sd * (ln - mu) / sigma_ln


# --- helpers: metrics, per-world aggregation -------------------------------------------------


def test_metric_direction_orients_every_metric_of_the_data_model():
    assert metric_direction("success") == 1
    assert metric_direction("nees_in_band_fraction") == 1
    assert metric_direction("return") == 1
    assert metric_direction("map_error_m") == -1
    assert metric_direction("interface_cpu_s") == -1
    assert metric_direction("anees") == 0
    with pytest.raises(ValueError, match="^metric="):
        metric_direction("pose_error")


def test_world_differences_orient_drop_and_count():
    a = np.array([1.0, 2.0, np.nan, 4.0, 5.0])
    b = np.array([2.0, 1.0, 3.0, np.inf, 5.5])
    wd = world_differences(a, b, np.array([0, 1, 2, 3, 3]), clusters=np.array([7, 7, 8, 8, 9]))
    assert wd.n_left_out == 2 and len(wd) == 3
    np.testing.assert_array_equal(wd.clusters, [7, 7, 9])
    np.testing.assert_array_equal(wd.differences, [1.0, -1.0, 0.5])
    np.testing.assert_array_equal(wd.strata, [0, 1, 3])
    lower = world_differences(a, b, lower_is_better=True)
    np.testing.assert_array_equal(lower.differences, [-1.0, 1.0, -0.5])
    np.testing.assert_array_equal(lower.strata, [0, 0, 0])


# --- the decision rule -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("lo", "hi", "margin", "expected"),
    [
        (0.01, 0.2, 0.05, "better"),
        (0.0, 0.2, 0.05, "not worse"),
        (-0.049, 0.2, 0.05, "not worse"),
        (-0.05, 0.2, 0.05, "undecided"),  # lo == -margin is not above it
        (-0.3, -0.051, 0.05, "worse"),
        (-0.3, -0.05, 0.05, "undecided"),
        (0.0, 0.0, 0.0, "undecided"),  # margin 0: equality is neither better nor worse
        (-0.2, -0.01, 0.0, "worse"),
    ],
)
def test_decide_rule(lo, hi, margin, expected):
    assert decide(lo, hi, margin) == expected


def test_decide_is_vectorised():
    out = decide(np.array([0.1, -0.01, -0.5, -0.5]), np.array([0.2, 0.1, -0.2, 0.1]), 0.05)
    assert out.tolist() == ["better", "not worse", "worse", "undecided"]


# --- fixed sample: continuous metrics ----------------------------------------------------------


def test_bootstrap_estimate_clusters_and_reproducibility():
    d = np.array([1.0, 3.0, 10.0, 14.0, 2.0, 6.0])
    strata = np.array([0, 0, 1, 1, 2, 3])  # levels 2 and 3 have one cluster each: merged
    one = cluster_bootstrap_interval(d, strata, rng=7, n_resamples=999)
    two = cluster_bootstrap_interval(d, strata, rng=7, n_resamples=999)
    assert one == two
    # the mean of 6 small floats: equal up to a few ulps of it, whatever the summation order
    assert one.estimate == pytest.approx(d.mean(), rel=1e-12)
    assert one.lo < one.estimate < one.hi
    # constant within every cluster's stratum: nothing to resample, the estimate is the interval
    flat = cluster_bootstrap_interval(np.array([1.0, 1.0, 3.0, 3.0]), np.array([0, 0, 1, 1]),
                                      rng=0)
    assert flat.lo == flat.hi == flat.estimate


COVERAGE_TRIALS = 1000


def bootstrap_coverage(n: int, sigma_world: float, methods: tuple[str, ...], seed: int
                       ) -> dict[str, tuple[float, float, float]]:
    """Coverage, lower miss (truth below lo) and upper miss of compare's cluster bootstrap on map
    errors of ``n`` worlds (``n / 4`` seeds at four levels; B 20 % better, K = 3 draws, 10 % of
    runs without a map error), through :func:`pairing.world_means`."""
    rng = np.random.default_rng(seed)
    truth = map_error_truth(n, 0.8, sigma_world)
    hits = {m: np.zeros(3) for m in methods}
    for _ in range(COVERAGE_TRIALS):
        a, b, strata = map_error_worlds(rng, n, 3, 0.8, sigma_world)
        keep = np.isfinite(a) & np.isfinite(b)  # a pair needs both values
        level = np.repeat(strata[:, None], 3, axis=1)[keep]
        seed_ = np.repeat((np.arange(n) // 4)[:, None], 3, axis=1)[keep]
        wd = pairing.world_means(level, seed_, a[keep], b[keep]).differences(lower_is_better=True)
        for method in methods:
            iv = cluster_bootstrap_interval(wd.differences, wd.strata, wd.clusters, rng=rng,
                                            n_resamples=999, method=method)
            hits[method] += (iv.lo <= truth <= iv.hi, truth < iv.lo, truth > iv.hi)
    return {m: tuple(h / COVERAGE_TRIALS) for m, h in hits.items()}


def test_bootstrap_covers_skewed_clustered_map_errors_at_96_worlds():
    """The default (corrected percentile) covers at >= 93 % (1 000 trials; MC SE 0.7 pp at 95 %)
    on differences with skewness ~1 and excess kurtosis ~9, 96 worlds on 24 seeds (the size of
    a comparison); measured 0.931 (truth below lo 0.025, above hi 0.044)."""
    (cover, below, above), = bootstrap_coverage(96, 0.3, ("percentile",), seed=1).values()
    logging.getLogger(__name__).info("bootstrap 96 worlds: coverage %.3f, below %.3f, above %.3f",
                                     cover, below, above)
    assert cover >= 0.93


def test_percentile_beats_bca_on_clustered_map_errors_at_48_worlds():
    """Why percentile: on the same 1 000 comparisons of 48 worlds, BCa (same corrections) covers
    less than the percentile interval, which is >= 93 % (measured 0.930 against 0.950)."""
    res = bootstrap_coverage(48, 0.3, ("percentile", "BCa"), seed=2)
    assert res["percentile"][0] >= 0.93
    assert res["percentile"][0] > res["BCa"][0]


def seeded_map_error_runs(rng: np.random.Generator, seeds: int, *, seed_sd: float,
                          level_effect: float = 0.5, own_seeds: bool = False, k: int = 2):
    """Map-error-like pairs of runs: ``seeds`` seeds at four levels, ``k`` draws. The difference
    A - B is ``0.2 exp(level_effect level)`` (B better, more so at high clutter) plus a seed
    effect (sd ``seed_sd``, shared by the seed's four worlds), a world effect (sd 0.3, shared by
    its draws) and a draw's own noise (sd 0.2). ``own_seeds``: every level its own seeds (no
    seed effect). Returns levels, seeds, a, b (one per pair) and the true mean difference."""
    lv = np.repeat(np.arange(4), k)[None, :].repeat(seeds, axis=0)
    sd = np.repeat(np.arange(seeds), 4 * k).reshape(seeds, -1)
    if own_seeds:
        sd = 4 * sd + lv
    seed_effect = 0.0 if own_seeds else seed_sd * rng.standard_normal(seeds)[:, None]
    world = 0.3 * np.repeat(rng.standard_normal((seeds, 4)), k, axis=1)
    scale = np.exp(level_effect * lv)
    a = scale * rng.lognormal(0.0, 0.3, lv.shape)
    d = 0.2 * scale + seed_effect + world + 0.2 * rng.standard_normal(lv.shape)
    truth = float(np.mean(0.2 * np.exp(level_effect * np.arange(4))))
    return lv.ravel(), sd.ravel(), a.ravel(), (a - d).ravel(), truth


def map_error_coverage(seeds: int, trials: int, seed: int, **kwargs) -> float:
    """Coverage of compare's fixed interval for the map error (:func:`fixed_interval`) on
    :func:`seeded_map_error_runs`, runs paired to worlds by :func:`pairing.world_means`."""
    rng = np.random.default_rng(seed)
    hit = 0
    for _ in range(trials):
        lv, sd, a, b, truth = seeded_map_error_runs(rng, seeds, **kwargs)
        d = pairing.world_means(lv, sd, a, b).differences(lower_is_better=True)
        iv = fixed_interval(d, "map_error_m", 0.95)
        hit += iv.lo <= truth <= iv.hi
    return hit / trials


def test_bootstrap_small_sample_correction_on_few_seeds():
    """8 seeds at four levels with a seed effect (seed sd 0.6 against world sd 0.3): compare's
    interval covers >= 93 % (1 000 trials, 3 MC SE below 95 % is 93.0 %); measured 0.952.
    Mutation checked: without the small-sample correction (adjusted values and the t-level)
    it covered 0.88 and this test fails."""
    cover = map_error_coverage(8, COVERAGE_TRIALS, 31, seed_sd=0.6)
    assert cover >= 0.95 - 3 * mc_se(0.95, COVERAGE_TRIALS)


def test_bootstrap_resamples_seeds_not_worlds_where_the_seed_matters():
    """12 seeds at four levels, strong seed effect (seed sd 0.6): resampling seeds covers >= 93 %
    (measured 0.94). Mutation checked: the levels of a seed as independent worlds (clusters
    (level, seed) in pairing.world_means) covered 0.72 and this test fails."""
    cover = map_error_coverage(12, 600, 32, seed_sd=0.6)
    assert cover >= 0.95 - 3 * mc_se(0.95, 600)


def test_bootstrap_is_stratified_where_every_level_has_its_own_seeds():
    """Every level its own 6 seeds, means far apart by level (level effect 1.5: 0.2 to 18 m):
    the interval stratified by level covers 95 % within 3 MC SE either way (1 000 trials;
    measured 0.953). Mutation checked: the strata ignored, the between-level spread enters the
    resampling and it covered 1.000, above 95 % + 3 MC SE: this test fails."""
    cover = map_error_coverage(6, COVERAGE_TRIALS, 33, seed_sd=0.0, level_effect=1.5,
                               own_seeds=True)
    assert abs(cover - 0.95) <= 3 * mc_se(0.95, COVERAGE_TRIALS)


# --- fixed sample: success rates ---------------------------------------------------------------


def two_by_two_interval(b_fails_a_wins: int, b_wins_a_fails: int, n: int, add: float,
                        z: float = 1.959963984540054) -> tuple[float, float]:
    """Adjusted Wald interval of the paired 2x2 table (Agresti & Min 2005: add 1/2 to every cell;
    Bonett & Price 2012: add 1 to each discordant cell), written from the table."""
    n_adj = n + 2.0
    p12 = (b_fails_a_wins + add) / n_adj
    p21 = (b_wins_a_fails + add) / n_adj
    diff = p21 - p12
    half = z * math.sqrt((p12 + p21 - diff * diff) / n_adj)
    return diff - half, diff + half


@pytest.mark.parametrize("weight", [0.5, 1.0])
def test_rate_interval_is_the_published_two_by_two_interval_for_one_draw(weight):
    """Without the small-sample correction, every world its own cluster, the cluster interval is
    the published 2x2 one (pytest.approx's default 1e-6 relative: the two are the same
    arithmetic in another order, equal to ~1e-15)."""
    d = np.array([1.0] * 7 + [-1.0] * 3 + [0.0] * 30)
    iv = matched_rate_interval(d, pseudo_weight=weight, small_sample_correction=False)
    lo, hi = two_by_two_interval(3, 7, 40, weight)
    assert (iv.lo, iv.hi) == (pytest.approx(lo), pytest.approx(hi))
    corrected = matched_rate_interval(d, pseudo_weight=weight)  # CR1 and t_39: a little wider
    assert corrected.lo < iv.lo and corrected.hi > iv.hi


def test_rate_interval_with_no_discordant_world_has_width():
    iv = matched_rate_interval(np.zeros(40), small_sample_correction=False)
    half = 1.959963984540054 * math.sqrt(2.0 / 42.0) / math.sqrt(42.0)
    # a sum of zeros is exactly 0 in any order; the half-width to approx's 1e-6 relative
    assert iv.estimate == 0.0
    assert (iv.lo, iv.hi) == (pytest.approx(-half), pytest.approx(half))


RATE_TRIALS = 4000

RATE_SCENARIOS = {
    # name: (draws K, worlds, catalogue of (p_a, p_b), probabilities, share of independent draws)
    "one draw, moderate discordance": (1, 40, [(0.9, 0.9), (0, 1), (1, 0), (0.2, 0.2)],
                                       [0.7, 0.12, 0.08, 0.1], 0.0),
    "one draw, rare discordance": (1, 80, [(0.9, 0.9), (0, 1), (1, 0)], [0.97, 0.02, 0.01], 0.0),
    "one draw, B only loses": (1, 40, [(1, 1), (1, 0)], [0.93, 0.07], 0.0),
    "one draw, B only wins": (1, 40, [(1, 1), (0, 1)], [0.95, 0.05], 0.0),
    "3 draws, clustered worlds": (3, 48, [(0.95, 0.95), (0.5, 0.8), (0.8, 0.5), (0.3, 0.3),
                                          (0.6, 0.7)], [0.5, 0.1, 0.1, 0.2, 0.1], 0.3),
    "3 draws, rare clustered discordance": (3, 48, [(0.95, 0.95), (0.3, 0.9), (0.9, 0.6)],
                                            [0.94, 0.04, 0.02], 0.0),
    "3 draws, B loses whole worlds": (3, 80, [(0.9, 0.9), (1, 0)], [0.93, 0.07], 0.0),
    "3 draws, independent draws": (3, 96, [(0.9, 0.9), (0.2, 0.8), (0.7, 0.3), (0.4, 0.4)],
                                   [0.6, 0.15, 0.1, 0.15], 0.5),
}


@pytest.mark.parametrize("name", list(RATE_SCENARIOS))
def test_rate_interval_covers(name):
    """Coverage >= 93.97 % (nominal 95 % minus 3 MC SE, 4 000 trials) in every scenario,
    including rare and one-directional discordance and clustered draws (worlds independent:
    each its own cluster). Identical arms are not a scenario here: an interval around 0 of
    differences that are all 0 cannot miss."""
    k, n, catalogue, probs, independent = RATE_SCENARIOS[name]
    rng = np.random.default_rng(100 + list(RATE_SCENARIOS).index(name))
    a, b, truth = rate_worlds(rng, RATE_TRIALS, n, k, catalogue, probs, independent)
    iv = matched_rate_interval(b - a)
    cover = float(np.mean((iv.lo <= truth) & (truth <= iv.hi)))
    assert cover >= 0.95 - 3 * mc_se(0.95, RATE_TRIALS)


SEED_TYPES = [(0.9, 0.9), (0.05, 0.05), (0.1, 0.8), (0.8, 0.2)]
"""Success probabilities (A, B) of a seed at every clutter level: the seed decides (issue 56:
the best rule on ZonesStarved-v1 succeeds at all four levels or none on 6 of 10 seeds)."""
SEED_TYPE_PROBS = [0.35, 0.35, 0.2, 0.1]


def seeded_success_runs(rng: np.random.Generator, seeds: int, k: int = 2):
    """Success pairs of runs: ``seeds`` seeds at four levels, ``k`` draws under common random
    numbers, each seed of a :data:`SEED_TYPES` type. Returns levels, seeds, draws, a, b (0/1,
    one per pair) and the true difference of success rates (+8 pp)."""
    cat = np.asarray(SEED_TYPES)
    kind = rng.choice(len(cat), p=SEED_TYPE_PROBS, size=seeds)
    shape = (seeds, 4 * k)
    u = rng.random(shape)
    a = (u < cat[kind, 0][:, None]).astype(float)
    b = (u < cat[kind, 1][:, None]).astype(float)
    lv = np.repeat(np.arange(4), k)[None, :].repeat(seeds, axis=0)
    sd = np.repeat(np.arange(seeds), 4 * k).reshape(shape)
    dr = np.tile(np.arange(k), 4)[None, :].repeat(seeds, axis=0)
    truth = float(np.dot(SEED_TYPE_PROBS, cat[:, 1] - cat[:, 0]))
    return lv.ravel(), sd.ravel(), dr.ravel(), a.ravel(), b.ravel(), truth


@pytest.mark.parametrize("seeds", [10, 20])
def test_success_interval_treats_the_seed_as_the_unit(seeds):
    """Success with a strong seed effect, 2 draws, through compare's path (pairing.world_means,
    then fixed_interval): coverage >= 95 % - 3 MC SE (2 000 trials; measured 0.961 at 10
    seeds, 0.957 at 20). Mutations checked: the levels of a seed as independent worlds (clusters
    (level, seed) in pairing.world_means) covered 0.75 / 0.74; the draws as independent worlds
    (worlds and clusters keyed by draw too) 0.60 / 0.60: this test fails under each."""
    rng = np.random.default_rng(50 + seeds)
    trials, hit = 2000, 0
    for _ in range(trials):
        lv, sd, dr, a, b, truth = seeded_success_runs(rng, seeds)
        d = pairing.world_means(lv, sd, a, b, draws=dr).differences()
        iv = fixed_interval(d, "success", 0.95)
        hit += iv.lo <= truth <= iv.hi
    assert hit / trials >= 0.95 - 3 * mc_se(0.95, trials)


@pytest.mark.parametrize(("worlds", "draws"), [(5, 5), (10, 2), (10, 5)])
def test_success_rate_interval_of_one_policy_covers_with_draws(worlds, draws):
    """``success_ci95`` of a benchmark group (summary.clustered_wilson_interval) on worlds whose
    type decides (success probability 0.05, 0.5 or 0.95): coverage >= 95 % - 3 MC SE (2 000
    trials; measured 0.95-0.97). Mutation checked: the draws as independent runs (plain
    Wilson over all runs) covered 0.73-0.89 and this test fails."""
    rng = np.random.default_rng(60 + worlds + draws)
    truth = 0.3 * 0.05 + 0.3 * 0.5 + 0.4 * 0.95
    trials, hit = 2000, 0
    for _ in range(trials):
        p = rng.choice([0.05, 0.5, 0.95], size=worlds, p=[0.3, 0.3, 0.4])
        outcomes = rng.random((worlds, draws)) < p[:, None]
        lo, hi = clustered_wilson_interval(outcomes.tolist())
        hit += lo <= truth <= hi
    assert hit / trials >= 0.95 - 3 * mc_se(0.95, trials)


def test_agresti_min_weight_fails_where_b_only_loses():
    """Why Bonett-Price's weight: with Agresti-Min's half pseudo-worlds the interval misses a
    one-directional loss of 7 pp on 80 worlds too often (measured 0.92; Bonett-Price 0.97)."""
    rng = np.random.default_rng(5)
    a, b, truth = rate_worlds(rng, RATE_TRIALS, 80, 1, [(1, 1), (1, 0)], [0.93, 0.07])
    half = matched_rate_interval(b - a, pseudo_weight=0.5)
    full = matched_rate_interval(b - a)
    cover_half = float(np.mean((half.lo <= truth) & (truth <= half.hi)))
    cover_full = float(np.mean((full.lo <= truth) & (truth <= full.hi)))
    assert cover_half < 0.95 - 5 * mc_se(0.95, RATE_TRIALS) < cover_full


# --- the confidence sequence -------------------------------------------------------------------


def test_cs_rho_minimises_the_width_at_the_planned_worlds():
    t_star, d = 96, np.random.default_rng(0).standard_normal(96)

    def half_width(scale: float) -> float:
        rho = scale * cs_rho(t_star)
        x = t_star * rho * rho
        return math.sqrt(2 * (x + 1) / (t_star * x) * math.log(math.sqrt(x + 1) / ALPHA))

    assert half_width(1.0) < min(half_width(0.9), half_width(1.1))
    cs = paired.confidence_sequence(d, planned_worlds=t_star)
    # c(0.05) = 3.035 (the boundary's value at t*, from Lambert's W; 1e-3 is its printed digits)
    assert cs_multiplier() == pytest.approx(3.035, abs=1e-3)
    assert cs.hi - cs.estimate == pytest.approx(3.035 * d.std(ddof=1) / math.sqrt(96), rel=1e-3)


def test_confidence_sequence_error_over_compare_looks():
    """The boundary by simulation: normal per-seed differences with mean 0, margin 0, looks every
    2 seeds from 16 to 100 (compare's default batches up to 400 worlds), 4 000 comparisons:
    a ``better`` or ``worse`` verdict is an error. Theory: at most alpha over all looks; over
    these finitely many looks the sequence spends about half (measured 0.025), so the test
    bounds it at alpha / 2 + 3 MC SE (0.032). Mutation checked: the half-width narrowed by 10 %
    made the error 0.050 and this test fails."""
    rng = np.random.default_rng(5)
    d = rng.standard_normal((SEQ_TRIALS, 100))
    out = sequential_decisions(d, margin=0.0, batch_size=2, planned_worlds=100)
    error = float(np.mean(out.decision != "undecided"))
    assert error <= ALPHA / 2 + 3 * mc_se(ALPHA / 2, SEQ_TRIALS)


SEQ_TRIALS = 4000
MARGIN = 0.05


def false_positive(d: np.ndarray, *, rate: bool, design: str = "confidence-sequence") -> float:
    """Share of comparisons declared ``not worse``/``better`` by the sequential ``design``,
    looking after every batch of 8 units from 16 on."""
    out = sequential_decisions(d, margin=MARGIN, alpha=ALPHA, batch_size=8, rate=rate,
                               design=design)
    return float(np.isin(out.decision, ["better", "not worse"]).mean())


NULL_SCENARIOS = {
    # success, true difference -5 pp = -margin
    "success, one draw, B only loses": lambda rng, n: rate_worlds(
        rng, SEQ_TRIALS, n, 1, [(1, 1), (1, 0)], [0.95, 0.05]),
    "success, one draw, both directions": lambda rng, n: rate_worlds(
        rng, SEQ_TRIALS, n, 1, [(0.5, 0.5), (0, 1), (1, 0)], [0.85, 0.05, 0.10]),
    "success, 3 clustered draws": lambda rng, n: rate_worlds(
        rng, SEQ_TRIALS, n, 3, [(0.9, 0.9), (0.6, 0.4), (0.3, 0.2), (0.5, 0.6)],
        [0.5, 0.2, 0.2, 0.1], 0.3),
}


DESIGNS = paired.SEQUENTIAL_DESIGNS


@pytest.mark.parametrize("design", DESIGNS)
@pytest.mark.parametrize("max_worlds", [96, 200])
@pytest.mark.parametrize("name", list(NULL_SCENARIOS))
def test_sequential_false_positive_rate_success(name, max_worlds, design):
    """True difference exactly -margin, looks after every batch of 8 up to ``max_worlds`` units:
    either design declares ``not worse`` at most alpha (+ 2 MC SE, 4 000 trials) of the time.
    Measured: the confidence sequence 0.000-0.026, the group-sequential design 0.011-0.052
    (its one-sided nominal is alpha / 2; it reaches alpha where B only ever loses, 5 % of
    units: a skewed 0/1 difference)."""
    rng = np.random.default_rng(40 + max_worlds + len(name))
    a, b, truth = NULL_SCENARIOS[name](rng, max_worlds)
    assert truth == pytest.approx(-MARGIN)  # a dot product of probabilities: to 1e-6 relative
    fp = false_positive(b - a, rate=True, design=design)
    assert fp <= ALPHA + 2 * mc_se(ALPHA, SEQ_TRIALS)


@pytest.mark.parametrize("design", DESIGNS)
def test_sequential_false_positive_rate_on_seeds(design):
    """compare's units: per-seed means of success over four levels x 2 draws, a strong seed
    effect (B loses whole seeds 20 % of the time, wins a quarter of them back on 20 %), true
    difference exactly -margin, looks every 2 seeds from 16 to 100 (400 worlds), pseudo-worlds
    the size of a world (``pseudo_units`` 1/4): ``not worse`` at most alpha + 2 MC SE of 4 000
    comparisons (measured 0.015 for the sequence, 0.037 for the group-sequential design).
    Mutation checked: the group-sequential bounds narrowed by 10 % fail it."""
    rng = np.random.default_rng(77)
    cat = np.array([(0.9, 0.9), (0.8, 0.3), (0.3, 0.55)])
    probs = [0.6, 0.2, 0.2]
    kind = rng.choice(3, p=probs, size=(SEQ_TRIALS, 100))
    u = rng.random((SEQ_TRIALS, 100, 8))
    d = ((u < cat[kind, 1][..., None]).astype(float)
         - (u < cat[kind, 0][..., None]).astype(float)).mean(axis=-1)
    assert float(np.dot(probs, cat[:, 1] - cat[:, 0])) == pytest.approx(-MARGIN)
    out = sequential_decisions(d, margin=MARGIN, batch_size=2, rate=True, design=design,
                               pseudo_units=0.25)
    fp = float(np.isin(out.decision, ["better", "not worse"]).mean())
    assert fp <= ALPHA + 2 * mc_se(ALPHA, SEQ_TRIALS)


@pytest.mark.parametrize("max_worlds", [96, 200])
def test_sequential_false_positive_rate_skewed_continuous(max_worlds):
    """Left-skewed differences (skewness 1.75), mean exactly -margin, sd 4 margins: the same
    check as for success. Measured 0.040 (96) and 0.034 (200); heavier skew is documented. (The
    group-sequential design is refused for continuous metrics: on these data it measured 0.064
    at 96 worlds, 0.044 at 200.)"""
    rng = np.random.default_rng(7 + max_worlds)
    d = left_skewed(rng, SEQ_TRIALS, max_worlds, -MARGIN, 4 * MARGIN)
    assert false_positive(d, rate=False) <= ALPHA + 2 * mc_se(ALPHA, SEQ_TRIALS)


def test_group_sequential_bounds_are_the_published_ones():
    """Five equally spaced looks, two-sided alpha 0.05, O'Brien-Fleming-type spending of
    alpha / 2 a side: gsDesign's sfLDOF bounds (Jennison & Turnbull 2000, table 2.3's
    Lan-DeMets analogue) 4.877, 3.357, 2.680, 2.290, 2.031; one look is the fixed 1.96."""
    bounds = paired.group_sequential_bounds([0.2, 0.4, 0.6, 0.8, 1.0])
    assert bounds == pytest.approx([4.877, 3.357, 2.680, 2.290, 2.031], abs=2e-3)
    assert paired.group_sequential_bounds([1.0])[0] == pytest.approx(stats.norm.isf(0.025))
    assert paired.obrien_fleming_spending(1.0) == pytest.approx(ALPHA)


def test_group_sequential_bounds_hold_alpha_on_brownian_paths():
    """The recursion itself, by simulation: a standard Brownian motion seen at looks 16, 24, ...,
    200 of 200 leaves the bounds at some look with probability alpha (200 000 paths: within 3
    MC SE), and at each look k at most the spending function's alpha(t_k). Mutation checked:
    the bounds narrowed by 10 % crossed with probability 0.08 and this test fails."""
    looks = np.arange(16, 201, 8)
    t = looks / 200.0
    bounds = paired.group_sequential_bounds(t)
    rng = np.random.default_rng(46)
    trials = 200_000
    steps = rng.standard_normal((trials, len(t))) * np.sqrt(np.diff(t, prepend=0.0))
    z = np.cumsum(steps, axis=1) / np.sqrt(t)
    crossed = np.abs(z) >= bounds
    first = np.where(crossed.any(axis=1), crossed.argmax(axis=1), len(t))
    by_look = np.array([np.mean(first <= k) for k in range(len(t))])
    assert by_look[-1] == pytest.approx(ALPHA, abs=3 * mc_se(ALPHA, trials))
    spent = paired.obrien_fleming_spending(t)
    assert np.all(by_look <= spent + 3 * np.sqrt(spent * (1 - spent) / trials) + 1e-12)


def test_group_sequential_design_decides_worse_where_the_sequence_cannot():
    """Why the group-sequential design exists: success about 10 pp lower with a per-world SD of
    ~34 pp (2 draws; what ``fixed-10s`` against ``fixed-10s-optimise`` measured, RESULTS issue
    46), margin 5 pp, at most 400 worlds in looks of 8: the group-sequential design answers
    ``worse`` clearly more often than the confidence sequence, and neither answers ``not
    worse`` or ``better`` (1 000 comparisons)."""
    rng = np.random.default_rng(4646)
    a, b, truth = rate_worlds(rng, 1000, 400, 2, [(0.9, 0.9), (0.9, 0.5), (0.3, 0.3), (0.6, 0.7)],
                              [0.45, 0.3, 0.15, 0.1], 0.5)
    assert truth == pytest.approx(-0.11)
    worse = {}
    for design in DESIGNS:
        out = sequential_decisions(b - a, margin=MARGIN, rate=True, design=design)
        assert not np.isin(out.decision, ["better", "not worse"]).any()
        worse[design] = float(np.mean(out.decision == "worse"))
    assert worse["group-sequential"] >= worse["confidence-sequence"] + 0.2


def test_group_sequential_design_is_refused_for_continuous_metrics():
    with pytest.raises(ValueError, match="design='group-sequential' is invalid"):
        sequential_decisions(np.zeros(32), margin=MARGIN, design="group-sequential")
    with pytest.raises(ValueError, match="design='sprt' is invalid"):
        sequential_decisions(np.zeros(32), margin=MARGIN, rate=True, design="sprt")


@pytest.mark.parametrize(("margin", "by"), [(0.05, 96), (0.1, 56), (0.2, 32)])
def test_identical_arms_decide_not_worse(margin, by):
    """Success: no discordant seed at all (identical policies) still decides ``not worse``
    after a modest number of seeds (planned 200, looks every 8): the pseudo-worlds keep the
    interval's width finite and shrinking."""
    out = sequential_decisions(np.zeros(200), margin=margin, rate=True, planned_worlds=200)
    assert out.decision == "not worse" and out.n_worlds <= by
    flat = sequential_decisions(np.zeros(200), margin=1e-6)  # continuous: zero variance
    assert flat.decision == "not worse" and flat.n_worlds == paired.MIN_SEEDS


def test_clearly_worse_b_decides_worse():
    """Success 20 pp lower (3 draws, clustered), margin 5 pp: ``worse`` in >= 99 % of 2 000
    comparisons of at most 200 worlds, never ``not worse``."""
    rng = np.random.default_rng(13)
    a, b, truth = rate_worlds(rng, 2000, 200, 3, [(0.9, 0.9), (0.8, 0.3), (0.5, 0.25)],
                              [0.5, 0.3, 0.2], 0.3)
    assert truth == pytest.approx(-0.20)
    out = sequential_decisions(b - a, margin=MARGIN, rate=True)
    assert np.mean(out.decision == "worse") >= 0.99
    assert not np.isin(out.decision, ["better", "not worse"]).any()


# --- the plan ----------------------------------------------------------------------------------


NULL_SEED_TYPES = [(0.9, 0.9), (0.05, 0.05), (0.3, 0.8), (0.8, 0.3)]
NULL_SEED_PROBS = [0.4, 0.3, 0.15, 0.15]
"""A strong seed effect and a true difference of 0: B wins whole seeds as often as it loses."""


def seed_world_differences(rng: np.random.Generator, trials: int, seeds: int, k: int = 2
                           ) -> tuple[np.ndarray, np.ndarray, float]:
    """``(trials, 4 seeds)`` per-world success differences of :data:`NULL_SEED_TYPES` seeds (four
    levels, ``k`` draws under common random numbers, worlds seed-major as compare orders them),
    their clusters ``(4 seeds,)`` and the true difference."""
    cat = np.asarray(NULL_SEED_TYPES)
    kind = rng.choice(len(cat), p=NULL_SEED_PROBS, size=(trials, seeds))
    u = rng.random((trials, seeds, 4, k))
    a = u < cat[kind, 0][..., None, None]
    b = u < cat[kind, 1][..., None, None]
    d = (b.astype(float) - a.astype(float)).mean(axis=-1).reshape(trials, 4 * seeds)
    truth = float(np.dot(NULL_SEED_PROBS, cat[:, 1] - cat[:, 0]))
    return d, np.repeat(np.arange(seeds), 4), truth


def test_fixed_plan_gives_its_power_on_success():
    """The plan under the clustered model: from a pilot's per-seed means (strong seed effect,
    true difference 0; 20 000 seeds, so that the test checks the formula, not the pilot's
    luck), 4 000 comparisons of the planned seeds (x 4 levels): compare's fixed interval (the
    cluster Bonett-Price interval over seeds) decides ``not worse`` at margin 5 pp with the
    planned 80 % (within 3 MC SE; measured 0.81 at 271 seeds). Mutation checked: planning on
    the per-world differences (the levels of a seed as independent worlds) asked for 369 worlds,
    93 seeds, where the power is 0.31: this test fails."""
    rng = np.random.default_rng(21)
    pilot, clusters, _ = seed_world_differences(rng, 1, 20000)
    plan = plan_worlds(paired.cluster_means(pilot[0], clusters), MARGIN, rate=True,
                       sequential=False, worlds_per_unit=4)
    d, clusters, truth = seed_world_differences(rng, RATE_TRIALS, plan.worlds)
    # +-(0.8 - 0.3) x 0.15 cancel; the rounding of 0.8 - 0.3 is the same on both sides
    assert truth == pytest.approx(0.0, abs=1e-12)
    iv = matched_rate_interval(d, clusters=clusters)  # compare's fixed_interval
    power = float(np.mean(np.isin(decide(iv.lo, iv.hi, MARGIN), ["better", "not worse"])))
    assert abs(power - 0.8) <= 3 * mc_se(0.8, RATE_TRIALS)


@pytest.mark.parametrize("rate", [False, True])
def test_sequential_plan_gives_at_least_its_power(rate):
    """Sequential plan (batches of 2 seeds) from a pilot of 20 000 seeds (true difference 0;
    normal per-seed differences, or success with a strong seed effect): the sequence over
    per-seed means tuned to the planned seeds decides ``not worse`` by then in >= 80 % (minus
    3 MC SE) of 2 000 comparisons, and the earlier looks do not make the plan wasteful
    (< 97 %)."""
    rng = np.random.default_rng(22)
    trials = 2000
    if rate:
        pilot, clusters, _ = seed_world_differences(rng, 1, 20000)
        pilot = paired.cluster_means(pilot[0], clusters)
    else:
        pilot = 0.3 * rng.standard_normal(20000)
    plan = plan_worlds(pilot, MARGIN, batch_size=2, rate=rate)
    if rate:
        d, clusters, _ = seed_world_differences(rng, trials, plan.worlds)
        units = paired.cluster_means(d, clusters)
    else:
        units = 0.3 * rng.standard_normal((trials, plan.worlds))
    out = sequential_decisions(units, margin=MARGIN, planned_worlds=plan.worlds, rate=rate,
                               batch_size=2)
    power = float(np.isin(out.decision, ["better", "not worse"]).mean())
    assert plan.worlds % 2 == 0
    assert 0.8 - 3 * mc_se(0.8, trials) <= power < 0.97


def test_plan_for_identical_arms_is_finite_and_enough():
    plan = plan_worlds(np.zeros(20), MARGIN, rate=True, batch_size=8)
    out = sequential_decisions(np.zeros(plan.worlds), margin=MARGIN, rate=True)
    assert 16 <= plan.worlds <= 200 and out.decision == "not worse"


# --- bad input ---------------------------------------------------------------------------------


def _ok() -> np.ndarray:
    return np.linspace(-0.5, 0.5, 20)


@pytest.mark.parametrize(
    ("name", "call"),
    [
        ("b", lambda: world_differences(np.ones(3), np.ones(4))),
        ("a", lambda: world_differences(np.ones(0), np.ones(0))),
        ("strata", lambda: world_differences(np.ones(3), np.ones(3), np.zeros(2, dtype=int))),
        ("clusters", lambda: world_differences(np.ones(3), np.ones(3), clusters=np.zeros(2))),
        ("a", lambda: pairing.world_means([0, 1], [0, 1], [1.0], [1.0])),
        ("differences", lambda: cluster_bootstrap_interval(np.ones(1), rng=0)),
        ("differences", lambda: cluster_bootstrap_interval(np.array([1.0, np.nan]), rng=0)),
        ("strata", lambda: cluster_bootstrap_interval(_ok(), np.zeros(3, dtype=int), rng=0)),
        ("clusters", lambda: cluster_bootstrap_interval(_ok(), clusters=np.zeros(20, dtype=int),
                                                        rng=0)),
        ("confidence", lambda: cluster_bootstrap_interval(_ok(), rng=0, confidence=1.0)),
        ("method", lambda: cluster_bootstrap_interval(_ok(), rng=0, method="studentized")),
        ("rng", lambda: cluster_bootstrap_interval(_ok(), rng=None)),
        ("clusters", lambda: matched_rate_interval(np.zeros(4), clusters=np.zeros(3, int))),
        ("looks", lambda: sequential_decisions(_ok(), margin=0.05, looks=[16, 12, 20])),
        ("differences", lambda: matched_rate_interval(np.array([0.0, 1.5]))),
        ("differences", lambda: matched_rate_interval(np.array([]))),
        ("confidence", lambda: matched_rate_interval(_ok(), confidence=0.0)),
        ("pseudo_weight", lambda: matched_rate_interval(_ok(), pseudo_weight=0.0)),
        ("alpha", lambda: paired.confidence_sequence(_ok(), planned_worlds=20, alpha=0.0)),
        ("alpha", lambda: paired.confidence_sequence(_ok(), planned_worlds=20, alpha=1.0)),
        ("planned_worlds", lambda: paired.confidence_sequence(_ok(), planned_worlds=0)),
        ("margin", lambda: decide(-0.1, 0.1, -0.01)),
        ("hi", lambda: decide(0.1, -0.1, 0.05)),
        ("hi", lambda: decide(np.zeros(2), np.zeros(3), 0.05)),
        ("margin", lambda: sequential_decisions(_ok(), margin=-0.05)),
        ("alpha", lambda: sequential_decisions(_ok(), margin=0.05, alpha=1.5)),
        ("batch_size", lambda: sequential_decisions(_ok(), margin=0.05, batch_size=0)),
        ("margin", lambda: plan_worlds(_ok(), -0.05)),
        ("alpha", lambda: plan_worlds(_ok(), 0.05, alpha=0.0)),
        ("power", lambda: plan_worlds(_ok(), 0.05, power=1.0)),
        ("expected_difference", lambda: plan_worlds(_ok(), 0.05, expected_difference=-0.05)),
        ("pilot_differences", lambda: plan_worlds(np.ones(1), 0.05)),
    ],
)
def test_bad_input_raises_naming_the_argument(name, call):
    with pytest.raises(ValueError, match=f"^{name}="):
        call()
