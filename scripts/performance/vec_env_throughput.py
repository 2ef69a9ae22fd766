"""Decisions and episodes per wall second of a training's vectorised env, by number of workers.

Usage: python scripts/performance/vec_env_throughput.py [--n-envs 2,4] [--seconds 120]
e.g.   python scripts/performance/vec_env_throughput.py --env SlamGym/HybridSLAM-Interval-v0

SB3's ``SubprocVecEnv`` steps its workers in lock step: every ``step`` waits for the slowest
worker. An interval action of ``SlamGym/HybridSLAM-Interval-v0`` covers 2-20 s of the world, so
workers given different intervals finish at different times and the faster one idles. This
steps the training's own env constructor (``slam_gym.training.run.make_env_fn``: random clutter
level and price, the env options of a ``slam-gym train`` run) in a ``SubprocVecEnv`` of each
``--n-envs`` for ``--seconds`` of wall time, with actions drawn uniformly from a seeded
generator (a learner that varies its intervals; ``--actions rule`` plays the constant rule
action instead), and prints decisions/s, episodes/s and the workers' CPU use (their
``/proc/<pid>/stat`` user + system time over the wall time, in cores). No policy update runs,
so this is the env side of a training run only.

``--rule T`` (issue 57) measures instead what the issue's target names: SB3's
``make_vec_env(ENV, n_envs=N, vec_env_cls=SubprocVecEnv)`` (``--vec sb3``) or Gymnasium's
``gym.make_vec(ENV, num_envs=N, vectorization_mode="async")`` (``--vec gymnasium``) of the plain
registered env, each worker stepping the best rule's actions,
``threshold-optimise[global_position_std_m>=T]`` (docs/RESULTS.md: T = 2 on
``SlamGym/HybridSLAM-Zones-v1``, 1 on ``-ZonesStarved-v1``), from its own infos, until
``--episodes`` episodes ended; it prints episodes and decisions per wall second and the workers'
CPU. The worlds are those of the vector env's seed (``--seed``), so two checkouts play the same.

Supports docs/PERFORMANCE.md, "What a user meets" (a training run's wall time) and "The decision
compiled around the filter (issue 57 items 2-4)". The command behind the latter::

    python scripts/performance/vec_env_throughput.py --env SlamGym/HybridSLAM-Zones-v1 \
        --n-envs 2 --rule 2 --episodes 6 --vec sb3
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from slam_gym.envs.interval import RULE_ACTION
from slam_gym.training.hyperparams import load_hyperparams
from slam_gym.training.run import TrainingSetup, make_env_fn

CLOCK_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def cpu_s(pids: list[int]) -> float:
    """User + system CPU seconds of the processes ``pids`` so far."""
    total = 0
    for pid in pids:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14, 15 of stat)
    return total / CLOCK_TICKS_PER_S


def measure(setup: TrainingSetup, n_envs: int, seconds: float, actions: str, seed: int) -> dict:
    from stable_baselines3.common.vec_env import SubprocVecEnv

    vec = SubprocVecEnv([make_env_fn(setup, rank) for rank in range(n_envs)],
                        start_method="spawn")
    try:
        vec.seed(seed)
        vec.reset()
        pids = [p.pid for p in vec.processes]
        space = vec.action_space
        rng = np.random.default_rng(seed)
        decisions = episodes = 0
        cpu0, t0 = cpu_s(pids), time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            if actions == "rule":
                batch = np.tile(RULE_ACTION, (n_envs, 1))
            else:
                batch = np.stack([rng.integers(0, space.nvec) for _ in range(n_envs)])
            _, _, dones, _ = vec.step(batch)
            decisions += n_envs
            episodes += int(np.sum(dones))
        wall = time.perf_counter() - t0
        cpu = cpu_s(pids) - cpu0
    finally:
        vec.close()
    return {"n_envs": n_envs, "wall_s": wall, "decisions": decisions, "episodes": episodes,
            "decisions_per_s": decisions / wall, "episodes_per_s": episodes / wall,
            "worker_cores": cpu / wall}


def _rule_actions(rules, infos) -> np.ndarray:
    """Each worker's rule action from its info (``infos`` a list of dicts)."""
    return np.stack([rule.act(None, info) for rule, info in zip(rules, infos, strict=True)])


