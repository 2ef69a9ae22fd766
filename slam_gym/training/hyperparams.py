"""Hyper-parameters per algorithm and env id, read from YAML files in rl-zoo3's layout.

A file maps env ids to settings; the packaged ones are ``slam_gym/training/hyperparams/<algo>.yml``.
An entry holds two kinds of keys:

* the training run's own (:data:`RUN_KEYS`): ``n_timesteps`` (env decisions), ``n_envs``
  (``SubprocVecEnv`` workers), ``policy`` (SB3 policy name), ``normalize`` / ``norm_reward`` /
  ``clip_obs`` (``VecNormalize``, saved with the model), ``env_kwargs`` (keyword arguments of the
  env over the id's own, checked by the env before any run; the packaged files set none: the
  ids say the env, and training, evaluation and the model's record use the same ones),
  ``initial_fuse_probability`` / ``initial_optimise_probability`` (PPO, A2C and MaskablePPO: the
  untrained policy's chance of each action per decision, set through the action head's bias;
  default 0.5, SB3's uniform start; MaskablePPO's one ``Discrete(4)`` head starts at the product
  of the two, renormalised over the actions the mask leaves); ``compute_price_range``
  (``[low, high]``, per second of modelled compute: each training episode draws the reward's
  ``w_compute`` log-uniformly from it and the policy
  observes it as the feature ``compute_price_per_s``, so one policy is conditioned on the price
  of compute; ``env_kwargs.w_compute`` stays the price its evaluations are scored at);
  ``behaviour_cloning_decisions`` (on-policy algorithms: before training, the actor is fitted to
  the rule's decisions on this many decisions of training worlds,
  :mod:`slam_gym.training.imitation`), ``rule_anchor_weight`` and ``rule_anchor_fraction``
  (kickstarting: every decision that differs from the rule's costs this weight in the training
  reward, decaying linearly to 0 at this fraction of ``n_timesteps``;
  :class:`slam_gym.envs.wrappers.RuleAnchor`); ``rule`` (the policy name of that rule, a
  heuristic of :mod:`policies.heuristics` such as
  ``threshold-optimise[global_position_std_m>=2]``; default :data:`DEFAULT_RULE`; only with
  cloning or the anchor, and only the default in the interval env, whose one rule action is
  ``fixed-10s-optimise``'s); ``frame_stack`` (K >= 1, default 1: the policy observes its last K
  observations, oldest first, flattened, Gymnasium's ``FrameStackObservation`` after ``log1p``
  and before ``VecNormalize``; not with ``recurrent-ppo``, which has its own memory, nor in the
  interval env);
* the algorithm's constructor arguments (:data:`ALGO_KEYS`), e.g. PPO's ``n_steps``.

``policy_kwargs`` is a YAML mapping (rl-zoo3 writes a Python string; a mapping needs no ``eval``).
Unknown keys raise ``ValueError`` naming the key, so a typo never trains silently with a default.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

ALGOS: tuple[str, ...] = ("ppo", "a2c", "dqn", "maskable-ppo", "recurrent-ppo")
"""``maskable-ppo`` is sb3-contrib's ``MaskablePPO`` on the env's ``Discrete(4)`` actions with the
redundant optimisation masked (:class:`slam_gym.envs.wrappers.DiscreteActions`);
``recurrent-ppo`` is sb3-contrib's ``RecurrentPPO`` (an LSTM between the features and the heads,
so a decision can depend on the decisions and observations before it in the episode) on the
env's own ``MultiDiscrete([2, 2])``. sb3-contrib is the optional dependency
``pip install slam-gym[contrib]``."""

HYPERPARAMS_DIR = Path(__file__).resolve().parent / "hyperparams"
"""The packaged YAML files, one per algorithm."""

RUN_KEYS: tuple[str, ...] = (
    "n_timesteps", "n_envs", "policy", "normalize", "norm_reward", "clip_obs", "env_kwargs",
    "initial_fuse_probability", "initial_optimise_probability", "compute_price_range",
    "behaviour_cloning_decisions", "rule_anchor_weight", "rule_anchor_fraction", "rule",
    "frame_stack",
)

DEFAULT_RULE = "fixed-10s-optimise"
"""The rule a learner is cloned from and anchored to when its entry names none (``rule``):
round three's (issue 39)."""
_ON_POLICY = ("learning_rate", "n_steps", "gamma", "gae_lambda", "ent_coef", "vf_coef",
              "max_grad_norm", "policy_kwargs", "normalize_advantage")
