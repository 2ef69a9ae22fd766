"""The benchmark as a Python function: any policies, the same rows, summary and figures as
``slam-gym benchmark`` (which calls it).

>>> from slam_gym.evaluation import benchmark
>>> result = benchmark(["fixed-10s", MyRule(), "my_package.rules:OtherRule"],
...                    clutter_levels=[2], seeds=5, out="out/mine")      # doctest: +SKIP
>>> result.summary["groups"][0]["success_rate"]                          # doctest: +SKIP

A policy is given as

* a name of :func:`policies.available` (the project's rules, installed plug-ins of entry-point
  group ``slam_gym.policies``, names registered with :func:`policies.register`);
* a reference ``package.module:attribute`` to a policy class, factory or object;
* a policy object (``act(obs, info)`` and ``reset()``), named in the results by its ``name``
  attribute (else its class name); or a mapping ``{name: policy object or factory}`` to choose
  the names.

Every run builds its own policy: a factory is called, an object deep-copied, so no state passes
between runs and the serial, process and Ray executors give the same rows. For the process and
Ray executors, objects and factories must pickle (module-level classes and functions; in a
script, under ``if __name__ == "__main__":``), and the module defining them must be importable
by the worker processes (they start with this process's ``sys.path``).

Each action is checked as it is returned (:func:`policies.base.check_action`): a wrong shape,
dtype or value is a ``ValueError`` naming the policy and the value. A policy that raises turns
its runs into error rows (``status="error"``, the message and traceback in the row) and the rest
of the benchmark completes; the summary counts errors apart and excludes them from the rates.

The figures never call a policy: the runs of the figure world (the first seed at the last
clutter level) record what the episode figures draw as they run (:mod:`.episodes`), under the
executors' error handling and time limit, and the figures are drawn from those recordings and
from the summary. A policy whose run of that world is an error row is left out of them, with a
note in the figure; a figure that cannot be drawn is logged in one line and left out
(:attr:`BenchmarkResult.figure_errors`), and changes nothing else.
"""

from __future__ import annotations

import functools
import logging
import os
import pickle
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from filters.validation import require

logger = logging.getLogger(__name__)

BASELINE_SYSTEMS = ("dead-reckoning",)
"""Systems that can run beside the policies on the same worlds (``baselines``)."""

MAX_RUNS = {"process": 20_000, "serial": 20_000, "ray": 200_000}
"""The most runs one benchmark makes, per executor, checked before any job is built: 20 000 runs
on one machine are days of work at the benchmark's default size (a run takes seconds to
minutes; 2 cores), and a list of a million jobs takes the better part of a gigabyte and minutes
to build before the first run. More worlds: several benchmarks with other ``seed_start`` values,
or Ray on a cluster."""


