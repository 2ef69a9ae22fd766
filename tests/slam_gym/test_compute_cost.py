"""The compute-cost model: its calibration recovers a known linear cost, and its inputs."""

import math

import numpy as np
import pytest

from slam_gym.compute_cost import (
    COMPUTE_KINDS,
    DEFAULT_COSTS,
    ComputeModel,
    calibrate,
    filter_ops,
    summarise_records,
)


def test_calibration_recovers_a_known_linear_cost_and_reports_correlation():
    rng = np.random.default_rng(0)
    ops = rng.uniform(1e3, 1e6, size=200)
    cpu = 2e-3 + 3e-8 * ops + rng.normal(scale=1e-4, size=200)
    fit = calibrate([("optimise", o, c) for o, c in zip(ops, cpu, strict=True)])
    cost = fit.costs["optimise"]
    assert cost.intercept_s == pytest.approx(2e-3, rel=0.05)
    assert cost.seconds_per_op == pytest.approx(3e-8, rel=0.01)
    assert fit.correlation["optimise"] > 0.99
    assert fit.n_samples["optimise"] == 200


def test_calibration_never_fits_negative_costs():
    ops = np.linspace(1.0, 100.0, 20)
    fit = calibrate([("fusion-ekf", o, 1.0 - 0.001 * o) for o in ops])  # decreasing: nonsense
    assert fit.costs["fusion-ekf"].seconds_per_op >= 0.0
    assert fit.costs["fusion-ekf"].intercept_s >= 0.0
    assert math.isnan(calibrate([("optimise", 5.0, 0.1)]).correlation["optimise"])


def test_every_kind_has_a_default_cost_and_unknown_kinds_are_rejected():
    assert set(DEFAULT_COSTS) == set(COMPUTE_KINDS)
    with pytest.raises(ValueError, match="kind"):
        ComputeModel().seconds("teleport", 1.0)


def test_filter_operations_grow_with_particles_and_local_features():
    assert filter_ops("fastslam", 500, 10)[1] == 500 * 11
    assert filter_ops("fastslam", 500, 20)[1] > filter_ops("fastslam", 100, 20)[1]
    assert filter_ops("ekf", 1, 4) == ("filter-ekf", 121.0)


def test_records_are_summarised_by_what_they_did():
    records = [("filter-fastslam", 1e4, 0.01), ("fusion-relative", 1e3, 0.02),
               ("optimise", 5e3, 0.3), ("filter-fastslam", 2e4, 0.015)]
    out = summarise_records(records)
    assert out["filter_cpu_s"] == pytest.approx(0.025)
    assert out["fusion_cpu_s"] == pytest.approx(0.02)
    assert out["optimise_cpu_s"] == pytest.approx(0.3)
    assert out["total_cpu_s"] == pytest.approx(0.345)
    model = ComputeModel()
    expected = sum(model.seconds(k, o) for k, o, _ in records)
    assert out["modelled_compute_s"] == pytest.approx(expected)
