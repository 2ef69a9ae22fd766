"""The Gymnasium env, parametrised over every registered id (checker, seeding, rendering, pickling,
vector envs, configuration errors) and checked against the systems it drives."""

import dataclasses
import multiprocessing as mp
import pickle
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import slam_gym
from slam_gym.envs.hybrid_slam import FEATURE_NAMES, HybridSLAMEnv
from slam_gym.envs.wrappers import DiscreteActions, discrete_to_multi

# every id at the current version; the -v0 ids are the same envs with ordered draws
# (test_v0_ids_are_the_same_env_with_ordered_streams)
ENV_IDS = (sorted(i for i in slam_gym.ENV_VARIANTS if i.endswith("-v1"))
           + sorted(slam_gym.TASK_ENV_VARIANTS))  # the tasks of issue 48, only at -v1
SMALL = {"n_particles": 20, "n_steps": 150}


def make(env_id, **kwargs):
    with warnings.catch_warnings():  # gymnasium calls a -v0 id out of date
        warnings.simplefilter("ignore", DeprecationWarning)
        return gym.make(f"slam_gym:{env_id}", **(SMALL | kwargs))


def rollout(env, seed, actions):
    obs, info = env.reset(seed=seed)
    out = [(obs, 0.0, info["features"], info["nees"])]
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        out.append((obs, reward, info["features"], info["nees"]))
        if terminated or truncated:
            break
    return out


ACTIONS = [np.array([i % 5 == 4, i % 7 == 6], dtype=np.int64) for i in range(14)]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gymnasium_env_checker_without_warnings(env_id):
    """Gymnasium's checker with its render check: every declared render mode is made from the
    spec, reset and rendered, and must return what the mode promises."""
    from gymnasium.utils.env_checker import check_env

    env = make(env_id, render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_human_rendering_returns_none(env_id, caplog):
    env = make(env_id, render_mode="human")
    env.reset(seed=0)
    assert env.render() is None
    env.step(np.array([0, 0]))  # renders too (human mode draws at every step)
    assert env.render() is None
    warned = [r for r in caplog.records if "interactive matplotlib backend" in r.getMessage()]
    assert len(warned) <= 1  # headless: said once, not at every frame
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_render_fps_is_one_frame_per_decision_in_real_time(env_id):
    env = make(env_id)
    assert env.metadata["render_fps"] == pytest.approx(1.0)  # 10 iterations x 0.1 s
    assert make(env_id, decision_interval=5).metadata["render_fps"] == pytest.approx(2.0)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_registered_time_limit_does_not_cut_a_normal_episode(env_id):
    spec = gym.registry[env_id]
    env = gym.make(f"slam_gym:{env_id}", n_particles=10)
    scenario = env.unwrapped.config.scenario_config()
    decisions = scenario.path_length_m / scenario.speed_mps * scenario.filter_rate_hz / 10
    assert decisions < spec.max_episode_steps <= 2 * decisions


@pytest.mark.parametrize(
    "action", [np.array([0.5, 1.0]), np.array([1.0, 0.0]), np.array([1, 0, 1]), np.array([2, 0]),
               np.array([[1, 0]]), 3, "fuse"],
)
def test_invalid_actions_raise_value_error(action):
    env = make("SlamGym/HybridSLAM-v1")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(action)
    env.step(np.array([True, False]))  # booleans are integers 0/1


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_sb3_env_checker_without_warnings(env_id):
    from stable_baselines3.common.env_checker import check_env

    env = make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped, warn=True)
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_same_seed_same_episode_and_different_seeds_differ(env_id):
    a = rollout(make(env_id), 3, ACTIONS)
    b = rollout(make(env_id), 3, ACTIONS)
    c = rollout(make(env_id), 4, ACTIONS)
    assert len(a) == len(b)
    for (oa, ra, fa, na), (ob, rb, fb, nb) in zip(a, b, strict=True):
        assert np.array_equal(oa, ob) and ra == rb and fa == fb
        assert na == nb or (np.isnan(na) and np.isnan(nb))
    assert any(not np.array_equal(x[0], y[0]) for x, y in zip(a, c, strict=False))


