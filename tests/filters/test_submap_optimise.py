"""Sub-map optimisation (filters/submap_optimise.py, CM III.C) and the relative back-end
(filters/back_ends.py)."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
import pytest

from filters.back_ends import GlobalMap, RelativeBackEnd, make_back_end
from filters.ekf_slam import EKFSLAM
from filters.geometry import compose, wrap_angle
from filters.optimiser import POINT, POSE
from filters.submap import SubmapSLAM
from filters.submap_optimise import (
    build_submap_problem,
    gaussian_information,
    joint_covariance,
    optimise_submaps,
)
from filters.types import GaussianMap
from slam_gym.episode import Episode
from slam_gym.scenarios import SQUARE_LOOP_OVERRIDES
from slam_gym.world import make_stream

# its module-scoped fixtures are built once: every test of this file on one worker (pytest -n)
pytestmark = pytest.mark.xdist_group("test_submap_optimise")

FUSE_EVERY = 100
#: a small closed loop (side 27 m, ~1100 iterations) in a 60 m world: fast, with a loop closure
# a small square loop (no sharp first turn: initial_heading_spread_rad=0, as before #14)
SMALL_LOOP = dict(path_length_m=120.0, world_size_m=60.0, n_landmarks=25, waypoint_spacing_m=9.0,
                  initial_heading_spread_rad=0.0)
NOISE_FREE = dict(
    v_noise_fraction=0.0,
    omega_noise_fraction=0.0,
    v_noise_floor_mps=0.0,
    omega_noise_floor_radps=0.0,
    range_std_m=1e-4,
    bearing_std_rad=1e-5,
)


@dataclass
class Run:
    stream: object
    system: SubmapSLAM
    episode: Episode
    true_poses: list = field(default_factory=list)  # true pose at each fusion pose index
    est_poses: list = field(default_factory=list)  # back-end v- right after each fusion


def run(stream, kind="ekf", fuse_every=FUSE_EVERY, **back_options) -> Run:
    front = EKFSLAM(stream.sensor, stream.clutter, stream.odometry_noise)
    back = make_back_end(kind, stream.initial_pose, **back_options)
    system = SubmapSLAM(front, back_end=back)
    ep = Episode(system, stream, record_trace=False)
    out = Run(stream, system, ep, [np.array(stream.initial_pose)], [np.array(stream.initial_pose)])
    while not ep.done:
        ep.advance(fuse_every)
        ep.fuse()
        out.true_poses.append(np.array(ep.last_step.truth.pose))
        out.est_poses.append(system.back_end.x[:3].copy())
    return out


def unoptimised(system) -> SubmapSLAM:
    """A copy of ``system`` that has forgotten its last optimum (so the next optimisation is
    neither redundant nor warm-started), whatever the module's other tests did to it."""
    out = copy.deepcopy(system)
    out.last_optimum = None
    return out


def is_spd(P) -> bool:
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return False
    return bool(np.array_equal(P, P.T))


@pytest.fixture(scope="module")
def loop_ekf() -> Run:
    return run(make_stream("brooks-bailey", seed=2, **SMALL_LOOP))


@pytest.fixture(scope="module")
def loop_relative() -> Run:
    return run(make_stream("brooks-bailey", seed=2, **SMALL_LOOP), "relative")


# ------------------------------------------------------------------ the optimiser on sub-maps
def test_optimised_covariance_is_spd_symmetric_and_pose_is_consistent(loop_ekf):
    r = loop_ekf
    res = optimise_submaps(r.system)
    g = r.system.back_end
    assert res.converged and res.n_submaps == len(r.system.submaps) == res.pose_index
    assert is_spd(g.P)
    assert g.P.shape == (len(g.x), len(g.x)) and len(g.x) == 3 + 2 * len(g.ids)
    np.testing.assert_array_equal(res.ids, g.ids)
    # SubmapSLAM.pose() composes v- with the local pose: v- is the optimised last end pose
    local_mean, _ = r.system.front_end.pose()
    mean, cov = r.system.pose()
    np.testing.assert_allclose(mean, compose(g.x[:3], local_mean), atol=1e-12)
    assert is_spd(0.5 * (cov + cov.T))
    assert r.system.n_optimisations >= 1
    assert r.system.interface_features()["fusions_since_optimise"] == 0.0


