"""Training: hyper-parameter files, a run's outputs, resuming, seeds' summary, the saved model's
observation transform."""

import csv
import json

import numpy as np
import pytest
from untrained import untrained_model

from slam_gym.cli import main
from slam_gym.envs.hybrid_slam import FEATURE_NAMES
from slam_gym.envs.spec import registered_ids
from slam_gym.training.evaluation import evaluate_policy
from slam_gym.training.hyperparams import (
    ALGOS,
    load_hyperparams,
    parse_overrides,
    validate_hyperparams,
)
from slam_gym.training.run import (
    TrainingSetup,
    chosen_mode,
    read_eval_log,
    registered_kwargs,
    train_run,
    training_env,
)

SIMULATED = [i for i in registered_ids() if "MRCLAM" not in i]


@pytest.mark.parametrize("algo", ALGOS)
@pytest.mark.parametrize(("env_id", "want"), [
    ("SlamGym/HybridSLAM-v1", 500), ("SlamGym/HybridSLAM-Light-v1", 100),
    ("SlamGym/HybridSLAM-Zones-v1", 500), ("SlamGym/HybridSLAM-ZonesStarved-v1", 150)])
def test_packaged_hyperparams_leave_the_env_to_its_id(algo, env_id, want):
    """The packaged entries set no option of the env (issue 55: the id says it), so a run
    trains with the id's particles, a task's included."""
    params = load_hyperparams(algo, env_id)
    assert params["env_kwargs"] == {}
    setup = TrainingSetup(algo, env_id, 0, params)
    assert setup.evaluation_env().get("n_particles") == want
    assert params["n_timesteps"] >= 1 and params["n_envs"] >= 1 and params["normalize"] is True


def test_overrides_parse_as_yaml_and_merge_env_kwargs():
    over = parse_overrides(["learning_rate=1e-3", "policy_kwargs={net_arch: [8, 8]}",
                            "env_kwargs={n_steps: 50}"])
    params = load_hyperparams("ppo", "SlamGym/HybridSLAM-v1", overrides=over)
    assert params["learning_rate"] == pytest.approx(1e-3)
    assert params["policy_kwargs"] == {"net_arch": [8, 8]}
    assert params["env_kwargs"] == {"n_steps": 50}


@pytest.mark.parametrize("params, field", [
    ({"n_timesteps": 10, "n_envs": 1, "learning_rat": 1e-3}, "learning_rat"),
    ({"n_timesteps": 0, "n_envs": 1}, "n_timesteps"),
    ({"n_timesteps": 10, "n_envs": 1.5}, "n_envs"),
    ({"n_timesteps": 10, "n_envs": 1, "normalize": "yes"}, "normalize"),
    ({"n_timesteps": 10, "n_envs": 1, "env_kwargs": ["w_map", 2.0]}, "env_kwargs"),
    ({"n_timesteps": 10, "n_envs": 1, "buffer_size": 10}, "buffer_size"),  # a DQN key for PPO
])
def test_bad_hyperparams_raise_naming_the_field(params, field):
    with pytest.raises(ValueError, match=field):
        validate_hyperparams("ppo", params)


