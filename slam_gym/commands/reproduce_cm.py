"""``slam-gym reproduce conte-martinelli``: CM section IV.B, ESDF vs the hybrid filter/optimiser.

For each simulation (``conte-martinelli-1`` / ``-2``) and seed, one stream is played through

* the ESDF (:class:`filters.esdf.ESDF`, known association, CM II), and
* the hybrid: the relative-coordinate ESDF (:class:`filters.relative_esdf.RelativeESDF`, CM III.B)
  plus the nonlinear optimiser (CM III.C), called **once, at the end of the run** (CM: in sim 2 it
  is "activated only once, after a long time from the first loop closure"; in sim 1 the run ends
  shortly after the closure, so once at the end is the same rule).

Map error (CM IV.B): the mean over the mapped landmarks of the distance between the estimated and
the true position (associations are known, so every feature has its landmark).

* **Before loop closure**: the estimate just before the *closing scan*, defined from the truth ids
  as the first scan that observes a landmark whose previous observation is at least
  ``gap_scans`` scans earlier (default 10 scans = 50 s at CM's 0.2 Hz; a landmark stays in the
  12 m range for at most ~5 scans at 1 m/s, so only a return after a long absence -- the start
  area at the end of the loop -- qualifies). Without such a scan the run's end is used.
* **After**: at the end of the run; for the ESDF after integrating everything (its reported
  estimates are always the exact mean recovery ``Lambda^-1 eta``), for the hybrid after the one
  optimisation.
* ``hybrid_map_error_pre_optimisation_m``: the hybrid at the end of the run just before the
  optimisation (each landmark from its first coordinates, phantoms not counted). This is what CM
  show as the hybrid "before exploiting the loop closure information" in sim 2 (Fig. 6), where
  the optimiser runs "after a long time from the first loop closure"; in sim 1 the run ends soon
  after the closure and the two instants nearly coincide.

The map is in the global frame fixed by the known start pose, as CM measure it, so what anchors
the first landmarks to that pose matters: the CM scenarios take their first scan at the start
pose (:mod:`slam_gym.scenarios`). With the first scan after 5 s of odometry instead, the heading
error of that first observing pose rotates the whole map about the start, which no loop closure
can correct (it dominated the old sim-1 numbers).

Times (CM report ``T_c`` split into filtering and optimisation): the filters' compute time in
``predict``/``update`` (:class:`slam_gym.episode.Episode`) and the optimiser's wall time. Rows also
carry the keys the evaluation machinery requires (``map_error_m`` = the hybrid's error after the
optimisation, NEES metrics of the hybrid's filter run; ``n_fusions`` = 0, ``n_optimisations`` = 1).

BLAS: the worker function limits BLAS to one thread with ``threadpoolctl`` (L-BFGS-B's tiny BLAS
calls are slow with a multi-threaded OpenBLAS on a busy machine; see :mod:`filters.optimiser`).
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from pathlib import Path

import numpy as np

from slam_gym.commands.common import emit, out_dir
from slam_gym.commands.runs import (
    add_run_options,
    check_run_options,
    errors_exit_code,
    int_list,
    print_table,
    run_options,
)

logger = logging.getLogger(__name__)

#: the job name of one CM comparison run (both methods on one stream)
CM_SYSTEM = "esdf-vs-hybrid"
CM_SIMS = (1, 2)
DEFAULT_GAP_SCANS = 10
OPTIMISER_METHODS = ("reduced", "gauss-newton", "levenberg-marquardt")

#: CM section IV.B: map errors (m) before -> after loop closure and compute times (s)
CM_PAPER = {
    1: {
        "esdf_map_error_before_m": 2.02,
        "esdf_map_error_after_m": 1.01,
        "hybrid_map_error_before_m": 1.30,
        "hybrid_map_error_after_m": 0.15,
        "esdf_time_s": 39.67,
        "hybrid_filter_time_s": 5.45,
        "hybrid_optimise_time_s": 10.75,
    },
    2: {
        "esdf_map_error_before_m": 3.91,
        "esdf_map_error_after_m": 0.58,
        "hybrid_map_error_before_m": 3.17,
        "hybrid_map_error_after_m": 0.38,
        "esdf_time_s": 91.44,
        "hybrid_filter_time_s": 13.67,
        "hybrid_optimise_time_s": 32.70,
    },
}
CM_KEYS = tuple(CM_PAPER[1])


# --------------------------------------------------------------------------- the run
def scenario_of(sim: int) -> str:
    if sim not in CM_SIMS:
        raise ValueError(f"sims={sim!r} is invalid: must be among {list(CM_SIMS)}")
    return f"conte-martinelli-{sim}"


def closing_scan_step(stream, gap_scans: int = DEFAULT_GAP_SCANS) -> int | None:
    """Index of the step of the first scan re-observing a landmark after ``gap_scans`` scans.

    A scan is a step with at least one observation; the truth ids tell which landmark each
    observation comes from. Returns None if no scan qualifies.
    """
    if not (isinstance(gap_scans, int) and gap_scans >= 1):
        raise ValueError(f"gap_scans={gap_scans!r} is invalid: must be an integer >= 1")
    last_scan: dict[int, int] = {}
    n_scan = 0
    for step in stream:
        ids = step.truth.landmark_ids
        ids = ids[ids >= 0]
        if len(step.z) == 0:
            continue
        if any(n_scan - last_scan[int(j)] >= gap_scans for j in ids if int(j) in last_scan):
            return int(step.index)
        for j in ids:
            last_scan[int(j)] = n_scan
        n_scan += 1
    return None


def _map_error(estimator, stream, among=None) -> float:
    """CM's map error: mean distance of each mapped landmark to its true position.

    ``among``: only the landmarks (truth ids) in this set.
    """
    lm = estimator.landmarks()
    ids = estimator.landmark_ids()
    keep = np.ones(len(ids), dtype=bool) if among is None else np.isin(ids, list(among))
    if not keep.any():
        return float("nan")
    true = stream.landmarks_true[ids[keep]]
    return float(np.mean(np.linalg.norm(np.asarray(lm.means)[keep] - true, axis=1)))


def _snapshot(estimator, episode) -> dict:
    """What a figure panel needs: true path so far, estimated trajectory, landmark estimates."""
    lm = estimator.landmarks()
    snap = {
        "true_path": np.array(episode.trace.true_poses) if episode.trace else np.zeros((0, 3)),
        "est_path": estimator.trajectory(),
        "landmarks": np.asarray(lm.means).copy(),
        "phantoms": np.zeros((0, 2)),
    }
    if hasattr(estimator, "loop_closures") and estimator.loop_closures:
        from filters.geometry import transform_point

        traj = snap["est_path"]
        snap["phantoms"] = np.array(
            [
                transform_point(traj[lc.epoch], estimator.info.mean_of(lc.coordinates_entity))
                for lc in estimator.loop_closures
            ]
        )
    return snap


def run_cm(
    scenario: str,
    seed: int,
    *,
    n_steps: int | None = None,
    method: str = "reduced",
    gap_scans: int = DEFAULT_GAP_SCANS,
    keep: bool = False,
    **overrides,
) -> dict:
    """One CM comparison on one stream: ESDF and hybrid, errors before/after loop closure, times.

    ``overrides``: scenario fields (e.g. ``chong_kleeman_k_m``); ``n_steps`` cuts the run.
    Returns the result row (see the module docstring); with ``keep`` also ``"snapshots"``
    (figure data: ``{method: {"before": ..., "after": ...}}``) and ``"stream"``.
    """
    from slam_gym.episode import Episode
    from slam_gym.systems import make_system
    from slam_gym.world import make_stream

    if method not in OPTIMISER_METHODS:
        raise ValueError(f"method={method!r} is invalid: must be one of {OPTIMISER_METHODS}")
    if n_steps is not None:
        overrides["n_steps"] = int(n_steps)
    stream = make_stream(scenario, seed=seed, **overrides)
    closing = closing_scan_step(stream, gap_scans)
    n_before = len(stream) if closing is None else closing
    out: dict = {
        "alpha": stream.clutter.alpha,
        "beta": stream.clutter.beta,
        "loop_closure_step": closing,
        "loop_closure_time_s": None if closing is None else closing * stream.dt_s,
        "method": method,
        "gap_scans": gap_scans,
    }
    snapshots: dict = {}
    for label, name in (("esdf", "esdf"), ("hybrid", "relative-esdf")):
        system = make_system(name, stream, np.random.default_rng(seed))  # (unused: no sampling)
        est = system.estimator
        ep = Episode(system, stream, known_association=True, record_trace=keep)
        ep.advance(n_before)
        before = _map_error(est, stream)
        mapped_before = set(est.landmark_ids().tolist())
        if keep:
            snapshots[label] = {"before": _snapshot(est, ep)}
        ep.advance(len(stream))
        filter_time = ep.compute_time_s
        metrics = ep.metrics()
        if label == "hybrid":
            # CM Fig. 6 (sim 2): the hybrid "before exploiting the loop closure information" is
            # the filter's estimate just before the one optimisation, at the end of the run
            out["hybrid_map_error_pre_optimisation_m"] = _map_error(est, stream)
            t0 = time.perf_counter()
            res = est.optimise(method)
            out["hybrid_optimise_time_s"] = time.perf_counter() - t0
            out["optimiser_iterations"] = int(res.iterations)
            out["optimiser_converged"] = bool(res.converged)
            out["n_loop_closures"] = int(est.n_loop_closures)
            out["hybrid_filter_time_s"] = filter_time
        else:
            out["esdf_time_s"] = filter_time
        after = _map_error(est, stream)
        mean, _ = est.pose()
        true_pose = ep.last_step.truth.pose
        out[f"{label}_map_error_before_m"] = before
        out[f"{label}_map_error_after_m"] = after
        out[f"{label}_map_error_after_same_m"] = _map_error(est, stream, mapped_before)
        out[f"{label}_final_pose_error_m"] = float(np.linalg.norm(mean[:2] - true_pose[:2]))
        out[f"{label}_anees"] = metrics["anees"]
        out[f"{label}_success"] = metrics["success"]
        out[f"{label}_n_landmarks"] = int(len(est.landmarks()))
        if keep:
            snapshots[label]["after"] = _snapshot(est, ep)
        if label == "hybrid":
            out.update(
                success=metrics["success"],
                failure_iteration=metrics["failure_iteration"],
                anees=metrics["anees"],
                nees_in_band_fraction=metrics["nees_in_band_fraction"],
            )
    out.update(
        map_error_m=out["hybrid_map_error_after_m"],
        final_pose_error_m=out["hybrid_final_pose_error_m"],
        n_fusions=0,
        n_optimisations=1,
    )
    if keep:
        out["snapshots"] = snapshots
        out["stream"] = stream
    return out


def run_cm_job(job) -> dict:
    """The run function for :func:`slam_gym.evaluation.run_jobs` (picklable, module level)."""
    from threadpoolctl import threadpool_limits

    opts = job.options_dict()
    with threadpool_limits(1):
        return run_cm(
            job.scenario,
            job.seed,
            n_steps=opts.get("n_steps"),
            method=opts.get("method", "reduced"),
            gap_scans=int(opts.get("gap_scans", DEFAULT_GAP_SCANS)),
        )


# --------------------------------------------------------------------------- tables, figures
def cm_summary(rows) -> dict:
    """Mean and median over seeds (ok rows) of the CM quantities, per sim, with CM's numbers."""
    out = {}
    for sim in CM_SIMS:
        ok = [r for r in rows if r.get("scenario") == scenario_of(sim) and r.get("status") == "ok"]
        if not ok:
            continue
        entry = {"n": len(ok)}
        for key in (*CM_KEYS, "hybrid_map_error_pre_optimisation_m", "optimiser_iterations",
                    "n_loop_closures"):
            vals = [float(r[key]) for r in ok if isinstance(r.get(key), (int, float))
                    and math.isfinite(r[key])]
            entry[key] = {
                "mean": statistics.fmean(vals) if vals else None,
                "median": statistics.median(vals) if vals else None,
                "paper": CM_PAPER[sim].get(key),
            }
        out[str(sim)] = entry
    return out


