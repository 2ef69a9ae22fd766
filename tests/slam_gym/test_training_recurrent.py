"""``slam-gym train --algo recurrent-ppo`` (issue 29 item 2): sb3-contrib's RecurrentPPO on the
env's MultiDiscrete([2, 2]), its start at the configured action probabilities, and a saved model
that ``LearnedPolicy`` runs with its LSTM state carried from decision to decision and cleared by
``reset()``."""

import json

import numpy as np
import pytest
from untrained import train_tiny, untrained_model

from slam_gym.envs.hybrid_slam import FEATURE_NAMES
from slam_gym.training.hyperparams import load_hyperparams, validate_hyperparams
from slam_gym.training.run import TrainingSetup

LSTM_KEYS = {"lstm_hidden_size", "n_lstm_layers"}


def test_packaged_recurrent_ppo_hyperparams_are_ppos_with_a_memory():
    for env_id in ("SlamGym/HybridSLAM-v1", "SlamGym/HybridSLAM-Light-v1"):
        recurrent = load_hyperparams("recurrent-ppo", env_id)
        ppo = load_hyperparams("ppo", env_id)
        assert recurrent["policy"] == "MlpLstmPolicy"
        assert set(recurrent["policy_kwargs"]) - set(ppo["policy_kwargs"]) == LSTM_KEYS
        # they compare on the memory alone
        strip = {"policy", "policy_kwargs"}
        assert {k: v for k, v in recurrent.items() if k not in strip} == {
            k: v for k, v in ppo.items() if k not in strip}
        assert {k: v for k, v in recurrent["policy_kwargs"].items() if k not in LSTM_KEYS} == \
            ppo["policy_kwargs"]
    setup = TrainingSetup("recurrent-ppo", "SlamGym/HybridSLAM-v1", 0, recurrent)
    assert not setup.discrete and setup.samples
    # without a policy entry the recurrent algorithm gets the LSTM policy, not the MLP one
    assert validate_hyperparams("recurrent-ppo", {"n_timesteps": 8, "n_envs": 1})["policy"] == \
        "MlpLstmPolicy"


def test_the_untrained_recurrent_policy_starts_at_the_configured_action_probabilities(tmp_path):
    import torch

    model, _ = untrained_model(tmp_path, "recurrent-ppo", 0.1, 0.03)
    obs = np.random.default_rng(1).uniform(0, 5, (64, len(FEATURE_NAMES))).astype(np.float32)
    policy = model.policy
    layers, _, hidden = policy.lstm_hidden_state_shape
    zeros = torch.zeros(layers, 64, hidden)
    dist, _ = policy.get_distribution(policy.obs_to_tensor(obs)[0], (zeros, zeros),
                                      torch.ones(64))
    fuse, optimise = (d.probs[:, 1].detach().numpy() for d in dist.distribution)
    np.testing.assert_allclose(fuse, 0.1, atol=0.02)
    np.testing.assert_allclose(optimise, 0.03, atol=0.01)


def _features(rng, n):
    return [{"features": dict(zip(FEATURE_NAMES, row, strict=True))}
            for row in rng.uniform(0, 5, (n, len(FEATURE_NAMES)))]


def _probabilities(policy, info):
    """The (fuse, optimise) probabilities the policy gives at ``info`` from its carried state,
    without advancing it."""
    import torch

    saved = policy._lstm_state
    x = np.asarray([info["features"][n] for n in FEATURE_NAMES], dtype=np.float32)
    with torch.no_grad():
        dist = policy._recurrent_distribution(policy.model.policy.obs_to_tensor(x)[0])
    policy._lstm_state = saved
    return np.array([d.probs[0, 1].item() for d in dist.distribution])


@pytest.mark.parametrize("deterministic", [True, False])
def test_learned_policy_carries_the_memory_and_reset_clears_it(tmp_path, deterministic):
    """The same observation after two different histories gets different action probabilities
    (the LSTM state is carried; a feed-forward model's would be equal); the deterministic actions
    are those of SB3's own ``predict`` with the state threaded through; and after ``reset()`` an
    episode's actions repeat exactly."""
    import policies

    _, path = untrained_model(tmp_path, "recurrent-ppo", 0.3, 0.3,
                              policy_kwargs={"lstm_hidden_size": 16})
    policy = policies.make("learned", path=str(path), deterministic=deterministic)
    assert policy.algo == "recurrent-ppo" and policy.recurrent and not policy.discrete
    rng = np.random.default_rng(3)
    history_a, history_b, probe = _features(rng, 6), _features(rng, 6), _features(rng, 1)[0]
    after = []
    for history in (history_a, history_b):
        policy.reset()
        for info in history:
            policy.act(None, info)
        after.append(_probabilities(policy, probe))
    assert np.abs(after[0] - after[1]).max() > 1e-4
    policy.reset()
    assert np.array_equal(_probabilities(policy, probe), _probabilities(policy, probe))

    episode = _features(rng, 40)
    runs = []
    for _ in range(2):
        policy.reset()
        runs.append([tuple(policy.act(None, info)) for info in episode])
    assert runs[0] == runs[1]
    if deterministic:
        state, expected = None, []
        for info in episode:
            x = np.asarray([info["features"][n] for n in FEATURE_NAMES], dtype=np.float32)
            action, state = policy.model.predict(x, state=state, deterministic=True,
                                                 episode_start=np.zeros(1, dtype=bool))
            expected.append(tuple(int(a) for a in action))
        assert runs[0] == expected


def test_a_tiny_recurrent_ppo_training_saves_a_model_learned_policy_runs(tmp_path, capsys):
    import policies
    from slam_gym.envs.spec import resolve_env
    from slam_gym.evaluation.core import run_policy_object

    tiny = resolve_env(None, {"n_particles": 10, "n_steps": 120})

    config = train_tiny(tmp_path, "recurrent-ppo",
                        "--hp", "policy_kwargs={net_arch: [8], lstm_hidden_size: 8}")
    assert json.loads(capsys.readouterr().out)["summary"]["chosen_seed"] == 0
    assert config["algo"] == "recurrent-ppo" and config["timesteps"] >= 128
    assert config["hyperparams"]["policy"] == "MlpLstmPolicy"
    final = config["final_evaluation"]
    assert final["n_episodes"] == 1 and final["sampled_n_episodes"] == 1  # both modes evaluated
    policy = policies.make("learned", path=str(tmp_path / "model.zip"), deterministic=False)
    assert policy.algo == "recurrent-ppo"
    runs = []
    for _ in range(2):  # the same policy object twice: reset() between episodes clears memory
        seen = []
        run_policy_object(policy, tiny, 1, 5,
                          on_step=lambda action, info, seen=seen: seen.append(tuple(action)))
        runs.append(seen)
    assert runs[0] and runs[0] == runs[1]
    assert all(a in {(0, 0), (0, 1), (1, 0), (1, 1)} for a in runs[0])
