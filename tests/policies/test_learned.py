"""Learned policies (policies.learned): stable-baselines3 zips trained on a toy interface env."""

from __future__ import annotations

import logging
import subprocess
import sys
import zipfile

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces

import policies
import policies.learned as learned
from policies.base import INTERFACE_FEATURES, discrete_to_multi, multi_to_discrete

# its module-scoped fixtures are built once: every test of this file on one worker (pytest -n)
pytestmark = pytest.mark.xdist_group("test_learned")

N_OBS = 5


class ToyInterfaceEnv(gym.Env):
    """A tiny stand-in for the interface env: Box observation, (fuse, optimise) action.

    Reward 1 for fusing when the first feature (a 'local-map age') is above 0.5 and for not
    optimising; episodes of 16 decisions. ``discrete=True`` gives the Discrete(4) action space of
    the env's DQN wrapper, decoded with ``discrete_to_multi``.
    """

    def __init__(self, discrete: bool = False):
        super().__init__()
        self.discrete = discrete
        self.observation_space = spaces.Box(0.0, 1.0, shape=(N_OBS,), dtype=np.float32)
        self.action_space = spaces.Discrete(4) if discrete else spaces.MultiDiscrete([2, 2])
        self._t = 0
        self._obs = np.zeros(N_OBS, np.float32)

    def _draw(self):
        return self.np_random.random(N_OBS).astype(np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._t = 0
        self._obs = self._draw()
        return self._obs, {}

    def step(self, action):
        fuse, optimise = discrete_to_multi(action) if self.discrete else np.asarray(action)
        reward = float(fuse == (self._obs[0] > 0.5)) + float(optimise == 0)
        self._t += 1
        self._obs = self._draw()
        return self._obs, reward, False, self._t >= 16, {}


def _observations(n=20, seed=7):
    return np.random.default_rng(seed).random((n, N_OBS)).astype(np.float32)


@pytest.fixture(scope="module")
def ppo_zip(tmp_path_factory):
    from stable_baselines3 import PPO

    model = PPO(
        "MlpPolicy",
        ToyInterfaceEnv(),
        n_steps=64,
        batch_size=32,
        n_epochs=2,
        seed=0,
        device="cpu",
        policy_kwargs={"net_arch": [16]},
    )
    model.learn(total_timesteps=256)
    path = tmp_path_factory.mktemp("ppo") / "ppo-model.zip"
    model.save(path)
    return path


@pytest.fixture(scope="module")
def dqn_zip(tmp_path_factory):
    from stable_baselines3 import DQN

    model = DQN(
        "MlpPolicy",
        ToyInterfaceEnv(discrete=True),
        learning_starts=32,
        buffer_size=1000,
        batch_size=16,
        train_freq=4,
        seed=0,
        device="cpu",
        policy_kwargs={"net_arch": [16]},
    )
    model.learn(total_timesteps=256)
    path = tmp_path_factory.mktemp("dqn") / "dqn-model.zip"
    model.save(path)
    return path


@pytest.fixture(scope="module")
def a2c_zip(tmp_path_factory):
    from stable_baselines3 import A2C

    model = A2C(
        "MlpPolicy",
        ToyInterfaceEnv(),
        n_steps=8,
        seed=0,
        device="cpu",
        policy_kwargs={"net_arch": [16]},
    )
    model.learn(total_timesteps=128)
    path = tmp_path_factory.mktemp("a2c") / "a2c-model.zip"
    model.save(path)
    return path


# ------------------------------------------------------------------------------------------------
# Discrete(4) <-> (fuse, optimise)
# ------------------------------------------------------------------------------------------------
def test_discrete_mapping_is_2_fuse_plus_optimise_and_a_bijection():
    expected = {0: (0, 0), 1: (0, 1), 2: (1, 0), 3: (1, 1)}
    for a, pair in expected.items():
        out = discrete_to_multi(a)
        assert out.dtype == np.int64 and out.shape == (2,)
        assert tuple(out.tolist()) == pair
        assert multi_to_discrete(out) == a
        assert multi_to_discrete(np.array(pair)) == a
        assert discrete_to_multi(np.int64(a)).tolist() == list(pair)
        assert discrete_to_multi(np.array([a])).tolist() == list(pair)  # predict's shape (1,)


@pytest.mark.parametrize("bad", [-1, 4, 2.0, True, "1", np.array([0, 1])])
def test_discrete_to_multi_rejects_bad_actions(bad):
    with pytest.raises(ValueError, match=r"discrete action=.*must be an integer in \[0, 3\]"):
        discrete_to_multi(bad)


@pytest.mark.parametrize("bad", [(0, 2), (1,), (1, 0, 1), (0.0, 1.0), ((0, 1), (1, 0))])
def test_multi_to_discrete_rejects_bad_pairs(bad):
    with pytest.raises(ValueError, match="action pair=.*must be two integers"):
        multi_to_discrete(bad)


# ------------------------------------------------------------------------------------------------
# Loading and acting
# ------------------------------------------------------------------------------------------------
def _check_deterministic_actions(policy, model, decode):
    obs = _observations()
    first = [policy.act(o, {}) for o in obs]
    policy.reset()
    second = [policy.act(o, {"features": {}}) for o in obs]
    for a, b, o in zip(first, second, obs, strict=True):
        assert a.dtype == np.int64 and a.shape == (2,)
        assert set(a.tolist()) <= {0, 1}
        assert a.tolist() == b.tolist()
        raw, _ = model.predict(o, deterministic=True)
        assert a.tolist() == decode(raw).tolist()
    return first


def test_ppo_zip_acts_deterministically_with_the_env_action_shape(ppo_zip):
    from stable_baselines3 import PPO

    policy = policies.make("learned", path=ppo_zip)
    assert policy.algo == "ppo"
    assert policy.required_features == ()
    assert policy.observation_shape == (N_OBS,)
    assert not policy.discrete
    reference = PPO.load(ppo_zip, device="cpu")
    _check_deterministic_actions(policy, reference, lambda raw: np.asarray(raw, np.int64))
    # a float64 list works too (cast to the model's float32 Box)
    obs = _observations(1)[0]
    assert policy.act(obs.astype(np.float64).tolist(), {}).tolist() == policy.act(obs, {}).tolist()


def test_dqn_has_no_sampled_mode(dqn_zip):
    with pytest.raises(ValueError, match="deterministic"):
        policies.make("learned", path=str(dqn_zip), deterministic=False)


def test_dqn_zip_maps_discrete_actions_to_pairs(dqn_zip):
    from stable_baselines3 import DQN

    policy = policies.make("learned", path=str(dqn_zip))  # algo detected from the zip
    assert policy.algo == "dqn"
    assert policy.discrete
    reference = DQN.load(dqn_zip, device="cpu")
    actions = _check_deterministic_actions(policy, reference, discrete_to_multi)
    flat = [int(reference.predict(o, deterministic=True)[0]) for o in _observations()]
    assert [multi_to_discrete(a) for a in actions] == flat


def test_a2c_by_option_and_by_detection(a2c_zip):
    from stable_baselines3 import A2C

    assert learned.detect_algorithm(a2c_zip) == "a2c"
    by_option = policies.make("learned", path=a2c_zip, algo="A2C")
    detected = policies.make("learned", path=a2c_zip)
    assert by_option.algo == detected.algo == "a2c"
    reference = A2C.load(a2c_zip, device="cpu")
    _check_deterministic_actions(by_option, reference, lambda raw: np.asarray(raw, np.int64))


def test_path_without_zip_suffix_is_accepted(ppo_zip):
    policy = policies.make("learned", path=str(ppo_zip)[: -len(".zip")])
    assert policy.path == ppo_zip


def test_detect_algorithm(ppo_zip, dqn_zip):
    assert learned.detect_algorithm(ppo_zip) == "ppo"
    assert learned.detect_algorithm(dqn_zip) == "dqn"


def test_algo_contradicting_the_zip_raises(ppo_zip, dqn_zip):
    with pytest.raises(ValueError, match="algo='dqn'.*'ppo'"):
        policies.make("learned", path=ppo_zip, algo="dqn")
    with pytest.raises(ValueError, match="algo='ppo'.*'dqn'"):
        policies.make("learned", path=dqn_zip, algo="ppo")


@pytest.mark.parametrize("algo", ["sac", "", 3])
def test_unknown_algo_raises(ppo_zip, algo):
    with pytest.raises(ValueError, match="algo=.*must be one of 'ppo', 'a2c', 'dqn'"):
        policies.make("learned", path=ppo_zip, algo=algo)


def test_bad_options_raise(ppo_zip):
    with pytest.raises(ValueError, match="deterministic=1 is invalid"):
        policies.make("learned", path=ppo_zip, deterministic=1)
    with pytest.raises(ValueError, match="path=.*must be a file path"):
        policies.make("learned", path=3)
    with pytest.raises(ValueError, match="temperature.*deterministic, sample_seed, device"):
        policies.make("learned", path=ppo_zip, temperature=1.0)


def test_wrong_observation_shape_raises(ppo_zip):
    policy = policies.make("learned", path=ppo_zip)
    with pytest.raises(ValueError, match=r"obs shape=\(4,\).*\(5,\)"):
        policy.act(np.zeros(4, np.float32), {})


def test_model_with_a_foreign_action_space_is_rejected(tmp_path):
    from stable_baselines3 import PPO

    env = ToyInterfaceEnv()
    env.action_space = spaces.Discrete(3)
    path = tmp_path / "three.zip"
    PPO("MlpPolicy", env, n_steps=16, batch_size=16, device="cpu").save(path)
    with pytest.raises(ValueError, match=r"model action_space=.*MultiDiscrete\(\[2, 2\]\)"):
        policies.make("learned", path=path)


def test_not_a_model_zip_raises(tmp_path):
    path = tmp_path / "junk.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("readme.txt", "not a model")
    with pytest.raises(ValueError, match="must be a stable-baselines3 model zip"):
        policies.make("learned", path=path)


def test_missing_model_says_how_to_train_one(tmp_path, monkeypatch):
    monkeypatch.setattr(learned, "MODELS_DIR", tmp_path)
    with pytest.raises(FileNotFoundError, match="slam-gym train") as excinfo:
        policies.make("learned")
    assert str(tmp_path / "learned-default.zip") in str(excinfo.value)
    with pytest.raises(FileNotFoundError, match="slam-gym train"):  # no model for it, no default
        policies.make("learned", env_id="SlamGym/HybridSLAM-Zones-v1")
    with pytest.raises(FileNotFoundError, match="slam-gym train"):
        policies.make("learned", path=tmp_path / "nowhere.zip")


def test_default_model_path_is_inside_the_package():
    assert learned.DEFAULT_MODEL_PATH.name == "learned-default.zip"
    assert learned.DEFAULT_MODEL_PATH.parent.name == "models"
    assert learned.DEFAULT_MODEL_PATH.parent.parent.name == "policies"


def test_importing_policies_loads_neither_sb3_nor_the_rest_of_the_project():
    # policies reads two light modules of filters (the feature names, the validation; both
    # import numpy at most), never a filter, numba or the env
    code = (
        "import sys, policies; "
        "bad = [m for m in ('stable_baselines3', 'torch', 'gymnasium', 'slam_gym', 'numba') "
        "if m in sys.modules]; "
        "bad += [m for m in sys.modules if m.startswith('filters.') "
        "and m not in ('filters.interface_features', 'filters.validation')]; "
        "print(','.join(bad))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == ""


def test_the_shipped_model_loads_acts_and_says_how_it_was_made():
    import json

    policy = policies.make("learned")
    assert policy.path == learned.DEFAULT_MODEL_PATH
    assert policy.observation_transform == "log1p"  # from learned-default.json
    config = json.loads(learned.DEFAULT_MODEL_PATH.with_suffix(".json").read_text())
    assert config["command"].startswith("slam-gym train")
    # trained at the paper's configuration, with its normaliser, seed and evaluation mode recorded
    assert config["env_options"]["n_particles"] == 500
    assert config["seed"] in config["chosen_among_seeds"]
    assert len(config["observation_normalisation"]["mean"]) == len(policy.feature_names)
    assert policy.deterministic is config["deterministic"]
    # its hyper-parameters ship as the YAML entry it was trained with, readable by `slam-gym train`
    from slam_gym.training.hyperparams import load_hyperparams

    shipped_yaml = learned.DEFAULT_MODEL_PATH.with_suffix(".yml")
    assert load_hyperparams(config["algo"], config["env_id"], shipped_yaml) == config["hyperparams"]
    assert learned.DEFAULT_MODEL_PATH.with_name("learned-default_training_curves.png").is_file()
    from slam_gym.envs.hybrid_slam import ENV_FEATURE_NAMES

    every_feature = (*INTERFACE_FEATURES, *ENV_FEATURE_NAMES)  # what info["features"] holds
    features = dict.fromkeys(every_feature, 0.0)
    features["compute_price_per_s"] = 10.0
    action = policy.act(np.zeros(len(every_feature), dtype=np.float32), {"features": features})
    assert action.shape == (2,) and action.dtype == np.int64
    # it reads the features it was trained on, by name, whatever the env's observation holds;
    # a model trained over a range of prices of compute reads the price (issue 29)
    assert set(policy.feature_names) <= set(every_feature)
    assert ("compute_price_per_s" in policy.feature_names) == bool(
        config.get("compute_price_range"))
    assert len(policy.feature_names) == policy.observation_shape[0]
    others = [n for n in every_feature if n not in policy.feature_names]
    shifted = dict(features, **dict.fromkeys(others, 5.0))
    policy.reset()  # a sampling policy replays its draws after a reset
    assert policy.act(None, {"features": shifted}).tolist() == action.tolist()
    with pytest.raises(ValueError, match="info"):
        policy.act(None, {"features": {}})


@pytest.mark.parametrize("model", learned.shipped_models(), ids=lambda m: m.path.name)
def test_every_packaged_model_matches_the_code_and_names_its_env(model):
    """Each shipped model (the default and any model shipped for a task) was trained on the
    system this code is: its recorded fingerprint (a fixed seeded rollout of the env under its
    env options) equals the code's. Fails when the filters, features or reward change under a
    shipped model: retrain and ship it (or, for a model trained on this code whose JSON
    predates fingerprints, `slam-gym fingerprint --stamp`). Its config names the env it is for,
    so that ``learned`` in that env loads it."""
    from slam_gym.envs.spec import check_env_id
    from slam_gym.training.provenance import compare_fingerprints, fingerprint_of_config

    config = learned.read_model_config(model.path)
    assert config is not None, f"{model.path.name} ships without its config JSON"
    check_env_id(model.env_id, "env_id")  # a registered id
    differences = compare_fingerprints(config.get("fingerprint"), fingerprint_of_config(config))
    assert not differences, (
        f"the packaged model {model.path.name} does not match the code it ships "
        "with (trained on a different system): " + "; ".join(differences))
    assert learned.resolve_model_path(None, model.env_id, warn=False) == model.path


def test_the_default_model_ships():
    assert learned.DEFAULT_MODEL_PATH in [m.path for m in learned.shipped_models()]


def test_model_digest_identifies_the_file_and_a_stale_digest_is_rejected(ppo_zip, a2c_zip):
    digest = learned.model_digest(ppo_zip)
    assert len(digest) == 16 and digest == learned.model_digest(str(ppo_zip))
    assert learned.model_digest(a2c_zip) != digest
    learned.check_model_digest(ppo_zip, digest)
    learned.check_model_digest(ppo_zip, None)  # no digest given: nothing to check
    with pytest.raises(ValueError, match="model_sha256"):
        learned.check_model_digest(a2c_zip, digest)


def test_benchmark_jobs_of_the_learned_policy_name_its_model(ppo_zip, a2c_zip):
    """A resumed benchmark must not reuse one model's rows for another saved under the same
    name: the model's digest is part of the job (and so of its key)."""
    from slam_gym.envs.spec import resolve_env
    from slam_gym.evaluation.core import learned_options, run_policy

    first, second = learned_options(str(ppo_zip)), learned_options(str(a2c_zip))
    assert first["model_sha256"] != second["model_sha256"]
    assert learned_options(None)["model_sha256"] == learned.model_digest(None)
    with pytest.raises(ValueError, match="model_sha256"):
        run_policy("learned", resolve_env(None, {"n_steps": 20}), 0, 0,
                   model_path=str(a2c_zip), model_sha256=first["model_sha256"])


# ------------------------------------------------------------------------------------------------
# the model of the env it runs in (issue 58 item 6)
# ------------------------------------------------------------------------------------------------
ZONES = "SlamGym/HybridSLAM-Zones-v1"
INTERVAL = "SlamGym/HybridSLAM-Interval-v1"
BB = "SlamGym/HybridSLAM-v1"


@pytest.fixture
def models_dir(tmp_path, monkeypatch):
    """A models directory standing in for the package's: the packaged default model, and a
    model shipped for the Zones task; fallback warnings not yet given in this process."""
    from shipped_models import ship_copy

    directory = tmp_path / "models"
    ship_copy(directory, "learned-default.zip", INTERVAL)
    ship_copy(directory, "learned-zones.zip", ZONES)
    monkeypatch.setattr(learned, "MODELS_DIR", directory)
    monkeypatch.setattr(learned, "_FALLBACK_WARNED", set())
    return directory


def fallback_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "policies.learned" and r.levelname == "WARNING"]


def test_the_shipped_table_maps_each_env_id_to_its_model(models_dir):
    table = learned.model_table()
    assert table == {ZONES: models_dir / "learned-zones.zip",
                     INTERVAL: models_dir / "learned-default.zip",
                     BB: models_dir / "learned-default.zip"}  # the system Interval-v1 wraps
    assert learned.model_table(models_dir) == table  # a directory given, not the patched one
    assert [(m.path.name, m.env_id, m.is_default) for m in learned.shipped_models()] == [
        ("learned-default.zip", INTERVAL, True), ("learned-zones.zip", ZONES, False)]


def test_the_packaged_table_gives_bbs_world_the_default_model():
    assert learned.model_table()[BB] == learned.DEFAULT_MODEL_PATH
    assert learned.resolve_model_path(None, BB) == learned.DEFAULT_MODEL_PATH


def test_learned_resolves_the_model_shipped_for_its_env(models_dir, caplog):
    with caplog.at_level(logging.WARNING, logger="policies.learned"):
        zones = policies.make("learned", env_id=ZONES, check_provenance=False)
        bb = policies.make("learned", env_id=BB, check_provenance=False)
        unnamed = policies.make("learned", check_provenance=False)
        prefixed = learned.resolve_model_path(None, "slam_gym:" + ZONES)  # as gym.make takes it
    assert zones.path == models_dir / "learned-zones.zip" and zones.env_id == ZONES
    assert zones.options["env_id"] == ZONES
    assert bb.path == unnamed.path == models_dir / "learned-default.zip"
    assert prefixed == models_dir / "learned-zones.zip"
    assert fallback_warnings(caplog) == []  # every env here has a model of its own
    assert learned.model_digest(None, ZONES) != learned.model_digest(None, BB)
    assert learned.model_digest(None, BB) == learned.model_digest(None)


def test_an_env_without_a_model_falls_back_to_the_default_with_one_warning(models_dir, caplog):
    task = "SlamGym/HybridSLAM-LongMission-v1"
    with caplog.at_level(logging.WARNING, logger="policies.learned"):
        first = learned.resolve_model_path(None, task)
        policy = policies.make("learned", env_id=task, check_provenance=False)
    assert first == policy.path == models_dir / "learned-default.zip"
    (message,) = fallback_warnings(caplog)  # once per env id and process, not per policy
    assert task in message and INTERVAL in message and "learned-default.zip" in message
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="policies.learned"):
        learned.resolve_model_path(None, "SlamGym/HybridSLAM-v0")  # another env: its own warning
        learned.resolve_model_path(None, "SlamGym/HybridSLAM-Light-v1", warn=False)
    (message,) = fallback_warnings(caplog)
    assert "SlamGym/HybridSLAM-v0" in message


