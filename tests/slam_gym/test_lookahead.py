"""The env's copies and re-seeded futures, and the lookahead policy planned on them (issue 39)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import policies
from slam_gym.envs.hybrid_slam import HybridSLAMEnv
from slam_gym.envs.spec import resolve_env
from slam_gym.evaluation.core import run_policy_object
from slam_gym.lookahead import FullLookahead, LookaheadPolicy, PrivilegedLookahead
from slam_gym.scenarios import get_scenario
from slam_gym.stream import ArraySteps, Stream
from slam_gym.world import RedrawnFuture, simulate

RULE = "fixed-10s-optimise"


def _env_after(n_decisions: int, **options) -> tuple[HybridSLAMEnv, np.ndarray, dict]:
    env = HybridSLAMEnv(**({"n_particles": 40, "clutter_level": 2} | options))
    rule = policies.make(RULE)
    obs, info = env.reset(seed=5, options={"world_seed": 12})
    for _ in range(n_decisions):
        obs, _, terminated, truncated, info = env.step(rule.act(obs, info))
        assert not (terminated or truncated)
    return env, obs, info


def _play(env, actions):
    """Observations, rewards and the comparable parts of the infos of ``actions`` from env."""
    out = []
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(np.asarray(action, dtype=np.int64))
        out.append((obs.tobytes(), reward, terminated, info["nees"], info["n_fusions"],
                    info["n_optimisations"], info["pose_error_m"], info["map_error_m"]))
        if terminated or truncated:
            break
    return out


# every kind of decision: nothing, fuse, optimise alone, fuse and optimise
ACTIONS = [(0, 0), (1, 0), (0, 1), (1, 1), (0, 0), (1, 1), (0, 0), (1, 0), (0, 0), (0, 1)] * 2


@pytest.mark.parametrize("back_end", ["ekf", "relative"])
def test_a_clone_continues_bit_for_bit_and_leaves_the_original_alone(back_end):
    env, _, _ = _env_after(12, back_end=back_end)
    twin = env.clone()
    cloned = _play(twin, ACTIONS)  # the copy first: it must not move the original
    original = _play(env, ACTIONS)
    assert len(original) == len(cloned) > 5
    assert cloned == original
    assert twin.episode_return == env.episode_return
    mine, theirs = twin.episode.metrics(), env.episode.metrics()
    for name in mine.keys() - {"filter_time_s"}:  # a wall-clock time never repeats
        a, b = mine[name], theirs[name]
        assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), name


def test_a_clone_shares_the_world_and_copies_the_filter():
    env, _, _ = _env_after(3)
    twin = env.clone()
    assert twin.stream is env.stream  # read-only world, shared
    assert twin.episode.system is twin.system and twin.system is not env.system
    assert twin.filter_draws is not env.filter_draws
    before = env.system.pose()[0].copy()
    twin.step(np.array([1, 1]))
    np.testing.assert_array_equal(env.system.pose()[0], before)
    with pytest.raises(RuntimeError, match="reset"):
        HybridSLAMEnv(n_particles=10).clone()


def test_reseeded_futures_repeat_for_a_seed_and_differ_between_seeds():
    env, _, _ = _env_after(6)
    a, b, c = env.clone(), env.clone(), env.clone()
    a.reseed_future(3)
    b.reseed_future(3)
    c.reseed_future(4)
    play_a, play_b, play_c = (_play(x, ACTIONS[:8]) for x in (a, b, c))
    assert play_a == play_b
    assert [p[0] for p in play_a] != [p[0] for p in play_c]
    own = _play(env.clone(), ACTIONS[:8])
    assert [p[0] for p in play_a] != [p[0] for p in own]  # not the episode's own future
    # the path is kept: every future of the same world has the same true poses
    steps_a = [a.episode._steps.source[i].truth.pose for i in range(0, 50)]
    assert all(np.array_equal(p, q.truth.pose)
               for p, q in zip(steps_a, env.stream.make_steps.steps, strict=False))


@pytest.mark.parametrize("name", ["brooks-bailey", "brooks-bailey-compass"])
def test_a_redrawn_future_from_the_worlds_own_generator_is_the_world_to_the_bit(name):
    """The redraw draws what the simulator draws, in its order: given the simulator's own sensor
    generator it reproduces every scan (and compass reading) of the world, across its lazy
    blocks."""
    scenario = get_scenario(name, clutter_level=2, n_steps=300)
    world = simulate(scenario, 21)
    future = RedrawnFuture(world, 0, 99)
    future.rng = np.random.default_rng(np.random.SeedSequence(21).spawn(3)[2])
    redrawn = list(future)
    original = list(world)
    assert len(redrawn) == len(original) == 300
    for r, o in zip(redrawn, original, strict=True):
        np.testing.assert_array_equal(r.z, o.z)
        np.testing.assert_array_equal(r.truth.landmark_ids, o.truth.landmark_ids)
        np.testing.assert_array_equal(r.odometry, o.odometry)
        assert r.scanned == o.scanned and r.t_s == o.t_s and r.compass_rad == o.compass_rad


def test_a_redrawn_future_keeps_the_path_and_redraws_the_scans():
    scenario = get_scenario("brooks-bailey", clutter_level=3, n_steps=400)
    world = simulate(scenario, 2)
    start = 150
    redrawn = list(RedrawnFuture(world, start, 7))
    original = list(world)[start:]
    assert len(redrawn) == len(original)
    assert all(np.array_equal(r.truth.pose, o.truth.pose) for r, o in zip(redrawn, original,
                                                                          strict=True))
    scans = [(r, o) for r, o in zip(redrawn, original, strict=True) if o.scanned and len(o.z)]
    assert scans and sum(not np.array_equal(r.z, o.z) for r, o in scans) > 0.9 * len(scans)
    # the sensor model is the same: detections per scan agree in the mean
    det_r = np.mean([np.sum(r.truth.landmark_ids >= 0) for r, _ in scans])
    det_o = np.mean([np.sum(o.truth.landmark_ids >= 0) for _, o in scans])
    assert abs(det_r - det_o) < 0.2 * det_o + 0.5


def test_a_recording_cannot_be_redrawn_and_bad_seeds_are_named():
    steps = ArraySteps([0.0, 0.1], 0.1, np.zeros((1, 2)), np.zeros((0, 2)),
                       np.zeros(0, dtype=np.int64), [0, 0], np.zeros((1, 3)))
    world = simulate(get_scenario("brooks-bailey", n_steps=20), 0)
    recording = Stream(name="recorded", sensor=world.sensor, clutter=world.clutter,
                       odometry_noise=world.odometry_noise, initial_pose=np.zeros(3),
                       landmarks_true=np.zeros((0, 2)), n_steps=1, dt_s=0.1, make_steps=steps)
    with pytest.raises(ValueError, match="simulated world"):
        RedrawnFuture(recording, 0, 1)
    env, _, _ = _env_after(1)
    for bad in (-1, 1.5, "3", True):
        with pytest.raises(ValueError, match="seed"):
            env.reseed_future(bad)


def test_lookahead_that_never_leaves_the_rule_plays_the_rules_episode_to_the_bit():
    """Planning happens on copies only: with a gate no gain can pass, the lookahead's episode is
    the rule's, every decision (so the copies never touched the real env or its generators)."""
    rule_actions, la_actions = [], []
    options = dict(n_particles=60, n_steps=500, w_compute=10.0, compute_clip_s=0.2)
    ep_rule, env_rule = run_policy_object(policies.make(RULE), resolve_env(None, options), 1, 1,
                                          on_step=lambda a, i: rule_actions.append(a))
    lookahead = LookaheadPolicy(horizon_decisions=3, n_futures=2, min_gain=1e9)
    ep_la, env_la = run_policy_object(lookahead, resolve_env(None, options), 1, 1,
                                      on_step=lambda a, i: la_actions.append(a))
    assert lookahead.planned_decisions > 0 and lookahead.simulated_decisions > 0
    assert lookahead.deviations == 0
    assert [a.tolist() for a in la_actions] == [a.tolist() for a in rule_actions]
    assert env_la.episode_return == env_rule.episode_return
    assert ep_la.metrics()["anees"] == ep_rule.metrics()["anees"]


