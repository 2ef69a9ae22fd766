"""Across training seeds: the spread of their evaluations, the chosen seed, the curves (PNG).

The seed to ship is chosen on the *training-time* evaluation worlds (``eval.csv``, seeds below
the training worlds and disjoint from the benchmark's reported worlds), by the mean return of
its final evaluation (the objective the agent optimised), success rate breaking ties. Nothing
here reads the reported worlds. Each seed is represented by the evaluation mode (deterministic
or sampled actions, :data:`slam_gym.training.run.EVAL_MODES`) with the higher mean return on
those same worlds; that mode ships with its model (``deterministic`` in ``model.json``).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from slam_gym.training.run import chosen_mode, mode_record, read_eval_log

SUMMARY_KEYS: tuple[str, ...] = ("success_rate", "mean_return", "map_error_m", "anees",
                                 "n_fusions", "n_optimisations", "interface_cpu_s")


def read_monitor(run_dir: Path) -> list[dict[str, float]]:
    """Every training episode of a run (all segments), with its cumulative decision count ``t``.

    A segment is the run from one start (``monitor_<start>.monitor.csv``); a resumed run starts a
    new one at its checkpoint, so the episodes an interrupted segment ran past the next segment's
    start were discarded with the lost progress and are left out here."""
    rows: list[dict[str, float]] = []
    files = sorted(Path(run_dir, "logs").glob("monitor_*.monitor.csv"),
                   key=lambda p: int(p.name.split("_")[1].split(".")[0]))
    starts = [float(f.name.split("_")[1].split(".")[0]) for f in files]
    for file, start, end in zip(files, starts, starts[1:] + [math.inf], strict=True):
        t = start
        with file.open() as fh:
            fh.readline()  # the JSON header line
            for row in csv.DictReader(fh):
                t += float(row["l"])
                if t > end:
                    break
                rows.append({"t": t, "return": float(row["r"]), "length": float(row["l"]),
                             "failed": row.get("failed") == "True",
                             "n_optimisations": _number(row.get("n_optimisations"))})
    return rows


def _number(text: Any) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def summarise_seeds(runs: dict[int, Path]) -> dict[str, Any]:
    """Final training-time evaluation per seed, its mean/std/min/max, and the chosen seed."""
    finals = {}
    for seed, run_dir in runs.items():
        log = read_eval_log(run_dir)
        if log:
            mode = chosen_mode(log[-1])
            finals[seed] = {**mode_record(log[-1], mode), "mode": mode}
    if not finals:
        raise ValueError("runs are invalid: no run has an evaluation yet (eval.csv)")
    spread = {}
    for key in SUMMARY_KEYS:
        values = np.array([f[key] for f in finals.values()], dtype=float)
        values = values[np.isfinite(values)]
        spread[key] = ({"mean": float(values.mean()), "std": float(values.std(ddof=1))
                        if len(values) > 1 else 0.0, "min": float(values.min()),
                        "max": float(values.max())} if len(values) else None)
    best = max(finals, key=lambda s: (finals[s]["mean_return"], finals[s]["success_rate"]))
    return {
        "seeds": sorted(finals),
        "final_evaluation": {str(s): finals[s] for s in sorted(finals)},
        "spread": spread,
        "chosen_seed": int(best),
        "chosen_by": "mean return of the final evaluation on the training-time evaluation "
                     "worlds (success rate breaks ties)",
    }


def write_summary(out: Path, algo: str, runs: dict[int, Path],
                  baseline: tuple[str, dict[str, float]] | None = None) -> dict[str, Any]:
    """``summary.json`` and ``summary.md`` in ``out`` (with ``baseline``'s record on the same
    worlds, if given)."""
    doc = {"algo": algo, **summarise_seeds(runs)}
    if baseline is not None:
        doc["baseline"] = {"policy": baseline[0], **baseline[1]}
    (out / "summary.json").write_text(json.dumps(doc, indent=2) + "\n")
    lines = [f"# {algo.upper()}: final training-time evaluation per seed", "",
             "| seed | mode | decisions | success | mean return | map error (m) | ANEES | "
             "fusions | optimisations |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for seed, f in doc["final_evaluation"].items():
        lines.append(f"| {seed} | {f['mode']} | {f['timesteps']:.0f} | {f['success_rate']:.2f} | "
                     f"{f['mean_return']:.0f} | {f['map_error_m']:.2f} | {f['anees']:.2f} | "
                     f"{f['n_fusions']:.0f} | {f['n_optimisations']:.1f} |")
    s = doc["spread"]
    lines += ["", "spread over seeds (mean ± std [min, max]):"]
    for key in SUMMARY_KEYS:
        if s[key] is not None:
            lines.append(f"- {key}: {s[key]['mean']:.3g} ± {s[key]['std']:.2g} "
                         f"[{s[key]['min']:.3g}, {s[key]['max']:.3g}]")
    if baseline is not None:
        b = doc["baseline"]
        lines += ["", f"on the same worlds, `{b['policy']}`: success {b['success_rate']:.2f}, "
                  f"return {b['mean_return']:.0f}, map error {b['map_error_m']:.2f} m, "
                  f"{b['n_optimisations']:.1f} optimisations/episode"]
    lines += ["", f"chosen seed: {doc['chosen_seed']} ({doc['chosen_by']})", ""]
    (out / "summary.md").write_text("\n".join(lines))
    return doc


def plot_curves(out_png: Path, runs: dict[int, Path], title: str,
                baseline: tuple[str, dict[str, float]] | None = None) -> Path:
    """Training return (rolling mean of 20 episodes), and evaluation success, return and
    optimisations per episode, against decisions, one line per seed; ``baseline`` (a policy's
    name and its :func:`~slam_gym.training.evaluation.evaluate_policy` record on the same
    evaluation worlds) is drawn as a horizontal line on the evaluation panels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for seed, run_dir in sorted(runs.items()):
        episodes = read_monitor(run_dir)
        if len(episodes) >= 1:
            t = np.array([e["t"] for e in episodes])
            r = np.array([e["return"] for e in episodes])
            window = min(20, len(r))
            smooth = np.convolve(r, np.ones(window) / window, mode="valid")
            axes[0, 0].plot(t[window - 1:], smooth, label=f"seed {seed}")
        log = read_eval_log(run_dir)
        if log:
            t = [row["timesteps"] for row in log]
            for prefix, style, what in (("", "o-", "deterministic"), ("sampled_", "s--",
                                                                      "sampled")):
                if prefix and not any(np.isfinite(r.get(prefix + "mean_return", np.nan))
                                      for r in log):
                    continue
                colour = {} if not prefix else {"color": axes[0, 1].lines[-1].get_color()}
                for ax, key in ((axes[0, 1], "mean_return"), (axes[1, 0], "success_rate"),
                                (axes[1, 1], "n_optimisations")):
                    ax.plot(t, [r.get(prefix + key, np.nan) for r in log], style,
                            label=f"seed {seed}, {what}", **colour)
    if baseline is not None:
        name, record = baseline
        for ax, key in ((axes[0, 1], "mean_return"), (axes[1, 0], "success_rate"),
                        (axes[1, 1], "n_optimisations")):
            ax.axhline(record[key], color="black", linestyle=":", label=f"{name} (same worlds)")
    axes[0, 0].set_title("training episodes: return (rolling mean of 20)")
    axes[0, 1].set_title("evaluation worlds: mean return")
    axes[1, 0].set_title("evaluation worlds: success rate")
    axes[1, 1].set_title("evaluation worlds: optimisations per episode")
    axes[1, 0].set_ylim(-0.05, 1.05)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax in axes[1]:
        ax.set_xlabel("decisions trained")
    fig.suptitle(title)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png


def summarise_runs(out: Path, algo: str, runs: dict[int, Path], title: str,
                   baseline: tuple[str, dict[str, float]] | None = None) -> dict[str, Any]:
    """What ``slam-gym train`` writes for its seeds, into ``out``: ``summary.{json,md}``,
    ``training_curves.png`` (with ``baseline``'s line, see :func:`plot_curves`) and the chosen
    seed's model as ``model.zip`` / ``model.json`` (with ``chosen_among_seeds`` and
    ``chosen_by``). Returns the summary document (``baseline``: its name and record)."""
    from slam_gym.training.run import copy_model

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = write_summary(out, algo, runs, baseline)
    plot_curves(out / "training_curves.png", runs, title=title, baseline=baseline)
    chosen = copy_model(runs[doc["chosen_seed"]], out / "model.zip")
    config = json.loads(chosen.with_suffix(".json").read_text())
    config["chosen_among_seeds"] = doc["seeds"]
    config["chosen_by"] = doc["chosen_by"]
    chosen.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
    return doc
