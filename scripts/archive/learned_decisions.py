"""When an interface policy fuses and optimises, over several worlds (#15: "whether the learned
policy uses the optimise action, and when").

Usage: python scripts/archive/learned_decisions.py [POLICY] [SEED_START] [N_SEEDS] [LEVELS]
e.g.   python scripts/archive/learned_decisions.py learned 100 5 0,1,2,3

Plays POLICY (default ``learned``: the shipped model) on ``SlamGym/HybridSLAM-v0`` worlds
SEED_START..SEED_START+N_SEEDS-1 at each clutter level (the benchmark's worlds and seeds, so the
episodes are the benchmark's) and prints per episode, then pooled:

* fusions and optimisations per episode;
* *redundant* optimisations: those with no fusion since the previous optimisation (the stored
  sub-maps and associations are unchanged, so the optimum is the one already applied:
  ``tests/filters/test_submap_optimise.py::test_optimising_twice_changes_nothing``, and in the
  env an extra optimisation after each one changes no observation but ``time_since_optimise_s``,
  docs/RESULTS.md);
* optimisations that follow a fusion in the same decision, and those after the true loop
  closure;
* the reward's compute term over the episode (modelled seconds, ``w_compute`` = 1 /s at the
  defaults) against the episode's return;
* whether the policy acts in turns: the rate of fusions and of optimisations per decision in
  the decisions whose interval turned faster than ``TURN_RADPS`` (mean odometry turn rate)
  against the rate in the others.

Supports docs/results/history.md, "Learned interface policies (issue 15)".
The command behind it::

    python scripts/archive/learned_decisions.py learned 100 5 0,1,2,3
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np

import policies
from slam_gym.evaluation.timeline import decision_timeline

logger = logging.getLogger(__name__)
TURN_RADPS = 0.2
"""A decision interval turning faster than this on average counts as a turn."""


def interval_turn_rates(stream, t_s) -> np.ndarray:
    """Mean absolute odometry turn rate (rad/s) over each decision's interval (up to ``t_s``)."""
    steps = [s for s in stream if s.dt_s > 0.0]
    t = np.array([s.t_s for s in steps])
    turn = np.abs(np.array([s.odometry[1] for s in steps]))
    edges = np.searchsorted(t, np.concatenate([[-np.inf], t_s]), side="right")
    bounds = zip(edges[:-1], edges[1:], strict=True)
    return np.array([turn[a:b].mean() if b > a else 0.0 for a, b in bounds])


def decision_counts(timeline, turn_rates) -> dict[str, float]:
    fused = np.asarray(timeline["fused"], bool)
    optimised = np.asarray(timeline["optimised"], bool)
    t = np.asarray(timeline["t_s"], float)
    redundant, fused_since = 0, False
    for f, o in zip(fused, optimised, strict=True):
        fused_since |= bool(f)
        if o:
            redundant += not fused_since
            fused_since = False
    closure = timeline["true_loop_closure_s"]
    n_opt = int(optimised.sum())
    return {
        "fusions": int(fused.sum()),
        "optimisations": n_opt,
        "redundant": redundant,
        "with_fusion": int((optimised & fused).sum()),
        "after_closure": int((optimised & (t >= closure)).sum()) if closure is not None else 0,
        "turning_decisions": int((turn_rates > TURN_RADPS).sum()),
        "fusions_turning": int((fused & (turn_rates > TURN_RADPS)).sum()),
        "optimisations_turning": int((optimised & (turn_rates > TURN_RADPS)).sum()),
        "decisions": len(t),
        "end_s": float(timeline["end_s"]),
        "failed": bool(timeline["failed"]),
        "closure_s": closure,
    }


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("policy", nargs="?", default="learned")
    parser.add_argument("seed_start", nargs="?", type=int, default=100)
    parser.add_argument("n_seeds", nargs="?", type=int, default=5)
    parser.add_argument("levels", nargs="?", default="0,1,2,3")
    args = parser.parse_args(argv)
    name, seed_start, n_seeds = args.policy, args.seed_start, args.n_seeds
    levels = [int(x) for x in args.levels.split(",")]
    rows = []
    for level in levels:
        for seed in range(seed_start, seed_start + n_seeds):
            policy = policies.make(name)
            timeline, _, env = decision_timeline(policy, "SlamGym/HybridSLAM-v1", level, seed)
            turn_rates = interval_turn_rates(env.stream, np.asarray(timeline["t_s"]))
            row = decision_counts(timeline, turn_rates) | {
                "level": level, "seed": seed,
                "compute_s": float(np.sum(timeline["compute_s"])),
                "return": float(env.unwrapped.episode_return)}
            rows.append(row)
            closure = "-" if row["closure_s"] is None else f"{row['closure_s']:.0f} s"
            logger.info(
                "level %d seed %d: %s at %.0f s, %d fusions, %d optimisations (%d redundant, "
                "%d with a fusion, %d after the loop closure at %s); compute term %.1f s of a "
                "return of %.0f", level, seed,
                "failed" if row["failed"] else "ended", row["end_s"], row["fusions"],
                row["optimisations"], row["redundant"], row["with_fusion"],
                row["after_closure"], closure, row["compute_s"], row["return"])
    n_opt = sum(r["optimisations"] for r in rows)
    logger.info(
        "%s, %d episodes: %.1f fusions and %.1f optimisations per episode; of the optimisations "
        "%.0f %% redundant (no fusion since the previous one), %.0f %% in the decision of a "
        "fusion; %d of %d episodes reached the loop closure, %.0f %% of all optimisations "
        "after it", name, len(rows), np.mean([r["fusions"] for r in rows]),
        np.mean([r["optimisations"] for r in rows]),
        100 * sum(r["redundant"] for r in rows) / max(n_opt, 1),
        100 * sum(r["with_fusion"] for r in rows) / max(n_opt, 1),
        sum(r["closure_s"] is not None and r["end_s"] >= r["closure_s"] for r in rows), len(rows),
        100 * sum(r["after_closure"] for r in rows) / max(n_opt, 1))
    logger.info("compute term %.1f s per episode (mean), return %.0f per episode (mean)",
                np.mean([r["compute_s"] for r in rows]), np.mean([r["return"] for r in rows]))
    turning = sum(r["turning_decisions"] for r in rows)
    straight = sum(r["decisions"] for r in rows) - turning
    for what in ("fusions", "optimisations"):
        in_turns = sum(r[f"{what}_turning"] for r in rows)
        total = sum(r[what] for r in rows)
        logger.info("%s per decision: %.2f in turns (%d decisions turning faster than %.1f "
                    "rad/s), %.2f elsewhere (%d decisions)", what, in_turns / max(turning, 1),
                    turning, TURN_RADPS, (total - in_turns) / max(straight, 1), straight)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
