"""A stable-baselines3 callback that evaluates the model being trained with the benchmark.

Use it as SB3's own ``EvalCallback``::

    import gymnasium as gym
    from stable_baselines3 import PPO
    from slam_gym.training.callbacks import BenchmarkEvalCallback

    env = gym.make("slam_gym:SlamGym/HybridSLAM-Light-v1")
    model = PPO("MlpPolicy", env)
    callback = BenchmarkEvalCallback(eval_freq=5_000, env_id="SlamGym/HybridSLAM-Light-v1",
                                     clutter_levels=(1, 2), log_path="out/ppo")
    model.learn(50_000, callback=callback)
    callback.evaluations[-1]        # {"timesteps": ..., "success_rate": ..., "anees": ...}

Every ``eval_freq`` calls (with ``n_envs`` training envs, every ``eval_freq * n_envs``
decisions, as in SB3's ``EvalCallback``) it saves a snapshot of the model with the JSON
:class:`policies.learned.LearnedPolicy` reads (the observation transform, the ``VecNormalize``
statistics of the training env if it has one), runs it as policy ``learned`` on fixed worlds
through the benchmark's own code (:func:`slam_gym.training.evaluation.evaluate_model_file`) and
records the benchmark's metrics (:data:`slam_gym.training.evaluation.EVAL_METRICS`) on the
model's logger under ``eval/`` (CSV, TensorBoard: whatever the logger writes), in
:attr:`BenchmarkEvalCallback.evaluations`, and in ``log_path/evaluations.csv``. The snapshot
with the highest mean return is kept as ``log_path/best_model.zip`` (+ ``.json``).

For other libraries, :func:`slam_gym.training.evaluation.evaluate_policy` takes any policy
object and returns the same record.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from stable_baselines3.common.callbacks import BaseCallback

from filters.validation import require
from slam_gym.training.evaluation import (
    DEFAULT_EVAL_SEEDS,
    EVAL_METRICS,
    append_csv_row,
    evaluate_model_file,
    evaluation_env,
    evaluation_record,
)

logger = logging.getLogger(__name__)

OBSERVATION_TRANSFORMS = ("none", "log1p")
"""What stands between the env's observation and the model (``log1p``: the training env was
wrapped in :class:`slam_gym.envs.wrappers.LogFeatures`)."""


class BenchmarkEvalCallback(BaseCallback):
    """Evaluate the model on fixed worlds every ``eval_freq`` calls and log the benchmark's
    metrics (see the module docstring).

    ``env_id`` and ``env_kwargs``: what the training env was made with (``gym.make(env_id,
    **env_kwargs)``; default ``SlamGym/HybridSLAM-v1``; a task id evaluates on the task's
    worlds); the evaluation's env is that env with every option the same
    (:func:`~slam_gym.training.evaluation.evaluation_env`), and a model trained on a subset of
    the features (``features=``) reads them by name. ``clutter_levels`` (None: the env's own)
    and ``seeds``: the fixed worlds. ``observation_transform``: ``"log1p"`` if the training env
    was wrapped in ``LogFeatures``. ``deterministic``: act by the mode of the action distribution
    (True) or by draws from it with a seeded generator (False). ``log_path``: where snapshots,
    their benchmark rows, ``evaluations.csv`` and ``best_model.zip`` go (None: a temporary
    folder, removed at the end of training). ``workers`` > 1 evaluates in a process pool.
    """

    def __init__(
        self,
        eval_freq: int = 10_000,
        *,
        env_id: str | None = None,
        env_kwargs: Mapping[str, Any] | None = None,
        clutter_levels: Iterable[int] | None = None,
        seeds: Iterable[int] = DEFAULT_EVAL_SEEDS,
        observation_transform: str = "none",
        deterministic: bool = True,
        log_path: str | Path | None = None,
        workers: int = 1,
        verbose: int = 1,
    ) -> None:
        super().__init__(verbose=verbose)
        require(isinstance(eval_freq, int) and eval_freq >= 1, "eval_freq", eval_freq,
                "an integer >= 1")
        require(observation_transform in OBSERVATION_TRANSFORMS, "observation_transform",
                observation_transform, f"one of {OBSERVATION_TRANSFORMS}")
        require(isinstance(deterministic, bool), "deterministic", deterministic, "True or False")
        require(isinstance(workers, int) and workers >= 1, "workers", workers, "an integer >= 1")
        self.eval_freq = eval_freq
        from slam_gym.envs.spec import DEFAULT_ENV_ID, registered_kwargs, system_id

        kwargs = dict(env_kwargs or {})
        self.feature_names = kwargs.pop("features", None)
        self.env_id = DEFAULT_ENV_ID if env_id is None else env_id
        self.env = evaluation_env(self.env_id, kwargs, clutter_levels)
        #: what the snapshot's config records (``model.json``'s ``env_options``, as ``slam-gym
        #: train`` writes them): the id's registered options, then the given ones
        self.env_options = {**registered_kwargs(system_id(self.env_id)), **kwargs}
        self.clutter_levels = tuple(self.env.levels)
        self.seeds = tuple(int(seed) for seed in seeds)
        require(bool(self.seeds), "seeds", self.seeds, "at least one seed")
        self.observation_transform = observation_transform
        self.deterministic = deterministic
        self.workers = workers
        self.log_path = None if log_path is None else Path(log_path)
        self._tmp: tempfile.TemporaryDirectory | None = None
        self.evaluations: list[dict[str, Any]] = []
        """One record per evaluation: ``timesteps`` and :data:`EVAL_METRICS`."""
        self.best_mean_return = -math.inf

    def _init_callback(self) -> None:
        if self.log_path is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="slam-gym-callback-")
            self.log_path = Path(self._tmp.name)
        self.log_path.mkdir(parents=True, exist_ok=True)

    def _on_step(self) -> bool:
        if self.n_calls % self.eval_freq == 0:
            self.evaluate()
        return True

    def _on_training_end(self) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()

    def save_snapshot(self, path: Path) -> Path:
        """Save the model and the JSON :class:`policies.learned.LearnedPolicy` needs to act as
        it does in training; returns the zip's path."""
        from slam_gym.training.provenance import system_fingerprint
        from slam_gym.training.run import observation_normalisation

        env_id = self.env_id

        path.parent.mkdir(parents=True, exist_ok=True)
        self.model.save(path)
        config = {
            "timesteps": int(self.num_timesteps),
            "observation_transform": self.observation_transform,
            "observation_normalisation": observation_normalisation(
                self.model.get_vec_normalize_env()),
            "deterministic": self.deterministic,
            "env_id": env_id,
            "env_options": self.env_options,
            "fingerprint": system_fingerprint(env_id, self.env_options),
        }
        if self.feature_names is not None:
            config["feature_names"] = list(self.feature_names)
        path.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
        return path

    def evaluate(self) -> dict[str, Any]:
        """Evaluate the model now; the record (also logged and appended to ``evaluations``)."""
        t = int(self.num_timesteps)
        snapshot = self.save_snapshot(self.log_path / "evals" / f"t{t}" / "model.zip")
        rows = evaluate_model_file(snapshot, snapshot.parent, env=self.env, seeds=self.seeds,
                                   workers=self.workers)
        record = {"timesteps": t, **evaluation_record(rows, self.clutter_levels)}
        self.evaluations.append(record)
        for key, value in record.items():
            if key != "timesteps":
                self.logger.record(f"eval/{key}", value)
        self.logger.record("time/total_timesteps", t, exclude="tensorboard")
        self.logger.dump(t)
        self._append_csv(record)
        if record["mean_return"] > self.best_mean_return:
            self.best_mean_return = record["mean_return"]
            for suffix in (".zip", ".json"):
                shutil.copyfile(snapshot.with_suffix(suffix),
                                self.log_path / f"best_model{suffix}")
        if self.verbose >= 1:
            logger.info("evaluation at %d decisions: success %.2f, return %.1f, ANEES %.2f, "
                        "map error %.2f m, completeness %.2f, interface CPU %.2f s", t,
                        record["success_rate"], record["mean_return"], record["anees"],
                        record["map_error_m"], record["map_completeness"],
                        record["interface_cpu_s"])
        return record

    def _append_csv(self, record: dict[str, Any]) -> None:
        path = self.log_path / "evaluations.csv"
        fields = ["timesteps", *EVAL_METRICS,
                  *(f"success_level_{level}" for level in self.clutter_levels)]
        append_csv_row(path, fields, record)
