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
"""

from __future__ import annotations

import functools
import logging
import os
import pickle
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from filters.validation import require

logger = logging.getLogger(__name__)

BASELINE_SYSTEMS = ("dead-reckoning",)
"""Systems that can run beside the policies on the same worlds (``baselines``)."""


@dataclass(frozen=True)
class BenchmarkResult:
    """What :func:`benchmark` returns: the ``results.jsonl`` rows of its jobs (in job order),
    the ``summary.json`` document, the figures written (name -> path) and the output folder."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    figures: dict[str, str]
    out: Path


@dataclass(frozen=True)
class PolicyEntry:
    """A policy of the benchmark: its name in the results and, when a worker process cannot
    build it from the name, the factory or object that travels with the jobs."""

    name: str
    shipped: Any = None
    digest: str | None = None
    """:func:`policies.registry.policy_digest` of a user's policy (None: the project's)."""


def resolve_policies(specs: Any, model: str | None = None) -> list[PolicyEntry]:
    """Check and name the ``policies`` argument of :func:`benchmark` (``ValueError`` naming the
    entry at fault). Names and references are resolved here, so a typo fails before any run."""
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
            policies.make("learned", **({"path": model} if model else {}))
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


def _check_picklable(entries: Sequence[PolicyEntry], executor: str) -> None:
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


def _seed_range(seeds: int | Iterable[int], seed_start: int) -> list[int]:
    if isinstance(seeds, (int, np.integer)) and not isinstance(seeds, bool):
        require(seeds >= 1, "seeds", seeds, "a number of worlds >= 1 or a list of seeds")
        return list(range(seed_start, seed_start + int(seeds)))
    values = list(seeds)
    require(bool(values) and all(isinstance(s, int) and s >= 0 for s in values), "seeds",
            seeds, "a number of worlds >= 1 or a list of seeds >= 0")
    return values


def _check_env_options(scenario: str, levels: Sequence[int], **options: Any) -> None:
    """The env's own validation of every option, at every level, before any run."""
    from slam_gym.envs.hybrid_slam import HybridSLAMConfig

    given = {k: v for k, v in options.items() if v is not None}
    for level in levels:
        HybridSLAMConfig.from_kwargs(scenario=scenario, clutter_level=level, **given)


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


def env_id_streams(env: str) -> str:
    """The ``random_streams`` of a registered simulated env id (``-v1``: synchronised)."""
    from slam_gym.envs import ENV_VARIANTS

    require(env in ENV_VARIANTS, "env", env, f"one of {sorted(ENV_VARIANTS)}")
    return ENV_VARIANTS[env].get("random_streams", "synchronised")


def env_id_ends(env: str) -> tuple[str, str]:
    """The (front-end, back-end) of a registered simulated env id."""
    from slam_gym.envs import ENV_VARIANTS

    require(env in ENV_VARIANTS, "env", env, f"one of {sorted(ENV_VARIANTS)}")
    kwargs = ENV_VARIANTS[env]
    return kwargs.get("front_end", "fastslam"), kwargs.get("back_end", "ekf")


