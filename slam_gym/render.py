"""Matplotlib drawing of worlds, paths, maps and covariance ellipses (headless: Agg backend).

Shared by ``slam-gym simulate``, the env's ``render()`` and the evaluation plots.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402


def covariance_ellipse(mean, cov, n_sigma: float = 2.0, **style) -> Ellipse:
    """An ellipse patch at ``mean`` covering ``n_sigma`` standard deviations of a 2x2 ``cov``."""
    cov = np.asarray(cov, dtype=float)
    values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
    values = np.maximum(values, 0.0)
    angle = np.degrees(np.arctan2(vectors[1, 1], vectors[0, 1]))
    width, height = 2.0 * n_sigma * np.sqrt(values[::-1])
    style.setdefault("fill", False)
    return Ellipse(xy=mean, width=width, height=height, angle=angle, **style)


def draw_map(
    ax,
    landmarks_true=None,
    true_path=None,
    est_path=None,
    est_landmarks=None,
    est_landmark_covs=None,
    pose_ellipses=(),
    particles=None,
    local_boundary=None,
    world_size_m=None,
):
    """Draw a run: truth in blue, estimates in red (BB Fig. 2 colours), ellipses at 2 sigma."""
    if landmarks_true is not None and len(landmarks_true):
        ax.plot(*np.asarray(landmarks_true).T, "b+", ms=8, mew=1.5, label="true landmarks")
    if true_path is not None and len(true_path):
        ax.plot(*np.asarray(true_path)[:, :2].T, "b-", lw=1.2, label="true path")
    if est_path is not None and len(est_path):
        ax.plot(*np.asarray(est_path)[:, :2].T, "r-.", lw=1.0, label="estimated path")
    for mean, cov in pose_ellipses:
        ax.add_patch(covariance_ellipse(mean[:2], np.asarray(cov)[:2, :2], ec="r", lw=0.8))
    if est_landmarks is not None and len(est_landmarks):
        ax.plot(*np.asarray(est_landmarks).T, "rx", ms=6, label="estimated landmarks")
        if est_landmark_covs is not None:
            for mean, cov in zip(est_landmarks, est_landmark_covs, strict=True):
                ax.add_patch(covariance_ellipse(mean, cov, ec="r", lw=0.6, alpha=0.8))
    if particles is not None and len(particles):
        ax.plot(*np.asarray(particles)[:, :2].T, ".", color="orange", ms=1.5, label="particles")
    if local_boundary is not None:
        centre, radius = local_boundary
        ax.add_patch(plt.Circle(centre, radius, fill=False, ls="--", ec="green", lw=0.8))
    if world_size_m is not None:
        ax.set_xlim(-5, world_size_m + 5)
        ax.set_ylim(-5, world_size_m + 5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)


def figure_to_rgb(fig) -> np.ndarray:
    """The figure's pixels as a uint8 (H, W, 3) array."""
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[..., :3])
