"""Victoria Park: trees mapped twice, counted as pairs of mapped trees closer than 1 m (and 2 m).

Usage: python scripts/vp_close_pairs.py OUT_DIR [OUT_DIR ...]

Reads the ``results.jsonl`` of ``slam-gym reproduce victoria-park`` runs (their
``figure.trees_xy``: the confirmed trees at the end) and prints, per system and seed, the trees
mapped and the pairs closer than 1 m and 2 m. A tree trunk seen by the laser is one point feature,
so a pair of mapped trees within a metre is most likely one tree mapped twice (EKF-SLAM's map,
with full covariance and JCBB, has none).
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

logger = logging.getLogger(__name__)


def main(argv) -> int:
    if not argv:
        raise ValueError("out_dirs: give at least one reproduce victoria-park output directory")
    for out in argv:
        path = Path(out) / "results.jsonl"
        if not path.is_file():
            raise ValueError(f"out_dir={out!r}: no results.jsonl there")
        for line in path.read_text().splitlines():
            row = json.loads(line)
            trees = np.asarray(row["figure"]["trees_xy"], dtype=float).reshape(-1, 2)
            tree = cKDTree(trees)
            logger.info("%s seed %s: %d trees, %d pairs closer than 1 m, %d closer than 2 m",
                        row["system"], row["seed"], len(trees), len(tree.query_pairs(1.0)),
                        len(tree.query_pairs(2.0)))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(main(sys.argv[1:]))
