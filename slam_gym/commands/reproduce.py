"""``slam-gym reproduce``: the papers' experiments (BB Table 1 and Figs. 3-4; CM IV)."""

from __future__ import annotations

import json

import numpy as np

from slam_gym.commands.common import emit, out_dir
from slam_gym.commands.runs import (
    add_run_options,
    errors_exit_code,
    execute,
    int_list,
    name_list,
    plot_episode_map,
    print_table,
)

#: BB Table 1, success rates per clutter level (BB 5.3)
BB_TABLE1 = {
    "fastslam": {0: 0.0, 1: 0.0, 2: 0.0, 3: 0.0},
    "ekf-submap": {0: 0.79, 1: 0.76, 2: 0.72, 3: 0.30},
    "hybrid": {0: 0.87, 1: 0.89, 2: 0.83, 3: 0.63},
}
#: the names BB uses for its three filters -> our systems (plus the dead-reckoning baseline)
BB_SYSTEMS = {"fastslam": "fastslam", "ekf": "ekf-submap", "hybrid": "hybrid",
              "dead-reckoning": "dead-reckoning"}
#: Student t quantiles (0.975) for small paired samples; the normal 1.96 beyond the table
_T975 = {1: 12.71, 2: 4.30, 3: 3.18, 4: 2.78, 5: 2.57, 6: 2.45, 7: 2.36, 8: 2.31, 9: 2.26,
         10: 2.23, 12: 2.18, 15: 2.13, 20: 2.09, 25: 2.06, 30: 2.04, 40: 2.02, 60: 2.00}


def _t975(dof: int) -> float:
    if dof < 1:
        return float("nan")
    known = [d for d in sorted(_T975) if d <= dof]
    return _T975[known[-1]] if dof <= 60 else 1.96


