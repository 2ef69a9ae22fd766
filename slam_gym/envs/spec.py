"""The env a run is made in: a registered id and its keyword arguments, resolved once (issue 55).

Every command and library function that runs episodes names its env the way Gymnasium's registry
does: an id (``gym.spec(id)``) and keyword arguments over the id's own (``EnvSpec.kwargs``; the
``--env-kwargs KEY:VALUE`` of rl-zoo3). :func:`resolve_env` is the one place where they are
checked and merged:

* an unknown id is a one-line ``ValueError`` naming the closest registered ids;
* the id's registered keyword arguments come first (a task's are its class's ``DEFAULTS``,
  :mod:`slam_gym.envs.tasks`), then ``env_kwargs``, then the commands' shorthands
  (``--particles``, ``--scenario``, ...), which are keyword arguments under other names;
* a given option that contradicts one the id sets overrides it, and says so in one logged line
  (``WARNING``, so the command line prints it); a shorthand and ``env_kwargs`` that disagree are
  refused; nothing is dropped;
* the result, :class:`ResolvedEnv`, holds every option of the env (the class's
  :meth:`~slam_gym.envs.hybrid_slam.HybridSLAMEnv.resolved_kwargs`: the id's and the given ones
  over the defaults), validated by the env's own config (``ValueError`` naming the option).

A worker builds the env with :meth:`ResolvedEnv.make`, that is ``gym.make(id, **kwargs)``: the
run's env is the one ``gym.make(id)`` gives, but for the options given. The world (seed and
clutter level) and the filter's draw are ``reset`` options, so they are not part of it. Rows and
resume keys hold the id and the resolved keyword arguments (:mod:`slam_gym.evaluation.jobs`).

The clutter levels a command runs by default are the env's own (:attr:`ResolvedEnv.levels`):
the level an id fixes (``-Clutter2-v1``), the levels a task draws from (0-3), none for a
recording, and BB's four otherwise (BB's Table 1 over the plain ids, whose ``gym.make`` default
level is 2).
"""

from __future__ import annotations

import difflib
import json
import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from filters.validation import require

logger = logging.getLogger(__name__)

DEFAULT_ENV_ID = "SlamGym/HybridSLAM-v1"
"""The env of every command that is given none: BB's world and configuration, ``-v1`` draws."""

NAMESPACE = "SlamGym/"

ALL_LEVELS: tuple[int, ...] = (0, 1, 2, 3)
"""BB's clutter levels (Table 1): what a command runs on an id that does not fix its level."""


def registered_ids() -> list[str]:
    """Every registered id of this package, sorted."""
    import gymnasium as gym

    from slam_gym.envs import register_envs

    register_envs()
    return sorted(i for i in gym.registry if i.startswith(NAMESPACE))


def check_env_id(env_id: Any, field_name: str = "env") -> str:
    """``env_id`` when it is a registered id of this package; else a one-line ``ValueError``
    naming ``field_name`` and the closest registered ids."""
    ids = registered_ids()
    if isinstance(env_id, str) and env_id in ids:
        return env_id
    close = difflib.get_close_matches(str(env_id), ids, n=3, cutoff=0.5)
    hint = (f"did you mean {' or '.join(close)}?" if close
            else f"one of the {len(ids)} ids starting {NAMESPACE}HybridSLAM, "
            f"{NAMESPACE}EKFSubmap or {NAMESPACE}MRCLAM (python -c \"from slam_gym.envs.spec "
            "import registered_ids; print(registered_ids())\" lists them)")
    raise ValueError(f"{field_name}={env_id!r} is invalid: not a registered env id; {hint}")


def system_id(env_id: str) -> str:
    """The id of the system ``env_id`` runs: itself, or the one a wrapped id wraps (the
    interval env's actions are a schedule of the per-decision env's)."""
    from slam_gym.envs import WRAPPED_SYSTEM_IDS

    return WRAPPED_SYSTEM_IDS.get(env_id, env_id)


