"""One training run of an interface policy: one algorithm, one env id, one seed, resumable.

The run lives in its own directory::

    model.zip, model.json        the final model and everything needed to repeat and load it,
                                 with the fingerprint of the system it was trained on
    checkpoints/                 model_<t>.zip + vecnormalize_<t>.pkl (+ replay_<t>.pkl for DQN)
    logs/progress_<t0>.csv       SB3's logger (losses, rollout returns), one file per segment
    logs/monitor_<t0>.monitor.csv  every training episode: return, length, failed, fusions, ...
    logs/tensorboard/            when tensorboard is installed
    eval.csv                     one row per periodic evaluation on held-out worlds
    evals/t<t>/                  the evaluated snapshot and its results.jsonl (benchmark rows)
    behaviour_cloning.json       with behaviour_cloning_decisions: the rule cloned, the epochs
                                 and the agreement reached (also in model.json)

A segment starts at ``t0`` decisions: 0 for a fresh run, the checkpoint's count for a resumed
one. Resuming loads the newest checkpoint (model, ``VecNormalize`` statistics, DQN's replay buffer)
and trains the remaining decisions; the training worlds continue from a seed derived from the
checkpoint, so a resumed run is deterministic given its checkpoint, though not bit-identical to
an uninterrupted one.

Observations pass through ``log1p`` (:class:`~slam_gym.envs.wrappers.LogFeatures`), with
``frame_stack`` K > 1 through Gymnasium's ``FrameStackObservation`` (the last K, oldest first,
the episode's first observation repeated where there is no history yet) flattened, and then,
with ``normalize``, through ``VecNormalize`` (its statistics cover the stacked vector); the
statistics and K are written into ``model.json`` (``observation_normalisation``,
``frame_stack``) so :class:`policies.learned.LearnedPolicy` applies the same transform without
SB3's pickles. Evaluation runs the snapshot through the benchmark's own code
(:func:`slam_gym.evaluation.run_jobs`, policy ``learned``) on worlds below
:data:`~slam_gym.envs.wrappers.TRAINING_WORLD_SEED_OFFSET`, never trained on.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import platform
import re
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policies.learned import algorithm_class
from slam_gym.training.evaluation import DEFAULT_EVAL_SEEDS, append_csv_row, read_csv_rows
from slam_gym.training.hyperparams import ALGO_KEYS, DEFAULT_RULE

logger = logging.getLogger(__name__)

EVAL_FIELDS: tuple[str, ...] = (
    "timesteps", "success_rate", "mean_return", "anees", "map_error_m", "map_completeness",
    "n_fusions", "n_optimisations", "interface_cpu_s", "n_episodes", "eval_time_s",
)
"""Columns of ``eval.csv`` (then ``success_level_<L>`` per clutter level, and all of them but
``timesteps`` and ``eval_time_s`` again prefixed ``sampled_``)."""

EPISODE_INFO_KEYS: tuple[str, ...] = ("failed", "n_fusions", "n_optimisations", "map_error_m",
                                      "map_completeness")
"""``info`` entries written per training episode into the monitor CSV."""


@dataclass(frozen=True)
class TrainingSetup:
    """Everything one training run needs; written into ``model.json``."""

    algo: str
    env_id: str
    seed: int
    hyperparams: dict[str, Any]
    clutter_levels: tuple[int, ...] = (0, 1, 2, 3)
    eval_seeds: tuple[int, ...] = DEFAULT_EVAL_SEEDS
    eval_every: int = 25_000
    eval_workers: int = 2
    checkpoint_every: int = 25_000
    command: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        from slam_gym.envs.wrappers import TRAINING_WORLD_SEED_OFFSET

        if self.algo not in ALGO_KEYS:
            raise ValueError(f"algo={self.algo!r} is invalid: must be one of {tuple(ALGO_KEYS)}")
        if not self.clutter_levels:
            raise ValueError("clutter_levels=() is invalid: must name at least one level")
        bad = [s for s in self.eval_seeds if not 0 <= s < TRAINING_WORLD_SEED_OFFSET]
        if bad:
            raise ValueError(f"eval_seeds={bad} is invalid: must be in [0, "
                             f"{TRAINING_WORLD_SEED_OFFSET}) (higher seeds are training worlds)")
        for name in ("eval_every", "eval_workers", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}={getattr(self, name)} is invalid: must be >= 1")
        if not (isinstance(self.seed, int) and not isinstance(self.seed, bool)
                and 0 <= self.seed < 2**32):
            raise ValueError(f"seed={self.seed!r} is invalid: must be an integer in [0, 2**32)")
        self.evaluation_env()  # the id and every env option, checked before anything runs
        self._check_rule_and_history()

    def _check_rule_and_history(self) -> None:
        """``rule`` and ``frame_stack`` against the env and the algorithm (their values were
        checked with the hyper-parameters; checked again here for a setup built directly)."""
        from slam_gym.envs import INTERVAL_ENV_ID
        from slam_gym.training.hyperparams import check_rule

        if "rule" in self.hyperparams:
            check_rule(self.hyperparams["rule"])
        if self.env_id == INTERVAL_ENV_ID and self.rule != DEFAULT_RULE:
            raise ValueError(f"rule={self.rule!r} is invalid in {INTERVAL_ENV_ID}: its one rule "
                             f"action is {DEFAULT_RULE}'s (10 s, optimise)")
        k = self.frame_stack
        if not (isinstance(k, int) and not isinstance(k, bool) and k >= 1):
            raise ValueError(f"frame_stack={k!r} is invalid: must be an integer >= 1")
        if k > 1 and self.env_id == INTERVAL_ENV_ID:
            raise ValueError(f"frame_stack={k} is invalid in {INTERVAL_ENV_ID}: a learned model "
                             "of the interval env is played between its fusions without the "
                             "observations it would stack (use frame_stack 1)")
        if k > 1 and self.algo == "recurrent-ppo":
            raise ValueError(f"frame_stack={k} is invalid for recurrent-ppo (its LSTM carries "
                             "the history; use frame_stack 1)")

    @property
    def rule(self) -> str:
        """The rule the learner is cloned from and anchored to (``rule``, default
        :data:`~slam_gym.training.hyperparams.DEFAULT_RULE`)."""
        return self.hyperparams.get("rule", DEFAULT_RULE)

    @property
    def frame_stack(self) -> int:
        """How many of its last observations the policy sees (``frame_stack``, default 1)."""
        return self.hyperparams.get("frame_stack", 1)

    @property
    def discrete(self) -> bool:
        """Whether the policy acts in ``Discrete(4)`` (the env's ``DiscreteActions`` wrapper)."""
        return self.algo in ("dqn", "maskable-ppo")

    @property
    def samples(self) -> bool:
        """Whether the policy has a sampled evaluation mode (every algorithm but DQN, whose only
        stochastic mode is epsilon-greedy exploration)."""
        return self.algo != "dqn"

    def env_options(self) -> dict[str, Any]:
        """The env's options: the id's registered keyword arguments, then ``env_kwargs``."""
        return {**registered_kwargs(self.env_id), **self.hyperparams.get("env_kwargs", {})}

    def evaluation_env(self):
        """The env the run's evaluations (and its baseline) are made in: the system of
        :attr:`env_id` (a wrapped id's) with the run's options, every feature in the
        observation (a model reads its own by name), at :attr:`clutter_levels`
        (a :class:`~slam_gym.envs.spec.ResolvedEnv`; the options were checked when the run
        was set up)."""
        from slam_gym.envs.spec import ResolvedEnv, env_class, system_id

        kwargs = {**self.env_options(), "features": None}
        env_id = system_id(self.env_id)
        return ResolvedEnv.of(env_id, env_class(env_id).resolved_kwargs(**kwargs),
                              self.clutter_levels)

    @property
    def price_range(self) -> tuple[float, float] | None:
        """``[low, high]`` of the price of compute drawn per training episode (None: fixed)."""
        value = self.hyperparams.get("compute_price_range")
        return None if value is None else (float(value[0]), float(value[1]))

    @property
    def feature_names(self) -> tuple[str, ...]:
        """The features the policy observes: every interface feature, and the price of compute
        when it is drawn per episode (:attr:`price_range`)."""
        from slam_gym.envs.hybrid_slam import FEATURE_NAMES

        return FEATURE_NAMES + (("compute_price_per_s",) if self.price_range else ())


def registered_kwargs(env_id: str) -> dict[str, Any]:
    """The keyword arguments ``env_id`` is registered with (a simulated id; a wrapped variant
    such as ``SlamGym/HybridSLAM-Interval-v1`` has those of the system it wraps): a task's are
    its class's defaults (:mod:`slam_gym.envs.tasks`)."""
    from slam_gym.envs import spec

    env_id = spec.system_id(spec.check_env_id(env_id, "env_id"))
    if spec.resolve_env(env_id).scenario == "recorded":
        raise ValueError(f"env_id={env_id!r} is invalid for training: a recording is one "
                         "episode per robot (train on a simulated id, e.g. "
                         f"{spec.DEFAULT_ENV_ID} or SlamGym/HybridSLAM-Zones-v1)")
    return spec.registered_kwargs(env_id)


def training_env(env_id: str, env_kwargs: dict[str, Any] | None = None,
                 clutter_levels=None):
    """The :class:`~slam_gym.envs.spec.ResolvedEnv` a run trains in, evaluates in and records
    in its model (every option checked before anything runs or is written)."""
    from slam_gym.envs.spec import resolve_env

    registered_kwargs(env_id)  # a simulated id
    return resolve_env(env_id, env_kwargs, clutter_levels=clutter_levels)


def make_env_fn(setup: TrainingSetup, rank: int):
    """A picklable constructor of training env ``rank`` (for ``SubprocVecEnv``)."""
    env_id, options = setup.env_id, dict(setup.hyperparams.get("env_kwargs", {}))
    levels, discrete, price_range = setup.clutter_levels, setup.discrete, setup.price_range
    anchored = "rule_anchor_weight" in setup.hyperparams
    rule, frame_stack = setup.rule, setup.frame_stack
    if price_range is not None:
        options["features"] = setup.feature_names

    def make():
        import gymnasium as gym

        from slam_gym.envs.wrappers import (
            DiscreteActions,
            LogFeatures,
            RandomClutterLevel,
            RandomComputePrice,
            RuleAnchor,
        )

        env = gym.make(f"slam_gym:{env_id}", **options)
        env = RandomClutterLevel(env, levels)
        if price_range is not None:
            env = RandomComputePrice(env, *price_range)
        if anchored:  # the callback sets the weight (train_run)
            env = RuleAnchor(env, RuleAction(env_id, rule))
        env = LogFeatures(env)
        if frame_stack > 1:  # what policies.learned.ObservationHistory rebuilds at play
            env = gym.wrappers.FlattenObservation(
                gym.wrappers.FrameStackObservation(env, frame_stack))
        if discrete:
            env = DiscreteActions(env)
        return env

    return make


class RuleAction:
    """The action of ``rule`` (a policy name, default ``fixed-10s-optimise``) in env ``env_id``
    from a decision's ``info``: the rule itself in the per-decision env, its constant action in
    the interval env, where only ``fixed-10s-optimise`` has one (the rule a learner is cloned
    from and anchored to, issue 39 item 2; issue 58: the task's best rule).

    The rule is asked once per decision from that decision's ``info`` alone, by every env of a
    vector env in turn and never reset, so it must keep no state between decisions: a heuristic
    on the features (the threshold rules, ``fixed-*``; ``ValueError`` naming ``rule`` for a name
    that is not a heuristic, or for another rule in the interval env)."""

    def __init__(self, env_id: str, rule: str = DEFAULT_RULE):
        import policies
        from slam_gym.envs import INTERVAL_ENV_ID
        from slam_gym.training.hyperparams import check_rule

        check_rule(rule, "RuleAction")
        if env_id == INTERVAL_ENV_ID and rule != DEFAULT_RULE:
            raise ValueError(f"rule={rule!r} is invalid in {env_id}: its one rule action is "
                             f"{DEFAULT_RULE}'s (10 s, optimise)")
        self.env_id = env_id
        self.name = rule
        self.rule = policies.make(rule)

    def __call__(self, info) -> np.ndarray:
        from slam_gym.envs import INTERVAL_ENV_ID

        if self.env_id == INTERVAL_ENV_ID:
            from slam_gym.envs.interval import RULE_ACTION

            return RULE_ACTION.copy()
        return self.rule.act(None, info)


def anchor_weight(params: dict[str, Any], t: int) -> float:
    """The rule anchor's weight after ``t`` decisions: ``rule_anchor_weight`` decaying linearly
    to 0 at ``rule_anchor_fraction`` (default 0.5) of ``n_timesteps``."""
    w0 = float(params.get("rule_anchor_weight", 0.0))
    end = float(params.get("rule_anchor_fraction", 0.5)) * float(params["n_timesteps"])
    return 0.0 if end <= 0 else w0 * max(0.0, 1.0 - t / end)


def _newest_checkpoint(run_dir: Path) -> int | None:
    steps = [int(m.group(1)) for p in (run_dir / "checkpoints").glob("model_*.zip")
             if (m := re.fullmatch(r"model_(\d+)\.zip", p.name))]
    return max(steps) if steps else None


def observation_normalisation(vec) -> dict[str, Any] | None:
    """The ``VecNormalize`` observation statistics as plain JSON (None without it)."""
    from stable_baselines3.common.vec_env import VecNormalize

    if not isinstance(vec, VecNormalize) or not vec.norm_obs:
        return None
    return {
        "mean": [float(v) for v in vec.obs_rms.mean],
        "var": [float(v) for v in vec.obs_rms.var],
        "clip": float(vec.clip_obs),
        "epsilon": float(vec.epsilon),
    }


def model_config(setup: TrainingSetup, vec, timesteps: int, **extra) -> dict[str, Any]:
    """The JSON written beside a model: how to load it and how it was made, and the fingerprint
    of the system it was trained on (:mod:`slam_gym.training.provenance`: computed once per env
    options in a process), which :class:`policies.learned.LearnedPolicy` checks on loading."""
    from slam_gym.envs import system_env_id
    from slam_gym.training.provenance import system_fingerprint

    return {
        "command": setup.command,
        "algo": setup.algo,
        "env_id": setup.env_id,
        "env_options": setup.env_options(),
        "seed": setup.seed,
        "timesteps": int(timesteps),
        "hyperparams": setup.hyperparams,
        "clutter_levels": list(setup.clutter_levels),
        "eval_seeds": list(setup.eval_seeds),
        "training_world_seeds": ">= 1000000",
        "feature_names": list(setup.feature_names),
        "compute_price_range": (list(setup.price_range) if setup.price_range else None),
        "observation_transform": "log1p",
        "observation_normalisation": observation_normalisation(vec),
        "versions": {"python": platform.python_version(), **package_versions()},
        "fingerprint": system_fingerprint(system_env_id(setup.env_id), setup.env_options()),
        **interval_config(setup.env_id),
        **({"frame_stack": setup.frame_stack} if setup.frame_stack > 1 else {}),
        **extra,
    }


def interval_config(env_id: str) -> dict[str, Any]:
    """For a model of the interval env: ``fusion_intervals_s``, which its first action indexes
    (:class:`policies.learned.LearnedPolicy` plays it in the per-decision env); else {}."""
    from slam_gym.envs import INTERVAL_ENV_ID

    if env_id != INTERVAL_ENV_ID:
        return {}
    from slam_gym.envs.interval import FUSION_INTERVALS_S

    return {"fusion_intervals_s": list(FUSION_INTERVALS_S)}


def package_versions() -> dict[str, str]:
    """The versions of the learning stack a model was made with (written into its config)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {pkg: version(pkg) for pkg in ("stable-baselines3", "torch", "gymnasium", "numpy")}
    try:
        out["sb3-contrib"] = version("sb3-contrib")
    except PackageNotFoundError:
        pass
    return out


def save_model(model, vec, setup: TrainingSetup, path: Path, timesteps: int, **extra) -> Path:
    """``path`` (a .zip) and its config JSON (same stem)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    config = model_config(setup, vec, timesteps, **extra)
    path.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
    return path


EVAL_MODES: tuple[str, ...] = ("deterministic", "sampled")
"""How a snapshot acts in evaluation: the mode of its action distribution, and draws from it
with the policy's own seeded generator (:class:`policies.learned.LearnedPolicy`). ``eval.csv``
holds the deterministic figures under their names and the sampled ones prefixed ``sampled_``."""


def evaluate_snapshot(model_path: Path, setup: TrainingSetup, out: Path,
                      progress: bool = False) -> dict[str, Any]:
    """Run the saved model on the evaluation worlds with the benchmark's code, in both
    :data:`EVAL_MODES` (DQN: deterministic only); one summary row
    (:func:`slam_gym.training.evaluation.evaluation_record`, the callback's figures)."""
    from slam_gym.training.evaluation import evaluate_model_file, evaluation_record

    env = setup.evaluation_env()
    modes = EVAL_MODES if setup.samples else EVAL_MODES[:1]
    start = time.perf_counter()
    record: dict[str, Any] = {}
    for mode in modes:
        rows = evaluate_model_file(
            model_path, out, env=env, seeds=setup.eval_seeds,
            deterministic=None if mode == "deterministic" else False,
            workers=setup.eval_workers, progress=progress)
        prefix = "" if mode == "deterministic" else "sampled_"
        summary = evaluation_record(rows, setup.clutter_levels)
        record.update({prefix + k: v for k, v in summary.items()})
    return {"eval_time_s": time.perf_counter() - start, **record}


def chosen_mode(record: dict[str, float]) -> str:
    """The evaluation mode with the higher mean return in ``record`` (deterministic on ties or
    when the sampled mode was not evaluated)."""
    sampled = record.get("sampled_mean_return", math.nan)
    if np.isfinite(sampled) and sampled > record["mean_return"]:
        return "sampled"
    return "deterministic"


def mode_record(record: dict[str, float], mode: str) -> dict[str, float]:
    """The figures of one mode of an ``eval.csv`` row, under the unprefixed names."""
    if mode == "deterministic":
        return {k: v for k, v in record.items() if not k.startswith("sampled_")}
    return {"timesteps": record["timesteps"],
            **{k[len("sampled_"):]: v for k, v in record.items() if k.startswith("sampled_")}}


def complete_evaluations(run_dir: Path, setup: TrainingSetup) -> list[dict[str, float]]:
    """Evaluate every snapshot of ``eval.csv`` in the modes it lacks (runs trained before the
    sampled mode existed); the rows already there are reused (``run_jobs`` resumes)."""
    log = read_eval_log(run_dir)
    if not setup.samples or all(np.isfinite(r.get("sampled_mean_return", math.nan)) for r in log):
        return log
    (run_dir / "eval.csv").unlink()
    for row in log:
        t = int(row["timesteps"])
        snapshot = run_dir / "evals" / f"t{t}" / "model.zip"
        _append_eval(run_dir, {"timesteps": t,
                               **evaluate_snapshot(snapshot, setup, snapshot.parent)})
    return read_eval_log(run_dir)


def read_eval_log(run_dir: Path) -> list[dict[str, float]]:
    """The rows of ``eval.csv`` (numbers as floats), oldest first."""
    return read_csv_rows(Path(run_dir) / "eval.csv")


def _append_eval(run_dir: Path, record: dict[str, Any]) -> None:
    path = run_dir / "eval.csv"
    levels = sorted(k for k in record if k.startswith("success_level_"))
    fields = list(EVAL_FIELDS) + levels
    if any(k.startswith("sampled_") for k in record):
        fields += ["sampled_" + k for k in EVAL_FIELDS[1:] if k != "eval_time_s"]
        fields += ["sampled_" + k for k in levels]
    append_csv_row(path, fields, record)


def _forget_after(run_dir: Path, checkpoint: int) -> None:
    """Drop the evaluations a resumed run will redo (those after its checkpoint)."""
    kept = [r for r in read_eval_log(run_dir) if r["timesteps"] <= checkpoint]
    if (run_dir / "eval.csv").is_file():
        (run_dir / "eval.csv").unlink()
        for record in kept:
            _append_eval(run_dir, {k: (int(v) if k == "timesteps" else v)
                                   for k, v in record.items()})
    for folder in (run_dir / "evals").glob("t*"):
        if folder.name[1:].isdigit() and int(folder.name[1:]) > checkpoint:
            shutil.rmtree(folder)


def _build_vec_env(setup: TrainingSetup, run_dir: Path, t0: int, checkpoint: int | None):
    from stable_baselines3.common.vec_env import (
        DummyVecEnv,
        SubprocVecEnv,
        VecMonitor,
        VecNormalize,
    )

    params = setup.hyperparams
    fns = [make_env_fn(setup, rank) for rank in range(params["n_envs"])]
    vec = (SubprocVecEnv(fns, start_method="spawn") if len(fns) > 1 else DummyVecEnv(fns))
    (run_dir / "logs").mkdir(parents=True, exist_ok=True)
    vec = VecMonitor(vec, filename=str(run_dir / "logs" / f"monitor_{t0}"),
                     info_keywords=EPISODE_INFO_KEYS)
    if checkpoint is not None and params["normalize"]:
        vec = VecNormalize.load(str(run_dir / "checkpoints" / f"vecnormalize_{checkpoint}.pkl"),
                                vec)
        vec.training = True
    elif params["normalize"]:
        vec = VecNormalize(vec, norm_obs=True, norm_reward=params["norm_reward"],
                           clip_obs=params["clip_obs"], gamma=params.get("gamma", 0.99))
    # each segment draws its own training worlds, deterministically from seed and start
    vec.seed(setup.seed + 7919 * t0)
    return vec


def set_initial_action_probabilities(model, params: dict[str, Any]) -> None:
    """Start an actor-critic policy at the given chance of fusing and of optimising.

    SB3 initialises the action head with weights of gain 0.01 and zero bias, so the untrained
    policy picks each action with probability ~0.5 whatever it observes. Setting the bias of
    each ``Discrete(2)`` head to ``(0, logit p)`` starts it at probability ~p instead; a
    ``Discrete(4)`` head (MaskablePPO) gets the logarithms of the joint chances of the four
    pairs (the two independent). The weights, and so what the policy learns from the features,
    are untouched.
    """
    import torch

    probabilities = [params.get("initial_fuse_probability"),
                     params.get("initial_optimise_probability")]
    if all(p is None for p in probabilities):
        return
    bias = model.policy.action_net.bias
    if not _multi_discrete(model):
        # one Discrete(4) head (a = 2 fuse + optimise): the logits of the product of the two
        # chances (an action masked at a decision leaves the others in the same ratios)
        fuse, optimise = (0.5 if p is None else float(p) for p in probabilities)
        joint = [(1 - fuse) * (1 - optimise), (1 - fuse) * optimise, fuse * (1 - optimise),
                 fuse * optimise]
        with torch.no_grad():
            for a, q in enumerate(joint):
                bias[a] = math.log(q)
        return
    with torch.no_grad():
        for head, p in enumerate(probabilities):
            if p is not None:
                bias[2 * head] = 0.0
                bias[2 * head + 1] = math.log(p / (1.0 - p))


def _multi_discrete(model) -> bool:
    from gymnasium import spaces

    return isinstance(model.action_space, spaces.MultiDiscrete)


def train_run(setup: TrainingSetup, run_dir: Path, *, resume: bool = False,
              progress: bool = True) -> dict[str, Any]:
    """Train (or resume) one run into ``run_dir``; returns its final ``model.json`` content.

    A finished run (``model.zip`` and ``model.json`` present) is not trained again.
    """
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import configure

    run_dir = Path(run_dir)
    final_zip = run_dir / "model.zip"
    if final_zip.is_file() and final_zip.with_suffix(".json").is_file():
        logger.info("%s is finished: skipping (delete it to train again)", run_dir)
        final = complete_evaluations(run_dir, setup)[-1]
        config = json.loads(final_zip.with_suffix(".json").read_text())
        config.update(final_evaluation=final, deterministic=chosen_mode(final) == "deterministic")
        final_zip.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
        return config
    checkpoint = _newest_checkpoint(run_dir) if resume else None
    if not resume and run_dir.exists() and any(run_dir.iterdir()):
        raise ValueError(f"out={str(run_dir)!r} is invalid: it holds an unfinished run; pass "
                         "--resume to continue it or choose an empty directory")
    run_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        _forget_after(run_dir, checkpoint or 0)
        complete_evaluations(run_dir, setup)  # eval.csv's columns stay those of every row
    t0 = checkpoint or 0
    params = setup.hyperparams
    total = int(params["n_timesteps"])
    vec = _build_vec_env(setup, run_dir, t0, checkpoint)
    algo_cls = algorithm_class(setup.algo)
    # a copy: SB3 writes into the dicts it is given (A2C puts RMSprop's class in policy_kwargs)
    kwargs = copy.deepcopy({k: v for k, v in params.items() if k in ALGO_KEYS[setup.algo]})
    if checkpoint is None:
        model = algo_cls(params["policy"], vec, seed=setup.seed, device="cpu", verbose=0,
                         **kwargs)
        set_initial_action_probabilities(model, params)
        if params.get("behaviour_cloning_decisions"):
            from slam_gym.training.imitation import clone_rule, rule_demonstrations

            demos = rule_demonstrations(vec, RuleAction(setup.env_id, setup.rule),
                                        int(params["behaviour_cloning_decisions"]))
            report = clone_rule(model, *demos, seed=setup.seed)
            setup.extra["behaviour_cloning"] = {"rule": setup.rule, **report}
            # kept beside the checkpoints, so a resumed run's model.json still reports it
            (run_dir / "behaviour_cloning.json").write_text(
                json.dumps(setup.extra["behaviour_cloning"], indent=2) + "\n")
            logger.warning("%s: cloned %s on %d decisions: agreement %.4f after %d epochs",
                           run_dir.name, setup.rule, len(demos[1]), report["agreement"],
                           report["epochs"])
    else:
        model = algo_cls.load(str(run_dir / "checkpoints" / f"model_{checkpoint}.zip"),
                              env=vec, device="cpu")
        replay = run_dir / "checkpoints" / f"replay_{checkpoint}.pkl"
        if replay.is_file():
            model.load_replay_buffer(str(replay))
        logger.warning("resuming %s from its checkpoint at %d decisions", run_dir, checkpoint)
        cloning = run_dir / "behaviour_cloning.json"
        if cloning.is_file():
            setup.extra["behaviour_cloning"] = json.loads(cloning.read_text())
    formats = ["csv"] + (["tensorboard"] if _has_tensorboard() else [])
    sb3_logger = configure(str(run_dir / "logs"), formats)
    for fmt in sb3_logger.output_formats:  # one CSV per segment: SB3 truncates its file
        if fmt.__class__.__name__ == "CSVOutputFormat":
            fmt.file.close()
            (run_dir / "logs" / "progress.csv").unlink(missing_ok=True)
            target = run_dir / "logs" / f"progress_{t0}.csv"
            fmt.file = target.open("w+t")
    model.set_logger(sb3_logger)

    class Periodic(BaseCallback):
        """Checkpoints and evaluations at fixed decision counts (resume-safe)."""

        def __init__(self):
            super().__init__()
            self.next_eval = (t0 // setup.eval_every + 1) * setup.eval_every
            self.next_checkpoint = (t0 // setup.checkpoint_every + 1) * setup.checkpoint_every

        def _on_step(self) -> bool:
            t = self.num_timesteps
            if "rule_anchor_weight" in params:
                weight = round(anchor_weight(params, t), 3)  # a change per ~0.1 % of w0
                if weight != getattr(self, "anchor", None):
                    self.training_env.env_method("set_anchor_weight", weight)
                    self.anchor = weight
                    self.logger.record("train/rule_anchor_weight", weight)
            if t >= self.next_checkpoint:
                self.next_checkpoint += setup.checkpoint_every
                save_checkpoint(self.model, t)
            if t >= self.next_eval and t < total:
                self.next_eval += setup.eval_every
                evaluate(self.model, t)
            return True

    def save_checkpoint(model, t: int) -> None:
        folder = run_dir / "checkpoints"
        folder.mkdir(exist_ok=True)
        if params["normalize"]:
            model.get_vec_normalize_env().save(str(folder / f"vecnormalize_{t}.pkl"))
        if setup.algo == "dqn":
            model.save_replay_buffer(str(folder / f"replay_{t}.pkl"))
        model.save(folder / f"model_{t}.zip")  # last: its presence marks a whole checkpoint
        for old in folder.glob("*.*"):  # keep the newest two checkpoints
            m = re.search(r"_(\d+)\.", old.name)
            if m and int(m.group(1)) < t - setup.checkpoint_every:
                old.unlink()

    def evaluate(model, t: int) -> dict[str, Any]:
        snapshot = save_model(model, model.get_env(), setup,
                              run_dir / "evals" / f"t{t}" / "model.zip", t)
        record = {"timesteps": t, **evaluate_snapshot(snapshot, setup, snapshot.parent)}
        _append_eval(run_dir, record)
        logger.warning(
            "%s at %d decisions: success %.2f (sampled %.2f), return %.0f (%.0f), map error "
            "%.2f m, %.1f optimisations/episode (%.1f) [%.0f s]", run_dir.name, t,
            record["success_rate"], record.get("sampled_success_rate", math.nan),
            record["mean_return"], record.get("sampled_mean_return", math.nan),
            record["map_error_m"], record["n_optimisations"],
            record.get("sampled_n_optimisations", math.nan), record["eval_time_s"])
        return record

    due = (t0 // setup.eval_every) * setup.eval_every
    if checkpoint and 0 < due < total and not any(
            r["timesteps"] >= due for r in read_eval_log(run_dir)):
        evaluate(model, t0)  # the run stopped between its checkpoint and this evaluation
    start = time.perf_counter()
    remaining = total - t0
    if remaining > 0:
        model.learn(total_timesteps=remaining, callback=Periodic(),
                    reset_num_timesteps=checkpoint is None, progress_bar=progress)
    train_time = time.perf_counter() - start
    done = int(model.num_timesteps)
    final = evaluate(model, done)
    save_checkpoint(model, done)
    config = save_model(model, model.get_env(), setup, final_zip, done,
                        final_evaluation=final, train_time_s=train_time,
                        deterministic=chosen_mode(final) == "deterministic",
                        training_setup={k: v for k, v in asdict(setup).items()
                                        if k != "hyperparams"})
    vec.close()
    sb3_logger.close()
    return json.loads(config.with_suffix(".json").read_text())


def _has_tensorboard() -> bool:
    import importlib.util

    return importlib.util.find_spec("tensorboard") is not None


def copy_model(run_dir: Path, dest_zip: Path) -> Path:
    """Copy a finished run's ``model.zip`` and ``model.json`` to ``dest_zip`` (+ .json)."""
    src = Path(run_dir) / "model.zip"
    if not src.is_file():
        raise ValueError(f"run_dir={str(run_dir)!r} is invalid: no finished model.zip")
    dest_zip.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dest_zip)
    shutil.copyfile(src.with_suffix(".json"), dest_zip.with_suffix(".json"))
    return dest_zip
