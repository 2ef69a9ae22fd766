"""Train a PPO interface policy with stable-baselines3 on ``gym.make``, then benchmark it.

    .venv/bin/python examples/train_ppo.py [--env ID] [--timesteps 3000] [--particles P] \
        [--out out/ppo]

Plain stable-baselines3 on the registered env (no project training code but one helper): PPO on
``--env`` (default ``SlamGym/HybridSLAM-Light-v1``; a task id such as
``SlamGym/HybridSLAM-Zones-v1`` trains, evaluates and benchmarks on the task's worlds) at
clutter level 2, with
:class:`slam_gym.BenchmarkEvalCallback` evaluating snapshots on two held-out
worlds during training (success, ANEES, map error, completeness, interface CPU, return on the
model's logger under ``eval/``, and in ``OUT/eval/evaluations.csv``). The model is saved with the
JSON the ``learned`` policy reads, and benchmarked with :func:`slam_gym.evaluation.benchmark`
against ``fixed-10s`` (BB's rule) on the benchmark's worlds (seeds 0 and 1 at clutter level 2).
The policy acts by draws from its action distribution (``deterministic=False``, with its own
seeded generator): the mode of a head that fuses with probability 0.3 per decision is "never",
a different policy from the one trained (docs/ARCHITECTURE.md, "Training").

Untrained PPO picks each action with probability 0.5, i.e. optimises at every other decision,
which makes the env about 3x slower and is no prior anyone would choose;
:func:`slam_gym.set_initial_action_probabilities` starts it at BB's rate (0.1 per
decision) instead (docs/ARCHITECTURE.md, "Training").

A few thousand decisions are a demonstration, not a trained policy: ``slam-gym train`` (rl-zoo3
hyper-parameter files, ``VecNormalize``, several seeds, checkpoints) made the shipped model
from 80 000 decisions at 500 particles (at 3 000 decisions this one does no better than BB's
rule). At the defaults (3 000 decisions, two evaluations on 2 worlds, 2 x 2 benchmark runs at 100
particles) this script took 4 min 17 s of wall time on 2 cores shared with other jobs (2 min 57 s
of CPU). The test runs it with ``--timesteps 32 --particles 10 --n-steps 150 --seeds 1``.
"""

import argparse
from pathlib import Path

import gymnasium as gym
from stable_baselines3 import PPO

from slam_gym import BenchmarkEvalCallback, set_initial_action_probabilities
from slam_gym.evaluation import benchmark, markdown_table

ENV_ID = "SlamGym/HybridSLAM-Light-v1"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default=ENV_ID, help=f"the env id to train on (default {ENV_ID}; "
                        "e.g. SlamGym/HybridSLAM-Zones-v1)")
    parser.add_argument("--timesteps", type=int, default=3000, help="training decisions")
    parser.add_argument("--particles", type=int, default=None,
                        help="FastSLAM particles (default: the env id's own)")
    parser.add_argument("--n-steps", type=int, default=None, help="cut every path (tests)")
    parser.add_argument("--seeds", type=int, default=2, help="benchmark worlds")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default="out/train_ppo")
    args = parser.parse_args()
    out = Path(args.out)

    env_kwargs = {"n_particles": args.particles, "n_steps": args.n_steps}
    env_kwargs = {k: v for k, v in env_kwargs.items() if v is not None}
    env = gym.make(f"slam_gym:{args.env}", clutter_level=2, **env_kwargs)
    rollout = min(512, max(16, args.timesteps // 4))
    model = PPO("MlpPolicy", env, n_steps=rollout, batch_size=min(64, rollout), n_epochs=5,
                learning_rate=3e-4, seed=0, device="cpu", verbose=0)
    set_initial_action_probabilities(
        model, {"initial_fuse_probability": 0.1, "initial_optimise_probability": 0.1})
    callback = BenchmarkEvalCallback(
        eval_freq=max(rollout, args.timesteps // 2), env_id=args.env, env_kwargs=env_kwargs,
        clutter_levels=(2,), seeds=(900_000, 900_001), deterministic=False,
        log_path=out / "eval", workers=args.workers)
    model.learn(args.timesteps, callback=callback, progress_bar=False)
    for record in callback.evaluations:
        print(f"evaluation at {record['timesteps']} decisions: success "
              f"{record['success_rate']:.2f}, return {record['mean_return']:.0f}, ANEES "
              f"{record['anees']:.1f}, map error {record['map_error_m']:.2f} m")
    model_path = callback.save_snapshot(out / "model.zip")  # model.zip + model.json
    env.close()

    result = benchmark(
        ["learned", "fixed-10s"], model=str(model_path), env=args.env, env_kwargs=env_kwargs,
        clutter_levels=[2], seeds=args.seeds, workers=args.workers,
        executor="process" if args.workers > 1 else "serial", out=out / "benchmark",
        baselines=[], figures=False,  # figures=True adds the plots of slam-gym benchmark
    )
    print(markdown_table(result.summary))
    print(f"model {model_path}; benchmark rows in {out / 'benchmark' / 'results.jsonl'}")


if __name__ == "__main__":  # the benchmark's worker processes import this file again
    main()
