"""``slam-gym train``: train an interface policy with stable-baselines3 (PPO by default).

Training runs ``n_envs`` copies of ``SlamGym/HybridSLAM-v0`` in ``SubprocVecEnv`` workers (one per
core by default), each episode in a random clutter level and a fresh training world (seeds
>= 1e6, never used by evaluations), with observations passed through ``log1p``
(:class:`~slam_gym.envs.wrappers.LogFeatures`). DQN trains through the ``Discrete(4)`` wrapper.
An evaluation callback runs the current policy deterministically on fixed evaluation worlds with
the benchmark's evaluation code and logs success rate, ANEES and map error.

Writes ``model.zip``, ``model.json`` (every setting, the command line, versions: enough to repeat
the run) and ``eval_log.jsonl``.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import sys
import time

import numpy as np

from slam_gym.commands.common import add_common_options, emit, out_dir
from slam_gym.commands.runs import int_list

logger = logging.getLogger(__name__)

ALGOS = ("ppo", "dqn", "a2c")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("train", help="train a learned interface policy (SB3)")
    p.add_argument("--algo", choices=ALGOS, default="ppo")
    p.add_argument("--timesteps", type=int, default=100_000, help="env decisions to train on")
    p.add_argument("--n-envs", type=int, default=None, help="parallel envs (default: cores)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--particles", type=int, default=100)
    p.add_argument("--clutter-levels", default="0,1,2,3")
    p.add_argument("--eval-every", type=int, default=20_000, help="decisions between evaluations")
    p.add_argument("--eval-seeds", default="0", help="evaluation worlds (seeds < 1e6)")
    p.add_argument("--eval-particles", type=int, default=None,
                   help="particles in evaluation (default: --particles)")
    p.add_argument("--n-steps", type=int, default=None,
                   help="cut every training and evaluation path to this many iterations")
    p.add_argument("--learning-rate", type=float, default=3e-4)
    p.add_argument("--rollout-steps", type=int, default=256,
                   help="PPO/A2C steps per env per update")
    add_common_options(p, default_out="out/train")
    p.set_defaults(run=run)


class ModelPolicy:
    """An in-memory SB3 model as a policy object (log1p observations), for evaluation."""

    def __init__(self, model, discrete: bool):
        self.model = model
        self.discrete = discrete

    def reset(self):
        pass

    def act(self, obs, info=None):
        action, _ = self.model.predict(np.log1p(obs).astype(np.float32), deterministic=True)
        if self.discrete:
            from slam_gym.envs.wrappers import discrete_to_multi

            return discrete_to_multi(int(action))
        return np.asarray(action, dtype=np.int64).reshape(2)


def make_env_fn(rank: int, seed: int, levels, particles: int, n_steps, discrete: bool):
    def make():
        import gymnasium as gym

        from slam_gym.envs.wrappers import DiscreteActions, LogFeatures, RandomClutterLevel

        env = gym.make("slam_gym:SlamGym/HybridSLAM-v0", n_particles=particles, n_steps=n_steps)
        env = RandomClutterLevel(env, levels)
        env = LogFeatures(env)
        if discrete:
            env = DiscreteActions(env)
        env.reset(seed=seed + 1000 * rank)
        return env

    return make


def run(args) -> int:
    from stable_baselines3 import A2C, DQN, PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

    from slam_gym.evaluation.core import evaluate_policy
    from slam_gym.evaluation.summary import summarise

    if args.timesteps < 1:
        raise ValueError(f"timesteps={args.timesteps} is invalid: must be >= 1")
    n_envs = args.n_envs or (os.cpu_count() or 1)
    if n_envs < 1:
        raise ValueError(f"n_envs={n_envs} is invalid: must be >= 1")
    levels = int_list(args.clutter_levels)
    eval_seeds = int_list(args.eval_seeds)
    if any(s >= 1_000_000 for s in eval_seeds):
        raise ValueError(f"eval_seeds={eval_seeds} is invalid: must be < 1000000 (training worlds)")
    discrete = args.algo == "dqn"
    out = out_dir(args)
    fns = [make_env_fn(i, args.seed, levels, args.particles, args.n_steps, discrete)
           for i in range(n_envs)]
    vec = SubprocVecEnv(fns, start_method="spawn") if n_envs > 1 else DummyVecEnv(fns)
    vec = VecMonitor(vec)
    common = {"seed": args.seed, "verbose": 0, "device": "cpu", "learning_rate": args.learning_rate}
    if args.algo == "ppo":
        model = PPO("MlpPolicy", vec, n_steps=args.rollout_steps, batch_size=64, **common)
    elif args.algo == "a2c":
        model = A2C("MlpPolicy", vec, n_steps=args.rollout_steps, **common)
    else:
        model = DQN("MlpPolicy", vec, buffer_size=50_000, learning_starts=1000, **common)
    eval_particles = args.eval_particles or args.particles
    log_path = out / "eval_log.jsonl"
    log_path.write_text("")

    class EvalCallback(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next_eval = args.eval_every

        def _evaluate(self):
            start = time.perf_counter()
            rows = evaluate_policy(ModelPolicy(self.model, discrete), "brooks-bailey", levels,
                                   eval_seeds, n_particles=eval_particles,
                                   n_steps=args.n_steps)
            groups = summarise(rows)
            record = {
                "timesteps": int(self.num_timesteps),
                "success_rate": float(np.mean([r["success"] for r in rows])),
                "anees": float(np.nanmean([r["anees"] for r in rows])),
                "map_error_m": float(np.nanmean([r["map_error_m"] for r in rows])),
                "n_fusions": float(np.mean([r["n_fusions"] for r in rows])),
                "n_optimisations": float(np.mean([r["n_optimisations"] for r in rows])),
                "per_level": [{k: g.get(k) for k in ("clutter_level", "success_rate", "anees")}
                              for g in groups],
                "eval_time_s": time.perf_counter() - start,
            }
            with log_path.open("a") as fh:
                fh.write(json.dumps(record) + "\n")
            logger.warning(
                "eval at %d: success %.2f, ANEES %.2f, map error %.2f m, fusions %.0f",
                record["timesteps"], record["success_rate"], record["anees"],
                record["map_error_m"], record["n_fusions"],
            )
            return record

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_eval:
                self.next_eval += args.eval_every
                self._evaluate()
            return True

    callback = EvalCallback()
    start = time.perf_counter()
    model.learn(total_timesteps=args.timesteps, callback=callback,
                progress_bar=not args.quiet and not args.json)
    train_time = time.perf_counter() - start
    final = callback._evaluate()
    vec.close()
    model.save(out / "model.zip")
    config = {
        "command": "slam-gym " + " ".join(sys.argv[1:]),
        "algo": args.algo,
        "timesteps": args.timesteps,
        "n_envs": n_envs,
        "seed": args.seed,
        "particles": args.particles,
        "clutter_levels": levels,
        "n_steps": args.n_steps,
        "learning_rate": args.learning_rate,
        "rollout_steps": args.rollout_steps,
        "eval_seeds": eval_seeds,
        "env_id": "SlamGym/HybridSLAM-v0",
        "observation_transform": "log1p",
        "training_world_seeds": ">= 1000000",
        "train_time_s": train_time,
        "final_evaluation": final,
        "versions": {"python": platform.python_version(), **_versions()},
    }
    (out / "model.json").write_text(json.dumps(config, indent=2) + "\n")
    emit(args, config, [
        f"trained {args.algo.upper()} for {args.timesteps} decisions in {train_time:.0f} s "
        f"on {n_envs} envs",
        f"final evaluation: success {final['success_rate']:.2f}, ANEES {final['anees']:.2f}, "
        f"map error {final['map_error_m']:.2f} m",
        f"wrote {out / 'model.zip'}, model.json, eval_log.jsonl",
    ])
    return 0


def _versions() -> dict:
    from importlib.metadata import version

    return {pkg: version(pkg) for pkg in ("stable-baselines3", "torch", "gymnasium", "numpy")}
