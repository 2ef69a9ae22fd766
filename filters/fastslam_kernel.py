"""Compiled work of one FastSLAM 2.0 iteration (numba).

:class:`filters.fastslam.FastSLAM2` keeps its state in (P, C) arrays. What is sequential within
one particle (the observations of a scan refine the particle's proposal one
after the other) runs here, in one compiled pass over the particles: visibility and the
missed-detection terms, Data Association Sampling, the FS2 proposal refinement, the pose draw,
and the existence and map updates at the drawn pose. The equations are those of the
:mod:`filters.fastslam` module docstring, which this module follows line by line. Since issue 40
the bookkeeping after the scan that concerns all particles at once is compiled too
(:func:`finish_scan`, :func:`normalise_weights`, :func:`systematic_resample`: below, with why
each stops where it does).

Why compiled: with numpy vectorised over the particles every observation costs some hundred
array operations of a few microseconds each whatever the particle count, which capped the
default training env at 60-65 decisions per second and HYBRID at 500 particles at 38x real
time (docs/PERFORMANCE.md, issues #4 and #6). The random numbers are drawn by the caller with
its own ``numpy.random.Generator`` and passed in, so the stream and the seeding are unchanged.

The scalar measurement functions below are the ones of :mod:`filters.models` (``h``, its
Jacobian w.r.t. the feature, the inverse observation ``g`` and its Jacobian w.r.t. ``z``)
written out per element; ``tests/filters/test_fastslam_kernel.py`` checks them against the
vectorised reference.
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
    vote_one_observation,
)
from filters.existence import (
    detection_update_one,
    existence_false_alarm_one,
    miss_update_one,
)
from filters.geometry import wrap_angle_one as _wrap

_TWO_PI = 2.0 * math.pi
_SQRT_HALF = math.sqrt(0.5)


class ScanModel(NamedTuple):
    """The constants of one scan update (sensor, clutter and filter options), in the order of
    the last parameters of :func:`scan_update` (passed unpacked: numba types scalars faster than
    a named tuple)."""

    r_var: float
    b_var: float
    detection_probability: float
    beta: float
    gate_chi2: float
    max_range_m: float
    fov_rad: float
    range_std_m: float
    bearing_std_rad: float
    new_landmark_density: float
    max_existence: float
    literal_beta: bool
    sample_clutter: bool


@njit(cache=True, inline="always")
def _innovation(zr, zb, x, y, th, mx, my):
    """Innovation ``z - h(pose, m)`` (bearing wrapped) and ``H_m``, the Jacobian of ``h`` w.r.t.
    the feature (:func:`filters.models.observe_jacobians`; ``H_pose = [-H_m | (0, -1)^T]``)."""
    dx = mx - x
    dy = my - y
    q = max(dx * dx + dy * dy, 1e-12)
    r = math.sqrt(q)
    return zr - r, _wrap(zb - math.atan2(dy, dx) + th), dx / r, dy / r, -dy / q, dx / q


@njit(cache=True, inline="always")
def _observation_terms(zr, zb, x, y, th, Pc, mx, my, sxx, sxy, syy, r_var, b_var):
    """Innovation, ``S = G P G^T + H_m Sigma H_m^T + R`` and ``H_m`` of one feature for one
    particle with proposal ``(x, y, th)``, ``Pc`` (3, 3) (module doc of filters.fastslam)."""
    nu_r, nu_b, h00, h01, h10, h11 = _innovation(zr, zb, x, y, th, mx, my)
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
def _refine(pose, Pc, nu_r, nu_b, S00, S01, S11, det, h00, h01, h10, h11, scratch):
    """FS2 proposal in Kalman form: ``x += P G^T S^-1 nu``, ``P -= P G^T S^-1 G P`` with
    ``G = [-H_m | (0, -1)^T]`` (in place; well defined for a singular P). ``scratch`` (4, 3):
    work space the caller allocates once (no allocation per observation)."""
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


@njit(cache=True)
def draw_poses(poses, prop_cov, normals):
    """Draw every particle's pose from its proposal ``N(x, P)`` (in place; FS2)."""
    step = np.empty(3)
    for p in range(poses.shape[0]):
        _ldl_draw(prop_cov[p], normals[p], step)
        poses[p, 0] += step[0]
        poses[p, 1] += step[1]
        poses[p, 2] = _wrap(poses[p, 2] + step[2])