def mean_ci95(values) -> dict:
    """Mean and its t-based 95 % interval (None where fewer than 2 values)."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if len(v) == 0:
        return {"n": 0, "mean": None, "ci95": None}
    mean = float(v.mean())
    if len(v) < 2:
        return {"n": 1, "mean": mean, "ci95": None}
    half = _t975(len(v) - 1) * float(v.std(ddof=1)) / np.sqrt(len(v))
    return {"n": int(len(v)), "mean": mean, "ci95": [mean - half, mean + half]}


def _inside(value, interval):
    """Whether ``value`` lies in the closed ``interval`` (None without a value)."""
    return None if value is None else bool(interval[0] <= value <= interval[1])


def bb_table(rows, first="hybrid", second="ekf-submap") -> dict:
    """BB Table 1 as a reviewer would ask (#14): per system, existence model and clutter level the
    success rate (Wilson 95 %), ANEES, map error, map completeness; and per level and existence
    model the paired ``first - second`` differences (same worlds: seeds in both) in success and
    map error with t-based 95 % intervals. Only rows with status ok count."""
    from slam_gym.evaluation.summary import wilson_interval

    ok = [r for r in rows if r.get("status") == "ok" and r.get("system")]
    groups: dict[tuple, list] = {}
    for r in ok:
        model = (r.get("options") or {}).get("existence_model", "gate")
        if r["system"] == "dead-reckoning":
            model = "-"
        groups.setdefault((r["system"], model, r["clutter_level"]), []).append(r)
    table = []
    order = ["dead-reckoning", "fastslam", "ekf-submap", "hybrid"]
    for (system, model, level), members in sorted(groups.items(), key=lambda kv: (
            order.index(kv[0][0]) if kv[0][0] in order else len(order), kv[0][1], kv[0][2])):
        n_success = sum(1 for r in members if r.get("success") is True)
        def mean_of(key, members=members):
            return mean_ci95([r.get(key) for r in members])["mean"]
        table.append({
            "system": system, "existence_model": model, "clutter_level": level,
            "n": len(members), "n_success": n_success,
            "success_rate": n_success / len(members),
            "success_ci95": list(wilson_interval(n_success, len(members))),
            "paper_success_rate": BB_TABLE1.get(system, {}).get(level),
            "paper_inside_ci95": _inside(BB_TABLE1.get(system, {}).get(level),
                                         wilson_interval(n_success, len(members))),
            "anees": mean_of("anees"), "map_error_m": mean_of("map_error_m"),
            "map_completeness": mean_of("map_completeness"),
        })
    paired = []
    models = sorted({k[1] for k in groups if k[1] != "-"})
    levels = sorted({k[2] for k in groups})
    for model in models:
        for level in levels:
            a = {r["seed"]: r for r in groups.get((first, model, level), [])}
            b = {r["seed"]: r for r in groups.get((second, model, level), [])}
            seeds = sorted(set(a) & set(b))
            if not seeds:
                continue
            d_success = [float(a[s]["success"] is True) - float(b[s]["success"] is True)
                         for s in seeds]
            d_map = [a[s]["map_error_m"] - b[s]["map_error_m"] for s in seeds
                     if a[s].get("map_error_m") is not None and b[s].get("map_error_m") is not None]
            paired.append({
                "existence_model": model, "clutter_level": level, "n_worlds": len(seeds),
                "success_difference": mean_ci95(d_success),
                "map_error_difference_m": mean_ci95(d_map),
            })
    pooled = []
    for model in models:
        d_success = []
        for level in levels:
            a = {r["seed"]: r for r in groups.get((first, model, level), [])}
            b = {r["seed"]: r for r in groups.get((second, model, level), [])}
            d_success += [float(a[s]["success"] is True) - float(b[s]["success"] is True)
                          for s in sorted(set(a) & set(b))]
        if d_success and len([p for p in paired if p["existence_model"] == model]) > 1:
            pooled.append({"existence_model": model, "n_pairs": len(d_success),
                           "success_difference": mean_ci95(d_success)})
    return {"difference": f"{first} - {second}, paired by world (seed)", "rows": table,
            "paired": paired, "pooled": pooled}


def bb_table_markdown(doc: dict) -> str:
    def pct(x):
        return "-" if x is None else f"{100 * x:.0f} %"

    def num(x, d=2):
        return "-" if x is None else f"{x:.{d}f}"

    def ci(c, scale=1.0, d=0):
        return "-" if c is None else f"[{scale * c[0]:.{d}f}, {scale * c[1]:.{d}f}]"

    inside = {None: "", True: " (inside)", False: " (outside)"}
    lines = ["| system | existence | level | n | success [Wilson 95 %] | BB | ANEES "
             "| map error (m) | completeness |", "|---|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        lines.append(
            f"| {r['system']} | {r['existence_model']} | {r['clutter_level']} | {r['n']} | "
            f"{pct(r['success_rate'])} {ci(r['success_ci95'], 100)} | "
            f"{pct(r['paper_success_rate'])}{inside[r['paper_inside_ci95']]} | "
            f"{num(r['anees'])} | {num(r['map_error_m'])} | "
            f"{pct(r['map_completeness'])} |"
        )
    lines += ["", f"Paired differences ({doc['difference']}), mean [t 95 % CI]:", "",
              "| existence | level | worlds | success difference | map error difference (m) |",
              "|---|---|---|---|---|"]
    for p in doc["paired"]:
        s, m = p["success_difference"], p["map_error_difference_m"]
        lines.append(
            f"| {p['existence_model']} | {p['clutter_level']} | {p['n_worlds']} | "
            f"{num(None if s['mean'] is None else 100 * s['mean'], 0)} pp {ci(s['ci95'], 100)} | "
            f"{num(m['mean'])} {ci(m['ci95'], 1.0, 2)} |"
        )
    if doc.get("pooled"):
        lines += ["", "Pooled over the levels (one pair per world and level), mean [t 95 % CI]:",
                  "", "| existence | pairs | success difference |", "|---|---|---|"]
        for p in doc["pooled"]:
            s = p["success_difference"]
            lines.append(f"| {p['existence_model']} | {p['n_pairs']} | "
                         f"{num(100 * s['mean'], 0)} pp {ci(s['ci95'], 100)} |")
    return "\n".join(lines) + "\n"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("reproduce", help="reproduce the papers' experiments")
    targets = p.add_subparsers(dest="target", required=True, metavar="TARGET")
    bb = targets.add_parser(
        "brooks-bailey",
        help="BB Table 1 (FASTSLAM, EKF, HYBRID x clutter levels) and Figs. 3-4",
        description="Success rates of BB Table 1 over random worlds, with Wilson intervals, "
        "and the vehicle-uncertainty traces of BB Figs. 3 and 4.",
    )
    bb.add_argument("--systems", default="fastslam,ekf,hybrid",
                    help="comma-separated among fastslam, ekf, hybrid, dead-reckoning")
    bb.add_argument("--existence-model", default="gate",
                    help="comma-separated readings of BB (11) among gate (clutter in the gate, "
                    "the default) and bb (BB's beta as written); filters.existence")
    bb.add_argument("--clutter-levels", default="0,1,2,3", metavar="L,...",
                    help="comma-separated clutter levels 0-3 (default 0,1,2,3)")
    bb.add_argument("--particles", type=int, default=500, metavar="P",
                    help="FastSLAM particles (default 500, BB's)")
    bb.add_argument("--fusion-interval-s", type=float, default=10.0, metavar="S",
                    help="seconds between fusions of the sub-map systems (default 10, BB's)")
    bb.add_argument("--optimise", choices=["never", "at-end", "every-fusion", "after-loop-closure"],
                    default="never",
                    help="optimise() schedule of the sub-map systems (BB: never)")
    bb.add_argument("--no-figures", action="store_true", help="skip the trace figures")
    bb.add_argument("--scenario", default="brooks-bailey",
                    help="the world (a scenario without compass; Fig. 3 uses its compass twin "
                    "only for brooks-bailey)")
    bb.add_argument("--path-perturbation-m", type=float, default=None,
                    help="the waypoint jitter of the path (m; default: the scenario's), the one "
                    "scalar that sets the path's turning (issue 28)")
    add_run_options(bb, default_out="out/reproduce-brooks-bailey")
    bb.set_defaults(run=run_brooks_bailey)
    from slam_gym.commands import reproduce_cm, reproduce_real

    reproduce_cm.add_parser(targets)
    reproduce_real.add_parser(targets)


def run_brooks_bailey(args) -> int:
    from slam_gym.evaluation import Job, write_summary

    systems = name_list(args.systems)
    unknown = [s for s in systems if s not in BB_SYSTEMS]
    if unknown:
        raise ValueError(f"systems={unknown} is invalid: must be among {sorted(BB_SYSTEMS)}")
    levels = int_list(args.clutter_levels, "clutter_levels")
    from filters.existence import validate_existence_model

    models = [validate_existence_model(m) for m in name_list(args.existence_model)]
    from slam_gym.scenarios import get_scenario

    world = {} if args.path_perturbation_m is None else {
        "path_perturbation_m": float(args.path_perturbation_m)}
    scenario = get_scenario(args.scenario, **world)  # validates the name and the jitter
    from filters.validation import require

    require(bool(levels) and len(set(levels)) == len(levels), "clutter_levels", levels,
            "distinct levels (at least one)")
    for level in levels:  # each level of the world, before any run
        get_scenario(args.scenario, clutter_level=level, **world)
    out = out_dir(args)

    def options(system, model):
        # the jitter enters a job's options (its key) only when given, so runs made before the
        # option existed resume into the same out directory
        if system == "dead-reckoning":
            return dict(world)
        if system == "fastslam":
            return {"n_particles": args.particles, "existence_model": model} | world
        return {"n_particles": args.particles, "fusion_interval_s": args.fusion_interval_s,
                "optimise": args.optimise, "existence_model": model} | world

    # seeds outermost: an interrupted run leaves whole worlds (every system and level), and a
    # rerun with a larger --trials into the same --out only runs the new worlds (results.jsonl)
    jobs, seen = [], set()
    for seed in range(args.seed_start, args.seed_start + args.trials):
        for level in levels:
            for model in models:
                for s in systems:
                    job = Job("system", BB_SYSTEMS[s], args.scenario, level, seed,
                              options(BB_SYSTEMS[s], model))
                    if job.key not in seen:
                        seen.add(job.key)
                        jobs.append(job)
    rows = execute(args, jobs, out)
    paper = BB_TABLE1
    doc = write_summary(out, rows, paper=paper)
    table1 = bb_table(rows)
    table1["existence_models"] = models
    table1["scenario"] = args.scenario
    table1["path_perturbation_m"] = scenario.path_perturbation_m
    world_line = (f"World: {args.scenario}, path_perturbation_m={scenario.path_perturbation_m:g}"
                  f"{'' if world else ' (the scenario default)'}")
    (out / "table1.json").write_text(json.dumps(table1, indent=2, allow_nan=False) + "\n")
    (out / "table1.md").write_text(
        f"{world_line}\n\nExistence model(s): {', '.join(models)}\n\n"
        + bb_table_markdown(table1)
    )
    from slam_gym.evaluation import plot_success_rates
    from slam_gym.evaluation.benchmarking import draw_figure

    figures: dict[str, str] = {}
    if any(g.get("success_rate") is not None for g in doc["groups"]):  # not when all errored
        draw_figure("success", lambda: plot_success_rates(
            doc, out / "success_rates.png", paper=paper, title="BB Table 1: success rate"),
            figures, {})
    if not args.no_figures:
        figures.update(trace_figures(systems, args.seed_start, args.particles, out,
                                     scenario=args.scenario, **world))
    print_table(args, doc, paper=paper, title="BB Table 1 reproduced (paper in the last column)")
    emit(args, {"summary": doc, "table1": table1, "existence_models": models,
                "figures": figures, "out": str(out)},
         [world_line, f"existence model(s) (BB (11)): {', '.join(models)}",
          bb_table_markdown(table1),
          f"wrote {out / 'results.jsonl'}, summary.json, table.md, table1.md and "
          f"{len(figures)} figures"])
    return errors_exit_code(args, rows)


def trace_figures(systems, seed, n_particles, out, scenario="brooks-bailey",
                  **overrides) -> dict:
    """BB Figs. 3 (compass, no clutter) and 4 (no compass): trace of the vehicle covariance.

    ``scenario`` (and scenario field ``overrides``) is Fig. 4's world; Fig. 3 is the same world
    with BB 5.5's compass."""
    from slam_gym.evaluation import plot_nees, plot_uncertainty_traces
    from slam_gym.evaluation.core import make_job_stream, run_system
    from slam_gym.scenarios import BB_COMPASS_STD_RAD

    figures = {}
    for compass, figure in ((BB_COMPASS_STD_RAD, "fig3"), (None, "fig4")):
        stream = make_job_stream(scenario, 0, seed, compass_std_rad=compass, **overrides)
        name_of = f"{scenario}-compass" if compass is not None else scenario
        traces, nees_traces, episodes = {}, {}, {}
        for s in systems:
            ep = run_system(BB_SYSTEMS[s], stream, seed, n_particles=n_particles,
                            stop_on_failure=False, record_trace=True)
            traces[s.upper()] = np.array(ep.trace.cov_trace)
            nees_traces[s.upper()] = np.array(ep.trace.nees)
            episodes[s] = ep
        name = f"{figure}_uncertainty_{name_of}.png"
        figures[figure] = str(plot_uncertainty_traces(
            traces, out / name, dt_s=stream.dt_s,
            title=f"Vehicle uncertainty, {name_of}, clutter 0, seed {seed}",
        ))
        figures[f"{figure}_nees"] = str(plot_nees(
            nees_traces, out / f"{figure}_nees_{name_of}.png", dt_s=stream.dt_s,
            title=f"Vehicle NEES, {name_of}, seed {seed}",
        ))
        if figure == "fig4" and "hybrid" in episodes:
            figures["map"] = plot_episode_map(
                episodes["hybrid"], out / "map_hybrid.png", f"HYBRID, {name_of}, seed {seed}"
            )
    return figures
