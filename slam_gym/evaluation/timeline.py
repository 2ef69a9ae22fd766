"""When a policy fuses and optimises along one episode, against the loop closure (a figure).

:func:`decision_timeline` plays one episode of a policy object and records, per decision, the
time, whether a fusion and an optimisation happened (the counters' increments, so an action the
system could not carry out is not drawn), the back-end's loop-closure flag (CM Definition 1,
the ``loop_closure_flag`` feature) and the reward's modelled compute seconds (``compute_s``).
The *true* loop closure is the first scan in the second half of the path that sees a landmark
seen in its first tenth (the re-observation that closes BB's loop, as ``slam-gym simulate``
reports it). :func:`plot_decision_timelines` draws one row per policy. The recording itself
(:class:`TimelineRecorder`, :func:`true_loop_closure_s`) lives in :mod:`.episodes`, where the
benchmark's runs use it to record their figure world.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from slam_gym.evaluation.core import run_policy_object
from slam_gym.evaluation.episodes import TimelineRecorder, true_loop_closure_s
from slam_gym.scenarios import get_scenario

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn, not in the workers
    from matplotlib.figure import Figure

DPI = 110
LEGEND_ORDER = ("fusion", "optimisation", "closure detected (CM Def. 1)", "true loop closure",
                "end of path", "failure (BB's criterion)")
"""The entries of the decisions figure's legend, in this order (those drawn)."""

__all__ = ["TimelineRecorder", "decision_timeline", "decisions_figure",
           "plot_decision_timelines", "true_loop_closure_s"]


def decision_timeline(policy, env, clutter_level, seed: int, *, draw: int = 0):
    """One episode of ``policy`` in ``env`` (a :class:`~slam_gym.envs.spec.ResolvedEnv` or a
    registered id) with its decisions recorded (see the module docstring);
    ``(timeline, episode, env)``."""
    from slam_gym.envs.spec import ResolvedEnv, resolve_env

    spec = env if isinstance(env, ResolvedEnv) else resolve_env(env)
    recorder = TimelineRecorder(get_scenario(spec.scenario).filter_rate_hz)
    episode, env = run_policy_object(policy, spec, clutter_level, seed, draw=draw,
                                     on_step=recorder.on_step)
    return recorder.finish(episode, env), episode, env


def plot_decision_timelines(
    timelines: Mapping[str, Mapping[str, Any]], path: str | os.PathLike, title: str = "",
    notes: Sequence[str] = (),
) -> Path:
    """:func:`decisions_figure`, saved to ``path`` as a PNG."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    decisions_figure(timelines, title=title, notes=notes).savefig(out, dpi=DPI)
    return out


def decisions_figure(timelines: Mapping[str, Mapping[str, Any]], title: str = "",
                     notes: Sequence[str] = ()) -> Figure:
    """One row per policy: fusions (ticks above its line), optimisations (below), the
    back-end's detected closures (triangles), where its run ended or failed, and the true loop
    closure (dashed line). The legend lists only what is drawn; ``notes`` (policies left out)
    are written under the figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from slam_gym.evaluation.plots import add_notes

    names = list(timelines)
    fig = Figure(figsize=(11, 1.0 + 0.8 * len(names)))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    labelled = set()

    def label(text, drawn):
        """The legend label of an artist: only once, and only for one that shows something."""
        if text in labelled or not drawn:
            return None
        labelled.add(text)
        return text

    for row, name in enumerate(names):
        tl = timelines[name]
        t = np.asarray(tl["t_s"], dtype=float)
        y = len(names) - 1 - row
        fused = t[np.asarray(tl["fused"], bool)]
        optimised = t[np.asarray(tl["optimised"], bool)]
        flags = t[np.asarray(tl["closure_flag"], bool)]
        if len(fused):
            ax.vlines(fused, y + 0.02, y + 0.32, color="tab:blue", lw=1.0,
                      label=label("fusion", True))
        if len(optimised):
            ax.vlines(optimised, y - 0.32, y - 0.02, color="tab:red", lw=1.2,
                      label=label("optimisation", True))
        if len(flags):
            ax.plot(flags, np.full(len(flags), y + 0.4), "kv", ms=4,
                    label=label("closure detected (CM Def. 1)", True))
        failed = bool(tl.get("failed"))
        ax.plot([tl["end_s"]], [y], "x" if failed else "|", color="k", ms=10,
                label=label("failure (BB's criterion)" if failed else "end of path", True))
        if tl.get("true_loop_closure_s") is not None:
            ax.vlines(tl["true_loop_closure_s"], y - 0.45, y + 0.45, colors="tab:green",
                      linestyles="--", lw=1.5, label=label("true loop closure", True))
    ax.set_yticks(range(len(names)))
    ax.set_yticklabels(
        [f"{n} ({timelines[n]['n_fusions']} fus., {timelines[n]['n_optimisations']} opt.)"
         for n in reversed(names)], fontsize=8)
    ax.set_ylim(-0.7, len(names) - 0.2)
    ends = [float(timelines[n]["end_s"]) for n in names]
    ends += [float(timelines[n]["true_loop_closure_s"]) for n in names
             if timelines[n].get("true_loop_closure_s") is not None]
    ax.set_xlim(0.0, 1.02 * max(ends + [1.0]))
    ax.set_xlabel("time (s)")
    ax.set_title(title)
    pairs = dict(zip(*reversed(ax.get_legend_handles_labels()), strict=True))
    labels = sorted(pairs, key=LEGEND_ORDER.index)
    handles = [pairs[label] for label in labels]
    notes_h = add_notes(fig, notes)
    fig.legend(handles, labels, loc="lower center", ncol=max(1, len(labels)), fontsize=8,
               frameon=False, bbox_to_anchor=(0.5, notes_h))
    legend_h = 0.35 / fig.get_figheight()  # one row of the legend, in figure height
    fig.tight_layout(rect=(0, notes_h + legend_h + 0.02, 1, 1))
    return fig