_PPO = _ON_POLICY + ("batch_size", "n_epochs", "clip_range", "clip_range_vf", "target_kl")
ALGO_KEYS: dict[str, tuple[str, ...]] = {
    "ppo": _PPO,
    "maskable-ppo": _PPO,
    "recurrent-ppo": _PPO,
    "a2c": _ON_POLICY + ("rms_prop_eps", "use_rms_prop"),
    "dqn": ("learning_rate", "buffer_size", "learning_starts", "batch_size", "tau", "gamma",
            "train_freq", "gradient_steps", "target_update_interval", "exploration_fraction",
            "exploration_initial_eps", "exploration_final_eps", "max_grad_norm",
            "policy_kwargs"),
}


def hyperparams_path(algo: str) -> Path:
    """The packaged YAML file of ``algo``."""
    if algo not in ALGOS:
        raise ValueError(f"algo={algo!r} is invalid: must be one of {ALGOS}")
    return HYPERPARAMS_DIR / f"{algo}.yml"


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``["key=value", ...]`` (values parsed as YAML, as rl-zoo3's ``--hyperparams``)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"hp={item!r} is invalid: must be key=value")
        out[key.strip()] = _number_if_numeric(yaml.safe_load(text))
    return out


def _number_if_numeric(value: Any) -> Any:
    """YAML 1.1 reads ``1e-3`` (no dot) as a string: read it as the number it means."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


TASK_IDS_SETTINGS_OF: dict[str, str] = {
    "SlamGym/HybridSLAM-Zones-v1": "SlamGym/HybridSLAM-v0",
    "SlamGym/HybridSLAM-ZonesStarved-v1": "SlamGym/HybridSLAM-v0",
    "SlamGym/HybridSLAM-LongMission-v1": "SlamGym/HybridSLAM-v0",
}
"""The entry a task's training reads when a file has none of its own: the settings of the
system it is a world of (the env's options are the task's own: an entry holds none of them)."""


def load_hyperparams(
    algo: str,
    env_id: str,
    path: str | Path | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The validated settings of ``algo`` for ``env_id`` from ``path`` (default: packaged file).

    ``overrides`` replace entries (``env_kwargs`` is merged key by key).
    """
    file = Path(path) if path is not None else hyperparams_path(algo)
    if not file.is_file():
        raise ValueError(f"hyperparams={str(file)!r} is invalid: no such file")
    try:
        doc = yaml.safe_load(file.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"hyperparams={str(file)!r} is invalid: not YAML ({exc})") from exc
    key = env_id
    if isinstance(doc, dict) and key not in doc and key.endswith("-v1"):
        key = key[:-3] + "-v0"  # -v1 is -v0 with synchronised draws: the same settings
    if isinstance(doc, dict) and key not in doc and env_id in TASK_IDS_SETTINGS_OF:
        key = TASK_IDS_SETTINGS_OF[env_id]  # a task: its system's settings
    if not isinstance(doc, dict) or key not in doc:
        ids = sorted(doc) if isinstance(doc, dict) else []
        raise ValueError(f"env_id={env_id!r} is invalid: {file} has entries for {ids}")
    params = copy.deepcopy(doc[key])
    if not isinstance(params, dict):
        raise ValueError(f"hyperparams[{env_id!r}] in {file} is invalid: must be a mapping")
    for key, value in (overrides or {}).items():
        if key == "env_kwargs" and isinstance(value, dict):
            params["env_kwargs"] = {**params.get("env_kwargs", {}), **value}
        else:
            params[key] = value
    return validate_hyperparams(algo, params, where=f"{file}[{env_id}]")


def validate_hyperparams(algo: str, params: dict[str, Any], where: str = "hyperparams") -> dict:
    """Check the keys and the run settings' values; returns ``params`` with defaults filled."""
    allowed = set(RUN_KEYS) | set(ALGO_KEYS[algo])
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise ValueError(
            f"{where}: keys {unknown} are invalid for {algo}: must be among {sorted(allowed)}"
        )
    params.setdefault("policy", "MlpLstmPolicy" if algo == "recurrent-ppo" else "MlpPolicy")
    params.setdefault("normalize", True)
    params.setdefault("norm_reward", params["normalize"])
    params.setdefault("clip_obs", 10.0)
    params.setdefault("env_kwargs", {})
    for key in ("n_timesteps", "n_envs"):
        value = params.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{where}: {key}={value!r} is invalid: must be an integer >= 1")
    for key in ("normalize", "norm_reward"):
        if not isinstance(params[key], bool):
            raise ValueError(f"{where}: {key}={params[key]!r} is invalid: must be true or false")
    if not isinstance(params["env_kwargs"], dict):
        raise ValueError(f"{where}: env_kwargs={params['env_kwargs']!r} is invalid: "
                         "must be a mapping")
    for key in ("initial_fuse_probability", "initial_optimise_probability"):
        if key not in params:
            continue
        if algo == "dqn":
            raise ValueError(f"{where}: {key} is invalid for dqn (its exploration is "
                             "epsilon-greedy over the four actions)")
        value = params[key]
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 < value < 1:
            raise ValueError(f"{where}: {key}={value!r} is invalid: must be in (0, 1)")
    if "compute_price_range" in params:
        price_range = params["compute_price_range"]
        ok = (isinstance(price_range, (list, tuple)) and len(price_range) == 2
              and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                      for v in price_range)
              and 0 < price_range[0] <= price_range[1] <= 1e6)
        if not ok:
            raise ValueError(f"{where}: compute_price_range={price_range!r} is invalid: must be "
                             "[low, high] with 0 < low <= high <= 1e6 (per second)")
        params["compute_price_range"] = [float(v) for v in price_range]
    for key, low, high, kind in (("behaviour_cloning_decisions", 1, 10**8, int),
                                 ("rule_anchor_weight", 0.0, 1e6, float),
                                 ("rule_anchor_fraction", 0.0, 1.0, float)):
        if key not in params:
            continue
        value = params[key]
        if algo == "dqn":
            raise ValueError(f"{where}: {key} is invalid for dqn (an on-policy actor is cloned "
                             "and anchored)")
        if (not isinstance(value, (int, float)) or isinstance(value, bool)
                or (kind is int and value != int(value)) or not low <= value <= high):
            raise ValueError(f"{where}: {key}={value!r} is invalid: must be a number in "
                             f"[{low}, {high}]")
        params[key] = kind(value)
    if "rule" in params:
        check_rule(params["rule"], where)
        if not ({"behaviour_cloning_decisions", "rule_anchor_weight"} & set(params)):
            raise ValueError(f"{where}: rule={params['rule']!r} is invalid without "
                             "behaviour_cloning_decisions or rule_anchor_weight (nothing "
                             "would imitate it or be anchored to it)")
    if "frame_stack" in params:
        value = params["frame_stack"]
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{where}: frame_stack={value!r} is invalid: must be an integer "
                             ">= 1")
        if value > 1 and algo == "recurrent-ppo":
            raise ValueError(f"{where}: frame_stack={value!r} is invalid for recurrent-ppo "
                             "(its LSTM carries the history; use frame_stack 1)")
    if "policy_kwargs" in params and not isinstance(params["policy_kwargs"], dict):
        raise ValueError(f"{where}: policy_kwargs={params['policy_kwargs']!r} is invalid: "
                         "must be a mapping")
    return params


def check_rule(rule: Any, where: str = "hyperparams") -> str:
    """``rule`` if it names a heuristic that acts on one decision's features (what
    :class:`slam_gym.training.run.RuleAction` asks it for); else ``ValueError`` naming
    ``rule``. The name is built with :func:`policies.make`, so a bad name fails here, before any
    run is set up or written."""
    import policies
    from policies.base import HeuristicPolicy

    if not isinstance(rule, str) or not rule:
        raise ValueError(f"{where}: rule={rule!r} is invalid: must be a policy name, e.g. "
                         f"{DEFAULT_RULE!r}")
    try:
        policy = policies.make(rule)
    except ValueError as exc:
        raise ValueError(f"{where}: rule={rule!r} is invalid: {exc}") from exc
    if not isinstance(policy, HeuristicPolicy):
        raise ValueError(f"{where}: rule={rule!r} is invalid: must be a heuristic rule on the "
                         "interface features (e.g. threshold-optimise[...]); "
                         f"{type(policy).__name__} is not one")
    return rule
