"""The banded factorisation of the compiled Gauss-Newton (filters/submap_gauss_newton.py, issue 40
item 2) against the dense one it replaced, on a full path of Brooks-Bailey's world at clutter
level 2 (HYBRID, fusing and optimising every 10 s as ``fixed-10s-optimise`` does).

The two factorise the same matrices in different orders, so they differ in rounding only; the
optimum of CM (12) is flat along some directions (the cost agrees to 1e-14 where the
estimates differ by up to 1.4e-5 m), so that rounding moves the iterate at which Gauss-Newton
stops. Measured on the full paths of worlds 0, 1, 3-6 (30 particles, 42-43 optimisations each):
the estimate written back differs by at most 1.2e-6 of its own standard deviation, its
covariance by at most 6e-7 of its largest entry, the cost by 1e-13 relative, and the iteration
counts are equal. The bound tested on every optimisation of world 1, each from the same state:
1e-5 standard deviations, 1e-5 of the covariance's largest entry, 1e-12 of the cost, at most one
iteration more or fewer.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from filters import submap_gauss_newton as gn
from filters.submap_optimise import _global_ids_of, _information_of, submap_arrays
from slam_gym.systems import make_system
from slam_gym.world import make_stream

# its module-scoped fixtures are built once: every test of this file on one worker (pytest -n)
pytestmark = pytest.mark.xdist_group("test_submap_band_factor")


@pytest.fixture(scope="module")
def path_run():
    """Per optimisation of a full path: the band result, the dense result from the same state;
    and the system at the end."""
    stream = make_stream("brooks-bailey", seed=1, clutter_level=2)
    system = make_system("hybrid", stream, np.random.default_rng(1), n_particles=30).estimator
    pairs = []
    for i, step in enumerate(stream):
        system.predict(step.odometry, step.dt_s)
        system.update(step.z)
        if (i + 1) % 100 == 0:
            system.fuse()
            dense = copy.deepcopy(system).optimise(band=False)
            pairs.append((system.optimise(), dense))
    return pairs, system


def test_band_and_dense_optima_differ_by_rounding_only(path_run):
    pairs, _ = path_run
    assert len(pairs) >= 40  # the whole path
    for band, dense in pairs:
        assert band.converged and dense.converged
        assert abs(band.iterations - dense.iterations) <= 1
        assert band.cost == pytest.approx(dense.cost, rel=1e-12, abs=1e-12)
        sigma = np.sqrt(np.diag(dense.P))
        assert np.max(np.abs(band.x - dense.x) / sigma) <= 1e-5
        np.testing.assert_allclose(band.P, dense.P, rtol=0, atol=1e-5 * np.abs(dense.P).max())
    # rounding, not nothing: the two factorisations are not the same computation
    assert any(not np.array_equal(b.P, d.P) for b, d in pairs)


def test_the_full_path_problem_is_factorised_in_a_narrow_band(path_run):
    _, system = path_run
    submaps = list(system.submaps)
    global_ids = [_global_ids_of(s, n) for n, s in enumerate(submaps)]
    feature_index = {g: j for j, g in enumerate(dict.fromkeys(np.concatenate(global_ids)
                                                             .tolist()))}
    arrays = submap_arrays(submaps, global_ids, feature_index, len(submaps) + 1,
                           [_information_of(s, 1e-10) for s in submaps])
    poses = np.zeros((arrays.n_poses, 3))
    poses[1:] = np.cumsum(np.ones((arrays.n_poses - 1, 3)), axis=0)
    points = np.ones((arrays.n_features, 2))
    *_, rows, cols, vals = gn._normal_equations(
        poses, points, arrays.n_poses, arrays.origin, arrays.end, arrays.feature_start,
        arrays.features, arrays.mean_start, arrays.means, arrays.info_start, arrays.infos,
        arrays.n_variables, False)
    ordering = gn.BandOrdering.of(arrays)
    n = arrays.n_variables
    assert np.array_equal(np.sort(ordering.order), np.arange(n))
    assert np.array_equal(ordering.order[ordering.position], np.arange(n))
    assert ordering.pays and ordering.bandwidth < n // 3
    # the band holds every entry: the banded matrix is the dense one, permuted
    dense = gn._dense(n, rows, cols, vals)
    ab = gn._band(n, ordering.bandwidth, ordering.position, rows, cols, vals)
    permuted = dense[np.ix_(ordering.order, ordering.order)]
    for k in range(ordering.bandwidth + 1):
        np.testing.assert_array_equal(ab[k, :n - k], np.diagonal(permuted, -k))
    assert not np.any(np.tril(permuted, -ordering.bandwidth - 1))
    # and its solve is the dense solve, to rounding
    normal = gn._Normal(n, rows, cols, vals, ordering)
    assert normal.ordering is ordering
    b = np.random.default_rng(0).normal(size=(n, 3))
    np.testing.assert_allclose(normal.factor()(b), np.linalg.solve(dense, b), rtol=1e-8,
                               atol=1e-10 * np.abs(np.linalg.solve(dense, b)).max())
    damped = normal.factor(0.5)(b[:, 0])
    np.testing.assert_allclose(damped, np.linalg.solve(dense + 0.5 * np.diag(np.diag(dense)),
                                                       b[:, 0]), rtol=1e-8)


def test_band_option_is_checked():
    stream = make_stream("brooks-bailey", seed=0, clutter_level=2, n_steps=200)
    system = make_system("hybrid", stream, np.random.default_rng(0), n_particles=5).estimator
    for step in stream:
        system.predict(step.odometry, step.dt_s)
        system.update(step.z)
    system.fuse()
    with pytest.raises(ValueError, match="band"):
        system.optimise(band="yes")
