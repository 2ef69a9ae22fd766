"""The compiled FastSLAM helpers against their numpy definitions."""

import numpy as np
import pytest


@pytest.mark.parametrize("seed", range(5))
def test_compact_features_is_the_stable_argsort_permutation(seed):
    from filters.fastslam_kernel import compact_features

    rng = np.random.default_rng(seed)
    P, C = 20, 15
    active = rng.random((P, C)) < 0.5
    # every other particle already compact (active slots first, as after a cull): left as it is
    active[::2] = np.arange(C) < rng.integers(0, C + 1, (P // 2, 1))
    floats = [rng.random((P, C)) for _ in range(6)]
    cid = rng.integers(-1, 9, (P, C))
    order = np.argsort(~active, axis=1, kind="stable")
    expected = [np.take_along_axis(a, order, axis=1) for a in [active, *floats, cid]]
    got = [a.copy() for a in [active, *floats, cid]]
    compact_features(*got)
    assert all(np.array_equal(e, g) for e, g in zip(expected, got, strict=True))