def _rollout_in_subprocess(env_id, seed, queue):
    import gymnasium as gym  # a fresh interpreter: no prior import of slam_gym

    env = gym.make(f"slam_gym:{env_id}", **SMALL)
    queue.put([(o.tolist(), r) for o, r, _, _ in rollout(env, seed, ACTIONS)])


def test_same_episode_across_spawned_processes():
    env_id = "SlamGym/HybridSLAM-v1"
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_rollout_in_subprocess, args=(env_id, 11, queue))
    proc.start()
    remote = queue.get(timeout=300)
    proc.join(timeout=60)
    local = [(o.tolist(), r) for o, r, _, _ in rollout(make(env_id), 11, ACTIONS)]
    assert remote == local


def test_make_in_a_fresh_interpreter_without_importing_slam_gym():
    code = (
        "import gymnasium as gym, sys; "
        "env = gym.make('slam_gym:SlamGym/HybridSLAM-v1', n_particles=5, n_steps=30); "
        "obs, info = env.reset(seed=0); assert obs.shape == (19,); "
        "assert 'slam_gym' in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_registration_is_idempotent():
    before = {k for k in gym.registry if k.startswith("SlamGym/")}
    assert slam_gym.register_envs() == list(slam_gym.ENV_VARIANTS)
    assert {k for k in gym.registry if k.startswith("SlamGym/")} == before


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_rgb_array_frames(env_id):
    env = make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.array([1, 0]))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.shape[0] > 100 and frame.shape[1] > 100
    assert frame.std() > 5  # something is drawn
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_env_pickles_and_the_copy_continues_identically(env_id):
    env = make(env_id)
    env.reset(seed=5)
    env.step(np.array([1, 0]))
    clone = pickle.loads(pickle.dumps(env))
    a = env.step(np.array([0, 1]))
    b = clone.step(np.array([0, 1]))
    assert np.array_equal(a[0], b[0]) and a[1] == b[1]


def test_observation_matches_features_by_name_and_info_keys():
    env = make("SlamGym/HybridSLAM-v1")
    obs, info = env.reset(seed=1)
    assert obs.dtype == np.float32 and obs.shape == (len(FEATURE_NAMES),)
    assert list(info["features"]) == list(FEATURE_NAMES) + ["compute_price_per_s"]
    assert info["features"]["compute_price_per_s"] == 1.0  # the default w_compute
    np.testing.assert_allclose(obs, [info["features"][n] for n in FEATURE_NAMES], rtol=1e-6)
    obs, reward, terminated, truncated, info = env.step(np.array([1, 1]))
    for key in ("nees", "pose_error_m", "map_error_m", "failed", "n_fusions", "n_optimisations",
                "reward_components"):
        assert key in info
    assert "filter_time_s" not in info  # wall-clock time is opt-in: infos must repeat
    assert info["n_fusions"] == 1 and info["n_optimisations"] == 1
    c = info["reward_components"]
    w = env.unwrapped.config
    expected = -(w.w_nees * (c["nees_over"] + c["nees_under"]) + w.w_pose * c["pose_error_m"]
                 + w.w_map * c["map_ospa_m"] + w.w_compute * c["compute_s"]
                 + c["failure_charge"])
    assert reward == pytest.approx(expected)


def test_compute_time_in_info_on_request():
    env = make("SlamGym/HybridSLAM-v1", info_compute_time=True)
    env.reset(seed=0)
    info = env.step(np.array([1, 0]))[4]
    assert info["filter_time_s"] == env.unwrapped.episode.compute_time_s > 0


