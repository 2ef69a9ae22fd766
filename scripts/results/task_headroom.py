"""The headroom of a task: ``slam-gym headroom`` (:mod:`slam_gym.commands.headroom`; the report is
:mod:`slam_gym.evaluation.headroom`). Kept so that the commands in docs/RESULTS.md that name this
script run as printed: ``--task ID`` is ``--env ID``; every other option is the command's.
"""

from __future__ import annotations

import sys

from slam_gym.evaluation.headroom import *  # noqa: F403 (the report's functions, for scripts)


def main(argv=None) -> int:
    from slam_gym.cli import main as cli_main

    argv = list(sys.argv[1:] if argv is None else argv)
    argv = ["--env" if a == "--task" else a.replace("--task=", "--env=", 1) for a in argv]
    return cli_main(["headroom", *argv])


if __name__ == "__main__":
    raise SystemExit(main())