def test_optimum_reduces_cost_below_the_unoptimised_estimate(loop_ekf):
    r = loop_ekf
    res = optimise_submaps(unoptimised(r.system), solver="general")
    g = res
    g = r.system.back_end
    sp = res.problem
    # the EKF estimate: v- recorded at each fusion, features as the EKF back-end had them last
    ekf = run(r.stream)
    features = dict(zip(ekf.system.back_end.ids.tolist(), ekf.system.back_end.x[3:].reshape(-1, 2),
                        strict=True))
    np.testing.assert_array_equal(ekf.system.back_end.ids, g.ids)
    tau_ekf = sp.tau_of(np.array(ekf.est_poses), features)
    assert res.cost <= sp.cost(tau_ekf)
    assert res.cost <= res.initial_cost
    # the optimum is a stationary point of CM (13)
    grad = sp.problem.gradient(res.optimiser.tau)
    assert np.max(np.abs(grad)) < 1e-6 * max(1.0, np.max(np.abs(sp.problem.eta)))


def test_optimising_twice_is_redundant_and_changes_nothing_to_the_bit(loop_ekf):
    """Issue 27: a second optimisation with nothing fused since returns at once, leaves the
    system's state bit-identical (no book-keeping either) and says it was redundant; after a
    fusion it optimises again."""
    system = unoptimised(loop_ekf.system)
    first = optimise_submaps(system)
    assert not first.redundant and first.iterations > 0
    before = copy.deepcopy(system)
    again = optimise_submaps(system)
    assert again.redundant and again.iterations == 0
    np.testing.assert_array_equal(again.x, first.x)
    np.testing.assert_array_equal(again.P, first.P)
    for name in ("x", "P", "ids", "existence"):
        np.testing.assert_array_equal(getattr(system.back_end, name),
                                      getattr(before.back_end, name))
    assert system.n_optimisations == before.n_optimisations
    assert system.interface_features() == before.interface_features()
    # other settings are another optimisation, not a repeat
    assert not optimise_submaps(system, max_iterations=150).redundant
    system.fuse()
    after_fusion = optimise_submaps(system)
    assert not after_fusion.redundant and after_fusion.n_submaps == first.n_submaps + 1


@pytest.mark.parametrize("fuse_every", [50, 100])
def test_compiled_gauss_newton_reaches_the_general_optimum(fuse_every):
    """Issue 27: the compiled Newton/Gauss-Newton (filters.submap_gauss_newton) and the general
    sparse optimiser (filters.optimiser.RelativeProblem) give the same optimum and covariance,
    cold and warm-started, on a loop with its closure."""
    r = run(make_stream("brooks-bailey", seed=3, **SMALL_LOOP), fuse_every=fuse_every)
    compiled, general = copy.deepcopy(r.system), copy.deepcopy(r.system)
    a = optimise_submaps(compiled)
    b = optimise_submaps(general, solver="general")
    assert a.converged and b.converged and a.problem is None and b.problem is not None
    assert a.cost == pytest.approx(b.cost, rel=1e-9)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-8 * np.abs(b.P).max())
    # a warm start from the optimum of all but the last sub-maps: the same optimum again
    warm = copy.deepcopy(r.system)
    last = warm.submaps.pop()
    optimise_submaps(warm)
    warm.submaps.append(last)
    warm._fusions_since_optimise = 1
    c = optimise_submaps(warm)
    assert not c.redundant and c.iterations <= a.iterations
    np.testing.assert_allclose(c.x, b.x, rtol=0, atol=1e-6)
    assert c.cost == pytest.approx(b.cost, rel=1e-9)


def test_reduced_method_reaches_the_gauss_newton_optimum(loop_ekf):
    r = loop_ekf
    gn = optimise_submaps(r.system, "gauss-newton")
    x_gn = r.system.back_end.x.copy()
    red = optimise_submaps(r.system, "reduced")
    assert red.converged
    np.testing.assert_allclose(r.system.back_end.x, x_gn, atol=1e-5)
    assert red.cost == pytest.approx(gn.cost, rel=1e-6)


def test_noise_free_optimum_equals_the_truth():
    stream = make_stream("brooks-bailey", seed=0, **SMALL_LOOP, **NOISE_FREE)
    r = run(stream)
    res = optimise_submaps(r.system, solver="general")
    sp = res.problem
    poses = res.optimiser.means[sp.pose_entity]
    err = np.array(r.true_poses) - poses
    err[:, 2] = wrap_angle(err[:, 2])
    assert np.max(np.abs(err)) < 1e-4
    truth = r.episode.feature_truth
    g = r.system.back_end
    lm = stream.landmarks_true[[truth.landmark_of(int(i)) for i in g.ids]]
    np.testing.assert_allclose(g.x[3:].reshape(-1, 2), lm, atol=2e-4)
    pose_err = np.array(r.true_poses[-1]) - g.x[:3]
    assert np.max(np.abs(wrap_angle(pose_err))) < 1e-4
    assert is_spd(g.P)
    # features seen in several sub-maps: the loop-closure redundancy was there
    counts = np.bincount([q.target for q in sp.problem.quantities if q.kind == POINT])
    assert counts.max() > 1


