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
* :func:`update_iteration`: all of the scan's work above in one compiled call;
* :func:`heading_update`: a compass reading (the FS2 proposal refined, or the weights alone);
* :func:`iteration`: one whole filter iteration in one compiled call (issue 47): the pending pose
  draw, the prediction, the compass, CM's innovation ratio against the prior, the scan, the
  local pose's moments, the pose composed with the local map's origin and its NEES against the
  truth (:mod:`filters.global_frame`).

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
from filters.global_frame import compose_with_covariance, nearest_global_innovations, pose_metrics

_TWO_PI = 2.0 * math.pi
_SQRT_HALF = math.sqrt(0.5)
_CERTAIN_MARGIN = 8.5
"""Range margins, in radial standard deviations, beyond which :func:`_visibility` is 1:
``Phi(8.5) = 1 - 1e-17``, 1 in double precision."""


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


class IterationInput(NamedTuple):
    """What one filter iteration is given: the odometry ``(v, omega)`` over ``dt`` seconds and its
    covariance ``Q`` (2, 2), a compass heading in the local frame with its variance (NaN: no
    reading), and the scan ``z`` (K, 2) with ``known_cids`` as :func:`scan_update` takes them;
    ``scanned`` False for an iteration without a scan (``z`` then empty)."""

    v: float
    omega: float
    dt: float
    Q: np.ndarray
    heading: float
    heading_var: float
    scanned: bool
    z: np.ndarray
    known_cids: np.ndarray


class IterationDraws(NamedTuple):
    """The random numbers of one filter iteration, one block per role of
    :data:`filters.draws.ROLES`: ``pending_normals`` (P, 3) the pose draw of a proposal left by
    an iteration without a scan (``pending_pose``; empty when there is none), the resampling
    uniforms after it (``resample_after_pending``) and after a compass reading that came after
    the pose was drawn (``resample_after_heading``), then the scan's :class:`ScanDraws` fields
    (``association``, ``scan_pose``, ``resample_after_scan``). A uniform is used only where the
    weights call for a resampling."""

    pending_normals: np.ndarray
    pending_offset: float
    heading_offset: float
    uniforms: np.ndarray
    normals: np.ndarray
    resample_offset: float


class GlobalFrame(NamedTuple):
    """Where the local map sits (BB Fig. 3): its origin ``v-`` (3,) with covariance (3, 3), and
    the global map CM's innovation ratio tests the scan against (CM III.B): the back-end's state
    ``x``, covariance ``P``, its features' columns ``cols`` (N, 2) (none: no ratio) and the
    search radius (:func:`filters.global_frame.nearest_global_innovations`). A front-end alone
    sits at a zero origin known exactly, with no global features."""

    origin: np.ndarray
    origin_cov: np.ndarray
    x: np.ndarray
    P: np.ndarray
    cols: np.ndarray
    radius_m: float


