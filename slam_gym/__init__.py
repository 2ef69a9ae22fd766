"""slam-gym: the local-to-global interface of hybrid SLAM as a decision problem.

Importing the package registers its Gymnasium environments (idempotently)::

    import gymnasium as gym
    env = gym.make("slam_gym:SlamGym/HybridSLAM-v0", clutter_level=3, n_particles=200)
"""

from policies.learned import set_provenance_check
from slam_gym.envs import ENV_VARIANTS, register_envs
from slam_gym.training.provenance import check_model_provenance

register_envs()
# a learned policy loaded in a process that uses the env is checked against it (issue 29)
set_provenance_check(check_model_provenance)

__all__ = ["ENV_VARIANTS", "register_envs"]
__version__ = "0.1.0"
