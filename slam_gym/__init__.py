"""slam-gym: the local-to-global interface of hybrid SLAM as a decision problem.

Importing the package registers its Gymnasium environments (idempotently)::

    import gymnasium as gym
    env = gym.make("slam_gym:SlamGym/HybridSLAM-v0", clutter_level=3, n_particles=200)
"""

from slam_gym.envs import ENV_VARIANTS, register_envs

register_envs()

__all__ = ["ENV_VARIANTS", "register_envs"]
__version__ = "0.1.0"