class IterationResult(NamedTuple):
    """:func:`iteration`'s answer: how often the state and the spare swapped (an odd count: the
    spare holds the state), CM's innovation ratio of the scan against the prior (0 without global
    features), the scan's winners and margins (K,) and fresh ids, ``N_eff / P`` of the last
    resampling test (NaN: none ran), the local pose's moments, the global pose's (the local one
    composed with the origin) and ``J_a``, its NEES and position error against the truth (NaN
    without truth)."""

    swaps: int
    innovation_ratio: float
    winners: np.ndarray
    margins: np.ndarray
    n_new_ids: int
    ess_ratio: float
    local_mean: np.ndarray
    local_cov: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    J_a: np.ndarray
    nees: float
    position_error_m: float


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
def _observation_terms(zr, zb, pose, Pc, mx, my, sxx, sxy, syy, r_var, b_var):
    """Innovation, ``S = G P G^T + H_m Sigma H_m^T + R`` and ``H_m`` of the feature ``N((mx, my),
    [[sxx, sxy], [sxy, syy]])`` for the proposal ``N(pose, Pc)`` (FS2; module doc of
    filters.fastslam). Returns ``(nu_r, nu_b, S00, S01, S11, det S, nu^T S^-1 nu, h00, h01, h10,
    h11)``."""
    nu_r, nu_b, h00, h01, h10, h11 = _innovation(zr, zb, pose, mx, my)
    m00 = sxx + Pc[0, 0]
    m01 = sxy + Pc[0, 1]
    m11 = syy + Pc[1, 1]
    t00 = h00 * m00 + h01 * m01
    t01 = h00 * m01 + h01 * m11
    t10 = h10 * m00 + h11 * m01
    t11 = h10 * m01 + h11 * m11
    c0, c1 = Pc[0, 2], Pc[1, 2]
    S00 = h00 * t00 + h01 * t01 + r_var
    S01 = h10 * t00 + h11 * t01 + (h00 * c0 + h01 * c1)
    S11 = h10 * t10 + h11 * t11 + 2.0 * (h10 * c0 + h11 * c1) + Pc[2, 2] + b_var
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
def _ldl_draw(c00, c10, c11, c20, c21, c22, n0, n1, n2):
    """``L sqrt(D) n`` for a PSD covariance (the lower triangle ``c``) and standard normals ``n``
    via a guarded LDL^T: a pivot that is zero up to round-off (relative 1e-12 of the trace) gets
    a zero column, so singular proposals (rank-2 motion noise) are sampled correctly. Scalars
    only (an array argument would cost its reference counts at every call)."""
    tiny = 1e-12 * max(c00 + c11 + c22, 1e-300)
    d0 = c00
    ok0 = d0 > tiny
    l10 = c10 / d0 if ok0 else 0.0
    l20 = c20 / d0 if ok0 else 0.0
    d1 = c11 - l10 * l10 * d0
    ok1 = d1 > tiny
    l21 = (c21 - l20 * l10 * d0) / d1 if ok1 else 0.0
    d2 = c22 - l20 * l20 * d0 - l21 * l21 * d1
    y0 = math.sqrt(d0) * n0 if ok0 else 0.0
    y1 = math.sqrt(d1) * n1 if ok1 else 0.0
    y2 = math.sqrt(d2) * n2 if d2 > tiny else 0.0
    return y0, l10 * y0 + y1, l20 * y0 + l21 * y1 + y2


@njit(cache=True, inline="always")
def _draw_pose(pose, Pc, normals):
    """The pose drawn from the proposal ``N(pose, Pc)`` with the normals (3,), in place (heading
    wrapped), and ``Pc`` zeroed (FS2)."""
    s0, s1, s2 = _ldl_draw(Pc[0, 0], Pc[1, 0], Pc[1, 1], Pc[2, 0], Pc[2, 1], Pc[2, 2],
                           normals[0], normals[1], normals[2])
    pose[0] += s0
    pose[1] += s1
    pose[2] = _wrap(pose[2] + s2)
    Pc[:, :] = 0.0


@njit(cache=True, inline="always")
def _feature_ekf(pose, mx, my, sxx, sxy, syy, zr, zb, r_var, b_var):
    """EKF update of one feature from a known pose: ``K = Sigma H^T S^-1``, ``m += K nu``,
    ``Sigma -= K H Sigma`` (the FS2 map update at the sampled pose); returns the feature's new
    ``(mx, my, sxx, sxy, syy)``."""
    nu_r, nu_b, h00, h01, h10, h11 = _innovation(zr, zb, pose, mx, my)
    t00 = h00 * sxx + h01 * sxy
    t01 = h00 * sxy + h01 * syy
    t10 = h10 * sxx + h11 * sxy
    t11 = h10 * sxy + h11 * syy
    S00 = h00 * t00 + h01 * t01 + r_var
    S01 = h10 * t00 + h11 * t01
    S11 = h10 * t10 + h11 * t11 + b_var
    inv_det = 1.0 / (S00 * S11 - S01 * S01)
    K00 = (t00 * S11 - t10 * S01) * inv_det
    K01 = (t10 * S00 - t00 * S01) * inv_det
    K10 = (t01 * S11 - t11 * S01) * inv_det
    K11 = (t11 * S00 - t01 * S01) * inv_det
    return (
        mx + K00 * nu_r + K01 * nu_b,
        my + K10 * nu_r + K11 * nu_b,
        sxx - (K00 * t00 + K01 * t10),
        sxy - (K00 * t01 + K01 * t11),
        syy - (K10 * t01 + K11 * t11),
    )


