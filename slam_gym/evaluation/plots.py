"""Benchmark figures (matplotlib, headless: figures are drawn with the Agg canvas, no pyplot).

- :func:`plot_success_rates`: success rate per clutter level with Wilson 95 % error bars, one line
  per system or policy, reference values (e.g. BB Table 1) as hollow markers;
- :func:`plot_uncertainty_traces`: vehicle uncertainty over time, the trace of the pose covariance
  per iteration (BB Figs. 3 and 4);
- :func:`plot_nees`: vehicle NEES over time with the two-sided chi-square 95 % band for 3 dof;
- :func:`plot_pareto`: accuracy against compute, one point per policy with 95 % intervals, one
  panel per clutter level, the non-dominated front drawn and dominated policies hollow
  (:func:`pareto_front`);
- :func:`plot_run_map`: one run's map: true landmarks, estimated landmarks with 2-sigma ellipses,
  true and estimated paths (BB Figs. 2 and 6), and where the run failed if it did.

Each function saves a PNG of exactly ``figsize * dpi`` pixels and returns its path; the
``*_figure`` functions return the figure itself, laid out, so that tests can read what is drawn.
What a reader must be able to read (issue 49): a log axis labels a few round values ("0.02",
"0.05") and never runs its labels together; panels share one axis label; the number beside a
point is moved (with a leader line) where it would cover another; lines that are identical are
drawn once and named together in the legend ("fixed-10s = esdf-innovation"); a legend lists
only what is drawn; what was left out is said on the figure ("Not drawn: ...").
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import ticker
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from filters.validation import require
from slam_gym.evaluation.jobs import JOB_KINDS
from slam_gym.evaluation.summary import (
    NON_NEGATIVE_KEYS,
    PaperValues,
    options_distinguish,
    paper_rate,
)

DPI = 120
CURVE_FIGSIZE = (7.0, 4.5)
MAP_FIGSIZE = (6.5, 6.5)
_COLORS = (
    "#1f77b4",
    "#d62728",
    "#2ca02c",
    "#ff7f0e",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#17becf",
    "#7f7f7f",
    "#bcbd22",
)


def _new_figure(figsize: tuple[float, float], dpi: int) -> tuple[Figure, Any]:
    require(
        len(figsize) == 2 and all(isinstance(v, (int, float)) and v > 0 for v in figsize),
        "figsize",
        figsize,
        "two positive numbers (inches)",
    )
    require(isinstance(dpi, int) and dpi >= 10, "dpi", dpi, "an int >= 10")
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.grid(True, alpha=0.3, linewidth=0.6)
    return fig, ax


def _save(fig: Figure, path: str | os.PathLike, dpi: int) -> Path:
    """Save a laid-out figure as a PNG of exactly its size."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")  # no bbox_inches="tight": the size stays exact
    return path


NOTE_FONTSIZE = 8


def add_notes(fig: Figure, notes: Sequence[str]) -> float:
    """Write what a figure leaves out under it, one line per note (``"Not drawn: ..."``);
    returns the fraction of the figure's height the lines take (for the layout's rect)."""
    if not notes:
        return 0.0
    line_h = 1.45 * NOTE_FONTSIZE / 72 / fig.get_figheight()
    for i, note in enumerate(notes):
        fig.text(0.01, 0.01 + (len(notes) - 1 - i) * line_h, f"Not drawn: {note}",
                 fontsize=NOTE_FONTSIZE, color="0.25", ha="left", va="bottom")
    return 0.015 + len(notes) * line_h


def identical_series(series: Mapping[str, Any]) -> list[list[str]]:
    """The names of ``series`` grouped by equal values (same length, equal elementwise, NaN
    equal to NaN), in first-seen order: ``[["fixed-10s", "esdf-innovation"], ["learned"]]``."""
    groups: list[list[str]] = []
    arrays: list[np.ndarray] = []
    for name, values in series.items():
        arr = np.asarray(values, dtype=float)
        for group, first in zip(groups, arrays, strict=True):
            if first.shape == arr.shape and np.array_equal(first, arr, equal_nan=True):
                group.append(name)
                break
        else:
            groups.append([name])
            arrays.append(arr)
    return groups


def _same_label(names: Sequence[str]) -> str:
    """A legend's name of lines drawn once for several series: ``"a = b (identical here)"``."""
    return names[0] if len(names) == 1 else f"{' = '.join(names)} (identical here)"