def test_problem_structure_and_pose_prior_with_uncertain_initial_pose(loop_ekf):
    r = loop_ekf
    submaps = r.system.submaps
    sp = build_submap_problem(submaps, r.stream.initial_pose)
    q = sp.problem.quantities
    n_points = sum(s.gaussian.n_features for s in submaps)
    assert sum(x.kind == POSE for x in q) == len(submaps)
    assert sum(x.kind == POINT for x in q) == n_points
    assert sp.n_poses == len(submaps) + 1 and not sp.world
    # an uncertain start: a world gauge and a prior; nothing else fixes the absolute frame, so
    # the optimised start pose keeps exactly its prior covariance
    P0 = np.diag([0.04, 0.09, 0.01])
    sp0 = build_submap_problem(submaps, r.stream.initial_pose, P0)
    assert sp0.world
    res = sp0.problem.optimise("gauss-newton")
    np.testing.assert_allclose(joint_covariance(res, [sp0.pose_entity[0]]), P0, atol=1e-9)
    np.testing.assert_allclose(res.means[sp0.pose_entity[0]], r.stream.initial_pose, atol=1e-8)


def test_singular_submap_covariance_is_floored():
    # a fusion right after a restart: zero-motion local map with an exactly zero covariance
    stream = make_stream("brooks-bailey", seed=1, n_steps=250)
    front = EKFSLAM(stream.sensor, stream.clutter, stream.odometry_noise)
    system = SubmapSLAM(front, back_end=make_back_end("ekf", stream.initial_pose))
    ep = Episode(system, stream, record_trace=False)
    ep.advance(120)
    ep.fuse()
    ep.fuse()  # nothing happened in between
    ep.advance(130)
    ep.fuse()
    assert not np.any(system.submaps[1].gaussian.P)
    W = gaussian_information(system.submaps[1].gaussian.P)
    assert np.all(np.isfinite(W)) and is_spd(W)
    res = optimise_submaps(system, solver="general")
    assert res.converged and is_spd(system.back_end.P)
    np.testing.assert_allclose(
        res.optimiser.means[res.problem.pose_entity[1], :2],
        res.optimiser.means[res.problem.pose_entity[2], :2],
        atol=1e-6,
    )


def test_no_submap_is_a_redundant_no_op():
    stream = make_stream("brooks-bailey", seed=0, n_steps=20)
    front = EKFSLAM(stream.sensor, stream.clutter, stream.odometry_noise)
    system = SubmapSLAM(front, back_end=make_back_end("ekf", stream.initial_pose))
    x, features = system.back_end.x.copy(), system.interface_features()
    res = optimise_submaps(system)
    assert res.n_submaps == 0 and res.redundant and system.n_optimisations == 0
    np.testing.assert_array_equal(system.back_end.x, x)
    assert system.interface_features() == features


# ------------------------------------------------------------------ the relative back-end
def test_relative_chain_equals_ekf_back_end_before_any_loop_closure():
    # the innovation test disabled and a long chain allowed: no loop closure on this stretch;
    # on the square loop (BB's path of #14 turns more: the two back-ends then linearise at
    # different points, 0.25 std apart at seed 1, which is not what this test is about)
    stream = make_stream("brooks-bailey", seed=1, n_steps=700, **SQUARE_LOOP_OVERRIDES)
    ekf = run(stream)
    rel = run(stream, "relative", innovation_sigmas=100.0, max_chain=1000)
    ge, gr = ekf.system.back_end, rel.system.back_end
    assert gr.n_loop_closures == 0 and gr.n_submaps == len(rel.system.submaps) == 7
    np.testing.assert_array_equal(ge.ids, gr.ids)
    assert any(s.gaussian.n_features for s in rel.system.submaps[1:])
    n_reobserved = sum(
        sum(1 for lid, gid in s.id_map.items() if lid != gid) for s in rel.system.submaps
    )
    assert n_reobserved > 5  # features seen in consecutive sub-maps were integrated
    std = np.sqrt(np.diag(ge.P))
    assert np.max(np.abs(ge.x - gr.x) / std) < 0.15
    scale = np.sqrt(np.outer(np.diag(ge.P), np.diag(ge.P)))
    assert np.max(np.abs(ge.P - gr.P) / scale) < 0.05
    assert is_spd(gr.P)
    mean_e, cov_e = ekf.system.pose()
    mean_r, cov_r = rel.system.pose()
    assert np.max(np.abs(mean_e - mean_r) / np.sqrt(np.diag(cov_e))) < 0.15


