"""Gymnasium environments of slam-gym and their registration.

``import slam_gym`` registers every id (idempotently), and ``gym.make("slam_gym:<id>")`` imports
the package first, so the ids also resolve in a fresh interpreter and in spawned workers.
"""

from __future__ import annotations

import gymnasium as gym

ENTRY_POINT = "slam_gym.envs.hybrid_slam:HybridSLAMEnv"

ORDERED_STREAMS = {"random_streams": "ordered"}
"""What a ``-v0`` id sets: the filter's random numbers in one ordered stream (the Version
History of :mod:`slam_gym.envs.hybrid_slam`); ``-v1`` ids draw them synchronised."""


def _both_versions(variants: dict[str, dict]) -> dict[str, dict]:
    """``name -> kwargs`` as the ids ``name-v1`` (synchronised draws) and ``name-v0``."""
    return ({f"{name}-v1": dict(kwargs) for name, kwargs in variants.items()}
            | {f"{name}-v0": dict(kwargs) | ORDERED_STREAMS for name, kwargs in variants.items()})


#: id -> default keyword arguments (each overridable in gym.make)
ENV_VARIANTS: dict[str, dict] = _both_versions({
    "SlamGym/HybridSLAM": {},
    "SlamGym/HybridSLAM-Light": {"n_particles": 100},
    "SlamGym/HybridSLAM-Clutter0": {"clutter_level": 0},
    "SlamGym/HybridSLAM-Clutter1": {"clutter_level": 1},
    "SlamGym/HybridSLAM-Clutter2": {"clutter_level": 2},
    "SlamGym/HybridSLAM-Clutter3": {"clutter_level": 3},
    "SlamGym/HybridSLAM-Compass": {"scenario": "brooks-bailey-compass", "clutter_level": 0},
    "SlamGym/EKFSubmap": {"front_end": "ekf"},
    "SlamGym/HybridSLAM-Relative": {"back_end": "relative"},
})

DEFAULT_ENV_ID = "SlamGym/HybridSLAM-v1"
"""The id to report and to train on by default."""


def env_version(env_id: str) -> int:
    """The version number at the end of an id (``...-v1`` -> 1)."""
    head, sep, version = env_id.rpartition("-v")
    if not (sep and head and version.isdigit()):
        raise ValueError(f"env_id={env_id!r} is invalid: must end in -v<number>")
    return int(version)


#: envs on recorded data: id -> (entry point, default keyword arguments)
RECORDED_ENV_VARIANTS: dict[str, tuple[str, dict]] = {
    "SlamGym/MRCLAM-v1": ("slam_gym.envs.mrclam:MRCLAMEnv", {}),
    "SlamGym/MRCLAM-v0": ("slam_gym.envs.mrclam:MRCLAMEnv", dict(ORDERED_STREAMS)),
}


#: the same system under another action space (a wrapper of the env): id -> (entry point, default
#: keyword arguments); the time limit is the wrapped env's, which an action never exceeds
INTERVAL_ENV_ID = "SlamGym/HybridSLAM-Interval-v1"
"""One action per fusion (:mod:`slam_gym.envs.interval`)."""

WRAPPED_ENV_VARIANTS: dict[str, tuple[str, dict]] = {
    INTERVAL_ENV_ID: ("slam_gym.envs.interval:make_interval_env", {}),
    "SlamGym/HybridSLAM-Interval-v0": ("slam_gym.envs.interval:make_interval_env",
                                       dict(ORDERED_STREAMS)),
}

#: the id of the system each wrapped variant runs (its fingerprint and options are that id's)
WRAPPED_SYSTEM_IDS: dict[str, str] = {INTERVAL_ENV_ID: "SlamGym/HybridSLAM-v1",
                                      "SlamGym/HybridSLAM-Interval-v0": "SlamGym/HybridSLAM-v0"}


def system_env_id(env_id: str) -> str:
    """The id of the system ``env_id`` runs: itself, or the id a wrapped variant wraps."""
    return WRAPPED_SYSTEM_IDS.get(env_id, env_id)


RECORDED_MAX_EPISODE_STEPS = 2000
"""Decisions (1 s each at the defaults) of a recorded env's episode before Gymnasium's time limit:
above the length of every MRCLAM recording (Dataset 7: ~890 s)."""


def max_episode_steps(kwargs: dict) -> int:
    """1.5 times the decisions of the scenario's nominal path (length / speed) at the default
    decision interval: a margin for the path's random detours, never a cut of a normal run."""
    import math

    from slam_gym.envs.hybrid_slam import HybridSLAMConfig

    config = HybridSLAMConfig.from_kwargs(**kwargs)
    scenario = config.scenario_config()
    steps = scenario.path_length_m / scenario.speed_mps * scenario.filter_rate_hz
    return math.ceil(1.5 * steps / config.decision_interval)


#: the tasks of issue 48 (slam_gym.envs.tasks), only at -v1: id -> entry point; each is
#: registered with its class's own defaults (``DEFAULTS``), so ``gym.spec(id).kwargs`` shows them
TASK_ENTRY_POINTS: dict[str, str] = {
    "SlamGym/HybridSLAM-Zones-v1": "slam_gym.envs.tasks:ZonesEnv",
    "SlamGym/HybridSLAM-ZonesStarved-v1": "slam_gym.envs.tasks:ZonesStarvedEnv",
    "SlamGym/HybridSLAM-LongMission-v1": "slam_gym.envs.tasks:LongMissionEnv",
}


def _task_variants() -> dict[str, tuple[str, dict]]:
    from gymnasium.envs.registration import load_env_creator

    return {env_id: (entry_point, dict(load_env_creator(entry_point).DEFAULTS))
            for env_id, entry_point in TASK_ENTRY_POINTS.items()}


#: id -> (entry point, default keyword arguments: the class's ``DEFAULTS``)
TASK_ENV_VARIANTS: dict[str, tuple[str, dict]] = _task_variants()


def register_envs() -> list[str]:
    """Register every variant that is not registered yet; returns the simulated ids."""
    for env_id, kwargs in ENV_VARIANTS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=ENTRY_POINT, kwargs=dict(kwargs),
                         max_episode_steps=max_episode_steps(kwargs))
    for env_id, (entry_point, kwargs) in WRAPPED_ENV_VARIANTS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, kwargs=dict(kwargs),
                         max_episode_steps=max_episode_steps(kwargs))
    for env_id, (entry_point, kwargs) in TASK_ENV_VARIANTS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, kwargs=dict(kwargs),
                         max_episode_steps=max_episode_steps(kwargs))
    for env_id, (entry_point, kwargs) in RECORDED_ENV_VARIANTS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, kwargs=dict(kwargs),
                         max_episode_steps=RECORDED_MAX_EPISODE_STEPS)
    return list(ENV_VARIANTS)
