"""Calibration tests of slam_gym/evaluation/paired.py: coverage of the fixed intervals, error rate
of the sequential decision under repeated looks, the decision rule, the plan, bad input.

Every simulation is seeded and vectorised; the synthetic comparisons follow the data model of
``slam-gym compare``: worlds in four clutter strata, K filter draws per world and policy with
common random numbers (the same uniform decides both arms' draw unless a share of the draws is
made independent), per-world means, left-out worlds. Monte Carlo standard errors are quoted
where a threshold is set from them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from slam_gym.evaluation import paired
from slam_gym.evaluation.paired import (
    cs_multiplier,
    cs_rho,
    decide,
    matched_rate_interval,
    metric_direction,
    plan_worlds,
    sequential_decisions,
    stratified_bootstrap_interval,
    world_differences,
    world_means,
)

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


def naive_repeated_t(d: np.ndarray, margin: float, alpha: float, batch: int,
                     min_worlds: int) -> np.ndarray:
    """The wrong way: at every look a one-sided level-``alpha`` t-test of ``mean > -margin``
    (lower t bound > -margin), stopping at the first success. Each look alone is a valid test."""
    n = d.shape[-1]
    hit = np.zeros(d.shape[:-1], dtype=bool)
    for t in range(batch, n + 1, batch):
        if t < min_worlds:
            continue
        x = d[..., :t]
        se = x.std(axis=-1, ddof=1) / math.sqrt(t)
        lo = x.mean(axis=-1) - stats.t.ppf(1.0 - alpha, t - 1) * se
        hit |= lo > -margin
    return hit


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


def test_world_means_leave_out_missing_draws_and_empty_worlds():
    values = np.array([[1.0, np.nan, 3.0], [np.nan, np.nan, np.nan], [0.0, 1.0, 1.0]])
    means = world_means(values)
    assert means[0] == 2.0 and np.isnan(means[1]) and means[2] == pytest.approx(2 / 3)


def test_world_differences_orient_drop_and_count():
    a = np.array([1.0, 2.0, np.nan, 4.0, 5.0])
    b = np.array([2.0, 1.0, 3.0, np.inf, 5.5])
    wd = world_differences(a, b, np.array([0, 1, 2, 3, 3]))
    assert wd.n_left_out == 2 and len(wd) == 3
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


def test_bootstrap_estimate_strata_and_reproducibility():
    d = np.array([1.0, 3.0, 10.0, 14.0, 2.0, 6.0])
    strata = np.array([0, 0, 1, 1, 2, 3])  # levels 2 and 3 have one world each: merged
    one = stratified_bootstrap_interval(d, strata, rng=7, n_resamples=999)
    two = stratified_bootstrap_interval(d, strata, rng=7, n_resamples=999)
    assert one == two
    assert one.estimate == pytest.approx(d.mean())
    assert one.lo < one.estimate < one.hi
    flat = stratified_bootstrap_interval(np.zeros(5), rng=0)
    assert (flat.lo, flat.hi) == (0.0, 0.0)


COVERAGE_TRIALS = 1000


def bootstrap_coverage(n: int, sigma_world: float, methods: tuple[str, ...], seed: int
                       ) -> dict[str, tuple[float, float, float]]:
    """Coverage, lower miss (truth below lo) and upper miss of the stratified bootstrap on map
    errors of ``n`` worlds (B 20 % better, K = 3 draws, 10 % of runs without a map error)."""
    rng = np.random.default_rng(seed)
    truth = map_error_truth(n, 0.8, sigma_world)
    hits = {m: np.zeros(3) for m in methods}
    for _ in range(COVERAGE_TRIALS):
        a, b, strata = map_error_worlds(rng, n, 3, 0.8, sigma_world)
        wd = world_differences(world_means(a), world_means(b), strata, lower_is_better=True)
        for method in methods:
            iv = stratified_bootstrap_interval(wd.differences, wd.strata, rng=rng,
                                               n_resamples=999, method=method)
            hits[method] += (iv.lo <= truth <= iv.hi, truth < iv.lo, truth > iv.hi)
    return {m: tuple(h / COVERAGE_TRIALS) for m, h in hits.items()}


def test_bootstrap_covers_skewed_clustered_map_errors_at_96_worlds():
    """The default (corrected percentile) covers at >= 93 % (1 000 trials; MC SE 0.7 pp at 95 %)
    on differences with skewness ~1 and excess kurtosis ~9, 96 worlds (the size of a
    comparison); measured 0.938 (truth below lo 0.027, above hi 0.035)."""
    (cover, below, above), = bootstrap_coverage(96, 0.3, ("percentile",), seed=1).values()
    print(f"bootstrap 96 worlds: coverage {cover:.3f}, truth below lo {below:.3f}, "
          f"above hi {above:.3f}")
    assert cover >= 0.93


def test_percentile_beats_bca_on_clustered_map_errors_at_48_worlds():
    """Why percentile: on the same 1 000 comparisons of 48 worlds, BCa (same corrections) covers
    less than the percentile interval (measured 0.925 against 0.939, which is >= 93 %)."""
    res = bootstrap_coverage(48, 0.3, ("percentile", "BCa"), seed=2)
    print("bootstrap 48 worlds:", {m: round(float(v[0]), 3) for m, v in res.items()})
    assert res["percentile"][0] >= 0.93
    assert res["percentile"][0] > res["BCa"][0]


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
    d = np.array([1.0] * 7 + [-1.0] * 3 + [0.0] * 30)
    iv = matched_rate_interval(d, pseudo_weight=weight)
    lo, hi = two_by_two_interval(3, 7, 40, weight)
    assert (iv.lo, iv.hi) == (pytest.approx(lo), pytest.approx(hi))


def test_rate_interval_with_no_discordant_world_has_width():
    iv = matched_rate_interval(np.zeros(40))
    half = 1.959963984540054 * math.sqrt(2.0 / 42.0) / math.sqrt(42.0)
    assert (iv.estimate, iv.lo, iv.hi) == (0.0, pytest.approx(-half), pytest.approx(half))


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
    "identical arms": (3, 40, [(0.9, 0.9)], [1.0], 0.0),
}


@pytest.mark.parametrize("name", list(RATE_SCENARIOS))
def test_rate_interval_covers(name):
    """Coverage >= 93.97 % (nominal 95 % minus 3 MC SE, 4 000 trials) in every scenario,
    including rare, one-directional and zero discordance and clustered draws."""
    k, n, catalogue, probs, independent = RATE_SCENARIOS[name]
    rng = np.random.default_rng(100 + list(RATE_SCENARIOS).index(name))
    a, b, truth = rate_worlds(rng, RATE_TRIALS, n, k, catalogue, probs, independent)
    iv = matched_rate_interval(b - a)
    cover = float(np.mean((iv.lo <= truth) & (truth <= iv.hi)))
    print(f"{name}: truth {truth:+.3f}, coverage {cover:.4f}")
    assert cover >= 0.95 - 3 * mc_se(0.95, RATE_TRIALS)


def test_agresti_min_weight_fails_where_b_only_loses():
    """Why Bonett-Price's weight: with Agresti-Min's half pseudo-worlds the interval misses a
    one-directional loss of 7 pp on 80 worlds too often (measured 0.92; Bonett-Price 0.97)."""
    rng = np.random.default_rng(5)
    a, b, truth = rate_worlds(rng, RATE_TRIALS, 80, 1, [(1, 1), (1, 0)], [0.93, 0.07])
    half = matched_rate_interval(b - a, pseudo_weight=0.5)
    full = matched_rate_interval(b - a)
    cover_half = float(np.mean((half.lo <= truth) & (truth <= half.hi)))
    cover_full = float(np.mean((full.lo <= truth) & (truth <= full.hi)))
    print(f"B only loses 7 pp, 80 worlds: Agresti-Min {cover_half:.4f}, "
          f"Bonett-Price {cover_full:.4f}")
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
    assert cs.hi - cs.estimate == pytest.approx(cs_multiplier() * d.std(ddof=1) / math.sqrt(96))
    assert cs_multiplier() == pytest.approx(3.035, abs=1e-3)


SEQ_TRIALS = 4000
MARGIN = 0.05


def false_positive(d: np.ndarray, *, rate: bool,
                   design: str = "confidence-sequence") -> tuple[float, float]:
    """Share of comparisons declared ``not worse``/``better`` by the sequential ``design`` and by
    the naive repeated t-test, looking after every batch of 8 worlds from 16 on."""
    out = sequential_decisions(d, margin=MARGIN, alpha=ALPHA, batch_size=8, rate=rate,
                               design=design)
    fp = float(np.isin(out.decision, ["better", "not worse"]).mean())
    naive = float(naive_repeated_t(d, MARGIN, ALPHA, 8, paired.MIN_WORLDS).mean())
    return fp, naive


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
    """True difference exactly -margin, looks after every batch of 8 up to ``max_worlds``: either
    design declares ``not worse`` at most alpha (+ 2 MC SE, 4 000 trials) of the time; the
    naive repeated t-test on the same data, clearly more (at least alpha + 10 MC SE). Measured:
    the confidence sequence 0.000-0.026, the group-sequential design 0.011-0.052 (its one-sided
    nominal is alpha / 2; it reaches alpha where B only ever loses, 5 % of worlds: a skewed 0/1
    difference)."""
    rng = np.random.default_rng(40 + max_worlds + len(name))
    a, b, truth = NULL_SCENARIOS[name](rng, max_worlds)
    assert truth == pytest.approx(-MARGIN)
    fp, naive = false_positive(b - a, rate=True, design=design)
    print(f"{name}, {max_worlds} worlds, {design}: false positive {fp:.4f}, naive t {naive:.4f}")
    assert fp <= ALPHA + 2 * mc_se(ALPHA, SEQ_TRIALS)
    assert naive >= ALPHA + 10 * mc_se(ALPHA, SEQ_TRIALS)


@pytest.mark.parametrize("max_worlds", [96, 200])
def test_sequential_false_positive_rate_skewed_continuous(max_worlds):
    """Left-skewed differences (skewness 1.75), mean exactly -margin, sd 4 margins: the same
    check as for success. Measured 0.040 (96) and 0.034 (200); heavier skew is documented. (The
    group-sequential design is refused for continuous metrics: on these data it measured 0.064
    at 96 worlds, 0.044 at 200.)"""
    rng = np.random.default_rng(7 + max_worlds)
    d = left_skewed(rng, SEQ_TRIALS, max_worlds, -MARGIN, 4 * MARGIN)
    fp, naive = false_positive(d, rate=False)
    print(f"left-skewed, {max_worlds} worlds: false positive {fp:.4f}, naive t {naive:.4f}")
    assert fp <= ALPHA + 2 * mc_se(ALPHA, SEQ_TRIALS)
    assert naive >= ALPHA + 10 * mc_se(ALPHA, SEQ_TRIALS)


def test_group_sequential_bounds_are_the_published_ones():
    """Five equally spaced looks, two-sided alpha 0.05, O'Brien-Fleming-type spending of
    alpha / 2 a side: gsDesign's sfLDOF bounds (Jennison & Turnbull 2000, table 2.3's
    Lan-DeMets analogue) 4.877, 3.357, 2.680, 2.290, 2.031; one look is the fixed 1.96."""
    bounds = paired.group_sequential_bounds([0.2, 0.4, 0.6, 0.8, 1.0])
    assert bounds == pytest.approx([4.877, 3.357, 2.680, 2.290, 2.031], abs=2e-3)
    assert paired.group_sequential_bounds([1.0])[0] == pytest.approx(stats.norm.isf(0.025))
    assert paired.obrien_fleming_spending(1.0) == pytest.approx(ALPHA)


def test_group_sequential_bounds_hold_alpha_on_brownian_paths():
    """The recursion itself, by simulation: a standard Brownian motion seen at the looks of
    ``compare``'s default batches (16, 24, ..., 200 worlds of 200) leaves the bounds at some look
    with probability alpha (200 000 paths: within 3 MC SE), and at each look k at most the
    spending function's alpha(t_k)."""
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
    print(f"worse by 400 worlds: {worse}")
    assert worse["group-sequential"] >= worse["confidence-sequence"] + 0.2