def test_lookahead_is_deterministic_and_plans_only_where_the_rule_fuses():
    options = dict(n_particles=60, n_steps=400, w_compute=10.0, compute_clip_s=0.2)
    runs = []
    for _ in range(2):
        actions = []
        policy = LookaheadPolicy(horizon_decisions=4, n_futures=2, min_gain=0.0, z_gain=0.0)
        _, env = run_policy_object(policy, resolve_env(None, options), 2, 8,
                                   on_step=lambda a, i, actions=actions: actions.append(a))
        runs.append(([a.tolist() for a in actions], env.episode_return, policy.episode_fields()))
    assert runs[0][:2] == runs[1][:2]
    fields = runs[0][2]
    fusions = sum(a[0] for a in runs[0][0])
    # every planned decision was a rule fusion point; waiting adds planned decisions
    assert 0 < fields["planned_decisions"] <= len(runs[0][0])
    assert fields["planned_decisions"] >= fusions
    assert fields["simulated_decisions"] <= fields["planned_decisions"] * 3 * 2 * 4


def test_early_fusion_plans_where_the_rule_waits_and_can_fuse_there():
    """With early_fusion_from_s the planner also plans decisions where the rule waits (local map
    old enough): fuse+optimise and fuse against waiting. With no gate it fuses before the rule's
    10 s wherever a rollout says so; off (None), the options and decisions are issue 39's."""
    options = dict(n_particles=60, n_steps=400, w_compute=10.0, compute_clip_s=0.2)
    actions, ages = [], []
    policy = LookaheadPolicy(horizon_decisions=3, n_futures=1, privileged=True, min_gain=0.0,
                             z_gain=0.0, early_fusion_from_s=6.0)

    def seen(action, info):
        actions.append(action.tolist())
        ages.append(info["features"]["local_map_age_s"])

    run_policy_object(policy, resolve_env(None, options), 2, 8, on_step=seen)
    fusions = sum(a[0] for a in actions)
    assert policy.planned_decisions > fusions  # decisions where the rule waited were planned
    # the fusion at the first planned decision: the age the observation showed before it
    observed = [None] + ages[:-1]
    early = [a for a, age in zip(actions, observed, strict=True)
             if a[0] and age is not None and age + 1e-4 < 10.0]
    assert early, "no fusion before the rule's 10 s although every rollout gain passes"
    assert all(age is None or age + 1e-4 >= 6.0
               for a, age in zip(actions, observed, strict=True) if a[0])
    assert "early_fusion_from_s" not in LookaheadPolicy().options
    with pytest.raises(ValueError, match="early_fusion_from_s"):
        LookaheadPolicy(early_fusion_from_s=-1.0)


