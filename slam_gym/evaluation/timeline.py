"""When a policy fuses and optimises along one episode, against the loop closure (a figure).

:func:`decision_timeline` plays one episode of a policy object and records, per decision, the
time, whether a fusion and an optimisation happened (the counters' increments, so an action the
system could not carry out is not drawn), the back-end's loop-closure flag (CM Definition 1,
the ``loop_closure_flag`` feature) and the reward's modelled compute seconds (``compute_s``).
The *true* loop closure is the first scan in the second half of the path that sees a landmark
seen in its first tenth (the re-observation that closes BB's loop, as ``slam-gym simulate``
reports it). :func:`plot_decision_timelines` draws one row per policy.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slam_gym.evaluation.core import run_policy_object
from slam_gym.scenarios import get_scenario


def true_loop_closure_s(stream, start_fraction: float = 0.1) -> float | None:
    """Time of the first scan after half the path that sees a landmark of the path's first
    ``start_fraction`` (None if the path never closes its loop)."""
    scans = [(s.t_s, s.truth.visible_ids) for s in stream if s.truth.visible_ids is not None]
    if not scans:
        return None
    head = {int(i) for _, ids in scans[:max(1, int(start_fraction * len(scans)))] for i in ids}
    for t, ids in scans[len(scans) // 2:]:
        if head & {int(i) for i in ids}:
            return float(t)
    return None


def decision_timeline(policy, scenario: str, clutter_level, seed: int, **env_options):
    """One episode of ``policy`` with its decisions recorded (see the module docstring);
    ``(timeline, episode, env)``."""
    records: dict[str, list] = {"t_s": [], "fused": [], "optimised": [], "closure_flag": [],
                                "compute_s": []}
    counts = {"n_fusions": 0, "n_optimisations": 0}
    rate_hz = get_scenario(scenario).filter_rate_hz

    def on_step(action, info):
        records["t_s"].append(info["iteration"] / rate_hz)
        records["fused"].append(info["n_fusions"] > counts["n_fusions"])
        records["optimised"].append(info["n_optimisations"] > counts["n_optimisations"])
        records["closure_flag"].append(bool(info["features"]["loop_closure_flag"]))
        records["compute_s"].append(float(info["reward_components"]["compute_s"]))
        counts.update(n_fusions=info["n_fusions"], n_optimisations=info["n_optimisations"])

    episode, env = run_policy_object(policy, scenario, clutter_level, seed, on_step=on_step,
                                     **env_options)
    out: dict[str, Any] = {k: np.asarray(v) for k, v in records.items()}
    out.update(
        true_loop_closure_s=true_loop_closure_s(env.stream),
        end_s=float(episode.t_s),
        failed=bool(episode.failure.failed),
        n_fusions=episode.n_fusions,
        n_optimisations=episode.n_optimisations,
    )
    return out, episode, env


def plot_decision_timelines(
    timelines: Mapping[str, Mapping[str, Any]], path: str | os.PathLike, title: str = ""
) -> Path:
    """One row per policy: fusions (ticks above its line), optimisations (below), the
    back-end's detected closures (triangles) and the true loop closure (dashed line)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(timelines)
    fig, ax = plt.subplots(figsize=(11, 1.0 + 0.8 * len(names)))
    labelled = set()

    def label(text):
        if text in labelled:
            return None
        labelled.add(text)
        return text

    for row, name in enumerate(names):
        tl = timelines[name]
        t = np.asarray(tl["t_s"])
        y = len(names) - 1 - row
        ax.vlines(t[np.asarray(tl["fused"], bool)], y + 0.02, y + 0.32, color="tab:blue",
                  lw=1.0, label=label("fusion"))
        ax.vlines(t[np.asarray(tl["optimised"], bool)], y - 0.32, y - 0.02, color="tab:red",
                  lw=1.2, label=label("optimisation"))
        flags = t[np.asarray(tl["closure_flag"], bool)]
        ax.plot(flags, np.full(len(flags), y + 0.4), "kv", ms=4,
                label=label("closure detected (CM Def. 1)"))
        ax.plot([tl["end_s"]], [y], "x" if tl.get("failed") else "|", color="k", ms=10,
                label=label("failure" if tl.get("failed") else "end of path"))
        if tl.get("true_loop_closure_s") is not None:
            ax.vlines(tl["true_loop_closure_s"], y - 0.45, y + 0.45, colors="tab:green",
                      linestyles="--", lw=1.5, label=label("true loop closure"))
    ax.set_yticks(range(len(names)))
    ax.set_yticklabels(
        [f"{n} ({timelines[n]['n_fusions']} fus., {timelines[n]['n_optimisations']} opt.)"
         for n in reversed(names)], fontsize=8)
    ax.set_ylim(-0.7, len(names) - 0.2)
    ax.set_xlabel("time (s)")
    ax.set_title(title)
    fig.legend(loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.12 if len(names) > 2 else 0.2, 1, 1))
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
