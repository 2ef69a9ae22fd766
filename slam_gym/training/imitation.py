"""Start a learner at a rule: behaviour cloning through SB3's own policy (issue 39 item 2).

A learner that starts from SB3's random initialisation must rediscover "fuse every 10 s" before
it can improve on it. :func:`clone_rule` instead trains the actor (not the critic) of an on-policy
model to make a rule's decisions on states the rule itself visits, before any reinforcement
learning: the negative log-likelihood of the rule's actions under the policy
(``policy.evaluate_actions``, the function PPO's own loss uses), minimised with Adam until the
policy's mode agrees with the rule on at least ``target_agreement`` of the demonstrations, on
observations normalised exactly as the learner will see them (the demonstrations are drawn
through the learner's own vector env, ``VecNormalize`` included).

Demonstrations come from the training worlds (seeds at or above
:data:`~slam_gym.envs.wrappers.TRAINING_WORLD_SEED_OFFSET`, which the training env draws), so
the agreement the tests measure on evaluation worlds is agreement on worlds never seen.

``imitation`` 1.0.1 pins stable-baselines3 ~2.2 and gymnasium ~0.29, which this stack has moved
past; the few lines here are what it would do for a discrete policy.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

RuleAction = Callable[[Mapping[str, Any]], np.ndarray]
"""The rule's action from one env's ``info`` (its interface features)."""


def rule_demonstrations(vec, rule_action: RuleAction, n_decisions: int,
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Play ``rule_action`` in every env of ``vec`` (an SB3 ``VecEnv``) for ``n_decisions``
    decisions in all; the observations the learner sees there and the rule's actions."""
    if not isinstance(n_decisions, (int, np.integer)) or n_decisions < 1:
        raise ValueError(f"n_decisions={n_decisions!r} is invalid: must be a positive integer")
    observations, actions = [], []
    # the reset infos live on the innermost vector env (a VecNormalize keeps an empty copy)
    inner = getattr(vec, "unwrapped", vec)
    obs = vec.reset()
    infos = list(inner.reset_infos)
    while len(observations) * vec.num_envs < n_decisions:
        chosen = np.array([rule_action(info) for info in infos], dtype=np.int64)
        observations.append(np.array(obs, copy=True))
        actions.append(chosen)
        obs, _, dones, infos = vec.step(chosen)
        # an env that finished resets itself; its next info is the new episode's reset info
        infos = [inner.reset_infos[i] if done else info
                 for i, (done, info) in enumerate(zip(dones, infos, strict=True))]
    return np.concatenate(observations), np.concatenate(actions)


def agreement(model, observations: np.ndarray, actions: np.ndarray) -> float:
    """The fraction of ``observations`` where the policy's mode is the demonstrated action."""
    predicted, _ = model.predict(observations, deterministic=True)
    predicted = np.asarray(predicted).reshape(actions.shape)
    same = predicted == actions
    return float(np.mean(same.all(axis=1) if same.ndim > 1 else same))


def _actor_optimiser(model, learning_rate: float):
    """Adam over the actor's parameters (the critic's, ``value_net``, are left alone)."""
    import torch

    actor = [p for name, p in model.policy.named_parameters()
             if not name.startswith("value_net")]
    return torch.optim.Adam(actor, lr=learning_rate)


def _nll_epoch(policy, optimiser, obs_t, act_t, order: np.ndarray, batch_size: int,
               weight_t=None) -> float:
    """One pass of minibatch steps on the negative log-likelihood of the demonstrated actions
    (``policy.evaluate_actions``, PPO's own log-likelihood), weighted per decision by
    ``weight_t`` when given (the weighted mean over the minibatch); the mean loss."""
    losses = []
    for start in range(0, len(order), batch_size):
        batch = order[start:start + batch_size]
        _, log_prob, _ = policy.evaluate_actions(obs_t[batch], act_t[batch])
        if weight_t is None:
            loss = -log_prob.mean()
        else:
            loss = -(weight_t[batch] * log_prob).sum() / weight_t[batch].sum()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    return float(np.mean(losses))


def mean_nll(model, observations: np.ndarray, actions: np.ndarray,
             weights: np.ndarray | None = None) -> float:
    """The mean negative log-likelihood of ``actions`` under the policy at ``observations``
    (weighted by ``weights`` when given: sum w nll / sum w)."""
    import torch

    with torch.no_grad():
        _, log_prob, _ = model.policy.evaluate_actions(
            torch.as_tensor(observations, dtype=torch.float32),
            torch.as_tensor(actions, dtype=torch.int64))
    if weights is None:
        return float(-log_prob.mean())
    return float(np.average(-log_prob.numpy(), weights=weights))