def test_group_sequential_design_is_refused_for_continuous_metrics():
    with pytest.raises(ValueError, match="design='group-sequential' is invalid"):
        sequential_decisions(np.zeros(32), margin=MARGIN, design="group-sequential")
    with pytest.raises(ValueError, match="design='sprt' is invalid"):
        sequential_decisions(np.zeros(32), margin=MARGIN, rate=True, design="sprt")


def test_naive_test_is_valid_at_one_look():
    """The naive test's error comes from the repeated looks: looked at once (at 96 worlds) it
    keeps its level on normal differences (within 3 MC SE)."""
    rng = np.random.default_rng(9)
    d = -MARGIN + 4 * MARGIN * rng.standard_normal((SEQ_TRIALS, 96))
    once = naive_repeated_t(d, MARGIN, ALPHA, 96, 96).mean()
    assert abs(once - ALPHA) <= 3 * mc_se(ALPHA, SEQ_TRIALS)


@pytest.mark.parametrize(("margin", "by"), [(0.05, 96), (0.1, 56), (0.2, 32)])
def test_identical_arms_decide_not_worse(margin, by):
    """Success: no discordant world at all (identical policies) still decides ``not worse``
    after a modest number of worlds (planned 200, looks every 8)."""
    out = sequential_decisions(np.zeros(200), margin=margin, rate=True, planned_worlds=200)
    assert out.decision == "not worse" and out.n_worlds <= by
    flat = sequential_decisions(np.zeros(200), margin=1e-6)  # continuous: zero variance
    assert flat.decision == "not worse" and flat.n_worlds == paired.MIN_WORLDS


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
    by_96 = np.mean((out.decision == "worse") & (out.n_worlds <= 96))
    print(f"clearly worse: worse by 96 worlds {by_96:.3f}, median worlds {np.median(out.n_worlds)}")


