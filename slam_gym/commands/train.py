"""``slam-gym train``: train interface policies with stable-baselines3, several seeds, resumable.

Hyper-parameters come from a YAML file per algorithm in rl-zoo3's layout
(``slam_gym/training/hyperparams/<algo>.yml``, or ``--hyperparams FILE``; ``--hp key=value``
overrides one entry), see :mod:`slam_gym.training.hyperparams`. Each seed trains in
``OUT/seed-<s>/`` (:mod:`slam_gym.training.run`: ``n_envs`` ``SubprocVecEnv`` workers, each
episode in a random clutter level and a fresh training world with seed >= 1e6, observations
through ``log1p`` and ``VecNormalize``, checkpoints, SB3's CSV/TensorBoard logs, a CSV of every
training episode, periodic evaluation on held-out worlds with the benchmark's code). ``--resume``
continues every unfinished seed from its newest checkpoint and skips finished ones.

At the end ``OUT/summary.{json,md}`` gives the spread of the seeds' final evaluations and the
seed chosen on those training-time evaluation worlds, ``OUT/training_curves.png`` the curves, and
``OUT/model.zip`` / ``model.json`` is a copy of the chosen seed's model, loadable with
``policies.make("learned", path="OUT/model.zip")``.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from slam_gym.commands.common import add_common_options, emit, out_dir
from slam_gym.commands.runs import int_list
from slam_gym.training.hyperparams import ALGOS, load_hyperparams, parse_overrides

logger = logging.getLogger(__name__)

DEFAULT_EVAL_SEEDS = "900000,900001,900002,900003,900004"
"""Training-time evaluation worlds (5 per level): below the training worlds and far from the
benchmark's reported worlds (0-199)."""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("train", help="train learned interface policies (SB3), resumable")
    p.add_argument("--algo", choices=ALGOS, default="ppo")
    p.add_argument("--env", default="SlamGym/HybridSLAM-v0", help="env id to train on")
    p.add_argument("--hyperparams", default=None,
                   help="YAML file (rl-zoo3 layout; default: the packaged <algo>.yml)")
    p.add_argument("--hp", action="append", default=[], metavar="KEY=VALUE",
                   help="override one hyper-parameter (value parsed as YAML); repeatable")
    p.add_argument("--timesteps", type=int, default=None,
                   help="decisions per seed (default: the YAML's n_timesteps)")
    p.add_argument("--n-envs", type=int, default=None,
                   help="parallel envs (default: the YAML's n_envs)")
    p.add_argument("--seeds", default="0,1,2", help="training seeds, each its own run")
    p.add_argument("--particles", type=int, default=None,
                   help="FastSLAM particles (default: the YAML's env_kwargs)")
    p.add_argument("--n-steps", type=int, default=None,
                   help="cut every training and evaluation path to this many iterations")
    p.add_argument("--clutter-levels", default="0,1,2,3")
    p.add_argument("--eval-every", type=int, default=25_000, help="decisions between evaluations")
    p.add_argument("--eval-seeds", default=DEFAULT_EVAL_SEEDS,
                   help="evaluation worlds per level (seeds < 1e6, never trained on)")
    p.add_argument("--eval-workers", type=int, default=None,
                   help="processes for evaluation (default: n_envs)")
    p.add_argument("--checkpoint-every", type=int, default=25_000)
    p.add_argument("--resume", action="store_true",
                   help="continue unfinished seeds from their newest checkpoints")
    add_common_options(p, default_out="out/train")
    p.set_defaults(run=run)


def build_hyperparams(args) -> dict:
    overrides = parse_overrides(args.hp)
    if args.timesteps is not None:
        overrides["n_timesteps"] = args.timesteps
    if args.n_envs is not None:
        overrides["n_envs"] = args.n_envs
    env_kwargs = {}
    if args.particles is not None:
        env_kwargs["n_particles"] = args.particles
    if args.n_steps is not None:
        env_kwargs["n_steps"] = args.n_steps
    if env_kwargs:
        overrides["env_kwargs"] = {**overrides.get("env_kwargs", {}), **env_kwargs}
    return load_hyperparams(args.algo, args.env, args.hyperparams, overrides)


def run(args) -> int:
    from slam_gym.training.report import plot_curves, write_summary
    from slam_gym.training.run import TrainingSetup, copy_model, train_run

    params = build_hyperparams(args)
    seeds = int_list(args.seeds)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds={args.seeds!r} is invalid: must be distinct integers")
    out = out_dir(args)
    runs = {}
    for seed in seeds:
        setup = TrainingSetup(
            algo=args.algo, env_id=args.env, seed=seed, hyperparams=params,
            clutter_levels=tuple(int_list(args.clutter_levels)),
            eval_seeds=tuple(int_list(args.eval_seeds)), eval_every=args.eval_every,
            eval_workers=args.eval_workers or params["n_envs"],
            checkpoint_every=args.checkpoint_every,
            command="slam-gym " + " ".join(sys.argv[1:]),
        )
        run_dir = out / f"seed-{seed}"
        logger.warning("training %s seed %d for %d decisions into %s", args.algo.upper(), seed,
                       params["n_timesteps"], run_dir)
        train_run(setup, run_dir, resume=args.resume, progress=not args.quiet and not args.json)
        runs[seed] = run_dir
    doc = write_summary(out, args.algo, runs)
    curves = plot_curves(out / "training_curves.png", runs,
                         title=f"{args.algo.upper()} on {args.env}, seeds {seeds}")
    chosen = copy_model(runs[doc["chosen_seed"]], out / "model.zip")
    chosen_config = json.loads(chosen.with_suffix(".json").read_text())
    chosen_config["chosen_among_seeds"] = doc["seeds"]
    chosen_config["chosen_by"] = doc["chosen_by"]
    chosen.with_suffix(".json").write_text(json.dumps(chosen_config, indent=2) + "\n")
    spread = doc["spread"]
    emit(args, {"summary": doc, "model": str(chosen), "curves": str(curves)}, [
        (Path(out) / "summary.md").read_text().rstrip(),
        f"success over seeds {spread['success_rate']['mean']:.2f} ± "
        f"{spread['success_rate']['std']:.2f}; chosen seed {doc['chosen_seed']}",
        f"wrote {chosen} (+ .json), {curves}, summary.json, summary.md",
    ])
    return 0