def test_an_explicit_path_wins_over_the_env(models_dir, ppo_zip, caplog):
    with caplog.at_level(logging.WARNING, logger="policies.learned"):
        policy = policies.make("learned", path=ppo_zip, env_id=ZONES, check_provenance=False)
        other = policies.make("learned", path=ppo_zip, env_id="SlamGym/HybridSLAM-LongMission-v1",
                              check_provenance=False)
    assert policy.path == other.path == ppo_zip
    assert learned.resolve_model_path(models_dir / "learned-default", ZONES) == (
        models_dir / "learned-default.zip")
    assert fallback_warnings(caplog) == []  # the env's model is not used: nothing to warn about
    assert learned.model_digest(ppo_zip, ZONES) == learned.model_digest(ppo_zip)


@pytest.mark.parametrize("env_id", [3, "", "  ", ["SlamGym/HybridSLAM-v1"], b"SlamGym/X-v1"])
def test_a_bad_env_id_raises_naming_it(models_dir, ppo_zip, env_id):
    with pytest.raises(ValueError, match="env_id="):
        learned.resolve_model_path(None, env_id)
    with pytest.raises(ValueError, match="env_id="):
        policies.make("learned", path=ppo_zip, env_id=env_id)  # checked with a path too


def test_shipping_a_model_for_an_env_is_dropping_it_in_the_directory(models_dir, caplog):
    from shipped_models import ship_copy

    task = "SlamGym/HybridSLAM-ZonesStarved-v1"
    before = learned.resolve_model_path(None, task)
    assert before == models_dir / "learned-default.zip"
    shipped = ship_copy(models_dir, "learned-zones-starved.zip", task)
    assert learned.resolve_model_path(None, task) == shipped
    assert learned.model_digest(None, task) != learned.model_digest(None, ZONES)
    shipped.with_suffix(".json").unlink()  # a zip without its config names no env: not shipped
    assert learned.resolve_model_path(None, task) == before