def _f(x, digits=2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def cm_markdown(summary: dict) -> str:
    """``cm_table.md``: map errors before -> after and times, ours (mean / median) next to CM's."""
    lines = [
        "# CM section IV.B reproduced: map error before -> after loop closure (m), compute time",
        "",
        "| sim | method | n | before: mean / median | after: mean / median | CM before -> after "
        "| filter time (s): mean / median | optimisation time (s): mean / median | CM time (s) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for sim, e in summary.items():
        p = CM_PAPER[int(sim)]
        for label, name in (("esdf", "ESDF"), ("hybrid", "hybrid (relative ESDF + optimiser)")):
            b, a = e[f"{label}_map_error_before_m"], e[f"{label}_map_error_after_m"]
            if label == "esdf":
                ft, ot = e["esdf_time_s"], None
                paper_t = f"{p['esdf_time_s']:.2f}"
            else:
                ft, ot = e["hybrid_filter_time_s"], e["hybrid_optimise_time_s"]
                paper_t = (f"{p['hybrid_filter_time_s']:.2f} + {p['hybrid_optimise_time_s']:.2f}")
            lines.append(
                f"| {sim} | {name} | {e['n']} | {_f(b['mean'])} / {_f(b['median'])} "
                f"| {_f(a['mean'])} / {_f(a['median'])} "
                f"| {b['paper']:.2f} -> {a['paper']:.2f} "
                f"| {_f(ft['mean'], 3)} / {_f(ft['median'], 3)} "
                f"| {'–' if ot is None else _f(ot['mean'], 3) + ' / ' + _f(ot['median'], 3)} "
                f"| {paper_t} |"
            )
    lines += [
        "",
        "Map error: mean distance between each mapped landmark and its true position (CM IV.B). "
        "Before: the estimate just before the first scan re-observing a landmark after a long "
        "absence (the loop closure); after: end of the run, the hybrid optimised once (CM). "
        "CM's times are Matlab on a 1.7 GHz Pentium M; ours are Python on this machine.",
        "",
    ]
    return "\n".join(lines)


def cm_figure(result: dict, path, *, sim: int, seed: int) -> Path:
    """CM Figs 2-5 / 6-9 for one run: 4 panels (hybrid and ESDF, before and after)."""
    import matplotlib.pyplot as plt

    from slam_gym.render import draw_map

    stream = result["stream"]
    snaps = result["snapshots"]
    fig, axes = plt.subplots(2, 2, figsize=(12, 12))
    panels = (
        ("hybrid", "before", "hybrid (relative ESDF), before loop closure"),
        ("esdf", "before", "ESDF, before loop closure"),
        ("hybrid", "after", "hybrid, after the optimisation"),
        ("esdf", "after", "ESDF, after loop closure"),
    )
    for ax, (label, when, title) in zip(axes.ravel(), panels, strict=True):
        s = snaps[label][when]
        draw_map(
            ax,
            landmarks_true=stream.landmarks_true,
            true_path=s["true_path"],
            est_path=s["est_path"],
            est_landmarks=s["landmarks"],
        )
        if label == "hybrid" and when == "before" and len(s["phantoms"]):
            ax.plot(*s["phantoms"].T, "r*", ms=7, label="redundant coordinates (phantoms)")
        key = f"{label}_map_error_{when}_m"
        ax.set_title(
            f"{title}\nmap error {result[key]:.3f} m (CM: {CM_PAPER[sim][key]:.2f} m)", fontsize=10
        )
        ax.legend(loc="upper right", fontsize=7)
    fig.suptitle(f"CM simulation {sim}, seed {seed}: true (blue) and estimated (red) map and path")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- the command
def add_parser(targets) -> None:
    """Add ``reproduce conte-martinelli`` to the ``reproduce`` targets (subparsers object)."""
    cm = targets.add_parser(
        "conte-martinelli",
        help="CM IV.B: map errors before/after loop closure, ESDF vs hybrid optimiser, times",
        description="Map errors before and after loop closure of the ESDF and of CM's hybrid "
        "(relative-coordinate ESDF + nonlinear optimiser), and their compute times, over random "
        "worlds of CM's simulations 1 and 2 (CM section IV.B).",
    )
    cm.add_argument("--sims", default="1,2", help="comma-separated among 1, 2")
    cm.add_argument("--method", choices=list(OPTIMISER_METHODS), default="reduced",
                    help="optimiser (CM: quasi-Newton over headings = reduced)")
    cm.add_argument("--gap-scans", type=int, default=DEFAULT_GAP_SCANS,
                    help="a landmark re-observed after this many scans closes the loop")
    cm.add_argument("--n-steps", type=int, default=None, help="cut each run (for quick checks)")
    cm.add_argument("--no-figures", action="store_true", help="skip the map figures")
    add_run_options(cm, default_out="out/reproduce-conte-martinelli")
    cm.set_defaults(run=run_conte_martinelli)


def run_conte_martinelli(args) -> int:
    from threadpoolctl import threadpool_limits

    from slam_gym.evaluation import Job, read_results, run_jobs, write_summary

    sims = int_list(args.sims, "sims")
    for sim in sims:
        scenario_of(sim)
    if args.trials < 1:
        raise ValueError(f"trials={args.trials} is invalid: must be >= 1")
    if args.gap_scans < 1:
        raise ValueError(f"gap_scans={args.gap_scans} is invalid: must be >= 1")
    if args.n_steps is not None and args.n_steps < 1:
        raise ValueError(f"n_steps={args.n_steps} is invalid: must be >= 1")
    out = out_dir(args)
    options = {"method": args.method, "gap_scans": args.gap_scans, "n_steps": args.n_steps}
    jobs = [
        Job("system", CM_SYSTEM, scenario_of(sim), None, seed, options)
        for seed in range(args.seed_start, args.seed_start + args.trials)
        for sim in sims
    ]
    check_run_options(args)
    run_jobs(jobs, run_cm_job, out, **run_options(args))
    keys = {j.key for j in jobs}
    rows = [r for r in read_results(out) if r.get("key") in keys]
    doc = write_summary(out, rows)
    cm = cm_summary(rows)
    (out / "cm_table.md").write_text(cm_markdown(cm), encoding="utf-8")
    figures = {}
    if not args.no_figures:
        with threadpool_limits(1):
            for sim in sims:
                result = run_cm(scenario_of(sim), args.seed_start, n_steps=args.n_steps,
                                method=args.method, gap_scans=args.gap_scans, keep=True)
                figures[f"sim{sim}"] = str(cm_figure(
                    result, out / f"cm_sim{sim}_maps.png", sim=sim, seed=args.seed_start))
    print_table(args, doc, title="CM runs (map error = hybrid after optimisation)")
    human = ["CM IV.B, map error before -> after loop closure (mean over seeds, m):"]
    for sim, e in cm.items():
        for label in ("esdf", "hybrid"):
            b = e[f"{label}_map_error_before_m"]
            a = e[f"{label}_map_error_after_m"]
            human.append(
                f"  sim {sim} {label:6s}: {_f(b['mean'])} -> {_f(a['mean'])}  "
                f"(CM {b['paper']:.2f} -> {a['paper']:.2f})"
            )
    human.append(f"wrote {out / 'results.jsonl'}, summary.json, table.md, cm_table.md and "
                 f"{len(figures)} figures")
    emit(args, {"summary": doc, "cm": cm, "figures": figures, "out": str(out)}, human)
    return errors_exit_code(args, rows)