@dataclass(frozen=True)
class BenchmarkResult:
    """What :func:`benchmark` returns: the ``results.jsonl`` rows of its jobs (in job order),
    the ``summary.json`` document, the figures written (name -> path), the output folder, and
    the figures that could not be drawn (name -> one-line reason; also logged)."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    figures: dict[str, str]
    out: Path
    figure_errors: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class PolicyEntry:
    """A policy of the benchmark: its name in the results and, when a worker process cannot
    build it from the name, the factory or object that travels with the jobs."""

    name: str
    shipped: Any = None
    digest: str | None = None
    """:func:`policies.registry.policy_digest` of a user's policy (None: the project's)."""


def resolve_policies(specs: Any, model: str | None = None,
                     env_id: str | None = None) -> list[PolicyEntry]:
    """Check and name the ``policies`` argument of :func:`benchmark` (``ValueError`` naming the
    entry at fault). Names and references are resolved here, so a typo fails before any run;
    ``learned`` loads ``model``, or the model shipped for ``env_id`` (the env the jobs run in),
    else the default (:func:`policies.learned.resolve_model_path`, which warns once for an env
    with no model of its own)."""
    import policies
    from policies.registry import is_policy, policy_digest, policy_label

    if isinstance(specs, (str, bytes)) or is_policy(specs):
        specs = [specs]
    items: list[tuple[str, Any]]
    if isinstance(specs, Mapping):
        items = [(k, v) for k, v in specs.items()]
        for key, value in items:
            require(isinstance(key, str) and bool(key) and "," not in key,
                    "policies key", key, "a non-empty name without ','")
            require(is_policy(value) or callable(value), f"policies[{key!r}]", value,
                    "a policy object or a factory returning one")
    else:
        require(isinstance(specs, Iterable), "policies", specs,
                "a list of policy names, references or objects, or a {name: policy} mapping")
        items = []
        for i, spec in enumerate(specs):
            if isinstance(spec, str):
                items.append((spec, None))
            else:
                require(is_policy(spec), f"policies[{i}]", spec,
                        "a policy name, a 'package.module:attribute' reference or an object "
                        "with act(obs, info) and reset()")
                items.append((policy_label(spec), spec))
    require(bool(items), "policies", specs, "at least one policy")
    names = [name for name, _ in items]
    dupes = sorted({n for n in names if names.count(n) > 1})
    require(not dupes, "policies", dupes, "distinct names (give a {name: policy} mapping to "
            "name objects of one class apart)")
    entries = []
    for name, value in items:
        if value is not None:
            entries.append(PolicyEntry(name, value, policy_digest(value)))
            continue
        if name == "learned":  # load the model now: a missing file fails before any run
            policies.make("learned", **({"path": model} if model else {}), env_id=env_id)
            entries.append(PolicyEntry(name))
            continue
        target = policies.REGISTRY.factory(name)  # ValueError for an unknown name
        digest = policies.REGISTRY.digest(name)
        if digest is not None:  # a user's policy: one built now, so what is no policy fails here
            policies.REGISTRY.make(name)
        shipped = target if policies.REGISTRY.needs_shipping(name) else None
        entries.append(PolicyEntry(name, shipped, digest))
    require(model is None or "learned" in names, "model", model,
            "given only with policy 'learned' (no other policy reads it)")
    return entries


def check_picklable(entries: Sequence[Any], executor: str) -> None:
    """Every entry's ``shipped`` policy object (if any) pickles, as a worker process needs
    (``ValueError`` naming the policy otherwise); entries have ``name`` and ``shipped``."""
    for entry in entries:
        if entry.shipped is None:
            continue
        try:
            pickle.dumps(entry.shipped)
        except Exception as exc:
            raise ValueError(
                f"policy {entry.name!r} is invalid for executor={executor!r}: it must pickle to "
                "reach the worker processes (define its class or factory at module level, not "
                f"in a function or as a lambda; or use executor='serial'): {exc}") from exc


def _check_size(n_seeds: int, seeds: Any, runs_per_seed: int, n_levels: int,
                executor: str) -> None:
    """At most :data:`MAX_RUNS` runs (``ValueError`` naming ``seeds``), before any job is
    built."""
    limit = MAX_RUNS.get(executor, MAX_RUNS["process"])
    n_runs = n_seeds * runs_per_seed * n_levels
    if n_runs <= limit:
        return
    ray = "" if executor == "ray" else (f", or use the ray executor (--executor ray, at most "
                                        f"{MAX_RUNS['ray']} runs) on a cluster")
    require(False, "seeds", seeds,
            f"at most {limit} runs with executor {executor!r}, and {n_seeds} seeds x "
            f"{runs_per_seed} policies and baselines x {n_levels} clutter levels are {n_runs}: "
            f"split them over several benchmarks with other first seeds (--seed-start) and "
            f"outputs{ray}")


def _seed_range(seeds: int | Iterable[int], seed_start: int, runs_per_seed: int = 1,
                n_levels: int = 1, executor: str = "process") -> list[int]:
    """The seeds of the benchmark, each a world seed of the env (:data:`WORLD_SEED_LIMIT`),
    checked against :data:`MAX_RUNS` before the list is made."""
    from slam_gym.envs.hybrid_slam import WORLD_SEED_LIMIT

    if isinstance(seeds, (int, np.integer)) and not isinstance(seeds, bool):
        require(seeds >= 1, "seeds", seeds, "a number of worlds >= 1 or a list of seeds")
        _check_size(int(seeds), seeds, runs_per_seed, n_levels, executor)
        last = WORLD_SEED_LIMIT - int(seeds)
        require(isinstance(seed_start, (int, np.integer)) and not isinstance(seed_start, bool)
                and 0 <= seed_start <= last, "seed_start", seed_start,
                f"an integer in [0, {last}], so that all {int(seeds)} seeds from it are world "
                "seeds of the env (integers in [0, 2**63))")
        return list(range(int(seed_start), int(seed_start) + int(seeds)))
    if hasattr(seeds, "__len__"):  # a range or list: its size before it is copied
        _check_size(len(seeds), f"<{len(seeds)} seeds>", runs_per_seed, n_levels, executor)
    values = list(seeds)
    require(bool(values) and all(isinstance(s, (int, np.integer)) and not isinstance(s, bool)
                                 and 0 <= s < WORLD_SEED_LIMIT for s in values), "seeds",
            seeds, "a number of worlds >= 1 or a list of seeds in [0, 2**63)")
    require(len(set(values)) == len(values), "seeds", seeds, "distinct seeds")
    _check_size(len(values), f"<{len(values)} seeds>", runs_per_seed, n_levels, executor)
    return [int(s) for s in values]


def make_out_dir(out: str | os.PathLike) -> Path:
    """Create the output folder ``out``; ``ValueError`` naming it when it cannot be (a file is
    in the way, no permission, a read-only file system)."""
    path = Path(out)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write-test"
        probe.touch()
        probe.unlink()
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        if path.exists() and not path.is_dir():
            reason = "it is a file, not a directory"
        raise ValueError(f"out={str(path)!r} is invalid: cannot use it as the output directory "
                         f"({reason})") from exc
    return path


MAX_DRAWS = 1000
"""Filter draws per world a benchmark accepts."""


def env_of(env: Any = None, env_kwargs: Mapping[str, Any] | None = None,
           clutter_levels: Iterable[int] | None = None):
    """The :class:`~slam_gym.envs.spec.ResolvedEnv` of a library call's ``env`` (an id, None
    for the default, or an env already resolved) with ``env_kwargs`` and ``clutter_levels``
    (None: the env's own), interface policies deciding every decision
    (:func:`slam_gym.envs.spec.resolve_env`: where every option of the env is checked)."""
    from slam_gym.envs.spec import ResolvedEnv, resolve_env

    if isinstance(env, ResolvedEnv):
        require(not env_kwargs, "env_kwargs", env_kwargs,
                "left out when env is already resolved (resolve them together)")
        return env if clutter_levels is None else env.replace(levels=clutter_levels)
    return resolve_env(env, env_kwargs, clutter_levels=clutter_levels, per_decision=True)


def check_draws(draws: Any) -> int:
    """Filter draws per world (``ValueError`` naming ``draws``): the one check of every
    command and function that takes them."""
    require(isinstance(draws, (int, np.integer)) and not isinstance(draws, bool)
            and 1 <= draws <= MAX_DRAWS, "draws", draws, f"an integer in [1, {MAX_DRAWS}]")
    return int(draws)


def benchmark(
    policies: Any,
    *,
    env: Any = None,
    env_kwargs: Mapping[str, Any] | None = None,
    clutter_levels: Iterable[int] | None = None,
    seeds: int | Iterable[int] = 3,
    seed_start: int = 0,
    model: str | None = None,
    draws: int = 1,
    baselines: Iterable[str] = BASELINE_SYSTEMS,
    out: str | os.PathLike = "out/benchmark",
    workers: int | None = None,
    executor: str = "process",
    ray_address: str | None = None,
    figures: bool = True,
    progress: bool = False,
    retry_errors: bool = False,
    rerun_changed: bool = False,
    run_timeout_s: float | None = None,
) -> BenchmarkResult:
    """Run ``policies`` x ``clutter_levels`` x ``seeds`` in the env (and ``baselines`` on the
    same worlds), write ``results.jsonl`` (resumable: rows already in ``out`` are reused),
    ``summary.json``, ``table.md`` and, with ``figures``, the plots of ``slam-gym benchmark``.

    ``env``: a registered env id (default ``SlamGym/HybridSLAM-v1``) or a
    :class:`~slam_gym.envs.spec.ResolvedEnv`, with ``env_kwargs`` over the id's own (every run's
    env is ``gym.make(id, **kwargs)``; :func:`env_of`). ``clutter_levels``: None runs the env's
    own (a task's four, the level an id fixes, BB's four otherwise). ``seeds``: a number of
    worlds from ``seed_start``, or the seeds themselves. ``model``: the model zip of policy
    ``learned`` (None: the one shipped for the env's id, else the default). ``draws``: filter
    draws per world for every policy (each run's row carries its ``draw``; a draw is the same
    on every policy: common random numbers, issue 46). ``workers``, ``executor``
    (``"process"``, ``"ray"``, ``"serial"``) and ``ray_address`` as
    :func:`slam_gym.evaluation.run_jobs`, and so are ``retry_errors`` (run the error rows
    again), ``rerun_changed`` (replace the rows of a user policy whose code or options changed;
    without it such rows make the call refuse with ``ValueError`` naming the policy) and
    ``run_timeout_s`` (the time limit of one run; None: none).

    Every option is checked before any run (``ValueError`` naming it).
    """
    from slam_gym.evaluation.core import learned_options
    from slam_gym.evaluation.executors import run_jobs
    from slam_gym.evaluation.jobs import Job
    from slam_gym.evaluation.summary import write_summary

    spec = env_of(env, env_kwargs, clutter_levels)
    levels = list(spec.levels)
    entries = resolve_policies(policies, model, spec.env_id)
    draws = check_draws(draws)
    baselines = list(baselines)
    bad = [b for b in baselines if b not in BASELINE_SYSTEMS]
    require(not bad, "baselines", bad, f"among {list(BASELINE_SYSTEMS)}")
    require(len(set(baselines)) == len(baselines), "baselines", baselines, "distinct systems")
    if spec.scenario == "recorded":
        require(not baselines, "baselines", baselines,
                f"none for {spec.env_id} (the baselines run on simulated worlds)")
    seed_list = _seed_range(seeds, seed_start, len(entries) + len(baselines), len(levels),
                            executor)
    if executor != "serial":
        check_picklable(entries, executor)
    out = make_out_dir(out)

    jobs = []
    for entry in entries:
        opts = learned_options(model, spec.env_id) if entry.name == "learned" else {}
        if entry.digest is not None:
            opts["policy_sha256"] = entry.digest
        jobs += [Job.in_env("policy", entry.name, spec, level, seed, opts | {"draw": draw})
                 for level in levels for seed in seed_list for draw in range(draws)]
    jobs += [Job.in_env("system", name, spec, level, seed)
             for name in baselines for level in levels for seed in seed_list]
    shipped = {e.name: e.shipped for e in entries if e.shipped is not None}
    world = (levels[-1], seed_list[0])  # the world of the episode figures
    recorder = None
    if figures:
        from slam_gym.evaluation.episodes import EpisodeRecorder

        recorder = EpisodeRecorder(str(out), frozenset(  # draw 0 of each policy's world run
            j.key for j in jobs if j.kind == "policy" and (j.clutter_level, j.seed) == world
            and j.options_dict().get("draw", 0) == 0))
    run_fn = _run_function(shipped, recorder)
    run_kwargs = {"workers": workers, "executor": executor, "ray_address": ray_address,
                  "retry_errors": retry_errors, "rerun_changed": rerun_changed,
                  "run_timeout_s": run_timeout_s}
    rows = run_jobs(jobs, run_fn, out, progress=progress, **run_kwargs)
    doc = write_summary(out, rows)
    written: dict[str, str] = {}
    errors: dict[str, str] = {}
    if figures:
        summary_figures(doc, out, spec.describe(), written, errors)
        world_jobs = [j for j in jobs if j.key in recorder.keys]
        _record_missing(world_jobs, rows, jobs, out, run_fn, run_kwargs, errors)
        draw_figure("episodes", lambda: episode_figures(
            world_jobs, {j.key: r for j, r in zip(jobs, rows, strict=True)}, out,
            level=world[0], seed=world[1], written=written, errors=errors), written, errors)
    return BenchmarkResult(rows=rows, summary=doc, figures=written, out=out,
                           figure_errors=errors)


def _run_function(shipped: Mapping[str, Any], recorder: Any) -> Callable:
    """The run function of the benchmark's jobs: :func:`~slam_gym.evaluation.core.run_job`
    with the policies only this process knows and the recorder of the figure world's runs."""
    from slam_gym.evaluation.core import run_job

    kwargs = {k: v for k, v in (("policy_factories", shipped or None), ("recorder", recorder))
              if v is not None}
    return functools.partial(run_job, **kwargs) if kwargs else run_job


def draw_figure(name: str, draw: Callable[[], Any], written: dict[str, str],
                errors: dict[str, str]) -> None:
    """Draw one figure (``draw()`` returns its path, or None when it has nothing to draw):
    its path goes into ``written``; an exception is logged in one line and kept in ``errors``,
    never raised (a figure cannot undo the runs)."""
    try:
        path = draw()
    except Exception as exc:
        errors[name] = f"{type(exc).__name__}: {exc}".splitlines()[0]
        logger.warning("figure %s not written: %s", name, errors[name])
        return
    if path is not None:
        written[name] = str(path)


def summary_figures(doc: Mapping[str, Any], out: Path, system: str, written: dict[str, str],
                    errors: dict[str, str]) -> None:
    """The figures of the summary: success rates and the two Pareto figures, each left out
    with a logged line when no group has what it draws."""
    from slam_gym.evaluation.plots import plot_pareto, plot_success_rates

    groups = doc["groups"]
    if any(g.get("success_rate") is not None for g in groups):
        draw_figure("success", lambda: plot_success_rates(
            doc, out / "success_rates.png", title="Success rate per clutter level"),
            written, errors)
    else:
        logger.warning("no run finished without an error: no success rates to plot "
                       "(success_rates.png is left out)")
    if not any(g.get("map_error_m_succeeded") is not None for g in groups):
        logger.warning("no policy succeeded in any world: no map error to plot against "
                       "compute (the Pareto figures are left out)")
        return
    draw_figure("pareto", lambda: plot_pareto(
        doc, out / "pareto.png", title=f"Map error against all compute ({system})"),
        written, errors)
    draw_figure("pareto_interface", lambda: plot_pareto(
        doc, out / "pareto_interface.png", x="interface_cpu_s",
        title=f"Map error against the compute of fusions and optimisations ({system})"),
        written, errors)


def _record_missing(world_jobs: Sequence[Any], rows: Sequence[Mapping[str, Any]],
                    jobs: Sequence[Any], out: Path, run_fn: Callable,
                    run_kwargs: Mapping[str, Any], errors: dict[str, str]) -> None:
    """Runs of the figure world that finished without a recording (their rows predate
    recordings, e.g. an output folder of an earlier version) are run again to record them,
    through the same executor, error handling and time limit as the benchmark's runs, into
    ``OUT/episodes`` (resumable there too); their rows there are not the benchmark's."""
    from slam_gym.evaluation.episodes import EPISODES_DIRNAME, episode_path
    from slam_gym.evaluation.executors import run_jobs

    status = {j.key: r.get("status") for j, r in zip(jobs, rows, strict=True)}
    missing = [j for j in world_jobs
               if status.get(j.key) == "ok" and not episode_path(out, j.key).is_file()]
    if not missing:
        return
    logger.warning("%d run(s) of the figure world have no recording (rows of an earlier "
                   "version): running them again to record them", len(missing))
    try:
        run_jobs(missing, run_fn, out / EPISODES_DIRNAME, progress=False, **run_kwargs)
    except Exception as exc:  # the figures then leave those policies out, and say so
        errors["recordings"] = f"{type(exc).__name__}: {exc}".splitlines()[0]
        logger.warning("the figure world's runs were not recorded: %s", errors["recordings"])


def episode_figures(world_jobs: Sequence[Any], rows_by_key: Mapping[str, Mapping[str, Any]],
                    out: Path, *, level: int, seed: int, written: dict[str, str],
                    errors: dict[str, str]) -> None:
    """The figures of one world from its runs' recordings (:mod:`.episodes`): every policy's
    vehicle uncertainty and NEES traces, when each fused and optimised against the loop
    closure, and the map of one run (the first policy's run that did not fail, else the first
    drawn, its failure in the title). A policy whose run there is an error row, or has no
    readable recording, is left out with a note in each figure."""
    from slam_gym.evaluation.episodes import episode_path, read_episode, timeline_of
    from slam_gym.evaluation.plots import plot_nees, plot_recorded_map, plot_uncertainty_traces
    from slam_gym.evaluation.timeline import plot_decision_timelines

    recordings: dict[str, dict[str, Any]] = {}
    notes: list[str] = []
    for job in world_jobs:
        row = rows_by_key.get(job.key) or {}
        path = episode_path(out, job.key)
        if row.get("status") != "ok":
            notes.append(f"{job.name}: its run here is an error row")
        elif not path.is_file():
            notes.append(f"{job.name}: its run here was not recorded")
        else:
            try:
                recordings[job.name] = read_episode(path)
            except ValueError as exc:
                logger.warning("%s", exc)
                notes.append(f"{job.name}: its recording cannot be read")
    where = f"clutter level {level}, seed {seed}"
    if not recordings:
        logger.warning("no policy's run on %s finished with a recording: the uncertainty, "
                       "NEES, decision and map figures are left out", where)
        return
    dt = next(iter(recordings.values()))["dt_s"]
    draw_figure("uncertainty", lambda: plot_uncertainty_traces(
        {n: r["cov_trace"] for n, r in recordings.items()}, out / "uncertainty_traces.png",
        dt_s=dt, title=f"Vehicle uncertainty, {where}", notes=notes), written, errors)
    draw_figure("nees", lambda: plot_nees(
        {n: r["nees"] for n, r in recordings.items()}, out / "nees.png", dt_s=dt,
        title=f"Vehicle NEES, {where}", notes=notes), written, errors)
    draw_figure("decisions", lambda: plot_decision_timelines(
        {n: timeline_of(r) for n, r in recordings.items()}, out / "decisions.png",
        title=f"Fusions and optimisations, {where}", notes=notes), written, errors)
    name = next((n for n, r in recordings.items() if not r["failed"]), next(iter(recordings)))
    draw_figure("map", lambda: plot_recorded_map(
        recordings[name], out / "map.png", f"{name}, {where}"), written, errors)