@njit(cache=True, inline="always")
def _new_feature(pose, zr, zb, r_var, b_var):
    """A feature initialised from ``z`` at the known pose: ``m = g(pose, z)`` and ``Sigma = G_z
    R G_z^T`` with ``G_z = [[c, -r s], [s, r c]]`` (FS2, :func:`filters.models.inverse_observe`);
    returns ``(mx, my, sxx, sxy, syy)``."""
    c = math.cos(pose[2] + zb)
    s = math.sin(pose[2] + zb)
    rs2 = zr * zr * b_var
    return (pose[0] + zr * c, pose[1] + zr * s, c * c * r_var + s * s * rs2,
            c * s * (r_var - rs2), s * s * r_var + c * c * rs2)


@njit(cache=True)
def _visibility(dx, dy, heading, cxx, cxy, cyy, max_range_m, fov_rad):
    """Probability that a feature at ``(dx, dy)`` from the pose lies inside the sensor's range:
    ``Phi((r_max - r) / sigma_r)`` with ``sigma_r^2`` the radial variance of the sum ``[[cxx, cxy],
    [cxy, cyy]]`` of the feature's and the proposal's position covariances; a limited field of
    view is a hard bearing test on the mean against ``heading`` (module doc of filters.fastslam).
    Scalars only: an array argument would cost its reference counts at every call."""
    q = max(dx * dx + dy * dy, 1e-12)
    r = math.sqrt(q)
    if fov_rad < _TWO_PI and abs(_wrap(math.atan2(dy, dx) - heading)) > 0.5 * fov_rad:
        return 0.0
    radial = (dx * dx * cxx + 2.0 * dx * dy * cxy + dy * dy * cyy) / q
    sigma = math.sqrt(max(radial, 0.0)) + 1e-9
    margin = (max_range_m - r) / sigma
    if margin > _CERTAIN_MARGIN:
        return 1.0
    if margin < -40.0:  # Phi underflows
        return 0.0
    return 0.5 * math.erfc(-margin * _SQRT_HALF)


@njit(cache=True, inline="always")
def _certainly_in_range(dx, dy, cxx, cxy, cyy, std_bound, max_range_m):
    """Whether :func:`_visibility` of a feature at ``(dx, dy)`` with the position covariance
    ``[[cxx, cxy], [cxy, cyy]]`` is 1 for certain (its range margin beyond
    :data:`_CERTAIN_MARGIN` standard deviations), decided without its square roots and
    divisions: for a positive semi-definite covariance the radial variance is at most the
    largest eigenvalue, at most the trace, and ``std_bound`` bounds the trace's square root (the
    caller's ``sqrt(feature trace) + sqrt(proposal trace)``, since ``sqrt(a + b) <= sqrt(a) +
    sqrt(b)``). The bound is widened by a relative 1e-9 and the range shortened by as much, far
    beyond the rounding of :func:`_visibility`'s own arithmetic, so a feature passed here is one
    it would give 1.0, and the scan's numbers are unchanged to the bit. Anything else (a
    covariance not semi-definite, NaN, a feature near the edge) returns False: the caller then
    asks :func:`_visibility`."""
    if not (cxx >= 0.0 and cyy >= 0.0 and cxy * cxy <= cxx * cyy):
        return False
    reach = max_range_m - _CERTAIN_MARGIN * (std_bound * (1.0 + 1e-9) + 2e-9)
    return reach > 0.0 and dx * dx + dy * dy < reach * reach * (1.0 - 1e-9)


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
    poses, prop_cov = state.poses, state.prop_cov
    for p in range(poses.shape[0]):
        _draw_pose(poses[p], prop_cov[p], normals[p])


