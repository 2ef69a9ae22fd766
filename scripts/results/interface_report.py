"""The interface decisions of a benchmark, as docs/RESULTS.md reports them (#13).

Usage: python scripts/results/interface_report.py OUT_DIR [OUT_DIR ...]
e.g.   python scripts/results/interface_report.py out/bench-relative

Reads the ``results.jsonl`` of ``slam-gym benchmark`` runs (rules only: baselines such as dead
reckoning have no decisions and no return) and prints, per rule and clutter level:

* the decisions: success, worlds in which the rule optimised at least once, optimisations per
  episode, map error of the runs that did not fail (mean [t 95 % interval]) and the CPU seconds
  of fusions + optimisations;
* the returns: mean over all, failed and surviving runs;
* paired against ``fixed-10s`` (BB's rule, never optimising) by world, per level and pooled:
  the success difference, the ANEES ratio (geometric mean of the per-world ratios) and, on the
  worlds where both survived, the map error difference (mean [t 95 % interval]) and in how many
  of those worlds it was lower;
* which rules are dominated: per clutter level, the rules no other rule beats on both the map
  error of the runs that did not fail and the CPU of fusions + optimisations (the Pareto figure
  ``pareto_interface.png``), on the map error and the total CPU (``pareto.png``), and with the
  success rate as a third objective;
* the paired check the reward is built for: over every world (clutter level, seed) and every pair
  of rules where one failed and the other survived, how often the failed run's return is the
  higher one (it must be never). Exit status 1 if it ever is.

Supports docs/RESULTS.md, "The front on worlds never used before, and the goal".
The command behind it::

    python scripts/results/interface_report.py out/front27/rules
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from slam_gym.evaluation.summary import mean_interval

logger = logging.getLogger(__name__)


def load_runs(out_dirs) -> list[dict]:
    runs = []
    for out in out_dirs:
        path = Path(out) / "results.jsonl"
        if not path.is_file():
            raise ValueError(f"out_dir={str(out)!r} is invalid: it holds no results.jsonl")
        with path.open() as handle:
            for line in handle:
                row = json.loads(line)
                if row.get("status") == "ok" and row.get("return") is not None and "policy" in row:
                    runs.append(row)
    return runs


def paired_failures(runs) -> tuple[int, int, list[tuple]]:
    """(pairs compared, pairs where the failed run returned more, those pairs)."""
    by_world = defaultdict(list)
    for r in runs:
        by_world[(r["clutter_level"], r["seed"])].append(r)
    n_pairs, bad = 0, []
    for world, rows in sorted(by_world.items()):
        failed = [r for r in rows if not r["success"]]
        survived = [r for r in rows if r["success"]]
        for f in failed:
            for s in survived:
                n_pairs += 1
                if f["return"] >= s["return"]:
                    bad.append((world, f["policy"], f["return"], s["policy"], s["return"]))
    return n_pairs, len(bad), bad


def decisions_table(runs) -> str:
    groups = defaultdict(list)
    for r in runs:
        groups[(r["policy"], r["clutter_level"])].append(r)
    lines = ["| rule | clutter | success | worlds optimised | optimisations | "
             "map error, runs that did not fail (m) | interface CPU (s) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for (name, level), rows in groups.items():
        survived = [r["map_error_m"] for r in rows if r["success"] and r["map_error_m"] is not None]
        if len(survived) > 1:
            ci = mean_interval(survived)
            error = f"{np.mean(survived):.2f} [{ci[0]:.2f}, {ci[1]:.2f}]"
        else:
            error = f"{survived[0]:.2f}" if survived else "–"
        cpu = np.mean([r["fusion_cpu_s"] + r["optimise_cpu_s"] for r in rows])
        lines.append(
            f"| {name} | {level} | {sum(r['success'] for r in rows)}/{len(rows)} | "
            f"{sum(r['n_optimisations'] > 0 for r in rows)}/{len(rows)} | "
            f"{np.mean([r['n_optimisations'] for r in rows]):.1f} | {error} | {cpu:.2f} |"
        )
    return "\n".join(lines)


def _paired(by, name, reference, levels):
    """Per-world differences of ``name`` against ``reference`` over ``levels``: success (all
    worlds), log ANEES (all worlds) and map error (worlds both survived)."""
    from slam_gym.evaluation.pairing import paired_worlds

    success, log_anees, mine, refs = [], [], [], []
    for (n, level, seed), r in by.items():
        ref = by.get((reference, level, seed))
        if n != name or level not in levels or ref is None:
            continue
        success.append(float(r["success"]) - float(ref["success"]))
        log_anees.append(np.log(r["anees"]) - np.log(ref["anees"]))
        mine.append(r)
        refs.append(ref)
    pairs = paired_worlds(refs, mine, "map_error_m")  # the one pairing: worlds both survived
    return success, log_anees, [float(v) for v in pairs.b - pairs.a]


def _interval(values, fmt, scale=1.0):
    if len(values) < 2:
        return "–"
    lo, hi = mean_interval(values) or (np.nan, np.nan)
    return (f"{fmt.format(scale * np.mean(values))} "
            f"[{fmt.format(scale * lo)}, {fmt.format(scale * hi)}]")


def paired_table(runs, reference: str = "fixed-10s") -> str:
    by = {(r["policy"], r["clutter_level"], r["seed"]): r for r in runs}
    names = [n for n in dict.fromkeys(r["policy"] for r in runs) if n != reference]
    levels = sorted({r["clutter_level"] for r in runs})
    lines = [f"| rule | clutter | success minus {reference}'s (pp) | ANEES / {reference}'s "
             "(geometric mean) | worlds both survived | map error minus its (m) | lower in |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for name in names:
        for label, lvls in [(str(lv), [lv]) for lv in levels] + [("all", levels)]:
            success, log_anees, map_error = _paired(by, name, reference, lvls)
            if not success:
                continue
            if len(log_anees) > 1:
                lo, hi = mean_interval(log_anees)
                ratio = f"{np.exp(np.mean(log_anees)):.2f} [{np.exp(lo):.2f}, {np.exp(hi):.2f}]"
            else:
                ratio = "–"
            lines.append(
                f"| {name} | {label} | {_interval(success, '{:+.0f}', 100.0)} | {ratio} | "
                f"{len(map_error)} | {_interval(map_error, '{:+.2f}')} | "
                f"{sum(d < 0 for d in map_error)} |"
            )
    return "\n".join(lines)


def _dominates(a, b) -> bool:
    """``a`` no worse than ``b`` in every (minimised) objective and better in one."""
    return all(x <= y for x, y in zip(a, b, strict=True)) and any(
        x < y for x, y in zip(a, b, strict=True))


def fronts_table(runs) -> str:
    groups = defaultdict(list)
    for r in runs:
        groups[(r["clutter_level"], r["policy"])].append(r)
    levels = sorted({lv for lv, _ in groups})
    lines = ["| clutter | objectives | non-dominated | dominated |", "|---:|---|---|---|"]
    for lv in levels:
        points = {}
        for (level, name), rows in groups.items():
            survived = [r["map_error_m"] for r in rows
                        if r["success"] and r["map_error_m"] is not None]
            if level != lv or not survived:
                continue
            points[name] = {
                "map": float(np.mean(survived)),
                "interface": float(np.mean([r["fusion_cpu_s"] + r["optimise_cpu_s"]
                                            for r in rows])),
                "total": float(np.mean([r["total_cpu_s"] for r in rows])),
                "failure": 1.0 - float(np.mean([r["success"] for r in rows])),
            }
        for label, keys in (("map error, interface CPU", ("map", "interface")),
                            ("map error, total CPU", ("map", "total")),
                            ("map error, interface CPU, success", ("map", "interface", "failure"))):
            vec = {n: tuple(p[k] for k in keys) for n, p in points.items()}
            beaten = {n: sorted(m for m in vec if m != n and _dominates(vec[m], vec[n]))
                      for n in vec}
            front = [n for n in vec if not beaten[n]]
            dominated = [f"{n} (by {', '.join(beaten[n])})" for n in vec if beaten[n]]
            lines.append(f"| {lv} | {label} | {', '.join(front)} | {'; '.join(dominated) or '–'} |")
    return "\n".join(lines)


def returns_table(runs) -> str:
    groups = defaultdict(list)
    for r in runs:
        groups[(r["policy"], r["clutter_level"])].append(r)
    policies = list(dict.fromkeys(r["policy"] for r in runs))
    levels = sorted({r["clutter_level"] for r in runs})
    lines = ["| rule | " + " | ".join(f"level {lv}" for lv in levels) + " |",
             "|---|" + "---:|" * len(levels)]

    def mean(rows):
        return f"{np.mean([r['return'] for r in rows]):.0f}" if rows else "–"

    for name in policies:
        cells = []
        for lv in levels:
            rows = groups[(name, lv)]
            failed = [r for r in rows if not r["success"]]
            survived = [r for r in rows if r["success"]]
            cells.append(f"{mean(rows)} ({mean(failed)} / {mean(survived)}, "
                         f"{len(failed)} failed)")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out_dir", nargs="+", help="slam-gym benchmark --out directories")
    runs = load_runs(parser.parse_args(argv).out_dir)
    n_pairs, n_bad, bad = paired_failures(runs)
    logger.info("decisions per rule and clutter level:\n%s", decisions_table(runs))
    if any(r["policy"] == "fixed-10s" for r in runs):
        logger.info("paired against fixed-10s:\n%s", paired_table(runs))
    logger.info("which rules are dominated (means per clutter level):\n%s", fronts_table(runs))
    logger.info("mean return (failed / surviving runs, failures) per rule and clutter level:\n%s",
                returns_table(runs))
    logger.info("%d runs; %d (failed, surviving) pairs on the same world; the failed run "
                "returned more in %d", len(runs), n_pairs, n_bad)
    for world, fp, fr, sp, sr in bad:
        logger.info("  level %d seed %d: %s failed with %.1f >= %s survived with %.1f",
                    *world, fp, fr, sp, sr)
    return 1 if n_bad else 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(main(sys.argv[1:]))
