"""Round four's learners beside the planners, per zoned task: one figure (issue 58 item 7).

    python scripts/results/round_four_figure.py [--out docs/figures/round_four_learners.png]

Reads the committed ``slam-gym headroom --report-only`` reports of each learner on issue 48's 40
worlds (``docs/results/issue58/gap-*/headroom.json``) and draws, per task, every arm's paired
difference in success to the task's best rule (points, with the reports' 95 % intervals, the
seed the cluster): the learners, ``fixed-10s-optimise``, the lookahead (``lookahead-full``, 4
futures; ``lookahead``, the fast planner) and the privileged bound. Beside each learner its gap
closed to ``lookahead-full`` (point and interval, from the same report), and the bar (half the
gap to ``lookahead-full``, dashed). Nothing is recomputed: the figure shows the reports'
numbers (``arms`` returns them, for a test to check).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results" / "issue58"

#: per task, the learners' reports (label, folder under docs/results/issue58); the first report
#: of a task also gives its planners' and rules' arms (every report of a task holds the same rows
#: of them, issue 48's and issue 57's)
LEARNERS: dict[str, tuple[tuple[str, str], ...]] = {
    "SlamGym/HybridSLAM-Zones-v1": (("DAgger (Learner 1)", "gap-zones"),
                                    ("weighted refit (1b)", "gap-zones-weighted"),
                                    ("PPO (Learner 2)", "gap-zones-rl")),
    "SlamGym/HybridSLAM-ZonesStarved-v1": (("DAgger (Learner 1)", "gap-starved"),
                                           ("PPO (Learner 2)", "gap-starved-rl")),
}
#: the reference arms, in the order drawn, and their labels
REFERENCES = (("fixed-10s-optimise", "fixed-10s-optimise"), ("lookahead-full", "lookahead-full"),
              ("lookahead", "lookahead (fast)"), ("lookahead-privileged", "bound (privileged)"))


def read_report(folder: Path) -> dict:
    path = folder / "headroom.json"
    if not path.is_file():
        raise ValueError(f"report={str(path)!r} is invalid: no such file (a headroom report)")
    return json.loads(path.read_text(encoding="utf-8"))


def arms(task: str, results: Path = RESULTS) -> list[dict]:
    """The arms of ``task`` in drawing order: label, success difference to the best rule and its
    interval (pp), whether a learner, and a learner's gap closed to ``lookahead-full`` (point
    and interval) or None."""
    if task not in LEARNERS:
        raise ValueError(f"task={task!r} is invalid: one of {sorted(LEARNERS)}")
    reports = [(label, read_report(results / folder)) for label, folder in LEARNERS[task]]
    out = [_arm(label, report, "learned") for label, report in reports]
    out += [_arm(label, reports[0][1], policy) for policy, label in REFERENCES]
    return out


def _arm(label: str, report: dict, policy: str) -> dict:
    """One arm of :func:`arms`: ``policy``'s row of ``report``, in points; a learner (the
    report's ``learned``) with its gap closed."""
    mean, lo, hi = report["policies"][policy]["success_diff"]
    arm = {"label": label, "diff_pp": 100 * mean, "ci_pp": (100 * lo, 100 * hi),
           "learner": False, "gap_closed": None, "gap_closed_ci": None}
    if policy == "learned":
        gap = report["gap_closed"]["learned"]["lookahead-full"]
        arm.update(learner=True, gap_closed=gap["point"]["success"],
                   gap_closed_ci=tuple(gap["interval"]["success"]))
    return arm


def best_rule(task: str, results: Path = RESULTS) -> tuple[str, float]:
    """The task's best rule and its success on the 40 worlds."""
    report = read_report(results / LEARNERS[task][0][1])
    label = report["best_rule_label"]
    return label, float(report["policies"][label]["success"])


def draw(out: Path, results: Path = RESULTS) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(LEARNERS)
    fig, axes = plt.subplots(1, len(tasks), figsize=(6.2 * len(tasks), 3.8), sharex=True)
    for ax, task in zip(axes, tasks, strict=True):
        rows = arms(task, results)
        rule, rule_success = best_rule(task, results)
        ys = list(range(len(rows)))[::-1]
        for y, row in zip(ys, rows, strict=True):
            colour = "tab:blue" if row["learner"] else "0.45"
            lo, hi = row["ci_pp"]
            ax.errorbar(row["diff_pp"], y, xerr=[[row["diff_pp"] - lo], [hi - row["diff_pp"]]],
                        fmt="o", color=colour, capsize=3)
            if row["learner"]:
                glo, ghi = row["gap_closed_ci"]
                ax.annotate(f"gap closed {row['gap_closed']:.2f} [{glo:.2f}, {ghi:.2f}]",
                            (hi, y), xytext=(6, 0), textcoords="offset points", va="center",
                            fontsize=8, color=colour)
        ax.axvline(0, color="k", lw=0.8)
        half_gap = 0.5 * next(r["diff_pp"] for r in rows if r["label"] == "lookahead-full")
        ax.axvline(half_gap, color="tab:red", lw=0.8, ls="--")
        ax.set_yticks(ys, [row["label"] for row in rows])
        ax.set_title(f"{task}\nbest rule {rule}: {100 * rule_success:.0f} %", fontsize=9)
        ax.set_xlabel("success against the best rule (pp), 40 worlds, 95 % interval")
        ax.grid(axis="x", alpha=0.3)
    fig.suptitle("Round four (issue 58): learners (blue) against the planners; the bar (red) "
                 "is half the gap to lookahead-full", fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" /
                        "round_four_learners.png")
    args = parser.parse_args(argv)
    print(f"wrote {draw(args.out)}")


if __name__ == "__main__":
    main()