def benchmark(
    policies: Any,
    *,
    clutter_levels: Iterable[int] = (0, 1, 2, 3),
    seeds: int | Iterable[int] = 3,
    seed_start: int = 0,
    scenario: str = "brooks-bailey",
    env: str | None = None,
    n_particles: int = 500,
    decision_interval: int = 10,
    front_end: str | None = None,
    back_end: str | None = None,
    n_steps: int | None = None,
    w_compute: float | None = None,
    compute_clip_s: float | None = None,
    model: str | None = None,
    draws: int = 1,
    random_streams: str | None = None,
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

    ``seeds``: a number of worlds from ``seed_start``, or the seeds themselves. ``env``: a
    registered simulated env id whose front-end and back-end to use (else ``front_end``,
    default ``"fastslam"``, and ``back_end``, default ``"ekf"``). ``n_steps`` cuts the path
    (quick looks and tests); ``w_compute`` and ``compute_clip_s`` (None: the env's defaults) set
    the reward's price of compute, so a policy's return is scored under the reward it was
    trained for. ``model``: the model zip of policy ``learned`` (None: the shipped
    one). ``draws``: filter draws per world for every policy (each run's row carries its
    ``draw``; a draw is the same on every policy: common random numbers, issue 46).
    ``random_streams``: ``"synchronised"`` (``-v1``, the default) or ``"ordered"`` (``-v0``;
    else ``env``'s). ``workers``, ``executor`` (``"process"``, ``"ray"``, ``"serial"``) and
    ``ray_address`` as :func:`slam_gym.evaluation.run_jobs`, and so are ``retry_errors`` (run
    the error rows again), ``rerun_changed`` (replace the rows of a user policy whose code or
    options changed; without it such rows make the call refuse with ``ValueError`` naming the
    policy) and ``run_timeout_s`` (the time limit of one run; None: none).

    Every option is checked before any run (``ValueError`` naming it): the env's options
    through :class:`~slam_gym.envs.hybrid_slam.HybridSLAMConfig` at every clutter level.
    """
    from slam_gym.evaluation.core import learned_options, run_job
    from slam_gym.evaluation.executors import run_jobs
    from slam_gym.evaluation.jobs import Job
    from slam_gym.evaluation.plots import plot_pareto, plot_success_rates
    from slam_gym.evaluation.summary import write_summary

    entries = resolve_policies(policies, model)
    if env is not None:
        env_front, env_back = env_id_ends(env)
        for field, given, implied in (("front_end", front_end, env_front),
                                      ("back_end", back_end, env_back)):
            require(given in (None, implied), field, given, f"{implied!r} for env={env!r} "
                    "(or left out)")
        front_end, back_end = env_front, env_back
        implied = env_id_streams(env)
        require(random_streams in (None, implied), "random_streams", random_streams,
                f"{implied!r} for env={env!r} (or left out)")
        random_streams = implied
    front_end, back_end = front_end or "fastslam", back_end or "ekf"
    random_streams = random_streams or "synchronised"
    require(isinstance(draws, (int, np.integer)) and not isinstance(draws, bool)
            and 1 <= draws <= MAX_DRAWS, "draws", draws, f"an integer in [1, {MAX_DRAWS}]")
    baselines = list(baselines)
    bad = [b for b in baselines if b not in BASELINE_SYSTEMS]
    require(not bad, "baselines", bad, f"among {list(BASELINE_SYSTEMS)}")
    levels = [int(level) for level in clutter_levels]
    require(bool(levels), "clutter_levels", levels, "at least one level")
    seed_list = _seed_range(seeds, seed_start)
    _check_env_options(scenario, levels, n_particles=n_particles,
                       decision_interval=decision_interval, front_end=front_end,
                       back_end=back_end, n_steps=n_steps, w_compute=w_compute,
                       compute_clip_s=compute_clip_s, random_streams=random_streams)
    if executor != "serial":
        _check_picklable(entries, executor)
    out = make_out_dir(out)

    options: dict[str, Any] = {"n_particles": n_particles, "decision_interval": decision_interval,
                               "front_end": front_end, "back_end": back_end,
                               "random_streams": random_streams}
    for key, value in (("n_steps", n_steps), ("w_compute", w_compute),
                       ("compute_clip_s", compute_clip_s)):
        if value is not None:
            options[key] = value
    jobs = []
    for entry in entries:
        opts = options | (learned_options(model) if entry.name == "learned" else {})
        if entry.digest is not None:
            opts["policy_sha256"] = entry.digest
        jobs += [Job("policy", entry.name, scenario, level, seed, opts | {"draw": draw})
                 for level in levels for seed in seed_list for draw in range(draws)]
    system_opts = {"n_steps": int(n_steps)} if n_steps is not None else {}
    jobs += [Job("system", name, scenario, level, seed, system_opts)
             for name in baselines for level in levels for seed in seed_list]
    shipped = {e.name: e.shipped for e in entries if e.shipped is not None}
    run_fn = functools.partial(run_job, policy_factories=shipped) if shipped else run_job
    rows = run_jobs(jobs, run_fn, out, workers=workers, executor=executor,
                    ray_address=ray_address, progress=progress, retry_errors=retry_errors,
                    rerun_changed=rerun_changed, run_timeout_s=run_timeout_s)
    doc = write_summary(out, rows)
    written: dict[str, str] = {}
    if figures:
        written["success"] = str(plot_success_rates(doc, out / "success_rates.png",
                                                    title="Success rate per clutter level"))
        env_name = env or f"{front_end} front-end, {back_end} back-end"
        if any(g.get("map_error_m_succeeded") is not None for g in doc["groups"]):
            written["pareto"] = str(plot_pareto(
                doc, out / "pareto.png",
                title=f"Map error against all compute ({env_name}, {n_particles} particles)",
            ))
            written["pareto_interface"] = str(plot_pareto(
                doc, out / "pareto_interface.png", x="interface_cpu_s",
                title=f"Map error against the compute of fusions and optimisations "
                f"({env_name}, {n_particles} particles)",
            ))
        else:
            logger.warning("no policy succeeded in any world: no map error to plot against "
                           "compute (the Pareto figures are left out)")
        written.update(episode_figures(
            entries, scenario=scenario, level=levels[-1], seed=seed_list[0], out=out,
            model=model, n_particles=n_particles, decision_interval=decision_interval,
            front_end=front_end, back_end=back_end, n_steps=n_steps, w_compute=w_compute,
            compute_clip_s=compute_clip_s))
    return BenchmarkResult(rows=rows, summary=doc, figures=written, out=out)


def episode_figures(entries: Sequence[PolicyEntry], *, scenario: str, level: int, seed: int,
                    out: Path, model: str | None, **env_options: Any) -> dict[str, str]:
    """Uncertainty and NEES traces of every policy on one world, that world's map (of the first
    policy), and when each policy fused and optimised against the loop closure."""
    from slam_gym.evaluation.core import make_policy
    from slam_gym.evaluation.plots import plot_episode_map, plot_nees, plot_uncertainty_traces
    from slam_gym.evaluation.timeline import decision_timeline, plot_decision_timelines

    shipped = {e.name: e.shipped for e in entries if e.shipped is not None}
    traces, nees, runs, timelines = {}, {}, [], {}
    for entry in entries:
        policy = make_policy(entry.name, model_path=model, factories=shipped)
        timeline, episode, env = decision_timeline(policy, scenario, level, seed,
                                                   policy_name=entry.name, **env_options)
        traces[entry.name] = np.array(episode.trace.cov_trace)
        nees[entry.name] = np.array(episode.trace.nees)
        timelines[entry.name] = timeline
        runs.append((entry.name, episode, env))
    dt = runs[0][2].stream.dt_s
    where = f"clutter level {level}, seed {seed}"
    figures = {
        "uncertainty": str(plot_uncertainty_traces(
            traces, out / "uncertainty_traces.png", dt_s=dt,
            title=f"Vehicle uncertainty, {where}")),
        "nees": str(plot_nees(nees, out / "nees.png", dt_s=dt, title=f"Vehicle NEES, {where}")),
        "decisions": str(plot_decision_timelines(
            timelines, out / "decisions.png", title=f"Fusions and optimisations, {where}")),
    }
    name, episode, _ = runs[0]
    figures["map"] = plot_episode_map(episode, out / "map.png", f"{name}, {where}")
    return figures