def test_vector_envs_run():
    fns = [lambda: make("SlamGym/HybridSLAM-v1") for _ in range(2)]
    for vec in (gym.vector.SyncVectorEnv(fns), gym.vector.AsyncVectorEnv(fns, context="spawn")):
        obs, _ = vec.reset(seed=[0, 1])
        assert obs.shape == (2, len(FEATURE_NAMES))
        obs, rewards, *_ = vec.step(np.array([[1, 0], [0, 0]]))
        assert rewards.shape == (2,)
        vec.close()


def test_sb3_subproc_vec_env_runs():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    vec = make_vec_env("slam_gym:SlamGym/HybridSLAM-v1", n_envs=2, seed=0,
                       vec_env_cls=SubprocVecEnv, env_kwargs=SMALL,
                       vec_env_kwargs={"start_method": "spawn"})
    obs = vec.reset()
    obs, rewards, dones, infos = vec.step(np.array([[1, 0], [0, 1]]))
    assert obs.shape == (2, len(FEATURE_NAMES)) and rewards.shape == (2,)
    vec.close()


def test_policies_know_the_same_feature_names():
    """``policies`` reads the names' one definition (``filters.interface_features``)."""
    from policies.base import INTERFACE_FEATURES

    assert tuple(INTERFACE_FEATURES) == FEATURE_NAMES


def test_discrete_wrapper_matches_the_policies_mapping():
    from policies.base import discrete_to_multi as policies_mapping

    for a in range(4):
        assert np.array_equal(discrete_to_multi(a), policies_mapping(a))
    env = DiscreteActions(make("SlamGym/HybridSLAM-v1"))
    assert env.action_space == gym.spaces.Discrete(4)
    env.reset(seed=0)
    _, _, _, _, info = env.step(3)
    assert info["n_fusions"] == 1 and info["n_optimisations"] == 1
    with pytest.raises(ValueError, match="action"):
        discrete_to_multi(4)


@pytest.mark.filterwarnings("ignore:.*render_mode")  # gym.make's own warning before ours
@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"clutter_level": 7}, "clutter_level"),
        ({"n_particles": 0}, "n_particles"),
        ({"decision_interval": -1}, "decision_interval"),
        ({"front_end": "ukf"}, "front_end"),
        ({"back_end": "graph"}, "back_end"),
        ({"scenario": "moon"}, "scenario"),
        ({"w_nees": -1.0}, "w_nees"),
        ({"alpha": 2.0, "beta": 0.0}, "alpha"),
        ({"no_such_option": 1}, "no_such_option"),
        ({"render_mode": "ascii"}, "render_mode"),
    ],
)
def test_bad_keyword_values_raise_value_error(kwargs, field):
    with pytest.raises(ValueError, match=field):
        make("SlamGym/HybridSLAM-v1", **kwargs)


def test_reset_options_override_and_are_validated():
    env = make("SlamGym/HybridSLAM-v1")
    env.reset(seed=0, options={"clutter_level": 3, "world_seed": 9})
    assert env.unwrapped.stream.clutter.alpha == 0.1 and env.unwrapped.world_seed == 9
    with pytest.raises(ValueError, match="bogus"):
        env.reset(seed=0, options={"bogus": 1})
    with pytest.raises(ValueError, match="clutter_level"):
        env.reset(seed=0, options={"clutter_level": 9})


