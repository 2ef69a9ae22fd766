"""The ``slam-gym`` command line (docs/ARCHITECTURE.md, "The command line and its output files")."""

from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = ("simulate", "reproduce", "benchmark", "compare", "train", "threshold-rule",
                   "front", "fingerprint", "speed")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slam-gym",
        description="The local-to-global interface of hybrid SLAM as a decision problem.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true",
                        help="show the whole traceback of an error instead of one line")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"slam_gym.commands.{name.replace('-', '_')}")
        module.add_parser(subparsers)
    return parser


BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread_per_process() -> None:
    """Parallelism is across processes (one run per core): BLAS gets one thread per process.

    Multi-threaded OpenBLAS slows the small matrix products of the filters and SciPy's L-BFGS-B
    badly. The variables reach the worker processes started later; threadpoolctl limits the BLAS
    this process has already loaded.
    """
    import os

    from threadpoolctl import threadpool_limits

    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    threadpool_limits(1)


EXIT_USAGE = 2
"""An invalid or conflicting option value, an unusable ``--out``, a policy or model that cannot
be loaded: nothing ran (argparse exits 2 for its own errors too)."""
EXIT_FAILED = 1
"""The command could not run: the output is locked by another run, an optional dependency is
missing; also ``speed --compare`` and ``fingerprint`` report a failed check with it."""
EXIT_INTERRUPTED = 130
"""Ctrl-C (128 + SIGINT, the shell's convention)."""
# A command that finished with error rows exits slam_gym.commands.runs.EXIT_RUN_ERRORS (3).


OPTIONAL_EXTRAS = {"ray": "ray", "sb3_contrib": "contrib"}
"""Top-level module -> the extra of pyproject.toml that installs it."""


def one_line_error(exc: BaseException) -> tuple[str, int] | None:
    """The one-line message and exit code of a foreseeable failure, or None for a bug (whose
    traceback is shown)."""
    from slam_gym.evaluation.results import ResultsLockedError

    if isinstance(exc, KeyboardInterrupt):
        return (str(exc) or "interrupted; the runs finished so far are kept in --out's "
                "results.jsonl: rerun the same command to resume"), EXIT_INTERRUPTED
    if isinstance(exc, (ValueError, FileNotFoundError)):  # a missing model names its path
        return str(exc), EXIT_USAGE
    if isinstance(exc, ResultsLockedError):
        return str(exc), EXIT_FAILED
    if isinstance(exc, ImportError):
        if "pip install" in str(exc):  # the message names the extra already
            return str(exc), EXIT_FAILED
        extra = OPTIONAL_EXTRAS.get((exc.name or "").partition(".")[0])
        hint = (f": it is the optional dependency of extra [{extra}], pip install "
                f"'slam-gym[{extra}]'" if extra else "")
        return f"cannot import {exc.name or 'a module'} ({exc}){hint}", EXIT_FAILED
    return None


def main(argv: list[str] | None = None) -> int:
    """Run one command; its exit code: 0, or :data:`EXIT_USAGE`, :data:`EXIT_FAILED`,
    ``EXIT_RUN_ERRORS`` (3: some runs are error rows), :data:`EXIT_INTERRUPTED`. Foreseeable
    failures print one line (``--debug``: the traceback too)."""
    from slam_gym.commands.common import configure_logging

    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    one_blas_thread_per_process()
    try:
        return int(args.run(args) or 0)
    except (Exception, KeyboardInterrupt) as exc:
        known = one_line_error(exc)
        if known is None or args.debug:
            raise
        message, code = known
        print(f"slam-gym {args.command}: error: {message}", file=sys.stderr)
        return code


if __name__ == "__main__":
    sys.exit(main())