@njit(cache=True)
def propagate(poses, prop_cov, v, omega, dt, Q):
    """Motion prediction of every particle, in place: the pose through the unicycle mid-point
    model (:func:`filters.models.motion`) and the FS2 proposal prior ``J_u Q J_u^T`` in
    ``prop_cov`` (``J_u`` of :func:`filters.models.motion_jacobians`)."""
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


@njit(cache=True, inline="always")
def _feature_ekf(x, y, th, mx, my, sxx, sxy, syy, zr, zb, r_var, b_var):
    """EKF update of one feature from a known pose: ``K = Sigma H^T S^-1``, ``m += K nu``,
    ``Sigma -= K H Sigma`` (the FS2 map update at the sampled pose)."""
    nu_r, nu_b, h00, h01, h10, h11 = _innovation(zr, zb, x, y, th, mx, my)
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


@njit(cache=True)
def _visibility(x, y, th, Pc, mx, my, sxx, sxy, syy, max_range_m, fov_rad):
    """Probability that a feature lies inside the sensor's range: ``Phi((r_max - r) / sigma_r)``
    with ``sigma_r^2`` the radial variance of feature and proposal position; a limited field of
    view is a hard bearing test on the mean (module doc of filters.fastslam)."""
    dx = mx - x
    dy = my - y
    q = max(dx * dx + dy * dy, 1e-12)
    r = math.sqrt(q)
    if fov_rad < _TWO_PI and abs(_wrap(math.atan2(dy, dx) - th)) > 0.5 * fov_rad:
        return 0.0
    radial = (
        dx * dx * (sxx + Pc[0, 0]) + 2.0 * dx * dy * (sxy + Pc[0, 1]) + dy * dy * (syy + Pc[1, 1])
    ) / q
    sigma = math.sqrt(max(radial, 0.0)) + 1e-9
    margin = (max_range_m - r) / sigma
    if margin > 8.5:  # Phi(8.5) = 1 - 1e-17: 1 in double precision
        return 1.0
    if margin < -40.0:  # Phi underflows
        return 0.0
    return 0.5 * math.erfc(-margin * _SQRT_HALF)


