"""Victoria Park: trees mapped twice, and how many of a map's trees another system maps too.

Usage: python scripts/archive/vp_close_pairs.py OUT_DIR [OUT_DIR ...] [--reference OUT_DIR:SYSTEM]

Reads the ``results.jsonl`` of ``slam-gym reproduce victoria-park`` runs (their
``figure.trees_xy``: the confirmed trees at the end) and prints, per system and seed, the trees
mapped and the pairs closer than 1 m and 2 m. A tree trunk seen by the laser is one point feature,
so a pair of mapped trees within a metre is most likely one tree mapped twice (EKF-SLAM's map,
with full covariance and JCBB, has none).

With ``--reference`` (e.g. ``out/vp-ekf:ekf-slam``) each map is also fitted rigidly onto the
reference system's map (iterated closest points: nearest neighbours within 3 m, then the
least-squares rotation and translation, 30 rounds, starting from the identity, as both maps
start at the same pose) and the script prints the share of its trees within 1 m of a reference
tree and the share of the reference's trees within 1 m of one of its trees. No landmark truth
exists on this data set; this measures agreement between systems, not accuracy.

A map that is bent relative to the reference (its heading drifted somewhere along the path) has
no single rigid fit; ``--local-radius R`` (e.g. 40 m) then also fits, for each tree, the trees
within R of it onto the reference by the same iterated closest points (starting from the global
fit) and tests that tree only, in both directions: which trees the two maps share, whatever the
bending.

Supports docs/results/real_data.md, "HYBRID's duplicate trees (issue 16 item 4): fixed by the
lineage term and the small-sample factor".
The command behind it::

    python scripts/archive/vp_close_pairs.py out/vp-ekf out/vp-lineage out/vp-lineage-5-9 out/vp-ss
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

logger = logging.getLogger(__name__)

MATCH_M = 1.0
FIT_GATE_M = 3.0
FIT_ROUNDS = 30


def read_rows(out: str) -> list[dict]:
    path = Path(out) / "results.jsonl"
    if not path.is_file():
        raise ValueError(f"out_dir={out!r}: no results.jsonl there")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def trees_of(row) -> np.ndarray:
    return np.asarray(row["figure"]["trees_xy"], dtype=float).reshape(-1, 2)


def rigid_fit(points, reference) -> np.ndarray:
    """``points`` moved by the rotation and translation that iterated closest points finds onto
    ``reference``."""
    rotation, shift = np.eye(2), np.zeros(2)
    tree = cKDTree(reference)
    for _ in range(FIT_ROUNDS):
        distance, nearest = tree.query(points @ rotation.T + shift)
        close = distance < FIT_GATE_M
        if close.sum() < 3:
            break
        p, q = points[close], reference[nearest[close]]
        p_mean, q_mean = p.mean(axis=0), q.mean(axis=0)
        u, _, vt = np.linalg.svd((p - p_mean).T @ (q - q_mean))
        d = np.sign(np.linalg.det(vt.T @ u.T))
        rotation = vt.T @ np.diag([1.0, d]) @ u.T
        shift = q_mean - p_mean @ rotation.T
    return points @ rotation.T + shift


def locally_matched(points, reference, radius_m) -> np.ndarray:
    """For each of ``points`` (already fitted globally onto ``reference``): is it within 1 m of
    a reference tree after fitting its neighbours within ``radius_m`` rigidly onto the
    reference?"""
    near = cKDTree(points)
    ref_tree = cKDTree(reference)
    matched = np.zeros(len(points), dtype=bool)
    for i, p in enumerate(points):
        neighbours = near.query_ball_point(p, radius_m)
        moved = rigid_fit(points[neighbours], reference)[neighbours.index(i)]
        matched[i] = ref_tree.query(moved)[0] < MATCH_M
    return matched


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dirs", nargs="+")
    parser.add_argument("--reference", default=None, help="OUT_DIR:SYSTEM")
    parser.add_argument("--local-radius", type=float, default=None, metavar="R",
                        help="also match each tree after a rigid fit of its neighbours within R m")
    args = parser.parse_args(argv)
    if args.local_radius is not None and not args.local_radius > 0:
        raise ValueError(f"local_radius={args.local_radius!r}: must be a positive number of m")
    reference = None
    if args.reference is not None:
        out, _, system = args.reference.partition(":")
        rows = [r for r in read_rows(out) if r["system"] == system]
        if not rows:
            raise ValueError(f"reference={args.reference!r}: no {system!r} row in {out}")
        reference = trees_of(rows[0])
    for out in args.out_dirs:
        for row in read_rows(out):
            trees = trees_of(row)
            tree = cKDTree(trees)
            line = (f"{row['system']} seed {row['seed']}: {len(trees)} trees, "
                    f"{len(tree.query_pairs(1.0))} pairs closer than 1 m, "
                    f"{len(tree.query_pairs(2.0))} closer than 2 m")
            if reference is not None and len(trees):
                fitted = rigid_fit(trees, reference)
                ours, _ = cKDTree(reference).query(fitted)
                theirs, _ = cKDTree(fitted).query(reference)
                line += (f"; within {MATCH_M:g} m of the reference's trees "
                         f"{np.mean(ours < MATCH_M):.2f}, reference's trees matched "
                         f"{np.mean(theirs < MATCH_M):.2f}")
                if args.local_radius is not None:
                    ours_local = locally_matched(fitted, reference, args.local_radius)
                    theirs_local = locally_matched(reference, fitted, args.local_radius)
                    line += (f"; fitted within {args.local_radius:g} m: {ours_local.mean():.2f} "
                             f"of its trees, {theirs_local.mean():.2f} of the reference's")
            logger.info("%s", line)
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
