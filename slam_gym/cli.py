"""The ``slam-gym`` command line (DESIGN section 7)."""

from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = ("simulate", "reproduce", "benchmark", "train", "speed")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slam-gym",
        description="The local-to-global interface of hybrid SLAM as a decision problem.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"slam_gym.commands.{name}").add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    from slam_gym.commands.common import configure_logging

    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    try:
        return int(args.run(args) or 0)
    except ValueError as exc:
        print(f"slam-gym {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
