"""Trajectory time series: fixed-grid resampling and SE(2) rigid alignment.

Two groups of helpers shared by the real-data loaders (:mod:`slam_gym.datasets.mrclam`,
:mod:`slam_gym.datasets.victoria_park`) and by the evaluation on real data:

* **Resampling on a time grid.** :func:`hold_integral` / :func:`hold_average` treat a logged
  signal as piecewise constant (zero-order hold: a row is in force from its time stamp until the
  next row), which is how velocity commands and wheel-encoder readings are logged.
  :func:`interpolate_poses` interpolates a pose track linearly in position and along the shorter
  arc in heading.
* **Rigid alignment.** :func:`fit_se2` is the least-squares rotation and translation (no scale)
  mapping one 2-D point set onto another (Kabsch/Umeyama without scale; in 2-D the optimal angle
  has a closed form). :func:`path_error_after_alignment` compares an estimated path with a
  reference that lives in another frame (Victoria Park's GPS is rotated and shifted; the data
  set's README): interpolate the estimate at the reference times, fit SE(2), report the RMSE.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from filters.geometry import wrap_angle
from filters.validation import require


# --------------------------------------------------------------------------- time series
def _as_times(name, t):
    t = np.asarray(t, dtype=float)
    require(t.ndim == 1 and t.size >= 1, name, t.shape, "a non-empty 1-D array of times")
    require(bool(np.all(np.isfinite(t))), name, "non-finite values", "finite times")
    return t


def hold_integral(row_t, row_values, t):
    """Integral from ``row_t[0]`` to ``t`` of a zero-order-hold signal.

    ``row_t`` (N,) non-decreasing row times, ``row_values`` (N, D): row ``i`` holds from
    ``row_t[i]`` until ``row_t[i + 1]`` (rows sharing a time stamp: the last one wins, the others
    hold for zero seconds); the last row holds forever. ``t`` (M,) must not precede ``row_t[0]``.
    Returns (M, D).
    """
    row_t = _as_times("row_t", row_t)
    values = np.asarray(row_values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    require(values.shape[0] == row_t.size, "row_values", values.shape, f"{row_t.size} rows")
    require(bool(np.all(np.diff(row_t) >= 0.0)), "row_t", "decreasing times", "non-decreasing")
    t = np.atleast_1d(np.asarray(t, dtype=float))
    early = t < row_t[0]
    if np.any(early):
        require(False, "t", float(t[early][0]), f"times >= {row_t[0]} (the first row)")
    durations = np.diff(row_t)
    cumulative = np.zeros((row_t.size, values.shape[1]))
    cumulative[1:] = np.cumsum(values[:-1] * durations[:, None], axis=0)
    k = np.searchsorted(row_t, t, side="right") - 1
    return cumulative[k] + values[k] * (t - row_t[k])[:, None]


def hold_average(row_t, row_values, grid_t):
    """Time-weighted mean of a zero-order-hold signal over each interval of ``grid_t``.

    ``grid_t`` (M + 1,) increasing boundaries; returns (M, D): the mean over
    ``[grid_t[k], grid_t[k + 1]]`` for each k (see :func:`hold_integral`).
    """
    grid_t = _as_times("grid_t", grid_t)
    require(grid_t.size >= 2, "grid_t", grid_t.size, "at least 2 boundaries")
    require(bool(np.all(np.diff(grid_t) > 0.0)), "grid_t", "non-increasing", "increasing times")
    integral = hold_integral(row_t, row_values, grid_t)
    return np.diff(integral, axis=0) / np.diff(grid_t)[:, None]


def interpolate_poses(row_t, poses, t):
    """Poses (M, 3) at times ``t`` from a pose track (N, 3) at increasing times ``row_t``.

    Position is interpolated linearly; heading along the shorter arc between the two bracketing
    rows (``theta_i + f * wrap(theta_{i+1} - theta_i)``), then wrapped to [-pi, pi). Times
    outside ``[row_t[0], row_t[-1]]`` give NaN.
    """
    row_t = _as_times("row_t", row_t)
    poses = np.asarray(poses, dtype=float)
    require(poses.shape == (row_t.size, 3), "poses", poses.shape, f"shape ({row_t.size}, 3)")
    require(bool(np.all(np.diff(row_t) > 0.0)), "row_t", "non-increasing", "increasing times")
    t = np.atleast_1d(np.asarray(t, dtype=float))
    out = np.full((t.size, 3), np.nan)
    inside = (t >= row_t[0]) & (t <= row_t[-1])
    if row_t.size == 1:
        out[inside] = poses[0]
        return out
    tt = t[inside]
    k = np.clip(np.searchsorted(row_t, tt, side="right") - 1, 0, row_t.size - 2)
    f = (tt - row_t[k]) / (row_t[k + 1] - row_t[k])
    a, b = poses[k], poses[k + 1]
    out[inside, 0] = a[:, 0] + f * (b[:, 0] - a[:, 0])
    out[inside, 1] = a[:, 1] + f * (b[:, 1] - a[:, 1])
    out[inside, 2] = wrap_angle(a[:, 2] + f * wrap_angle(b[:, 2] - a[:, 2]))
    return out


# --------------------------------------------------------------------------- SE(2) alignment
def _as_points(name, xy):
    xy = np.asarray(xy, dtype=float)
    require(xy.ndim == 2 and xy.shape[1] == 2, name, xy.shape, "an (N, 2) array of points")
    require(bool(np.all(np.isfinite(xy))), name, "non-finite values", "finite coordinates")
    return xy


def fit_se2(estimate_xy, reference_xy):
    """Least-squares rigid alignment: ``(R, t)`` minimising sum ||R e_i + t - r_i||^2.

    ``estimate_xy`` and ``reference_xy`` are (N, 2) corresponding points, N >= 2. With centred
    points e', r' the optimal angle is ``atan2(sum(e'_x r'_y - e'_y r'_x), sum(e' . r'))`` (the
    2-D case of Kabsch/Umeyama, always a proper rotation) and ``t = mean(r) - R mean(e)``.
    Returns R (2, 2) and t (2,).
    """
    e = _as_points("estimate_xy", estimate_xy)
    r = _as_points("reference_xy", reference_xy)
    require(r.shape == e.shape, "reference_xy", r.shape, f"the shape of estimate_xy {e.shape}")
    require(e.shape[0] >= 2, "estimate_xy", e.shape[0], "at least 2 points")
    e_mean, r_mean = e.mean(axis=0), r.mean(axis=0)
    ec, rc = e - e_mean, r - r_mean
    cross = np.sum(ec[:, 0] * rc[:, 1] - ec[:, 1] * rc[:, 0])
    dot = np.sum(ec[:, 0] * rc[:, 0] + ec[:, 1] * rc[:, 1])
    angle = np.arctan2(cross, dot)
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s], [s, c]])
    return R, r_mean - R @ e_mean


@dataclass(frozen=True)
class AlignedPathError:
    """Result of :func:`path_error_after_alignment`.

    ``t_s`` (M,) the reference times used (those inside the estimate's time span);
    ``aligned_xy`` (M, 2) the estimate interpolated at ``t_s`` and mapped into the reference
    frame; ``reference_xy`` (M, 2) the reference at ``t_s``; ``errors_m`` (M,) point distances;
    ``rmse_m`` their root mean square; ``rotation`` (2, 2) and ``translation`` (2,) the fit
    (reference ~= rotation @ estimate + translation); ``aligned_path_xy`` (N, 2) the whole
    estimated path mapped into the reference frame.
    """

    rmse_m: float
    rotation: np.ndarray
    translation: np.ndarray
    t_s: np.ndarray
    aligned_xy: np.ndarray
    reference_xy: np.ndarray
    errors_m: np.ndarray
    aligned_path_xy: np.ndarray


def path_error_after_alignment(est_t, est_xy, ref_t, ref_xy):
    """RMSE between an estimated path and a reference path after the best SE(2) alignment.

    The estimate (``est_t`` (N,) increasing, ``est_xy`` (N, 2)) is interpolated linearly at the
    reference times ``ref_t`` (M,) that fall inside its time span; :func:`fit_se2` maps it onto
    ``ref_xy`` (M, 2); the RMSE of the residual distances is returned with the aligned path in an
    :class:`AlignedPathError`. Reference outliers (e.g. GPS jumps) are not rejected: filter them
    before calling if needed.
    """
    est_t = _as_times("est_t", est_t)
    est_xy = _as_points("est_xy", est_xy)
    require(est_xy.shape[0] == est_t.size, "est_xy", est_xy.shape, f"{est_t.size} rows")
    require(bool(np.all(np.diff(est_t) > 0.0)), "est_t", "non-increasing", "increasing times")
    ref_t = _as_times("ref_t", ref_t)
    ref_xy = _as_points("ref_xy", ref_xy)
    require(ref_xy.shape[0] == ref_t.size, "ref_xy", ref_xy.shape, f"{ref_t.size} rows")
    inside = (ref_t >= est_t[0]) & (ref_t <= est_t[-1])
    require(
        int(inside.sum()) >= 2,
        "ref_t",
        f"{int(inside.sum())} times inside the estimate's span",
        "at least 2 reference times inside [est_t[0], est_t[-1]]",
    )
    t = ref_t[inside]
    reference = ref_xy[inside]
    estimate = np.column_stack(
        [np.interp(t, est_t, est_xy[:, 0]), np.interp(t, est_t, est_xy[:, 1])]
    )
    R, translation = fit_se2(estimate, reference)
    aligned = estimate @ R.T + translation
    errors = np.hypot(*(aligned - reference).T)
    return AlignedPathError(
        rmse_m=float(np.sqrt(np.mean(errors**2))),
        rotation=R,
        translation=translation,
        t_s=t,
        aligned_xy=aligned,
        reference_xy=reference,
        errors_m=errors,
        aligned_path_xy=est_xy @ R.T + translation,
    )
