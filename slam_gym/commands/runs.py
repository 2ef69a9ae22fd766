"""Options and steps shared by the commands that run many jobs (reproduce, benchmark)."""

from __future__ import annotations

import os

from slam_gym.commands.common import add_common_options


def plot_episode_map(episode, path, title: str):
    """BB Fig. 2 for one finished episode (:func:`slam_gym.evaluation.plots.plot_episode_map`)."""
    from slam_gym.evaluation.plots import plot_episode_map as plot

    return plot(episode, path, title)


def int_list(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip() != ""]
    except ValueError as exc:
        raise ValueError(f"{text!r} is invalid: must be comma-separated integers") from exc


def name_list(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def add_run_options(parser, default_out: str, *, trials_flag: str = "--trials") -> None:
    parser.add_argument(trials_flag, dest="trials", type=int, default=20,
                        help="runs per configuration (seeds)")
    parser.add_argument("--seed-start", type=int, default=0, help="first seed")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="parallel worker processes (default: all cores)")
    parser.add_argument("--executor", choices=["process", "ray", "serial"], default="process")
    parser.add_argument("--ray-address", default=None, help="existing Ray cluster (executor ray)")
    add_common_options(parser, default_out)


def execute(args, jobs, out):
    """Run the jobs (resumable) and write summary.json / table.md; the rows and summary doc."""
    from slam_gym.evaluation import run_jobs
    from slam_gym.evaluation.core import run_job

    if args.trials < 1:
        raise ValueError(f"trials={args.trials} is invalid: must be >= 1")
    rows = run_jobs(
        jobs,
        run_job,
        out,
        workers=args.workers,
        executor=args.executor,
        ray_address=args.ray_address,
        progress=not args.quiet and not args.json,
    )
    return rows


def print_table(args, doc, paper=None, title=None) -> None:
    if args.json:
        return
    from rich.console import Console

    from slam_gym.evaluation.summary import format_table

    Console(width=160).print(format_table(doc, paper=paper, title=title))
