"""slam-gym: the local-to-global interface of hybrid SLAM as a decision problem.

Importing the package registers its Gymnasium environments (idempotently)::

    import gymnasium as gym
    env = gym.make("slam_gym:SlamGym/HybridSLAM-v1", clutter_level=3, n_particles=200)

The public API is :data:`__all__` (with ``slam_gym.evaluation``'s, ``policies``' and
``filters``'): the env and its options (:class:`HybridSLAMEnv`, :class:`HybridSLAMConfig`,
:class:`MRCLAMEnv`), the ``Discrete(4)`` wrapper (:class:`DiscreteActions`), the real-data
loaders, the benchmark and the training helpers. Every other module path is internal and may
change. The training helpers are imported on first use (they load stable-baselines3).
"""

from typing import Any

from policies.learned import set_provenance_check
from slam_gym.datasets import load_mrclam, load_victoria_park
from slam_gym.envs import ENV_VARIANTS, TASK_ENV_VARIANTS, register_envs
from slam_gym.envs.hybrid_slam import HybridSLAMConfig, HybridSLAMEnv
from slam_gym.envs.mrclam import MRCLAMEnv, default_mrclam_dir
from slam_gym.envs.wrappers import DiscreteActions
from slam_gym.evaluation import benchmark
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


def __getattr__(name: str) -> Any:
    # the training helpers, imported on first use (stable-baselines3 and torch are heavy)
    if name == "BenchmarkEvalCallback":
        from slam_gym.training.callbacks import BenchmarkEvalCallback

        return BenchmarkEvalCallback
    if name == "evaluate_policy":
        from slam_gym.training.evaluation import evaluate_policy

        return evaluate_policy
    if name == "set_initial_action_probabilities":
        from slam_gym.training.run import set_initial_action_probabilities

        return set_initial_action_probabilities
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