def _returns_with_failure_at(env_id, fail_at, n_decisions=14, seed=0):
    """The return of a fixed action sequence on world ``seed``, with BB's failure criterion
    forced to fire at decision ``fail_at`` (None: never)."""
    env = make(env_id)
    env.reset(seed=seed)
    total, components = 0.0, []
    run_interval = env.unwrapped._run_interval

    def failing_interval():
        out = run_interval()
        det = env.unwrapped.episode.failure
        det.failed, det.failure_iteration = True, env.unwrapped.episode.iteration
        return out

    for k in range(n_decisions):
        if k == fail_at:
            env.unwrapped._run_interval = failing_interval
        _, reward, terminated, truncated, info = env.step(ACTIONS[k % len(ACTIONS)])
        total += reward
        components.append(info["reward_components"])
        if terminated or truncated:
            break
    return total, components, env.unwrapped


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_failing_never_pays(env_id):
    """Every decision without failure costs at most the config's bound, and a failure charges
    the penalty plus that bound for every remaining decision: so a rollout that fails at any
    decision returns less than the same rollout surviving on the same world."""
    # the first world where the fixed actions survive at SMALL's 20 particles (a real failure
    # would leave nothing to compare with; on world 0 that is every id but the long mission)
    for seed in range(5):
        surviving, components, env = _returns_with_failure_at(env_id, None, seed=seed)
        if not env.episode.failure.failed:
            break
    bound = env.config.max_decision_cost
    weights = env.config.reward_weights()
    for c in components:
        assert sum(w * c[k] for k, w in weights.items()) <= bound + 1e-9
        assert c["failure_charge"] == 0.0
    for fail_at in (0, 6, 13):
        failing, comps, _ = _returns_with_failure_at(env_id, fail_at, seed=seed)
        assert len(comps) == fail_at + 1  # the episode ended at the failure
        assert comps[-1]["failure_charge"] >= env.config.failure_penalty
        assert failing < surviving, (fail_at, failing, surviving)


def test_a_real_failure_returns_less_than_surviving_on_the_same_world():
    """Pure FastSLAM with 5 particles in heavy clutter fails early on world 0; fusing at every
    decision survives it (with BB's compass, Fig. 3); the failing rollout's return is the lower
    one."""
    import policies

    returns = {}
    for name in ("never", "always"):
        env = make("SlamGym/HybridSLAM-Compass-v1", n_steps=None, clutter_level=3, n_particles=5)
        policy = policies.make(name)
        obs, info = env.reset(seed=0)
        total, terminated, truncated = 0.0, False, False
        while not (terminated or truncated):
            obs, reward, terminated, truncated, info = env.step(policy.act(obs, info))
            total += reward
        returns[name] = (total, info["failed"])
    assert returns["never"][1] and not returns["always"][1]
    assert returns["never"][0] < returns["always"][0]


def test_the_map_term_charges_an_empty_map_the_cutoff():
    env = make("SlamGym/HybridSLAM-v1", clutter_level=0)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0, 0]))
    score = env.unwrapped.episode.map_score()
    assert info["reward_components"]["map_ospa_m"] == pytest.approx(score.ospa_m(5.0))
    assert score.ospa_m(5.0) <= 5.0


def test_under_confidence_is_penalised():
    """A NEES far below the 95 % band (an estimate claiming far more uncertainty than its error)
    costs nees_under; inside the band costs nothing."""
    env = make("SlamGym/HybridSLAM-v1", clutter_level=0)
    env.reset(seed=0)
    lo, hi = env.unwrapped._nees_band
    ep = env.unwrapped.episode
    env.unwrapped._run_interval = lambda: ([lo / 5.0] * 10, [0.1] * 10)
    _, _, _, _, info = env.step(np.array([0, 0]))
    assert info["reward_components"]["nees_under"] == pytest.approx(4.0)
    assert info["reward_components"]["nees_over"] == 0.0
    env.unwrapped._run_interval = lambda: ([0.5 * (lo + hi)] * 10, [0.1] * 10)
    _, _, _, _, info = env.step(np.array([0, 0]))
    assert info["reward_components"]["nees_under"] == 0.0 == info["reward_components"]["nees_over"]
    assert ep is env.unwrapped.episode


@pytest.mark.parametrize(
    "option, value",
    [("w_compute", -1.0), ("w_map", float("nan")), ("map_cutoff_m", 0.0),
     ("compute_clip_s", -2.0), ("features", ("bogus_feature",)), ("features", ()),
     ("fusion_cost", 0.02)],
)
def test_bad_reward_weights_features_and_options_raise_value_error_naming_the_field(option, value):
    with pytest.raises(ValueError, match=option):
        make("SlamGym/HybridSLAM-v1", **{option: value})