def test_relative_back_end_on_a_loop(loop_relative, loop_ekf):
    r = loop_relative
    g = r.system.back_end
    assert isinstance(g, RelativeBackEnd) and isinstance(g, GlobalMap)
    assert g.n_loop_closures > 0 and g.redundancies
    assert any(lc.reason == "chain" for lc in g.loop_closures)
    assert is_spd(g.P) and len(g.x) == 3 + 2 * len(g.ids)
    # quantities: one end pose per sub-map, features relative to pose indices
    assert sum(q.kind == POSE for q in g.quantities) == len(r.system.submaps)
    res = optimise_submaps(r.system)
    assert res.converged and is_spd(g.P)
    np.testing.assert_allclose(g.x, res.x, atol=1e-12)
    # the optimum over the same sub-maps and associations as the EKF back-end's
    if np.array_equal(loop_ekf.system.back_end.ids, g.ids) and all(
        a.id_map == b.id_map for a, b in zip(loop_ekf.system.submaps, r.system.submaps,
                                             strict=True)
    ):
        optimise_submaps(loop_ekf.system)
        np.testing.assert_allclose(loop_ekf.system.back_end.x, g.x, atol=1e-9)
    # the hybrid's map after optimisation is better than its chain before it
    before = run(r.stream, "relative").episode.map_score().map_error_m
    assert r.episode.map_score().map_error_m < before


def test_relative_entities_after_optimisation_chain_onto_the_optimum():
    stream = make_stream("brooks-bailey", seed=3, n_steps=900)
    front = EKFSLAM(stream.sensor, stream.clutter, stream.odometry_noise)
    system = SubmapSLAM(front, back_end=make_back_end("relative", stream.initial_pose))
    ep = Episode(system, stream, record_trace=False)
    for _ in range(6):
        ep.advance(FUSE_EVERY)
        ep.fuse()
    res = optimise_submaps(system)
    g = system.back_end
    anchored = dict(zip(g.ids.tolist(), g.x[3:].reshape(-1, 2), strict=True))
    ep.advance(FUSE_EVERY)
    ep.fuse()
    # covered features keep the optimum; v- = optimum (+) the new sub-map's end pose
    for gid, m in anchored.items():
        k = int(np.flatnonzero(g.ids == gid)[0])
        np.testing.assert_array_equal(g.x[3 + 2 * k : 5 + 2 * k], m)
    d = g.info.mean_of(g._d[-1])
    np.testing.assert_allclose(g.x[:3], compose(res.x[:3], d), atol=1e-10)
    assert is_spd(g.P)
    assert np.all(np.diag(g.P)[:3] >= np.diag(res.P)[:3] - 1e-12)