@njit(cache=True)
def heading_update(state, theta, var, pending):
    """A compass reading ``theta`` (variance ``var``) of every particle's heading, in place
    (:meth:`filters.fastslam.FastSLAM2.update_heading`). While the proposal is ``pending`` it is
    refined by the scalar Kalman update ``x += P e3 nu / s``, ``P -= P e3 e3^T P / s`` (then
    symmetrised), ``s = P_tt + var``, ``nu = theta - x_t`` wrapped, and the weight multiplied by
    ``N(nu; 0, s)``; after the pose draw only the weight, with ``s = var``. The log weights are
    shifted to a maximum of 0."""
    poses, prop_cov, logw = state.poses, state.prop_cov, state.logw
    k = np.empty(3)
    for p in range(poses.shape[0]):
        nu = _wrap(theta - poses[p, 2])
        s = var
        if pending:
            Pc = prop_cov[p]
            s = Pc[2, 2] + var
            for i in range(3):
                k[i] = Pc[i, 2] / s
            poses[p, 0] += k[0] * nu
            poses[p, 1] += k[1] * nu
            poses[p, 2] = _wrap(poses[p, 2] + k[2] * nu)
            r0, r1, r2 = Pc[2, 0], Pc[2, 1], Pc[2, 2]
            for i in range(3):
                Pc[i, 0] -= k[i] * r0
                Pc[i, 1] -= k[i] * r1
                Pc[i, 2] -= k[i] * r2
            for i in range(3):
                for j in range(i + 1, 3):
                    Pc[i, j] = 0.5 * (Pc[i, j] + Pc[j, i])
                    Pc[j, i] = Pc[i, j]
        logw[p] += -0.5 * nu * nu / s - 0.5 * math.log(_TWO_PI * s)
    top = logw.max()
    for p in range(logw.shape[0]):
        logw[p] -= top