def test_the_features_option_selects_the_observation():
    names = ("loop_closure_flag", "local_map_age_s", "stored_submaps")
    env = make("SlamGym/HybridSLAM-v1", features=list(names))
    obs, info = env.reset(seed=0)
    assert env.observation_space.shape == (3,)
    np.testing.assert_allclose(obs, [info["features"][n] for n in names])


def test_the_registered_default_is_the_papers_configuration():
    assert gym.make("slam_gym:SlamGym/HybridSLAM-v1").unwrapped.config.n_particles == 500
    assert gym.make("slam_gym:SlamGym/HybridSLAM-Light-v1").unwrapped.config.n_particles == 100


def test_compute_cost_is_modelled_deterministically_and_recorded_for_calibration():
    a = rollout(make("SlamGym/HybridSLAM-Relative-v1"), 3, [np.array([1, 1])] * 4)
    b = rollout(make("SlamGym/HybridSLAM-Relative-v1"), 3, [np.array([1, 1])] * 4)
    assert [r for _, r, _, _ in a] == [r for _, r, _, _ in b]
    env = make("SlamGym/HybridSLAM-Relative-v1")
    env.reset(seed=3)
    _, _, _, _, info = env.step(np.array([1, 1]))
    kinds = [k for k, _, _ in env.unwrapped.compute_records]
    assert {"fusion-relative", "optimise", "filter-fastslam"} <= set(kinds)
    assert info["reward_components"]["compute_s"] > 0.0


def test_truncation_by_decision_limit():
    env = make("SlamGym/HybridSLAM-v1", max_decisions=3, clutter_level=0)
    env.reset(seed=0)
    flags = [env.step(np.array([0, 0]))[3] for _ in range(3)]
    assert flags == [False, False, True]


class _OriginStartEnv(HybridSLAMEnv):
    """The env on a stream whose start pose is the origin of the world frame.

    The hybrid front-end works in the local frame of its map (which starts at the start pose),
    pure FastSLAM in the world frame; FastSLAM 2.0 draws each particle's pose as ``mean + L n``
    with ``L`` a factor of the proposal covariance, and the factor of a rotated covariance is
    not the rotated factor, so the two only agree sample for sample when the frames coincide.
    Filters see odometry and observations only, which do not depend on the frame.
    """

    def _make_stream(self, world_seed):
        from filters.geometry import point_to_frame, relative
        from slam_gym.stream import steps_from_list

        stream = super()._make_stream(world_seed)
        start = stream.initial_pose
        steps = [
            dataclasses.replace(step, truth=dataclasses.replace(
                step.truth, pose=relative(start, step.truth.pose)))
            for step in stream
        ]
        return dataclasses.replace(
            stream, initial_pose=np.zeros(3), make_steps=steps_from_list(steps),
            landmarks_true=point_to_frame(start, stream.landmarks_true),
        )


def _env_and_reference(system_name, system_options=None, **config):
    """An env episode's stream and a system built exactly as the env builds its own."""
    from filters.draws import SynchronisedDraws
    from slam_gym.episode import Episode
    from slam_gym.systems import make_system

    env = _OriginStartEnv(**config)
    env.reset(seed=3, options={"world_seed": 5})
    draws = SynchronisedDraws((5, 0))  # what the env keys its filter's numbers by
    system = make_system(system_name, env.stream, draws,
                         n_particles=env.config.n_particles, **(system_options or {}))
    return env, Episode(system, env.stream, draws=draws)


