"""The distilled planner (issue 58): ``slam_gym.training.dagger`` and ``slam-gym distil``.

The run here is tiny (30 particles: the zoned world's episodes end early), so what it checks is
the loop's bookkeeping and the observation the learner sees, not a learner's quality.
"""

import json

import gymnasium as gym
import numpy as np
import pytest

import policies
from policies.learned import LearnedPolicy, ObservationHistory
from slam_gym.envs.hybrid_slam import FEATURE_NAMES
from slam_gym.envs.wrappers import LogFeatures
from slam_gym.training.dagger import DistillSetup, Episodes, distil, normalise
from slam_gym.training.imitation import fit_labels

TASK = "SlamGym/HybridSLAM-Zones-v1"
BEST = "threshold-optimise[global_position_std_m>=2]"
SMALL = {"n_particles": 30, "w_compute": 10.0, "compute_clip_s": 0.2}
AGE = FEATURE_NAMES.index("local_map_age_s")
STD = FEATURE_NAMES.index("global_position_std_m")


def _stacked_wrapper_env(k):
    """Gymnasium's own history: log1p, then FrameStackObservation, then flattened."""
    env = LogFeatures(gym.make(TASK, **SMALL))
    return gym.wrappers.FlattenObservation(gym.wrappers.FrameStackObservation(env, k))


def test_observation_history_is_gymnasiums_frame_stack_of_the_log_features():
    """The history a learned model keeps equals FrameStackObservation's (padding with the
    episode's first observation) over a whole episode and across a reset."""
    env = _stacked_wrapper_env(4)
    history = ObservationHistory(4)
    rule = policies.make(BEST)
    for seed in (3, 4):
        obs, info = env.reset(seed=seed)
        history.reset()
        rule.reset()
        for _ in range(60):
            mine = history(np.log1p([info["features"][n] for n in FEATURE_NAMES]))
            np.testing.assert_allclose(mine, obs, rtol=1e-6, atol=1e-7)
            obs, _, terminated, truncated, info = env.step(rule.act(None, info))
            if terminated or truncated:
                break


def test_observation_history_rejects_a_bad_size():
    with pytest.raises(ValueError, match="frame_stack"):
        ObservationHistory(0)


def test_fit_labels_learns_a_separable_rule_and_keeps_the_best_held_out_epoch():
    from slam_gym.training.dagger import new_model

    setup = DistillSetup(env_id=TASK, env_kwargs=SMALL, best_rule=BEST, frame_stack=1)
    model = new_model(setup)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, len(FEATURE_NAMES))).astype(np.float32)
    labels = np.stack([x[:, 0] > 0, (x[:, 0] > 0) & (x[:, 1] > 0)], axis=1).astype(np.int64)
    groups = np.arange(3000) // 100
    report = fit_labels(model, x, labels, groups, seed=1)
    assert report["validation_agreement"] > 0.95
    assert 1 <= report["best_epoch"] <= report["epochs"]
    with pytest.raises(ValueError, match="groups"):
        fit_labels(model, x[:10], labels[:10], np.zeros(10), seed=1)
    with pytest.raises(ValueError, match="validation_fraction"):
        fit_labels(model, x, labels, groups, validation_fraction=1.0)


@pytest.mark.parametrize("field, value", [("best_rule", "no-such-rule"), ("frame_stack", 0),
                                          ("beta", 1.5), ("selection_seeds", (2_000_000,)),
                                          ("env_id", "SlamGym/NoSuch-v1")])
def test_setup_names_the_bad_field(field, value):
    kwargs = {"env_id": TASK, "env_kwargs": SMALL, "best_rule": BEST, field: value}
    with pytest.raises(ValueError, match=field):
        DistillSetup(**kwargs)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("distil")
    setup = DistillSetup(env_id=TASK, env_kwargs=SMALL, best_rule=BEST, seed=3,
                         cloning_decisions=300, rounds=1, episodes_per_round=3,
                         selection_seeds=(900000,), command="test")
    config = distil(setup, out)
    return setup, out, config