def log_ticks(low: float, high: float, max_ticks: int = 5) -> list[float]:
    """Round values for a log axis from ``low`` to ``high`` (both > 0): the densest of 1-9,
    1-2-5, 1-3 and 1 times the powers of ten (then every 2nd, 3rd, ... power) that gives 2 to
    ``max_ticks`` values inside; the sparsest with 2 or more if none does."""
    require(0 < low < high and math.isfinite(high), "limits", (low, high), "0 < low < high")
    k0, k1 = math.floor(math.log10(low)), math.ceil(math.log10(high))
    options = [(tuple(range(1, 10)), 1), ((1, 2, 5), 1), ((1, 3), 1)]
    options += [((1,), stride) for stride in (1, 2, 3, 5, 10, 20)]
    candidates = []
    for subs, stride in options:
        ticks = [m * 10.0**k for k in range(k0, k1 + 1) if (k - k0) % stride == 0
                 for m in subs if low <= m * 10.0**k <= high]
        if 2 <= len(ticks) <= max_ticks:
            return ticks
        candidates.append(ticks)
    enough = [t for t in candidates if len(t) >= 2]
    return min(enough, key=len) if enough else [low, high]


def _tick_text(value: float) -> str:
    """``0.02``, ``0.5``, ``3``, ``100``, ``2e+04``: a tick value in few characters."""
    return f"{value:.3g}" if 1e-3 <= abs(value) < 1e4 else f"{value:.0e}"


def set_log_axis(axis, low: float, high: float, max_ticks: int = 5) -> None:
    """A logarithmic axis from ``low`` to ``high`` labelled at :func:`log_ticks` (minor ticks
    unlabelled): labels a reader can read that never run together."""
    axis.axes.set_xscale("log") if axis.axis_name == "x" else axis.axes.set_yscale("log")
    if axis.axis_name == "x":
        axis.axes.set_xlim(low, high)
    else:
        axis.axes.set_ylim(low, high)
    ticks = log_ticks(low, high, max_ticks)
    axis.set_major_locator(ticker.FixedLocator(ticks))
    axis.set_major_formatter(ticker.FixedFormatter([_tick_text(t) for t in ticks]))
    axis.set_minor_formatter(ticker.NullFormatter())


def _series_label(group: Mapping[str, Any], vary_scenario: bool, vary_options: bool) -> str:
    name = next(group[k] for k in JOB_KINDS if group.get(k) is not None)
    parts = [name]
    if vary_scenario:
        parts.append(str(group.get("scenario")))
    if vary_options and group.get("options"):
        parts.append(", ".join(f"{k}={v}" for k, v in group["options"].items()))
    return " · ".join(parts)