@njit(cache=True)
def scan_update(
    poses,
    prop_cov,
    logw,
    mx,
    my,
    sxx,
    sxy,
    syy,
    ex,
    active,
    cid,
    count,
    z,
    uniforms,
    normals,
    known_cids,
    votes,
    slots,
    logw_after,
    clutter_prob,
    r_var,
    b_var,
    detection_probability,
    beta,
    gate_chi2,
    max_range_m,
    fov_rad,
    range_std_m,
    bearing_std_rad,
    new_landmark_density,
    max_existence,
    literal_beta,
    sample_clutter,
):
    """One scan for every particle (module doc of filters.fastslam), in place.

    State (P, ...) arrays are updated in place; ``count`` (P,) grows by the features created
    (the caller guarantees ``C >= count + K``). ``uniforms`` (K, P) drive DAS, ``normals``
    (P, 3) the pose draw. ``known_cids`` (K,) is None for DAS, else the common id each
    observation belongs to (-1: a known false alarm). Outputs (K, P): ``votes`` (a common id,
    CLUTTER or NEW; a feature without id votes NEW), ``slots`` (the slot updated or created,
    -1 for clutter), ``logw_after`` (the log weight after each observation, for voting) and
    ``clutter_prob`` (the probability, under the particle's hypothesis, that the observation is a
    false alarm: 1 for clutter, ``1 - e_new`` for a new feature, 0 for an existing one). The
    remaining parameters are the fields of :class:`ScanModel`.
    """
    P = poses.shape[0]
    K = z.shape[0]
    n_hi = 0
    for p in range(P):
        n_hi = max(n_hi, count[p])
    alpha = detection_probability
    field = max_range_m * fov_rad
    gate_scale = math.sqrt(gate_chi2)
    area_r = math.pi * gate_chi2 * math.sqrt(r_var * b_var)
    p_vis = np.empty(n_hi)
    ratio = np.empty(n_hi)
    claimed = np.empty(n_hi, dtype=np.bool_)
    hyp_slot = np.empty(n_hi + 2, dtype=np.int64)
    hyp_value = np.empty(n_hi + 2)
    hyp_terms = np.empty((n_hi + 2, 11))  # _observation_terms of each gated feature
    feature_std = np.empty(n_hi)  # sqrt(trace) of each feature's covariance, for the pre-gate
    gate_areas = np.empty(K)
    new_existence = np.empty(K)
    step = np.empty(3)
    scratch = np.empty((4, 3))
    for p in range(P):
        pose = poses[p]
        Pc = prop_cov[p]
        n = count[p]
        # --- visibility and the missed-detection product prod_j (1 - alpha e_j p_vis,j)
        expected_visible = 0.0
        for j in range(n):
            claimed[j] = False
            if not active[p, j]:
                p_vis[j] = 0.0
                ratio[j] = 0.0
                continue
            feature_std[j] = math.sqrt(sxx[p, j] + syy[p, j])
            p_vis[j] = _visibility(
                pose[0], pose[1], pose[2], Pc, mx[p, j], my[p, j],
                sxx[p, j], sxy[p, j], syy[p, j], max_range_m, fov_rad,
            )
            seen = alpha * ex[p, j] * p_vis[j]
            logw[p] += math.log(1.0 - seen)
            ratio[j] = seen / (1.0 - seen)
            expected_visible += ex[p, j] * p_vis[j]
        n_vis = max(expected_visible, K / (alpha + beta))
        clutter_density = beta * n_vis / field

        # --- observations in turn: association, weight, proposal refinement
        for k in range(K):
            zr, zb = z[k, 0], z[k, 1]
            l_new = alpha * new_landmark_density * max(zr, range_std_m)
            new_existence[k] = min(l_new / (l_new + clutter_density), max_existence)
            chosen = -1
            clutter_prob[k, p] = 0.0
            if known_cids is not None:
                target = known_cids[k]
                votes[k, p] = target
                if target < 0:
                    slots[k, p] = CLUTTER
                    clutter_prob[k, p] = 1.0
                    logw_after[k, p] = logw[p]
                    continue
                for j in range(n):
                    if active[p, j] and not claimed[j] and cid[p, j] == target:
                        chosen = j
                        break
                if chosen >= 0:
                    t = _observation_terms(
                        zr, zb, pose[0], pose[1], pose[2], Pc, mx[p, chosen], my[p, chosen],
                        sxx[p, chosen], sxy[p, chosen], syy[p, chosen], r_var, b_var,
                    )
                    lik = math.exp(-0.5 * t[6]) / (_TWO_PI * math.sqrt(t[5]))
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
                    t = _observation_terms(
                        zr, zb, pose[0], pose[1], pose[2], Pc, mx[p, j], my[p, j],
                        sxx[p, j], sxy[p, j], syy[p, j], r_var, b_var,
                    )
                    if t[6] < gate_chi2:
                        like = ratio[j] * math.exp(-0.5 * t[6]) / (_TWO_PI * math.sqrt(abs(t[5])))
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
                logw[p] += math.log(max(total, 1e-300))
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
                _refine(pose, Pc, t[0], t[1], t[2], t[3], t[4], t[5], t[7], t[8], t[9], t[10],
                        scratch)
                claimed[chosen] = True
                gate_areas[k] = math.pi * gate_chi2 * math.sqrt(abs(t[5]))
                slots[k, p] = chosen
            logw_after[k, p] = logw[p]

        # --- draw the pose from the refined proposal, then existence and map at that pose
        _ldl_draw(Pc, normals[p], step)
        pose[0] += step[0]
        pose[1] += step[1]
        pose[2] = _wrap(pose[2] + step[2])
        Pc[:, :] = 0.0
        p_fa_miss = existence_false_alarm_one(
            literal_beta, beta, n_vis, area_r, max_range_m, fov_rad
        )
        for j in range(n):
            if not claimed[j] and p_vis[j] > 0.0:
                ex[p, j] = miss_update_one(ex[p, j], alpha * p_vis[j], p_fa_miss)
        for k in range(K):
            j = slots[k, p]
            zr, zb = z[k, 0], z[k, 1]
            if j >= 0:
                mx[p, j], my[p, j], sxx[p, j], sxy[p, j], syy[p, j] = _feature_ekf(
                    pose[0], pose[1], pose[2], mx[p, j], my[p, j],
                    sxx[p, j], sxy[p, j], syy[p, j], zr, zb, r_var, b_var,
                )
                p_fa = existence_false_alarm_one(
                    literal_beta, beta, n_vis, gate_areas[k], max_range_m, fov_rad
                )
                ex[p, j] = min(detection_update_one(ex[p, j], alpha, p_fa), max_existence)
            elif j == NEW:
                j = count[p]
                count[p] += 1
                c = math.cos(pose[2] + zb)
                s = math.sin(pose[2] + zb)
                mx[p, j] = pose[0] + zr * c
                my[p, j] = pose[1] + zr * s
                # G_z diag(R) G_z^T with G_z = [[c, -r s], [s, r c]]
                rs2 = zr * zr * b_var
                sxx[p, j] = c * c * r_var + s * s * rs2
                sxy[p, j] = c * s * (r_var - rs2)
                syy[p, j] = s * s * r_var + c * c * rs2
                ex[p, j] = new_existence[k]
                active[p, j] = True
                cid[p, j] = -1
                slots[k, p] = j


