"""The ceiling of the interface decisions (issue 39 item 1): the lookahead policy and its
privileged bound against ``fixed-10s-optimise`` on the same worlds, paired world by world.

Supports docs/RESULTS.md, "Learned interface policies, round three": "The ceiling". The
declared run::

    python scripts/results/lookahead_ceiling.py --seeds 10 --seed-start 500 --workers 2 \
        --out out/ceiling39

Runs ``fixed-10s-optimise``, ``lookahead`` and ``lookahead-privileged`` (default options:
:mod:`slam_gym.lookahead`; issue 39's rows were made with the full planner, which is
``lookahead-full`` since issue 57: pass ``--policies`` with it to repeat them) through
:func:`slam_gym.evaluation.benchmark` at the price
``--price`` with ``--compute-clip-s`` (the reward the learned policies are trained for), on
seeds ``--seed-start`` ... at clutter levels ``--clutter-levels``, 500 particles; resumable (a
rerun with the same ``--out`` keeps the finished runs). Writes ``OUT/ceiling.json`` and
``OUT/ceiling.md``: success, map error, interface CPU, return and the planning CPU of each
policy, each paired with ``fixed-10s-optimise`` (:func:`slam_gym.evaluation.front.compare`).
Exits 1 if any run errored.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from slam_gym.evaluation import benchmark
from slam_gym.evaluation.front import compare

REFERENCE = "fixed-10s-optimise"
POLICIES = (REFERENCE, "lookahead", "lookahead-privileged")


def _ci(values, digits=0, scale=1.0) -> str:
    if values is None:
        return "-"
    lo, hi = values
    return f"[{lo * scale:+.{digits}f}, {hi * scale:+.{digits}f}]"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=10, help="worlds per clutter level")
    parser.add_argument("--seed-start", type=int, default=500)
    parser.add_argument("--clutter-levels", default="0,1,2,3")
    parser.add_argument("--price", type=float, default=10.0, help="w_compute (/s)")
    parser.add_argument("--compute-clip-s", type=float, default=0.2)
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--n-steps", type=int, default=None, help="cut every path (quick looks)")
    parser.add_argument("--policies", default=",".join(POLICIES),
                        help=f"policy names (must include {REFERENCE})")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default="out/ceiling39")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    names = [n.strip() for n in args.policies.split(",") if n.strip()]
    if REFERENCE not in names:
        parser.error(f"--policies must include {REFERENCE}")
    levels = [int(v) for v in args.clutter_levels.split(",") if v.strip()]
    out = Path(args.out)
    result = benchmark(
        names, env_kwargs={k: v for k, v in (
            ("n_particles", args.particles), ("n_steps", args.n_steps), ("w_compute", args.price),
            ("compute_clip_s", args.compute_clip_s)) if v is not None},
        clutter_levels=levels, seeds=args.seeds, seed_start=args.seed_start,
        baselines=[], out=out, workers=args.workers,
        executor="process" if args.workers > 1 else "serial", figures=False, progress=True,
    )
    errors = [r for r in result.rows if r.get("status") != "ok"]
    ok = [r for r in result.rows if r.get("status") == "ok"]
    by_policy = {name: [r for r in ok if r["policy"] == name] for name in names}
    reference = by_policy[REFERENCE]
    doc = {"price": args.price, "compute_clip_s": args.compute_clip_s, "seeds": args.seeds,
           "seed_start": args.seed_start, "clutter_levels": levels, "policies": {}}
    lines = [
        f"Paired with `{REFERENCE}` on {len(reference)} worlds (seeds {args.seed_start}-"
        f"{args.seed_start + args.seeds - 1} at levels {args.clutter_levels}), price "
        f"{args.price:g} /s, compute clip {args.compute_clip_s:g} s.",
        "",
        "| policy | success | vs rule (pp) | map error (m) | paired diff (m) | interface CPU (s) "
        "| CPU ratio | planning CPU (s/episode) | fusions | optimisations | deviations "
        "| return | paired diff |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name in names:
        rows = by_policy[name]
        if len(rows) != len(reference):
            lines.append(f"| {name} | incomplete: {len(rows)} of {len(reference)} worlds |")
            continue
        c = compare(rows, reference, args.price)
        planning = float(np.mean([r.get("planning_cpu_s", 0.0) for r in rows]))
        deviations = float(np.mean([r.get("deviations_from_base", 0) for r in rows]))
        c |= {"planning_cpu_s": planning, "deviations_from_base": deviations}
        doc["policies"][name] = c
        lines.append(
            f"| {name} | {100 * c['success_rate']:.0f} % | "
            f"{c['success_diff_pp']:+.0f} {_ci(c['success_diff_ci_pp'])} | "
            f"{c['map_error_m']:.2f} | "
            + (f"{c['map_error_diff_m']:+.2f} {_ci(c['map_error_diff_ci_m'], 2)}"
               if c.get("map_error_diff_ci_m") else "-")
            + f" | {c['interface_cpu_s']:.2f} | {c['interface_cpu_ratio']:.2f} | {planning:.1f} | "
            f"{c['n_fusions']:.0f} | {c['n_optimisations']:.0f} | {deviations:.1f} | "
            f"{c['mean_return']:.0f} | {c['return_diff']:+.0f} {_ci(c['return_diff_ci'])} |"
        )
    if errors:
        lines.append(f"\n{len(errors)} runs errored: " + ", ".join(
            f"{r['policy']} level {r['clutter_level']} seed {r['seed']}" for r in errors[:10]))
    out.mkdir(parents=True, exist_ok=True)
    (out / "ceiling.json").write_text(json.dumps(doc, indent=2) + "\n")
    (out / "ceiling.md").write_text("\n".join(lines) + "\n")
    sys.stdout.write("\n".join(lines) + "\n")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
