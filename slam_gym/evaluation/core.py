"""The evaluation core: run one (system or policy, scenario, clutter level, seed).

:func:`run_job` is the single run function behind ``slam-gym benchmark``, every ``slam-gym
reproduce`` and the training callback. It builds the stream, the system (or the env and the
policy), plays the whole path through :class:`~slam_gym.episode.Episode`, and returns the metrics
of docs/ARCHITECTURE.md, "Evaluation metrics".

System jobs (BB Table 1, CM) take options:
``n_particles`` (500), ``fusion_interval_s`` (10, BB's rule; sub-map systems only),
``optimise`` (``"never"``, ``"at-end"``: once after the last fusion, ``"every-fusion"``, or
``"after-loop-closure"``: once, right after the first fusion that matches a global feature no
fusion had touched for 60 s),
``back_end`` (``"ekf"``/``"relative"``), ``known_association`` (False; forced on for the ESDFs),
``stop_on_failure`` (True: stop at BB's failure, the outcome is known), ``n_steps`` (cut the path),
``existence_model`` (``"gate"``/``"bb"``: the reading of BB (11), :mod:`filters.existence`),
``path_perturbation_m`` (None: the scenario's; else the waypoint jitter of the world's path, a
scenario field, so the world of the job changes with it: issue 28's calibration).
Policy jobs run in their env (``job.env``, :class:`~slam_gym.envs.spec.ResolvedEnv`: built by
``gym.make(id, **kwargs)``; the world ``seed`` at the job's clutter level and the filter's
``draw`` are ``reset`` options) and take only the policy's own options: ``model_path``,
``model_sha256`` (the model file's :func:`policies.learned.model_digest`: a run checks it, so a
job key names the model it was run with; without ``model_path`` the model is the one shipped for
the job's env id, :func:`policies.learned.resolve_model_path`) and ``deterministic`` (for
``learned``),
``policy_sha256`` (a user policy's :func:`policies.registry.policy_digest`, checked likewise)
and ``draw`` (0: which draw of the filter's random numbers on the world). Every option of the env
(particles, back-end, the price of compute, ...) is in its keyword arguments, never a job option.
The env ends an episode at BB's failure. A learned policy's rows carry ``model_matches_code`` and
``model_differences`` (:func:`provenance_fields`: whether the model's fingerprint matches the code
that ran it).
"""

from __future__ import annotations

import time

import numpy as np

from filters.validation import require
from slam_gym.compute_cost import summarise_records
from slam_gym.episode import Episode

SYSTEM_OPTIONS = {
    "n_particles": 500,
    "fusion_interval_s": 10.0,
    "optimise": "never",
    "back_end": "ekf",
    "known_association": False,
    "stop_on_failure": True,
    "n_steps": None,
    "existence_model": "gate",
    "path_perturbation_m": None,
}
POLICY_OPTIONS = {
    "model_path": None,
    "model_sha256": None,
    "deterministic": None,
    "policy_sha256": None,
    "draw": 0,
}
"""A policy job's own options (the env's are in ``job.env``)."""
OPTIMISE_MODES = ("never", "at-end", "every-fusion", "after-loop-closure")
LOOP_CLOSURE_UNSEEN_S = 60.0
"""A fusion closes a loop when it matches a global feature no fusion has touched for this long."""


def _options(given: dict, defaults: dict, what: str) -> dict:
    unknown = sorted(set(given) - set(defaults))
    require(not unknown, f"{what} options", unknown, f"among {sorted(defaults)}"
            + (" (an env's options are keyword arguments of the job's env)"
               if what == "policy" else ""))
    return defaults | given


