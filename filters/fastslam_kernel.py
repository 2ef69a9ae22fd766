"""Compiled work of one FastSLAM 2.0 iteration (numba), on one state structure.

:class:`ParticleState` holds every particle and its features: the arrays of the
:mod:`filters.fastslam` module docstring, one (P, C) array per feature component. Every kernel
below takes that state, and at most the scan, the model, the draws and the outputs besides; the
scalar helpers that each read as one equation take their scalars. The equations are those of the
:mod:`filters.fastslam` module docstring (FS2: Montemerlo et al. 2003; BB: Brooks & Bailey 2008),
which this module follows line by line:

* :func:`propagate`, :func:`draw_poses`: the motion prediction and the FS2 proposal prior, and
  the pose draw of an iteration that ended without a scan;
* :func:`scan_update`: one scan for every particle: the missed-detection product, Data
  Association Sampling (or known association), the FS2 proposal refinement, the pose draw and
  the map and existence updates at the drawn pose (BB (11));
* :func:`finish_scan`: the correspondence votes (BB 3.1), the ids, the clutter rate and culling;
* :func:`normalise_weights`, :func:`systematic_resample`: the weights, the resampling test and
  the resampling;
* :func:`update_iteration`: all of the scan's work above in one compiled call.

Why compiled: vectorised over the particles with numpy, every observation cost some hundred
array operations of a few microseconds each whatever the particle count (docs/PERFORMANCE.md,
issues #4, #6, 40). The random numbers are drawn by the caller from the generator of each
purpose (:mod:`filters.draws`) and handed over in blocks (:class:`ScanDraws`).

Since issue 47 the results are no longer kept equal to the bit to an earlier numpy code: the
weights' exponential is the compiled one (``math.exp``, the C library's), which rounds
differently from numpy's SIMD ``np.exp`` in about 5 % of arguments. Equivalence is checked by
distributions (docs/RESULTS.md) and each kernel against a plain numpy reference to rounding
(``tests/filters/test_fastslam_kernel.py``).

The scalar measurement functions below are those of :mod:`filters.models` (``h``, its Jacobian
w.r.t. the feature, the inverse observation ``g`` and its Jacobian w.r.t. ``z``) written out per
element; ``tests/filters/test_fastslam_kernel.py`` checks them against the vectorised reference.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from filters.conversion import CLUTTER_VOTE as CLUTTER
from filters.conversion import NEW_VOTE as NEW
from filters.conversion import (
    assign_correspondence_ids_unchecked,
    pose_moments_unchecked,
    vote_scan,
)
from filters.existence import (
    detection_update_one,
    existence_false_alarm_one,
    miss_update_one,
)
from filters.geometry import wrap_angle_one as _wrap

_TWO_PI = 2.0 * math.pi
_SQRT_HALF = math.sqrt(0.5)


class ParticleState(NamedTuple):
    """Every particle of the filter and its features (P particles, C feature slots each; a
    particle's active features are packed in slots ``0 .. count[p] - 1``)."""

    poses: np.ndarray         # (P, 3) x, y, theta: the proposal's mean until the pose is drawn
    prop_cov: np.ndarray      # (P, 3, 3) the FS2 proposal's covariance (zero once drawn)
    logw: np.ndarray          # (P,) log weights, shifted to a maximum of 0 after each scan
    mx: np.ndarray            # (P, C) feature means
    my: np.ndarray
    sxx: np.ndarray           # (P, C) feature covariances [[sxx, sxy], [sxy, syy]]
    sxy: np.ndarray
    syy: np.ndarray
    ex: np.ndarray            # (P, C) existence probabilities (BB (11))
    active: np.ndarray        # (P, C) bool: the slot holds a feature
    cid: np.ndarray           # (P, C) int64 common ids (BB (8)); -1: not yet a common feature
    count: np.ndarray         # (P,) int64 active features of each particle
    lineage: np.ndarray       # (P,) int64 each particle's ancestor at the last restart
    clutter_sums: np.ndarray  # (2,) the clutter rate's running numerator and denominator


FEATURE_FIELDS = ("mx", "my", "sxx", "sxy", "syy", "ex", "active", "cid")
"""The (P, C) fields of :class:`ParticleState`, which grow with the capacity."""
FEATURE_FILL = {"active": False, "cid": -1}
"""What an empty slot holds (0 in every other feature field)."""
_FEATURE_DTYPE = {"active": np.bool_, "cid": np.int64}


def new_state(n_particles: int, capacity: int, pose0) -> ParticleState:
    """P particles at ``pose0`` with zero uncertainty, equal weights and no features."""
    P, C = int(n_particles), int(capacity)
    features = {name: np.full((P, C), FEATURE_FILL.get(name, 0.0),
                              dtype=_FEATURE_DTYPE.get(name, np.float64))
                for name in FEATURE_FIELDS}
    return ParticleState(
        poses=np.tile(np.asarray(pose0, dtype=float), (P, 1)),
        prop_cov=np.zeros((P, 3, 3)),
        logw=np.zeros(P),
        count=np.zeros(P, dtype=np.int64),
        lineage=np.arange(P, dtype=np.int64),
        clutter_sums=np.zeros(2),
        **features,
    )


def grow_state(state: ParticleState, capacity: int) -> ParticleState:
    """The state with ``capacity`` feature slots per particle (empty slots appended)."""
    P, C = state.mx.shape
    extra = int(capacity) - C
    if extra <= 0:
        return state
    grown = {}
    for name in FEATURE_FIELDS:
        a = getattr(state, name)
        pad = np.full((P, extra), FEATURE_FILL.get(name, 0.0), dtype=a.dtype)
        grown[name] = np.concatenate([a, pad], axis=1)
    return state._replace(**grown)


class FilterModel(NamedTuple):
    """The constants of the filter's iteration: sensor, clutter and the filter's options."""

    r_var: float                  # range variance of R (diagonal)
    b_var: float                  # bearing variance of R
    detection_probability: float  # alpha (clipped)
    beta: float                   # false alarms per visible landmark (BB 5.1)
    gate_chi2: float              # association gate on S
    max_range_m: float
    fov_rad: float
    range_std_m: float
    bearing_std_rad: float
    new_landmark_density: float   # rho of L_new
    max_existence: float
    literal_beta: bool            # BB (11)'s P_fa read as beta itself ("bb")
    sample_clutter: bool          # clutter and new feature drawn as two hypotheses
    clutter_decay: float          # 1 - 1 / clutter_rate_memory
    cull_threshold: float
    resample_threshold: float     # resample when N_eff < threshold * P


class ScanDraws(NamedTuple):
    """The random numbers of one scan: ``uniforms`` (K, P) drive DAS (zeros under known
    association), ``normals`` (P, 3) the pose draw, ``resample_offset`` the systematic
    resampling's uniform (used only if the weights call for it)."""

    uniforms: np.ndarray
    normals: np.ndarray
    resample_offset: float


class ScanOutputs(NamedTuple):
    """What :func:`scan_update` leaves per observation k and particle p, (K, P) each: ``votes``
    (a common id, CLUTTER or NEW; a feature without id votes NEW), ``slots`` (the slot updated or
    created, -1 for clutter), ``logw_after`` (the log weight after the observation, for voting)
    and ``clutter_prob`` (the probability, under the particle's hypothesis, that the observation
    is a false alarm: 1 for clutter, ``1 - e_new`` for a new feature, 0 for an existing one)."""

    votes: np.ndarray
    slots: np.ndarray
    logw_after: np.ndarray
    clutter_prob: np.ndarray


def new_outputs(K: int, P: int) -> ScanOutputs:
    return ScanOutputs(np.empty((K, P), dtype=np.int64), np.empty((K, P), dtype=np.int64),
                       np.empty((K, P)), np.empty((K, P)))


class ScanResult(NamedTuple):
    """:func:`update_iteration`'s answer: the winning id of each observation (K,) and its vote
    margin (K,), the number of fresh ids it took, whether it resampled, and ``N_eff / P``
    before the resampling test."""

    winners: np.ndarray
    margins: np.ndarray
    n_new_ids: int
    resampled: bool
    ess_ratio: float


# --------------------------------------------------------------------------- scalar equations
@njit(cache=True, inline="always")
def _innovation(zr, zb, pose, mx, my):
    """Innovation ``z - h(pose, m)`` (bearing wrapped) and ``H_m``, the Jacobian of ``h`` w.r.t.
    the feature (:func:`filters.models.observe_jacobians`; ``H_pose = [-H_m | (0, -1)^T]``)."""
    dx = mx - pose[0]
    dy = my - pose[1]
    q = max(dx * dx + dy * dy, 1e-12)
    r = math.sqrt(q)
    return zr - r, _wrap(zb - math.atan2(dy, dx) + pose[2]), dx / r, dy / r, -dy / q, dx / q


@njit(cache=True, inline="always")
def _observation_terms(zr, zb, pose, Pc, state, p, j, model):
    """Innovation, ``S = G P G^T + H_m Sigma H_m^T + R`` and ``H_m`` of feature ``j`` of particle
    ``p`` for the proposal ``N(pose, Pc)`` (FS2; module doc of filters.fastslam). Returns
    ``(nu_r, nu_b, S00, S01, S11, det S, nu^T S^-1 nu, h00, h01, h10, h11)``."""
    nu_r, nu_b, h00, h01, h10, h11 = _innovation(zr, zb, pose, state.mx[p, j], state.my[p, j])
    m00 = state.sxx[p, j] + Pc[0, 0]
    m01 = state.sxy[p, j] + Pc[0, 1]
    m11 = state.syy[p, j] + Pc[1, 1]
    t00 = h00 * m00 + h01 * m01
    t01 = h00 * m01 + h01 * m11
    t10 = h10 * m00 + h11 * m01
    t11 = h10 * m01 + h11 * m11
    c0, c1 = Pc[0, 2], Pc[1, 2]
    S00 = h00 * t00 + h01 * t01 + model.r_var
    S01 = h10 * t00 + h11 * t01 + (h00 * c0 + h01 * c1)
    S11 = h10 * t10 + h11 * t11 + 2.0 * (h10 * c0 + h11 * c1) + Pc[2, 2] + model.b_var
    det = S00 * S11 - S01 * S01
    d2 = (S11 * nu_r * nu_r - 2.0 * S01 * nu_r * nu_b + S00 * nu_b * nu_b) / det
    return nu_r, nu_b, S00, S01, S11, det, d2, h00, h01, h10, h11


@njit(cache=True)
def _refine(pose, Pc, t, scratch):
    """FS2 proposal in Kalman form: ``x += P G^T S^-1 nu``, ``P -= P G^T S^-1 G P`` with
    ``G = [-H_m | (0, -1)^T]`` (in place; well defined for a singular P). ``t``: the
    :func:`_observation_terms` of the chosen feature; ``scratch`` (4, 3): work space."""
    nu_r, nu_b, S00, S01, S11, det = t[0], t[1], t[2], t[3], t[4], t[5]
    h00, h01, h10, h11 = t[7], t[8], t[9], t[10]
    inv_det = 1.0 / det
    pg0 = scratch[0]
    pg1 = scratch[1]
    for i in range(3):
        pg0[i] = -(Pc[i, 0] * h00 + Pc[i, 1] * h01)
        pg1[i] = -(Pc[i, 0] * h10 + Pc[i, 1] * h11 + Pc[i, 2])
    k0 = scratch[2]
    k1 = scratch[3]
    for i in range(3):
        k0[i] = (pg0[i] * S11 - pg1[i] * S01) * inv_det
        k1[i] = (pg1[i] * S00 - pg0[i] * S01) * inv_det
        pose[i] += k0[i] * nu_r + k1[i] * nu_b
    pose[2] = _wrap(pose[2])
    for i in range(3):
        for j in range(3):
            Pc[i, j] -= k0[i] * pg0[j] + k1[i] * pg1[j]


@njit(cache=True)
def _ldl_draw(cov, normals, out):
    """``out = L sqrt(D) n`` for a PSD ``cov`` (3, 3) via a guarded LDL^T: a pivot that is zero
    up to round-off (relative 1e-12 of the trace) gets a zero column, so singular proposals
    (rank-2 motion noise) are sampled correctly."""
    tiny = 1e-12 * max(cov[0, 0] + cov[1, 1] + cov[2, 2], 1e-300)
    d0 = cov[0, 0]
    ok0 = d0 > tiny
    l10 = cov[1, 0] / d0 if ok0 else 0.0
    l20 = cov[2, 0] / d0 if ok0 else 0.0
    d1 = cov[1, 1] - l10 * l10 * d0
    ok1 = d1 > tiny
    l21 = (cov[2, 1] - l20 * l10 * d0) / d1 if ok1 else 0.0
    d2 = cov[2, 2] - l20 * l20 * d0 - l21 * l21 * d1
    y0 = math.sqrt(d0) * normals[0] if ok0 else 0.0
    y1 = math.sqrt(d1) * normals[1] if ok1 else 0.0
    y2 = math.sqrt(d2) * normals[2] if d2 > tiny else 0.0
    out[0] = y0
    out[1] = l10 * y0 + y1
    out[2] = l20 * y0 + l21 * y1 + y2


@njit(cache=True, inline="always")
def _feature_ekf(pose, state, p, j, zr, zb, model):
    """EKF update of feature ``j`` of particle ``p`` from the known pose, in place: ``K = Sigma
    H^T S^-1``, ``m += K nu``, ``Sigma -= K H Sigma`` (the FS2 map update at the sampled
    pose)."""
    sxx, sxy, syy = state.sxx[p, j], state.sxy[p, j], state.syy[p, j]
    nu_r, nu_b, h00, h01, h10, h11 = _innovation(zr, zb, pose, state.mx[p, j], state.my[p, j])
    t00 = h00 * sxx + h01 * sxy
    t01 = h00 * sxy + h01 * syy
    t10 = h10 * sxx + h11 * sxy
    t11 = h10 * sxy + h11 * syy
    S00 = h00 * t00 + h01 * t01 + model.r_var
    S01 = h10 * t00 + h11 * t01
    S11 = h10 * t10 + h11 * t11 + model.b_var
    inv_det = 1.0 / (S00 * S11 - S01 * S01)
    K00 = (t00 * S11 - t10 * S01) * inv_det
    K01 = (t10 * S00 - t00 * S01) * inv_det
    K10 = (t01 * S11 - t11 * S01) * inv_det
    K11 = (t11 * S00 - t01 * S01) * inv_det
    state.mx[p, j] += K00 * nu_r + K01 * nu_b
    state.my[p, j] += K10 * nu_r + K11 * nu_b
    state.sxx[p, j] = sxx - (K00 * t00 + K01 * t10)
    state.sxy[p, j] = sxy - (K00 * t01 + K01 * t11)
    state.syy[p, j] = syy - (K10 * t01 + K11 * t11)


@njit(cache=True, inline="always")
def _new_feature(pose, state, p, j, zr, zb, model):
    """Feature ``j`` of particle ``p`` initialised from ``z`` at the known pose: ``m = g(pose,
    z)`` and ``Sigma = G_z R G_z^T`` with ``G_z = [[c, -r s], [s, r c]]`` (FS2,
    :func:`filters.models.inverse_observe`)."""
    c = math.cos(pose[2] + zb)
    s = math.sin(pose[2] + zb)
    state.mx[p, j] = pose[0] + zr * c
    state.my[p, j] = pose[1] + zr * s
    rs2 = zr * zr * model.b_var
    state.sxx[p, j] = c * c * model.r_var + s * s * rs2
    state.sxy[p, j] = c * s * (model.r_var - rs2)
    state.syy[p, j] = s * s * model.r_var + c * c * rs2


@njit(cache=True)
def _visibility(pose, Pc, state, p, j, max_range_m, fov_rad):
    """Probability that feature ``j`` of particle ``p`` lies inside the sensor's range:
    ``Phi((r_max - r) / sigma_r)`` with ``sigma_r^2`` the radial variance of feature and
    proposal position; a limited field of view is a hard bearing test on the mean (module doc of
    filters.fastslam)."""
    dx = state.mx[p, j] - pose[0]
    dy = state.my[p, j] - pose[1]
    q = max(dx * dx + dy * dy, 1e-12)
    r = math.sqrt(q)
    if fov_rad < _TWO_PI and abs(_wrap(math.atan2(dy, dx) - pose[2])) > 0.5 * fov_rad:
        return 0.0
    radial = (
        dx * dx * (state.sxx[p, j] + Pc[0, 0])
        + 2.0 * dx * dy * (state.sxy[p, j] + Pc[0, 1])
        + dy * dy * (state.syy[p, j] + Pc[1, 1])
    ) / q
    sigma = math.sqrt(max(radial, 0.0)) + 1e-9
    margin = (max_range_m - r) / sigma
    if margin > 8.5:  # Phi(8.5) = 1 - 1e-17: 1 in double precision
        return 1.0
    if margin < -40.0:  # Phi underflows
        return 0.0
    return 0.5 * math.erfc(-margin * _SQRT_HALF)


@njit(cache=True, inline="always")
def _gaussian_likelihood(d2, det):
    """``N(nu; 0, S)`` of a 2-vector from its Mahalanobis square ``d2`` and ``det S``."""
    return math.exp(-0.5 * d2) / (_TWO_PI * math.sqrt(abs(det)))


# --------------------------------------------------------------------------- prediction
@njit(cache=True)
def propagate(state, v, omega, dt, Q):
    """Motion prediction of every particle, in place: the pose through the unicycle mid-point
    model (:func:`filters.models.motion`) and the FS2 proposal prior ``J_u Q J_u^T`` in
    ``state.prop_cov`` (``J_u`` of :func:`filters.models.motion_jacobians`)."""
    poses, prop_cov = state.poses, state.prop_cov
    half_v_dt2 = 0.5 * v * dt * dt
    J = np.zeros((3, 2))
    J[2, 1] = dt
    for p in range(poses.shape[0]):
        heading = poses[p, 2] + 0.5 * omega * dt
        c, s = math.cos(heading), math.sin(heading)
        J[0, 0], J[0, 1] = dt * c, -half_v_dt2 * s
        J[1, 0], J[1, 1] = dt * s, half_v_dt2 * c
        for i in range(3):
            jq0 = J[i, 0] * Q[0, 0] + J[i, 1] * Q[1, 0]
            jq1 = J[i, 0] * Q[0, 1] + J[i, 1] * Q[1, 1]
            for j in range(3):
                prop_cov[p, i, j] = jq0 * J[j, 0] + jq1 * J[j, 1]
        poses[p, 0] += v * dt * c
        poses[p, 1] += v * dt * s
        poses[p, 2] = _wrap(poses[p, 2] + omega * dt)


@njit(cache=True)
def draw_poses(state, normals):
    """Draw every particle's pose from its proposal ``N(x, P)`` and zero ``P`` (in place;
    FS2)."""
    step = np.empty(3)
    for p in range(state.poses.shape[0]):
        _ldl_draw(state.prop_cov[p], normals[p], step)
        pose = state.poses[p]
        pose[0] += step[0]
        pose[1] += step[1]
        pose[2] = _wrap(pose[2] + step[2])
        state.prop_cov[p, :, :] = 0.0


# --------------------------------------------------------------------------- the scan
class _ScanWork(NamedTuple):
    """Work space of :func:`scan_update`, allocated once per scan and reused per particle."""

    p_vis: np.ndarray        # (n,) p_vis,j of each feature
    ratio: np.ndarray        # (n,) alpha e_j p_vis,j / (1 - alpha e_j p_vis,j)
    feature_std: np.ndarray  # (n,) sqrt(trace Sigma_j), for the Cartesian pre-gate
    claimed: np.ndarray      # (n,) taken by an earlier observation of the scan
    hyp_slot: np.ndarray     # (n + 2,) DAS hypotheses: slots, then NEW and CLUTTER
    hyp_value: np.ndarray    # (n + 2,) their likelihoods L
    hyp_terms: np.ndarray    # (n + 2, 11) the _observation_terms of each gated feature
    gate_areas: np.ndarray   # (K,) the gate area of the feature each observation updated
    new_existence: np.ndarray  # (K,) e_new of each observation
    step: np.ndarray         # (3,) the pose draw
    scratch: np.ndarray      # (4, 3) for _refine


@njit(cache=True)
def _scan_work(n, K):
    return _ScanWork(np.empty(n), np.empty(n), np.empty(n), np.empty(n, dtype=np.bool_),
                     np.empty(n + 2, dtype=np.int64), np.empty(n + 2), np.empty((n + 2, 11)),
                     np.empty(K), np.empty(K), np.empty(3), np.empty((4, 3)))


@njit(cache=True)
def _missed_detections(state, p, K, model, work):
    """The missed-detection product ``prod_j (1 - alpha e_j p_vis,j)`` into particle ``p``'s log
    weight, ``p_vis`` and the detection ratios of its features; returns ``n_vis``, the larger of
    ``sum_j e_j p_vis,j`` and the scan's own estimate ``K / (alpha + beta)``."""
    pose, Pc = state.poses[p], state.prop_cov[p]
    alpha = model.detection_probability
    expected_visible = 0.0
    for j in range(state.count[p]):
        work.claimed[j] = False
        if not state.active[p, j]:
            work.p_vis[j] = 0.0
            work.ratio[j] = 0.0
            continue
        work.feature_std[j] = math.sqrt(state.sxx[p, j] + state.syy[p, j])
        work.p_vis[j] = _visibility(pose, Pc, state, p, j, model.max_range_m, model.fov_rad)
        seen = alpha * state.ex[p, j] * work.p_vis[j]
        state.logw[p] += math.log(1.0 - seen)
        work.ratio[j] = seen / (1.0 - seen)
        expected_visible += state.ex[p, j] * work.p_vis[j]
    return max(expected_visible, K / (alpha + model.beta))


@njit(cache=True)
def _associate_known(state, p, k, zr, zb, target, l_new, work, model, out):
    """Known association of observation ``k`` in particle ``p``: the feature of common id
    ``target`` not yet claimed (weight ``ratio_j N(nu; 0, S)``), else a new feature (``L_new``);
    a known false alarm changes nothing. Returns the slot chosen (-1: none), or CLUTTER."""
    out.votes[k, p] = target
    if target < 0:
        out.slots[k, p] = CLUTTER
        out.clutter_prob[k, p] = 1.0
        return CLUTTER
    for j in range(state.count[p]):
        if state.active[p, j] and not work.claimed[j] and state.cid[p, j] == target:
            t = _observation_terms(zr, zb, state.poses[p], state.prop_cov[p], state, p, j, model)
            for i in range(11):
                work.hyp_terms[0, i] = t[i]
            lik = _gaussian_likelihood(t[6], t[5])
            state.logw[p] += math.log(max(work.ratio[j] * lik, 1e-300))
            return j
    state.logw[p] += math.log(max(l_new, 1e-300))
    out.slots[k, p] = NEW
    out.clutter_prob[k, p] = 1.0 - work.new_existence[k]
    return -1


@njit(cache=True)
def _associate_sampled(state, p, k, zr, zb, u, clutter_density, work, model, out):
    """Data Association Sampling (FS2) of observation ``k`` in particle ``p`` with the uniform
    ``u`` among the gated features (``L_j``), a new feature (``L_new``) and clutter; the weight
    is multiplied by ``sum_j L_j + L_new + L_clutter``. Returns the hypothesis drawn: its index
    into ``work.hyp_slot`` / ``work.hyp_terms``."""
    pose, Pc = state.poses[p], state.prop_cov[p]
    l_new = model.detection_probability * model.new_landmark_density * max(zr, model.range_std_m)
    gate_scale = math.sqrt(model.gate_chi2)
    sig_pos = math.sqrt(max(Pc[0, 0] + Pc[1, 1], 0.0))
    sig_th = math.sqrt(max(Pc[2, 2], 0.0))
    spread = sig_pos + zr * sig_th + model.range_std_m + zr * model.bearing_std_rad
    angle = pose[2] + zb
    px = pose[0] + zr * math.cos(angle)
    py = pose[1] + zr * math.sin(angle)
    n_hyp = 0
    for j in range(state.count[p]):
        if not state.active[p, j] or work.claimed[j]:
            continue
        # cheap Cartesian pre-gate: a sum of stds bounds the std of the sum
        radius = gate_scale * (spread + work.feature_std[j]) + 0.5
        ddx = state.mx[p, j] - px
        ddy = state.my[p, j] - py
        if ddx * ddx + ddy * ddy >= radius * radius:
            continue
        t = _observation_terms(zr, zb, pose, Pc, state, p, j, model)
        if t[6] < model.gate_chi2:
            like = work.ratio[j] * _gaussian_likelihood(t[6], t[5])
            if like > 0.0:
                work.hyp_slot[n_hyp] = j
                work.hyp_value[n_hyp] = like
                for i in range(11):
                    work.hyp_terms[n_hyp, i] = t[i]
                n_hyp += 1
    work.hyp_slot[n_hyp] = NEW
    work.hyp_slot[n_hyp + 1] = CLUTTER
    if model.sample_clutter:  # the earlier rule: new feature and clutter drawn apart
        work.hyp_value[n_hyp] = l_new
        work.hyp_value[n_hyp + 1] = clutter_density
    else:  # one Bernoulli hypothesis: a new feature that exists with e_new
        work.hyp_value[n_hyp] = l_new + clutter_density
        work.hyp_value[n_hyp + 1] = 0.0
    total = 0.0
    for i in range(n_hyp + 2):
        total += work.hyp_value[i]
    threshold = u * total
    pick = n_hyp + 1
    cumulative = 0.0
    for i in range(n_hyp + 2):
        cumulative += work.hyp_value[i]
        if cumulative >= threshold:
            pick = i
            break
    if work.hyp_value[pick] <= 0.0:  # only through round-off: step past it
        pick = n_hyp
    state.logw[p] += math.log(max(total, 1e-300))
    chosen = work.hyp_slot[pick]
    if chosen >= 0:
        out.votes[k, p] = state.cid[p, chosen] if state.cid[p, chosen] >= 0 else NEW
    else:
        out.votes[k, p] = chosen
        out.slots[k, p] = chosen
        if chosen == CLUTTER:
            out.clutter_prob[k, p] = 1.0
        elif not model.sample_clutter:
            out.clutter_prob[k, p] = 1.0 - work.new_existence[k]
    return pick


@njit(cache=True)
def _update_map(state, p, z, n, n_vis, work, model, out):
    """Particle ``p``'s existence and map at its drawn pose: the miss update of every feature it
    did not associate (BB (11), ``P_fa`` of the smallest gate, R's alone), the detection update
    and EKF of those it did, and the new features it created."""
    pose = state.poses[p]
    alpha = model.detection_probability
    area_r = math.pi * model.gate_chi2 * math.sqrt(model.r_var * model.b_var)
    p_fa_miss = existence_false_alarm_one(model.literal_beta, model.beta, n_vis, area_r,
                                          model.max_range_m, model.fov_rad)
    for j in range(n):
        if not work.claimed[j] and work.p_vis[j] > 0.0:
            state.ex[p, j] = miss_update_one(state.ex[p, j], alpha * work.p_vis[j], p_fa_miss)
    for k in range(z.shape[0]):
        j = out.slots[k, p]
        zr, zb = z[k, 0], z[k, 1]
        if j >= 0:
            _feature_ekf(pose, state, p, j, zr, zb, model)
            p_fa = existence_false_alarm_one(model.literal_beta, model.beta, n_vis,
                                             work.gate_areas[k], model.max_range_m, model.fov_rad)
            state.ex[p, j] = min(detection_update_one(state.ex[p, j], alpha, p_fa),
                                 model.max_existence)
        elif j == NEW:
            j = state.count[p]
            state.count[p] += 1
            _new_feature(pose, state, p, j, zr, zb, model)
            state.ex[p, j] = work.new_existence[k]
            state.active[p, j] = True
            state.cid[p, j] = -1
            out.slots[k, p] = j


@njit(cache=True)
def scan_update(state, z, known_cids, draws, model, out):
    """One scan ``z`` (K, 2) for every particle (module doc of filters.fastslam), in place.

    ``state.count`` grows by the features created (the caller guarantees ``C >= count + K``).
    ``known_cids`` (K,): for known association, the common id each observation belongs to (-1:
    a known false alarm); empty (0,) for DAS. ``draws``: :class:`ScanDraws`; ``out``:
    :class:`ScanOutputs`, written for every (k, p)."""
    P = state.poses.shape[0]
    K = z.shape[0]
    known = known_cids.shape[0] > 0
    alpha = model.detection_probability
    field = model.max_range_m * model.fov_rad
    work = _scan_work(state.count.max(), K)
    for p in range(P):
        pose, Pc = state.poses[p], state.prop_cov[p]
        n = state.count[p]
        n_vis = _missed_detections(state, p, K, model, work)
        clutter_density = model.beta * n_vis / field  # L_clutter (BB 5.1)

        # observations in turn: association, weight, proposal refinement
        for k in range(K):
            zr, zb = z[k, 0], z[k, 1]
            l_new = alpha * model.new_landmark_density * max(zr, model.range_std_m)
            work.new_existence[k] = min(l_new / (l_new + clutter_density), model.max_existence)
            out.clutter_prob[k, p] = 0.0
            if known:
                chosen = _associate_known(state, p, k, zr, zb, known_cids[k], l_new, work, model,
                                          out)
                terms = work.hyp_terms[0]
            else:
                pick = _associate_sampled(state, p, k, zr, zb, draws.uniforms[k, p],
                                          clutter_density, work, model, out)
                chosen = work.hyp_slot[pick]
                terms = work.hyp_terms[pick]  # the terms the gate formed, at this proposal
            if chosen >= 0:
                _refine(pose, Pc, terms, work.scratch)
                work.claimed[chosen] = True
                work.gate_areas[k] = math.pi * model.gate_chi2 * math.sqrt(abs(terms[5]))
                out.slots[k, p] = chosen
            out.logw_after[k, p] = state.logw[p]

        # the pose drawn from the refined proposal, then existence and map at that pose
        _ldl_draw(Pc, draws.normals[p], work.step)
        pose[0] += work.step[0]
        pose[1] += work.step[1]
        pose[2] = _wrap(pose[2] + work.step[2])
        Pc[:, :] = 0.0
        _update_map(state, p, z, n, n_vis, work, model, out)


# --------------------------------------------------------------------------- after the scan
@njit(cache=True)
def _permute_row(a, p, order, buffer):
    """``a[p] = a[p, order]`` through ``buffer``."""
    C = a.shape[1]
    for c in range(C):
        buffer[c] = a[p, order[c]]
    for c in range(C):
        a[p, c] = buffer[c]


@njit(cache=True)
def compact_features(state):
    """Move each particle's active features to its first slots, in place: active slots first,
    then the inactive ones, each in slot order (the permutation
    ``np.argsort(~active, axis=1, kind="stable")`` gives). Data movement only; a particle whose
    active slots already come first is left as it is."""
    active = state.active
    P, C = active.shape
    order = np.empty(C, dtype=np.int64)
    floats = np.empty(C)
    ints = np.empty(C, dtype=np.int64)
    flags = np.empty(C, dtype=np.bool_)
    for p in range(P):
        n = 0
        for c in range(C):
            if active[p, c]:
                order[n] = c
                n += 1
        for c in range(C):
            if not active[p, c]:
                order[n] = c
                n += 1
        identity = True
        for c in range(C):
            if order[c] != c:
                identity = False
                break
        if identity:
            continue
        for a in (state.mx, state.my, state.sxx, state.sxy, state.syy, state.ex):
            _permute_row(a, p, order, floats)
        _permute_row(state.cid, p, order, ints)
        _permute_row(active, p, order, flags)


@njit(cache=True)
def cull_features(state, threshold):
    """Remove the features whose existence is below ``threshold`` and re-pack each particle's
    slots, in place (``state.count`` rewritten). Returns whether any feature was removed (else
    nothing changes)."""
    active, ex = state.active, state.ex
    P, C = active.shape
    any_dead = False
    for p in range(P):
        for c in range(C):
            if active[p, c] and ex[p, c] < threshold:
                any_dead = True
                active[p, c] = False
    if not any_dead:
        return False
    compact_features(state)
    for p in range(P):
        n = 0
        for c in range(C):
            if active[p, c]:
                n += 1
            else:
                ex[p, c] = 0.0
                state.cid[p, c] = -1
        state.count[p] = n
    return True


@njit(cache=True)
def finish_scan(state, out, known_cids, next_id, cull, model):
    """The bookkeeping of one scan after :func:`scan_update`, in place (module doc of
    :mod:`filters.fastslam`, "Correspondences"): the vote of each observation (BB 3.1) with the
    weights after it (fresh ids ``next_id, next_id + 1, ...`` for the observations *new feature*
    wins, in observation order), the clutter rate's running sums, the winners' ids written into
    ``state.cid``, culling when ``cull``, and the log weights shifted to a maximum of 0. With
    ``known_cids`` (K,) the winners are those ids, no vote is taken and the clutter rate is left
    alone. Returns ``(winners, margins, n_new_ids)``."""
    K = out.votes.shape[0]
    if known_cids.shape[0] == 0:
        winners, margins, shares = vote_scan(out.logw_after, out.votes, out.clutter_prob)
        n_new = 0
        for k in range(K):
            if winners[k] == NEW:
                winners[k] = next_id + n_new
                n_new += 1
        sums = state.clutter_sums
        for k in range(K):
            sums[0] = model.clutter_decay * sums[0] + shares[k]
            sums[1] = model.clutter_decay * sums[1] + 1.0
    else:
        winners = known_cids.copy()
        margins = np.ones(K)
        n_new = 0
    assign_correspondence_ids_unchecked(state.cid, state.active, out.slots, winners)
    if cull:
        cull_features(state, model.cull_threshold)
    logw = state.logw
    if logw.shape[0]:
        top = logw.max()
        for p in range(logw.shape[0]):
            logw[p] -= top
    return winners, margins, n_new


@njit(cache=True)
def normalise_weights(logw, w, threshold):
    """The normalised weights ``w = exp(logw - max) / sum`` (into ``w``) and the resampling test:
    returns ``(N_eff < threshold * P, N_eff / P)`` with ``N_eff = 1 / sum w^2``."""
    P = logw.shape[0]
    top = logw.max()
    total = 0.0
    for p in range(P):
        w[p] = math.exp(logw[p] - top)
        total += w[p]
    squares = 0.0
    for p in range(P):
        w[p] = w[p] / total
        squares += w[p] * w[p]
    n_eff = 1.0 / squares
    return not n_eff >= threshold * P, n_eff / P


@njit(cache=True)
def _gather_rows(a, idx, out):
    """``out[:] = a[idx]`` along the first axis."""
    for p in range(idx.shape[0]):
        out[p] = a[idx[p]]


@njit(cache=True)
def systematic_resample(state, w, start, spare):
    """Systematic resampling with the uniform ``start``: the particles
    ``searchsorted(cumsum(w), (start + arange(P)) / P, side="right")`` (the cdf's last entry set
    to 1, the index capped at P - 1) of ``state`` gathered into ``spare`` (a state of the same
    shapes, which the caller then takes as its state); the spare's log weights zeroed and ``w``
    made uniform, in place. The clutter sums are the filter's, not the particles': copied."""
    P = w.shape[0]
    cdf = np.empty(P)
    cdf[0] = w[0]
    for p in range(1, P):
        cdf[p] = cdf[p - 1] + w[p]
    cdf[P - 1] = 1.0
    idx = np.empty(P, dtype=np.int64)
    q = 0
    for p in range(P):  # the positions rise, so one pass over the cdf finds every index
        position = (start + p) / P
        while q < P - 1 and not position < cdf[q]:
            q += 1
        idx[p] = q
    _gather_rows(state.poses, idx, spare.poses)
    _gather_rows(state.prop_cov, idx, spare.prop_cov)
    for a, b in ((state.mx, spare.mx), (state.my, spare.my), (state.sxx, spare.sxx),
                 (state.sxy, spare.sxy), (state.syy, spare.syy), (state.ex, spare.ex)):
        _gather_rows(a, idx, b)
    _gather_rows(state.active, idx, spare.active)
    _gather_rows(state.cid, idx, spare.cid)
    _gather_rows(state.count, idx, spare.count)
    _gather_rows(state.lineage, idx, spare.lineage)
    spare.clutter_sums[:] = state.clutter_sums
    for p in range(P):
        spare.logw[p] = 0.0
        w[p] = 1.0 / P


@njit(cache=True)
def update_iteration(state, z, known_cids, draws, model, out, next_id, cull, w, spare):
    """One scan's whole work in one compiled call: :func:`scan_update`, :func:`finish_scan`, the
    weights (into ``w``) and the resampling test, and the resampling into ``spare`` when the
    test calls for it (the caller then takes ``spare`` as its state). Returns
    :class:`ScanResult`."""
    scan_update(state, z, known_cids, draws, model, out)
    winners, margins, n_new = finish_scan(state, out, known_cids, next_id, cull, model)
    resample, ess_ratio = normalise_weights(state.logw, w, model.resample_threshold)
    if resample:
        systematic_resample(state, w, draws.resample_offset, spare)
    return ScanResult(winners, margins, n_new, resample, ess_ratio)


# --------------------------------------------------------------------------- the local pose
@njit(cache=True)
def local_pose(state, w, pending, lineage_correction, small_sample):
    """The local pose's weighted mean and covariance, BB (7) (circular mean heading), from the
    normalised weights ``w``: with the proposals' covariances while ``pending``, the lineage term
    when ``lineage_correction`` and the small-sample factor when ``small_sample``
    (:func:`filters.conversion.pose_moments_unchecked`, module doc of filters.fastslam)."""
    covs = state.prop_cov if pending else np.zeros((0, 3, 3))
    lineage = state.lineage if lineage_correction else np.zeros(0, dtype=np.int64)
    return pose_moments_unchecked(state.poses, w, covs, lineage, lineage.shape[0], small_sample)