def test_the_gate_leaves_the_rule_only_for_a_clear_paired_gain():
    policy = LookaheadPolicy(min_gain=10.0, z_gain=2.0)
    base = (1, 1)
    futures = np.array([-100.0, -120.0, -90.0, -110.0])
    # a failure prevented in every future: thousands of points, clear
    assert policy.choose({base: futures - 3000, (1, 0): futures, (0, 0): futures - 5}, base) \
        == (1, 0)
    # a better mean from one lucky future only: not clear
    lucky = futures + np.array([60.0, -15.0, -15.0, -15.0])
    assert policy.choose({base: futures, (1, 0): lucky, (0, 0): futures - 1}, base) == base
    # a small steady gain below min_gain: not worth leaving the rule
    assert policy.choose({base: futures, (1, 0): futures + 5, (0, 0): futures}, base) == base
    # ties go to the rule
    assert policy.choose({base: futures, (1, 0): futures, (0, 0): futures}, base) == base


def test_lookahead_options_are_validated_and_the_env_is_required():
    for bad in ({"horizon_decisions": 0}, {"n_futures": 0}, {"n_futures": 2.5},
                {"min_gain": -1.0}, {"privileged": "yes"}, {"seed": -3}):
        field = next(iter(bad))
        with pytest.raises(ValueError, match=field):
            LookaheadPolicy(**bad)
    with pytest.raises(ValueError, match="n_futures"):
        LookaheadPolicy(privileged=True, n_futures=3)
    with pytest.raises(ValueError, match="base"):
        LookaheadPolicy(base="no-such-rule")
    with pytest.raises(ValueError, match="env"):
        LookaheadPolicy().bind_env(object())
    env, obs, info = _env_after(9)
    policy = LookaheadPolicy(horizon_decisions=2, n_futures=1)
    while not policy.base.act(obs, info)[0]:
        obs, _, _, _, info = env.step(np.array([0, 0]))
    with pytest.raises(RuntimeError, match="bind_env"):
        policy.act(obs, info)


