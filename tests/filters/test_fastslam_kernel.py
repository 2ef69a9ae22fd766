"""The compiled FastSLAM kernels against plain numpy references, step by step."""

import copy

import numpy as np
import pytest


@pytest.mark.parametrize("seed", range(5))
def test_compact_features_is_the_stable_argsort_permutation(seed):
    from filters.fastslam_kernel import compact_features, new_state

    rng = np.random.default_rng(seed)
    P, C = 20, 15
    active = rng.random((P, C)) < 0.5
    # every other particle already compact (active slots first, as after a cull): left as it is
    active[::2] = np.arange(C) < rng.integers(0, C + 1, (P // 2, 1))
    floats = [rng.random((P, C)) for _ in range(6)]
    cid = rng.integers(-1, 9, (P, C))
    order = np.argsort(~active, axis=1, kind="stable")
    expected = [np.take_along_axis(a, order, axis=1) for a in [active, *floats, cid]]
    state = new_state(P, C, np.zeros(3))._replace(
        active=active.copy(), mx=floats[0].copy(), my=floats[1].copy(), sxx=floats[2].copy(),
        sxy=floats[3].copy(), syy=floats[4].copy(), ex=floats[5].copy(), cid=cid.copy())
    compact_features(state)
    got = [state.active, state.mx, state.my, state.sxx, state.sxy, state.syy, state.ex, state.cid]
    assert all(np.array_equal(e, g) for e, g in zip(expected, got, strict=True))


def test_systematic_resample_is_numpys_searchsorted():
    """The resampling's single pass over the cdf picks the particles
    ``searchsorted(cdf, (u + arange(P)) / P, "right")`` (the cdf's last entry 1, capped at P - 1)
    and gathers every field of the state with them."""
    from filters.fastslam_kernel import new_state, systematic_resample

    rng = np.random.default_rng(1)
    for P in (1, 2, 7, 50, 500):
        for _ in range(20):
            w = rng.random(P) ** 8  # uneven weights, some near zero
            w /= w.sum()
            u = rng.random()
            state = new_state(P, 3, np.zeros(3))
            state = state._replace(poses=rng.normal(size=(P, 3)), mx=rng.normal(size=(P, 3)),
                                   lineage=rng.permutation(P))
            spare = state._replace(**{f: np.empty_like(getattr(state, f))
                                      for f in state._fields if f != "clutter_sums"})
            cdf = np.cumsum(w)
            cdf[-1] = 1.0
            idx = np.minimum(np.searchsorted(cdf, (u + np.arange(P)) / P, side="right"), P - 1)
            ww = w.copy()
            systematic_resample(state, ww, u, spare)
            np.testing.assert_array_equal(spare.poses, state.poses[idx])
            np.testing.assert_array_equal(spare.mx, state.mx[idx])
            np.testing.assert_array_equal(spare.lineage, state.lineage[idx])
            assert not spare.logw.any() and np.allclose(ww, 1.0 / P)


STATE = ("poses", "prop_cov", "logw", "mx", "my", "sxx", "sxy", "syy", "ex", "active", "cid",
         "count", "lineage", "clutter_sums")


def _numpy_update_tail(f, state, out, known_cids, offset):
    """What follows the scan, in plain numpy (the reference of finish_scan, normalise_weights and
    systematic_resample): the votes (tests/filters/test_conversion.py's references), fresh ids,
    the clutter rate, the ids written, culling, the weights, the resampling test and the
    resampling. Returns the new state, the winners, the margins and whether it resampled."""
    from test_conversion import clutter_share, vote_all

    from filters.conversion import NEW_VOTE, assign_correspondence_ids
    from filters.fastslam_kernel import compact_features

    state = state._replace(**{name: getattr(state, name).copy() for name in STATE})
    if len(known_cids) == 0:
        winners, margins, _ = vote_all(out.logw_after, out.votes)
        new = np.flatnonzero(winners == NEW_VOTE)
        if len(new):
            winners[new] = f.ids.next_id + np.arange(len(new))
        decay = 1.0 - 1.0 / f.clutter_rate_memory
        for share in clutter_share(out.logw_after, out.clutter_prob):
            state.clutter_sums[:] = decay * state.clutter_sums + [share, 1.0]
    else:
        winners, margins = known_cids.copy(), np.ones(len(known_cids))
    assign_correspondence_ids(state.cid, state.active, out.slots, winners)
    if (f._steps + 1) % f.cull_interval_steps == 0:
        dead = state.active & (state.ex < f.cull_threshold)
        if dead.any():
            state.active[dead] = False
            compact_features(state)
            state.count[:] = state.active.sum(axis=1)
            state.ex[~state.active] = 0.0
            state.cid[~state.active] = -1
    state.logw[:] -= state.logw.max()
    w = np.exp(state.logw - state.logw.max())
    w = w / w.sum()
    n_eff = 1.0 / np.sum(w * w)
    P = len(w)
    if n_eff >= f.resample_threshold * P:
        return state, winners, margins, False, n_eff / P
    positions = (offset + np.arange(P)) / P
    cdf = np.cumsum(w)
    cdf[-1] = 1.0
    idx = np.minimum(np.searchsorted(cdf, positions, side="right"), P - 1)
    state = state._replace(**{name: getattr(state, name)[idx] for name in STATE
                              if name != "clutter_sums"})
    state.logw[:] = 0.0
    return state, winners, margins, True, n_eff / P


@pytest.mark.parametrize("known", [False, True])
def test_update_iteration_equals_the_numpy_reference_on_captured_scans(known):
    """The compiled scan's bookkeeping (votes, ids, clutter rate, culling, weights, resampling)
    against the plain numpy reference, from the same state and the same scan at every step of a
    seeded run: every array of the state, the winners and margins to rounding (1e-12), and
    the integer arrays equal."""
    from filters.fastslam import FastSLAM2
    from filters.fastslam_kernel import ScanDraws, new_outputs, scan_update
    from slam_gym.world import make_stream

    stream = make_stream("brooks-bailey", seed=3, n_steps=80, clutter_level=3)
    f = FastSLAM2(stream.sensor, stream.clutter, stream.odometry_noise,
                  np.random.default_rng(5), n_particles=60, initial_pose=stream.initial_pose,
                  cull_interval_steps=3, cull_threshold=0.2, resample_threshold=0.8,
                  initial_capacity=2)
    n_resampled = n_culled = 0
    for step in stream:
        f.predict(step.odometry, step.dt_s)
        labels = step.truth.landmark_ids if known else None
        # the reference's input: the filter's state and draws just before the update
        K, P = len(step.z), f.n_particles
        ref = copy.deepcopy(f)
        known_cids = (np.array([ref._label_id(int(x)) for x in labels], dtype=np.int64)
                      if known else np.zeros(0, dtype=np.int64))
        ref._grow(int(ref._state.count.max()) + K)
        uniforms = (ref.draws.generator("association").random((K, P)) if not known
                    else np.zeros((0, P)))
        normals = ref.draws.generator("scan_pose").standard_normal((P, 3))
        offset = ref.draws.generator("resample_after_scan").random()
        state = ref._state
        out = new_outputs(K, P)
        scan_update(state, step.z, known_cids, ScanDraws(uniforms, normals, offset), ref._model,
                    out)
        active_before = int(state.active.sum())
        expected, winners, margins, resampled, ess = _numpy_update_tail(ref, state, out,
                                                                        known_cids, offset)
        f.update(step.z, labels)
        n_resampled += resampled
        n_culled += int(expected.active.sum()) < active_before
        for name in STATE:
            got, want = getattr(f._state, name), getattr(expected, name)
            assert got.dtype == want.dtype and got.shape == want.shape, name
            if got.dtype.kind == "f":
                np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12, err_msg=name)
            else:
                np.testing.assert_array_equal(got, want, err_msg=name)
        np.testing.assert_array_equal(f.last_associations, winners)
        np.testing.assert_allclose(f._vote_margins, margins, rtol=0, atol=1e-12)
        assert f._ess_ratio == pytest.approx(ess, rel=1e-12)
        w = np.exp(expected.logw - expected.logw.max())
        np.testing.assert_allclose(f.weights, w / w.sum(), rtol=1e-12, atol=1e-300)
    assert n_resampled > 5 and n_culled > 0  # both paths were exercised


def test_certainly_in_range_only_where_the_visibility_is_one():
    """The scan's shortcut for features certainly in range (no square roots) claims a feature
    only where :func:`_visibility` gives exactly 1.0, so the scan's numbers do not depend on it;
    it claims most features well inside the range, and none of a covariance that is not positive
    semi-definite (whose radial variance the trace does not bound)."""
    from filters.fastslam_kernel import _certainly_in_range, _visibility

    rng = np.random.default_rng(7)
    max_range = 30.0
    claimed = inside = 0
    for _ in range(20000):
        # features from the pose out to beyond the range, many near the visibility's edge
        r = max_range * rng.uniform(0.0, 1.3)
        bearing = rng.uniform(-np.pi, np.pi)
        dx, dy = r * np.cos(bearing), r * np.sin(bearing)
        feature = rng.uniform(0.0, 1.5, 2) ** 2
        proposal = rng.uniform(0.0, 1.0, 2) ** 2
        rho = rng.uniform(-1.0, 1.0)
        fxy = rho * np.sqrt(feature[0] * feature[1])
        pxy = rng.uniform(-1.0, 1.0) * np.sqrt(proposal[0] * proposal[1])
        cxx, cyy, cxy = feature[0] + proposal[0], feature[1] + proposal[1], fxy + pxy
        bound = np.sqrt(feature.sum()) + np.sqrt(proposal.sum())
        certain = _certainly_in_range(dx, dy, cxx, cxy, cyy, bound, max_range)
        if certain:
            claimed += 1
            assert _visibility(dx, dy, 0.0, cxx, cxy, cyy, max_range, 2 * np.pi) == 1.0
        if r + 9.0 * bound < max_range:
            inside += 1
            assert certain  # well inside the range, the shortcut takes it
        # a covariance that is not semi-definite is never claimed
        assert not _certainly_in_range(dx, dy, cxx, 2.0 * np.sqrt(cxx * cyy) + 1.0, cyy, bound,
                                       max_range)
    assert inside > 1000 and claimed >= inside