def _play(env, reference, fuse_every_iterations):
    reference.advance(env.config.decision_interval)  # the env runs the first interval in reset()
    terminated = truncated = False
    while not (terminated or truncated):
        fuse = bool(fuse_every_iterations) and env.episode.iteration % fuse_every_iterations == 0
        *_, terminated, truncated, _ = env.step(np.array([fuse, 0]))
        if fuse:
            reference.fuse()
        # to where the env is: the end of the interval, or the iteration where it failed
        reference.advance(env.episode.iteration - reference.iteration)
    assert env.episode.iteration == reference.iteration


def test_env_fusing_every_10_s_reproduces_hybrid_bit_for_bit():
    env, reference = _env_and_reference("hybrid", clutter_level=0, n_particles=100, n_steps=350)
    _play(env, reference, fuse_every_iterations=100)
    assert env.episode.n_fusions == reference.n_fusions == 3
    mine, theirs = env.system.pose(), reference.system.pose()
    assert np.array_equal(mine[0], theirs[0]) and np.array_equal(mine[1], theirs[1])
    assert np.array_equal(env.system.landmarks().means, reference.system.landmarks().means)


def test_env_never_fusing_reproduces_pure_fastslam():
    """HYBRID never fusing is FASTSLAM with the front-end's existence clip (the float guard,
    filters.fastslam.LOCAL_MAP_MAX_EXISTENCE; FASTSLAM's own default is 0.999)."""
    from filters.fastslam import LOCAL_MAP_MAX_EXISTENCE

    env, reference = _env_and_reference(
        "fastslam", {"max_existence": LOCAL_MAP_MAX_EXISTENCE},
        clutter_level=0, n_particles=100, n_steps=300)
    _play(env, reference, fuse_every_iterations=0)
    assert env.episode.n_fusions == 0
    mine, theirs = env.system.pose(), reference.system.pose()
    np.testing.assert_allclose(mine[0], theirs[0], atol=1e-9)
    np.testing.assert_allclose(mine[1], theirs[1], atol=1e-12)
    a, b = env.system.landmarks(), reference.system.landmarks()
    assert len(a) == len(b) > 0
    np.testing.assert_allclose(np.sort(a.means, axis=0), np.sort(b.means, axis=0), atol=1e-9)


def test_map_score_from_means_only_equals_the_score_of_the_full_landmarks():
    from slam_gym.metrics import score_map

    env = make("SlamGym/HybridSLAM-v1")
    env.reset(seed=5)
    ep = env.unwrapped.episode
    for k in range(40):
        _, _, terminated, truncated, _ = env.step(np.array([int(k % 10 == 9), 0]))
        lm = ep.confirmed_landmarks()
        full = score_map(lm.ids, lm.means, ep.feature_truth, ep.stream.landmarks_true,
                         ep.detected_landmarks)
        assert repr(ep.map_score()) == repr(full)  # exact, NaN included
        if terminated or truncated:  # this world ends at its 14th decision, after a fusion
            break
    assert k >= 12


def test_an_env_on_a_remembered_world_repeats_the_fresh_rollout():
    from slam_gym.world import _remembered_world

    def rollout():
        env = make("SlamGym/HybridSLAM-Light-v1")
        out = [env.reset(seed=4, options={"world_seed": 9})[0]]
        for k in range(30):
            obs, reward, terminated, truncated, _ = env.step(np.array([int(k % 10 == 9), 0]))
            out += [obs, reward]
            if terminated or truncated:
                break
        return out

    _remembered_world.cache_clear()
    fresh = rollout()
    assert _remembered_world.cache_info().currsize == 1
    remembered = rollout()
    assert _remembered_world.cache_info().hits >= 1
    for a, b in zip(fresh, remembered, strict=True):
        assert np.array_equal(a, b)