def plot_success_rates(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    path: str | os.PathLike,
    *,
    paper: PaperValues | None = None,
    paper_label: str = "paper",
    title: str | None = "Success rate per clutter level",
    figsize: tuple[float, float] = CURVE_FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """Success rate (%) against clutter level with Wilson 95 % error bars, one line per series
    (:func:`success_figure`), saved to ``path``."""
    return _save(success_figure(summary, paper=paper, paper_label=paper_label, title=title,
                                figsize=figsize, dpi=dpi), path, dpi)


def success_figure(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    *,
    paper: PaperValues | None = None,
    paper_label: str = "paper",
    title: str | None = "Success rate per clutter level",
    figsize: tuple[float, float] = CURVE_FIGSIZE,
    dpi: int = DPI,
) -> Figure:
    """Success rate (%) against clutter level with Wilson 95 % error bars, one line per series.

    ``summary`` is the output of :func:`~slam_gym.evaluation.summary.summarise` or the
    ``summary.json`` document. Groups with no ok run or no clutter level are left out (named
    under the figure). ``paper`` (name -> {level: rate}) or the groups' ``paper_success_rate``
    are drawn as hollow markers in the series' colour. Tick labels show (alpha, beta) when the
    groups carry them.
    """
    groups = list(summary["groups"] if isinstance(summary, Mapping) else summary)
    left_out = sorted({_name(g) for g in groups if g.get("success_rate") is None
                       and g.get("clutter_level") is not None} - {
        _name(g) for g in groups if g.get("success_rate") is not None})
    groups = [
        g
        for g in groups
        if g.get("success_rate") is not None and g.get("clutter_level") is not None
    ]
    require(len(groups) > 0, "summary", "no group", "at least one group with ok runs and a level")
    vary_scenario = len({g.get("scenario") for g in groups}) > 1
    vary_options = options_distinguish(groups)
    series: dict[str, list[Mapping[str, Any]]] = {}
    for g in groups:
        series.setdefault(_series_label(g, vary_scenario, vary_options), []).append(g)

    fig, ax = _new_figure(figsize, dpi)
    n = len(series)
    width = min(0.25, 0.6 / max(n, 1))  # horizontal dodge so error bars do not overlap
    any_paper = False
    tick_text: dict[int, str] = {}
    for i, (label, members) in enumerate(series.items()):
        members = sorted(members, key=lambda g: g["clutter_level"])
        color = _COLORS[i % len(_COLORS)]
        levels = np.array([g["clutter_level"] for g in members], dtype=float)
        x = levels + (i - (n - 1) / 2) * width
        rate = np.array([g["success_rate"] for g in members]) * 100
        lo = np.array([g["success_ci95"][0] for g in members]) * 100
        hi = np.array([g["success_ci95"][1] for g in members]) * 100
        ax.errorbar(
            x,
            rate,
            yerr=np.vstack([rate - lo, hi - rate]),
            color=color,
            marker="o",
            markersize=5,
            linewidth=1.6,
            capsize=3,
            label=f"{label} ({_runs_label(members)})",
        )
        for g, xi in zip(members, x, strict=True):
            name = next(g[k] for k in JOB_KINDS if g.get(k) is not None)
            ref = (
                paper_rate(paper, name, g["clutter_level"])
                if paper is not None
                else g.get("paper_success_rate")
            )
            if ref is not None:
                any_paper = True
                ax.plot(
                    xi,
                    100 * ref,
                    linestyle="none",
                    marker="D",
                    markersize=7,
                    markerfacecolor="none",
                    markeredgecolor=color,
                    markeredgewidth=1.5,
                )
            if g.get("alpha") is not None and g.get("beta") is not None:
                tick_text.setdefault(
                    g["clutter_level"],
                    f"{g['clutter_level']}\n(α={g['alpha']:.2f}, β={g['beta']:.2f})",
                )
    all_levels = sorted({g["clutter_level"] for g in groups})
    ax.set_xticks(all_levels)
    ax.set_xticklabels([tick_text.get(level, str(level)) for level in all_levels])
    ax.set_xlim(all_levels[0] - 0.5, all_levels[-1] + 0.5)
    ax.set_ylim(-4, 104)
    ax.set_xlabel("clutter level")
    ax.set_ylabel("success rate (%; bars: Wilson 95 % interval)")
    if title:
        ax.set_title(title)
    handles, labels = ax.get_legend_handles_labels()
    if any_paper:
        handles.append(
            Line2D([], [], linestyle="none", marker="D", markerfacecolor="none", color="0.3")
        )
        labels.append(paper_label)
    # under the axes: inside, the legend of five policies covered their error bars
    bottom = add_notes(fig, [f"{name} (no run finished without an error)" for name in left_out])
    ncol = 2 if len(labels) > 2 else len(labels)
    fig.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, bottom), fontsize=8,
               ncol=ncol, frameon=False)
    rows = math.ceil(len(labels) / ncol)
    legend_h = (rows * 1.4 * 8 / 72 + 0.15) / fig.get_figheight()
    fig.tight_layout(rect=(0, bottom + legend_h, 1, 1))
    return fig


def _runs_label(members: Sequence[Mapping[str, Any]]) -> str:
    """The runs behind each point of a series: ``"3 runs per level"`` or ``"3-5 runs per
    level"`` (the ok runs, over which the rate is taken)."""
    counts = sorted({int(g.get("n_ok", g.get("n", 0))) for g in members})
    span = str(counts[0]) if len(counts) == 1 else f"{counts[0]}-{counts[-1]}"
    return f"{span} run{'s' if counts[-1] != 1 else ''} per level"


