"""The ``slam-gym`` command line (docs/ARCHITECTURE.md, "The command line and its output files")."""

from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = ("simulate", "reproduce", "benchmark", "train", "threshold-rule", "front",
                   "fingerprint", "speed")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slam-gym",
        description="The local-to-global interface of hybrid SLAM as a decision problem.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
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


def main(argv: list[str] | None = None) -> int:
    from slam_gym.commands.common import configure_logging

    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    one_blas_thread_per_process()
    try:
        return int(args.run(args) or 0)
    except ValueError as exc:
        print(f"slam-gym {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
