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

from filters.validation import require
from slam_gym.commands.common import add_common_options, emit, out_dir
from slam_gym.commands.envargs import add_env_options
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
    p.add_argument("--hyperparams", default=None,
                   help="YAML file (rl-zoo3 layout; default: the packaged <algo>.yml)")
    p.add_argument("--hp", action="append", default=[], metavar="KEY=VALUE",
                   help="override one hyper-parameter (value parsed as YAML); repeatable")
    p.add_argument("--timesteps", type=int, default=None,
                   help="decisions per seed (default: the YAML's n_timesteps)")
    p.add_argument("--n-envs", type=int, default=None,
                   help="parallel envs (default: the YAML's n_envs)")
    p.add_argument("--seeds", default="0,1,2", help="training seeds, each its own run")
    add_env_options(p, ("scenario", "n_particles", "n_steps", "compute_clip_s"))
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
    """The run's settings: the YAML entry of ``--env`` (a task reads its system's), ``--hp``,
    and the env's keyword arguments (``--env-kwargs`` and the shorthands) under
    ``env_kwargs``."""
    from slam_gym.commands.envargs import env_shorthands
    from slam_gym.envs.spec import DEFAULT_ENV_ID, check_env_id, parse_env_kwargs

    args.env = check_env_id(DEFAULT_ENV_ID if args.env is None else args.env)
    overrides = parse_overrides(args.hp)
    if args.timesteps is not None:
        overrides["n_timesteps"] = args.timesteps
    if args.n_envs is not None:
        overrides["n_envs"] = args.n_envs
    env_kwargs = parse_env_kwargs(args.env_kwargs)
    for name, value in env_shorthands(args).items():
        if name in env_kwargs and env_kwargs[name] != value:
            raise ValueError(f"{name}={value!r} is invalid: --env-kwargs gives "
                             f"{name}:{env_kwargs[name]!r} (given twice, differently)")
        env_kwargs[name] = value
    if env_kwargs:
        overrides["env_kwargs"] = {**overrides.get("env_kwargs", {}), **env_kwargs}
    return load_hyperparams(args.algo, args.env, args.hyperparams, overrides)


def training_setups(args, params: dict, seeds: list[int]) -> list:
    """One :class:`~slam_gym.training.run.TrainingSetup` per seed, every option checked (the
    env's through :func:`slam_gym.envs.spec.resolve_env`, which says in one line where an option
    overrides the id's) before anything is written or trained."""
    from slam_gym.training.run import TrainingSetup, training_env

    env = training_env(args.env, params.get("env_kwargs"), None if args.clutter_levels is None
                       else int_list(args.clutter_levels, "clutter_levels"))
    require(None not in env.levels, "env", args.env, "an env with clutter levels to train in")
    return [TrainingSetup(
        algo=args.algo, env_id=args.env, seed=seed, hyperparams=params,
        clutter_levels=tuple(env.levels),
        eval_seeds=tuple(int_list(args.eval_seeds, "eval_seeds")), eval_every=args.eval_every,
        eval_workers=args.eval_workers or params["n_envs"],
        checkpoint_every=args.checkpoint_every,
        command="slam-gym " + " ".join(sys.argv[1:]),
    ) for seed in seeds]


def check_seeds(text: str) -> list[int]:
    """``--seeds``: distinct integers >= 0 (``ValueError`` naming ``seeds``)."""
    seeds = int_list(text, "seeds")
    require(bool(seeds) and len(set(seeds)) == len(seeds) and all(s >= 0 for s in seeds),
            "seeds", text, "distinct integers >= 0")
    return seeds


def run(args) -> int:
    from slam_gym.training.report import summarise_runs
    from slam_gym.training.run import train_run

    params = build_hyperparams(args)
    seeds = check_seeds(args.seeds)
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
    if baseline_name != "none":
        import policies

        policies.make(baseline_name)  # an unknown name fails here, before any training
    setups = training_setups(args, params, seeds)
    out = out_dir(args)
    runs = {}
    for setup in setups:
        run_dir = out / f"seed-{setup.seed}"
        logger.warning("training %s seed %d on %s for %d decisions into %s", args.algo.upper(),
                       setup.seed, args.env, params["n_timesteps"], run_dir)
        train_run(setup, run_dir, resume=args.resume, progress=not args.quiet and not args.json)
        runs[setup.seed] = run_dir
    setup = setups[-1]
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
    from slam_gym.training.evaluation import evaluate_policy

    return evaluate_policy(policy, env_id=setup.evaluation_env(), seeds=setup.eval_seeds,
                           out=out, workers=setup.eval_workers, progress=progress)


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
    levels = training_setups(args, params, seeds[:1])[0].clutter_levels  # every option checked
    out = out_dir(args)
    spec = SweepSpec(
        algo=args.algo, env_id=args.env, hyperparams=params, out=str(out.resolve()),
        clutter_levels=levels,
        eval_seeds=tuple(int_list(args.eval_seeds, "eval_seeds")), eval_every=args.eval_every,
        eval_workers=args.eval_workers or params["n_envs"],
        checkpoint_every=args.checkpoint_every, compute_clip_s=args.env_compute_clip_s,
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
