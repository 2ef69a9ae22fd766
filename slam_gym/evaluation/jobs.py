"""Benchmark jobs: one job = one run of a system or policy on a scenario, clutter level and seed.

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

    @property
    def key(self) -> str:
        """Stable identity used for resuming: compact JSON of the job's fields, options sorted."""
        return json.dumps(
            [
                self.kind,
                self.name,
                self.scenario,
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
            [self.kind, self.name, self.scenario, self.clutter_level, self.seed,
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
        return cls(
            kind=kinds[0],
            name=row[kinds[0]],
            scenario=row["scenario"],
            clutter_level=row["clutter_level"],
            seed=row["seed"],
            options=row.get("options") or {},
        )


def expand_grid(
    names: Iterable[str],
    clutter_levels: Iterable[int | None],
    seeds: Iterable[int],
    *,
    kind: str = "policy",
    scenario: str = "brooks-bailey",
    options: Mapping[str, Any] | None = None,
) -> list[Job]:
    """All jobs ``seeds x names x clutter_levels``, one scenario, seed-major order.

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
        Job(kind=kind, name=n, scenario=scenario, clutter_level=c, seed=s, options=opts)
        for s, n, c in itertools.product(seeds, names, levels)
    ]