def test_bad_files_ids_and_override_syntax_raise(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load_hyperparams("ppo", "SlamGym/HybridSLAM-v1", tmp_path / "missing.yml")
    (tmp_path / "h.yml").write_text("SlamGym/Other-v1: {n_timesteps: 5, n_envs: 1}\n")
    with pytest.raises(ValueError, match="env_id"):
        load_hyperparams("ppo", "SlamGym/HybridSLAM-v1", tmp_path / "h.yml")
    with pytest.raises(ValueError, match="key=value"):
        parse_overrides(["learning_rate"])
    with pytest.raises(ValueError, match="algo"):
        load_hyperparams("sac", "SlamGym/HybridSLAM-v1")


def test_every_simulated_id_trains_at_its_own_clutter_levels():
    for env_id in SIMULATED:
        registered_kwargs(env_id)
    assert training_env("SlamGym/HybridSLAM-Clutter2-v1").levels == (2,)
    assert training_env("SlamGym/HybridSLAM-Zones-v1").levels == (0, 1, 2, 3)
    with pytest.raises(ValueError, match="env_id='SlamGym/MRCLAM-v1' is invalid for training"):
        registered_kwargs("SlamGym/MRCLAM-v1")
    with pytest.raises(ValueError, match="did you mean"):
        registered_kwargs("SlamGym/HybridSLAM-Zone-v1")
    with pytest.raises(ValueError, match="eval_seeds"):
        TrainingSetup("ppo", "SlamGym/HybridSLAM-v1", 0, {}, eval_seeds=(1_000_000,))


def tiny_setup(seed=0, n_timesteps=96, algo="ppo"):
    params = validate_hyperparams(algo, {
        "n_timesteps": n_timesteps, "n_envs": 1, "normalize": True,
        "env_kwargs": {"n_particles": 5, "n_steps": 120},
        **{"ppo": {"n_steps": 32, "batch_size": 32, "n_epochs": 1},
           "a2c": {"n_steps": 8, "policy_kwargs": {"net_arch": [16]}},  # SB3 writes into it
           "dqn": {"learning_starts": 16, "buffer_size": 500}}[algo],
    })
    return TrainingSetup(algo, "SlamGym/HybridSLAM-v1", seed, params, clutter_levels=(0, 2),
                         eval_seeds=(7,), eval_every=64, eval_workers=1, checkpoint_every=32)


def test_a_run_writes_logs_evaluations_and_a_loadable_model(tmp_path):
    import policies

    config = train_run(tiny_setup(), tmp_path / "run", progress=False)
    run = tmp_path / "run"
    log = read_eval_log(run)
    assert [r["timesteps"] for r in log] == [64, 96]  # periodic, then final
    assert all(r["n_episodes"] == 2 and 0 <= r["success_rate"] <= 1 for r in log)
    assert all(r["sampled_n_episodes"] == 2 and 0 <= r["sampled_success_rate"] <= 1 for r in log)
    assert config["deterministic"] == (chosen_mode(log[-1]) == "deterministic")
    with (run / "logs" / "monitor_0.monitor.csv").open() as fh:
        fh.readline()
        episodes = list(csv.DictReader(fh))
    assert episodes and {"r", "l", "failed", "n_fusions", "n_optimisations"} <= set(episodes[0])
    assert (run / "logs" / "progress_0.csv").stat().st_size > 0
    assert config["timesteps"] == 96 and config["feature_names"] == list(FEATURE_NAMES)
    stats = config["observation_normalisation"]
    assert len(stats["mean"]) == len(FEATURE_NAMES) and min(stats["var"]) >= 0
    # the system it was trained on, which the policy checks on loading (provenance)
    assert config["fingerprint"]["env_options"] == {"n_particles": 5}
    policy = policies.make("learned", path=str(run / "model.zip"))
    assert policy.provenance["matches"] is True
    action = policy.act(np.ones(len(FEATURE_NAMES)), {"features": dict.fromkeys(FEATURE_NAMES,
                                                                             1.0)})
    assert action.shape == (2,) and set(action) <= {0, 1}


def test_the_policy_normalises_observations_as_vecnormalize_did(tmp_path):
    """The model acts on the same input at evaluation as in training: log1p, then VecNormalize's
    running statistics (read from model.json, not from SB3's pickle)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    import policies
    from slam_gym.training.run import make_env_fn

    setup = tiny_setup()
    train_run(setup, tmp_path / "run", progress=False)
    vec = VecNormalize.load(str(tmp_path / "run" / "checkpoints" / "vecnormalize_96.pkl"),
                            DummyVecEnv([make_env_fn(setup, 0)]))
    # deterministic: the mode that calls predict (a run may choose sampling by its evaluations)
    policy = policies.make("learned", path=str(tmp_path / "run" / "model.zip"), deterministic=True)
    raw = np.random.default_rng(0).uniform(0, 50, len(FEATURE_NAMES))
    seen = []
    policy.model.predict = lambda x, deterministic: (seen.append(x), (np.zeros(2), None))[1]
    policy.act(raw, {"features": dict(zip(FEATURE_NAMES, raw, strict=True))})
    want = vec.normalize_obs(np.log1p(raw).astype(np.float32))
    np.testing.assert_allclose(seen[0], want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("algo, evaluated", [("ppo", True), ("a2c", True), ("dqn", True),
                                             ("ppo", False)])
def test_resume_continues_from_the_newest_checkpoint(tmp_path, algo, evaluated):
    """With ``evaluated=False`` the run stopped after its checkpoint at 64 decisions but before
    the evaluation due there: the resumed run makes that evaluation first."""
    run = tmp_path / "run"
    train_run(tiny_setup(n_timesteps=64, algo=algo), run, progress=False)
    if algo == "dqn":
        assert (run / "checkpoints" / "replay_64.pkl").is_file()
    # an interrupted longer run: the final model is gone, the checkpoints are there
    (run / "model.zip").unlink()
    (run / "model.json").unlink()
    if not evaluated:
        (run / "eval.csv").unlink()
    with pytest.raises(ValueError, match="resume"):
        train_run(tiny_setup(n_timesteps=128, algo=algo), run, progress=False)
    config = train_run(tiny_setup(n_timesteps=128, algo=algo), run, resume=True, progress=False)
    assert config["timesteps"] == 128
    assert [r["timesteps"] for r in read_eval_log(run)] == [64, 128]
    assert (run / "logs" / "monitor_64.monitor.csv").is_file()
    # a finished run is not trained again
    assert train_run(tiny_setup(n_timesteps=128, algo=algo), run, resume=True)["timesteps"] == 128


def test_train_command_trains_seeds_summarises_and_copies_the_chosen_model(tmp_path, capsys):
    import policies

    assert main(["train", "--timesteps", "64", "--n-envs", "1", "--particles", "5",
                 "--n-steps", "120", "--hp", "n_steps=32", "--hp", "batch_size=32",
                 "--hp", "n_epochs=1", "--seeds", "0,1", "--eval-every", "1000",
                 "--eval-seeds", "3", "--eval-workers", "1", "--clutter-levels", "1",
                 "--out", str(tmp_path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    summary = doc["summary"]
    assert summary["seeds"] == [0, 1] and summary["chosen_seed"] in (0, 1)
    finals = summary["final_evaluation"]
    best = max(finals.values(), key=lambda f: f["mean_return"])
    assert finals[str(summary["chosen_seed"])]["mean_return"] == best["mean_return"]
    config = json.loads((tmp_path / "model.json").read_text())
    assert config["seed"] == summary["chosen_seed"] and config["chosen_among_seeds"] == [0, 1]
    assert (tmp_path / "training_curves.png").stat().st_size > 10_000
    assert policies.make("learned", path=str(tmp_path / "model.zip")).algo == "ppo"
    # the rule's line beside the curves: its record on the same worlds, with the same options
    baseline = summary["baseline"]
    assert baseline["policy"] == "fixed-10s-optimise" and baseline["n_episodes"] == 1
    rule = evaluate_policy("fixed-10s-optimise", clutter_levels=(1,), seeds=(3,),
                           env_kwargs={"n_particles": 5, "n_steps": 120})
    assert baseline["mean_return"] == rule["mean_return"]
    assert "fixed-10s-optimise" in (tmp_path / "summary.md").read_text()


def test_train_command_refuses_an_unknown_baseline_before_training(tmp_path):
    assert main(["train", "--baseline", "no-such-rule", "--out", str(tmp_path)]) == 2
    # a sweep's summaries draw no baseline: asking for one is refused, not ignored
    assert main(["train", "--baseline", "fixed-10s", "--prices", "1,10", "--out",
                 str(tmp_path)]) == 2
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("algo", ["ppo", "a2c"])
def test_the_untrained_policy_starts_at_the_configured_action_probabilities(tmp_path, algo):
    model, _ = untrained_model(tmp_path, algo, 0.1, 0.03)
    obs = np.random.default_rng(1).uniform(0, 5, (64, len(FEATURE_NAMES))).astype(np.float32)
    dist = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0])
    fuse, optimise = (d.probs[:, 1].detach().numpy() for d in dist.distribution)
    np.testing.assert_allclose(fuse, 0.1, atol=0.02)
    np.testing.assert_allclose(optimise, 0.03, atol=0.01)
    with pytest.raises(ValueError, match="initial_optimise_probability"):
        validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1,
                                     "initial_optimise_probability": 1.5})


def test_sampled_actions_follow_the_policy_and_repeat_after_reset(tmp_path):
    """deterministic=False draws from the policy's distribution with its own seeded generator:
    an untrained model started at probabilities 0.1 / 0.03 fuses and optimises at those rates,
    and every reset() replays the same draws."""
    import policies

    _, path = untrained_model(tmp_path, "ppo", 0.1, 0.03)
    policy = policies.make("learned", path=str(path), deterministic=False, sample_seed=4)
    obs = np.random.default_rng(2).uniform(0, 5, (3000, len(FEATURE_NAMES)))
    def info(o):
        return {"features": dict(zip(FEATURE_NAMES, o, strict=True))}

    first = np.array([policy.act(o, info(o)) for o in obs])
    assert first[:, 0].mean() == pytest.approx(0.1, abs=0.02)
    assert first[:, 1].mean() == pytest.approx(0.03, abs=0.01)
    policy.reset()
    again = np.array([policy.act(o, info(o)) for o in obs[:200]])
    np.testing.assert_array_equal(again, first[:200])
    # the mode of these distributions is (0, 0) everywhere
    greedy = policies.make("learned", path=str(path), deterministic=True)
    assert not np.any([greedy.act(o, info(o)) for o in obs[:50]])


def test_chosen_mode_is_the_higher_mean_return():
    assert chosen_mode({"mean_return": -10.0, "sampled_mean_return": -5.0}) == "sampled"
    assert chosen_mode({"mean_return": -5.0, "sampled_mean_return": -5.0}) == "deterministic"
    assert chosen_mode({"mean_return": -5.0}) == "deterministic"


def test_training_curve_leaves_out_episodes_an_interrupted_segment_ran_past_its_resumption(
        tmp_path):
    """Segment 0 ran to 70 decisions, then died; the run resumed from its checkpoint at 50: the
    episodes of segment 0 past 50 were discarded with the lost progress."""
    from slam_gym.training.report import read_monitor

    logs = tmp_path / "logs"
    logs.mkdir()
    header = '#{"t_start": 0}\nr,l,t,failed,n_fusions,n_optimisations\n'
    (logs / "monitor_0.monitor.csv").write_text(
        header + "-1,20,1,False,2,0\n-2,30,2,True,3,1\n-3,20,3,False,2,0\n")
    (logs / "monitor_50.monitor.csv").write_text(header + "-4,25,1,False,2,0\n")
    rows = read_monitor(tmp_path)
    assert [r["t"] for r in rows] == [20, 50, 75]
    assert [r["return"] for r in rows] == [-1, -2, -4]
    assert [r["failed"] for r in rows] == [False, True, False]


def test_training_entries_may_set_the_rewards_price_of_compute():
    params = validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1, "env_kwargs": {
        "n_particles": 5, "w_compute": 20.0, "compute_clip_s": 0.2}})
    assert params["env_kwargs"]["w_compute"] == 20.0
    # every option of the env is the env's to check, before a run is set up
    bad = validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1,
                                       "env_kwargs": {"w_nees": -2.0}})
    with pytest.raises(ValueError, match="w_nees"):
        TrainingSetup("ppo", "SlamGym/HybridSLAM-v1", 0, bad)
    unknown = validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1,
                                           "env_kwargs": {"w_mapp": 2.0}})
    with pytest.raises(ValueError, match="w_mapp"):
        TrainingSetup("ppo", "SlamGym/HybridSLAM-v1", 0, unknown)


def test_a_price_conditioned_run_observes_the_price_and_its_model_reads_it_by_name(tmp_path):
    """``compute_price_range``: each training episode at a drawn price, observed as the feature
    ``compute_price_per_s``; the saved model lists it, and the policy acts on it by name."""
    import policies
    from slam_gym.training.run import make_env_fn

    setup = tiny_setup()
    params = {**setup.hyperparams, "compute_price_range": [1, 100]}
    setup = TrainingSetup("ppo", setup.env_id, 0, validate_hyperparams("ppo", params),
                          clutter_levels=(0,), eval_seeds=(7,), eval_every=64, eval_workers=1,
                          checkpoint_every=64)
    assert setup.feature_names == (*FEATURE_NAMES, "compute_price_per_s")
    env = make_env_fn(setup, 0)()
    prices = []
    for seed in range(6):
        obs, info = env.reset(seed=seed)
        prices.append(info["features"]["compute_price_per_s"])
        assert obs.shape == (len(FEATURE_NAMES) + 1,)
        assert obs[-1] == pytest.approx(np.log1p(prices[-1]))  # the LogFeatures transform
    assert min(prices) >= 1 and max(prices) <= 100 and len(set(prices)) == 6
    config = train_run(setup, tmp_path / "run", progress=False)
    assert config["feature_names"][-1] == "compute_price_per_s"
    assert config["compute_price_range"] == [1.0, 100.0]
    policy = policies.make("learned", path=str(tmp_path / "run" / "model.zip"))
    features = dict.fromkeys(FEATURE_NAMES, 1.0)
    with pytest.raises(ValueError, match="compute_price_per_s"):
        policy.act(np.ones(len(FEATURE_NAMES)), {"features": features})
    action = policy.act(None, {"features": {**features, "compute_price_per_s": 10.0}})
    assert action.shape == (2,) and set(action) <= {0, 1}


@pytest.mark.parametrize("price_range", [[0, 10], [10, 1], [1], "1,10"])
def test_a_bad_price_range_raises_naming_it(price_range):
    with pytest.raises(ValueError, match="compute_price_range"):
        validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1,
                                     "compute_price_range": price_range})


def test_an_interval_learner_starts_at_the_rule_and_its_model_plays_the_rule(tmp_path):
    """Issue 39 items 2-3: a PPO run on the interval env is cloned on the rule before its first
    update and anchored to it; the saved model, loaded as policy ``learned`` in the per-decision
    env, makes fixed-10s-optimise's decisions there (the anchor's weight was still high)."""
    import policies
    from slam_gym.envs.spec import resolve_env
    from slam_gym.evaluation.core import run_policy_object
    from slam_gym.training.run import anchor_weight

    params = validate_hyperparams("ppo", {
        "n_timesteps": 48, "n_envs": 1, "normalize": True, "n_steps": 16, "batch_size": 16,
        "n_epochs": 1, "behaviour_cloning_decisions": 300, "rule_anchor_weight": 20.0,
        "rule_anchor_fraction": 0.5, "env_kwargs": {"n_particles": 20, "n_steps": 600}})
    setup = TrainingSetup("ppo", "SlamGym/HybridSLAM-Interval-v1", 0, params,
                          clutter_levels=(0, 1), eval_seeds=(7,), eval_every=10**6,
                          eval_workers=1, checkpoint_every=10**6)
    config = train_run(setup, tmp_path / "run", progress=False)
    assert config["fusion_intervals_s"][4] == 10.0
    assert config["training_setup"]["extra"]["behaviour_cloning"]["agreement"] >= 0.995
    assert config["fingerprint"]["env_id"] == "SlamGym/HybridSLAM-v1"
    assert anchor_weight(params, 0) == 20.0 and anchor_weight(params, 24) == 0.0
    assert anchor_weight(params, 12) == pytest.approx(10.0)
    learned = policies.make("learned", path=str(tmp_path / "run" / "model.zip"),
                            deterministic=True)
    assert learned.interval and learned.provenance["matches"] is True
    options = dict(n_particles=60, n_steps=600, w_compute=10.0)
    actions = {}
    for name, policy in (("rule", policies.make("fixed-10s-optimise")), ("learned", learned)):
        actions[name] = []
        run_policy_object(policy, resolve_env("SlamGym/HybridSLAM-v1", options), 1, 1,
                          on_step=lambda a, i, out=actions[name]: out.append(a.tolist()))
    assert actions["learned"] == actions["rule"] and sum(a[0] for a in actions["rule"]) >= 4


@pytest.mark.parametrize("key, value", [("behaviour_cloning_decisions", 0),
                                        ("behaviour_cloning_decisions", 2.5),
                                        ("rule_anchor_weight", -1.0),
                                        ("rule_anchor_fraction", 1.5)])
def test_cloning_and_anchor_options_are_validated(key, value):
    with pytest.raises(ValueError, match=key):
        validate_hyperparams("ppo", load_hyperparams("ppo", "SlamGym/HybridSLAM-v1")
                             | {key: value})


# ---- issue 58, Learner 2: the rule cloned and anchored to, and a stacked observation ----------
BEST_ZONED = "threshold-optimise[global_position_std_m>=2]"


def _info(age_s, position_std_m):
    return {"features": {**dict.fromkeys(FEATURE_NAMES, 0.0), "local_map_age_s": age_s,
                         "global_position_std_m": position_std_m}}


def test_rule_action_gives_the_named_rules_action_in_the_per_decision_env():
    """A threshold rule fuses on BB's clock and optimises only above its threshold, where
    fixed-10s-optimise (the default) optimises at every fusion."""
    from slam_gym.training.run import RuleAction

    best, default = RuleAction("SlamGym/HybridSLAM-v1", BEST_ZONED), RuleAction(
        "SlamGym/HybridSLAM-v1")
    assert default.name == "fixed-10s-optimise" and best.name == BEST_ZONED
    cases = {(10.0, 3.0): [1, 1], (10.0, 1.0): [1, 0], (4.0, 3.0): [0, 0]}
    for (age, std), want in cases.items():
        assert best(_info(age, std)).tolist() == want
    assert default(_info(10.0, 1.0)).tolist() == [1, 1]  # the case where the two rules differ


def test_the_interval_env_refuses_another_rule_and_keeps_its_own():
    from slam_gym.envs import INTERVAL_ENV_ID
    from slam_gym.envs.interval import RULE_ACTION
    from slam_gym.training.run import RuleAction

    with pytest.raises(ValueError, match="rule="):
        RuleAction(INTERVAL_ENV_ID, BEST_ZONED)
    np.testing.assert_array_equal(RuleAction(INTERVAL_ENV_ID)(_info(0.0, 0.0)), RULE_ACTION)
    params = validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1, "rule": BEST_ZONED,
                                          "behaviour_cloning_decisions": 10})
    with pytest.raises(ValueError, match="rule="):
        TrainingSetup("ppo", INTERVAL_ENV_ID, 0, params)
    with pytest.raises(ValueError, match="frame_stack=2"):
        TrainingSetup("ppo", INTERVAL_ENV_ID, 0, {**tiny_setup().hyperparams, "frame_stack": 2})


@pytest.mark.parametrize("extra, field", [
    ({"rule": "no-such-rule", "behaviour_cloning_decisions": 10}, "rule"),
    ({"rule": "lookahead", "behaviour_cloning_decisions": 10}, "rule"),  # not a feature rule
    ({"rule": 3, "rule_anchor_weight": 1.0}, "rule"),
    ({"rule": BEST_ZONED}, "rule"),  # nothing would clone it or be anchored to it
    ({"frame_stack": 0}, "frame_stack"),
    ({"frame_stack": 2.0}, "frame_stack"),
    ({"frame_stack": True}, "frame_stack"),
])
def test_bad_rule_and_frame_stack_raise_naming_the_field(extra, field):
    with pytest.raises(ValueError, match=f"{field}="):
        validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1, **extra})
    with pytest.raises(ValueError, match="frame_stack=3"):
        validate_hyperparams("recurrent-ppo", {"n_timesteps": 8, "n_envs": 1, "frame_stack": 3})


@pytest.mark.parametrize("hp, field", [
    (["rule=no-such-rule", "behaviour_cloning_decisions=10"], "rule"),
    (["frame_stack=0"], "frame_stack"),
])
def test_train_command_refuses_a_bad_rule_or_frame_stack_before_writing(tmp_path, capsys, hp,
                                                                        field):
    out = tmp_path / "out"
    argv = ["train", "--timesteps", "8", "--n-envs", "1", "--particles", "5", "--n-steps", "20",
            "--seeds", "0", "--baseline", "none", "--out", str(out)]
    for item in hp:
        argv += ["--hp", item]
    assert main(argv) == 2
    assert f"{field}=" in capsys.readouterr().err
    assert not out.exists()


def test_a_stacked_run_cloned_on_a_threshold_rule_saves_a_model_that_rebuilds_its_history(
        tmp_path):
    """frame_stack 2 and the zoned task's best rule: the run clones that rule (and reports the
    agreement), model.json says frame_stack 2 over a normalisation of 2 x 19 values, and the
    loaded policy, fed only the env's infos, builds at every decision exactly the vector the
    training env gave the network (log1p, the last two frames oldest first, VecNormalize)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    import policies
    from slam_gym.training.run import make_env_fn

    task = "SlamGym/HybridSLAM-Zones-v1"
    params = validate_hyperparams("ppo", {
        "n_timesteps": 64, "n_envs": 1, "normalize": True, "n_steps": 32, "batch_size": 32,
        "n_epochs": 1, "rule": BEST_ZONED, "behaviour_cloning_decisions": 240,
        "rule_anchor_weight": 20.0, "frame_stack": 2,
        "env_kwargs": {"n_particles": 5, "n_steps": 120}})
    setup = TrainingSetup("ppo", task, 0, params, clutter_levels=(0, 2), eval_seeds=(7,),
                          eval_every=10**6, eval_workers=1, checkpoint_every=10**6)
    config = train_run(setup, tmp_path / "run", progress=False)
    assert config["frame_stack"] == 2 and config["hyperparams"]["rule"] == BEST_ZONED
    cloning = config["training_setup"]["extra"]["behaviour_cloning"]
    assert cloning["rule"] == BEST_ZONED and cloning["epochs"] >= 1
    assert 0.9 <= cloning["agreement"] <= 1.0
    assert json.loads((tmp_path / "run" / "behaviour_cloning.json").read_text()) == cloning
    assert len(config["observation_normalisation"]["mean"]) == 2 * len(FEATURE_NAMES)

    vec = VecNormalize.load(str(tmp_path / "run" / "checkpoints" / "vecnormalize_64.pkl"),
                            DummyVecEnv([make_env_fn(setup, 0)]))
    env = make_env_fn(setup, 0)()
    policy = policies.make("learned", path=str(tmp_path / "run" / "model.zip"),
                           deterministic=True)
    assert policy.history.frame_stack == 2 and policy.provenance["matches"] is True
    assert env.get_wrapper_attr("rule_action").name == BEST_ZONED  # the anchor's rule
    seen = []
    predict = policy.model.predict
    policy.model.predict = lambda x, deterministic: (seen.append(x), predict(x, deterministic))[1]
    obs, info = env.reset(seed=5)
    policy.reset()
    rule = policies.make(BEST_ZONED)
    n, done = len(FEATURE_NAMES), False
    while not done:
        action = policy.act(None, info)
        assert action.shape == (2,) and set(action.tolist()) <= {0, 1}
        np.testing.assert_allclose(seen[-1], vec.normalize_obs(obs), rtol=1e-5, atol=1e-5)
        # the first decision's history is its observation twice (padding), then it moves on
        assert np.array_equal(obs[:n], obs[n:]) == (len(seen) == 1)
        obs, _, terminated, truncated, info = env.step(rule.act(None, info))
        done = terminated or truncated
    assert len(seen) >= 5