def test_redundant_optimisation_is_a_free_no_op():
    """Issue 27: optimising again with nothing fused since (or before any fusion) is free: the
    episode continues exactly as if the agent had not asked (observation, reward and its
    components, the optimisation count), while a fusion in between makes it count again."""
    def episode(actions):
        env = make("SlamGym/HybridSLAM-v1", n_steps=400)
        env.reset(seed=4)
        out = [env.step(np.array(a)) for a in actions]
        charged = sum(kind == "optimise" for kind, _, _ in env.unwrapped.compute_records)
        return out, (env.unwrapped.episode.n_optimisations, charged)
    asked, n_asked = episode([[0, 1], [1, 1], [0, 1], [0, 1], [1, 0], [0, 1]])
    plain, n_plain = episode([[0, 0], [1, 1], [0, 0], [0, 0], [1, 0], [0, 1]])
    for (obs_a, rew_a, *_, info_a), (obs_p, rew_p, *_, info_p) in zip(asked, plain, strict=True):
        np.testing.assert_array_equal(obs_a, obs_p)
        assert rew_a == rew_p
        assert info_a["reward_components"] == info_p["reward_components"]
    assert n_asked == n_plain == (2, 2)  # the 2nd and the last (after a fusion): charged


def test_price_of_compute_per_episode_is_observed_and_scored():
    """The price of compute (w_compute) set at reset is the feature compute_price_per_s, scales the
    reward's compute term, and a policy conditioned on it observes it (issue 29 item 4)."""
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    features = (*FEATURE_NAMES, "compute_price_per_s")
    env = HybridSLAMEnv(n_particles=20, n_steps=60, features=features)
    obs, info = env.reset(seed=3, options={"w_compute": 25.0, "compute_clip_s": 0.2})
    assert obs.shape == (len(features),) and obs[-1] == 25.0
    assert info["features"]["compute_price_per_s"] == 25.0
    _, reward, _, _, info = env.step(np.array([1, 0]))
    components = info["reward_components"]
    assert 0 < components["compute_s"] <= 0.2
    weights = env.config.reward_weights()
    assert weights["compute_s"] == 25.0
    assert reward == pytest.approx(-sum(weights[k] * v for k, v in components.items()))
    with pytest.raises(ValueError, match="features"):
        HybridSLAMEnv(features=("compute_price", "ess_ratio"))


def test_random_compute_price_is_seeded_and_log_uniform():
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv
    from slam_gym.envs.wrappers import RandomComputePrice

    def prices(seed):
        env = RandomComputePrice(HybridSLAMEnv(n_particles=5, n_steps=20), 1.0, 100.0)
        out = [env.reset(seed=seed)[1]["features"]["compute_price_per_s"]]
        out += [env.reset()[1]["features"]["compute_price_per_s"] for _ in range(39)]
        return np.array(out)

    a, b = prices(7), prices(7)
    np.testing.assert_array_equal(a, b)
    assert np.all((a >= 1.0) & (a <= 100.0))
    assert np.sum(a < 10.0) >= 10 and np.sum(a > 10.0) >= 10  # log-uniform: half below 10
    with pytest.raises(ValueError, match="low, high"):
        RandomComputePrice(HybridSLAMEnv(n_particles=5, n_steps=20), 10.0, 1.0)


def test_return_at_another_price_follows_from_the_compute_term():
    """A run's return at price w' is its return at w plus (w - w') x compute_term_s (the same
    actions at every price: a rule's decisions do not depend on the price)."""
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    def play(w_compute):
        env = HybridSLAMEnv(n_particles=20, n_steps=200, w_compute=w_compute, compute_clip_s=0.05)
        env.reset(seed=5)
        done, k = False, 0
        while not done:
            k += 1
            _, _, terminated, truncated, _ = env.step(np.array([k % 3 == 0, k % 6 == 0]))
            done = terminated or truncated
        return env.episode_return, env.episode_compute_term_s

    r1, term1 = play(1.0)
    r7, term7 = play(7.0)
    assert term1 == term7 > 0
    assert r7 == pytest.approx(r1 + (1.0 - 7.0) * term1, rel=1e-12, abs=1e-9)


