"""Untrained models saved as ``slam-gym train`` saves one, for the tests of training and of
``LearnedPolicy`` (shared so that every algorithm's model is built the same way)."""

from slam_gym.training.hyperparams import validate_hyperparams
from slam_gym.training.run import TrainingSetup


def untrained_model(tmp_path, algo, fuse=None, optimise=None, policy_kwargs=None):
    """An untrained ``algo`` model on ``SlamGym/HybridSLAM-v1`` (5 particles, no normalisation)
    started at the given chances of fusing and optimising (None: SB3's 0.5), and the path of the
    ``model.zip`` (+ ``model.json``) it was saved to."""
    from policies.learned import algorithm_class
    from slam_gym.training.run import (
        _build_vec_env,
        save_model,
        set_initial_action_probabilities,
    )

    params = {"n_timesteps": 8, "n_envs": 1, "normalize": False,
              "env_kwargs": {"n_particles": 5, "n_steps": 60}}
    if fuse is not None:
        params["initial_fuse_probability"] = fuse
    if optimise is not None:
        params["initial_optimise_probability"] = optimise
    params = validate_hyperparams(algo, params)
    setup = TrainingSetup(algo, "SlamGym/HybridSLAM-v1", 0, params)
    vec = _build_vec_env(setup, tmp_path, 0, None)
    model = algorithm_class(algo)(params["policy"], vec, seed=0, device="cpu",
                             policy_kwargs=policy_kwargs)
    set_initial_action_probabilities(model, params)
    path = save_model(model, vec, setup, tmp_path / "m" / "model.zip", 0)
    vec.close()
    return model, path


def train_tiny(tmp_path, algo, *extra_args):
    """``slam-gym train --algo algo`` for 128 decisions of 10 particles on one world of level 1,
    one seed, evaluated once on world 3 (its summary is printed as JSON); the chosen model's
    config."""
    import json

    from slam_gym.cli import main

    assert main(["train", "--algo", algo, "--timesteps", "128", "--n-envs", "1",
                 "--particles", "10", "--n-steps", "120", "--hp", "n_steps=32",
                 "--hp", "batch_size=32", "--hp", "n_epochs=1", "--seeds", "0", *extra_args,
                 "--eval-every", "1000", "--eval-seeds", "3", "--eval-workers", "1",
                 "--clutter-levels", "1", "--out", str(tmp_path), "--json"]) == 0
    return json.loads((tmp_path / "model.json").read_text())