@njit(cache=True)
def _permute_row(a, p, order, buffer):
    """``a[p] = a[p, order]`` through ``buffer``."""
    C = a.shape[1]
    for c in range(C):
        buffer[c] = a[p, order[c]]
    for c in range(C):
        a[p, c] = buffer[c]


@njit(cache=True)
def compact_features(active, mx, my, sxx, sxy, syy, ex, cid):
    """Move each particle's active features to its first slots, in place: active slots first,
    then the inactive ones, each in slot order (the permutation
    ``np.argsort(~active, axis=1, kind="stable")`` gives). Data movement only; a particle whose
    active slots already come first (the permutation is the identity) is left as it is."""
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
        _permute_row(mx, p, order, floats)
        _permute_row(my, p, order, floats)
        _permute_row(sxx, p, order, floats)
        _permute_row(sxy, p, order, floats)
        _permute_row(syy, p, order, floats)
        _permute_row(ex, p, order, floats)
        _permute_row(cid, p, order, ints)
        _permute_row(active, p, order, flags)


# --------------------------------------------------------------------------- after the scan
# What FastSLAM2.update did in numpy after scan_update (votes, ids, clutter rate, culling, the
# weights' shift and normalisation, the resampling decision and the resampling), compiled
# (issue 40 item 3). Every value is formed by the same operations in the same order as the numpy
# code it replaces, so the results are equal to the bit; where numpy's order is not the plain one
# (``np.sum``'s pairwise summation, ``np.searchsorted``'s binary search) it is written out
# (:func:`numpy_sum`, :func:`_searchsorted_right`). Three things stay in Python, measured
# (docs/PERFORMANCE.md): the weights' ``np.exp``, whose SIMD implementation rounds differently
# from the C library's ``exp`` that compiled code calls (in about 5 % of arguments on this
# machine kind); the resampling's uniform, since handing the ``Generator`` to a compiled function
# costs ~7 us a call whether or not it draws; and the allocation of the resampled arrays (numpy's
# allocator: arrays allocated here and returned made the gather twice as slow).


