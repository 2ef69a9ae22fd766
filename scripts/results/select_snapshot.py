"""Choose one of a training run's evaluated snapshots under issue 39's limit on interface CPU.

Usage: python scripts/results/select_snapshot.py RUN_DIR --baseline BENCH_OUT [--max-cpu-ratio 2]
           [--out DIR]
e.g.   python scripts/results/select_snapshot.py out/train39/seed-1 \
           --baseline out/train39/baseline-fixed-10s-optimise --out out/select39

``slam-gym train`` evaluates a snapshot of the policy every ``--eval-every`` decisions on the
training-time worlds, in both modes (deterministic and sampled), and keeps each snapshot in
``RUN_DIR/evals/t<decisions>/`` beside its row of ``RUN_DIR/eval.csv``. ``BENCH_OUT`` is the
benchmark of ``fixed-10s-optimise`` on the same worlds at the same price (the
``baseline-fixed-10s-optimise`` directory ``slam-gym train`` writes beside its seeds).

A (snapshot, mode) is eligible when its interface CPU (fusions and optimisations, per episode)
is at most ``--max-cpu-ratio`` times the rule's and its success rate is at least the rule's;
among the eligible, the highest mean return is chosen (success breaks ties). Only training-time
worlds enter the choice. The chosen snapshot is copied to ``DIR/model.zip`` with its
``model.json``, whose ``deterministic`` is set to the chosen mode and which gains ``selection``:
the rule, the rule's figures and every candidate's. Prints the candidates as a table; exits 1 if
none is eligible.

Supports docs/RESULTS.md, round three, "Addendum: a learner chosen under the CPU limit".
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from slam_gym.evaluation.front import interface_cpu_s
from slam_gym.evaluation.results import read_results
from slam_gym.training.evaluation import evaluation_record
from slam_gym.training.run import read_eval_log

MODES = (("deterministic", ""), ("sampled", "sampled_"))


def rule_figures(baseline: Path) -> dict[str, float]:
    """Interface CPU (s), success rate and return of the rule's ok rows in ``baseline``, by the
    same means as the training's evaluations (:func:`evaluation_record`)."""
    rows = [r for r in read_results(baseline) if r.get("status") == "ok"]
    if not rows:
        raise ValueError(f"baseline={str(baseline)!r} is invalid: no ok rows in its results.jsonl")
    record = evaluation_record([dict(r, interface_cpu_s=interface_cpu_s(r)) for r in rows], ())
    return {k: record[k] for k in ("interface_cpu_s", "success_rate", "mean_return", "n_episodes")}


def candidates(run_dir: Path, rule: dict[str, float], max_cpu_ratio: float) -> list[dict]:
    """Every (snapshot, mode) of ``run_dir``'s evaluations with its figures and eligibility."""
    found = []
    for row in read_eval_log(run_dir):
        t = int(row["timesteps"])
        for mode, prefix in MODES:
            if f"{prefix}mean_return" not in row:
                continue
            cpu_ratio = row[f"{prefix}interface_cpu_s"] / rule["interface_cpu_s"]
            success = row[f"{prefix}success_rate"]
            found.append({
                "timesteps": t, "mode": mode, "success_rate": success,
                "mean_return": row[f"{prefix}mean_return"],
                "n_fusions": row[f"{prefix}n_fusions"],
                "n_optimisations": row[f"{prefix}n_optimisations"],
                "interface_cpu_s": row[f"{prefix}interface_cpu_s"], "cpu_ratio": cpu_ratio,
                "eligible": bool(cpu_ratio <= max_cpu_ratio and success >= rule["success_rate"]),
            })
    return found


def choose(found: list[dict]) -> dict | None:
    eligible = [c for c in found if c["eligible"]]
    return max(eligible, key=lambda c: (c["mean_return"], c["success_rate"])) if eligible else None


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR",
                        help="one seed's directory of a slam-gym train output")
    parser.add_argument("--baseline", type=Path, required=True, metavar="BENCH_OUT",
                        help="fixed-10s-optimise's benchmark on the same worlds")
    parser.add_argument("--max-cpu-ratio", type=float, default=2.0)
    parser.add_argument("--out", type=Path, default=Path("out/select"))
    args = parser.parse_args(argv)
    if not args.max_cpu_ratio > 0:
        parser.error(f"max_cpu_ratio={args.max_cpu_ratio!r} is invalid: it must be > 0")
    if not (args.run_dir / "eval.csv").is_file():
        parser.error(f"run_dir={str(args.run_dir)!r} is invalid: it holds no eval.csv")
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    rule = rule_figures(args.baseline)
    found = candidates(args.run_dir, rule, args.max_cpu_ratio)
    chosen = choose(found)
    print(f"fixed-10s-optimise on the same worlds: success {rule['success_rate']:.2f}, return "
          f"{rule['mean_return']:.0f}, interface CPU {rule['interface_cpu_s']:.3f} s")
    print("| decisions | mode | success | return | fusions | optimisations | interface CPU (s) "
          "| CPU ratio | eligible |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---|")
    for c in found:
        mark = " **chosen**" if c is chosen else ""
        print(f"| {c['timesteps']} | {c['mode']} | {c['success_rate']:.2f} | "
              f"{c['mean_return']:.0f} | {c['n_fusions']:.1f} | {c['n_optimisations']:.1f} | "
              f"{c['interface_cpu_s']:.3f} | {c['cpu_ratio']:.2f} | "
              f"{'yes' if c['eligible'] else 'no'}{mark} |")
    if chosen is None:
        print(f"no snapshot has interface CPU <= {args.max_cpu_ratio} times the rule's and its "
              "success", file=sys.stderr)
        return 1
    snapshot = args.run_dir / "evals" / f"t{chosen['timesteps']}" / "model.zip"
    if not (snapshot.is_file() and snapshot.with_suffix(".json").is_file()):
        raise ValueError(f"{snapshot} (or its .json) is missing: the run kept no such snapshot")
    args.out.mkdir(parents=True, exist_ok=True)
    target = args.out / "model.zip"
    shutil.copyfile(snapshot, target)
    config = json.loads(snapshot.with_suffix(".json").read_text())
    config["deterministic"] = chosen["mode"] == "deterministic"
    config["selection"] = {
        "command": "python scripts/results/select_snapshot.py " + " ".join(argv),
        "rule": "highest mean return among the (snapshot, mode) with interface CPU <= "
                f"{args.max_cpu_ratio} times fixed-10s-optimise's and success >= its, on the "
                "training-time worlds",
        "fixed_10s_optimise": rule, "candidates": found, "chosen": chosen,
    }
    target.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
    print(f"chosen: {chosen['timesteps']} decisions, {chosen['mode']}; wrote {target} (+ .json)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
