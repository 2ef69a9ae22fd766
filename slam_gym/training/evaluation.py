"""The benchmark's measures inside any training loop: evaluate a policy on fixed worlds.

:func:`evaluate_policy` is the plain function (any RL library): it runs a policy -- an object
with ``act(obs, info)`` and ``reset()``, a policy name or a ``package.module:attribute``
reference -- through :func:`slam_gym.evaluation.benchmark` on fixed worlds and returns one
record of the benchmark's metrics::

    success_rate, mean_return, anees, map_error_m (runs that did not fail), map_completeness,
    n_fusions, n_optimisations, interface_cpu_s (CPU of fusions and optimisations),
    n_episodes, success_level_<L> per clutter level

:class:`slam_gym.training.callbacks.BenchmarkEvalCallback` does the same for a
stable-baselines3 model during ``model.learn`` (a snapshot of the model, evaluated as policy
``learned``), and ``slam-gym train`` evaluates its snapshots with :func:`evaluate_model_file`
and :func:`evaluation_record` too, so the three report the same figures.

The default worlds (:data:`DEFAULT_EVAL_SEEDS`) are those ``slam-gym train`` evaluates on: below
:data:`~slam_gym.envs.wrappers.TRAINING_WORLD_SEED_OFFSET`, so never trained on, and not the
seeds 0-99 the reported benchmarks use.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from filters.validation import require

DEFAULT_EVAL_SEEDS: tuple[int, ...] = (900_000, 900_001, 900_002, 900_003, 900_004)
"""The evaluation worlds of ``slam-gym train`` and of the callback (held out from training)."""

EVAL_METRICS: tuple[str, ...] = (
    "success_rate", "mean_return", "anees", "map_error_m", "map_completeness", "n_fusions",
    "n_optimisations", "interface_cpu_s", "n_episodes",
)
"""The keys of an evaluation record (then ``success_level_<L>`` per clutter level)."""

def append_csv_row(path: Path, fields: list[str], record: Mapping[str, Any]) -> None:
    """Append ``record`` (its ``fields``, in order; other keys ignored) to the CSV log ``path``,
    writing the header first when the file is new (the training logs)."""
    import csv

    new = not path.is_file()
    with path.open("a", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        if new:
            writer.writeheader()
        writer.writerow(record)


def read_csv_rows(path: Path) -> list[dict[str, float]]:
    """The rows of a CSV log :func:`append_csv_row` wrote (numbers as floats, an empty cell
    NaN), oldest first; [] when there is none yet."""
    import csv
    import math

    if not path.is_file():
        return []
    with path.open() as fh:
        return [{k: float(v) if v not in ("", None) else math.nan for k, v in row.items()}
                for row in csv.DictReader(fh)]


def evaluation_record(rows: Sequence[Mapping[str, Any]], levels: Iterable[int]) -> dict[str, Any]:
    """The means of :data:`EVAL_METRICS` over benchmark rows (map error over the runs that did
    not fail: a run that fails early keeps a small map with small errors) and the success rate
    per clutter level."""
    from slam_gym.evaluation.summary import metric_values

    survived = [r for r in rows if r["success"]]

    def mean(key, subset=rows):
        values = metric_values(subset, key)
        return float(np.mean(values)) if values else math.nan

    record: dict[str, Any] = {
        "success_rate": mean("success"),
        "mean_return": mean("return"),
        "anees": mean("anees"),
        "map_error_m": mean("map_error_m", survived),
        "map_completeness": mean("map_completeness"),
        "n_fusions": mean("n_fusions"),
        "n_optimisations": mean("n_optimisations"),
        "interface_cpu_s": mean("interface_cpu_s"),
        "n_episodes": len(rows),
    }
    for level in levels:
        record[f"success_level_{level}"] = float(
            np.mean([r["success"] for r in rows if r["clutter_level"] == level]))
    return record


def evaluation_env(env_id: Any = None, env_kwargs: Mapping[str, Any] | None = None,
                   clutter_levels: Iterable[int] | None = None):
    """The env of an evaluation: ``env_id`` (a registered id, default
    ``SlamGym/HybridSLAM-v1``, or a :class:`~slam_gym.envs.spec.ResolvedEnv`; a wrapped id's
    system) with the keyword arguments the policy was trained with, every feature in the
    observation (``features`` is left out: a model trained on a subset reads its own by name,
    from the ``feature_names`` of its config JSON), at ``clutter_levels`` (None: the env's own,
    a task's four). Every option is the env's to check (``ValueError`` naming it)."""
    from slam_gym.envs.spec import ResolvedEnv, resolve_env, system_id

    if isinstance(env_id, ResolvedEnv):
        require(not env_kwargs, "env_kwargs", env_kwargs, "left out with a resolved env")
        return env_id.replace(features=None, levels=clutter_levels)
    kwargs = {k: v for k, v in (env_kwargs or {}).items() if k != "features"}
    return resolve_env(None if env_id is None else system_id(env_id), kwargs,
                       clutter_levels=clutter_levels)


def _check_rows(rows: Sequence[Mapping[str, Any]], what: str) -> None:
    failed = [r for r in rows if r.get("status") != "ok"]
    if failed:
        raise RuntimeError(f"evaluation of {what} failed in {len(failed)} of {len(rows)} runs: "
                           f"{failed[0].get('error')}")


def evaluate_policy(
    policy: Any,
    *,
    env_id: Any = None,
    env_kwargs: Mapping[str, Any] | None = None,
    clutter_levels: Iterable[int] | None = None,
    seeds: Iterable[int] = DEFAULT_EVAL_SEEDS,
    out: str | Path | None = None,
    workers: int = 1,
    progress: bool = False,
) -> dict[str, Any]:
    """Evaluate ``policy`` (object, name or reference) on the worlds ``seeds`` x
    ``clutter_levels`` of ``env_id`` (a task id evaluates on the task's worlds); the record of
    :data:`EVAL_METRICS` (see :func:`evaluation_record`).

    The env is the one of ``env_id`` with ``env_kwargs`` (:func:`evaluation_env`). Runs go
    through :func:`slam_gym.evaluation.benchmark` (``workers`` > 1: a process pool, so the
    policy must pickle); their rows are written into ``out`` (None: a temporary folder). A run
    that raises makes this raise ``RuntimeError`` with the first error: a training loop should
    not go on logging the means of the runs that happened to work.
    """
    from slam_gym.evaluation import benchmark

    env = evaluation_env(env_id, env_kwargs, clutter_levels)
    with tempfile.TemporaryDirectory(prefix="slam-gym-eval-") as tmp:
        result = benchmark(
            [policy], env=env, seeds=list(seeds), baselines=[], figures=False,
            out=out if out is not None else tmp, workers=workers,
            executor="process" if workers > 1 else "serial", progress=progress)
    _check_rows(result.rows, repr(policy))
    return evaluation_record(result.rows, env.levels)


def evaluate_model_file(
    model_path: str | Path,
    out: str | Path,
    *,
    env: Any,
    seeds: Iterable[int] = DEFAULT_EVAL_SEEDS,
    deterministic: bool | None = None,
    workers: int = 1,
    progress: bool = False,
) -> list[dict[str, Any]]:
    """The benchmark rows of a saved stable-baselines3 model (policy ``learned``, its config
    JSON beside it) in ``env`` (a :class:`~slam_gym.envs.spec.ResolvedEnv`: :func:`evaluation_env`)
    on ``seeds`` x its levels, written into ``out`` (resumable). ``deterministic`` None: the
    model's own mode; False: draws from its action distribution."""
    from slam_gym.evaluation import Job, run_jobs
    from slam_gym.evaluation.core import run_job

    options: dict[str, Any] = {"model_path": str(model_path)}
    if deterministic is False:
        options["deterministic"] = False
    jobs = [Job.in_env("policy", "learned", env, level, int(seed), options)
            for level in env.levels for seed in seeds]
    rows = run_jobs(jobs, run_job, out, workers=min(workers, len(jobs)),
                    executor="process" if workers > 1 else "serial", progress=progress)
    _check_rows(rows, str(model_path))
    return rows
