"""Issue 46's decided comparisons recomputed from their committed rows with the statistics of
issue 56 (the seed as the unit, the map error over the draws both survived), replaying
``slam-gym compare``'s looks batch by batch (:func:`slam_gym.evaluation.compare.look`, then
:func:`~slam_gym.evaluation.compare.report`) without running anything::

    python scripts/results/decided_again.py [--json OUT.json]

Each comparison is replayed as declared (``--draws 2 --metric success --margin 5 --max-worlds
400``, batches of 2 seeds at levels 0-3, its design and ``--seed-start``) on the rows in
``docs/results/issue46/rows/``. The rows end where the original run stopped; a replay that has
not decided by then says so (``rows_end``): the new statistics are more careful, and the worlds
after that point were never run.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from slam_gym.evaluation.results import read_results

logger = logging.getLogger("decided_again")

ROWS = Path(__file__).resolve().parents[2] / "docs" / "results" / "issue46" / "rows"
LEVELS = (0, 1, 2, 3)
BATCH_SEEDS = 2
MAX_WORLDS = 400
COMPARISONS = (
    # (rows folder, A, B, design, seed start)
    ("compare-bb-gsd", "fixed-10s-optimise", "fixed-10s", "group-sequential", 30000),
    ("compare-bb-esdf", "fixed-10s-optimise", "esdf-innovation", "group-sequential", 40000),
    ("compare-bb-learned10", "fixed-10s-optimise", "learned", "group-sequential", 60000),
    ("compare-bb-learned46", "fixed-10s-optimise", "learned", "group-sequential", 70000),
)
REPORTED = ("success", "nees_in_band_fraction", "map_error_m", "return")


def replay(rows: list[dict], a: str, b: str, design: str, seed_start: int, *,
           metric: str = "success", margin: float = 5.0, alpha: float = 0.05) -> dict:
    """compare's looks on ``rows`` (both arms' rows of one comparison) in its batch order."""
    from slam_gym.evaluation.compare import look, report

    rows_a = [r for r in rows if r["policy"] == a]
    rows_b = [r for r in rows if r["policy"] == b]
    seeds_run = {int(r["seed"]) for r in rows_a} & {int(r["seed"]) for r in rows_b}
    n_batches = MAX_WORLDS // (BATCH_SEEDS * len(LEVELS))
    planned = n_batches * BATCH_SEEDS
    worlds: list[tuple[int, int]] = []
    looks: list[dict] = []
    seen: list[int] = []
    rows_end = False
    for batch in range(n_batches):
        seeds = [seed_start + batch * BATCH_SEEDS + i for i in range(BATCH_SEEDS)]
        if not set(seeds) <= seeds_run:
            rows_end = True
            break
        worlds += [(level, seed) for seed in seeds for level in LEVELS]
        entry, seen = look(rows_a, rows_b, worlds, metric, margin, alpha=alpha,
                           planned_seeds=planned, design=design, look_seeds=seen)
        looks.append(entry)
        if entry["decision"] != "undecided":
            break
    metrics, question = report(rows_a, rows_b, worlds, metric, margin, alpha=alpha,
                               planned_seeds=planned, design=design, look_seeds=seen,
                               looks=looks, max_worlds=MAX_WORLDS)
    return {"a": a, "b": b, "design": design, "seed_start": seed_start,
            "decision": looks[-1]["decision"] if looks else "undecided",
            "worlds": len(worlds), "seeds": len(worlds) // len(LEVELS), "rows_end": rows_end,
            "looks": len(seen), "question": question, "metrics": metrics}


def fixed(rows: list[dict], a: str, b: str, alpha: float = 0.05) -> dict:
    """The fixed-sample report on every world both arms ran (the same worlds as the replay's
    stop when the replay decides at the original stop)."""
    from slam_gym.evaluation.compare import report

    rows_a = [r for r in rows if r["policy"] == a]
    rows_b = [r for r in rows if r["policy"] == b]
    worlds = sorted({(int(r["clutter_level"]), int(r["seed"])) for r in rows_a})
    metrics, _ = report(rows_a, rows_b, worlds, None, None, alpha=alpha, planned_seeds=None)
    return metrics


def cell(m: dict, digits: int) -> str:
    if m["difference"] is None or m["ci"] is None:
        return "-"
    return (f"{m['difference']:+.{digits}f} [{m['ci'][0]:+.{digits}f}, "
            f"{m['ci'][1]:+.{digits}f}]")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", default=None, help="also write the replays here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = []
    print("| A | B | answer | worlds (seeds) | success (pp) | NEES in band (pp) | map error (m) "
          "| interface CPU (s) | return | ICC success | effective worlds |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for folder, a, b, design, start in COMPARISONS:
        rows = read_results(ROWS / folder)
        r = replay(rows, a, b, design, start)
        r["fixed_on_all_rows"] = fixed(rows, a, b)
        out.append(r)
        m = r["metrics"]
        answer = r["decision"] + (" (rows end)" if r["rows_end"] and
                                  r["decision"] == "undecided" else "")
        mp = m["map_error_m"]
        print(f"| `{a}` | `{b}` | {answer} | {r['worlds']} ({r['seeds']}) | "
              f"{cell(m['success'], 1)} | {cell(m['nees_in_band_fraction'], 1)} | "
              f"{cell(mp, 2)} over {mp['worlds']} | {cell(m['interface_cpu_s'], 3)} | "
              f"{cell(m['return'], 0)} | "
              f"{m['success']['icc']:.2f} | {m['success']['effective_worlds']:.0f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
