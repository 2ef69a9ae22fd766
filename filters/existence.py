"""Feature existence probabilities (BB (11)) with a false-alarm probability per validation gate.

Detection of a feature (BB (11), as in target detection, Stone et al.)::

    p <- p alpha / (p alpha + (1 - p) P_fa)

Complementary update for a feature predicted inside the field of view but not detected::

    p <- p (1 - alpha) / (p (1 - alpha) + (1 - p) (1 - P_fa))

What ``P_fa`` must be
---------------------
BB (11) writes ``beta`` in the denominator, but ``beta`` is the probability that a visible
*landmark* triggers a false alarm somewhere in the sensor's field; the quantity the update needs is
the probability that a false alarm explains *this* detection, i.e. lands inside *this* feature's
validation gate. With the clutter model of BB 5.1 each false alarm is uniform in range over
[0, r_max] and in bearing over the field of view, so its density in measurement space (range,
bearing) is constant, ``1 / (r_max * fov)``. The chi-square gate ``nu^T S^-1 nu <= gamma`` is an
ellipse in measurement space of area ``A = pi * gamma * sqrt(det S)``. A scan with ``n_visible``
visible landmarks carries on average ``lambda = beta * n_visible`` false alarms, a Poisson count in
the limit of many landmarks, so the expected number in the gate is
``lambda * A / (r_max * fov)`` and

    P_fa = 1 - exp(-beta * n_visible * A / (r_max * fov)).

For beta = 0 this gives P_fa = 0 and a single detection confirms a feature; for BB's level 3
(beta = 0.06, ~5 landmarks in view, a gate of a few cm by a few degrees) it is about 1e-4, far
below beta itself.

Two readings of BB (11) (``existence_model``, #14)
-------------------------------------------------
* ``"gate"`` (the default): ``P_fa`` as derived above, the chance that clutter lands in the gate;
  features confirm after 1-2 detections at every clutter level;
* ``"bb"``: BB's beta, as written in BB (11): ``P_fa = beta``. At level 3 (alpha 0.1, beta 0.06)
  a detection multiplies the odds by alpha / beta = 1.7 and a miss by (1 - alpha) / (1 - beta)
  = 0.96, so a feature needs tens of seconds of detections to pass 0.95.
Both models use the same update formulas; only ``P_fa`` differs.

A feature is *confirmed* when p > 0.95 (BB 5.1: only those are fused) and *culled* when p falls
below a cull threshold.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

CONFIRMED_PROBABILITY = 0.95
"""BB 5.1: only features with p(exists) above this are fused into the global map."""

EXISTENCE_MODELS = ("gate", "bb")
"""The two readings of BB (11) (module docstring): clutter in the gate, or BB's beta literally."""


def validate_existence_model(existence_model) -> str:
    if existence_model not in EXISTENCE_MODELS:
        raise ValueError(
            f"existence_model={existence_model!r} is invalid: must be one of {EXISTENCE_MODELS}"
        )
    return existence_model


def gate_area(S, gate_chi2):
    """Area (range x bearing units) of the gate ``nu^T S^-1 nu <= gate_chi2``; S (..., 2, 2)."""
    S = np.asarray(S, dtype=float)
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    return np.pi * gate_chi2 * np.sqrt(np.maximum(det, 0.0))


# Each formula is written once, for one element, compiled (``*_one``: the compiled FastSLAM scan,
# filters.fastslam_kernel, calls these); the array functions below apply it element by element
# over broadcast arrays.
@njit(cache=True)
def false_alarm_in_gate_probability_one(beta, n_visible, gate_area_rb, max_range_m, fov_rad):
    """Probability that at least one false alarm lands in a gate of the given area (see module)."""
    return -math.expm1(-beta * n_visible * gate_area_rb / (max_range_m * fov_rad))


@njit(cache=True)
def existence_false_alarm_one(
    literal_beta, beta, n_visible, gate_area_rb, max_range_m, fov_rad
):
    """``P_fa`` of BB (11): beta itself (``literal_beta``, the "bb" model) or the chance that a
    false alarm lands in the gate (the "gate" model)."""
    if literal_beta:
        return beta
    return false_alarm_in_gate_probability_one(beta, n_visible, gate_area_rb, max_range_m, fov_rad)


@njit(cache=True)
def detection_update_one(p, alpha, p_fa):
    """BB (11): existence after the feature was detected."""
    num = p * alpha
    den = num + (1.0 - p) * p_fa
    return num / den if den > 0.0 else 1.0


@njit(cache=True)
def miss_update_one(p, alpha, p_fa):
    """Existence after a feature predicted in view was not detected (complement of BB (11))."""
    num = p * (1.0 - alpha)
    den = num + (1.0 - p) * (1.0 - p_fa)
    return num / den if den > 0.0 else 0.0


def false_alarm_in_gate_probability(beta, n_visible, gate_area_rb, max_range_m, fov_rad):
    """:func:`false_alarm_in_gate_probability_one` over broadcast arrays."""
    return _elementwise(_false_alarm_loop, beta, n_visible, gate_area_rb, max_range_m, fov_rad)


def detection_update(p, alpha, p_fa):
    """:func:`detection_update_one` (BB (11)) over broadcast arrays."""
    return _elementwise(_detection_loop, p, alpha, p_fa)


def miss_update(p, alpha, p_fa):
    """:func:`miss_update_one` over broadcast arrays."""
    return _elementwise(_miss_loop, p, alpha, p_fa)


def _elementwise(loop, *args):
    arrays = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in args))
    out = np.empty(arrays[0].shape)
    loop(*(np.array(a).reshape(-1) for a in arrays), out.reshape(-1))  # copies: writable
    return out if out.ndim else out[()]


@njit(cache=True)
def _false_alarm_loop(beta, n_visible, area, max_range_m, fov_rad, out):
    for i in range(out.size):
        out[i] = false_alarm_in_gate_probability_one(
            beta[i], n_visible[i], area[i], max_range_m[i], fov_rad[i]
        )


@njit(cache=True)
def _detection_loop(p, alpha, p_fa, out):
    for i in range(out.size):
        out[i] = detection_update_one(p[i], alpha[i], p_fa[i])


@njit(cache=True)
def _miss_loop(p, alpha, p_fa, out):
    for i in range(out.size):
        out[i] = miss_update_one(p[i], alpha[i], p_fa[i])
