"""What synchronised random numbers buy a paired comparison: the same pairs of policies on the
same worlds with the filter's numbers in one ordered stream (``-v0``) and synchronised (``-v1``).

Usage: python scripts/results/crn_gain.py [--seeds 10] [--seed-start 700]
           [--clutter-levels 0,1,2,3] [--particles 500] [--workers 2] [--out out/crn]

Pairs (issue 46): ``fixed-10s-optimise`` against ``fixed-9s-optimise`` (``fixed-interval`` at 9 s,
optimising after every fusion) and against the shipped ``learned`` model. Each runs through the
benchmark (``slam_gym.evaluation.benchmark``; resumable under ``OUT/<streams>/``) at the price of
compute the shipped model was trained for (10 /s, clip 0.2 s). Per pair and design: the worlds
whose success differs (discordant), the paired mean and standard error of the map error
difference over the worlds where both have one, and the mean absolute difference. Also, from the
same rows: the shipped ``learned`` model on ``-v1`` against its ``-v0`` self (issue 46 item 1: not
worse by 3 pp on success, by 0.15 m on map error, paired by world with
:mod:`slam_gym.evaluation.paired`'s fixed-sample intervals; the two designs share the worlds, not
the filter's numbers) and each pair restated with ``slam-gym compare``'s statistics on the
``-v1`` rows. Writes ``OUT/crn_gain.md`` and ``.json``; supports docs/RESULTS.md, "Synchronised
random numbers".
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
    """Discordance and the paired map-error difference of ``b - a`` over their common worlds
    (the one pairing, :func:`slam_gym.evaluation.pairing.paired_worlds`: the map error over the
    worlds both survived; before issue 56 this script paired every run with a map error)."""
    from slam_gym.evaluation.pairing import paired_worlds

    rows_a = [r for r in rows if r.get("policy") == a]
    rows_b = [r for r in rows if r.get("policy") == b]
    success = paired_worlds(rows_a, rows_b, "success")
    discordant = int(np.sum(success.a != success.b))
    pairs = paired_worlds(rows_a, rows_b, "map_error_m")
    diffs = pairs.b - pairs.a
    n = len(diffs)
    return {"a": a, "b": b, "worlds": len(success), "discordant": discordant,
            "map_worlds": n, "map_seeds": pairs.n_clusters,
            "map_diff_mean_m": float(diffs.mean()) if n else None,
            "map_diff_sd_m": float(diffs.std(ddof=1)) if n > 1 else None,
            "map_diff_se_m": float(diffs.std(ddof=1) / np.sqrt(n)) if n > 1 else None,
            "map_diff_mean_abs_m": float(np.abs(diffs).mean()) if n else None,
            "identical_worlds": int(np.sum(diffs == 0.0)) if n else 0}


VERSION_MARGINS = {"success": 3.0, "map_error_m": 0.15}
"""The margins the shipped model's -v1 self must hold against its -v0 self (issue 46)."""


def version_check(rows_v0: list[dict], rows_v1: list[dict], policy: str = "learned") -> dict:
    """``policy`` on -v1 (B) against -v0 (A), paired by world: per metric the report of
    ``slam-gym compare`` and, for the margins of :data:`VERSION_MARGINS`, the decision."""
    from slam_gym.evaluation import paired
    from slam_gym.evaluation.compare import UNIT_SCALE, fixed_interval, metric_report, oriented

    a = [r for r in rows_v0 if r.get("policy") == policy]
    b = [r for r in rows_v1 if r.get("policy") == policy]
    worlds = sorted({(r["clutter_level"], r["seed"]) for r in a} & {(r["clutter_level"],
                                                                     r["seed"]) for r in b})
    out = {}
    for metric in ("success", "nees_in_band_fraction", "map_error_m", "interface_cpu_s"):
        report = metric_report(a, b, metric, worlds)
        if metric in VERSION_MARGINS and report["worlds"] >= 2:
            d = oriented(metric, a, b, worlds)
            scale = UNIT_SCALE.get(metric, 1.0)
            interval = fixed_interval(d, metric, 0.95)
            report["margin"] = VERSION_MARGINS[metric]
            report["decision"] = paired.decide(interval.lo, interval.hi,
                                               VERSION_MARGINS[metric] / scale)
        out[metric] = report
    return out


def restated(rows: list[dict], a: str, b: str) -> dict:
    """``slam-gym compare``'s report of ``b`` against ``a`` on one design's rows."""
    from slam_gym.evaluation.compare import METRICS, metric_report

    rows_a = [r for r in rows if r.get("policy") == a]
    rows_b = [r for r in rows if r.get("policy") == b]
    worlds = sorted({(r["clutter_level"], r["seed"]) for r in rows_a})
    return {m: metric_report(rows_a, rows_b, m, worlds) for m in METRICS}


def report_table(title: str, report: dict) -> str:
    lines = [title, "", "| metric | A | B | B - A [95 %] | worlds | decision |",
             "|---|---:|---:|---:|---:|---|"]
    for metric, m in report.items():
        def fmt(x, signed=False):
            return "-" if x is None else (f"{x:+.2f}" if signed else f"{x:.2f}")
        ci = "-" if m["ci"] is None else f"[{m['ci'][0]:+.2f}, {m['ci'][1]:+.2f}]"
        decision = (f"{m['decision']} (margin {m['margin']:g} {m['unit']})"
                    if "decision" in m else "")
        lines.append(f"| {metric} ({m['unit'] or '-'}) | {fmt(m['a'])} | {fmt(m['b'])} | "
                     f"{fmt(m['difference'], True)} {ci} | {m['worlds']} | {decision} |")
    return "\n".join(lines) + "\n"


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
    stats, rows = {}, {}
    for design in DESIGNS:
        env_id = "SlamGym/HybridSLAM-v1" if design == "synchronised" else "SlamGym/HybridSLAM-v0"
        kwargs = {"n_particles": args.particles, "n_steps": args.n_steps, "w_compute": 10.0,
                  "compute_clip_s": 0.2}
        result = benchmark(policy_factories(), env=env_id,
                           env_kwargs={k: v for k, v in kwargs.items() if v is not None},
                           clutter_levels=levels, seeds=args.seeds, seed_start=args.seed_start,
                           baselines=[], figures=False, out=args.out / design,
                           workers=args.workers, progress=True)
        stats[design] = [pair_statistics(result.rows, a, b) for a, b in PAIRS]
        rows[design] = result.rows
    check = version_check(rows["ordered"], rows["synchronised"])
    again = {f"{b} - {a}": restated(rows["synchronised"], a, b) for a, b in PAIRS}
    text = "\n".join([table(stats), report_table(
        "The shipped `learned` on -v1 (B) against its -v0 self (A), paired by world", check),
        *(report_table(f"{pair}, -v1, paired by world", r) for pair, r in again.items())])
    (args.out / "crn_gain.md").write_text(text)
    (args.out / "crn_gain.json").write_text(json.dumps(
        {"pairs": stats, "learned_v1_against_v0": check, "restated_v1": again},
        indent=2, default=float) + "\n")
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