def test_innovation_bound_dominates_the_prediction_covariance(loop_relative):
    g = loop_relative.system.back_end
    checked = 0
    for gid in g.ids[:: max(1, len(g.ids) // 12)]:
        pred, ents, Hs = g.predict_coordinates(int(gid))
        S_true = g.info.covariance_blocks([list(zip(ents, Hs, strict=True))])[0]
        S_bar = g.innovation_bound(ents, Hs)
        assert np.linalg.eigvalsh(S_bar - S_true)[0] >= -1e-12 * np.trace(S_bar)
        checked += 1
    assert checked >= 5


def test_chain_prediction_jacobians_match_finite_differences(loop_relative):
    g = loop_relative.system.back_end
    mu = g.info.mean().copy()
    gid = int(g.ids[0])
    b = g.n_submaps
    pred, ents, Hs = g._chain_prediction(gid, b, mu)
    eps = 1e-6
    for e, H in zip(ents, Hs, strict=True):
        o, size = g.info.offset(e), g.info.size(e)
        num = np.zeros((2, size))
        for k in range(size):
            mp, mm = mu.copy(), mu.copy()
            mp[o + k] += eps
            mm[o + k] -= eps
            num[:, k] = (g._chain_prediction(gid, b, mp)[0] - g._chain_prediction(gid, b, mm)[0])
            num[:, k] /= 2 * eps
        np.testing.assert_allclose(H, num, atol=1e-6)


def test_relative_back_end_is_deterministic():
    stream = make_stream("brooks-bailey", seed=4, n_steps=400)
    a = run(stream, "relative").system.back_end
    b = run(stream, "relative").system.back_end
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)


def test_empty_local_maps_and_first_fusion():
    back = RelativeBackEnd(np.array([1.0, 2.0, 0.3]))
    np.testing.assert_allclose(back.x, [1.0, 2.0, 0.3], atol=1e-15)
    local = GaussianMap(
        x=np.array([1.0, 0.0, 0.1, 2.0, 1.0]),
        P=np.diag([0.01, 0.01, 0.001, 0.02, 0.02]),
        ids=np.array([7]),
        existence=np.array([0.99]),
    )
    report = back.fuse(local)
    assert report.id_map == {7: 7} and report.n_new == 1
    ref = GlobalMap(np.array([1.0, 2.0, 0.3]))
    ref.fuse(local)
    np.testing.assert_allclose(back.x, ref.x, atol=1e-12)
    np.testing.assert_allclose(back.P, ref.P, atol=1e-12)
    empty = GaussianMap(np.zeros(3), np.zeros((3, 3)), np.zeros(0, dtype=np.int64), np.zeros(0))
    back.fuse(empty)
    np.testing.assert_allclose(back.x[:3], ref.x[:3], atol=1e-9)
    assert back.n_submaps == 2


# ------------------------------------------------------------------ validation
@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"innovation_sigmas": 0.0}, "innovation_sigmas"),
        ({"max_chain": 0}, "max_chain"),
        ({"min_variance": -1.0}, "min_variance"),
        ({"gate_probability": 1.5}, "gate_probability"),
    ],
)
def test_bad_options_raise_value_error_naming_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        RelativeBackEnd(**kwargs)


def test_bad_calls_raise_value_error_naming_field(loop_ekf):
    with pytest.raises(ValueError, match="back_end"):
        make_back_end("graph")
    with pytest.raises(ValueError, match="method"):
        optimise_submaps(loop_ekf.system, "newton")
    plain = SubmapSLAM(
        EKFSLAM(loop_ekf.stream.sensor, loop_ekf.stream.clutter, loop_ekf.stream.odometry_noise),
        back_end=GlobalMap(),
    )
    plain.submaps = loop_ekf.system.submaps
    for name in ("initial_pose", "initial_pose_cov"):  # a back-end that does not record them
        plain.back_end.__dict__.pop(name, None)
    with pytest.raises(ValueError, match="initial_pose"):
        optimise_submaps(plain)
    optimise_submaps(plain, initial_pose=loop_ekf.stream.initial_pose)  # given explicitly
    assert is_spd(plain.back_end.P)
    with pytest.raises(ValueError, match="submaps"):
        build_submap_problem([], np.zeros(3))
    back = RelativeBackEnd()
    with pytest.raises(ValueError, match="local"):
        back.fuse(GaussianMap(np.zeros(5), np.eye(3), np.array([1]), np.ones(1)))
    with pytest.raises(ValueError, match="pose_index"):
        back.apply_optimum(3, np.zeros(3), np.eye(3))


def test_robust_kernel_of_the_system_is_used_and_keeps_a_spd_covariance(loop_ekf):
    r = loop_ekf
    plain = optimise_submaps(r.system)
    x_plain = r.system.back_end.x.copy()
    r.system.robust_kernel = "cauchy"
    try:
        res = r.system.optimise()
    finally:
        r.system.robust_kernel = None
    assert res.converged and res.optimiser.robust == "cauchy"
    assert is_spd(r.system.back_end.P)
    # consistent simulated sub-maps carry no outlier: the robust optimum stays near the plain one
    np.testing.assert_allclose(r.system.back_end.x, x_plain, atol=0.05)
    # the call overrides it
    assert r.system.optimise(robust=None, solver="general").optimiser.robust is None
    np.testing.assert_allclose(r.system.back_end.x, plain.x, atol=1e-9)
    with pytest.raises(ValueError, match="robust_kernel"):
        SubmapSLAM(EKFSLAM(r.stream.sensor, r.stream.clutter, r.stream.odometry_noise),
                   back_end="ekf", initial_pose=r.stream.initial_pose, robust_kernel="tukey")
