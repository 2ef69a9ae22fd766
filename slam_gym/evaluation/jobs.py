"""Benchmark jobs: one job = one run of a system or policy in an env (or on a scenario), at a
clutter level and seed.

A :class:`Job` is frozen and hashable, pickles to worker processes (process pool or Ray) and has a
stable string :attr:`Job.key` that identifies it in ``results.jsonl`` (docs/ARCHITECTURE.md, "The
command line and its output files"): a rerun
with the same output directory skips the jobs whose key is already there.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from filters.validation import require

#: The kinds of job: a SLAM system run on its own schedule, an interface policy in the env, or
#: one training run of a learned policy (a ``slam-gym train`` sweep: name = algorithm,
#: scenario = env id, seed = training seed; :mod:`slam_gym.training.sweep`).
JOB_KINDS = ("system", "policy", "training")

_SCALAR_TYPES = (str, int, float, bool, type(None))

VERSION_OPTIONS = ("policy_sha256",)
"""Options that say which version of the code ran rather than what was run: a job whose key
differs from a recorded row's only by these is the same run of changed code
(:attr:`Job.identity`; :func:`slam_gym.evaluation.run_jobs` refuses or reruns it)."""


def _check_option_value(name: str, value: Any) -> None:
    """Options must be JSON scalars (so the key is stable and the row serialisable)."""
    ok = isinstance(value, _SCALAR_TYPES)
    if ok and isinstance(value, float):
        ok = math.isfinite(value)
    require(ok, f"options[{name!r}]", value, "a str, int, finite float, bool or None")


def normalise_options(options: Mapping[str, Any] | Iterable[tuple[str, Any]] | None) -> tuple:
    """Return options as a tuple of ``(key, value)`` pairs sorted by key (hashable, stable)."""
    if options is None:
        return ()
    items = list(options.items()) if isinstance(options, Mapping) else list(options)
    pairs = []
    for item in items:
        require(
            isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], str),
            "options",
            item,
            "a mapping from str to scalar, or (str, scalar) pairs",
        )
        _check_option_value(item[0], item[1])
        pairs.append(item)
    names = [k for k, _ in pairs]
    require(len(set(names)) == len(names), "options", names, "pairs with distinct keys")
    return tuple(sorted(pairs, key=lambda kv: kv[0]))


@dataclass(frozen=True)
class Job:
    """One run to do.

    ``kind`` is ``"system"`` (a SLAM system on its own fusion schedule, e.g. BB Table 1),
    ``"policy"`` (an interface policy driving the env) or ``"training"`` (a training run);
    ``name`` is the system or policy name (the algorithm of a training run); ``clutter_level``
    is the scenario's clutter level (BB 5.2: 0-3) or ``None`` where it does not apply (real
    data, training); ``options`` is a tuple of ``(key, value)`` pairs sorted by key (a mapping
    is accepted and normalised), e.g. ``(("particles", 500),)``.
    """

    kind: str
    name: str
    scenario: str
    clutter_level: int | None
    seed: int
    options: tuple[tuple[str, Any], ...] = field(default=())
    env: Any = None
    """The env the run is made in (:class:`~slam_gym.envs.spec.ResolvedEnv`: an id and every
    keyword argument of ``gym.make``), or None for a system run on its own schedule outside any
    env (BB's Table 1, CM)."""

    @classmethod
    def in_env(cls, kind: str, name: str, env: Any, clutter_level: int | None, seed: int,
               options: Mapping[str, Any] | None = None) -> Job:
        """A job in ``env`` (a :class:`~slam_gym.envs.spec.ResolvedEnv`): its scenario is the
        env's, the world ``seed`` at ``clutter_level`` and the options the policy's own."""
        return cls(kind, name, env.scenario, clutter_level, seed, options or (), env)

    def __post_init__(self) -> None:
        require(self.kind in JOB_KINDS, "kind", self.kind, f"one of {JOB_KINDS}")
        require(
            isinstance(self.name, str) and bool(self.name), "name", self.name, "a non-empty str"
        )
        require(
            isinstance(self.scenario, str) and bool(self.scenario),
            "scenario",
            self.scenario,
            "a non-empty str",
        )
        level_ok = self.clutter_level is None or (
            isinstance(self.clutter_level, int)
            and not isinstance(self.clutter_level, bool)
            and self.clutter_level >= 0
        )
        require(level_ok, "clutter_level", self.clutter_level, "an int >= 0 or None")
        seed_ok = isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0
        require(seed_ok, "seed", self.seed, "an int >= 0")
        object.__setattr__(self, "options", normalise_options(self.options))
        if self.env is not None:
            require(hasattr(self.env, "env_id") and hasattr(self.env, "kwargs_json"), "env",
                    self.env, "a slam_gym.envs.spec.ResolvedEnv or None")
            require(self.scenario == self.env.scenario, "scenario", self.scenario,
                    f"the env's ({self.env.scenario!r})")

    def _where(self) -> Any:
        """The key's part that says where the run is: the env (id and resolved keyword
        arguments) or, outside any env, the scenario."""
        if self.env is None:
            return self.scenario
        return {"env_id": self.env.env_id, "env_kwargs": self.env.kwargs}

    @property
    def key(self) -> str:
        """Stable identity used for resuming: compact JSON of the job's fields, options sorted
        (a job in an env: its id and every resolved keyword argument instead of the scenario,
        so a change of any option of the env is another run)."""
        return json.dumps(
            [
                self.kind,
                self.name,
                self._where(),
                self.clutter_level,
                self.seed,
                dict(self.options),
            ],
            sort_keys=True,
            separators=(",", ":"),
        )

    @property
    def identity(self) -> str:
        """:attr:`key` without the :data:`VERSION_OPTIONS`: the same run whatever the version of
        a user policy's code."""
        return json.dumps(
            [self.kind, self.name, self._where(), self.clutter_level, self.seed,
             {k: v for k, v in self.options if k not in VERSION_OPTIONS}],
            sort_keys=True,
            separators=(",", ":"),
        )

    def options_dict(self) -> dict[str, Any]:
        """The options as a plain dict (what a run function usually wants)."""
        return dict(self.options)

    def row_fields(self) -> dict[str, Any]:
        """The job's part of a ``results.jsonl`` row: ``system``/``policy`` key named by kind."""
        return {
            self.kind: self.name,
            "env_id": None if self.env is None else self.env.env_id,
            "env_kwargs": None if self.env is None else self.env.kwargs,
            "scenario": self.scenario,
            "clutter_level": self.clutter_level,
            "seed": self.seed,
            "options": self.options_dict(),
            "key": self.key,
        }

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> Job:
        """Rebuild the job a results row came from (exactly one of ``system``/``policy``)."""
        kinds = [k for k in JOB_KINDS if row.get(k) is not None]
        require(len(kinds) == 1, "row kind", kinds, f"exactly one of {JOB_KINDS} set")
        env = None
        if row.get("env_id") is not None:
            from slam_gym.envs.spec import ResolvedEnv

            env = ResolvedEnv.of(row["env_id"], row.get("env_kwargs") or {})
        return cls(
            kind=kinds[0],
            name=row[kinds[0]],
            scenario=row["scenario"],
            clutter_level=row["clutter_level"],
            seed=row["seed"],
            options=row.get("options") or {},
            env=env,
        )


def expand_grid(
    names: Iterable[str],
    clutter_levels: Iterable[int | None],
    seeds: Iterable[int],
    *,
    kind: str = "policy",
    scenario: str = "brooks-bailey",
    options: Mapping[str, Any] | None = None,
    env: Any = None,
) -> list[Job]:
    """All jobs ``seeds x names x clutter_levels``, one scenario (or ``env``, a
    :class:`~slam_gym.envs.spec.ResolvedEnv`, whose scenario it is), seed-major order.

    Seed-major order means an interrupted benchmark has results spread over every (name, clutter
    level) cell rather than all seeds of the first cells. Duplicate names, levels or seeds are
    rejected.
    """
    names, levels, seeds = list(names), list(clutter_levels), list(seeds)
    for field_name, values in (("names", names), ("clutter_levels", levels), ("seeds", seeds)):
        require(len(values) > 0, field_name, values, "a non-empty sequence")
        require(len(set(values)) == len(values), field_name, values, "distinct values")
    opts = normalise_options(options)
    return [
        Job(kind=kind, name=n, scenario=scenario if env is None else env.scenario,
            clutter_level=c, seed=s, options=opts, env=env)
        for s, n, c in itertools.product(seeds, names, levels)
    ]