# --------------------------------------------------------------------------- the scan
# One function body: a helper that took the state (a tuple of arrays) and was called per particle
# and observation counted a reference to every array of the tuple at each call, twice the scan's
# time (measured, docs/PERFORMANCE.md); the scalar helpers above take their scalars.
@njit(cache=True)
def scan_update(state, z, known_cids, draws, model, out):
    """One scan ``z`` (K, 2) for every particle (module doc of filters.fastslam), in place.

    ``state.count`` grows by the features created (the caller guarantees ``C >= count + K``).
    ``known_cids`` (K,): for known association, the common id each observation belongs to (-1:
    a known false alarm); empty (0,) for DAS. ``draws``: :class:`ScanDraws`; ``out``:
    :class:`ScanOutputs`, written for every (k, p). Per particle, in turn: the missed-detection
    product; each observation's association (DAS among the gated features, a new feature and
    clutter, or the known one), the weight's factor and the FS2 proposal refinement; the pose
    drawn from the refined proposal; existence (BB (11)) and the map at the drawn pose.
    """
    poses, prop_cov, logw, count = state.poses, state.prop_cov, state.logw, state.count
    mx, my, sxx, sxy, syy = state.mx, state.my, state.sxx, state.sxy, state.syy
    ex, active, cid = state.ex, state.active, state.cid
    votes, slots, logw_after, clutter_prob = out
    uniforms, normals = draws.uniforms, draws.normals
    r_var, b_var, alpha, beta = model.r_var, model.b_var, model.detection_probability, model.beta
    gate_chi2, max_range_m, fov_rad = model.gate_chi2, model.max_range_m, model.fov_rad
    range_std_m, bearing_std_rad = model.range_std_m, model.bearing_std_rad
    sample_clutter, literal_beta = model.sample_clutter, model.literal_beta
    P = poses.shape[0]
    K = z.shape[0]
    known = known_cids.shape[0] > 0
    n_hi = count.max()
    field = max_range_m * fov_rad
    gate_scale = math.sqrt(gate_chi2)
    area_r = math.pi * gate_chi2 * math.sqrt(r_var * b_var)  # the gate of R alone
    p_vis = np.empty(n_hi)
    ratio = np.empty(n_hi)  # alpha e_j p_vis,j / (1 - alpha e_j p_vis,j)
    claimed = np.empty(n_hi, dtype=np.bool_)  # taken by an earlier observation of the scan
    hyp_slot = np.empty(n_hi + 2, dtype=np.int64)  # DAS hypotheses: slots, NEW, CLUTTER
    hyp_value = np.empty(n_hi + 2)  # their likelihoods L
    hyp_terms = np.empty((n_hi + 2, 11))  # _observation_terms of each gated feature
    feature_std = np.empty(n_hi)  # sqrt(trace) of each feature's covariance, for the pre-gate
    gate_areas = np.empty(K)
    new_existence = np.empty(K)
    scratch = np.empty((4, 3))
    full_view = fov_rad >= _TWO_PI  # no bearing test: a feature in range is visible
    # the miss terms log(1 - seen) and seen / (1 - seen) of the last particle, per slot: after a
    # resampling neighbouring particles are copies of one ancestor, whose features (and so their
    # terms) are equal, and an equal argument gives the equal value without its log
    last_seen = np.full(n_hi, -1.0)
    last_log_miss = np.empty(n_hi)
    last_ratio = np.empty(n_hi)
    for p in range(P):
        pose = poses[p]
        Pc = prop_cov[p]
        n = count[p]
        # --- visibility and the missed-detection product prod_j (1 - alpha e_j p_vis,j)
        expected_visible = 0.0
        proposal_std = math.sqrt(max(Pc[0, 0] + Pc[1, 1], 0.0))
        for j in range(n):
            claimed[j] = False
            if not active[p, j]:
                p_vis[j] = 0.0
                ratio[j] = 0.0
                continue
            feature_std[j] = math.sqrt(sxx[p, j] + syy[p, j])
            dx = mx[p, j] - pose[0]
            dy = my[p, j] - pose[1]
            cxx = sxx[p, j] + Pc[0, 0]
            cxy = sxy[p, j] + Pc[0, 1]
            cyy = syy[p, j] + Pc[1, 1]
            if full_view and _certainly_in_range(dx, dy, cxx, cxy, cyy,
                                                 feature_std[j] + proposal_std, max_range_m):
                p_vis[j] = 1.0
            else:
                p_vis[j] = _visibility(dx, dy, pose[2], cxx, cxy, cyy, max_range_m, fov_rad)
            seen = alpha * ex[p, j] * p_vis[j]
            if seen != last_seen[j]:
                last_seen[j] = seen
                last_log_miss[j] = math.log(1.0 - seen)
                last_ratio[j] = seen / (1.0 - seen)
            logw[p] += last_log_miss[j]
            ratio[j] = last_ratio[j]
            expected_visible += ex[p, j] * p_vis[j]
        n_vis = max(expected_visible, K / (alpha + beta))
        clutter_density = beta * n_vis / field  # L_clutter (BB 5.1)

        # --- observations in turn: association, weight, proposal refinement
        for k in range(K):
            zr, zb = z[k, 0], z[k, 1]
            l_new = alpha * model.new_landmark_density * max(zr, range_std_m)
            new_existence[k] = min(l_new / (l_new + clutter_density), model.max_existence)
            chosen = -1
            clutter_prob[k, p] = 0.0
            if known:
                target = known_cids[k]
                votes[k, p] = target
                if target < 0:  # a known false alarm
                    slots[k, p] = CLUTTER
                    clutter_prob[k, p] = 1.0
                    logw_after[k, p] = logw[p]
                    continue
                for j in range(n):
                    if active[p, j] and not claimed[j] and cid[p, j] == target:
                        chosen = j
                        break
                if chosen >= 0:  # N(nu; 0, S) times the detection ratio
                    t = _observation_terms(zr, zb, pose, Pc, mx[p, chosen], my[p, chosen],
                                           sxx[p, chosen], sxy[p, chosen], syy[p, chosen],
                                           r_var, b_var)
                    lik = _gaussian_likelihood(t[6], t[5])
                    logw[p] += math.log(max(ratio[chosen] * lik, 1e-300))
                else:
                    logw[p] += math.log(max(l_new, 1e-300))
                    slots[k, p] = NEW
                    clutter_prob[k, p] = 1.0 - new_existence[k]
            else:
                # Data Association Sampling among the gated features, new feature and clutter
                sig_pos = math.sqrt(max(Pc[0, 0] + Pc[1, 1], 0.0))
                sig_th = math.sqrt(max(Pc[2, 2], 0.0))
                spread = sig_pos + zr * sig_th + range_std_m + zr * bearing_std_rad
                angle = pose[2] + zb
                px = pose[0] + zr * math.cos(angle)
                py = pose[1] + zr * math.sin(angle)
                n_hyp = 0
                for j in range(n):
                    if not active[p, j] or claimed[j]:
                        continue
                    # cheap Cartesian pre-gate: a sum of stds bounds the std of the sum
                    radius = gate_scale * (spread + feature_std[j]) + 0.5
                    ddx = mx[p, j] - px
                    ddy = my[p, j] - py
                    if ddx * ddx + ddy * ddy >= radius * radius:
                        continue
                    t = _observation_terms(zr, zb, pose, Pc, mx[p, j], my[p, j], sxx[p, j],
                                           sxy[p, j], syy[p, j], r_var, b_var)
                    if t[6] < gate_chi2:  # L_j
                        like = ratio[j] * _gaussian_likelihood(t[6], t[5])
                        if like > 0.0:
                            hyp_slot[n_hyp] = j
                            hyp_value[n_hyp] = like
                            for i in range(11):
                                hyp_terms[n_hyp, i] = t[i]
                            n_hyp += 1
                hyp_slot[n_hyp] = NEW
                hyp_slot[n_hyp + 1] = CLUTTER
                if sample_clutter:  # the earlier rule: new feature and clutter drawn apart
                    hyp_value[n_hyp] = l_new
                    hyp_value[n_hyp + 1] = clutter_density
                else:  # one Bernoulli hypothesis: a new feature that exists with e_new
                    hyp_value[n_hyp] = l_new + clutter_density
                    hyp_value[n_hyp + 1] = 0.0
                total = 0.0
                for i in range(n_hyp + 2):
                    total += hyp_value[i]
                threshold = uniforms[k, p] * total
                pick = n_hyp + 1
                cumulative = 0.0
                for i in range(n_hyp + 2):
                    cumulative += hyp_value[i]
                    if cumulative >= threshold:
                        pick = i
                        break
                if hyp_value[pick] <= 0.0:  # only through round-off: step past it
                    pick = n_hyp
                logw[p] += math.log(max(total, 1e-300))  # sum_j L_j + L_new + L_clutter
                chosen = hyp_slot[pick]
                if chosen >= 0:
                    votes[k, p] = cid[p, chosen] if cid[p, chosen] >= 0 else NEW
                    h = hyp_terms[pick]  # the terms the gate formed for it, at this proposal
                    t = (h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8], h[9], h[10])
                else:
                    votes[k, p] = chosen
                    slots[k, p] = chosen
                    if chosen == CLUTTER:
                        clutter_prob[k, p] = 1.0
                    elif not sample_clutter:
                        clutter_prob[k, p] = 1.0 - new_existence[k]
            if chosen >= 0:
                _refine(pose, Pc, t, scratch)
                claimed[chosen] = True
                gate_areas[k] = math.pi * gate_chi2 * math.sqrt(abs(t[5]))
                slots[k, p] = chosen
            logw_after[k, p] = logw[p]

        # --- draw the pose from the refined proposal, then existence and map at that pose
        _draw_pose(pose, Pc, normals[p])
        p_fa_miss = existence_false_alarm_one(literal_beta, beta, n_vis, area_r, max_range_m,
                                              fov_rad)
        for j in range(n):  # the miss update of BB (11) for every feature not associated
            if not claimed[j] and p_vis[j] > 0.0:
                ex[p, j] = miss_update_one(ex[p, j], alpha * p_vis[j], p_fa_miss)
        for k in range(K):
            j = slots[k, p]
            zr, zb = z[k, 0], z[k, 1]
            if j >= 0:  # the EKF at the drawn pose and BB (11)'s detection update
                mx[p, j], my[p, j], sxx[p, j], sxy[p, j], syy[p, j] = _feature_ekf(
                    pose, mx[p, j], my[p, j], sxx[p, j], sxy[p, j], syy[p, j], zr, zb, r_var,
                    b_var,
                )
                p_fa = existence_false_alarm_one(literal_beta, beta, n_vis, gate_areas[k],
                                                 max_range_m, fov_rad)
                ex[p, j] = min(detection_update_one(ex[p, j], alpha, p_fa), model.max_existence)
            elif j == NEW:
                j = count[p]
                count[p] += 1
                mx[p, j], my[p, j], sxx[p, j], sxy[p, j], syy[p, j] = _new_feature(
                    pose, zr, zb, r_var, b_var)
                ex[p, j] = new_existence[k]
                active[p, j] = True
                cid[p, j] = -1
                slots[k, p] = j


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
    """``out[:] = a[idx]`` along the first axis (C-contiguous arrays; element by element: a
    row slice's assignment costs more than the few elements it copies)."""
    src = a.reshape((a.shape[0], -1))
    dst = out.reshape((out.shape[0], -1))
    for p in range(idx.shape[0]):
        q = idx[p]
        for c in range(src.shape[1]):
            dst[p, c] = src[q, c]


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
def _resample_if_called_for(state, spare, w, offset, model):
    """The weights (into ``w``) and the resampling test; the resampling into ``spare`` when it
    calls for it. Returns ``(resampled, N_eff / P)``."""
    resample, ess_ratio = normalise_weights(state.logw, w, model.resample_threshold)
    if resample:
        systematic_resample(state, w, offset, spare)
    return resample, ess_ratio


