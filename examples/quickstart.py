"""Quickstart: make the env, run BB's fixed 10 s rule for one episode, print metrics, save a frame.

    .venv/bin/python examples/quickstart.py [--clutter-level 2] [--particles 100] [--seed 0]
"""

import argparse

import gymnasium as gym
import matplotlib.pyplot as plt

import policies


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clutter-level", type=int, default=2)
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frame", default="quickstart.png")
    args = parser.parse_args()

    env = gym.make(
        "slam_gym:SlamGym/HybridSLAM-v1",
        clutter_level=args.clutter_level,
        n_particles=args.particles,
        render_mode="rgb_array",
    )
    policy = policies.make("fixed-10s")  # BB: fuse every 10 s, never optimise
    obs, info = env.reset(seed=args.seed)
    total_reward, terminated, truncated = 0.0, False, False
    while not (terminated or truncated):
        action = policy.act(obs, info)
        obs, reward, terminated, truncated, info = env.step(action)
        total_reward += reward

    metrics = env.unwrapped.episode.metrics()
    print(f"clutter level {args.clutter_level}, seed {args.seed}, {args.particles} particles")
    print(f"  success (BB's criterion): {metrics['success']}")
    print(f"  ANEES {metrics['anees']:.2f}, "
          f"NEES in the 95 % band {metrics['nees_in_band_fraction']:.0%}")
    print(f"  map error {metrics['map_error_m']:.2f} m, final pose error "
          f"{metrics['final_pose_error_m']:.2f} m")
    print(f"  fusions {metrics['n_fusions']}, return {total_reward:.1f}, "
          f"filter time {metrics['filter_time_s']:.1f} s")
    plt.imsave(args.frame, env.render())
    print(f"  saved the last frame to {args.frame}")
    env.close()


if __name__ == "__main__":
    main()