def _as_series(name: str, values: Any, field: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 3:
        require(arr.shape[1:] == (3, 3), f"{field}[{name!r}]", arr.shape, "(T,) or (T, 3, 3)")
        arr = np.trace(arr, axis1=1, axis2=2)
    require(arr.ndim == 1 and arr.size > 0, f"{field}[{name!r}]", arr.shape, "(T,) or (T, 3, 3)")
    return arr


def _time_axis(n: int, dt_s: float | None) -> tuple[np.ndarray, str]:
    if dt_s is None:
        return np.arange(n, dtype=float), "iteration"
    require(dt_s > 0 and math.isfinite(dt_s), "dt_s", dt_s, "a number > 0")
    return np.arange(n, dtype=float) * dt_s, "time (s)"


def plot_uncertainty_traces(
    traces: Mapping[str, Any],
    path: str | os.PathLike,
    *,
    dt_s: float | None = None,
    log_y: bool = True,
    title: str | None = "Vehicle uncertainty (trace of the pose covariance)",
    notes: Sequence[str] = (),
    figsize: tuple[float, float] = CURVE_FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """Trace of the vehicle pose covariance per iteration, one line per name (BB Figs. 3, 4;
    :func:`uncertainty_figure`), saved to ``path``."""
    return _save(uncertainty_figure(traces, dt_s=dt_s, log_y=log_y, title=title, notes=notes,
                                    figsize=figsize, dpi=dpi), path, dpi)


def uncertainty_figure(
    traces: Mapping[str, Any],
    *,
    dt_s: float | None = None,
    log_y: bool = True,
    title: str | None = "Vehicle uncertainty (trace of the pose covariance)",
    notes: Sequence[str] = (),
    figsize: tuple[float, float] = CURVE_FIGSIZE,
    dpi: int = DPI,
) -> Figure:
    """Trace of the vehicle pose covariance per iteration, one line per name (BB Figs. 3, 4).

    ``traces[name]`` is either the traces (T,) or the pose covariances (T, 3, 3). The trace adds
    m^2 (x, y) and rad^2 (heading), as in BB. The x axis is the iteration, or time with ``dt_s``.
    Identical series are drawn once and named together (:func:`identical_series`); ``notes``
    (what was left out) are written under the figure.
    """
    require(len(traces) > 0, "traces", dict(traces), "a non-empty mapping name -> array")
    series = {name: _as_series(name, values, "traces") for name, values in traces.items()}
    fig, ax = _new_figure(figsize, dpi)
    colors = {name: _COLORS[i % len(_COLORS)] for i, name in enumerate(series)}
    for names in identical_series(series):
        y = series[names[0]]
        x, xlabel = _time_axis(y.size, dt_s)
        ax.plot(x, y, color=colors[names[0]], linewidth=1.3, label=_same_label(names))
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("trace of pose covariance (m² + rad²)")
    if title:
        ax.set_title(title)
    ax.legend(loc="best", fontsize=9, framealpha=0.9)
    fig.tight_layout(rect=(0, add_notes(fig, notes), 1, 1))
    return fig


def nees_band(dof: int = 3, n_runs: int = 1, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square band of the (run-averaged) NEES: chi2(dof * n_runs) / n_runs."""
    require(isinstance(dof, int) and dof >= 1, "dof", dof, "an int >= 1")
    require(isinstance(n_runs, int) and n_runs >= 1, "n_runs", n_runs, "an int >= 1")
    require(0 < confidence < 1, "confidence", confidence, "a number in (0, 1)")
    from scipy.stats import chi2  # imported here: scipy.stats is slow to import

    tail = (1 - confidence) / 2
    lo, hi = chi2.ppf([tail, 1 - tail], dof * n_runs) / n_runs
    return float(lo), float(hi)


def plot_nees(
    nees: Mapping[str, Any] | Any,
    path: str | os.PathLike,
    *,
    dof: int = 3,
    n_runs: int = 1,
    confidence: float = 0.95,
    dt_s: float | None = None,
    log_y: bool = True,
    title: str | None = "Vehicle NEES",
    notes: Sequence[str] = (),
    figsize: tuple[float, float] = CURVE_FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """NEES per iteration with the chi-square band (:func:`nees_figure`), saved to ``path``."""
    return _save(nees_figure(nees, dof=dof, n_runs=n_runs, confidence=confidence, dt_s=dt_s,
                             log_y=log_y, title=title, notes=notes, figsize=figsize, dpi=dpi),
                 path, dpi)


def nees_figure(
    nees: Mapping[str, Any] | Any,
    *,
    dof: int = 3,
    n_runs: int = 1,
    confidence: float = 0.95,
    dt_s: float | None = None,
    log_y: bool = True,
    title: str | None = "Vehicle NEES",
    notes: Sequence[str] = (),
    figsize: tuple[float, float] = CURVE_FIGSIZE,
    dpi: int = DPI,
) -> Figure:
    """NEES per iteration with the chi-square ``confidence`` band for ``dof`` (3: x, y, theta).

    ``nees`` is an array (T,) or a mapping name -> array; NaN entries (no truth) leave gaps. With
    ``n_runs`` > 1 the values are taken as averages over that many runs and the band narrows to
    chi2(dof * n_runs) / n_runs. The legend gives each line's fraction of iterations in the band;
    identical series are drawn once and named together; ``notes`` are written under the figure.
    """
    series = dict(nees) if isinstance(nees, Mapping) else {"NEES": nees}
    require(len(series) > 0, "nees", series, "a non-empty array or mapping")
    series = {name: _as_series(name, values, "nees") for name, values in series.items()}
    lo, hi = nees_band(dof, n_runs, confidence)
    fig, ax = _new_figure(figsize, dpi)
    ax.axhspan(
        lo,
        hi,
        color="0.55",
        alpha=0.18,
        linewidth=0,
        label=f"χ² {100 * confidence:.0f} % band ({dof} dof): [{lo:.2f}, {hi:.2f}]",
    )
    ax.axhline(dof, color="0.35", linewidth=0.9, linestyle="--", label=f"expected ({dof})")
    colors = {name: _COLORS[i % len(_COLORS)] for i, name in enumerate(series)}
    for names in identical_series(series):
        y = series[names[0]]
        finite = np.isfinite(y)
        frac = float(np.mean((y[finite] >= lo) & (y[finite] <= hi))) if finite.any() else math.nan
        x, xlabel = _time_axis(y.size, dt_s)
        ax.plot(
            x,
            y,
            color=colors[names[0]],
            linewidth=1.1,
            label=f"{_same_label(names)} ({100 * frac:.0f} % in band)",
        )
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("NEES")
    if title:
        ax.set_title(title)
    ax.legend(loc="best", fontsize=9, framealpha=0.9)
    fig.tight_layout(rect=(0, add_notes(fig, notes), 1, 1))
    return fig


def _points(values: Any, field: str, min_cols: int = 2) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2))
    require(
        arr.ndim == 2 and arr.shape[1] >= min_cols, field, arr.shape, f"(N, >= {min_cols}) array"
    )
    return arr[:, :2]


def plot_run_map(
    path: str | os.PathLike,
    *,
    landmarks_true: Any,
    landmark_means: Any,
    landmark_covs: Any,
    path_true: Any,
    path_est: Any,
    sigma: float = 2.0,
    title: str | None = "Map of one run",
    failure: tuple[float, float, float] | None = None,
    figsize: tuple[float, float] = MAP_FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """One run's map (:func:`run_map_figure`), saved to ``path``."""
    return _save(run_map_figure(
        landmarks_true=landmarks_true, landmark_means=landmark_means, landmark_covs=landmark_covs,
        path_true=path_true, path_est=path_est, sigma=sigma, title=title, failure=failure,
        figsize=figsize, dpi=dpi), path, dpi)


def failure_title(title: str | None, failure: tuple[float, float, float] | None) -> str | None:
    """``title`` and, for a run that failed at ``failure = (t_s, x, y)``, a second line saying
    when and where (BB's criterion)."""
    if failure is None:
        return title
    t_s, x, y = failure
    line = f"failed at {t_s:.0f} s, at ({x:.0f}, {y:.0f}) m (BB's criterion; ✕ on the map)"
    return f"{title}\n{line}" if title else line


def run_map_figure(
    *,
    landmarks_true: Any,
    landmark_means: Any,
    landmark_covs: Any,
    path_true: Any,
    path_est: Any,
    sigma: float = 2.0,
    title: str | None = "Map of one run",
    failure: tuple[float, float, float] | None = None,
    figsize: tuple[float, float] = MAP_FIGSIZE,
    dpi: int = DPI,
) -> Figure:
    """One run: true landmarks, estimated landmarks with ``sigma``-sigma ellipses, both paths.

    ``landmarks_true`` (N, 2); ``landmark_means`` (M, 2) and ``landmark_covs`` (M, 2, 2), e.g. from
    ``LandmarkEstimate``; ``path_true`` and ``path_est`` (T, 2 or 3) poses (x, y[, theta]).
    An ellipse has semi-axes ``sigma * sqrt(eigenvalue)`` along the covariance's eigenvectors.
    ``failure`` ``(t_s, x, y)``: the run failed then, there (marked, and said in the title).
    """
    require(sigma > 0 and math.isfinite(sigma), "sigma", sigma, "a number > 0")
    lm_true = _points(landmarks_true, "landmarks_true")
    means = _points(landmark_means, "landmark_means")
    covs = np.asarray(landmark_covs, dtype=np.float64).reshape(-1, 2, 2)
    require(
        covs.shape[0] == means.shape[0],
        "landmark_covs",
        covs.shape,
        f"({means.shape[0]}, 2, 2) to match landmark_means",
    )
    p_true = _points(path_true, "path_true")
    p_est = _points(path_est, "path_est")

    fig, ax = _new_figure(figsize, dpi)
    ax.plot(p_true[:, 0], p_true[:, 1], color="0.25", linewidth=1.4, label="true path")
    ax.plot(p_est[:, 0], p_est[:, 1], color="#1f77b4", linewidth=1.2, label="estimated path")
    if len(p_true):
        ax.plot(*p_true[0], marker="o", color="0.25", markersize=6, linestyle="none")
    ax.scatter(
        lm_true[:, 0],
        lm_true[:, 1],
        marker="+",
        s=50,
        color="0.1",
        linewidths=1.2,
        label="true landmarks",
        zorder=3,
    )
    if len(means):
        evals, evecs = np.linalg.eigh(0.5 * (covs + np.swapaxes(covs, 1, 2)))
        evals = np.clip(evals, 0.0, None)
        angles = np.degrees(np.arctan2(evecs[:, 1, 1], evecs[:, 0, 1]))  # major axis direction
        ax.add_collection(
            EllipseCollection(
                widths=2 * sigma * np.sqrt(evals[:, 1]),
                heights=2 * sigma * np.sqrt(evals[:, 0]),
                angles=angles,
                units="xy",
                offsets=means,
                offset_transform=ax.transData,
                facecolors="none",
                edgecolors="#d62728",
                linewidths=0.9,
                zorder=4,
            )
        )
        ax.scatter(
            means[:, 0],
            means[:, 1],
            marker="s",
            s=14,
            color="#d62728",
            label=f"estimated landmarks ({sigma:g}σ ellipses)",
            zorder=5,
        )
    if failure is not None:
        ax.plot(failure[1], failure[2], marker="X", markersize=11, color="#ff7f0e",
                markeredgecolor="k", linestyle="none", zorder=6,
                label=f"where it failed ({failure[0]:.0f} s)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    title = failure_title(title, failure)
    if title:
        ax.set_title(title, fontsize=11 if failure is None else 10)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, fontsize=8, frameon=False)
    fig.tight_layout()
    return fig


def plot_episode_map(episode, path: str | os.PathLike, title: str) -> str:
    """BB Fig. 2 for one finished :class:`~slam_gym.episode.Episode`: truth, confirmed features
    with ellipses, both paths, where it failed if it did (:func:`plot_run_map`); the path as a
    str."""
    from slam_gym.evaluation.episodes import failure_point

    lm = episode.confirmed_landmarks()
    return str(plot_run_map(
        path, landmarks_true=episode.stream.landmarks_true, landmark_means=lm.means,
        landmark_covs=lm.covs, path_true=np.array(episode.trace.true_poses),
        path_est=np.array(episode.trace.est_poses), title=title,
        failure=failure_point(episode),
    ))


def recorded_map_figure(recording: Mapping[str, Any], title: str) -> Figure:
    """:func:`run_map_figure` of a run's recording (:mod:`slam_gym.evaluation.episodes`)."""
    failure = None
    if recording["failed"] and recording["failure_t_s"] is not None:
        x, y = np.asarray(recording["failure_position"], dtype=float)[:2]
        failure = (float(recording["failure_t_s"]), float(x), float(y))
    return run_map_figure(
        landmarks_true=recording["landmarks_true"], landmark_means=recording["landmark_means"],
        landmark_covs=recording["landmark_covs"], path_true=recording["true_poses"],
        path_est=recording["est_poses"], title=title, failure=failure)


def plot_recorded_map(recording: Mapping[str, Any], path: str | os.PathLike, title: str) -> Path:
    """:func:`recorded_map_figure`, saved to ``path``."""
    return _save(recorded_map_figure(recording, title), path, DPI)


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point dominates, both coordinates to be minimised.

    ``a`` dominates ``b`` when it is no worse in both coordinates and better in one. Points with
    a non-finite coordinate are never on the front.
    """
    pts = [(float(x), float(y)) for x, y in points]
    front = []
    for i, (x, y) in enumerate(pts):
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        dominated = any(
            math.isfinite(a) and math.isfinite(b) and a <= x and b <= y and (a < x or b < y)
            for j, (a, b) in enumerate(pts)
            if j != i
        )
        if not dominated:
            front.append(i)
    return front


AXIS_LABELS = {
    "total_cpu_s": "CPU time per run: filtering, fusions and optimisations (s, log scale)",
    "interface_cpu_s": "CPU time per run of fusions and optimisations (s, log scale)",
    "fusion_cpu_s": "CPU time per run of fusions (s, log scale)",
    "optimise_cpu_s": "CPU time per run of optimisations (s, log scale)",
    "filter_cpu_s": "CPU time per run of filtering (s, log scale)",
    "map_error_m_succeeded": "map error of the successful runs (m)",
    "map_error_m": "map error (m)",
    "anees": "ANEES (average NEES, no unit)",
    "map_completeness": "map completeness (fraction of landmarks)",
}
"""Words and units of the fields :func:`plot_pareto` draws (CPU axes are logarithmic)."""


def pareto_figure(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    *,
    x: str = "total_cpu_s",
    y: str = "map_error_m_succeeded",
    title: str | None = "Map error against compute",
    dpi: int = DPI,
) -> Figure:
    """The figure of :func:`plot_pareto` (not saved): its axes and error bars can be checked."""
    groups = list(summary["groups"] if isinstance(summary, Mapping) else summary)

    def value(g, key):
        v = g.get(key)
        return v.get("mean") if isinstance(v, Mapping) else v

    groups = [g for g in groups if value(g, x) is not None and value(g, y) is not None]
    require(len(groups) > 0, "summary", "no group", f"groups with {x} and {y}")
    log_x = x.endswith("_cpu_s")
    if log_x:  # a point without CPU time has no place on a log axis: said on the figure
        left_out = sorted({_name(g) for g in groups if value(g, x) <= 0})
        groups = [g for g in groups if value(g, x) > 0]
        require(len(groups) > 0, "summary", "no group", f"groups with {x} > 0 and {y}")
    else:
        left_out = []
    levels = sorted({g.get("clutter_level") for g in groups}, key=lambda v: (v is None, v))
    names = list(dict.fromkeys(_name(g) for g in groups))
    colors = {n: _COLORS[i % len(_COLORS)] for i, n in enumerate(names)}
    width = max(3.6 * len(levels) + 3.2, 8.5)
    fig = Figure(figsize=(width, 4.6), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(levels), squeeze=False, sharey=True)[0]
    labels: list[tuple[Any, Any]] = []  # (axes, annotation) of the numbers beside the points
    for ax, level in zip(axes, levels, strict=True):
        members = [g for g in groups if g.get("clutter_level") == level]
        pts = [(value(g, x), value(g, y)) for g in members]
        front = set(pareto_front(pts))
        for i, g in enumerate(members):
            name = _name(g)
            ci = g.get("ci95") or {}
            xerr = _half_widths(pts[i][0], ci.get(x))
            yerr = _half_widths(pts[i][1], ci.get(y))
            ax.errorbar(
                [pts[i][0]], [pts[i][1]], xerr=xerr, yerr=yerr, fmt="o", ms=7,
                color=colors[name], mfc=colors[name] if i in front else "white",
                capsize=2, lw=0.8,
            )
            n_y, n_x = ((g.get("n_values") or {}).get(key) for key in (y, x))
            if n_y is not None:
                text = str(n_y) if n_x in (None, n_y) else f"{n_y}/{n_x}"
                labels.append((ax, ax.annotate(
                    text, (pts[i][0], pts[i][1]), textcoords="offset points",
                    xytext=LABEL_OFFSETS[0], fontsize=7, color=colors[name])))
        ordered = sorted(front, key=lambda i: pts[i][0])
        ax.plot([pts[i][0] for i in ordered], [pts[i][1] for i in ordered], "k--", lw=0.8)
        ax.grid(True, alpha=0.3, linewidth=0.6)
        ax.set_title(f"clutter level {level}" if level is not None else "", fontsize=10)
    # limits from the points and their intervals: a log axis shows every positive bound (a
    # bound at 0 runs to its edge), a non-negative quantity starts at 0
    xs, ys = _extent(groups, x, value), _extent(groups, y, value)
    if log_x:
        positive = [v for v in xs if v > 0]
        for ax in axes:  # one scale for every panel, labelled at a few round values
            set_log_axis(ax.xaxis, min(positive) / 1.5, max(positive) * 1.5,
                         max_ticks=4 if len(levels) > 1 else 6)
    if y in NON_NEGATIVE_KEYS:
        axes[0].set_ylim(0.0, max(max(ys), 1e-9) * 1.1)
    axes[0].set_ylabel(AXIS_LABELS.get(y, y))
    fig.supxlabel(AXIS_LABELS.get(x, x), fontsize=9)  # one label: the panels share the axis
    handles = [Line2D([], [], marker="o", ls="", color=colors[n], label=n) for n in names]
    handles += [
        Line2D([], [], marker="o", ls="", color="k", mfc="white", label="dominated"),
        Line2D([], [], ls="--", color="k", label="non-dominated front"),
        Line2D([], [], marker="|", ls="-", color="k",
               label="bars: 95 % interval of the mean\n(percentile bootstrap)"),
        Line2D([], [], ls="", label="number beside a point: runs\nbehind its mean (y/x where\n"
               "they differ)"),
    ]
    handles += [Line2D([], [], ls="", label=f"not drawn (no {x}):\n{', '.join(left_out)}")
                ] if left_out else []
    fig.legend(handles=handles, loc="center right", fontsize=7, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1 - 2.6 / width, 1))
    place_labels(fig, labels)
    return fig


LABEL_OFFSETS = ((5, 4), (5, -11), (-12, 4), (-12, -11), (5, 14), (-12, 14), (5, -21),
                 (-12, -21), (16, 4), (-24, 4), (16, -11), (-24, -11), (5, 24), (5, -31),
                 (-24, 24), (-24, -31))
"""Where (points from its point) a number beside a point of :func:`pareto_figure` may go, in
order of preference: the first where it covers no other number."""


def place_labels(fig: Figure, labels: Sequence[tuple[Any, Any]]) -> None:
    """Move each annotation of ``labels`` ((axes, annotation) pairs, in drawing order) to the
    first of :data:`LABEL_OFFSETS` where its text overlaps none placed before it (nor leaves its
    axes); one moved beyond the first ring gets a thin leader line to its point."""
    renderer = fig.canvas.get_renderer()
    placed: list[Any] = []
    for ax, ann in labels:
        frame = ax.get_window_extent(renderer)
        chosen = None
        for offset in LABEL_OFFSETS:
            ann.xyann = offset
            box = ann.get_window_extent(renderer).expanded(1.1, 1.15)
            inside = (frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0
                      and box.y1 <= frame.y1)
            if inside and not any(box.overlaps(other) for other in placed):
                chosen = offset
                break
        if chosen is None:  # no free place: the first, on top, rather than none
            chosen = LABEL_OFFSETS[0]
            ann.xyann = chosen
        if abs(chosen[0]) > 12 or abs(chosen[1]) > 11:  # far from its point: a leader line
            leader = {"arrowstyle": "-", "color": ann.get_color(), "lw": 0.5, "shrinkA": 0,
                      "shrinkB": 3}
            moved = ax.annotate(ann.get_text(), ann.xy, textcoords="offset points",
                                xytext=chosen, fontsize=ann.get_fontsize(),
                                color=ann.get_color(), arrowprops=leader)
            ann.remove()
            ann = moved
        placed.append(ann.get_window_extent(renderer))


def plot_pareto(
    summary: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    path: str | os.PathLike,
    *,
    x: str = "total_cpu_s",
    y: str = "map_error_m_succeeded",
    title: str | None = "Map error against compute",
    dpi: int = DPI,
) -> Path:
    """Mean ``y`` against mean ``x`` per policy (or system), one panel per clutter level.

    Error bars are the groups' 95 % intervals (``ci95``: percentile bootstrap intervals for the
    non-negative quantities, so they stay within the runs' range), and the number beside each
    point is the number of runs behind its ``y`` (``n_values``). A CPU axis is logarithmic (a
    group without CPU time is left out and named on the figure). Axes are labelled in words
    with units (:data:`AXIS_LABELS`). The non-dominated points of a panel are filled and joined
    by the front, dominated ones are hollow. Groups without both values are left out (e.g. a
    system row without compute). The default ``y`` is the map error of the runs that did not
    fail: a rule that fails everywhere (pure FastSLAM) has no point, rather than a small early
    map that would look accurate and cheap.
    """
    return _save(pareto_figure(summary, x=x, y=y, title=title, dpi=dpi), path, dpi)


def _extent(groups: Sequence[Mapping[str, Any]], key: str, value: Any) -> list[float]:
    """Every mean of ``key`` and every bound of its interval, over ``groups``."""
    out = []
    for g in groups:
        out.append(value(g, key))
        out += list((g.get("ci95") or {}).get(key) or [])
    return [float(v) for v in out if v is not None]


def _name(group: Mapping[str, Any]) -> str:
    return next(group[k] for k in JOB_KINDS if group.get(k))


def _half_widths(centre: float, ci) -> list[list[float]] | None:
    """Asymmetric error-bar half-widths from an interval (None: no bar)."""
    if ci is None:
        return None
    return [[max(centre - ci[0], 0.0)], [max(ci[1] - centre, 0.0)]]
