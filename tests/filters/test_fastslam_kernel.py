"""The compiled FastSLAM helpers against their numpy definitions."""

import math

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


def test_numpy_sum_is_numpys_pairwise_sum_to_the_bit():
    from filters.fastslam_kernel import numpy_sum

    rng = np.random.default_rng(0)
    lengths = [*range(0, 300), 500, 511, 1000, 1023, 1025, 4097, 20000]
    differing = 0
    for n in lengths:
        a = np.exp(rng.standard_normal(n) * rng.uniform(0.0, 30.0))  # sums that round
        differing += numpy_sum(a) != a.sum()
    assert differing == 0
    # a plain left-to-right sum is not numpy's: the check above can fail
    a = np.exp(rng.standard_normal(500) * 20.0)
    assert math.fsum(a) != a.sum() or sum(a.tolist()) != a.sum()


@pytest.mark.parametrize("case", ["sorted", "last set to one", "nan", "repeated keys"])
def test_searchsorted_right_is_numpys(case):
    from filters.fastslam_kernel import _searchsorted_right

    rng = np.random.default_rng(1)
    for _ in range(200):
        a = np.cumsum(rng.random(int(rng.integers(1, 600))))
        a /= a[-1] * rng.uniform(0.99, 1.01)
        keys = np.sort(rng.random(int(rng.integers(1, 600))))
        if case == "last set to one":  # the resampling cdf: a rounded sum above 1, then 1
            a[-1] = 1.0
            keys[-1] = 1.0
        elif case == "nan":
            a[rng.integers(0, len(a))] = np.nan
            keys[rng.random(len(keys)) < 0.1] = np.nan
        elif case == "repeated keys":
            keys = np.repeat(keys, 3)
            a[-1] = a[0]  # not sorted: numpy's answer depends on its search order
        np.testing.assert_array_equal(_searchsorted_right(a, keys),
                                      np.searchsorted(a, keys, side="right"))


def _numpy_update_tail(f, known_cids, votes, slots, logw_after, clutter_prob):
    """What FastSLAM2.update did after scan_update before issue 40 item 3, in numpy: the
    reference the compiled bookkeeping must equal to the bit."""
    from filters.conversion import NEW_VOTE, assign_correspondence_ids, vote_all
    from filters.fastslam import clutter_share
    from filters.fastslam_kernel import compact_features

    if known_cids is None:
        winners, margins, _ = vote_all(logw_after, votes)
        new = np.flatnonzero(winners == NEW_VOTE)
        if len(new):
            winners[new] = f.ids.new(len(new))
        decay = 1.0 - 1.0 / f.clutter_rate_memory
        for share in clutter_share(logw_after, clutter_prob):
            f._clutter_num = decay * f._clutter_num + share
            f._clutter_den = decay * f._clutter_den + 1.0
    else:
        winners, margins = known_cids, np.ones(len(known_cids))
    assign_correspondence_ids(f._cid, f._active, slots, winners)
    f._steps += 1
    if f._steps % f.cull_interval_steps == 0:
        dead = f._active & (f._ex < f.cull_threshold)
        if dead.any():
            f._active &= ~dead
            compact_features(f._active, f._mx, f._my, f._sxx, f._sxy, f._syy, f._ex, f._cid)
            f._count = f._active.sum(axis=1)
            f._ex[~f._active] = 0.0
            f._cid[~f._active] = -1
    f._logw -= f._logw.max()
    f.last_associations = winners
    f._vote_margins = margins
    w = np.exp(f._logw - f._logw.max())
    w = w / w.sum()
    n_eff = 1.0 / np.sum(w * w)
    f._ess_ratio = float(n_eff / f.n_particles)
    if n_eff >= f.resample_threshold * f.n_particles:
        return False
    P = f.n_particles
    positions = (f.rng.random() + np.arange(P)) / P
    cdf = np.cumsum(w)
    cdf[-1] = 1.0
    idx = np.minimum(np.searchsorted(cdf, positions, side="right"), P - 1)
    for name in STATE:
        if name != "_logw":
            setattr(f, name, np.take(getattr(f, name), idx, axis=0))
    f._logw = np.zeros(P)
    return True


STATE = ("_poses", "_prop_cov", "_logw", "_mx", "_my", "_sxx", "_sxy", "_syy", "_ex", "_active",
         "_cid", "_count", "_lineage")


@pytest.mark.parametrize("known", [False, True])
def test_update_bookkeeping_equals_the_numpy_code_to_the_bit(known, monkeypatch):
    """The compiled bookkeeping after the scan (votes, ids, clutter rate, culling, resampling,
    the pose) against the numpy code it replaced, step by step from the same state: every array
    of the state, the ids, the generator, the weights and the pose equal to the bit."""
    import copy

    from filters import fastslam as fastslam_module
    from filters.conversion import pose_moments_unchecked
    from filters.fastslam import FastSLAM2
    from slam_gym.world import make_stream

    stream = make_stream("brooks-bailey", seed=3, n_steps=80, clutter_level=3)
    f = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise,
                  np.random.default_rng(5), n_particles=60, initial_pose=stream.initial_pose,
                  cull_interval_steps=3, cull_threshold=0.2, resample_threshold=0.8,
                  initial_capacity=2)
    scan_update = fastslam_module.scan_update
    captured = []

    def capture(*args):  # the scan as it is; its outputs kept for the reference's bookkeeping
        scan_update(*args)
        captured[:] = [args[15], *(a.copy() for a in args[16:20])]

    n_resampled = n_culled = 0
    for step in stream:
        f.predict(step.odometry, step.dt_s)
        ref = copy.deepcopy(f)
        labels = step.truth.landmark_ids if known else None
        f.update(step.z, labels)
        mean, cov = f.pose()
        # the reference: the same head of update (validation, draws, the scan), no tail
        with monkeypatch.context() as m:
            m.setattr(fastslam_module, "scan_update", capture)
            m.setattr(fastslam_module, "finish_scan",
                      lambda *a: (None, None, 0, a[16], a[17]))
            m.setattr(FastSLAM2, "_maybe_resample", lambda self, role: None)
            ref.update(step.z, labels)
        ref._steps -= 1  # counted again by the reference's tail
        active_before = int(ref._active.sum())
        n_resampled += _numpy_update_tail(ref, *captured)
        n_culled += int(ref._active.sum()) < active_before
        for name in STATE:
            np.testing.assert_array_equal(getattr(f, name), getattr(ref, name), err_msg=name)
            assert getattr(f, name).dtype == getattr(ref, name).dtype
        assert f.ids.next_id == ref.ids.next_id
        assert f.rng.bit_generator.state == ref.rng.bit_generator.state
        assert (f._clutter_num, f._clutter_den, f._ess_ratio, f._steps) == (
            ref._clutter_num, ref._clutter_den, ref._ess_ratio, ref._steps)
        np.testing.assert_array_equal(f.last_associations, ref.last_associations)
        np.testing.assert_array_equal(f._vote_margins, ref._vote_margins)
        w = np.exp(ref._logw - ref._logw.max())
        w = w / w.sum()
        np.testing.assert_array_equal(f.weights, w)
        # FastSLAM2.pose before: the compiled moments of the filter's own weights
        ref_mean, ref_cov = pose_moments_unchecked(ref._poses, w, np.zeros((0, 3, 3)),
                                                   ref._lineage, len(ref._lineage), True)
        np.testing.assert_array_equal(mean, ref_mean)
        np.testing.assert_array_equal(cov, ref_cov)
    assert n_resampled > 5 and n_culled > 0  # both paths were exercised