def test_labels_are_the_rules_where_it_waits_and_the_planners_where_it_fuses(tiny_run):
    setup, out, _ = tiny_run
    age_reached = np.log1p(10.0 - 1e-3)
    cloned = Episodes.load(out / "round_0" / "labels.npz")
    last = cloned.observations[:, -len(FEATURE_NAMES):]  # the newest frame
    fuses = last[:, AGE] >= age_reached
    np.testing.assert_array_equal(cloned.labels[:, 0], fuses)  # the rule's clock
    np.testing.assert_array_equal(cloned.labels[:, 1], fuses & (last[:, STD] >= np.log1p(2.0)))
    assert not cloned.planned.any() and len(cloned.labels) >= 300
    taught = Episodes.load(out / "round_1" / "labels.npz")
    last = taught.observations[:, -len(FEATURE_NAMES):]
    np.testing.assert_array_equal(taught.planned, last[:, AGE] >= age_reached)
    assert not taught.labels[~taught.planned].any()  # both rules wait there
    assert taught.planned.any()
    config = json.loads((out / "round_1" / "model.json").read_text())
    assert config["round_stats"]["planner_labels"] == int(taught.planned.sum())
    assert config["round_stats"]["episodes"] == 3 == len(np.unique(taught.episode))
    assert config["frame_stack"] == 4 and config["env_id"] == TASK


def test_a_snapshot_acts_in_the_benchmark_as_gymnasiums_wrappers_and_its_stats_say(tiny_run):
    """The learned policy loaded from a snapshot (the code users run) takes the action the SB3
    model takes on Gymnasium's stacked observation normalised by the config's statistics."""
    setup, out, _ = tiny_run
    path = out / "round_1" / "model.zip"
    config = json.loads(path.with_suffix(".json").read_text())
    learner = policies.make("learned", path=str(path))
    assert isinstance(learner, LearnedPolicy) and learner.provenance["matches"]
    env = _stacked_wrapper_env(setup.frame_stack)
    obs, info = env.reset(seed=11)
    learner.reset()
    for _ in range(40):
        expected, _ = learner.model.predict(
            normalise(obs[None, :], config["observation_normalisation"]), deterministic=True)
        action = learner.act(None, info)
        np.testing.assert_array_equal(action, expected.reshape(2))
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break


def test_the_selected_snapshot_is_the_best_by_selection_success_then_return(tiny_run):
    from slam_gym.training.dagger import read_rounds

    _, out, config = tiny_run
    rounds = read_rounds(out)
    assert [int(r["round"]) for r in rounds] == [0, 1]
    best = max(rounds, key=lambda r: (r["selection_success_rate"], r["selection_mean_return"]))
    assert config["selected_round"] == int(best["round"])
    assert (out / "model.zip").read_bytes() == (
        out / f"round_{config['selected_round']}" / "model.zip").read_bytes()
    # a finished run is resumed, not redone: the same selection, no round appended
    again = distil(DistillSetup(env_id=TASK, env_kwargs=SMALL, best_rule=BEST, seed=3,
                                cloning_decisions=300, rounds=1, episodes_per_round=3,
                                selection_seeds=(900000,), command="test"), out)
    assert again["selected_round"] == config["selected_round"] and len(read_rounds(out)) == 2