@njit(cache=True)
def update_iteration(state, z, known_cids, draws, model, out, next_id, cull, w, spare):
    """One scan's whole work in one compiled call: :func:`scan_update`, :func:`finish_scan`, the
    weights (into ``w``) and the resampling test, and the resampling into ``spare`` when the
    test calls for it (the caller then takes ``spare`` as its state). Returns the fields of
    :class:`ScanResult`, in its order."""
    scan_update(state, z, known_cids, draws, model, out)
    winners, margins, n_new = finish_scan(state, out, known_cids, next_id, cull, model)
    resample, ess_ratio = _resample_if_called_for(state, spare, w, draws.resample_offset, model)
    # the fields of ScanResult (a plain tuple: boxing a named tuple costs an unpickling a call)
    return winners, margins, n_new, resample, ess_ratio


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


# --------------------------------------------------------------------------- the iteration
@njit(cache=True)
def iteration(state, spare, step, draws, model, frame, truth_pose, flags, out, w):
    """One filter iteration in one compiled call (module doc of filters.fastslam, "One filter
    iteration"), in place; ``step``: :class:`IterationInput`, ``draws``:
    :class:`IterationDraws`, ``frame``: :class:`GlobalFrame`, ``truth_pose`` (3,) (NaN: none),
    ``flags``: ``(pending, next_id, cull, lineage_correction, small_sample)``, ``out``:
    :class:`ScanOutputs` (K, P), ``w`` (P,) the normalised weights on return. In turn:

    1. if time passed (``dt > 0``): a proposal left pending by an iteration without a scan is
       drawn from (FS2) and the resampling test runs; then :func:`propagate`;
    2. a compass reading: :func:`heading_update` (and the resampling test if the pose was drawn);
    3. with a scan and global features: CM's innovation ratio ``||nu|| / (2 sigma)`` (CM III.B)
       of the scan against the prior, the local pose composed with the origin;
    4. the scan: :func:`update_iteration`;
    5. the local pose's moments (BB (7), :func:`local_pose`), the global pose ``v- (+) x_v^L``
       with covariance ``J_a P_v- J_a^T + J_b P_L J_b^T`` (BB Fig. 3) and its NEES and position
       error against the truth (:func:`filters.global_frame.pose_metrics`).

    Each resampling gathers into the other of ``state`` and ``spare``; the count of swaps says
    which holds the state at the end. Returns the fields of :class:`IterationResult`."""
    pending, next_id, cull, lineage_correction, small_sample = flags
    swaps = 0
    ess_ratio = np.nan
    if step.dt > 0.0:
        if pending:
            draw_poses(state, draws.pending_normals)
            resampled, ess_ratio = _resample_if_called_for(state, spare, w, draws.pending_offset,
                                                           model)
            if resampled:
                state, spare = spare, state
                swaps += 1
        propagate(state, step.v, step.omega, step.dt, step.Q)
        pending = True
    if not math.isnan(step.heading):
        heading_update(state, step.heading, step.heading_var, pending)
        if not pending:
            resampled, ess_ratio = _resample_if_called_for(state, spare, w, draws.heading_offset,
                                                           model)
            if resampled:
                state, spare = spare, state
                swaps += 1
    ratio = 0.0
    if step.scanned and step.z.shape[0] > 0 and frame.cols.shape[0] > 0:
        normalise_weights(state.logw, w, 0.0)
        prior_mean, prior_cov = local_pose(state, w, pending, lineage_correction, small_sample)
        pose, sigma, J_a = compose_with_covariance(frame.origin, frame.origin_cov, prior_mean,
                                                   prior_cov)
        _, ratios = nearest_global_innovations(step.z, pose, sigma, J_a, frame.x, frame.P,
                                               frame.cols, model.r_var, model.b_var,
                                               frame.radius_m)
        ratio = ratios.max()
    winners = np.zeros(0, dtype=np.int64)
    margins = np.zeros(0)
    n_new = 0
    if step.scanned:
        if not pending:
            state.prop_cov[:] = 0.0
        winners, margins, n_new, resampled, ess_ratio = update_iteration(
            state, step.z, step.known_cids,
            ScanDraws(draws.uniforms, draws.normals, draws.resample_offset), model, out, next_id,
            cull, w, spare)
        if resampled:
            state, spare = spare, state
            swaps += 1
        pending = False
    else:
        normalise_weights(state.logw, w, 0.0)
    local_mean, local_cov = local_pose(state, w, pending, lineage_correction, small_sample)
    mean, cov, J_a = compose_with_covariance(frame.origin, frame.origin_cov, local_mean,
                                             local_cov)
    nees, position_error = pose_metrics(truth_pose, mean, cov)
    return (swaps, ratio, winners, margins, n_new, ess_ratio, local_mean, local_cov, mean, cov,
            J_a, nees, position_error)


