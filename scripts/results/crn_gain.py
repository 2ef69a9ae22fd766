"""What synchronised random numbers buy a paired comparison: the same pairs of policies on the
same worlds with the filter's numbers in one ordered stream (``-v0``) and synchronised (``-v1``).

Usage: python scripts/results/crn_gain.py [--seeds 10] [--seed-start 700]
           [--clutter-levels 0,1,2,3] [--particles 500] [--workers 2] [--out out/crn]

Pairs (issue 46): ``fixed-10s-optimise`` against ``fixed-9s-optimise`` (``fixed-interval`` at 9 s,
optimising after every fusion) and against the shipped ``learned`` model. Each runs through the
benchmark (``slam_gym.evaluation.benchmark``; resumable under ``OUT/<streams>/``) at the price of
compute the shipped model was trained for (10 /s, clip 0.2 s). Per pair and design: the worlds
whose success differs (discordant), the paired mean and standard error of the map error
difference over the worlds where both have one, and the mean absolute difference. Writes
``OUT/crn_gain.md`` and ``.json``; supports docs/RESULTS.md, "Synchronised random numbers".
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import numpy as np

RULE = "fixed-10s-optimise"
PAIRS = (("fixed-10s-optimise", "fixed-9s-optimise"), ("fixed-10s-optimise", "learned"))
DESIGNS = ("ordered", "synchronised")


def policy_factories() -> dict:
    import policies

    return {
        "fixed-10s-optimise": functools.partial(policies.make, "fixed-10s-optimise"),
        "fixed-9s-optimise": functools.partial(policies.make, "fixed-interval", interval_s=9.0,
                                               optimise="every-fusion"),
        "learned": functools.partial(policies.make, "learned"),
    }


def pair_statistics(rows: list[dict], a: str, b: str) -> dict:
    """Discordance and the paired map-error difference of ``b - a`` over their common worlds."""
    by = {(r["policy"], r["clutter_level"], r["seed"]): r for r in rows
          if r.get("status") == "ok"}
    worlds = sorted({(lv, s) for p, lv, s in by if p == a} & {(lv, s) for p, lv, s in by
                                                                if p == b})
    discordant = sum(by[(a, *w)]["success"] != by[(b, *w)]["success"] for w in worlds)
    diffs = np.array([by[(b, *w)]["map_error_m"] - by[(a, *w)]["map_error_m"] for w in worlds
                      if by[(a, *w)].get("map_error_m") is not None
                      and by[(b, *w)].get("map_error_m") is not None])
    n = len(diffs)
    return {"a": a, "b": b, "worlds": len(worlds), "discordant": int(discordant),
            "map_worlds": n,
            "map_diff_mean_m": float(diffs.mean()) if n else None,
            "map_diff_sd_m": float(diffs.std(ddof=1)) if n > 1 else None,
            "map_diff_se_m": float(diffs.std(ddof=1) / np.sqrt(n)) if n > 1 else None,
            "map_diff_mean_abs_m": float(np.abs(diffs).mean()) if n else None,
            "identical_worlds": int(np.sum(diffs == 0.0)) if n else 0}


def table(stats: dict[str, list[dict]]) -> str:
    lines = ["| pair | design | worlds | discordant (success) | map diff mean (m) | paired SD (m) "
             "| paired SE (m) | mean abs diff (m) | identical map errors |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for design in DESIGNS:
        for s in stats.get(design, []):
            def fmt(x):
                return "-" if x is None else f"{x:+.3f}"
            lines.append(f"| {s['b']} - {s['a']} | {design} | {s['worlds']} | {s['discordant']} "
                         f"| {fmt(s['map_diff_mean_m'])} | {fmt(s['map_diff_sd_m'])} "
                         f"| {fmt(s['map_diff_se_m'])} | {fmt(s['map_diff_mean_abs_m'])} "
                         f"| {s['identical_worlds']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    from slam_gym.evaluation import benchmark

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--seed-start", type=int, default=700)
    parser.add_argument("--clutter-levels", default="0,1,2,3")
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--n-steps", type=int, default=None)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("out/crn"))
    args = parser.parse_args(argv)
    levels = [int(v) for v in args.clutter_levels.split(",")]
    stats = {}
    for design in DESIGNS:
        result = benchmark(policy_factories(), clutter_levels=levels, seeds=args.seeds,
                           seed_start=args.seed_start, n_particles=args.particles,
                           n_steps=args.n_steps, w_compute=10.0, compute_clip_s=0.2,
                           random_streams=design, baselines=[], figures=False,
                           out=args.out / design, workers=args.workers, progress=True)
        stats[design] = [pair_statistics(result.rows, a, b) for a, b in PAIRS]
    text = table(stats)
    (args.out / "crn_gain.md").write_text(text)
    (args.out / "crn_gain.json").write_text(json.dumps(stats, indent=2) + "\n")
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
