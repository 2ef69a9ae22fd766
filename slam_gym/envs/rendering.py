"""Drawing the env's state: truth, global map, local map, particles (headless by default)."""

from __future__ import annotations

import logging

import numpy as np

logger = logging.getLogger(__name__)

FRAME_SIZE_IN = (6.4, 6.4)
FRAME_DPI = 80


def _particles_of(system):
    """The front-end's particles in the global frame (None for an EKF front-end)."""
    poses = getattr(system.front_end, "poses", None)
    if poses is None:
        return None
    from filters.geometry import compose

    origin, _ = system.back_end.origin()
    return compose(np.asarray(origin)[None, :], np.asarray(poses))


def render_frame(env, figure, render_mode):
    """Draw the current state into ``figure`` (made on first use); returns (frame, figure)."""
    import matplotlib.pyplot as plt

    from slam_gym.render import draw_map, figure_to_rgb

    if figure is None:
        figure = plt.figure(figsize=FRAME_SIZE_IN, dpi=FRAME_DPI)
    figure.clf()
    ax = figure.add_subplot(111)
    ep = env.episode
    trace = ep.trace
    lm = ep.confirmed_landmarks()
    mean, cov = env.system.pose()
    draw_map(
        ax,
        landmarks_true=env.stream.landmarks_true,
        true_path=np.array(trace.true_poses) if trace and trace.true_poses else None,
        est_path=np.array(trace.est_poses) if trace and trace.est_poses else None,
        est_landmarks=lm.means,
        est_landmark_covs=lm.covs,
        pose_ellipses=[(mean, cov)],
        particles=_particles_of(env.system),
        local_boundary=(mean[:2], env.stream.sensor.max_range_m),
        world_size_m=getattr(env.stream.metadata.get("scenario"), "world_size_m", None),
    )
    ax.set_title(
        f"t = {ep.t_s:5.1f} s   fusions {ep.n_fusions}   optimisations {ep.n_optimisations}",
        fontsize=9,
    )
    ax.legend(loc="upper right", fontsize=6)
    figure.tight_layout()
    frame = figure_to_rgb(figure)
    return frame, figure


NON_INTERACTIVE_BACKENDS = ("agg", "cairo", "pdf", "pgf", "ps", "svg", "template")


def show_in_window(figure) -> bool:
    """Draw ``figure`` in its window (``render_mode="human"``); False if matplotlib's backend
    cannot show windows (a headless machine)."""
    import matplotlib
    import matplotlib.pyplot as plt

    if matplotlib.get_backend().lower() in NON_INTERACTIVE_BACKENDS:
        return False
    figure.show()
    plt.pause(0.001)
    return True