# --------------------------------------------------------------------------- called from Python
# numba types a plain tuple of arrays by a fast path and a named tuple by a slow one (~20 us a
# call for the state's 14 arrays against ~6 us, measured on this machine kind): the named tuples
# cross into compiled code as plain tuples and are named again inside.
@njit(cache=True)
def _propagate_entry(state, v, omega, dt, Q):
    propagate(ParticleState(*state), v, omega, dt, Q)


@njit(cache=True)
def _draw_poses_entry(state, normals):
    draw_poses(ParticleState(*state), normals)


@njit(cache=True)
def _heading_update_entry(state, theta, var, pending):
    heading_update(ParticleState(*state), theta, var, pending)


@njit(cache=True)
def _resample_entry(state, w, start, spare):
    systematic_resample(ParticleState(*state), w, start, ParticleState(*spare))


@njit(cache=True)
def _local_pose_entry(state, w, pending, lineage_correction, small_sample):
    return local_pose(ParticleState(*state), w, pending, lineage_correction, small_sample)


@njit(cache=True)
def _update_iteration_entry(state, z, known_cids, draws, model, out, next_id, cull, w, spare):
    return update_iteration(ParticleState(*state), z, known_cids, ScanDraws(*draws),
                            FilterModel(*model), ScanOutputs(*out), next_id, cull, w,
                            ParticleState(*spare))