# --- the plan ----------------------------------------------------------------------------------


def test_fixed_plan_gives_its_power_on_success():
    """Plan from a pilot (3 clustered draws, true difference 0; 20 000 worlds, so that the test
    checks the formula, not the pilot's luck), then 4 000 comparisons of the planned size: the
    fixed interval decides ``not worse`` at margin 5 pp with the planned 80 % (within 3 MC SE)."""
    rng = np.random.default_rng(21)
    catalogue, probs = [(0.9, 0.9), (0.6, 0.8), (0.8, 0.6), (0.4, 0.4)], [0.6, 0.15, 0.15, 0.1]
    pa, pb, _ = rate_worlds(rng, 1, 20000, 3, catalogue, probs, 0.3)
    plan = plan_worlds((pb - pa)[0], MARGIN, rate=True, sequential=False)
    a, b, truth = rate_worlds(rng, RATE_TRIALS, plan.worlds, 3, catalogue, probs, 0.3)
    assert truth == 0.0
    iv = matched_rate_interval(b - a)
    power = float(np.mean(np.isin(decide(iv.lo, iv.hi, MARGIN), ["better", "not worse"])))
    print(f"fixed plan: {plan.worlds} worlds, power {power:.3f}")
    assert abs(power - 0.8) <= 3 * mc_se(0.8, RATE_TRIALS)


