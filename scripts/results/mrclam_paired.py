"""A learner against a rule on recorded data, paired by robot and filter draw (issue 58 item 5).

    python scripts/results/mrclam_paired.py ROWS_DIR [ROWS_DIR ...] --a RULE --b learned \
        [--out REPORT.json]

Each ``ROWS_DIR`` holds a ``slam-gym benchmark`` of both policies on one robot of
``SlamGym/MRCLAM-v1`` with several filter draws. A recording is one world, so the robot is the
unit: per robot the mean over its draws of each policy and of the paired difference (B - A, the
same draw: the same filter numbers), then across robots the mean difference with a t interval
over the robots (``scipy.stats.t``; with 5 robots, 4 degrees of freedom). The env plays each
recording to its end (``terminate_on_failure`` False), so the map error is over every draw, not
only the surviving ones as in simulation; the surviving draws are counted beside it.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from scipy import stats

METRICS = ("map_error_m", "nees_in_band_fraction", "success", "anees", "interface_cpu_s",
           "n_fusions", "n_optimisations")


def value(row: dict, metric: str) -> float:
    if metric == "interface_cpu_s":
        return float(row["fusion_cpu_s"]) + float(row["optimise_cpu_s"])
    return float(row[metric])


def read_pairs(folder: Path, a: str, b: str) -> tuple[int, dict[int, tuple[dict, dict]]]:
    """The robot of ``folder``'s rows and its pairs by draw."""
    rows = [json.loads(line) for line in (folder / "results.jsonl").read_text().splitlines()
            if line.strip()]
    rows = [r for r in rows if r.get("status", "ok") == "ok"]
    robots = {r["env_kwargs"]["robot"] for r in rows}
    if len(robots) != 1:
        raise ValueError(f"rows_dir={str(folder)!r} is invalid: must hold one robot's rows "
                         f"(found {sorted(robots)})")
    by_draw: dict[int, dict[str, dict]] = {}
    for r in rows:
        by_draw.setdefault(int(r["draw"]), {})[r["policy"]] = r
    pairs = {d: (p[a], p[b]) for d, p in by_draw.items() if a in p and b in p}
    return robots.pop(), pairs


def report(folders: list[Path], a: str, b: str) -> dict:
    per_robot = []
    for folder in folders:
        robot, pairs = read_pairs(folder, a, b)
        entry = {"robot": robot, "draws": len(pairs),
                 "survived_a": sum(bool(p[0]["success"]) for p in pairs.values()),
                 "survived_b": sum(bool(p[1]["success"]) for p in pairs.values())}
        for m in METRICS:
            va = np.array([value(p[0], m) for p in pairs.values()])
            vb = np.array([value(p[1], m) for p in pairs.values()])
            entry[m] = {"a": float(va.mean()), "b": float(vb.mean()),
                        "b_minus_a": float((vb - va).mean())}
        per_robot.append(entry)
    per_robot.sort(key=lambda e: e["robot"])
    overall = {}
    for m in METRICS:
        d = np.array([e[m]["b_minus_a"] for e in per_robot])
        n = len(d)
        half = (stats.t.ppf(0.975, n - 1) * d.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
        overall[m] = {"a": float(np.mean([e[m]["a"] for e in per_robot])),
                      "b": float(np.mean([e[m]["b"] for e in per_robot])),
                      "b_minus_a": float(d.mean()), "ci95": [float(d.mean() - half),
                                                             float(d.mean() + half)]}
    return {"a": a, "b": b, "unit": "robot (draws nested)", "robots": len(per_robot),
            "per_robot": per_robot, "overall": overall}


def markdown(rep: dict) -> str:
    lines = [f"A = `{rep['a']}`, B = `{rep['b']}`; per robot the mean over its draws, "
             "B - A paired by draw; the interval a t interval over the robots.", "",
             "| robot | draws | survived A / B | map error A -> B (m) | NEES in band A -> B | "
             "interface CPU A -> B (s) | fusions A / B | optimisations A / B |",
             "|---|---|---|---|---|---|---|---|"]
    for e in rep["per_robot"]:
        lines.append(
            f"| {e['robot']} | {e['draws']} | {e['survived_a']} / {e['survived_b']} | "
            f"{e['map_error_m']['a']:.2f} -> {e['map_error_m']['b']:.2f} | "
            f"{e['nees_in_band_fraction']['a']:.1%} -> {e['nees_in_band_fraction']['b']:.1%} | "
            f"{e['interface_cpu_s']['a']:.2f} -> {e['interface_cpu_s']['b']:.2f} | "
            f"{e['n_fusions']['a']:.1f} / {e['n_fusions']['b']:.1f} | "
            f"{e['n_optimisations']['a']:.1f} / {e['n_optimisations']['b']:.1f} |")
    o = rep["overall"]
    for m, scale, unit in (("map_error_m", 1, " m"), ("nees_in_band_fraction", 100, " pp"),
                           ("success", 100, " pp"), ("interface_cpu_s", 1, " s")):
        lo, hi = o[m]["ci95"]
        lines.append(f"\n{m}: B - A {scale * o[m]['b_minus_a']:+.2f}{unit} "
                     f"[{scale * lo:+.2f}, {scale * hi:+.2f}] over {rep['robots']} robots")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rows_dirs", nargs="+", type=Path)
    parser.add_argument("--a", required=True, help="the rule's policy name in the rows")
    parser.add_argument("--b", default="learned", help="the learner's policy name in the rows")
    parser.add_argument("--out", type=Path, default=None, help="REPORT.json (+ .md beside it)")
    args = parser.parse_args()
    rep = report(args.rows_dirs, args.a, args.b)
    text = markdown(rep)
    if args.out:
        args.out.write_text(json.dumps(rep, indent=2) + "\n")
        args.out.with_suffix(".md").write_text(text)
    print(text, end="")


if __name__ == "__main__":
    main()
