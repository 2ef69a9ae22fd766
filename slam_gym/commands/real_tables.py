"""The tables (``real_table.md``) and figures of ``slam-gym reproduce mrclam`` /
``reproduce victoria-park``, from the rows of :mod:`slam_gym.evaluation.real_data`'s run
functions (the command: :mod:`slam_gym.commands.reproduce_real`).
"""

from __future__ import annotations

import logging
import math
import statistics
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------- tables
REAL_TABLE_FILENAME = "real_table.md"


def compact_row(row: dict) -> dict:
    """A result row without its figure data and traceback (what ``results.jsonl`` keeps)."""
    return {k: v for k, v in row.items() if k not in ("figure", "traceback")}


def _label(row: dict) -> str:
    if row.get("policy") is not None:
        return f"{row.get('driven_system') or 'hybrid'} + {row['policy']}"
    return str(row.get("system"))


def _mean(rows, key):
    values = [float(r[key]) for r in rows
              if isinstance(r.get(key), (int, float)) and not isinstance(r.get(key), bool)
              and math.isfinite(float(r[key]))]
    return statistics.fmean(values) if values else None


def _fmt(x, digits=2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _group(rows, key_fn) -> dict:
    groups: dict = {}
    for row in rows:
        groups.setdefault(key_fn(row), []).append(row)
    return groups


def _md(header, body) -> str:
    def line(cells):
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    align = "|" + "|".join(["---"] * 3 + ["---:"] * (len(header) - 3)) + "|"
    return "\n".join([line(header), align, *map(line, body)])


def mrclam_table(rows) -> str:
    """Per (system or policy, robot, association): the MRCLAM metrics (means over seeds),
    then the means over robots. A policy whose model does not match the code (rows'
    ``model_matches_code``) is marked with a footnote."""
    from slam_gym.evaluation.summary import MISMATCH_MARK, group_provenance, provenance_footnote

    ok = [r for r in rows if r.get("status") == "ok"]
    header = ["system", "robot", "association", "n", "map error (m)", "pose RMSE (m)",
              "pose RMSE held out (m)", "ANEES", "NEES in band", "BB success", "features",
              "spurious", "missed", "completeness", "fusions", "filter time (s)", "wall time (s)"]

    def cells(label, robot, assoc, members):
        successes = [bool(r["success"]) for r in members if r.get("success") is not None]
        if any(r.get("model_matches_code") is False for r in members):
            label = f"{label} {MISMATCH_MARK}"
        return [
            label, robot, assoc, len(members),
            _fmt(_mean(members, "map_error_m")), _fmt(_mean(members, "pose_rmse_m")),
            _fmt(_mean(members, "pose_rmse_held_out_m")),
            _fmt(_mean(members, "anees"), 1),
            "–" if _mean(members, "nees_in_band_fraction") is None
            else f"{100 * _mean(members, 'nees_in_band_fraction'):.0f} %",
            f"{sum(successes)}/{len(successes)}",
            _fmt(_mean(members, "n_features"), 1), _fmt(_mean(members, "n_spurious"), 1),
            _fmt(_mean(members, "n_missed"), 1), _fmt(_mean(members, "completeness")),
            _fmt(_mean(members, "n_fusions"), 0),
            _fmt(_mean(members, "filter_time_s"), 1), _fmt(_mean(members, "wall_time_s"), 1),
        ]

    per_robot = _group(ok, lambda r: (_label(r), r.get("robot"), r.get("association")))
    body = [cells(lab, rob, assoc, m) for (lab, rob, assoc), m in per_robot.items()]
    overall = _group(ok, lambda r: (_label(r), r.get("association")))
    body_all = [cells(lab, "all", assoc, m) for (lab, assoc), m in overall.items()]
    errors = [r for r in rows if r.get("status") != "ok"]
    parts = ["## Per robot", "", _md(header, body), "", "## Mean over robots", "",
             _md(header, body_all)]
    footnote = provenance_footnote([group_provenance(m) for m in overall.values()])
    if footnote:
        parts += ["", footnote]
    if errors:
        parts += ["", f"{len(errors)} runs errored (excluded): "
                  + "; ".join(f"{_label(r)} {r.get('scenario')}: {r.get('error')}"
                              for r in errors[:5])]
    return "\n".join(parts)


def victoria_park_table(rows) -> str:
    """Per system: path error against GPS after SE(2) alignment, trees, run time."""
    ok = [r for r in rows if r.get("status") == "ok"]
    header = ["system", "steps", "seeds", "path RMSE vs GPS (m)", "median (m)",
              "final error (m)", "trees mapped", "fusions", "filter time (s)",
              "real-time factor", "wall time (s)"]
    body = []
    for label, members in _group(ok, _label).items():
        body.append([
            label, _fmt(_mean(members, "iterations"), 0), len(members),
            _fmt(_mean(members, "gps_rmse_m")), _fmt(_mean(members, "gps_median_error_m")),
            _fmt(_mean(members, "final_pose_error_m")), _fmt(_mean(members, "n_trees"), 0),
            _fmt(_mean(members, "n_fusions"), 0), _fmt(_mean(members, "filter_time_s"), 1),
            _fmt(_mean(members, "real_time_factor"), 1), _fmt(_mean(members, "wall_time_s"), 1),
        ])
    out = _md(header, body)
    errors = [r for r in rows if r.get("status") != "ok"]
    if errors:
        out += "\n\n" + f"{len(errors)} runs errored (excluded): " + "; ".join(
            f"{_label(r)}: {r.get('error')}" for r in errors[:5])
    return out


PAIRED_REFERENCE = "fixed-10s-optimise"


def mrclam_paired_table(rows) -> str | None:
    """Every interface policy against ``fixed-10s-optimise`` on the same robots and seeds (all
    runs, BB's failure rule or not): map error, pose RMSE and interface CPU, each the paired
    difference with its t 95 % interval (:func:`slam_gym.evaluation.front.compare_all_runs`).
    None when the reference did not run or any policy run did not finish."""
    from slam_gym.evaluation.front import compare_all_runs

    policy_rows = [r for r in rows if r.get("driven_system") == "hybrid"]
    if any(r.get("status") != "ok" for r in policy_rows):
        return None
    by_policy: dict[str, list] = {}
    for r in policy_rows:
        by_policy.setdefault(r["policy"], []).append(r)
    reference = by_policy.get(PAIRED_REFERENCE)
    if reference is None:
        return None

    def ci(c, key, digits):
        lo, hi = c[f"{key}_diff_ci"] or (math.nan, math.nan)
        return f"{c[f'{key}_diff']:+.{digits}f} [{lo:+.{digits}f}, {hi:+.{digits}f}]"

    lines = [f"Paired against `{PAIRED_REFERENCE}` (same robot and seed; every run):", "",
             "| policy | runs | map error (m) | diff (m) | pose RMSE (m) | diff (m) "
             "| interface CPU (s) | CPU ratio | fusions | optimisations |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, members in by_policy.items():
        try:
            c = compare_all_runs(members, reference)
        except ValueError:  # not the reference's runs (an interrupted run): no pairing
            continue
        lines.append(
            f"| {name} | {c['n_runs']} | {c['map_error_m']:.2f} | {ci(c, 'map_error_m', 2)} "
            f"| {c['pose_rmse_m']:.2f} | {ci(c, 'pose_rmse_m', 2)} | {c['interface_cpu_s']:.2f} "
            f"| {c['interface_cpu_ratio']:.2f} | {c['n_fusions']:.0f} "
            f"| {c['n_optimisations']:.0f} |")
    return "\n".join(lines)


def write_real_table(out, rows, target: str, notes) -> str:
    """Write ``real_table.md`` (title, table, the policies paired with
    ``fixed-10s-optimise`` when it ran, notes); returns its text."""
    if target == "mrclam":
        title, table = "# MRCLAM: systems on real data", mrclam_table(rows)
        paired = mrclam_paired_table(rows)
        if paired:
            table = f"{table}\n\n{paired}"
    else:
        title, table = "# Victoria Park: systems on real data", victoria_park_table(rows)
    text = "\n".join([title, "", table, "", *(f"- {n}" for n in notes), ""])
    path = Path(out) / REAL_TABLE_FILENAME
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return text


# --------------------------------------------------------------------------- figures
def mrclam_figures(rows, data, out) -> dict:
    """One map per system/policy (unknown association, first seed) on the first robot run."""
    from slam_gym.datasets import read_mrclam
    from slam_gym.evaluation import plot_run_map

    figures = {}
    ok = [r for r in rows if r.get("status") == "ok" and r.get("figure")
          and r.get("association") == "unknown"]
    if not ok:
        return figures
    robot = ok[0]["robot"]
    landmarks = read_mrclam(data, robot).landmarks_xy
    for row in ok:
        label = _label(row)
        key = f"{label} robot{robot}"
        if row["robot"] != robot or key in figures:
            continue
        fig = row["figure"]
        safe = label.replace(" + ", "_").replace(" ", "_")
        figures[key] = str(plot_run_map(
            Path(out) / f"mrclam_map_{safe}_robot{robot}.png",
            landmarks_true=landmarks,
            landmark_means=np.asarray(fig["landmark_means"]).reshape(-1, 2),
            landmark_covs=np.asarray(fig["landmark_covs"]).reshape(-1, 2, 2),
            path_true=np.asarray(fig["true_path_xy"]).reshape(-1, 2),
            path_est=np.asarray(fig["est_path_xy"]).reshape(-1, 2),
            title=f"MRCLAM robot {robot}: {label} (map error "
                  f"{_fmt(row.get('map_error_m'))} m)",
        ))
    return figures


def plot_victoria_park_map(path, *, gps_xy, est_path_xy, trees_xy, title=None) -> Path:
    """The estimated map (trees) and path over the GPS fixes, in the GPS frame (after the SE(2)
    alignment); headless (Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 7.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    gps_xy = np.asarray(gps_xy, dtype=float).reshape(-1, 2)
    est = np.asarray(est_path_xy, dtype=float).reshape(-1, 2)
    trees = np.asarray(trees_xy, dtype=float).reshape(-1, 2)
    ax.scatter(gps_xy[:, 0], gps_xy[:, 1], s=3, color="0.55", label="GPS fixes", zorder=2)
    ax.plot(est[:, 0], est[:, 1], color="#1f77b4", lw=0.9, label="estimated path (aligned)",
            zorder=3)
    ax.scatter(trees[:, 0], trees[:, 1], marker="^", s=12, color="#2ca02c",
               label=f"mapped trees ({len(trees)})", zorder=4)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3, linewidth=0.6)
    ax.set_xlabel("x (m, GPS frame)")
    ax.set_ylabel("y (m, GPS frame)")
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def victoria_park_figures(rows, data, out) -> dict:
    """One PNG per system (first seed): the map over the GPS track."""
    from slam_gym.datasets import read_victoria_park

    gps = None
    figures = {}
    for row in rows:
        if row.get("status") != "ok" or not row.get("figure") or row["system"] in figures:
            continue
        if gps is None:
            rec = read_victoria_park(data)
            gps = rec.gps.copy()
            gps[:, 0] -= rec.inputs[0, 0]
        t0, t1 = row["figure"]["gps_span_s"]
        inside = (gps[:, 0] >= t0) & (gps[:, 0] <= t1)
        figures[row["system"]] = str(plot_victoria_park_map(
            Path(out) / f"victoria_park_map_{row['system']}.png",
            gps_xy=gps[inside, 1:3],
            est_path_xy=row["figure"]["est_path_xy"],
            trees_xy=row["figure"]["trees_xy"],
            title=f"Victoria Park: {row['system']}, path RMSE vs GPS "
                  f"{_fmt(row.get('gps_rmse_m'))} m, {row.get('n_trees')} trees",
        ))
    return figures
