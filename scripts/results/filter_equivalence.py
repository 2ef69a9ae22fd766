"""Two codes' filters compared by distributions, paired by world and draw (issue 47 item 3).

Usage: python scripts/results/filter_equivalence.py REF.jsonl[,MORE.jsonl] NEW.jsonl[,MORE.jsonl]
       [--resamples 4000] [--seed 0]

Each argument is one or more ``results.jsonl`` of :func:`slam_gym.evaluation.benchmark` (run once
from each checkout on the same worlds, policies, particles and ``draws``; under synchronised
random numbers both codes draw by the same keys, so rows of one (policy, level, seed, draw) are
paired). Per policy, over the pairs both codes finished, it prints the new code minus the
reference with a 95 % interval:

* success (pp): the difference of paired proportions with Agresti and Min's interval for matched
  pairs (Agresti & Min, "Simple improved confidence intervals for comparing matched
  proportions", Stat. Med. 2005: half a pair added to each of the four cells);
* map error (m) of the runs that did not fail, over the pairs in which neither failed: per world
  the mean over its draws, then a bootstrap over worlds stratified by clutter level;
* the fraction of pose NEES inside its band (pp): the same per-world means and bootstrap.

Supports docs/RESULTS.md, "The filter of issue 47 against its reference, by distributions".
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict

import numpy as np

Z95 = 1.959963984540054


def read_rows(spec: str) -> dict:
    """The ok rows of the files ``spec`` names (comma-separated), by (policy, level, seed,
    draw); a later file's row replaces an earlier one's."""
    rows = {}
    for path in spec.split(","):
        with open(path, encoding="utf-8") as f:
            for line in f:
                if not line.strip():
                    continue
                try:
                    row = json.loads(line)
                except json.JSONDecodeError:  # a line a kill cut
                    continue
                if row.get("status", "ok") != "ok" or row.get("error"):
                    continue
                key = (row["policy"], int(row["clutter_level"]), int(row["seed"]),
                       int(row.get("draw", 0)))
                rows[key] = row
    return rows


def agresti_min(ref: np.ndarray, new: np.ndarray) -> tuple[float, float, float]:
    """``new - ref`` of paired 0/1 outcomes and Agresti-Min's 95 % interval."""
    n = len(ref)
    b = float(np.sum(ref & ~new))  # the reference succeeded, the new code failed
    c = float(np.sum(~ref & new))
    diff = (c - b) / n
    m = n + 2.0
    p12, p21 = (b + 0.5) / m, (c + 0.5) / m
    centre = p21 - p12
    half = Z95 * math.sqrt(max((p12 + p21) - centre * centre, 0.0) / m)
    return diff, centre - half, centre + half


def stratified_bootstrap(per_world: dict, resamples: int, rng) -> tuple[float, float, float]:
    """Mean of the per-world differences and its 95 % percentile interval, worlds resampled
    within their clutter level. ``per_world``: {(level, seed): difference}."""
    strata = defaultdict(list)
    for (level, _), d in per_world.items():
        strata[level].append(d)
    values = {level: np.array(ds) for level, ds in strata.items()}
    total = sum(len(v) for v in values.values())
    mean = sum(v.sum() for v in values.values()) / total
    draws = np.zeros(resamples)
    for v in values.values():
        idx = rng.integers(0, len(v), (resamples, len(v)))
        draws += v[idx].sum(axis=1)
    draws /= total
    low, high = np.percentile(draws, [2.5, 97.5])
    return float(mean), float(low), float(high)


def compare(ref: dict, new: dict, policy: str, resamples: int, rng) -> dict:
    keys = sorted(k for k in ref if k[0] == policy and k in new)
    success_ref = np.array([bool(ref[k]["success"]) for k in keys])
    success_new = np.array([bool(new[k]["success"]) for k in keys])
    out = {"policy": policy, "pairs": len(keys),
           "worlds": len({k[1:3] for k in keys}),
           "success_ref": float(success_ref.mean()), "success_new": float(success_new.mean())}
    out["success_diff"] = agresti_min(success_ref, success_new)
    for field, only_successes in (("map_error_m", True), ("nees_in_band_fraction", False)):
        per_world = defaultdict(list)
        for k in keys:
            a, b = ref[k].get(field), new[k].get(field)
            if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
                continue
            if only_successes and not (ref[k]["success"] and new[k]["success"]):
                continue
            per_world[k[1:3]].append((a, b))
        diffs = {w: float(np.mean([b for _, b in v]) - np.mean([a for a, _ in v]))
                 for w, v in per_world.items()}
        out[field + "_worlds"] = len(diffs)
        out[field + "_ref"] = float(np.mean([np.mean([a for a, _ in v])
                                             for v in per_world.values()]))
        out[field + "_diff"] = stratified_bootstrap(diffs, resamples, rng)
    return out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("ref")
    parser.add_argument("new")
    parser.add_argument("--resamples", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    ref, new = read_rows(args.ref), read_rows(args.new)
    rng = np.random.default_rng(args.seed)
    for policy in sorted({k[0] for k in ref} & {k[0] for k in new}):
        r = compare(ref, new, policy, args.resamples, rng)
        s, m, e = r["success_diff"], r["map_error_m_diff"], r["nees_in_band_fraction_diff"]
        print(f"{policy}: {r['pairs']} pairs on {r['worlds']} worlds")
        print(f"  success {100 * r['success_ref']:.1f} % -> {100 * r['success_new']:.1f} %: "
              f"{100 * s[0]:+.1f} pp [{100 * s[1]:+.1f}, {100 * s[2]:+.1f}] (Agresti-Min)")
        print(f"  map error (both succeeded, {r['map_error_m_worlds']} worlds) "
              f"{r['map_error_m_ref']:.3f} m: {m[0]:+.2g} m [{m[1]:+.2g}, {m[2]:+.2g}]")
        print(f"  NEES in band ({r['nees_in_band_fraction_worlds']} worlds) "
              f"{100 * r['nees_in_band_fraction_ref']:.1f} %: {100 * e[0]:+.2g} pp "
              f"[{100 * e[1]:+.2g}, {100 * e[2]:+.2g}]")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