def test_the_learner_is_selected_across_its_seeds(tiny_run, tmp_path):
    """``slam-gym distil --select-from`` copies the best snapshot among several runs."""
    import shutil
    import subprocess
    import sys

    _, out, _ = tiny_run
    other = tmp_path / "seed-b"
    shutil.copytree(out, other)
    lines = (other / "rounds.csv").read_text().splitlines()
    header = lines[0].split(",")
    col = header.index("selection_success_rate")
    fields = lines[-1].split(",")
    fields[col] = "1.0"  # the other run's last round is the best one
    (other / "rounds.csv").write_text("\n".join(lines[:-1] + [",".join(fields)]) + "\n")
    dest = tmp_path / "chosen"
    done = subprocess.run([sys.executable, "-m", "slam_gym.cli", "distil", "--select-from",
                           str(out), str(other), "--out", str(dest)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    config = json.loads((dest / "model.json").read_text())
    assert config["selected_from"] == str(other) and config["selected_round"] == 1
    assert len(config["candidates"]) == 4


def test_weighted_fit_predicts_a_rare_label_the_unweighted_fit_outvotes():
    """Cost-sensitive fitting (Learner 1b): a label that is the minority where the inputs
    overlap is the mode after weighting it, and weights of 1 give the unweighted fit."""
    from slam_gym.training.dagger import new_model

    setup = DistillSetup(env_id=TASK, env_kwargs=SMALL, best_rule=BEST, frame_stack=1)
    rng = np.random.default_rng(2)
    x = rng.normal(size=(4000, len(FEATURE_NAMES))).astype(np.float32)
    # where x0 > 0 the label is "fuse, optimise" 80 % of the time and "wait" 20 %
    rare = (x[:, 0] > 0) & (rng.random(4000) < 0.2)
    labels = np.where(rare[:, None], 0, 1).astype(np.int64).repeat(2, axis=1)
    groups = np.arange(4000) // 100
    plain, weighted, ones = (new_model(setup) for _ in range(3))
    fit_labels(plain, x, labels, groups, seed=1)
    fit_labels(weighted, x, labels, groups, seed=1, weights=np.where(rare, 10.0, 1.0))
    fit_labels(ones, x, labels, groups, seed=1, weights=np.ones(4000))
    probe = x[x[:, 0] > 0.5][:200]
    waits = {name: float(np.mean(m.predict(probe, deterministic=True)[0][:, 0] == 0))
             for name, m in (("plain", plain), ("weighted", weighted), ("ones", ones))}
    assert waits["plain"] < 0.1 < 0.9 < waits["weighted"]
    assert waits["ones"] == pytest.approx(waits["plain"], abs=0.05)


@pytest.mark.parametrize("weights", [np.zeros(300), -np.ones(300), np.ones(299),
                                     np.full(300, np.nan)])
def test_fit_labels_names_bad_weights(weights):
    from slam_gym.training.dagger import new_model

    model = new_model(DistillSetup(env_id=TASK, env_kwargs=SMALL, best_rule=BEST,
                                   frame_stack=1))
    x = np.zeros((300, len(FEATURE_NAMES)), dtype=np.float32)
    with pytest.raises(ValueError, match="weights"):
        fit_labels(model, x, np.zeros((300, 2), dtype=np.int64), np.arange(300) // 10,
                   weights=weights)


def test_departures_are_the_planners_choices_other_than_its_base_rule():
    from slam_gym.training.dagger import departures

    labels = np.array([[1, 1], [0, 0], [1, 0], [0, 0], [1, 1]])
    planned = np.array([True, True, True, False, False])
    data = Episodes(np.zeros((5, 3), np.float32), labels, np.zeros(5, int), planned)
    np.testing.assert_array_equal(departures(data), [False, True, True, False, False])


def test_reweigh_refits_the_cloned_rule_on_the_runs_labels_and_is_selectable(tiny_run,
                                                                              tmp_path):
    """``slam-gym distil --reweigh``: the refit starts at round 0's learner, uses every DAgger
    round's labels with the departures weighted, is selected on the run's worlds, resumes, and
    ``--select-from`` takes it beside the plain run."""
    import subprocess
    import sys

    from slam_gym.training.dagger import departures, read_rounds, reweigh

    setup, out, _ = tiny_run
    dest = tmp_path / "weighted"
    config = reweigh(out, 7.0, dest, command="test")
    taught = Episodes.load(out / "round_1" / "labels.npz")
    assert config["learner"] == "dagger-weighted" and config["round"] == 1
    assert config["reweighted"]["departures"] == int(departures(taught).sum())
    assert config["reweighted"]["decisions"] == len(taught.labels)
    assert config["reweighted"]["departure_weight"] == 7.0
    assert config["observation_normalisation"] == json.loads(
        (out / "round_0" / "model.json").read_text())["observation_normalisation"]
    assert config["selection"]["success_rate"] == pytest.approx(
        read_rounds(dest)[0]["selection_success_rate"])
    assert (dest / "round_1" / "selection").is_dir()
    assert reweigh(out, 7.0, dest)["reweighted"] == config["reweighted"]  # resumed
    assert len(read_rounds(dest)) == 1
    chosen = tmp_path / "chosen"
    done = subprocess.run([sys.executable, "-m", "slam_gym.cli", "distil", "--select-from",
                           str(out), str(dest), "--out", str(chosen)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert len(json.loads((chosen / "model.json").read_text())["candidates"]) == 3
    with pytest.raises(ValueError, match="departure_weight"):
        reweigh(out, 0.0, tmp_path / "bad")
    with pytest.raises(ValueError, match="run_dir"):
        reweigh(tmp_path / "missing", 5.0, tmp_path / "bad")
    done = subprocess.run([sys.executable, "-m", "slam_gym.cli", "distil", "--reweigh",
                           str(out), "--out", str(tmp_path / "bad")],
                          capture_output=True, text=True)
    assert done.returncode != 0 and "departure_weight" in done.stderr
