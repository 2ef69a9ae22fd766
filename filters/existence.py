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

A feature is *confirmed* when p > 0.95 (BB 5.1: only those are fused) and *culled* when p falls
below a cull threshold.
"""

from __future__ import annotations

import math

import numpy as np
from numba import vectorize

CONFIRMED_PROBABILITY = 0.95
"""BB 5.1: only features with p(exists) above this are fused into the global map."""


def gate_area(S, gate_chi2):
    """Area (range x bearing units) of the gate ``nu^T S^-1 nu <= gate_chi2``; S (..., 2, 2)."""
    S = np.asarray(S, dtype=float)
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    return np.pi * gate_chi2 * np.sqrt(np.maximum(det, 0.0))


# The three updates below are numpy ufuncs (they broadcast over arrays) compiled by numba, so the
# compiled FastSLAM scan (filters.fastslam_kernel) calls the very same functions per element.
@vectorize(["float64(float64, float64, float64, float64, float64)"], cache=True)
def false_alarm_in_gate_probability(beta, n_visible, gate_area_rb, max_range_m, fov_rad):
    """Probability that at least one false alarm lands in a gate of the given area (see module)."""
    return -math.expm1(-beta * n_visible * gate_area_rb / (max_range_m * fov_rad))


@vectorize(["float64(float64, float64, float64)"], cache=True)
def detection_update(p, alpha, p_fa):
    """BB (11): existence after the feature was detected (p and p_fa broadcast)."""
    num = p * alpha
    den = num + (1.0 - p) * p_fa
    return num / den if den > 0.0 else 1.0


@vectorize(["float64(float64, float64, float64)"], cache=True)
def miss_update(p, alpha, p_fa):
    """Existence after a feature predicted in view was not detected (complement of BB (11))."""
    num = p * (1.0 - alpha)
    den = num + (1.0 - p) * (1.0 - p_fa)
    return num / den if den > 0.0 else 0.0
