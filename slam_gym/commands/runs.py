"""Options and steps shared by the commands that run many jobs (reproduce, benchmark, front,
threshold-rule)."""

from __future__ import annotations

import argparse
import sys

from slam_gym.commands.common import add_common_options

DEFAULT_RUN_TIMEOUT_S = 3600.0
"""The default limit of one run (``--run-timeout-s``): an hour, about 20 times the slowest run of
the benchmark's policies at BB's 500 particles on the whole path (docs/ARCHITECTURE.md)."""

EXIT_USAGE = 2
"""Exit code of an invalid or conflicting option (argparse's own, and every ``ValueError``)."""
EXIT_RUN_ERRORS = 3
"""Exit code of a command that finished but recorded error rows (without ``--allow-errors``)."""


class Given(argparse.Action):
    """Store an option's value and remember that it was given (:func:`given`), so a preset
    (``--quick``) or a check of unused options can tell a default from the user's choice."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.given = set(getattr(namespace, "given", None) or ()) | {self.dest}


def given(args, dest: str) -> bool:
    """Whether option ``dest`` was on the command line (options stored with :class:`Given`)."""
    return dest in (getattr(args, "given", None) or ())


def plot_episode_map(episode, path, title: str):
    """BB Fig. 2 for one finished episode (:func:`slam_gym.evaluation.plots.plot_episode_map`)."""
    from slam_gym.evaluation.plots import plot_episode_map as plot

    return plot(episode, path, title)


def int_list(text: str, field: str = "list") -> list[int]:
    """Comma-separated integers; ``field`` names the option in the error (its destination, so
    the command line names it as typed)."""
    try:
        return [int(v) for v in text.split(",") if v.strip() != ""]
    except ValueError as exc:
        raise ValueError(f"{field}={text!r} is invalid: must be comma-separated integers") \
            from exc


def float_list(text: str, field: str = "list") -> list[float]:
    """Comma-separated finite numbers (:func:`int_list`'s ``field``)."""
    import math

    from filters.validation import require

    try:
        values = [float(v) for v in text.split(",") if v.strip() != ""]
    except ValueError as exc:
        raise ValueError(f"{field}={text!r} is invalid: must be comma-separated numbers") \
            from exc
    require(all(math.isfinite(v) for v in values), field, text,
            "comma-separated finite numbers")
    return values


def name_list(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def add_run_options(parser, default_out: str, *, trials_flag: str | None = "--trials") -> None:
    """The run options; ``trials_flag`` None leaves out the number of worlds and the first seed
    (for a command that takes its own list of seeds)."""
    if trials_flag is not None:
        parser.add_argument(trials_flag, dest="trials", type=int, default=20, action=Given,
                            metavar="N", help="worlds (seeds) per configuration, from "
                            "--seed-start")
        parser.add_argument("--seed-start", type=int, default=0, metavar="S",
                            help="the first world's seed (the worlds are S, S+1, ...)")
    parser.add_argument("--workers", type=int, default=None, action=Given,
                        help="parallel worker processes (default: all cores; not with "
                        "--executor serial)")
    parser.add_argument("--executor", choices=["process", "ray", "serial"], default="process",
                        help="where the runs go: a process pool on this machine (default), Ray "
                        "(this machine or a cluster, pip install slam-gym[ray]) or this process, "
                        "one after the other (serial)")
    parser.add_argument("--ray-address", default=None,
                        help="existing Ray cluster (only with --executor ray)")
    parser.add_argument("--retry-errors", action="store_true",
                        help="run the error rows already in --out again (e.g. after fixing a "
                        "policy that raised)")
    parser.add_argument("--rerun-changed", action="store_true",
                        help="replace the rows of a user policy whose code or options changed "
                        "since they were run (without it such a rerun refuses)")
    parser.add_argument("--run-timeout-s", type=float, default=DEFAULT_RUN_TIMEOUT_S,
                        metavar="S", help="time limit of one run: a run still going after S "
                        "seconds becomes an error row and its worker is replaced (default "
                        f"{DEFAULT_RUN_TIMEOUT_S:g})")
    parser.add_argument("--allow-errors", action="store_true",
                        help=f"exit 0 even when some runs are error rows (else exit "
                        f"{EXIT_RUN_ERRORS})")
    add_common_options(parser, default_out)


def check_run_options(args) -> None:
    """Reject invalid and conflicting run options before any run (``ValueError`` naming the
    option: exit 2)."""
    import math
    import os

    from filters.validation import require

    if getattr(args, "trials", None) is not None:
        require(args.trials >= 1, "trials", args.trials, "a number of worlds >= 1")
    if getattr(args, "seed_start", None) is not None:
        require(args.seed_start >= 0, "seed_start", args.seed_start, "a seed >= 0")
    if args.workers is not None:
        require(args.workers >= 1, "workers", args.workers, "a number of processes >= 1")
    if args.executor == "serial" and given(args, "workers") and args.workers != 1:
        raise ValueError(f"--workers {args.workers} is invalid with --executor serial, which "
                         "runs one run at a time: leave --workers out, or use --executor process")
    if args.ray_address is not None and args.executor != "ray":
        raise ValueError(f"--ray-address {args.ray_address} is invalid with --executor "
                         f"{args.executor}: it is used only by --executor ray")
    require(math.isfinite(args.run_timeout_s) and args.run_timeout_s > 0, "run_timeout_s",
            args.run_timeout_s, "a number of seconds > 0")
    if args.workers is None:
        args.workers = os.cpu_count() or 1


def run_options(args) -> dict:
    """The keyword arguments of :func:`slam_gym.evaluation.run_jobs` the run options set."""
    return {
        "workers": args.workers,
        "executor": args.executor,
        "ray_address": args.ray_address,
        "progress": not args.quiet and not args.json,
        "retry_errors": args.retry_errors,
        "rerun_changed": args.rerun_changed,
        "run_timeout_s": args.run_timeout_s,
    }


def errors_exit_code(args, rows, where: str | None = None) -> int:
    """0, or :data:`EXIT_RUN_ERRORS` with a line on stderr when some rows are errors and
    ``--allow-errors`` is not given (after the summary was printed). ``where``: the results
    files the line names (default ``--out``'s ``results.jsonl``)."""
    errors = [r for r in rows if r.get("status") == "error"]
    if not errors:
        return 0
    first = errors[0].get("error") or "?"
    where = where or f"{args.out}/results.jsonl"
    line = (f"slam-gym {args.command}: {len(errors)} of {len(rows)} runs failed (error rows in "
            f"{where}; the first: {first[:160]})")
    if getattr(args, "allow_errors", False):
        print(f"{line}; exit 0 (--allow-errors)", file=sys.stderr)
        return 0
    print(f"{line}; fix the cause and rerun with --retry-errors, or pass --allow-errors to exit "
          f"0 (exit {EXIT_RUN_ERRORS})", file=sys.stderr)
    return EXIT_RUN_ERRORS


def execute(args, jobs, out):
    """Run the jobs (resumable) and write summary.json / table.md; the rows and summary doc."""
    from slam_gym.evaluation import run_jobs
    from slam_gym.evaluation.core import run_job

    check_run_options(args)
    return run_jobs(jobs, run_job, out, **run_options(args))


PIPED_WIDTH = 100
"""The width of the console table when the output is not a terminal (and ``COLUMNS`` is not
set): a pipe, a file, a CI log."""


def console_width() -> int:
    """The width to lay the console table out for: ``COLUMNS`` when set, else the terminal's,
    else (piped) :data:`PIPED_WIDTH`."""
    import shutil

    return max(40, shutil.get_terminal_size(fallback=(PIPED_WIDTH, 24)).columns)


def print_table(args, doc, paper=None, title=None) -> None:
    """The summary on stdout (not with ``--json``), laid out for :func:`console_width`: split
    into parts rather than any value cut (``table.md`` holds it whole)."""
    if args.json:
        return
    from rich.console import Console

    from slam_gym.evaluation.summary import format_tables

    width = console_width()
    console = Console(width=width, file=sys.stdout)
    for table in format_tables(doc, width=width, paper=paper, title=title):
        # a part wider than the terminal (its names alone are) is printed whole, not cropped
        console.print(table, width=max(width, table.min_width or 0), crop=False)