@njit(cache=True)
def _block_sum(a, start, n):
    """numpy's sum of one block of at most 128 elements: plain below 8, else eight
    accumulators combined pairwise, then the remainder."""
    if n < 8:
        res = 0.0
        for i in range(start, start + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = 8
    stop = n - n % 8
    while i < stop:
        b = start + i
        r0 += a[b]
        r1 += a[b + 1]
        r2 += a[b + 2]
        r3 += a[b + 3]
        r4 += a[b + 4]
        r5 += a[b + 5]
        r6 += a[b + 6]
        r7 += a[b + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[start + i]
        i += 1
    return res


@njit(cache=True)
def _pairwise_sum(a, start, n):
    """numpy's pairwise summation of ``a[start:start + n]`` (``pairwise_sum`` of its ``add``
    reduction for a contiguous float64 array): blocks of at most 128 (:func:`_block_sum`), a
    longer range split in two halves (the first a multiple of 8) and their sums added, so the
    sum is numpy's to the bit. numpy recurses; this walks the same tree with a stack (numba's
    cache does not reload a recursive function safely)."""
    if n <= 128:
        return _block_sum(a, start, n)
    starts = np.empty(64, dtype=np.int64)  # the tree's depth is log2(n / 128) < 64
    sizes = np.empty(64, dtype=np.int64)
    stage = np.zeros(64, dtype=np.int64)  # 0: left half next, 1: right half next, 2: add
    values = np.empty(64)
    starts[0], sizes[0] = start, n
    top, n_values = 0, 0
    while top >= 0:
        m = sizes[top]
        if m <= 128:
            values[n_values] = _block_sum(a, starts[top], m)
            n_values += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stage[top] == 2:
            values[n_values - 2] = values[n_values - 2] + values[n_values - 1]
            n_values -= 1
            top -= 1
            continue
        first = stage[top] == 0
        stage[top] += 1
        top += 1
        starts[top] = starts[top - 1] if first else starts[top - 1] + half
        sizes[top] = half if first else m - half
        stage[top] = 0
    return values[0]


@njit(cache=True)
def numpy_sum(a):
    """``np.sum(a)`` of a contiguous float64 vector, to the bit (:func:`_pairwise_sum`; numpy
    starts its ``add`` reduction from the identity 0.0, which changes no sum)."""
    return 0.0 + _pairwise_sum(a, 0, a.shape[0])


@njit(cache=True)
def clutter_shares(log_weights, clutter_prob):
    """Per observation, the weighted probability that it is a false alarm (the loop of
    :func:`filters.fastslam.clutter_share`)."""
    K, P = log_weights.shape
    out = np.empty(K)
    for k in range(K):
        top = log_weights[k].max()
        weighted, total = 0.0, 0.0
        for p in range(P):
            w = np.exp(log_weights[k, p] - top)
            weighted += w * clutter_prob[k, p]
            total += w
        out[k] = weighted / total
    return out


@njit(cache=True)
def _votes_and_clutter_shares(log_weights, votes, clutter_prob):
    """:func:`filters.conversion.vote_all`'s winners and margins (the same
    :func:`~filters.conversion.vote_one_observation` per observation) and
    :func:`clutter_shares` from one pass: each observation's weights ``exp(logw - max)`` are
    formed once for both (the same values each formed on its own, so the same results)."""
    K, P = votes.shape
    winners = np.empty(K, dtype=np.int64)
    margins = np.empty(K)
    shares = np.empty(K)
    options = np.empty(P, dtype=np.int64)
    option_shares = np.empty(P)
    weights = np.empty(P)
    for k in range(K):
        winners[k], margins[k], _ = vote_one_observation(log_weights[k], votes[k], weights,
                                                         options, option_shares)
        weighted, total = 0.0, 0.0
        for p in range(P):
            weighted += weights[p] * clutter_prob[k, p]
            total += weights[p]
        shares[k] = weighted / total
    return winners, margins, shares


@njit(cache=True)
def cull_features(active, mx, my, sxx, sxy, syy, ex, cid, count, threshold):
    """Remove the features whose existence is below ``threshold`` and re-pack each particle's
    slots (:meth:`filters.fastslam.FastSLAM2._cull`), in place; ``count`` (P,) is rewritten.
    Returns whether any feature was removed (else nothing changes)."""
    P, C = active.shape
    any_dead = False
    for p in range(P):
        for c in range(C):
            if active[p, c] and ex[p, c] < threshold:
                any_dead = True
                active[p, c] = False
    if not any_dead:
        return False
    compact_features(active, mx, my, sxx, sxy, syy, ex, cid)
    for p in range(P):
        n = 0
        for c in range(C):
            if active[p, c]:
                n += 1
            else:
                ex[p, c] = 0.0
                cid[p, c] = -1
        count[p] = n
    return True


@njit(cache=True)
def finish_scan(logw, logw_after, votes, slots, clutter_prob, known_cids, next_id, cid, active,
                count, mx, my, sxx, sxy, syy, ex, clutter_num, clutter_den, clutter_decay, cull,
                cull_threshold):
    """The bookkeeping of one scan after :func:`scan_update`, in place (module doc of
    :mod:`filters.fastslam`, "Correspondences"): the vote of each observation (BB 3.1) with the
    weights after it (fresh ids ``next_id, next_id + 1, ...`` for the observations *new feature*
    wins, in observation order), the clutter rate's running sums, the winners' ids written into
    ``cid``, culling when ``cull`` (every ``cull_interval_steps``), and the log weights shifted
    to a maximum of 0. With ``known_cids`` (K,) the winners are those ids, no vote is taken and
    the clutter rate is left alone. Returns ``(winners, margins, n_new_ids, clutter_num,
    clutter_den)``."""
    K = votes.shape[0]
    if known_cids is None:
        winners, margins, shares = _votes_and_clutter_shares(logw_after, votes, clutter_prob)
        n_new = 0
        for k in range(K):
            if winners[k] == NEW:
                winners[k] = next_id + n_new
                n_new += 1
        for k in range(K):
            clutter_num = clutter_decay * clutter_num + shares[k]
            clutter_den = clutter_decay * clutter_den + 1.0
    else:
        winners = known_cids.copy()
        margins = np.ones(K)
        n_new = 0
    assign_correspondence_ids_unchecked(cid, active, slots, winners)
    if cull:
        cull_features(active, mx, my, sxx, sxy, syy, ex, cid, count, cull_threshold)
    top = logw.max()
    for p in range(logw.shape[0]):
        logw[p] -= top
    return winners, margins, n_new, clutter_num, clutter_den


@njit(cache=True)
def _gather_rows(a, idx, out):
    """``out[:] = np.take(a, idx, axis=0)`` for (P, C) arrays."""
    for p in range(idx.shape[0]):
        q = idx[p]
        for c in range(a.shape[1]):
            out[p, c] = a[q, c]


@njit(cache=True, inline="always")
def _less(a, b):
    """numpy's sort order of floats (NaN last)."""
    return a < b or (b != b and a == a)


@njit(cache=True)
def _searchsorted_right(a, keys):
    """``np.searchsorted(a, keys, side="right")``: numpy's binary search, step for step (each
    search narrowed by the previous key's result, as numpy does), so even an ``a`` that is not
    sorted (a cdf whose last entry is set to 1 below a rounded sum) gives numpy's indices."""
    n = a.shape[0]
    out = np.empty(keys.shape[0], dtype=np.int64)
    lo, hi = 0, n
    last = keys[0] if keys.shape[0] else 0.0
    for i in range(keys.shape[0]):
        key = keys[i]
        if not _less(key, last):  # last <= key in numpy's order
            hi = n
        else:
            lo = 0
            hi = hi + 1 if hi < n else n
        last = key
        while lo < hi:
            mid = lo + ((hi - lo) >> 1)
            if not _less(key, a[mid]):
                lo = mid + 1
            else:
                hi = mid
        out[i] = lo
    return out


@njit(cache=True)
def normalise_weights(exp_w, threshold):
    """The weights and the resampling decision of
    :meth:`filters.fastslam.FastSLAM2._maybe_resample`, as numpy computed them, to the bit:
    ``exp_w`` (P,), ``np.exp(logw - logw.max())`` (numpy's exp: module note above), normalised
    in place; returns ``(resample, ess_ratio)``: whether ``N_eff < threshold * P``, and
    ``N_eff / P``."""
    P = exp_w.shape[0]
    total = numpy_sum(exp_w)
    squares = np.empty(P)
    for p in range(P):
        exp_w[p] = exp_w[p] / total
        squares[p] = exp_w[p] * exp_w[p]
    n_eff = 1.0 / numpy_sum(squares)
    return not n_eff >= threshold * P, n_eff / P


@njit(cache=True)
def systematic_resample(w, start, logw, state, spare):
    """Systematic resampling with the uniform ``start`` (drawn by the caller), as
    :meth:`filters.fastslam.FastSLAM2._maybe_resample` did it in numpy, to the bit: the
    particles ``np.searchsorted(cumsum(w), (start + arange(P)) / P, side="right")`` (the cdf's
    last entry set to 1, the index capped at P - 1) of ``state`` ``(poses, prop_cov, mx, my,
    sxx, sxy, syy, ex, active, cid, count, lineage)`` gathered into ``spare`` (arrays of the same
    shapes that the caller allocates and then takes as its state: arrays allocated here cost
    twice the copy), ``logw`` zeroed and ``w`` made the uniform weights, in place."""
    poses, prop_cov, mx, my, sxx, sxy, syy, ex, active, cid, count, lineage = state
    (s_poses, s_prop_cov, s_mx, s_my, s_sxx, s_sxy, s_syy, s_ex, s_active, s_cid, s_count,
     s_lineage) = spare
    P = w.shape[0]
    cdf = np.empty(P)
    cdf[0] = w[0]
    for p in range(1, P):  # np.cumsum's order
        cdf[p] = cdf[p - 1] + w[p]
    cdf[P - 1] = 1.0
    positions = np.empty(P)
    for p in range(P):
        positions[p] = (start + p) / P
    idx = _searchsorted_right(cdf, positions)
    for p in range(P):
        idx[p] = min(idx[p], P - 1)
    _gather_rows(poses, idx, s_poses)
    for p in range(P):
        q = idx[p]
        for i in range(3):
            for k in range(3):
                s_prop_cov[p, i, k] = prop_cov[q, i, k]
        s_count[p] = count[q]
        s_lineage[p] = lineage[q]
    _gather_rows(mx, idx, s_mx)
    _gather_rows(my, idx, s_my)
    _gather_rows(sxx, idx, s_sxx)
    _gather_rows(sxy, idx, s_sxy)
    _gather_rows(syy, idx, s_syy)
    _gather_rows(ex, idx, s_ex)
    _gather_rows(active, idx, s_active)
    _gather_rows(cid, idx, s_cid)
    for p in range(P):  # the weights of logw = 0: exp(0) = 1, normalised
        logw[p] = 0.0
        w[p] = 1.0
    total = numpy_sum(w)
    for p in range(P):
        w[p] = w[p] / total