class RecordingDraws:
    """Wraps the env's synchronised source: where each role's numbers started, per iteration."""

    def __init__(self, inner):
        self.inner, self.log = inner, {}

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __setattr__(self, name, value):
        if name == "iteration":
            self.inner.iteration = value
        else:
            object.__setattr__(self, name, value)

    def generator(self, role):
        generator = self.inner.generator(role)
        state = generator.bit_generator.state
        self.log.setdefault((self.inner.iteration, role), []).append(
            (tuple(int(k) for k in state["state"]["key"]),
             tuple(int(c) for c in state["state"]["counter"])))
        return generator


def recorded_episode(actions, decision_interval=10):
    """An episode of HybridSLAM-v1 under ``actions`` with the filter's draws recorded."""
    env = gym.make("slam_gym:SlamGym/HybridSLAM-v1", n_particles=30, n_steps=260).unwrapped
    env.reset(seed=4)
    recorder = RecordingDraws(env.filter_draws)
    front = env.system.estimator.front_end
    front.draws = recorder
    env.episode.draws = recorder
    env.filter_draws = recorder
    for action in actions:
        _, _, terminated, truncated, _ = env.step(np.array(action))
        if terminated or truncated:
            break
    return recorder.log, env.episode.metrics()


def test_two_policies_that_differ_at_a_decision_draw_the_same_numbers_for_each_purpose_after():
    """Synchronised streams (issue 46): B fuses and optimises at decision k where A waits; at
    every later iteration each role starts from the same generator state in both episodes."""
    k, n = 4, 25
    rule = [(int(i % 10 == 9), int(i % 10 == 9)) for i in range(n)]
    other = list(rule)
    other[k] = (1, 1)
    log_a, metrics_a = recorded_episode(rule)
    log_b, metrics_b = recorded_episode(other)
    assert metrics_a["n_fusions"] != metrics_b["n_fusions"]  # the decision did change the run
    first_after = (k + 1) * 10
    after_a = {key: v for key, v in log_a.items() if key[0] >= first_after}
    after_b = {key: v for key, v in log_b.items() if key[0] >= first_after}
    scans = {key for key in after_a if key[1] in ("association", "scan_pose")}
    assert len(scans) > 100 and scans == {key for key in after_b
                                           if key[1] in ("association", "scan_pose")}
    common = set(after_a) & set(after_b)
    assert common >= scans
    for key in common:  # every role present in both (resampling is state-dependent)
        assert after_a[key][0] == after_b[key][0], key


def test_v0_ids_are_the_same_env_with_ordered_streams():
    for env_id in sorted(i for i in slam_gym.ENV_VARIANTS if i.endswith("-v0")):
        twin = env_id[:-3] + "-v1"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            old = gym.make(f"slam_gym:{env_id}", **SMALL).unwrapped
        new = gym.make(f"slam_gym:{twin}", **SMALL).unwrapped
        assert old.config == dataclasses.replace(new.config, random_streams="ordered")
    env = make("SlamGym/HybridSLAM-v0")
    env.reset(seed=2)
    assert env.unwrapped.filter_draws is None and env.unwrapped.filter_rng is not None


def test_draw_option_changes_only_the_filters_numbers():
    env = make("SlamGym/HybridSLAM-v1")
    runs = {}
    for draw in (0, 0, 1):
        _, info = env.reset(seed=5, options={"world_seed": 5, "draw": draw})
        z = [step.z.copy() for _, step in zip(range(40), env.unwrapped.stream, strict=False)]
        runs.setdefault(draw, []).append((z, info["features"]))
    (z0, f0), (_, f0b) = runs[0]
    ((z1, f1),) = runs[1]
    assert all(np.array_equal(a, b) for a, b in zip(z0, z1, strict=True))  # the same world
    assert f0 == f0b and f0 != f1  # the same draw repeats, another draw differs
    with pytest.raises(ValueError, match="^draw="):
        env.reset(seed=1, options={"draw": -1})
