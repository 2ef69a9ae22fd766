"""How well what the learner observes predicts the planner's departures (issue 58, amendment 2).

    python scripts/results/departure_predictability.py RUN_DIR [RUN_DIR ...] \
        [--held-out 0.25] [--seed 0] [--out REPORT.json]

Each ``RUN_DIR`` is a ``slam-gym distil`` run: the DAgger rounds its ``rounds.csv`` lists (i >=
1) and their ``round_<i>/labels.npz``. Among the decisions where the teacher planned, a
*departure* is one where it chose other than its base rule's fuse-and-optimise
(:func:`slam_gym.training.dagger.departures`): a wait, or a fusion without optimising. The
question is whether the learner's own input (the stacked ``log1p`` features, exactly what it
was fitted on) ranks departures above the rest on episodes it was not fitted on:

* the episodes (per run and round) are split at random, ``--held-out`` of them held out;
* an L2-penalised logistic regression is fitted on the rest (features standardised on the
  fitted part; the penalised likelihood minimised by ``scipy.optimize.minimize``, L-BFGS, with
  its exact gradient);
* the held-out ranking is scored by ROC AUC, ``U / (n_1 n_0)`` from ``scipy.stats.mannwhitneyu``
  (0.5: no better than chance; 1: every departure ranked above every other decision), for all
  departures and for the waits alone.

A linear model is a floor on predictability, not a ceiling; RESULTS' amendment 2 reports a
gradient-boosted classifier (scikit-learn, outside this project) beside it, at the same AUC.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy import optimize, stats

from slam_gym.training.dagger import (
    ROUND_EPISODE_STRIDE,
    TEACHER_BASE_ACTION,
    Episodes,
    dagger_labels,
    departures,
)

WAIT = (0, 0)


def roc_auc(scores: np.ndarray, positive: np.ndarray) -> float:
    """ROC AUC of ``scores`` for the boolean ``positive``: the probability that a positive
    scores above a negative, ties counting one half (the Mann-Whitney U over ``n_1 n_0``)."""
    scores = np.asarray(scores, dtype=float)
    positive = np.asarray(positive, dtype=bool)
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if n_pos == 0 or n_neg == 0:
        raise ValueError(f"positive={n_pos} of {positive.size} is invalid: both classes needed")
    u = stats.mannwhitneyu(scores[positive], scores[~positive], alternative="two-sided").statistic
    return float(u) / (n_pos * n_neg)


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1.0) -> tuple[np.ndarray, float]:
    """Coefficients and intercept of the logistic regression of boolean ``y`` on ``x``, by the
    negative log-likelihood plus ``l2 / 2 |w|^2`` (the intercept not penalised)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.ndim != 2 or x.shape[0] != y.shape[0]:
        raise ValueError(f"x={x.shape} is invalid: one row per label of y={y.shape}")
    n, d = x.shape

    def loss(theta):
        w, b = theta[:d], theta[d]
        z = x @ w + b
        # log(1 + e^z) - y z, summed; its gradient x^T (sigmoid(z) - y)
        nll = float(np.sum(np.logaddexp(0.0, z) - y * z))
        residual = 1.0 / (1.0 + np.exp(-z)) - y
        grad = np.concatenate([x.T @ residual + l2 * w, [residual.sum()]])
        return nll + 0.5 * l2 * float(w @ w), grad

    result = optimize.minimize(loss, np.zeros(d + 1), jac=True, method="L-BFGS-B")
    if not result.success:
        raise RuntimeError(f"the logistic fit did not converge: {result.message}")
    return result.x[:d], float(result.x[d])


def load_runs(run_dirs: list[Path]) -> tuple[Episodes, np.ndarray]:
    """The planned decisions of every DAgger round of ``run_dirs``
    (:func:`~slam_gym.training.dagger.dagger_labels`) and, per decision, its episode's key
    ``"<run>/<round>/<episode in the round>"``, unique across runs (the held-out draw is over
    these keys in sorted order)."""
    parts, keys = [], []
    for r, run_dir in enumerate(run_dirs):
        rounds, data = dagger_labels(run_dir)
        mask = data.planned
        parts.append(Episodes(data.observations[mask], data.labels[mask], data.episode[mask],
                              data.planned[mask]))
        k, e = np.divmod(data.episode[mask], ROUND_EPISODE_STRIDE)
        keys.append(np.array([f"{r}/{rounds[ki]}/{ei}" for ki, ei in zip(k, e, strict=True)]))
    return Episodes.concatenate(parts), np.concatenate(keys)


def predictability(data: Episodes, episode_keys: np.ndarray, *, held_out: float = 0.25,
                   seed: int = 0) -> dict:
    """Held-out ROC AUC of a logistic regression for the departures and for the waits among
    ``data``'s planned decisions (module docstring)."""
    if not 0.0 < held_out < 1.0:
        raise ValueError(f"held_out={held_out!r} is invalid: a fraction in (0, 1)")
    x = np.asarray(data.observations, dtype=float).reshape(len(data.labels), -1)
    episodes = np.unique(episode_keys)
    rng = np.random.default_rng(seed)
    test_episodes = rng.choice(episodes, size=max(1, round(held_out * episodes.size)),
                               replace=False)
    test = np.isin(episode_keys, test_episodes)
    mean, std = x[~test].mean(axis=0), x[~test].std(axis=0)
    std[std == 0] = 1.0
    z = (x - mean) / std
    report = {"decisions": int(x.shape[0]), "episodes": int(episodes.size),
              "held_out_decisions": int(test.sum()), "held_out": held_out, "seed": seed}
    targets = {"departures": departures(data, TEACHER_BASE_ACTION),
               "waits": np.all(data.labels == np.asarray(WAIT), axis=1)}
    for name, y in targets.items():
        w, b = fit_logistic(z[~test], y[~test])
        report[name] = {"share": float(y.mean()), "held_out_positives": int(y[test].sum()),
                        "auc_logistic": roc_auc(z[test] @ w + b, y[test])}
    return report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--held-out", type=float, default=0.25)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    data, keys = load_runs(args.run_dirs)
    report = predictability(data, keys, held_out=args.held_out, seed=args.seed)
    report["runs"] = [str(p) for p in args.run_dirs]
    text = json.dumps(report, indent=2)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n", encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