def call_propagate(state: ParticleState, v, omega, dt, Q) -> None:
    """:func:`propagate` from Python."""
    _propagate_entry(tuple(state), v, omega, dt, Q)


def call_draw_poses(state: ParticleState, normals) -> None:
    """:func:`draw_poses` from Python."""
    _draw_poses_entry(tuple(state), normals)


def call_heading_update(state: ParticleState, theta, var, pending) -> None:
    """:func:`heading_update` from Python."""
    _heading_update_entry(tuple(state), theta, var, pending)


def call_systematic_resample(state: ParticleState, w, start, spare: ParticleState) -> None:
    """:func:`systematic_resample` from Python."""
    _resample_entry(tuple(state), w, start, tuple(spare))


def call_local_pose(state: ParticleState, w, pending, lineage_correction, small_sample):
    """:func:`local_pose` from Python."""
    return _local_pose_entry(tuple(state), w, pending, lineage_correction, small_sample)


def call_update_iteration(state: ParticleState, z, known_cids, draws: ScanDraws,
                          model: FilterModel, out: ScanOutputs, next_id, cull, w,
                          spare: ParticleState) -> ScanResult:
    """:func:`update_iteration` from Python."""
    return ScanResult(*_update_iteration_entry(tuple(state), z, known_cids, tuple(draws),
                                               tuple(model), tuple(out), next_id, cull, w,
                                               tuple(spare)))


@njit(cache=True)
def _iteration_entry(state, spare, step, draws, model, frame, truth_pose, flags, out, w):
    return iteration(ParticleState(*state), ParticleState(*spare), IterationInput(*step),
                     IterationDraws(*draws), FilterModel(*model), GlobalFrame(*frame),
                     truth_pose, flags, ScanOutputs(*out), w)


def call_iteration(state: ParticleState, spare: ParticleState, step: IterationInput,
                   draws: IterationDraws, model: FilterModel, frame: GlobalFrame, truth_pose,
                   flags, out: ScanOutputs, w) -> IterationResult:
    """:func:`iteration` from Python."""
    return IterationResult(*_iteration_entry(tuple(state), tuple(spare), tuple(step),
                                             tuple(draws), tuple(model), tuple(frame), truth_pose,
                                             flags, tuple(out), w))
