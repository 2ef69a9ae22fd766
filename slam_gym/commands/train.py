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

``--prices 1,10,100`` makes it a sweep (issue 29 item 7, :mod:`slam_gym.training.sweep`): every
(price, seed) is an independent resumable job (``OUT/price-<p>/seed-<s>/``, trained and
evaluated at ``w_compute = p``, with ``--compute-clip-s`` when given) run through the
benchmark's executors (``--executor serial|process|ray``, ``--workers N``, ``--ray-address``);
a rerun skips the finished jobs; each price gets the summary, curves and chosen model above in
``OUT/price-<p>/``, and ``OUT/sweep.{json,md}`` puts the prices side by side. Without
``--prices`` the seeds train here, one after the other, as before.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from slam_gym.commands.common import add_common_options, emit, out_dir
from slam_gym.commands.runs import int_list
from slam_gym.evaluation.executors import EXECUTORS
from slam_gym.training.hyperparams import ALGOS, load_hyperparams, parse_overrides

logger = logging.getLogger(__name__)

DEFAULT_EVAL_SEEDS = "900000,900001,900002,900003,900004"
"""Training-time evaluation worlds (5 per level): below the training worlds and far from the
benchmark's reported worlds (0-199)."""

DEFAULT_BASELINE = "fixed-10s-optimise"
"""The rule whose line a plain ``slam-gym train`` draws beside its curves (``--baseline``)."""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("train", help="train learned interface policies (SB3), resumable")
    p.add_argument("--algo", choices=ALGOS, default="ppo",
                   help="the stable-baselines3 (or sb3-contrib) algorithm (default ppo)")
    p.add_argument("--env", default="SlamGym/HybridSLAM-v1", help="env id to train on")
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
    p.add_argument("--clutter-levels", default="0,1,2,3", metavar="L,...",
                   help="clutter levels the training and evaluation worlds are drawn from")
    p.add_argument("--eval-every", type=int, default=25_000, help="decisions between evaluations")
    p.add_argument("--eval-seeds", default=DEFAULT_EVAL_SEEDS,
                   help="evaluation worlds per level (seeds < 1e6, never trained on)")
    p.add_argument("--baseline", default=None,
                   help="a policy evaluated once on the same worlds and options, drawn as a line "
                        f"beside the training curves and given in the summary (default "
                        f"{DEFAULT_BASELINE}; 'none': skip; not with --prices)")
    p.add_argument("--eval-workers", type=int, default=None,
                   help="processes for evaluation (default: n_envs)")
    p.add_argument("--checkpoint-every", type=int, default=25_000, metavar="N",
                   help="decisions between checkpoints (what --resume continues from)")
    p.add_argument("--resume", action="store_true",
                   help="continue unfinished seeds from their newest checkpoints")
    p.add_argument("--compute-clip-s", type=float, default=None,
                   help="the reward's clip of compute per decision (s; default: the env's)")
    p.add_argument("--prices", default=None,
                   help="a sweep: prices of compute (per s), each x every seed an independent "
                        "resumable job in OUT/price-<p>/seed-<s>/")
    p.add_argument("--executor", choices=EXECUTORS, default=None,
                   help="how a sweep runs its jobs (default process)")
    p.add_argument("--workers", type=int, default=None,
                   help="jobs of a sweep at once (default: cores / n_envs)")
    p.add_argument("--ray-address", default=None,
                   help="a sweep on an existing Ray cluster (executor ray; OUT must be shared)")
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
    if args.compute_clip_s is not None:
        env_kwargs["compute_clip_s"] = args.compute_clip_s
    if env_kwargs:
        overrides["env_kwargs"] = {**overrides.get("env_kwargs", {}), **env_kwargs}
    return load_hyperparams(args.algo, args.env, args.hyperparams, overrides)


