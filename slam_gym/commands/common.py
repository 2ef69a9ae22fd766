"""Options and output shared by every subcommand (docs/ARCHITECTURE.md, "The command line and its
output files")."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np


def add_common_options(parser, default_out: str) -> None:
    parser.add_argument(
        "--out", default=default_out, help=f"output directory (default {default_out})"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def out_dir(args) -> Path:
    """``--out``, created (``ValueError`` naming it when it cannot be used)."""
    from slam_gym.evaluation.benchmarking import make_out_dir

    return make_out_dir(args.out)


def to_jsonable(value):
    """numpy scalars and arrays to plain Python for json.dumps."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def emit(args, payload: dict, human_lines: list[str]) -> None:
    """Print the JSON object (``--json``) or the human summary."""
    if getattr(args, "json", False):
        print(json.dumps(to_jsonable(payload), sort_keys=True))
    else:
        for line in human_lines:
            print(line)


def configure_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
