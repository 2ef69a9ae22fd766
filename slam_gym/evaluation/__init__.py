"""Generic evaluation machinery: jobs, parallel resumable execution, results, summary, plots.

Typical use (the run function is any picklable ``run_fn(job) -> dict`` with the metrics of
:data:`RESULT_KEYS`)::

    jobs = expand_grid(["fixed-10s", "esdf-innovation"], [0, 1, 2, 3], range(50))
    rows = run_jobs(jobs, run_fn, "out/", workers=8)          # skips runs already in out/
    doc = write_summary("out/", rows)                         # summary.json, table.md
    plot_success_rates(doc, "out/success.png")

The whole benchmark of any policies (names, ``package.module:attribute`` references, policy
objects) is one call, the function ``slam-gym benchmark`` runs (:mod:`.benchmarking`)::

    result = benchmark(["fixed-10s", MyRule()], clutter_levels=[2], seeds=5, out="out/mine")
    result.rows, result.summary, result.figures

The output files and their keys are a public contract (docs/ARCHITECTURE.md, "The command line and
its output files"). The plotting
functions are imported lazily (matplotlib is not needed by the worker processes).
"""

from typing import Any

from slam_gym.evaluation.benchmarking import BenchmarkResult, benchmark
from slam_gym.evaluation.executors import run_jobs
from slam_gym.evaluation.jobs import Job, expand_grid
from slam_gym.evaluation.results import RESULT_KEYS, ResultError, read_results, validate_result
from slam_gym.evaluation.summary import markdown_table, summarise, wilson_interval, write_summary

_PLOTS = (
    "nees_band",
    "pareto_front",
    "plot_episode_map",
    "plot_nees",
    "plot_pareto",
    "plot_run_map",
    "plot_success_rates",
    "plot_uncertainty_traces",
)
"""The plotting functions, imported from :mod:`.plots` on first use."""

__all__ = [
    "RESULT_KEYS",
    "BenchmarkResult",
    "Job",
    "ResultError",
    "benchmark",
    "expand_grid",
    "markdown_table",
    "read_results",
    "run_jobs",
    "summarise",
    "validate_result",
    "wilson_interval",
    "write_summary",
    *_PLOTS,
]
"""The user-facing names: the benchmark, jobs and their execution, the results file, the
summary and the figures. The machinery behind them (executors, the writer, file names, the
table formats) is imported from its module (:mod:`.executors`, :mod:`.results`,
:mod:`.summary`)."""


def __getattr__(name: str) -> Any:
    if name in _PLOTS:
        from slam_gym.evaluation import plots

        return getattr(plots, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
