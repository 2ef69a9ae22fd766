"""Two codes' filters compared by distributions, paired by world and draw (issue 47 item 3).

Usage: python scripts/results/filter_equivalence.py REF.jsonl[,MORE.jsonl] NEW.jsonl[,MORE.jsonl]
       [--margins success=3,map_error_m=0.15,nees_in_band_fraction=2] [--json OUT.json]

Each argument is one or more ``results.jsonl`` of :func:`slam_gym.evaluation.benchmark` (run once
from each checkout on the same worlds, policies, particles and ``draws``; under synchronised
random numbers both codes draw by the same keys, so the rows of one (policy, clutter level, seed,
draw) are a pair). Only the runs both codes finished enter. Per policy, the reference is arm A
and the new code arm B of ``slam-gym compare``'s statistics
(:func:`slam_gym.evaluation.compare.metric_report`: per world the mean over its draws, the seed
the cluster; success by the cluster Bonett-Price interval, the other metrics by the cluster
bootstrap over seeds), and each metric with a margin gets
:func:`slam_gym.evaluation.paired.decide`'s answer to "is the new code not worse than the
reference by more than the margin?" on its fixed-sample 95 % interval: a non-inferiority
answer, not equivalence (that would take the two one-sided tests at both margins).

The default margins are issue 47's: success 3 pp, map error 0.15 m, the fraction of pose NEES
inside its band 2 pp. With no discordant world at all, the success interval's half-width is
``t_{0.975, G-1} sqrt(2 G / (G - 1)) / (n + 2)`` (G seeds, n worlds; issue 56): with four
levels a seed, below 3 pp from 25 seeds (100 worlds) on, so fewer cannot show non-inferiority
at 3 pp on success however alike the codes are (before issue 56, ``1.96 sqrt(2) / (n + 2)``:
91 worlds).

Supports docs/RESULTS.md, "The filter of issue 47 against its reference, by distributions".
"""

from __future__ import annotations

import argparse
import json
import sys

from slam_gym.evaluation import paired
from slam_gym.evaluation.compare import metric_report

REPORTED = ("success", "nees_in_band_fraction", "anees", "map_error_m", "interface_cpu_s")
"""The metrics printed per policy (those with a margin are decided)."""

DEFAULT_MARGINS = {"success": 3.0, "map_error_m": 0.15, "nees_in_band_fraction": 2.0}
"""Issue 47's margins, in the metrics' reported units (pp, m, pp)."""


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


def parse_margins(text: str) -> dict[str, float]:
    """``metric=value,...`` -> {metric: value} (``ValueError`` naming ``--margins``)."""
    margins = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        metric, _, value = item.partition("=")
        if metric not in REPORTED or paired.metric_direction(metric) == 0 or not value:
            raise ValueError(f"--margins {text!r} is invalid: each item is METRIC=VALUE with "
                             f"METRIC one of success, nees_in_band_fraction, map_error_m, "
                             f"interface_cpu_s")
        margins[metric] = float(value)
        if not margins[metric] >= 0:
            raise ValueError(f"--margins {text!r} is invalid: {metric}'s margin must be >= 0")
    return margins


def compare_codes(ref: dict, new: dict, policy: str, margins: dict[str, float]) -> dict:
    """One policy's report: pairs, worlds and per metric compare's report of new - reference,
    with ``decision`` where ``margins`` names the metric."""
    keys = sorted(k for k in ref if k[0] == policy and k in new)
    worlds = sorted({(k[1], k[2]) for k in keys})
    rows_ref, rows_new = [ref[k] for k in keys], [new[k] for k in keys]
    out = {"policy": policy, "pairs": len(keys), "worlds": len(worlds), "metrics": {}}
    for metric in REPORTED:
        report = metric_report(rows_ref, rows_new, metric, worlds)
        if metric in margins and report["ci"] is not None:
            lo, hi = report["ci"]
            if paired.metric_direction(metric) < 0:  # oriented: positive = the new code better
                lo, hi = -hi, -lo
            report["margin"] = margins[metric]
            report["decision"] = paired.decide(lo, hi, margins[metric])
        out["metrics"][metric] = report
    return out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("ref", help="the reference code's results.jsonl (comma-separated: several)")
    parser.add_argument("new", help="the new code's results.jsonl (comma-separated: several)")
    parser.add_argument("--margins", default=",".join(f"{k}={v:g}"
                                                      for k, v in DEFAULT_MARGINS.items()),
                        help="non-inferiority margins, METRIC=VALUE,... in reported units "
                        "(default issue 47's: %(default)s)")
    parser.add_argument("--json", default=None, metavar="OUT", help="also write the reports")
    args = parser.parse_args(argv)
    try:
        margins = parse_margins(args.margins)
    except ValueError as exc:
        parser.error(str(exc))
    ref, new = read_rows(args.ref), read_rows(args.new)
    reports = [compare_codes(ref, new, policy, margins)
               for policy in sorted({k[0] for k in ref} & {k[0] for k in new})]
    for r in reports:
        print(f"{r['policy']}: {r['pairs']} pairs on {r['worlds']} worlds (new - reference)")
        for metric, m in r["metrics"].items():
            if m["ci"] is None:
                print(f"  {metric}: too few worlds")
                continue
            verdict = (f"  -> {m['decision']} at {m['margin']:g} {m['unit']}"
                       if "decision" in m else "")
            print(f"  {metric} ({m['worlds']} worlds): {m['a']:.4g} -> {m['b']:.4g} {m['unit']}, "
                  f"{m['difference']:+.3g} [{m['ci'][0]:+.3g}, {m['ci'][1]:+.3g}]{verdict}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(reports, f, indent=2, sort_keys=True)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