def env_class(env_id: str) -> type:
    """The env class of a registered id (a wrapped id: the class of the system it wraps)."""
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    creator = load_env_creator(gym.spec(system_id(env_id)).entry_point)
    require(isinstance(creator, type), "env", env_id, "an id whose entry point is a class")
    return creator


def registered_kwargs(env_id: str) -> dict[str, Any]:
    """The keyword arguments ``env_id`` is registered with (``gym.spec(id).kwargs``)."""
    import gymnasium as gym

    return dict(gym.spec(check_env_id(env_id)).kwargs)


def _plain(value: Any) -> Any:
    """A value as JSON holds it (tuples as lists), to compare a given option with the id's."""
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


@dataclass(frozen=True)
class ResolvedEnv:
    """An env id and every keyword argument of its env, resolved (:func:`resolve_env`).

    Frozen and hashable (the arguments are held as canonical JSON), so it travels in a
    :class:`~slam_gym.evaluation.jobs.Job` to worker processes and keys its rows. ``levels``
    are the clutter levels a command runs by default (module docstring); they are not part of
    the env, so equality ignores them."""

    env_id: str
    kwargs_json: str
    levels: tuple = field(default=(), compare=False)

    @classmethod
    def of(cls, env_id: str, kwargs: Mapping[str, Any], levels: Iterable = ()) -> ResolvedEnv:
        """From an id and already-resolved keyword arguments (a row's), without resolving."""
        text = json.dumps(dict(kwargs), sort_keys=True, separators=(",", ":"))  # tuples: lists
        return cls(env_id, text, tuple(levels))

    @property
    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of ``gym.make`` (a fresh dict)."""
        return json.loads(self.kwargs_json)

    @property
    def scenario(self) -> str:
        """The simulated scenario, or ``"recorded"`` for an env on recorded data."""
        return self.kwargs.get("scenario", "recorded")

    def get(self, name: str, default: Any = None) -> Any:
        return self.kwargs.get(name, default)

    def make(self, **make_kwargs: Any):
        """``gym.make(id, **kwargs)``, with the time limit of these options (the registered one
        is computed from the id's own; a shorter ``decision_interval`` needs more decisions)."""
        import gymnasium as gym

        from slam_gym.envs import RECORDED_MAX_EPISODE_STEPS, max_episode_steps

        kwargs = self.kwargs
        if "scenario" in kwargs:
            limit = max_episode_steps(kwargs)
        else:
            limit = RECORDED_MAX_EPISODE_STEPS
        make_kwargs.setdefault("max_episode_steps", limit)
        return gym.make(self.env_id, **kwargs, **make_kwargs)

    def replace(self, *, levels: Iterable[int] | None = None, **changes: Any) -> ResolvedEnv:
        """This env with some options changed (``changes``, checked by the env's class) and/or
        other ``levels``, in silence: the options were resolved, and any override said, once."""
        from slam_gym.scenarios import CLUTTER_LEVELS

        kwargs = self.kwargs | changes
        resolved = env_class(self.env_id).resolved_kwargs(**kwargs) if changes else kwargs
        if levels is None:
            levels = self.levels
        else:
            levels = tuple(int(v) for v in levels)
            require(bool(levels) and len(set(levels)) == len(levels)
                    and all(v in CLUTTER_LEVELS for v in levels) and "scenario" in resolved,
                    "clutter_levels", list(levels), "distinct levels 0-3 of a simulated env")
        return ResolvedEnv.of(self.env_id, resolved, levels)

    def describe(self) -> str:
        """One line: the id and the options that differ from the id's own."""
        own = env_class(self.env_id).resolved_kwargs(**registered_kwargs(self.env_id))
        changed = {k: v for k, v in self.kwargs.items() if own.get(k) != v}
        if not changed:
            return self.env_id
        return f"{self.env_id} ({', '.join(f'{k}={v}' for k, v in sorted(changed.items()))})"


def _levels_of(given: Mapping[str, Any], resolved: Mapping[str, Any]) -> tuple:
    """The clutter levels an env with these options stands for (module docstring): ``given``
    the id's and the user's options, ``resolved`` all of them."""
    if "scenario" not in resolved or resolved.get("clutter_level") is None:
        return (None,)  # a recording, or a custom sensor (alpha and beta)
    if "clutter_level" in given:
        level = resolved["clutter_level"]
        return tuple(level) if isinstance(level, list) else (int(level),)
    return ALL_LEVELS


def resolve_env(
    env_id: str | None = None,
    env_kwargs: Mapping[str, Any] | None = None,
    *,
    shorthands: Mapping[str, Any] | None = None,
    clutter_levels: Iterable[int] | None = None,
    per_decision: bool = False,
) -> ResolvedEnv:
    """The env of ``env_id`` (default :data:`DEFAULT_ENV_ID`) with ``env_kwargs`` and the
    commands' ``shorthands`` (keyword arguments under the command's names; None values are
    "not given") over the id's own; every option checked (module docstring).

    ``clutter_levels``: the levels to run (None: the env's own, :attr:`ResolvedEnv.levels`);
    one the id excludes (it fixes another level) overrides it, with a logged line.
    ``per_decision``: the runs are interface policies deciding every decision, so a wrapped id
    (``SlamGym/HybridSLAM-Interval-v1``) resolves to the system it wraps, said in one line.
    """
    env_id = check_env_id(DEFAULT_ENV_ID if env_id is None else env_id)
    if per_decision and system_id(env_id) != env_id:
        logger.warning("%s: interface policies decide every decision, so the runs are in %s, "
                       "the env it wraps (the same system, world and reward)", env_id,
                       system_id(env_id))
        env_id = system_id(env_id)
    own = registered_kwargs(env_id)
    given = dict(env_kwargs or {})
    require(all(isinstance(k, str) for k in given), "env_kwargs", given,
            "a mapping from option names to values")
    for name, value in (shorthands or {}).items():
        if value is None:
            continue
        require(name not in given or given[name] == value, name, value,
                f"the same as env_kwargs' {name}={given.get(name)!r} (given twice, differently)")
        given[name] = value
    for name, value in sorted(given.items()):
        if name in own and _plain(own[name]) != _plain(value):
            logger.warning("%s: %s=%r overrides the id's %s=%r", env_id, name, value, name,
                           own[name])
    merged = own | given
    cls = env_class(env_id)
    resolved = cls.resolved_kwargs(**merged)  # the env's own validation, naming the option
    levels = _levels_of(merged, resolved)
    if clutter_levels is not None:
        wanted = [int(v) for v in clutter_levels]
        require(bool(wanted) and len(set(wanted)) == len(wanted), "clutter_levels", wanted,
                "distinct levels, at least one")
        require("scenario" in resolved, "clutter_levels", wanted,
                f"left out for {env_id}: its world is a recording, with no clutter level")
        from slam_gym.scenarios import CLUTTER_LEVELS

        bad = [v for v in wanted if v not in CLUTTER_LEVELS]
        require(not bad, "clutter_levels", wanted, f"levels among {sorted(CLUTTER_LEVELS)}")
        outside = [v for v in wanted if v not in levels]
        if outside and levels != ALL_LEVELS:
            logger.warning("%s: clutter levels %s override the id's %s", env_id,
                           ",".join(map(str, wanted)),
                           ",".join("custom" if v is None else str(v) for v in levels))
        levels = tuple(wanted)
    return ResolvedEnv.of(env_id, resolved, levels)


def parse_env_kwargs(items: Iterable[str] | None, field_name: str = "env_kwargs") -> dict:
    """``KEY:VALUE`` strings (rl-zoo3's ``--env-kwargs``) as a dict: each value is read as JSON
    (``n_particles:150``, ``features:["ess_ratio"]``, ``clutter_level:null``) and otherwise kept
    as the string (``scenario:brooks-bailey-zones``); a key given twice is refused."""
    out: dict[str, Any] = {}
    for item in items or ():
        key, sep, text = str(item).partition(":")
        require(bool(sep) and key.strip() != "", field_name, item,
                "KEY:VALUE pairs, e.g. n_particles:150 scenario:brooks-bailey-zones")
        key = key.strip()
        require(key not in out, field_name, item, f"each key once ({key} is given twice)")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        out[key] = value
    return out