def test_two_models_for_one_env_are_refused_naming_both(models_dir):
    from shipped_models import ship_copy

    ship_copy(models_dir, "learned-zones-again.zip", ZONES)
    with pytest.raises(ValueError, match="models_dir=") as excinfo:
        learned.resolve_model_path(None, ZONES)
    assert "learned-zones.zip" in str(excinfo.value)
    assert "learned-zones-again.zip" in str(excinfo.value)


def test_a_model_of_an_env_is_preferred_to_one_that_only_runs_its_system(models_dir):
    from shipped_models import ship_copy

    own = ship_copy(models_dir, "learned-bb.zip", BB)  # trained on BB's env itself
    assert learned.resolve_model_path(None, BB) == own
    assert learned.resolve_model_path(None, INTERVAL) == models_dir / "learned-default.zip"


def test_the_package_data_ships_every_model_of_the_models_directory():
    import fnmatch
    import tomllib
    from pathlib import Path

    root = Path(learned.__file__).resolve().parents[1]
    globs = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"]["policies"]
    for name in ("learned-default", "learned-zones", "learned-long-mission"):
        for suffix in (".zip", ".json"):
            assert any(fnmatch.fnmatch(f"models/{name}{suffix}", g) for g in globs), (name, globs)


def test_benchmark_and_compare_jobs_in_a_task_run_the_tasks_model(models_dir, tmp_path):
    """A job of ``learned`` in an env names the digest of the model shipped for that env (so
    rows of two models never share a key) and its run loads that model: a job made with
    another model's digest is refused by the run."""
    from slam_gym.envs.spec import resolve_env
    from slam_gym.evaluation import Job, benchmark
    from slam_gym.evaluation.compare import resolve_arm
    from slam_gym.evaluation.core import learned_options, run_job

    zones_digest = learned.model_digest(models_dir / "learned-zones.zip")
    default_digest = learned.model_digest(models_dir / "learned-default.zip")
    assert zones_digest != default_digest
    assert learned_options(None, ZONES) == {"model_sha256": zones_digest}
    assert learned_options(None, BB) == {"model_sha256": default_digest}
    assert resolve_arm("learned", ZONES).options == {"model_sha256": zones_digest}
    assert resolve_arm("learned", BB).options == {"model_sha256": default_digest}
    env = resolve_env(ZONES, {"n_particles": 5, "n_steps": 40})
    result = benchmark(["learned"], env=env, clutter_levels=[1], seeds=[3], baselines=[],
                       executor="serial", figures=False, out=tmp_path / "out")
    (row,) = result.rows
    assert row["status"] == "ok", row.get("error")
    assert row["env_id"] == ZONES and row["options"]["model_sha256"] == zones_digest
    assert row["model_matches_code"] is True  # the copy keeps the fingerprint of its weights
    stale = Job.in_env("policy", "learned", env, 1, 3, {"model_sha256": default_digest})
    with pytest.raises(ValueError, match="model_sha256"):
        run_job(stale)  # the run resolves the task's model, not the one the job names
