"""How often a rule's success on a world changes with the filter's random draws alone: the noise
floor of a paired success comparison.

Usage: python scripts/results/filter_noise.py [--policy fixed-10s-optimise] [--seeds 20]
           [--seed-start 600] [--clutter-levels 0,1,2,3] [--draws 3] [--workers 2] [--out DIR]

On each world (BB's path, ``--clutter-levels`` x seeds ``--seed-start`` ..), the policy runs once
as the benchmark runs it (``env.reset(seed=s, options={"world_seed": s})``: draw 0, the row
``slam-gym benchmark`` and ``slam-gym front`` write) and ``--draws`` more times on the same world
(path, landmarks, clutter and measurement noise) with other filter generators
(``env.reset(seed=<derived from s and k>, options={"world_seed": s})``). The rule's discordance
between draws is the scatter a paired success comparison against it meets by chance alone.
Per draw k >= 1 against draw 0: the worlds where only one succeeded, and the paired success
difference with its Student-t 95 % interval, as ``slam-gym front`` computes it.

Rows go to ``DIR/results.jsonl`` (one per world and draw, with the run's options; a rerun skips
the rows there with the same policy and options, and cuts off a partial last line a killed run
left), the table to ``DIR/filter_noise.md``. Supports docs/RESULTS.md, round three, "The noise
floor of the success test".
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from tqdm import tqdm

from slam_gym.evaluation.results import read_results
from slam_gym.evaluation.summary import mean_interval


def filter_reset_seed(world_seed: int, draw: int) -> int:
    """The ``reset`` seed of draw ``draw`` on world ``world_seed`` (draw 0: the world's seed, as
    the benchmark resets)."""
    if draw == 0:
        return int(world_seed)
    return int(np.random.SeedSequence([int(world_seed), int(draw), 104729]).generate_state(1)[0])


def run_options(n_particles: int, w_compute: float, compute_clip_s: float,
                n_steps: int | None) -> dict:
    """The options a row was run with (a rerun reuses only rows with the same)."""
    return {"n_particles": n_particles, "w_compute": w_compute, "compute_clip_s": compute_clip_s,
            "n_steps": n_steps}


def run_one(policy_name: str, clutter_level: int, world_seed: int, draw: int, n_particles: int,
            w_compute: float, compute_clip_s: float, n_steps: int | None) -> dict:
    import policies
    from slam_gym.evaluation.core import run_policy_object

    episode, env = run_policy_object(
        policies.make(policy_name), "brooks-bailey", clutter_level, world_seed,
        n_particles=n_particles, w_compute=w_compute, compute_clip_s=compute_clip_s,
        n_steps=n_steps, filter_reset_seed=filter_reset_seed(world_seed, draw))
    metrics = episode.metrics()
    return {"policy": policy_name, **run_options(n_particles, w_compute, compute_clip_s, n_steps),
            "clutter_level": clutter_level, "seed": world_seed,
            "draw": draw, "success": bool(metrics["success"]),
            "map_error_m": metrics.get("map_error_m"), "n_fusions": metrics.get("n_fusions"),
            "n_optimisations": metrics.get("n_optimisations"),
            "return": float(env.episode_return)}


def discordance(rows: list[dict], draws: int) -> list[dict]:
    """Per draw k >= 1: paired success against draw 0 over the worlds both ran."""
    by = {(r["clutter_level"], r["seed"], r["draw"]): r for r in rows}
    worlds = sorted({(lv, s) for lv, s, _ in by})
    out = []
    for k in range(1, draws + 1):
        pairs = [(by[(lv, s, 0)]["success"], by[(lv, s, k)]["success"]) for lv, s in worlds
                 if (lv, s, 0) in by and (lv, s, k) in by]
        if not pairs:
            continue
        diffs = [100.0 * (int(b) - int(a)) for a, b in pairs]
        ci = mean_interval(diffs)
        out.append({"draw": k, "worlds": len(pairs),
                    "success_draw0": sum(a for a, _ in pairs),
                    "success_draw_k": sum(b for _, b in pairs),
                    "only_draw0": sum(a and not b for a, b in pairs),
                    "only_draw_k": sum(b and not a for a, b in pairs),
                    "diff_pp": float(np.mean(diffs)),
                    "diff_ci_pp": None if ci is None else list(ci)})
    return out


def table(summary: list[dict], policy: str) -> str:
    lines = [f"`{policy}` on the same worlds with other filter draws, against draw 0 (the "
             "benchmark's run)", "",
             "| draw | worlds | successes, draw 0 / this draw | only draw 0 | only this draw "
             "| paired diff (pp) [95 %] |", "|---:|---:|---:|---:|---:|---:|"]
    for s in summary:
        ci = s["diff_ci_pp"]
        ci_text = "-" if ci is None else f"[{ci[0]:+.2f}, {ci[1]:+.2f}]"
        lines.append(f"| {s['draw']} | {s['worlds']} | {s['success_draw0']} / "
                     f"{s['success_draw_k']} | {s['only_draw0']} | {s['only_draw_k']} | "
                     f"{s['diff_pp']:+.2f} {ci_text} |")
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--policy", default="fixed-10s-optimise")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--seed-start", type=int, default=600)
    parser.add_argument("--clutter-levels", default="0,1,2,3")
    parser.add_argument("--draws", type=int, default=3, help="filter draws besides draw 0")
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--w-compute", type=float, default=10.0)
    parser.add_argument("--compute-clip-s", type=float, default=0.2)
    parser.add_argument("--n-steps", type=int, default=None, help="cut every path (quick looks)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("out/filter_noise"))
    args = parser.parse_args(argv)
    for name in ("seeds", "draws", "workers", "particles"):
        if getattr(args, name) < 1:
            parser.error(f"{name}={getattr(args, name)!r} is invalid: it must be >= 1")
    try:
        args.levels = [int(v) for v in args.clutter_levels.split(",")]
    except ValueError:
        parser.error(f"clutter_levels={args.clutter_levels!r} is invalid: integers, e.g. 0,1,2,3")
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "results.jsonl"
    kept = read_results(path)  # a partial last line, left by a kill, is dropped
    path.write_text("".join(json.dumps(r) + "\n" for r in kept))
    wanted = {"policy": args.policy,
              **run_options(args.particles, args.w_compute, args.compute_clip_s, args.n_steps)}
    rows = [r for r in kept if all(r.get(k, "missing") == v for k, v in wanted.items())]
    done = {(r["clutter_level"], r["seed"], r["draw"]) for r in rows}
    todo = [(lv, s, k) for lv in args.levels
            for s in range(args.seed_start, args.seed_start + args.seeds)
            for k in range(args.draws + 1) if (lv, s, k) not in done]
    with ProcessPoolExecutor(args.workers) as pool, path.open("a") as fh:
        futures = [pool.submit(run_one, args.policy, lv, s, k, args.particles, args.w_compute,
                               args.compute_clip_s, args.n_steps) for lv, s, k in todo]
        for future in tqdm(as_completed(futures), total=len(futures), desc="runs"):
            row = future.result()
            rows.append(row)
            fh.write(json.dumps(row) + "\n")
            fh.flush()
    summary = discordance(rows, args.draws)
    text = table(summary, args.policy)
    (args.out / "filter_noise.md").write_text(text)
    (args.out / "filter_noise.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