def fit_labels(model, observations: np.ndarray, actions: np.ndarray, groups: np.ndarray, *,
               validation_fraction: float = 0.15, max_epochs: int = 100, patience: int = 8,
               batch_size: int = 256, learning_rate: float = 1e-3, seed: int = 0,
               weights: np.ndarray | None = None) -> dict[str, float]:
    """Fit ``model``'s actor to labelled decisions (a teacher's, DAgger's aggregate) by the
    negative log-likelihood, with early stopping on held-out episodes.

    ``weights`` (one positive number a decision; default all 1) make the fit cost-sensitive:
    the loss and the held-out criterion are the weighted mean NLL, so a decision of weight W
    counts as W copies of itself (issue 58's Learner 1b weights the teacher's rare departures).

    Labels from a planner are not a function of what the policy observes, so a fit to the
    last label overfits; the decisions of a ``validation_fraction`` of the ``groups``
    (episodes, drawn with ``seed``) are held out, and the actor's weights of the epoch with the
    lowest held-out negative log-likelihood are kept (at most ``max_epochs``, stopping
    ``patience`` epochs after the best). Returns the epochs run, the best epoch, the held-out
    NLL and agreement (the mode against the label) there, and the training agreement."""
    import torch

    groups = np.asarray(groups)
    if not (len(observations) == len(actions) == len(groups) > 0):
        raise ValueError(f"observations, actions, groups=({len(observations)}, {len(actions)}, "
                         f"{len(groups)}) are invalid: must be the same positive length")
    if not 0.0 < validation_fraction < 1.0:
        raise ValueError(f"validation_fraction={validation_fraction!r} is invalid: must be in "
                         "(0, 1)")
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.shape != (len(actions),) or not np.all(np.isfinite(weights)) or not np.all(
                weights > 0):
            raise ValueError(f"weights (shape {weights.shape}) is invalid: must be one finite "
                             f"positive number per decision ({len(actions)})")
    generator = np.random.default_rng(seed)
    unique = np.unique(groups)
    n_held = max(1, int(round(validation_fraction * len(unique))))
    if n_held >= len(unique):
        raise ValueError(f"groups has {len(unique)} episode(s): too few to hold out "
                         f"{validation_fraction:.0%} and train on the rest")
    held = np.isin(groups, generator.choice(unique, size=n_held, replace=False))
    train_obs, train_act = observations[~held], actions[~held]
    val_obs, val_act = observations[held], actions[held]
    train_w = val_w = weight_t = None
    if weights is not None:
        train_w, val_w = weights[~held], weights[held]
        weight_t = torch.as_tensor(train_w, dtype=torch.float32)
    policy = model.policy
    optimiser = _actor_optimiser(model, learning_rate)
    obs_t = torch.as_tensor(train_obs, dtype=torch.float32)
    act_t = torch.as_tensor(train_act, dtype=torch.int64)
    best = (mean_nll(model, val_obs, val_act, val_w), 0, copy.deepcopy(policy.state_dict()))
    epochs = 0
    while epochs < max_epochs and epochs - best[1] < patience:
        policy.set_training_mode(True)
        _nll_epoch(policy, optimiser, obs_t, act_t, generator.permutation(len(train_act)),
                   batch_size, weight_t)
        policy.set_training_mode(False)
        epochs += 1
        held_nll = mean_nll(model, val_obs, val_act, val_w)
        if held_nll < best[0]:
            best = (held_nll, epochs, copy.deepcopy(policy.state_dict()))
    policy.load_state_dict(best[2])
    report = {"epochs": epochs, "best_epoch": best[1], "validation_nll": best[0],
              "validation_agreement": agreement(model, val_obs, val_act),
              "training_agreement": agreement(model, train_obs, train_act),
              "n_training": int(len(train_act)), "n_validation": int(len(val_act))}
    logger.info("fit to %d labels: held-out NLL %.4f, agreement %.4f (epoch %d of %d)",
                len(actions), best[0], report["validation_agreement"], best[1], epochs)
    return report


def clone_rule(model, observations: np.ndarray, actions: np.ndarray, *,
               target_agreement: float = 0.995, max_epochs: int = 200, batch_size: int = 256,
               learning_rate: float = 1e-3, seed: int = 0) -> dict[str, float]:
    """Fit ``model``'s actor to the demonstrations (module docstring); the critic and the
    optimiser state PPO keeps are untouched. Stops at ``target_agreement`` (the policy's mode
    on the demonstrations) or after ``max_epochs``; returns the epochs run, the final agreement
    and the final mean negative log-likelihood."""
    import torch

    if not 0.0 < target_agreement <= 1.0:
        raise ValueError(f"target_agreement={target_agreement!r} is invalid: must be in (0, 1]")
    if len(observations) != len(actions) or len(actions) == 0:
        raise ValueError(f"observations, actions=({len(observations)}, {len(actions)}) are "
                         "invalid: must be the same positive number of demonstrations")
    policy = model.policy
    optimiser = _actor_optimiser(model, learning_rate)
    obs_t = torch.as_tensor(observations, dtype=torch.float32)
    act_t = torch.as_tensor(actions, dtype=torch.int64)
    generator = np.random.default_rng(seed)
    policy.set_training_mode(True)
    epochs, nll = 0, float("nan")
    reached = agreement(model, observations, actions)
    while reached < target_agreement and epochs < max_epochs:
        nll = _nll_epoch(policy, optimiser, obs_t, act_t, generator.permutation(len(actions)),
                         batch_size)
        epochs += 1
        reached = agreement(model, observations, actions)
    policy.set_training_mode(False)
    logger.info("behaviour cloning: agreement %.4f after %d epochs (NLL %.4f) on %d decisions",
                reached, epochs, nll, len(actions))
    return {"epochs": epochs, "agreement": reached, "nll": nll}
