"""A deterministic model of the CPU time the interface decisions cost (issue 13, reward term).

Measured CPU time can never repeat, and the env's reward must (same seed -> same reward). So the
reward charges *modelled* seconds: an operation count of each piece of work, which depends only on
the sizes of the estimates, times a cost per operation fitted once against measured CPU time
(:func:`calibrate`, on the records ``slam-gym speed --calibrate-compute`` collects
(:func:`slam_gym.commands.speed.collect_records`); the fit and its correlation
with the measurements are in docs/PERFORMANCE.md).

Operation counts (the dominant dense or sparse linear algebra of each piece of work):

=====================  ==========================================================================
``filter-fastslam``    one FastSLAM iteration: ``P (1 + M)``, ``P`` particles, ``M`` local features
                       (the per-particle update and the copies of per-particle maps at resampling)
``filter-ekf``         one EKF-SLAM iteration: ``(3 + 2M)^2`` (the covariance update)
``fusion-ekf``         BB section 4: augmenting and updating the joint covariance,
                       ``n^2 (1 + 2k)``, ``n = 6 + 2N + 2M`` the augmented state (``N`` global,
                       ``M`` local features), ``k`` matched pairs (BB (10), 2 rows each)
``fusion-relative``    the same augmentation for JCBB, ``n^2``, plus the chain estimate's refresh,
                       ``(3 + 2N) d``, ``d`` the relative state's dimension
``optimise``           ``(i + 1) r + (3 + 2N)^2``: ``i`` Gauss-Newton iterations over the ``r``
                       rows of the stacked sub-map constraints, plus the covariance write-back
=====================  ==========================================================================

Each kind costs ``intercept_s + seconds_per_op * ops``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

COMPUTE_KINDS: tuple[str, ...] = (
    "filter-fastslam",
    "filter-ekf",
    "fusion-ekf",
    "fusion-relative",
    "optimise",
)


@dataclass(frozen=True)
class LinearCost:
    """``intercept_s + seconds_per_op * ops``."""

    intercept_s: float
    seconds_per_op: float

    def __call__(self, ops: float) -> float:
        return self.intercept_s + self.seconds_per_op * float(ops)


# Fitted by `slam-gym speed --calibrate-compute --calibration-seeds 0,1` (docs/PERFORMANCE.md
# gives the machine, the date, the commit and the correlation of model and measurement): the
# median of three fits on a quiet machine, two significant figures. The filter's intercept is per
# decision interval (its operations count all the interval's iterations). Refitted at the end of
# issue 27 (the compiled front-end and optimiser, and a machine on which the code before the
# lineage regression runs at the speed this project's docs first gave it).
DEFAULT_COSTS: dict[str, LinearCost] = {
    "filter-fastslam": LinearCost(1.4e-3, 5.0e-8),
    "filter-ekf": LinearCost(3.3e-3, 2.9e-7),
    "fusion-ekf": LinearCost(8.6e-4, 5.0e-9),
    "fusion-relative": LinearCost(7.8e-3, 9.4e-7),
    "optimise": LinearCost(8.4e-4, 2.4e-7),
}


@dataclass(frozen=True)
class ComputeModel:
    """Modelled CPU seconds per piece of work (module docstring)."""

    costs: dict = field(default_factory=lambda: dict(DEFAULT_COSTS))

    def seconds(self, kind: str, ops: float) -> float:
        if kind not in self.costs:
            raise ValueError(f"kind={kind!r} is invalid: must be one of {COMPUTE_KINDS}")
        return self.costs[kind](ops)


# ------------------------------------------------------------------------------ operation counts
def filter_ops(front_end_kind: str, n_particles: int, n_local_features: float) -> tuple[str, float]:
    """One filter iteration of the front-end (``"fastslam"`` or ``"ekf"``)."""
    if front_end_kind == "fastslam":
        return "filter-fastslam", float(n_particles) * (1.0 + n_local_features)
    return "filter-ekf", (3.0 + 2.0 * n_local_features) ** 2


def fusion_ops(system, report) -> tuple[str, float]:
    """The fusion that produced ``report`` (counted from the back-end after it)."""
    back = system.back_end
    n_local = report.n_matched + report.n_new
    n_global_before = back.n_features - report.n_new
    n_aug = 6.0 + 2.0 * n_global_before + 2.0 * n_local
    info = getattr(back, "info", None)
    if info is None:
        return "fusion-ekf", n_aug**2 * (1.0 + 2.0 * report.n_matched)
    return "fusion-relative", n_aug**2 + (3.0 + 2.0 * back.n_features) * float(info.dim)


def optimise_ops(system, result) -> tuple[str, float]:
    """The optimisation that returned ``result`` (an ``OptimiseResult`` of
    :mod:`filters.submap_optimise`)."""
    rows = sum(3 + 2 * s.gaussian.n_features for s in system.submaps)
    n_global = 3.0 + 2.0 * system.back_end.n_features
    iterations = 0 if result is None else int(result.iterations)
    return "optimise", (iterations + 1.0) * rows + n_global**2


def summarise_records(records, model: ComputeModel | None = None) -> dict[str, float]:
    """Measured CPU seconds of an episode's records by what they did (``filter_cpu_s``,
    ``fusion_cpu_s``, ``optimise_cpu_s``, ``total_cpu_s``) and the model's total
    (``modelled_compute_s``)."""
    model = model or ComputeModel()
    out = dict.fromkeys(("filter_cpu_s", "fusion_cpu_s", "optimise_cpu_s"), 0.0)
    modelled = 0.0
    for kind, ops, cpu_s in records:
        out[f"{kind.split('-')[0]}_cpu_s"] += cpu_s
        modelled += model.seconds(kind, ops)
    out["total_cpu_s"] = sum(out.values())
    out["modelled_compute_s"] = modelled
    return out


# ------------------------------------------------------------------------------ calibration
@dataclass(frozen=True)
class Calibration:
    """A least-squares fit per kind and how well the model explains the measurements."""

    costs: dict
    n_samples: dict
    correlation: dict
    overall_correlation: float


def calibrate(records: Iterable[tuple[str, float, float]]) -> Calibration:
    """Fit ``cpu_s = intercept + seconds_per_op * ops`` per kind to ``(kind, ops, cpu_s)`` records
    (least squares, both coefficients kept non-negative) and report Pearson's correlation between
    modelled and measured seconds per kind and over all records."""
    by_kind: dict[str, list[tuple[float, float]]] = {}
    for kind, ops, cpu_s in records:
        by_kind.setdefault(kind, []).append((float(ops), float(cpu_s)))
    costs, counts, corr = {}, {}, {}
    modelled, measured = [], []
    for kind, rows in sorted(by_kind.items()):
        ops, cpu = np.array(rows).T
        if len(rows) >= 2 and np.ptp(ops) > 0:
            slope, intercept = np.polyfit(ops, cpu, 1)
            if intercept < 0:
                slope, intercept = float(ops @ cpu / (ops @ ops)), 0.0
            if slope < 0:
                slope, intercept = 0.0, float(cpu.mean())
        else:
            slope, intercept = 0.0, float(cpu.mean())
        costs[kind] = LinearCost(float(intercept), float(slope))
        fit = intercept + slope * ops
        counts[kind] = len(rows)
        corr[kind] = _pearson(fit, cpu)
        modelled.extend(fit)
        measured.extend(cpu)
    return Calibration(costs, counts, corr, _pearson(np.array(modelled), np.array(measured)))


def _pearson(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if len(a) < 2 or np.std(a) == 0 or np.std(b) == 0:
        return math.nan
    return float(np.corrcoef(a, b)[0, 1])