def run(args) -> int:
    from slam_gym.training.report import summarise_runs
    from slam_gym.training.run import TrainingSetup, train_run

    params = build_hyperparams(args)
    seeds = int_list(args.seeds, "seeds")
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds={args.seeds!r} is invalid: must be distinct integers")
    if args.prices is not None:
        if args.baseline is not None:
            raise ValueError(f"baseline={args.baseline!r} is invalid with --prices: a sweep's "
                             "summaries have no baseline line")
        return run_sweep_command(args, params, seeds)
    baseline_name = DEFAULT_BASELINE if args.baseline is None else args.baseline
    for field in ("executor", "workers", "ray_address"):
        if getattr(args, field) is not None:
            raise ValueError(
                f"{field}={getattr(args, field)!r} is invalid without --prices: the jobs of a "
                "sweep (prices x seeds) go through executors; without --prices the seeds train "
                "here, one after the other")
    out = out_dir(args)
    if baseline_name != "none":
        import policies

        policies.make(baseline_name)  # an unknown name fails here, before any training
    runs = {}
    for seed in seeds:
        setup = TrainingSetup(
            algo=args.algo, env_id=args.env, seed=seed, hyperparams=params,
            clutter_levels=tuple(int_list(args.clutter_levels, "clutter_levels")),
            eval_seeds=tuple(int_list(args.eval_seeds, "eval_seeds")), eval_every=args.eval_every,
            eval_workers=args.eval_workers or params["n_envs"],
            checkpoint_every=args.checkpoint_every,
            command="slam-gym " + " ".join(sys.argv[1:]),
        )
        run_dir = out / f"seed-{seed}"
        logger.warning("training %s seed %d for %d decisions into %s", args.algo.upper(), seed,
                       params["n_timesteps"], run_dir)
        train_run(setup, run_dir, resume=args.resume, progress=not args.quiet and not args.json)
        runs[seed] = run_dir
    baseline = None if baseline_name == "none" else (baseline_name, evaluate_baseline(
        baseline_name, setup, out / f"baseline-{baseline_name}",
        progress=not args.quiet and not args.json))
    doc = summarise_runs(out, args.algo, runs,
                         title=f"{args.algo.upper()} on {args.env}, seeds {seeds}",
                         baseline=baseline)
    chosen, curves = out / "model.zip", out / "training_curves.png"
    spread = doc["spread"]
    emit(args, {"summary": doc, "model": str(chosen), "curves": str(curves)}, [
        (Path(out) / "summary.md").read_text().rstrip(),
        f"success over seeds {spread['success_rate']['mean']:.2f} ± "
        f"{spread['success_rate']['std']:.2f}; chosen seed {doc['chosen_seed']}",
        f"wrote {chosen} (+ .json), {curves}, summary.json, summary.md",
    ])
    return 0


def evaluate_baseline(policy: str, setup, out: Path, progress: bool) -> dict:
    """``policy``'s evaluation record on the training's evaluation worlds with the env options
    its snapshots are evaluated with (rows in ``out``, resumable)."""
    from slam_gym.evaluation.core import POLICY_OPTIONS
    from slam_gym.training.evaluation import evaluate_policy

    env_options = {k: v for k, v in setup.env_options().items() if k in POLICY_OPTIONS}
    return evaluate_policy(policy, clutter_levels=setup.clutter_levels, seeds=setup.eval_seeds,
                           env_kwargs=env_options, out=out, workers=setup.eval_workers,
                           progress=progress)


def run_sweep_command(args, params: dict, seeds: list[int]) -> int:
    """``--prices``: seeds x prices as jobs through the executors (:mod:`slam_gym.training.sweep`);
    exit status 1 when a job errored (its error is in ``sweep.md`` and ``results.jsonl``)."""
    import os

    from slam_gym.training.sweep import SweepSpec, parse_prices, run_sweep

    prices = parse_prices(args.prices)
    workers = args.workers or max(1, (os.cpu_count() or 1) // params["n_envs"])
    if workers < 1:
        raise ValueError(f"workers={workers} is invalid: must be >= 1")
    executor = args.executor or "process"
    if args.ray_address and executor != "ray":
        raise ValueError(f"ray_address={args.ray_address!r} is invalid with executor="
                         f"{executor!r}: give --executor ray")
    out = out_dir(args)
    spec = SweepSpec(
        algo=args.algo, env_id=args.env, hyperparams=params, out=str(out.resolve()),
        clutter_levels=tuple(int_list(args.clutter_levels, "clutter_levels")),
        eval_seeds=tuple(int_list(args.eval_seeds, "eval_seeds")), eval_every=args.eval_every,
        eval_workers=args.eval_workers or params["n_envs"],
        checkpoint_every=args.checkpoint_every, compute_clip_s=args.compute_clip_s,
        command="slam-gym " + " ".join(sys.argv[1:]))
    logger.warning("sweep of %s: %d prices x %d seeds = %d jobs (%s, %d at once) into %s",
                   args.algo.upper(), len(prices), len(seeds), len(prices) * len(seeds),
                   executor, workers, out)
    doc = run_sweep(spec, prices, seeds, executor=executor, workers=workers,
                    ray_address=args.ray_address, progress=not args.quiet and not args.json)
    emit(args, {"sweep": doc, "sweep_md": str(out / "sweep.md")}, [
        (out / "sweep.md").read_text().rstrip(),
        f"wrote {out / 'sweep.json'}, {out / 'sweep.md'} and per price summary.md, "
        "training_curves.png, model.zip",
    ])
    return 1 if doc["n_errors"] else 0