def filter_rng(seed: int):
    """The filter's generator for a job's seed, independent of the world's (the world uses the
    seed itself); every run of a system on a job's world draws from it (scripts too)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), 7919]))


def make_job_stream(scenario: str, clutter_level, seed: int, n_steps=None, **scenario_overrides):
    """The world of a job: scenario ``scenario`` at ``clutter_level`` for ``seed``, with the path
    cut to ``n_steps`` and any other scenario fields overridden by name (validated)."""
    from slam_gym.world import make_stream

    overrides = {k: v for k, v in scenario_overrides.items() if v is not None}
    if clutter_level is not None:
        overrides["clutter_level"] = clutter_level
    if n_steps is not None:
        overrides["n_steps"] = int(n_steps)
    return make_stream(scenario, seed=seed, **overrides)


def run_system(
    name: str,
    stream,
    seed: int,
    *,
    n_particles=500,
    fusion_interval_s=10.0,
    optimise="never",
    back_end="ekf",
    known_association=False,
    stop_on_failure=True,
    record_trace=False,
    system_options=None,
    existence_model="gate",
) -> Episode:
    """Run system ``name`` over ``stream`` on BB's fixed fusion schedule; the finished episode.

    ``system_options``: keyword options of the estimator (:func:`slam_gym.systems.make_system`;
    ``front_``-prefixed for sub-map systems)."""
    from slam_gym.systems import KNOWN_ASSOCIATION_ONLY, SUBMAP_SYSTEMS, make_system

    require(optimise in OPTIMISE_MODES, "optimise", optimise, f"one of {OPTIMISE_MODES}")
    system_options = dict(system_options or {})
    if existence_model != "gate":  # the filters' default; only systems with existence take it
        from filters.existence import validate_existence_model

        validate_existence_model(existence_model)
        key = "front_existence_model" if name in SUBMAP_SYSTEMS else "existence_model"
        if name in SUBMAP_SYSTEMS or name in ("fastslam", "ekf-slam"):
            system_options[key] = existence_model
    system = make_system(name, stream, filter_rng(seed), n_particles=n_particles, back_end=back_end,
                         **system_options)
    known = bool(known_association) or name in KNOWN_ASSOCIATION_ONLY
    episode = Episode(system, stream, known_association=known, record_trace=record_trace)
    submap = name in SUBMAP_SYSTEMS
    # without sub-maps, advance in 1 s chunks so that a failure stops the run promptly
    every = int(round((fusion_interval_s if submap else 1.0) / stream.dt_s))
    last_fused_s: dict[int, float] = {}
    loop_closed = False
    while not episode.done:
        episode.advance(max(1, every))
        if stop_on_failure and episode.failure.failed:
            break
        if submap:
            report = episode.fuse()
            if optimise == "every-fusion":
                episode.optimise()
            elif optimise == "after-loop-closure" and not loop_closed:
                matched = {g for loc, g in report.id_map.items() if loc != g}
                loop_closed = any(
                    episode.t_s - last_fused_s.get(g, episode.t_s) > LOOP_CLOSURE_UNSEEN_S
                    for g in matched
                )
                if loop_closed:
                    episode.optimise()
            last_fused_s.update(dict.fromkeys(report.id_map.values(), episode.t_s))
    if submap and optimise == "at-end":
        episode.optimise()
    return episode


def run_policy(
    policy_name: str,
    env,
    clutter_level,
    seed: int,
    *,
    model_path=None,
    model_sha256=None,
    deterministic=None,
    factories=None,
    **run_options,
):
    """Run the named interface policy in ``env`` (a :class:`~slam_gym.envs.spec.ResolvedEnv`
    or a registered id) for one episode; (episode, env).

    ``model_path``, ``model_sha256`` and ``deterministic`` are options of ``learned``,
    ``factories`` the policies only this process knows (:func:`make_policy`), ``run_options``
    those of :func:`run_policy_object` (``draw``, ``on_step``)."""
    env_id = env if isinstance(env, str) else getattr(env, "env_id", None)
    policy = make_policy(policy_name, model_path=model_path, model_sha256=model_sha256,
                         deterministic=deterministic, factories=factories, env_id=env_id)
    return run_policy_object(policy, env, clutter_level, seed, policy_name=policy_name,
                             **run_options)


def learned_options(model_path: str | None = None, env_id: str | None = None) -> dict:
    """The job options of policy ``learned`` in env ``env_id``: its model file (None: the model
    shipped for ``env_id``, else the packaged default; not named, so keys do not depend on where
    the package is installed) and the digest of the model that resolves to, so that a resumed
    run never reuses the rows of another model: one saved at the same path (e.g. the shipped
    default before it was retrained), or one shipped for another env. An env with no model of
    its own is warned about here, once (:func:`policies.learned.resolve_model_path`); the
    workers running the jobs resolve the same model quietly."""
    from policies.learned import model_digest, resolve_model_path

    resolve_model_path(model_path, env_id)  # the fallback's one WARNING, in the job's maker
    return ({"model_path": model_path} if model_path else {}) | {
        "model_sha256": model_digest(model_path, env_id)}


def make_policy(name: str, *, model_path=None, model_sha256=None, deterministic=None,
                factories=None, env_id=None):
    """The policy object a job names. For ``learned``: the model at ``model_path`` (None: the
    one shipped for the job's ``env_id``, else the packaged default:
    :func:`policies.learned.resolve_model_path`, resolved without its fallback warning, which
    the process that made the job gave), checked against the job's ``model_sha256`` (None: not
    checked; another digest is a ``ValueError``), acting by ``deterministic`` (None: the model's
    default). The other policies take none of these. ``factories`` (name -> factory or policy
    object) holds the policies a worker process cannot resolve by name (objects and names
    registered at run time in the process that made the jobs); other names go to
    :func:`policies.make` (the project's names, plug-ins' entry points,
    ``package.module:attribute`` references)."""
    import policies
    from policies.registry import build

    if factories and name in factories:
        return build(factories[name], name, {})
    if name != "learned":
        return policies.make(name)
    from policies.learned import check_model_digest, resolve_model_path

    check_model_digest(model_path, model_sha256, env_id)
    path = resolve_model_path(model_path, env_id, warn=False)
    kwargs = {k: v for k, v in (("path", str(path)), ("deterministic", deterministic),
                                ("env_id", env_id)) if v is not None}
    return policies.make("learned", **kwargs)


def check_policy_digest(name: str, digest: str | None, factories=None) -> None:
    """A job keyed by a user policy's digest (``policy_sha256``) runs only that code: a policy
    this process resolves by name (a reference, a plug-in) whose source now has another digest
    (its module was edited while the benchmark ran) is a ``ValueError`` naming it. Policies
    that travel with the job (``factories``) are the objects the digest was taken of."""
    if digest is None or (factories and name in factories):
        return
    import policies

    now = policies.REGISTRY.digest(name)
    require(now == digest, f"policy {name!r}", f"source digest {now}",
            f"the digest the job was made with ({digest}): its code changed while the "
            "benchmark ran")


def provenance_fields(policy) -> dict:
    """The row fields of a policy that records its provenance (a learned model:
    :attr:`policies.learned.LearnedPolicy.provenance`): ``model_matches_code`` (True, False, or
    None when not checked) and ``model_differences`` (what differs, named); {} for the others."""
    provenance = getattr(policy, "provenance", None)
    if not isinstance(provenance, dict):
        return {}
    return {"model_matches_code": provenance.get("matches"),
            "model_differences": list(provenance.get("differences") or [])}


def run_policy_object(
    policy,
    env,
    clutter_level,
    seed: int,
    *,
    on_step=None,
    policy_name=None,
    draw=0,
):
    """Run a policy object (``act(obs, info)``, ``reset()``) for one episode; (episode, env),
    the env unwrapped.

    ``env`` is a :class:`~slam_gym.envs.spec.ResolvedEnv` or a registered id (with its own
    options), built with ``gym.make``. The world is the env's world for ``seed`` at
    ``clutter_level`` (None: the env's own level, e.g. a recording's), the same as a system run
    with that seed; the episode ends at the end of the path or at BB's failure. ``draw`` chooses
    the draw of the filter's random numbers on that world (``reset``'s option).
    ``on_step(action, info)``, if given, sees every decision and the info that followed it. Every
    action is checked (:func:`policies.base.check_action`): a wrong shape, dtype or value raises
    ``ValueError`` naming the policy (``policy_name``, else the object's name) and what it
    returned.
    """
    from policies.base import check_action
    from policies.registry import policy_label
    from slam_gym.envs.spec import ResolvedEnv, resolve_env

    label = policy_name or policy_label(policy)
    spec = env if isinstance(env, ResolvedEnv) else resolve_env(env)
    gym_env = spec.make()
    inner = gym_env.unwrapped
    if callable(getattr(policy, "bind_env", None)):  # a planning policy acts on copies of env
        policy.bind_env(inner)
    policy.reset()
    options = {"world_seed": int(seed), "draw": int(draw)}
    if clutter_level is not None:
        options["clutter_level"] = int(clutter_level)
    obs, info = gym_env.reset(seed=int(seed), options=options)
    while True:
        action = check_action(policy.act(obs, info), label)
        obs, _, terminated, truncated, info = gym_env.step(action)
        if on_step is not None:
            on_step(action, info)
        if terminated or truncated:
            return inner.episode, inner


def play_decisions(env, policy, obs, info, n_decisions: int, *, seed: int = 0) -> int:
    """Play ``policy`` in ``env`` for ``n_decisions`` decisions from ``(obs, info)``, the start of
    world ``seed`` (``env.reset(seed=seed)`` and ``policy.reset()`` done by the caller, so a timer
    can start after them); at the end of an episode, go on with both reset on world ``seed + 1``,
    and so on. Returns the number of worlds played in. A fixed amount of work whatever the
    path's length, for speed measurements (``scripts/performance/env_cpu.py``,
    ``env_breakdown.py``)."""
    world = seed
    for _ in range(n_decisions):
        obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
        if terminated or truncated:
            world += 1
            policy.reset()
            obs, info = env.reset(seed=world)
    return world - seed + 1
def episode_result(episode: Episode, stream) -> dict:
    metrics = episode.metrics()
    metrics["alpha"] = stream.clutter.alpha
    metrics["beta"] = stream.clutter.beta
    return metrics


def run_job(job, policy_factories=None, recorder=None) -> dict:
    """The run function of the evaluation machinery (picklable, module level).

    ``policy_factories`` (policy name -> factory or policy object) names the policies a worker
    cannot resolve by name; pass it with ``functools.partial(run_job, policy_factories=...)``,
    which pickles when the factories do (module-level classes and functions, picklable objects).
    ``recorder`` (e.g. :class:`slam_gym.evaluation.episodes.EpisodeRecorder`): its
    ``start(job)`` returns None or a recording whose ``on_step`` sees every decision of a policy
    run and whose ``finish(episode, env)`` keeps what the figures draw (the benchmark's figures
    are drawn from the runs themselves, never from a replay).
    """
    if job.kind == "system":
        opts = _options(job.options_dict(), SYSTEM_OPTIONS, "system")
        world = {}
        if job.env is not None:  # a baseline on an env's worlds: its scenario and path cut
            world = dict(job.env.get("scenario_overrides") or [])
            if opts["n_steps"] is None:
                opts["n_steps"] = job.env.get("n_steps")
        stream = make_job_stream(job.scenario, job.clutter_level, job.seed, opts.pop("n_steps"),
                                 path_perturbation_m=opts.pop("path_perturbation_m"), **world)
        cpu_start = time.process_time()
        episode = run_system(job.name, stream, job.seed, **opts)
        row = episode_result(episode, stream)
        row["total_cpu_s"] = time.process_time() - cpu_start
        return row
    opts = _options(job.options_dict(), POLICY_OPTIONS, "policy")
    require(job.env is not None, "job", job.key, "a policy job with its env (Job.in_env)")
    check_policy_digest(job.name, opts.pop("policy_sha256"), policy_factories)
    policy = make_policy(job.name, model_path=opts.pop("model_path"),
                         model_sha256=opts.pop("model_sha256"),
                         deterministic=opts.pop("deterministic"), factories=policy_factories,
                         env_id=job.env.env_id)
    recording = recorder.start(job) if recorder is not None else None
    episode, env = run_policy_object(policy, job.env, job.clutter_level, job.seed,
                                     policy_name=job.name, draw=opts["draw"],
                                     on_step=None if recording is None else recording.on_step)
    if recording is not None:
        recording.finish(episode, env)
    row = episode_result(episode, env.stream)
    row["draw"] = int(opts["draw"])
    row.update(provenance_fields(policy))
    if callable(getattr(policy, "episode_fields", None)):  # e.g. a lookahead's planning cost
        row.update(policy.episode_fields())
    row["return"] = env.episode_return
    row["compute_term_s"] = env.episode_compute_term_s
    row["w_compute"] = env.config.w_compute
    row.update(summarise_records(env.compute_records, env.compute_model))
    return row
