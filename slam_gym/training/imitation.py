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
    actor = [p for name, p in policy.named_parameters() if not name.startswith("value_net")]
    optimiser = torch.optim.Adam(actor, lr=learning_rate)
    obs_t = torch.as_tensor(observations, dtype=torch.float32)
    act_t = torch.as_tensor(actions, dtype=torch.int64)
    generator = np.random.default_rng(seed)
    policy.set_training_mode(True)
    epochs, nll = 0, float("nan")
    reached = agreement(model, observations, actions)
    while reached < target_agreement and epochs < max_epochs:
        order = generator.permutation(len(actions))
        losses = []
        for start in range(0, len(order), batch_size):
            batch = order[start:start + batch_size]
            _, log_prob, _ = policy.evaluate_actions(obs_t[batch], act_t[batch])
            loss = -log_prob.mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            losses.append(loss.item())
        epochs += 1
        nll = float(np.mean(losses))
        reached = agreement(model, observations, actions)
    policy.set_training_mode(False)
    logger.info("behaviour cloning: agreement %.4f after %d epochs (NLL %.4f) on %d decisions",
                reached, epochs, nll, len(actions))
    return {"epochs": epochs, "agreement": reached, "nll": nll}
