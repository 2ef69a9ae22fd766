"""scripts/results/departure_predictability.py: the AUC and the logistic fit written here are
checked by simulation against what they estimate."""

import csv
from pathlib import Path

import numpy as np
import pytest
from script_loader import load_script

from slam_gym.training.dagger import Episodes

SCRIPT = "results/departure_predictability.py"


def brute_force_auc(scores, positive):
    pos, neg = scores[positive], scores[~positive]
    wins = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return wins / (pos.size * neg.size)


def test_roc_auc_is_the_pairwise_probability_with_ties_halved():
    module = load_script(SCRIPT)
    rng = np.random.default_rng(1)
    scores = rng.integers(0, 6, size=300).astype(float)  # many ties
    positive = rng.random(300) < 0.2
    assert module.roc_auc(scores, positive) == pytest.approx(brute_force_auc(scores, positive))
    assert module.roc_auc(np.arange(10.0), np.arange(10) >= 5) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="positive="):
        module.roc_auc(np.arange(4.0), np.zeros(4, dtype=bool))


def test_the_logistic_fit_recovers_the_simulated_coefficients():
    module = load_script(SCRIPT)
    rng = np.random.default_rng(2)
    w_true, b_true = np.array([1.5, -0.8, 0.0]), -2.0
    x = rng.normal(size=(40_000, 3))
    y = rng.random(40_000) < 1.0 / (1.0 + np.exp(-(x @ w_true + b_true)))
    w, b = module.fit_logistic(x, y, l2=1e-6)
    assert w == pytest.approx(w_true, abs=0.06)
    assert b == pytest.approx(b_true, abs=0.06)
    with pytest.raises(ValueError, match="x="):
        module.fit_logistic(x[:10], y[:11])


def synthetic(rng, informative: bool, n_episodes=200, per_episode=40):
    """Planned decisions whose departures follow feature 0 (informative) or nothing."""
    n = n_episodes * per_episode
    obs = rng.normal(size=(n, 4, 3)).astype(np.float32)
    logit = (3.0 * obs[:, -1, 0] if informative else np.zeros(n)) - 2.5
    depart = rng.random(n) < 1.0 / (1.0 + np.exp(-logit))
    wait = depart & (rng.random(n) < 0.5)
    labels = np.ones((n, 2), dtype=np.int64)
    labels[depart] = (1, 0)
    labels[wait] = (0, 0)
    episode = np.repeat(np.arange(n_episodes), per_episode)
    return Episodes(obs, labels, episode, np.ones(n, dtype=bool)), episode.astype(str)


@pytest.mark.parametrize("informative", [True, False])
def test_held_out_auc_sees_an_informative_feature_and_only_chance_without_one(informative):
    module = load_script(SCRIPT)
    data, keys = synthetic(np.random.default_rng(3), informative)
    report = module.predictability(data, keys, held_out=0.25, seed=0)
    assert report["held_out_decisions"] == 50 * 40  # whole episodes held out
    for target in ("departures", "waits"):
        auc = report[target]["auc_logistic"]
        if informative:
            assert auc > 0.85
        else:
            assert abs(auc - 0.5) < 0.08
    with pytest.raises(ValueError, match="held_out="):
        module.predictability(data, keys, held_out=1.0)


def test_a_run_without_dagger_rounds_names_the_field(tmp_path):
    module = load_script(SCRIPT)
    with pytest.raises(ValueError, match="run_dir="):
        module.load_runs([tmp_path])


def test_runs_load_the_dagger_rounds_planned_decisions_with_keys_unique_across_runs(tmp_path):
    module = load_script(SCRIPT)
    rng = np.random.default_rng(4)
    for run in ("a", "b"):
        for i in (0, 1, 2):
            data, _ = synthetic(rng, True, n_episodes=3, per_episode=5)
            data.planned[::2] = False
            (tmp_path / run / f"round_{i}").mkdir(parents=True)
            data.save(tmp_path / run / f"round_{i}" / "labels.npz")
        (tmp_path / run / "rounds.csv").write_text("round\n0\n1\n2\n")
    data, keys = module.load_runs([tmp_path / "a", tmp_path / "b"])
    assert len(data.labels) == 2 * 2 * 7  # rounds 1-2 of each run, 7 of 15 decisions planned
    assert data.planned.all()
    assert len(np.unique(keys)) == 2 * 2 * 3  # per run, round and episode


@pytest.mark.parametrize("seed", [0, 1])
def test_the_committed_labels_are_the_runs_rounds(seed):
    """The labels committed for RESULTS' figure hold, round by round, the decisions and planner
    labels the run's rounds.csv counts."""
    run = Path(__file__).resolve().parents[1] / "docs/results/issue58" / f"distil-zones-{seed}"
    rounds = {int(r["round"]): r for r in csv.DictReader((run / "rounds.csv").open())}
    for i in (1, 2, 3, 4):
        data = Episodes.load(run / f"round_{i}" / "labels.npz")
        assert len(data.labels) == int(rounds[i]["decisions"])
        assert int(data.planned.sum()) == int(rounds[i]["planner_labels"])
        assert len(np.unique(data.episode)) == int(rounds[i]["episodes"])
