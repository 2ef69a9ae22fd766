"""Heuristic interface policies on constructed feature sequences (policies.heuristics)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import policies
from policies.base import INTERFACE_FEATURES
from policies.heuristics import AGE_TOLERANCE_S

# the project's rules: not the learned policy, nor planners that plug in from slam_gym (lookahead)
HEURISTIC_NAMES = [n for n in policies.available()
                   if n != "learned" and policies.REGISTRY.source(n) == "built-in"]


def features(**overrides: float) -> dict[str, float]:
    """A calm, unambiguous interface state (every contract name), with overrides."""
    f = {
        "local_map_age_s": 0.0,
        "local_map_distance_m": 0.0,
        "ess_ratio": 0.9,
        "particle_position_spread_m": 0.1,
        "particle_heading_spread_rad": 0.01,
        "local_feature_count": 5.0,
        "local_confirmed_count": 3.0,
        "vote_margin": 1.0,
        "innovation_ratio": 0.0,
        "global_features_in_view": 4.0,
        "global_position_std_m": 0.5,
        "global_heading_std_rad": 0.02,
        "time_since_optimise_s": 1000.0,
        "fusions_since_optimise": 0.0,
        "clutter_rate": 0.0,
        "loop_closure_flag": 0.0,
        "local_map_budget_ratio": 0.1,
        "loop_closures_since_optimise": 0.0,
        "stored_submaps": 0.0,
    }
    assert set(f) == set(INTERFACE_FEATURES)
    f.update(overrides)
    return f


def info(**overrides: float) -> dict:
    return {"features": features(**overrides)}


class FakeInterface:
    """Plays decisions like the env: 10 filter periods of 0.1 s per decision (ages accumulated as
    floats, so 10 s reads 9.99999999999998), a fusion restarts the local map (age 0), an
    optimisation restarts ``time_since_optimise_s``. Other features come from ``schedule(t)``."""

    def __init__(self, schedule=None, filter_dt=0.1, periods_per_decision=10):
        self.schedule = schedule or (lambda t: {})
        self.filter_dt = filter_dt
        self.periods = periods_per_decision

    def run(self, policy, n_decisions, time_since_optimise_s=1000.0):
        """Return a list of (t, features, action) for decisions at t = 1, 2, ... seconds."""
        age, t, tso = 0.0, 0.0, time_since_optimise_s
        history = []
        for _ in range(n_decisions):
            for _ in range(self.periods):
                age += self.filter_dt
                t += self.filter_dt
                tso += self.filter_dt
            f = features(local_map_age_s=age, time_since_optimise_s=tso)
            f.update(self.schedule(round(t, 6)))
            action = policy.act(None, {"features": f})
            assert action.dtype == np.int64 and action.shape == (2,)
            assert set(action.tolist()) <= {0, 1}
            history.append((round(t, 6), f, action))
            if action[0]:
                age = 0.0
            if action[1]:
                tso = 0.0
        return history


def fusion_times(history):
    return [t for t, _, a in history if a[0]]


def optimise_times(history):
    return [t for t, _, a in history if a[1]]


# ------------------------------------------------------------------------------------------------
# threshold-optimise (issue 29 item 3)
# ------------------------------------------------------------------------------------------------
def test_threshold_optimise_fuses_like_bb_and_optimises_only_at_fusions_above_the_threshold():
    policy = policies.make("threshold-optimise", feature="time_since_optimise_s", threshold=25.0)
    history = FakeInterface().run(policy, 100, time_since_optimise_s=0.0)
    assert fusion_times(history) == [10.0 * k for k in range(1, 11)]
    # optimise at the first fusion where >= 25 s passed since the last optimisation: 30, 60, 90
    assert optimise_times(history) == [30.0, 60.0, 90.0]


@pytest.mark.parametrize("threshold, expected", [(0.0, "every"), (1e9, "never")])
def test_threshold_optimise_ends_are_the_papers_rules(threshold, expected):
    rule = policies.make("threshold-optimise", feature="global_heading_std_rad",
                         threshold=threshold)
    reference = policies.make("fixed-10s-optimise" if expected == "every" else "fixed-10s")

    def schedule(t):
        return {"global_heading_std_rad": 0.001 * t}

    a = FakeInterface(schedule).run(rule, 60)
    b = FakeInterface(schedule).run(reference, 60)
    assert [x[2].tolist() for x in a] == [x[2].tolist() for x in b]


# ------------------------------------------------------------------------------------------------
# fixed-interval / fixed-10s (BB section 6)
# ------------------------------------------------------------------------------------------------
def test_fixed_10s_fuses_exactly_at_age_10_and_again_10s_after_the_reset():
    history = FakeInterface().run(policies.make("fixed-10s"), 45)
    assert fusion_times(history) == [10.0, 20.0, 30.0, 40.0]
    # the accumulated age really is below 10 at the fusion (the tolerance is what catches it)
    ages = [f["local_map_age_s"] for t, f, a in history if a[0]]
    assert all(abs(age - 10.0) < 1e-9 for age in ages)
    assert ages[0] < 10.0
    assert optimise_times(history) == []


def test_fixed_10s_does_not_fuse_before_age_10():
    policy = policies.make("fixed-10s")
    for age in (0.0, 5.0, 9.0, 9.99, 10.0 - 2 * AGE_TOLERANCE_S):
        assert policy.act(None, info(local_map_age_s=age)).tolist() == [0, 0]
    for age in (10.0, 10.0 - AGE_TOLERANCE_S / 2, 10.5, 60.0):
        assert policy.act(None, info(local_map_age_s=age)).tolist() == [1, 0]


def test_fixed_interval_with_an_interval_between_decisions_fuses_at_the_next_decision():
    history = FakeInterface().run(policies.make("fixed-interval", interval_s=2.5), 10)
    assert fusion_times(history) == [3.0, 6.0, 9.0]


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    interval=st.floats(0.1, 100.0),
    age=st.floats(0.0, 200.0),
)
def test_fixed_interval_fuses_iff_age_reaches_the_interval(interval, age):
    policy = policies.make("fixed-interval", interval_s=interval)
    fuse = policy.act(None, info(local_map_age_s=age))[0]
    if age >= interval:
        assert fuse == 1
    elif age < interval - AGE_TOLERANCE_S:
        assert fuse == 0


def test_fixed_interval_every_fusion_optimises_with_each_fusion():
    history = FakeInterface().run(policies.make("fixed-10s", optimise="every-fusion"), 35)
    assert fusion_times(history) == [10.0, 20.0, 30.0]
    assert optimise_times(history) == fusion_times(history)


def test_fixed_interval_on_loop_closure_optimises_once_per_closure_passage():
    def schedule(t):
        on = 13 <= t <= 16 or t == 18  # one closure passage with a flicker
        return {"loop_closure_flag": 1.0 if on else 0.0}

    policy = policies.make("fixed-10s", optimise="on-loop-closure")
    assert set(policy.required_features) == {
        "local_map_age_s",
        "loop_closure_flag",
        "time_since_optimise_s",
    }
    history = FakeInterface(schedule).run(policy, 45)
    assert fusion_times(history) == [10.0, 20.0, 30.0, 40.0]
    assert optimise_times(history) == [13.0]  # at once; 14..18 are the same passage (< 20 s)


# ------------------------------------------------------------------------------------------------
# esdf-innovation (CM III.B-C: BB's interval, the optimiser once per loop closure)
# ------------------------------------------------------------------------------------------------
def test_esdf_innovation_fuses_on_bbs_interval_whatever_the_innovation():
    history = FakeInterface(lambda t: {"innovation_ratio": 5.0 if t == 3.0 else 0.1}).run(
        policies.make("esdf-innovation"), 35
    )
    assert fusion_times(history) == [10.0, 20.0, 30.0]


def test_esdf_innovation_fuses_when_the_local_map_outgrows_its_budget():
    policy = policies.make("esdf-innovation")
    assert policy.act(None, info(local_map_age_s=4.0, local_map_budget_ratio=0.99))[0] == 0
    assert policy.act(None, info(local_map_age_s=4.0, local_map_budget_ratio=1.0))[0] == 1


def test_esdf_innovation_optimises_once_per_detected_loop_closure():
    def schedule(t):
        # closure 1: closures reported after the fusions at 40 and 50 s (one passage), closure 2
        # after the fusion at 90 s
        return {"loop_closure_flag": 1.0 if t in (41.0, 51.0, 91.0) else 0.0}

    history = FakeInterface(schedule).run(policies.make("esdf-innovation"), 100)
    assert optimise_times(history) == [41.0, 91.0]
    assert fusion_times(history) == [float(t) for t in range(10, 101, 10)]


def test_esdf_innovation_debounce_interval_is_configurable():
    def schedule(t):
        return {"loop_closure_flag": 1.0 if t in (41.0, 51.0) else 0.0}

    short = FakeInterface(schedule).run(
        policies.make("esdf-innovation", min_optimise_interval_s=5.0), 60
    )
    assert optimise_times(short) == [41.0, 51.0]


def test_esdf_innovation_no_optimisation_with_optimise_never():
    history = FakeInterface(lambda t: {"loop_closure_flag": 1.0}).run(
        policies.make("esdf-innovation", optimise="never"), 30
    )
    assert optimise_times(history) == []


# ------------------------------------------------------------------------------------------------
# innovation-fusion (CM III.B's test as a fusion trigger)
# ------------------------------------------------------------------------------------------------
def test_innovation_fusion_fuses_when_the_ratio_crosses_one_and_not_before():
    policy = policies.make("innovation-fusion")
    ratios = [0.0, 0.3, 0.7, 0.95, 0.999, 1.0, 1.001, 1.7]
    fused = [policy.act(None, info(local_map_age_s=5.0, innovation_ratio=r))[0] for r in ratios]
    assert fused == [0, 0, 0, 0, 0, 0, 1, 1]


def test_innovation_fusion_in_a_sequence_fuses_at_the_crossing():
    ratios = {1: 0.2, 2: 0.4, 3: 0.8, 4: 0.99, 5: 1.3, 6: 0.1, 7: 0.2, 8: 1.2, 9: 0.3}
    history = FakeInterface(lambda t: {"innovation_ratio": ratios.get(int(t), 0.0)}).run(
        policies.make("innovation-fusion"), 12
    )
    assert fusion_times(history) == [5.0, 8.0]


def test_innovation_fusion_fuses_when_the_local_map_outgrows_its_budget():
    policy = policies.make("innovation-fusion")
    assert policy.act(None, info(local_map_age_s=4.0, local_map_budget_ratio=0.99))[0] == 0
    assert policy.act(None, info(local_map_age_s=4.0, local_map_budget_ratio=1.0))[0] == 1
    assert policy.act(None, info(local_map_age_s=4.0, local_map_budget_ratio=1.4))[0] == 1


def test_innovation_fusion_caps_the_local_map_age():
    history = FakeInterface().run(policies.make("innovation-fusion"), 65)
    assert fusion_times(history) == [30.0, 60.0]
    history = FakeInterface().run(policies.make("innovation-fusion", max_age_s=12.0), 30)
    assert fusion_times(history) == [12.0, 24.0]


def test_innovation_fusion_min_age_holds_a_young_local_map():
    policy = policies.make("innovation-fusion", min_age_s=3.0)
    assert policy.act(None, info(local_map_age_s=2.0, innovation_ratio=5.0))[0] == 0
    assert policy.act(None, info(local_map_age_s=3.0, innovation_ratio=5.0))[0] == 1


# ------------------------------------------------------------------------------------------------
# never / always (BB section 6: the two extremes)
# ------------------------------------------------------------------------------------------------
_feature_values = st.fixed_dictionaries(
    {name: st.floats(0.0, 100.0) for name in INTERFACE_FEATURES}
)


@settings(max_examples=100, deadline=None, derandomize=True)
@given(f=_feature_values)
def test_never_and_always_ignore_the_state(f):
    assert policies.make("never").act(None, {"features": f}).tolist() == [0, 0]
    assert policies.make("always").act(None, {"features": f}).tolist() == [1, 0]
    assert policies.make("always", optimise="every-fusion").act(None, {"features": f}).tolist() == [
        1,
        1,
    ]


def test_never_and_always_over_an_episode():
    assert fusion_times(FakeInterface().run(policies.make("never"), 30)) == []
    history = FakeInterface().run(policies.make("always"), 30)
    assert fusion_times(history) == [float(t) for t in range(1, 31)]
    assert all(abs(f["local_map_age_s"] - 1.0) < 1e-9 for _, f, _ in history)
    assert policies.make("never").required_features == ()
    assert policies.make("always").required_features == ()
    assert policies.make("never").act(None, {"features": {}}).tolist() == [0, 0]


# ------------------------------------------------------------------------------------------------
# adaptive-diversity (BB section 6)
# ------------------------------------------------------------------------------------------------
def test_adaptive_behaves_like_bb_when_unambiguous_and_diverse():
    history = FakeInterface().run(policies.make("adaptive-diversity"), 35)
    assert fusion_times(history) == [10.0, 20.0, 30.0]


def test_adaptive_delays_fusion_while_the_vote_margin_is_low():
    low = lambda t: {"vote_margin": 0.2 if 8 <= t <= 15 else 1.0}  # noqa: E731
    history = FakeInterface(low).run(policies.make("adaptive-diversity"), 30)
    assert fusion_times(history)[0] == 16.0  # held past 10 s, fused once the margin recovered
    assert fusion_times(history) == [16.0, 26.0]


def test_adaptive_delay_is_bounded_by_the_max_age():
    always_low = lambda t: {"vote_margin": 0.1}  # noqa: E731
    history = FakeInterface(always_low).run(policies.make("adaptive-diversity"), 65)
    assert fusion_times(history) == [30.0, 60.0]
    history = FakeInterface(always_low).run(policies.make("adaptive-diversity", max_age_s=15.0), 32)
    assert fusion_times(history) == [15.0, 30.0]


@pytest.mark.parametrize(
    "feature, value",
    [("particle_position_spread_m", 2.5), ("particle_heading_spread_rad", math.radians(12.0))],
)
def test_adaptive_delays_fusion_while_the_pose_distribution_is_spread(feature, value):
    spread = lambda t: {feature: value if 9 <= t <= 13 else 0.05}  # noqa: E731
    history = FakeInterface(spread).run(policies.make("adaptive-diversity"), 20)
    assert fusion_times(history) == [14.0]


def test_adaptive_fuses_early_when_particle_diversity_drops():
    low_ess = lambda t: {"ess_ratio": 0.1 if t == 5.0 else 0.9}  # noqa: E731
    history = FakeInterface(low_ess).run(policies.make("adaptive-diversity"), 16)
    assert fusion_times(history) == [5.0, 15.0]


def test_adaptive_early_fusion_respects_the_min_age():
    low_ess = lambda t: {"ess_ratio": 0.1}  # noqa: E731
    history = FakeInterface(low_ess).run(policies.make("adaptive-diversity"), 12)
    assert fusion_times(history) == [3.0, 6.0, 9.0, 12.0]
    history = FakeInterface(low_ess).run(policies.make("adaptive-diversity", min_age_s=5.0), 12)
    assert fusion_times(history) == [5.0, 10.0]


def test_adaptive_ambiguity_wins_over_low_diversity():
    policy = policies.make("adaptive-diversity")
    assert policy.act(None, info(local_map_age_s=5.0, ess_ratio=0.1)).tolist() == [1, 0]
    assert policy.act(None, info(local_map_age_s=5.0, ess_ratio=0.1, vote_margin=0.3))[0] == 0
    assert policy.act(None, info(local_map_age_s=5.0, ess_ratio=0.3))[0] == 0
    assert policy.act(None, info(local_map_age_s=2.9, ess_ratio=0.1))[0] == 0


# ------------------------------------------------------------------------------------------------
# imminent-closure (BB 5.4)
# ------------------------------------------------------------------------------------------------
def _exploring_then_old_region(rise_at: float, rise: float):
    """Global features in view fall while exploring and jump by ``rise`` at ``rise_at``.

    The local maps fused at 10 s and 20 s are in view from the next decision on (6 features, then
    fewer as the vehicle moves away)."""

    def schedule(t):
        since_fusion = (t - 1.0) % 10.0 if t <= 20 else t - 21.0
        count = max(6.0 - 0.5 * since_fusion, 1.0)
        return {"global_features_in_view": count + (rise if t >= rise_at else 0.0)}

    return schedule


def test_imminent_closure_runs_the_local_map_longer_when_old_features_come_into_view():
    history = FakeInterface(_exploring_then_old_region(25.0, 4.0)).run(
        policies.make("imminent-closure"), 60
    )
    # the local map started at 20 s saw old features arrive at 25 s: it runs until age 30
    assert fusion_times(history) == [10.0, 20.0, 50.0, 60.0]


def test_imminent_closure_ignores_a_small_rise():
    history = FakeInterface(_exploring_then_old_region(25.0, 2.0)).run(
        policies.make("imminent-closure"), 40
    )
    assert fusion_times(history) == [10.0, 20.0, 30.0, 40.0]


def test_imminent_closure_extends_on_the_loop_closure_flag():
    flag = lambda t: {"loop_closure_flag": 1.0 if t == 7.0 else 0.0}  # noqa: E731
    policy = policies.make("imminent-closure", extended_interval_s=25.0)
    history = FakeInterface(flag).run(policy, 40)
    assert fusion_times(history) == [25.0, 35.0]


def test_imminent_closure_reset_clears_the_latch():
    policy = policies.make("imminent-closure")
    assert policy.act(None, info(local_map_age_s=4.0, loop_closure_flag=1.0))[0] == 0
    assert policy.closure_imminent
    assert policy.act(None, info(local_map_age_s=10.0))[0] == 0  # extended to 30 s
    policy.reset()
    assert not policy.closure_imminent
    assert policy.act(None, info(local_map_age_s=10.0))[0] == 1


# ------------------------------------------------------------------------------------------------
# Contract: options, names, features
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name, options, field",
    [
        ("fixed-interval", {"interval_s": 0.0}, "interval_s"),
        ("fixed-interval", {"interval_s": -3.0}, "interval_s"),
        ("fixed-interval", {"interval_s": float("nan")}, "interval_s"),
        ("fixed-interval", {"interval_s": float("inf")}, "interval_s"),
        ("fixed-interval", {"interval_s": "10"}, "interval_s"),
        ("fixed-interval", {"interval_s": True}, "interval_s"),
        ("fixed-interval", {"optimise": "sometimes"}, "optimise"),
        ("fixed-10s", {"optimise": "always"}, "optimise"),
        ("fixed-interval", {"min_optimise_interval_s": -1.0}, "min_optimise_interval_s"),
        ("always", {"optimise": None}, "optimise"),
        ("innovation-fusion", {"threshold": 0.0}, "threshold"),
        ("innovation-fusion", {"budget_ratio": -1.0}, "budget_ratio"),
        ("innovation-fusion", {"max_age_s": 0.0}, "max_age_s"),
        ("innovation-fusion", {"min_age_s": 30.0}, "min_age_s"),
        ("esdf-innovation", {"budget_ratio": 0.0}, "budget_ratio"),
        ("esdf-innovation", {"interval_s": -1.0}, "interval_s"),
        ("adaptive-diversity", {"nominal_interval_s": 0.0}, "nominal_interval_s"),
        ("adaptive-diversity", {"min_age_s": 11.0}, "min_age_s"),
        ("adaptive-diversity", {"max_age_s": 9.0}, "max_age_s"),
        ("adaptive-diversity", {"vote_margin_threshold": 1.2}, "vote_margin_threshold"),
        ("adaptive-diversity", {"position_spread_threshold_m": 0.0}, "position_spread_threshold_m"),
        (
            "adaptive-diversity",
            {"heading_spread_threshold_rad": 4.0},
            "heading_spread_threshold_rad",
        ),
        ("adaptive-diversity", {"ess_threshold": -0.1}, "ess_threshold"),
        ("imminent-closure", {"rise_count": 0}, "rise_count"),
        ("imminent-closure", {"rise_count": 2.5}, "rise_count"),
        ("imminent-closure", {"extended_interval_s": 5.0}, "extended_interval_s"),
        ("threshold-optimise", {"feature": "ess_ratio"}, "feature"),
        ("threshold-optimise", {"threshold": -0.5}, "threshold"),
        ("threshold-optimise", {"threshold": float("nan")}, "threshold"),
    ],
)
def test_bad_option_raises_value_error_naming_field_value_and_range(name, options, field):
    with pytest.raises(ValueError) as excinfo:
        policies.make(name, **options)
    message = str(excinfo.value)
    assert message.startswith(f"{field}=")
    assert repr(options[field]) in message
    assert "must be" in message


def test_unknown_option_lists_the_allowed_options():
    with pytest.raises(ValueError, match="interval") as excinfo:
        policies.make("fixed-interval", intervall_s=5.0)
    assert "intervall_s" in str(excinfo.value)
    assert "optimise" in str(excinfo.value)
    with pytest.raises(ValueError, match="no options"):
        policies.make("never", interval_s=1.0)


def test_alias_fixes_its_interval():
    assert policies.make("fixed-10s").interval_s == 10.0
    assert policies.make("fixed-10s", interval_s=10.0).interval_s == 10.0
    with pytest.raises(ValueError, match="interval_s=5.0.*fixed-interval"):
        policies.make("fixed-10s", interval_s=5.0)


@pytest.mark.parametrize("bad", ["fixed-20s", "ESDF-innovation", "", None])
def test_unknown_policy_name_lists_the_available_names(bad):
    with pytest.raises(ValueError) as excinfo:
        policies.make(bad)
    message = str(excinfo.value)
    assert repr(bad) in message
    for name in policies.available():
        assert name in message


def test_available_lists_the_design_policies():
    names = policies.available()
    for expected in (
        "fixed-interval",
        "fixed-10s",
        "esdf-innovation",
        "never",
        "always",
        "adaptive-diversity",
        "imminent-closure",
        "learned",
    ):
        assert expected in names
    assert names == sorted(names)


@pytest.mark.parametrize(
    "name, options",
    [(n, {}) for n in HEURISTIC_NAMES]
    + [
        ("fixed-interval", {"optimise": "on-loop-closure"}),
        ("adaptive-diversity", {"optimise": "on-loop-closure"}),
        ("imminent-closure", {"optimise": "on-loop-closure"}),
    ],
)
def test_required_features_are_exactly_what_the_policy_reads(name, options):
    policy = policies.make(name, **options)
    required = policy.required_features
    assert set(required) <= set(INTERFACE_FEATURES)
    assert len(set(required)) == len(required)
    # only the declared names suffice ...
    full = features(local_map_age_s=12.0)
    only = {k: full[k] for k in required}
    assert (
        policy.act(None, {"features": only}).tolist()
        == policy.act(None, {"features": full}).tolist()
    )
    # ... and each one is needed
    for missing in required:
        policy.reset()
        partial = {k: v for k, v in only.items() if k != missing}
        with pytest.raises(KeyError) as excinfo:
            policy.act(None, {"features": partial})
        message = str(excinfo.value)
        assert missing in message
        assert policy.name in message  # an alias reports the policy it stands for


@pytest.mark.parametrize("name", HEURISTIC_NAMES)
def test_info_without_features_raises_key_error(name):
    with pytest.raises(KeyError, match="info\\['features'\\]"):
        policies.make(name).act(None, {})


def test_nan_feature_raises_value_error_naming_it():
    with pytest.raises(ValueError, match="innovation_ratio"):
        policies.make("innovation-fusion").act(None, info(innovation_ratio=float("nan")))


@pytest.mark.parametrize("name", HEURISTIC_NAMES)
def test_heuristics_never_read_the_observation_vector(name):
    state = info(local_map_age_s=10.0, innovation_ratio=1.2, ess_ratio=0.1)
    a = policies.make(name).act(None, state)
    b = policies.make(name).act(np.full(len(INTERFACE_FEATURES), np.nan, np.float32), state)
    assert a.tolist() == b.tolist()
    assert a.dtype == np.int64 and a.shape == (2,)