def measure_rule(env_id: str, n_envs: int, threshold: float, episodes: int, vec: str,
                 seed: int) -> dict:
    """Episodes per wall second of a vector env of ``env_id`` stepping the rule
    ``threshold-optimise[global_position_std_m>=threshold]`` in each worker (module doc)."""
    import gymnasium as gym

    import policies

    rules = [policies.make("threshold-optimise", threshold=threshold) for _ in range(n_envs)]
    for rule in rules:
        rule.reset()
    decisions = ended = 0
    if vec == "sb3":
        from stable_baselines3.common.env_util import make_vec_env
        from stable_baselines3.common.vec_env import SubprocVecEnv

        env = make_vec_env(f"slam_gym:{env_id}", n_envs=n_envs, seed=seed,
                           vec_env_cls=SubprocVecEnv)
        env.reset()
        pids = [p.pid for p in env.processes]
        infos = list(env.reset_infos)
        cpu0, t0 = cpu_s(pids), time.perf_counter()
        while ended < episodes:
            _, _, dones, step_infos = env.step(_rule_actions(rules, infos))
            infos = list(step_infos)
            decisions += n_envs
            for i in np.flatnonzero(dones):
                ended += 1
                rules[i].reset()
                infos[i] = env.reset_infos[i]  # the new episode's first info
    else:
        env = gym.make_vec(f"slam_gym:{env_id}", num_envs=n_envs, vectorization_mode="async")
        _, vinfo = env.reset(seed=seed)
        pids = [p.pid for p in env.processes]
        restarting = np.zeros(n_envs, dtype=bool)

        def split(vinfo):
            names = list(vinfo["features"].keys())
            return [{"features": {k: float(vinfo["features"][k][i]) for k in names
                                  if not k.startswith("_")}} for i in range(n_envs)]

        infos = split(vinfo)
        cpu0, t0 = cpu_s(pids), time.perf_counter()
        while ended < episodes:
            # gymnasium's next-step autoreset: a worker whose episode ended resets at this step
            _, _, terminated, truncated, vinfo = env.step(_rule_actions(rules, infos))
            decisions += int(np.sum(~restarting))
            infos = split(vinfo)
            done = np.logical_or(terminated, truncated)
            for i in np.flatnonzero(done):
                ended += 1
                rules[i].reset()
            restarting = done
    wall = time.perf_counter() - t0
    cpu = cpu_s(pids) - cpu0
    env.close()
    return {"n_envs": n_envs, "wall_s": wall, "decisions": decisions, "episodes": ended,
            "decisions_per_s": decisions / wall, "episodes_per_s": ended / wall,
            "worker_cores": cpu / wall}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="SlamGym/HybridSLAM-Interval-v0")
    parser.add_argument("--n-envs", default="2,4", help="worker counts to measure, in turn")
    parser.add_argument("--seconds", type=float, default=120.0, help="wall time of each")
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--actions", choices=("random", "rule"), default="random")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rule", type=float, default=None, metavar="T",
                        help="step threshold-optimise[global_position_std_m>=T] in a vector env "
                        "of the plain registered env until --episodes ended (module doc)")
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--vec", choices=("sb3", "gymnasium"), default="sb3")
    args = parser.parse_args(argv)
    counts = [int(v) for v in args.n_envs.split(",")]
    if any(n < 2 for n in counts):
        parser.error(f"n_envs={args.n_envs!r} is invalid: SubprocVecEnv needs >= 2 workers")
    if args.seconds <= 0:
        parser.error(f"seconds={args.seconds} is invalid: must be > 0")
    if args.rule is not None:
        for n in counts:
            r = measure_rule(args.env, n, args.rule, args.episodes, args.vec, args.seed)
            sys.stdout.write(
                f"{args.env} {args.vec} n_envs {n}, threshold-optimise[global_position_std_m>="
                f"{args.rule:g}]: {r['episodes_per_s']:.4f} episodes/s, {r['decisions_per_s']:.1f}"
                f" decisions/s ({r['episodes']} episodes, {r['decisions']} decisions in "
                f"{r['wall_s']:.1f} s), workers {r['worker_cores']:.2f} cores busy\n")
        return 0
    params = load_hyperparams("ppo", args.env)
    params["env_kwargs"] = {**params.get("env_kwargs", {}), "n_particles": args.particles,
                            "w_compute": 10.0, "compute_clip_s": 0.2}
    params["compute_price_range"] = [1, 100]
    params.pop("rule_anchor_weight", None)  # no anchor: the training reward's extra term only
    setup = TrainingSetup(algo="ppo", env_id=args.env, seed=args.seed, hyperparams=params)
    sys.stdout.write(f"{args.env}, {args.particles} particles, {args.actions} actions, "
                     f"{args.seconds:g} s each, {os.cpu_count()} cores\n")
    for n in counts:
        r = measure(setup, n, args.seconds, args.actions, args.seed)
        sys.stdout.write(f"n_envs {n}: {r['decisions_per_s']:.1f} decisions/s, "
                         f"{r['episodes_per_s']:.3f} episodes/s ({r['decisions']} decisions, "
                         f"{r['episodes']} episodes in {r['wall_s']:.0f} s), workers "
                         f"{r['worker_cores']:.2f} cores busy\n")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
