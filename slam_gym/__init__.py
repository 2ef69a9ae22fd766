"""slam-gym: the local-to-global interface of hybrid SLAM as a decision problem.

Importing the package registers its Gymnasium environments (idempotently)::

    import gymnasium as gym
    env = gym.make("slam_gym:SlamGym/HybridSLAM-v1", clutter_level=3, n_particles=200)

The public API is :data:`__all__` (with ``slam_gym.evaluation``'s, ``policies``' and
``filters``'): the env and its options (:class:`HybridSLAMEnv`, :class:`HybridSLAMConfig`,
:class:`MRCLAMEnv`), the ``Discrete(4)`` wrapper (:class:`DiscreteActions`), the real-data
loaders, the benchmark and the training helpers. Every other module path is internal and may
change. The training helpers, the real-data loaders, the recorded env and the benchmark are
imported on first use (:data:`_ON_FIRST_USE`): making an env loads none of them.
"""

import importlib
from typing import Any

from policies.learned import set_provenance_check
from slam_gym.envs import ENV_VARIANTS, TASK_ENV_VARIANTS, register_envs
from slam_gym.envs.hybrid_slam import HybridSLAMConfig, HybridSLAMEnv
from slam_gym.envs.wrappers import DiscreteActions
from slam_gym.training.provenance import check_model_provenance

register_envs()
# a learned policy loaded in a process that uses the env is checked against it (issue 29)
set_provenance_check(check_model_provenance)

__all__ = [
    "ENV_VARIANTS",
    "TASK_ENV_VARIANTS",
    "BenchmarkEvalCallback",
    "DiscreteActions",
    "HybridSLAMConfig",
    "HybridSLAMEnv",
    "MRCLAMEnv",
    "benchmark",
    "default_mrclam_dir",
    "evaluate_policy",
    "load_mrclam",
    "load_victoria_park",
    "register_envs",
    "set_initial_action_probabilities",
]
__version__ = "0.1.0"


_ON_FIRST_USE = {
    # name: the module that defines it, imported when the name is first read, so that a
    # process that only makes an env does not load the real-data loaders, the evaluation's
    # table and plot code, or stable-baselines3 and torch (the training helpers)
    "BenchmarkEvalCallback": "slam_gym.training.callbacks",
    "MRCLAMEnv": "slam_gym.envs.mrclam",
    "benchmark": "slam_gym.evaluation",
    "default_mrclam_dir": "slam_gym.envs.mrclam",
    "evaluate_policy": "slam_gym.training.evaluation",
    "load_mrclam": "slam_gym.datasets",
    "load_victoria_park": "slam_gym.datasets",
    "set_initial_action_probabilities": "slam_gym.training.run",
}


def __getattr__(name: str) -> Any:
    if name in _ON_FIRST_USE:
        return getattr(importlib.import_module(_ON_FIRST_USE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_ON_FIRST_USE))
