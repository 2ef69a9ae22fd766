"""SLAM systems by name, built for a :class:`~slam_gym.stream.Stream` (docs/ARCHITECTURE.md,
"Filter interface").

=================  ============================================================================
``dead-reckoning``  odometry (and compass) only
``ekf-slam``        EKF-SLAM with JCBB, clutter and existence probabilities
``fastslam``        FastSLAM 2.0 with data association sampling (BB's FASTSLAM row)
``ekf-submap``      EKF front-end, EKF back-end (BB's EKF row: sub-mapping)
``hybrid``          FastSLAM 2.0 front-end, EKF (or relative) back-end (BB's HYBRID row)
``esdf``            Exactly Sparse Delayed-state Filter (Eustice et al.; CM II), known association
``relative-esdf``   CM's ESDF in relative coordinates with loop-closure detection (CM III.B)
=================  ============================================================================

:class:`System` gives every estimator one shape: ``update(z, known_ids=None)`` (known ids are
the truth labels of CM's known-association setting and of the comparison mode on real data),
``fuse()`` / ``optimise()`` (sub-map systems; a clear error elsewhere) and
``interface_features()``.
"""

from __future__ import annotations

import numpy as np

from filters.validation import require

SYSTEM_NAMES = (
    "dead-reckoning",
    "ekf-slam",
    "fastslam",
    "ekf-submap",
    "hybrid",
    "esdf",
    "relative-esdf",
)
SUBMAP_SYSTEMS = ("ekf-submap", "hybrid")
KNOWN_ASSOCIATION_ONLY = ("esdf", "relative-esdf")


class System:
    """A named estimator with the uniform interface the episode, the env and the CLI use."""

    def __init__(self, name: str, estimator, known_ids_keyword: str | None):
        self.name = name
        self.estimator = estimator
        self._known_ids_keyword = known_ids_keyword

    def __getattr__(self, attribute):
        # everything else (front_end, back_end, submaps, ...) is the estimator's
        estimator = self.__dict__.get("estimator")
        if estimator is None:  # while unpickling, before __dict__ is restored
            raise AttributeError(attribute)
        return getattr(estimator, attribute)

    def predict(self, u, dt):
        self.estimator.predict(u, dt)

    def update_heading(self, theta, std_rad):
        self.estimator.update_heading(theta, std_rad)

    def update(self, z, known_ids=None):
        if known_ids is None:
            if self.name in KNOWN_ASSOCIATION_ONLY:
                raise ValueError(
                    f"system={self.name!r} needs known association (CM IV.A): run it with "
                    "known_association=True"
                )
            self.estimator.update(z)
            return
        require(
            self._known_ids_keyword is not None, "known_association", True,
            f"False for system {self.name!r} (it has no known-association mode)",
        )
        self.estimator.update(z, **{self._known_ids_keyword: np.asarray(known_ids)})

    @property
    def last_associations(self):
        return self.estimator.last_associations

    def pose(self):
        return self.estimator.pose()

    def landmarks(self):
        return self.estimator.landmarks()

    def fuse(self):
        if not hasattr(self.estimator, "fuse"):
            raise ValueError(f"system={self.name!r} has no local map to fuse")
        return self.estimator.fuse()

    def optimise(self):
        if not hasattr(self.estimator, "optimise"):
            raise ValueError(f"system={self.name!r} has nothing to optimise")
        return self.estimator.optimise()

    def optimisation_is_redundant(self) -> bool:
        """Whether :meth:`optimise` now would be a redundant no-op (nothing fused since the
        optimum applied last): the estimator's own test; False for one that has none (asking
        it to optimise is then never known to be free)."""
        test = getattr(self.estimator, "optimisation_is_redundant", None)
        return bool(test()) if test is not None else False

    def interface_features(self) -> dict[str, float]:
        if not hasattr(self.estimator, "interface_features"):
            raise ValueError(f"system={self.name!r} is not a sub-map system")
        return self.estimator.interface_features()


def make_system(
    name: str,
    stream,
    rng,
    *,
    n_particles: int = 500,
    back_end: str = "ekf",
    **options,
) -> System:
    """Build system ``name`` with the stream's sensor, clutter and odometry models.

    Every filter starts at the stream's initial pose, known exactly (BB, CM). ``options`` go to
    the estimator (front-end options for sub-map systems, prefixed ``front_``/``back_`` where
    the two need telling apart). ``rng``: the filters' random numbers, a
    ``numpy.random.Generator`` (one stream in order of use) or a source of
    :mod:`filters.draws`.
    """
    require(name in SYSTEM_NAMES, "system", name, f"one of {SYSTEM_NAMES}")
    from filters.draws import as_draws
    from filters.types import FeatureIds

    rng = as_draws(rng)  # ValueError naming rng unless a Generator or a source of draws

    ids = FeatureIds()
    sensor, clutter, noise = stream.sensor, stream.clutter, stream.odometry_noise
    pose0 = np.asarray(stream.initial_pose, dtype=float)
    if name == "dead-reckoning":
        from filters.dead_reckoning import DeadReckoning

        return System(name, DeadReckoning(noise, pose0), None)
    if name == "ekf-slam":
        from filters.ekf_slam import EKFSLAM

        return System(name, EKFSLAM(sensor, clutter, noise, ids, initial_pose=pose0, **options),
                      "associations")
    if name == "fastslam":
        from filters.fastslam import FastSLAM2

        est = FastSLAM2(
            sensor, clutter, noise, rng, ids, n_particles=n_particles, initial_pose=pose0,
            **options,
        )
        return System(name, est, "associations")
    if name in SUBMAP_SYSTEMS:
        from filters.submap import SubmapSLAM

        front_options = {k[len("front_"):]: v for k, v in options.items() if k.startswith("front_")}
        back_options = {k[len("back_"):]: v for k, v in options.items() if k.startswith("back_")}
        stray = sorted(k for k in options if not k.startswith(("front_", "back_")))
        require(not stray, "options", stray, "prefixed front_ or back_ for sub-map systems")
        if name == "hybrid":
            from filters.fastslam import LOCAL_MAP_MAX_EXISTENCE, FastSLAM2

            front_options.setdefault("max_existence", LOCAL_MAP_MAX_EXISTENCE)
            front = FastSLAM2(
                sensor, clutter, noise, rng, ids, n_particles=n_particles, **front_options
            )
        else:
            from filters.ekf_slam import EKFSLAM

            front = EKFSLAM(sensor, clutter, noise, ids, **front_options)
        est = SubmapSLAM(front, back_end=back_end, initial_pose=pose0, **back_options)
        return System(name, est, None)
    if name == "esdf":
        from filters.esdf import ESDF

        return System(name, ESDF(sensor, clutter, noise, ids, initial_pose=pose0, **options),
                      "ids")
    from filters.relative_esdf import RelativeESDF

    return System(
        name, RelativeESDF(sensor, clutter, noise, ids, initial_pose=pose0, **options), "ids"
    )