def test_lookahead_names_round_trip_through_policies_make():
    """Every lookahead name a table prints builds that planner again, with its documented
    options: the fast default, the full planner of issue 39 and the bound over its horizon."""
    assert {"lookahead", "lookahead-full", "lookahead-privileged"} <= set(policies.available())
    expected = {
        "lookahead": (LookaheadPolicy, dict(horizon_decisions=14, n_futures=1, prune=True,
                                            privileged=False)),
        "lookahead-full": (FullLookahead, dict(horizon_decisions=20, n_futures=4, prune=False,
                                               privileged=False)),
        "lookahead-privileged": (PrivilegedLookahead, dict(horizon_decisions=20, n_futures=1,
                                                           prune=False, privileged=True)),
    }
    for name, (cls, options) in expected.items():
        policy = policies.make(name)
        assert type(policy) is cls and policy.name == name
        assert {k: policy.options[k] for k in options} == options
        assert policies.make(policy.name).options == policy.options
    policy = policies.make("lookahead-privileged", horizon_decisions=5)
    assert policy.privileged and policy.n_futures == 1 and policy.horizon_decisions == 5
    assert policies.make("lookahead-full", n_futures=2).n_futures == 2
    with pytest.raises(ValueError, match="prune"):
        LookaheadPolicy(prune="yes")


def _planning_state(n_particles: int = 40):
    """An env at a decision where the rule fuses (a planning point), and the rule's action."""
    env, obs, info = _env_after(9, n_particles=n_particles)
    rule = policies.make(RULE)
    while not rule.act(obs, info)[0]:
        obs, _, _, _, info = env.step(np.array([0, 0]))
    return env, rule.act(obs, info)


class _Counting(LookaheadPolicy):
    """Records the futures and the length of every rollout the planner plays."""

    def _rollouts(self, env, first_action, seeds, base_returns):
        before = self.simulated_decisions
        out = super()._rollouts(env, first_action, seeds, base_returns)
        self.played.append((first_action, tuple(seeds), self.simulated_decisions - before))
        return out


def test_the_planner_plays_the_futures_and_horizon_it_claims():
    env, base_action = _planning_state()
    for n_futures, horizon in ((1, 3), (3, 2)):
        policy = _Counting(horizon_decisions=horizon, n_futures=n_futures, prune=False)
        policy.played = []
        policy.bind_env(env)
        returns = policy.action_returns(base_action)
        assert set(returns) == {(1, 1), (1, 0), (0, 0)}
        assert all(len(r) == n_futures for r in returns.values())
        # every alternative on the same futures (common random numbers), each to the horizon
        assert [a for a, _, _ in policy.played] == [(1, 1), (1, 0), (0, 0)]
        assert len({seeds for _, seeds, _ in policy.played}) == 1
        assert all(len(seeds) == n_futures for _, seeds, _ in policy.played)
        assert [n for _, _, n in policy.played] == [n_futures * horizon] * 3
    # the fast planner's one future is the full planner's first (seeds do not depend on M)
    one = LookaheadPolicy(n_futures=1)._future_seeds(env)
    four = FullLookahead()._future_seeds(env)
    assert len(one) == 1 and len(four) == 4 and one[0] == four[0]


def test_pruning_stops_hopeless_rollouts_without_changing_the_choice():
    """Stopped rollouts save decisions, and the choice is the unpruned planner's on the same
    futures, whatever the gate; the base action's returns are the same exact returns."""
    env, base_action = _planning_state()
    base = tuple(int(v) for v in base_action)
    saved = 0
    for min_gain in (0.0, 10.0, 1e9):
        plain = LookaheadPolicy(horizon_decisions=6, n_futures=2, min_gain=min_gain,
                                z_gain=0.0, prune=False)
        pruned = LookaheadPolicy(horizon_decisions=6, n_futures=2, min_gain=min_gain,
                                 z_gain=0.0, prune=True)
        plain.bind_env(env)
        pruned.bind_env(env)
        full, cut = plain.action_returns(base_action), pruned.action_returns(base_action)
        np.testing.assert_array_equal(cut[base], full[base])
        assert pruned.choose(cut, base) == plain.choose(full, base)
        for alternative in full:  # a stopped alternative holds an upper bound of its return
            assert np.all(cut[alternative] >= full[alternative])
        assert pruned.simulated_decisions <= plain.simulated_decisions
        saved += plain.simulated_decisions - pruned.simulated_decisions
    # with a gate no gain passes, every alternative stops after its first decision
    assert pruned.simulated_decisions == 2 * 6 + 2 * 2 * 1
    assert saved > 0
