"""Sub-map fusion (BB section 4) and the sub-mapping system :class:`SubmapSLAM`.

The system keeps a Gaussian **global map** (a back-end of :mod:`filters.back_ends`: the global
vehicle pose ``v`` and
the global features, jointly Gaussian) and a **local map** built by a front-end (EKF-SLAM or
FastSLAM) in its own frame. The global vehicle pose stored in the global map is the pose at the
previous fusion, ``v-``: the origin of the current local map. Local and global maps are
independent, so between fusions (BB Fig. 3 caption) the current global pose is

    pose = v- (+) x_v^L,   cov = J_a P_v- J_a^T + J_b P_v^L J_b^T

with ``J_a``, ``J_b`` the Jacobians of the composition (:func:`filters.geometry.compose_jacobians`).

Fusion and the back-ends (the EKF :class:`filters.back_ends.GlobalMap` and CM's relative
:class:`filters.back_ends.RelativeBackEnd`) are in :mod:`filters.back_ends`.

The system (:class:`SubmapSLAM`) routes ``predict``/``update``/``update_heading`` to the
front-end, offers ``fuse()`` (any iteration, also with an empty local map), keeps every fused
sub-map in ``self.submaps`` for the optimiser, and computes the interface features of
docs/ARCHITECTURE.md. Compass: a global heading ``theta`` is given to the front-end as the local
heading ``theta - theta(v-)`` with the compass noise; this ignores the uncertainty of the origin's
heading (it is common to every compass reading of one local map, so it cannot be treated as white
noise), which makes the composed heading covariance conservative by up to ``P_v-,theta theta``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from filters.association import DEFAULT_NODE_BUDGET, validate_gate_probability, validate_node_budget
from filters.back_ends import (
    DEFAULT_CLOSURE_RADIUS_M,
    DEFAULT_LOOP_CLOSURE_UNSEEN_S,
    GlobalMap,
    RelativeBackEnd,
    SubmapLoopClosure,
    combine_existence,
    make_back_end,
    transform_points_jacobians,
)
from filters.blas import DEFAULT_BLAS_THREADS, check_blas_threads
from filters.existence import CONFIRMED_PROBABILITY
from filters.fastslam import own_frame, read_only
from filters.fastslam_kernel import GlobalFrame
from filters.geometry import transform_point, wrap_angle
from filters.global_frame import (
    compose_with_covariance,
    nearest_global_innovations,
    stepwise_iteration,
)
from filters.interface_features import INTERFACE_FEATURE_NAMES
from filters.models import observe
from filters.optimiser import ROBUST_KERNELS
from filters.submap_optimise import optimisation_is_redundant, optimise_submaps
from filters.types import FusionReport, GaussianMap, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

__all__ = [
    "GlobalMap",
    "RelativeBackEnd",
    "StoredSubmap",
    "SubmapLoopClosure",
    "SubmapSLAM",
    "combine_existence",
    "transform_points_jacobians",
]


# --------------------------------------------------------------------------- the system
@dataclass
class StoredSubmap:
    """A fused local map, kept for the optimiser (CM III.C).

    ``gaussian``: the local map as fused (local frame, local ids); ``id_map``: local id -> global
    id; ``origin_index``: which pose of the chain of fusion poses is its origin (0 = the initial
    pose, ``s`` = the pose at the ``s``-th fusion); ``end_index = origin_index + 1``: the pose it
    ends at (its vehicle pose); ``time_s``: when it was fused.
    """

    gaussian: GaussianMap
    id_map: dict[int, int]
    origin_index: int
    end_index: int
    time_s: float
    cache: dict = field(default_factory=dict, repr=False, compare=False)
    """What the optimiser derives from the sub-map (its information ``P^-1``, the global ids of
    its features), computed once: a stored sub-map never changes."""


class SubmapSLAM:
    """Sub-mapping SLAM (BB section 4): a local-map front-end fused into a global back-end.

    ``front_end``: a filter with ``to_gaussian()``, ``restart()``, ``local_statistics()`` and a
    ``sensor`` attribute (e.g. :class:`filters.ekf_slam.EKFSLAM`); it is restarted here so the
    first local map starts at the origin. ``back_end``: a back-end object of
    :mod:`filters.back_ends` or its name, ``"ekf"`` or ``"relative"`` (a new one from
    ``initial_pose``, ``initial_pose_cov``, ``gate_probability``, ``node_budget``, and for
    ``"ekf"`` the loop-closure test's ``loop_closure_unseen_s`` and ``closure_radius_m``).
    ``closure_radius_m`` also bounds the search of the per-observation innovation test.
    ``robust_kernel``: the kernel :meth:`optimise` uses by default (None: CM (12) as it is;
    ``"huber"`` / ``"cauchy"``: :mod:`filters.optimiser`). ``blas_threads``: the BLAS threads
    :meth:`optimise` runs with (default one; None: the process's setting; :mod:`filters.blas`).

    Interface events are aggregated over a *decision interval*: :meth:`start_interval` (the env
    calls it before each decision) clears them; until then every update and fusion adds to them.
    """

    def __init__(
        self,
        front_end,
        back_end="ekf",
        *,
        initial_pose=None,
        initial_pose_cov=None,
        gate_probability: float = 0.999,
        node_budget: int = DEFAULT_NODE_BUDGET,
        loop_closure_unseen_s: float = DEFAULT_LOOP_CLOSURE_UNSEEN_S,
        closure_radius_m: float = DEFAULT_CLOSURE_RADIUS_M,
        robust_kernel: str | None = None,
        blas_threads: int | None = DEFAULT_BLAS_THREADS,
    ):
        validate_gate_probability(gate_probability)
        self.blas_threads = check_blas_threads(blas_threads)
        require(robust_kernel in ROBUST_KERNELS, "robust_kernel", robust_kernel,
                f"one of {ROBUST_KERNELS}")
        validate_node_budget(node_budget)
        check_range("loop_closure_unseen_s", loop_closure_unseen_s, 0.0, 1e9)
        check_range("closure_radius_m", closure_radius_m, 0.0, 1e6)
        if isinstance(back_end, str):
            options = dict(gate_probability=gate_probability, node_budget=node_budget)
            if back_end == "ekf":
                options.update(
                    loop_closure_unseen_s=loop_closure_unseen_s, closure_radius_m=closure_radius_m
                )
            back_end = make_back_end(back_end, initial_pose, initial_pose_cov, **options)
        else:
            require(
                initial_pose is None and initial_pose_cov is None,
                "initial_pose",
                initial_pose,
                "None when back_end is given as an object (it holds its own initial pose)",
            )
        self.front_end = front_end
        self.back_end = back_end
        self.gate_probability = float(gate_probability)
        self.closure_radius_m = float(closure_radius_m)
        self.robust_kernel = robust_kernel
        self.front_end.restart()
        self.submaps: list[StoredSubmap] = []
        self.n_fusions = 0
        self.n_optimisations = 0
        self._t = 0.0
        self._t_last_optimise = 0.0
        self._fusions_since_optimise = 0
        self._closures_since_optimise = 0
        self._composed = None  # the composed pose of the current state (_compose_with_origin)
        self._frames = None  # the back-end's frames of the compiled iteration (_frame)
        self.last_optimum = None  # the OptimiseResult applied last (filters.submap_optimise)
        self.start_interval()

    # ------------------------------------------------------------------ filter interface
    @property
    def last_associations(self) -> np.ndarray:
        """The front-end's associations of the last update (local ids; -1 = clutter)."""
        return self.front_end.last_associations

    @property
    def time_s(self) -> float:
        return self._t

    def predict(self, u, dt):
        self.front_end.predict(u, dt)
        self._t += float(dt)
        self._composed = None

    def update(self, z):
        z = np.asarray(z, dtype=float).reshape(-1, 2)
        ratio = self.observation_innovation_ratio(z)  # against the prior of this update
        self.interval_innovation_ratio = max(self.interval_innovation_ratio, ratio)
        self.front_end.update(z)
        self._composed = None

    def update_heading(self, theta, std_rad):
        """Compass: the local heading ``theta - theta(v-)`` goes to the front-end (module doc)."""
        check_range("theta", theta, -1e6, 1e6)
        v_theta = self.back_end.x[2]
        self.front_end.update_heading(float(wrap_angle(theta - v_theta)), std_rad)
        self._composed = None

    def iterate(self, u, dt, z=None, *, heading=None, truth_pose=None):
        """One filter iteration: what ``predict(u, dt)``, ``update_heading(*heading)``
        (``heading`` = ``(theta, std_rad)``, global; None: no compass), ``update(z)`` (None: no
        scan) and :meth:`pose` do, and the pose's NEES and position error against ``truth_pose``
        (None: NaN). Returns ``(mean, cov, nees, position_error_m)``.

        With a front-end that has a compiled iteration
        (:meth:`filters.fastslam.FastSLAM2.run_iteration`)
        all of it, the innovation ratio of :meth:`update` and the composition with the origin
        included, is one compiled call given the origin and the global map
        (:class:`filters.fastslam_kernel.GlobalFrame`); otherwise the separate calls
        (:func:`filters.global_frame.stepwise_iteration`)."""
        front = self.front_end
        if not hasattr(front, "run_iteration"):
            return stepwise_iteration(self, u, dt, z, heading, truth_pose)
        if heading is not None:  # the local heading (module doc)
            check_range("theta", heading[0], -1e6, 1e6)
            heading = (float(wrap_angle(heading[0] - self.back_end.x[2])), heading[1])
        if z is not None:
            z = np.asarray(z, dtype=float).reshape(-1, 2)
        result = front.run_iteration(u, dt, z, heading=heading, frame=self._frame(z),
                                     truth_pose=truth_pose)
        self._t += float(dt)
        if z is not None:
            self.interval_innovation_ratio = max(self.interval_innovation_ratio,
                                                 float(result.innovation_ratio))
        self._composed = (result.mean, result.cov, result.J_a)
        return result.mean.copy(), result.cov.copy(), float(result.nees), float(
            result.position_error_m)

    def _frame(self, z) -> GlobalFrame:
        """The local map's origin and, when a scan ``z`` may observe global features, the global
        map the innovation ratio tests it against (:meth:`observation_innovation_ratio`).

        Both frames are formed once per state of the back-end (:meth:`_back_end_frames`): the
        back-end changes only when the system fuses or optimises, which forget them."""
        g = self.back_end
        frames = getattr(self, "_frames", None)  # (a pickle of an older system has none)
        if frames is None or frames[0] is not g.x or frames[1] is not g.P:
            frames = self._frames = self._back_end_frames()
        if z is None or len(z) == 0 or g.n_features == 0:
            return frames[2]
        return frames[3]

    def _back_end_frames(self):
        """``(x, P, origin frame, frame with the global map)`` of the back-end's state: the
        frame of a scan that cannot observe a global feature (the origin alone) and of one that
        can (:meth:`_frame`)."""
        g = self.back_end
        v, P_v = g.origin()
        alone = own_frame()._replace(origin=v, origin_cov=P_v)
        with_map = alone
        if g.n_features:
            with_map = GlobalFrame(v, P_v, np.asarray(g.x, dtype=float),
                                   np.asarray(g.P, dtype=float), read_only(g.feature_cols()),
                                   self.closure_radius_m)
        return g.x, g.P, alone, with_map

    def _compose_with_origin(self):
        """``(v- (+) x_v^L, its covariance, J_a)``; computed once per state (every method that
        changes the front-end or the back-end resets it)."""
        if self._composed is None:
            v, P_v = self.back_end.origin()
            xl, Pl = self.front_end.pose()
            self._composed = compose_with_covariance(v, P_v, xl, Pl)
        mean, cov, J_a = self._composed
        return mean.copy(), cov.copy(), J_a.copy()

    def pose(self):
        """``v- (+) x_v^L`` with covariance ``J_a P_v- J_a^T + J_b P_L J_b^T`` (BB Fig. 3)."""
        mean, cov, _ = self._compose_with_origin()
        return mean, cov

    def landmarks(self) -> LandmarkEstimate:
        """Global features plus the confirmed local features carried into the global frame."""
        glob = self.back_end.landmarks()
        loc = self.front_end.landmarks()
        keep = loc.existence > CONFIRMED_PROBABILITY
        if not keep.any():
            return glob
        v, P_v = self.back_end.origin()
        pts = loc.means[keep]
        J_v, rot = transform_points_jacobians(v, pts)
        means = transform_point(v, pts)
        covs = J_v @ P_v @ np.swapaxes(J_v, 1, 2) + rot @ loc.covs[keep] @ rot.T
        return LandmarkEstimate(
            ids=np.concatenate([glob.ids, loc.ids[keep]]),
            means=np.vstack([glob.means, means]),
            covs=np.concatenate([glob.covs, 0.5 * (covs + np.swapaxes(covs, 1, 2))]),
            existence=np.concatenate([glob.existence, loc.existence[keep]]),
        )

    def landmark_means(self):
        """``(ids, means, existence)`` of :meth:`landmarks` without the local features'
        covariances (the same numbers), when the front-end can skip them (map scoring)."""
        if not hasattr(self.front_end, "landmark_means"):
            lm = self.landmarks()
            return lm.ids, lm.means, lm.existence
        g_ids, g_means, g_existence = self.back_end.landmark_means()
        ids, means, existence = self.front_end.landmark_means()
        keep = existence > CONFIRMED_PROBABILITY
        if not keep.any():
            return g_ids, g_means, g_existence
        v = self.back_end.x[:3]
        return (
            np.concatenate([g_ids, ids[keep]]),
            np.vstack([g_means, transform_point(v, means[keep])]),
            np.concatenate([g_existence, existence[keep]]),
        )

    # ------------------------------------------------------------------ fusion / optimisation
    def fuse(self) -> FusionReport:
        """Fuse the local map into the global map and restart the front-end (BB section 4)."""
        local = self.front_end.to_gaussian()
        count = getattr(self.front_end, "landmark_count", None)  # a count without the moments
        n_local = count() if count is not None else len(self.front_end.landmarks())
        report = self.back_end.fuse(local, time_s=self._t)
        report.n_dropped = n_local - local.n_features
        self.submaps.append(
            StoredSubmap(
                gaussian=local,
                id_map=dict(report.id_map),
                origin_index=len(self.submaps),
                end_index=len(self.submaps) + 1,
                time_s=self._t,
            )
        )
        self.front_end.restart()
        self._composed = None
        self._frames = None
        self.n_fusions += 1
        self._fusions_since_optimise += 1
        self.interval_loop_closures.extend(report.loop_closures)
        self._closures_since_optimise += len(report.loop_closures)
        return report

    def optimise(self, method: str = "gauss-newton", **options):
        """CM III.C: minimise CM (12) over the stored sub-maps and replace the global estimate
        by the optimum and its Gauss-Newton covariance (:mod:`filters.submap_optimise`); with the
        system's ``robust_kernel`` (None, ``"huber"``, ``"cauchy"``) unless ``robust`` is given."""
        options.setdefault("robust", self.robust_kernel)
        options.setdefault("blas_threads", self.blas_threads)
        return optimise_submaps(self, method, **options)

    def optimisation_is_redundant(self, method: str = "gauss-newton", **options) -> bool:
        """Whether :meth:`optimise` with these arguments would be redundant now: nothing fused
        since the optimum applied last (or nothing fused at all), so it would change nothing and
        be charged nothing (:func:`filters.submap_optimise.optimisation_is_redundant`)."""
        options.setdefault("robust", self.robust_kernel)
        return optimisation_is_redundant(self, method, **options)

    def _optimised(self):
        """Book-keeping after an optimisation (for the optimiser's implementation)."""
        self.n_optimisations += 1
        self._composed = None
        self._frames = None
        self._t_last_optimise = self._t
        self._fusions_since_optimise = 0
        self._closures_since_optimise = 0

    # ------------------------------------------------------------------ interface events
    def start_interval(self) -> None:
        """Start a decision interval: clear the events aggregated since the last call."""
        self.interval_innovation_ratio = 0.0
        self.interval_loop_closures: list[SubmapLoopClosure] = []

    def observation_innovation_ratio(self, z) -> float:
        """The largest CM ratio ``||nu|| / (2 sigma)`` (CM III.B) of the observations ``z`` of a
        global feature, against the current estimate (:func:`nearest_global_innovations`)."""
        g = self.back_end
        if g.n_features == 0 or len(z) == 0:
            return 0.0
        pose, sigma, J_a = self._compose_with_origin()
        sensor = self.front_end.sensor  # R's diagonal, without forming R at every step
        _, ratio = nearest_global_innovations(
            z, pose, sigma, J_a, np.asarray(g.x, dtype=float), np.asarray(g.P, dtype=float),
            g.feature_cols(), float(sensor.range_std_m**2), float(sensor.bearing_std_rad**2),
            self.closure_radius_m,
        )
        return float(ratio.max())

    def global_features_in_view(self) -> int:
        g = self.back_end
        if g.n_features == 0:
            return 0
        pose = self._composed_mean()
        sensor = self.front_end.sensor
        features = g.x[g.feature_cols()]
        if sensor.fov_rad >= 2.0 * np.pi:  # in view is in range: the bearings are not needed
            ranges = np.hypot(features[:, 0] - pose[0], features[:, 1] - pose[1])
            return int(np.count_nonzero(ranges <= sensor.max_range_m))
        return int(np.count_nonzero(sensor.in_view(observe(pose, features))))

    def _composed_mean(self) -> np.ndarray:
        """The composed pose's mean of :meth:`_compose_with_origin` (not a copy: read it only)."""
        if self._composed is None:
            self._compose_with_origin()
        return self._composed[0]

    def interface_features(self) -> dict[str, float]:
        """All interface features of docs/ARCHITECTURE.md (names in INTERFACE_FEATURE_NAMES)."""
        out = dict(self.front_end.local_statistics())
        _, cov = self.pose()
        closures = self.interval_loop_closures
        out.update(
            innovation_ratio=max(
                self.interval_innovation_ratio,
                max((lc.innovation_ratio for lc in closures), default=0.0),
            ),
            global_features_in_view=float(self.global_features_in_view()),
            global_position_std_m=float(np.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))),
            global_heading_std_rad=float(np.sqrt(max(cov[2, 2], 0.0))),
            time_since_optimise_s=float(self._t - self._t_last_optimise),
            fusions_since_optimise=float(self._fusions_since_optimise),
            loop_closure_flag=float(len(closures) > 0),
            loop_closures_since_optimise=float(self._closures_since_optimise),
            stored_submaps=float(len(self.submaps)),
        )
        missing = [k for k in INTERFACE_FEATURE_NAMES if k not in out]
        require(not missing, "front_end.local_statistics()", sorted(out), f"to include {missing}")
        return {k: float(out[k]) for k in INTERFACE_FEATURE_NAMES}
