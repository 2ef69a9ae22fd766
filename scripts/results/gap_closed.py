"""How much of the gap between ``fixed-10s-optimise`` and the lookahead a learned policy closes
(issue 39's goal: "what fraction of the gap between the rule and the lookahead the learner
closes; the stretch aim is half").

Supports docs/RESULTS.md, "Learned interface policies, round three". The declared use::

    python scripts/results/gap_closed.py --front out/front39 --ceiling out/ceiling39 --price 10

reads the learned policy's rows at ``--price`` and the rule's rows of a ``slam-gym front`` output
(``FRONT/learned-<price>``, ``FRONT/rules``) and the rows of ``lookahead_ceiling.py``
(``CEILING/results.jsonl``), keeps the worlds both ran (the ceiling's declared subset), and
pairs each policy with the rule *of its own run* (the ceiling's rule rows were run beside the
lookahead, the front's beside the learner). Per measure: the gap (lookahead minus rule, paired
mean), the learner's paired difference to the rule, and the fraction ``learner / gap`` (reported
only where the gap's interval excludes 0: dividing by a gap indistinguishable from none measures
noise). Map error counts the worlds where both policies of a pair succeeded, lower is better, and
the fraction is taken in the same direction. The lookahead and its privileged bound each get a
table, both in one output (``--lookahead`` chooses), so no run overwrites the other's figures.
Writes ``FRONT/gap_closed.{json,md}``.

``--ceiling`` may instead name a *recorded gap* (a ``.json`` file: the worlds the ceiling ran and,
per planner and measure, its paired gap and interval as reported), for when the ceiling's rows
are no longer there: the learner is then paired with its own run's rule on those worlds and
divided by the recorded gap. ``docs/ceiling39_gap.json`` records RESULTS' round-three ceiling
(its rows were lost with the machine of 2026-11-27)::

    python scripts/results/gap_closed.py --front out/front39 --ceiling docs/ceiling39_gap.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from slam_gym.evaluation.front import compare
from slam_gym.evaluation.results import read_results

REFERENCE = "fixed-10s-optimise"
PLANNERS = ("lookahead", "lookahead-privileged")
MEASURES = (("success_diff_pp", "success_diff_ci_pp", "success (pp)"),
            ("map_error_diff_m", "map_error_diff_ci_m", "map error (m)"),
            ("return_diff", "return_diff_ci", "return"))


def _rows(path: Path) -> list[dict]:
    if not path.is_file():
        raise ValueError(f"rows={str(path)!r} is invalid: no such file")
    return [r for r in read_results(path) if r.get("status") == "ok"]


def _world(row) -> tuple[int, int]:
    return int(row["clutter_level"]), int(row["seed"])


def recorded_gap(path: Path, lookahead: str, price: float) -> tuple[set, dict]:
    """The worlds and the per-measure gaps (``compare``'s keys) of a recorded ceiling."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"ceiling={str(path)!r} is invalid: {exc}") from None
    if float(doc.get("price", float("nan"))) != price:
        raise ValueError(f"price={price:g} is invalid: {path} records the gap at "
                         f"{doc.get('price')} /s")
    planners = doc.get("planners", {})
    if lookahead not in planners:
        raise ValueError(f"lookahead={lookahead!r} is invalid: {path} records {sorted(planners)}")
    worlds = {(int(level), int(seed)) for level, seed in doc["worlds"]}
    gaps = {}
    for key, ci_key, label in MEASURES:
        entry = planners[lookahead][label]
        gaps[key], gaps[ci_key] = float(entry["gap"]), [float(v) for v in entry["gap_ci"]]
    return worlds, gaps


def gap_closed(front: Path, ceiling: Path, price: float, lookahead: str = "lookahead") -> dict:
    recorded = ceiling.suffix == ".json"
    if recorded:
        ceiling_worlds, planned = recorded_gap(ceiling, lookahead, price)
    else:
        ceiling_rows = _rows(ceiling / "results.jsonl")
        planner = [r for r in ceiling_rows if r["policy"] == lookahead]
        ceiling_rule = [r for r in ceiling_rows if r["policy"] == REFERENCE]
        ceiling_worlds = {_world(r) for r in planner} & {_world(r) for r in ceiling_rule}
    learner = _rows(front / f"learned-{price:g}" / "results.jsonl")
    front_rule = [r for r in _rows(front / "rules" / "results.jsonl") if r["policy"] == REFERENCE]
    worlds = {_world(r) for r in learner} & {_world(r) for r in front_rule} & ceiling_worlds
    if not worlds:
        raise ValueError(f"front={str(front)!r} is invalid: no world in common with the ceiling")
    if recorded and worlds != ceiling_worlds:
        # a recorded gap holds for its own worlds only
        raise ValueError(f"front={str(front)!r} is invalid: it ran {len(worlds)} of the "
                         f"{len(ceiling_worlds)} worlds of the recorded gap")

    def keep(rows):
        return [r for r in rows if _world(r) in worlds]

    learned = compare(keep(learner), keep(front_rule), price)
    if not recorded:
        planned = compare(keep(planner), keep(ceiling_rule), price)
    measures = {}
    for key, ci_key, label in MEASURES:
        gap, gap_ci, mine = planned[key], planned[ci_key], learned[key]
        clear = gap_ci is not None and (gap_ci[0] > 0 or gap_ci[1] < 0)
        measures[label] = {
            "gap": gap, "gap_ci": gap_ci, "learner_diff": mine, "learner_ci": learned[ci_key],
            "fraction_closed": mine / gap if clear and gap != 0 and math.isfinite(mine) else None,
        }
    return {"price": price, "n_worlds": len(worlds), "lookahead": lookahead,
            "gap_from": "recorded" if recorded else "rows", "ceiling": str(ceiling),
            "worlds": sorted(worlds), "measures": measures}


def _fmt(value, ci, digits) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    text = f"{value:+.{digits}f}"
    return text + (f" [{ci[0]:+.{digits}f}, {ci[1]:+.{digits}f}]" if ci else "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--front", required=True, help="a `slam-gym front` output directory")
    parser.add_argument("--ceiling", required=True,
                        help="a lookahead_ceiling.py output directory, or a recorded gap (.json)")
    parser.add_argument("--price", type=float, default=10.0)
    parser.add_argument("--lookahead", default=",".join(PLANNERS),
                        help="the planners to measure the gap to, comma-separated (default: "
                             "%(default)s); one table each, all in one output")
    args = parser.parse_args(argv)
    planners = [name.strip() for name in args.lookahead.split(",") if name.strip()]
    if not planners:
        parser.error("lookahead='' is invalid: name at least one planner")
    try:
        docs = [gap_closed(Path(args.front), Path(args.ceiling), args.price, name)
                for name in planners]
    except ValueError as exc:
        parser.error(str(exc))
    lines = []
    for doc in docs:
        source = (f" (the gap as recorded in `{doc['ceiling']}`)"
                  if doc["gap_from"] == "recorded" else "")
        lines += [f"On the {doc['n_worlds']} worlds both ran, price {args.price:g} /s; each "
                  f"policy paired with `{REFERENCE}` of its own run (mean [t 95 %]){source}.",
                  "",
                  f"| measure | gap: `{doc['lookahead']}` - rule | learner - rule | "
                  "fraction closed |", "|---|---:|---:|---:|"]
        for label, m in doc["measures"].items():
            digits = 2 if "map" in label else 0
            fraction = ("-" if m["fraction_closed"] is None
                        else f"{100 * m['fraction_closed']:.0f} %")
            lines.append(f"| {label} | {_fmt(m['gap'], m['gap_ci'], digits)} | "
                         f"{_fmt(m['learner_diff'], m['learner_ci'], digits)} | {fraction} |")
        lines.append("")
    lines.append("A fraction is given only where the gap's interval excludes 0.")
    front = Path(args.front)
    (front / "gap_closed.json").write_text(json.dumps({d["lookahead"]: d for d in docs},
                                                      indent=2) + "\n")
    (front / "gap_closed.md").write_text("\n".join(lines) + "\n")
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