@pytest.mark.parametrize("rate", [False, True])
def test_sequential_plan_gives_at_least_its_power(rate):
    """Sequential plan (batches of 8) from a pilot of 20 000 worlds (true difference 0; normal
    differences, or success over 3 clustered draws): the sequence tuned to the planned worlds
    decides ``not worse`` by then in >= 80 % (minus 3 MC SE) of 2 000 comparisons, and the
    earlier looks do not make the plan wasteful (< 97 %)."""
    rng = np.random.default_rng(22)
    trials = 2000
    catalogue, probs = [(0.9, 0.9), (0.6, 0.8), (0.8, 0.6), (0.4, 0.4)], [0.7, 0.1, 0.1, 0.1]
    if rate:
        pa, pb, _ = rate_worlds(rng, 1, 20000, 3, catalogue, probs, 0.3)
        pilot = (pb - pa)[0]
    else:
        pilot = 0.3 * rng.standard_normal(20000)
    plan = plan_worlds(pilot, MARGIN, batch_size=8, rate=rate)
    if rate:
        a, b, _ = rate_worlds(rng, trials, plan.worlds, 3, catalogue, probs, 0.3)
        d = b - a
    else:
        d = 0.3 * rng.standard_normal((trials, plan.worlds))
    out = sequential_decisions(d, margin=MARGIN, planned_worlds=plan.worlds, rate=rate)
    power = float(np.isin(out.decision, ["better", "not worse"]).mean())
    print(f"sequential plan (rate={rate}): {plan.worlds} worlds, power {power:.3f}")
    assert plan.worlds % 8 == 0
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
        ("values", lambda: world_means(np.ones(3))),
        ("differences", lambda: stratified_bootstrap_interval(np.ones(1), rng=0)),
        ("differences", lambda: stratified_bootstrap_interval(np.array([1.0, np.nan]), rng=0)),
        ("strata", lambda: stratified_bootstrap_interval(_ok(), np.zeros(3, dtype=int), rng=0)),
        ("confidence", lambda: stratified_bootstrap_interval(_ok(), rng=0, confidence=1.0)),
        ("method", lambda: stratified_bootstrap_interval(_ok(), rng=0, method="studentized")),
        ("rng", lambda: stratified_bootstrap_interval(_ok(), rng=None)),
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
