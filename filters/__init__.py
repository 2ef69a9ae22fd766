"""slam-gym's estimation library: numpy/scipy (and numba, and threadpoolctl for the BLAS thread
limit of :mod:`filters.blas`) only, importing nothing else of the project (docs/ARCHITECTURE.md,
"Layers").

The estimators (each a filterpy-like class: ``predict(u, dt)``, ``update(z)``, ``pose()``,
``landmarks()``; docs/ARCHITECTURE.md, "Filter interface"):

==========================  ===================================================================
:class:`DeadReckoning`      odometry only (:mod:`filters.dead_reckoning`)
:class:`EKFSLAM`            EKF-SLAM, the baseline and the EKF front-end (:mod:`filters.ekf_slam`)
:class:`FastSLAM2`          FastSLAM 2.0 with data association sampling, existence and
                            correspondence voting, the particle front-end (:mod:`filters.fastslam`)
:class:`SubmapSLAM`         a front-end and a back-end joined by the local-to-global interface,
                            BB section 4 (:mod:`filters.submap`)
:class:`GlobalMap`          BB's global EKF back-end (:mod:`filters.back_ends`)
:class:`RelativeBackEnd`    CM's relative representation as a sub-map back-end
                            (:mod:`filters.back_ends`); :func:`make_back_end` builds either
:class:`ESDF`               CM's exactly sparse delayed-state filter (:mod:`filters.esdf`)
:class:`RelativeESDF`       CM's relative-coordinate ESDF (:mod:`filters.relative_esdf`)
==========================  ===================================================================

Their models (:mod:`filters.models`): :class:`RangeBearingSensor`, :class:`ClutterModel`,
:class:`ProportionalVelocityNoise`, :class:`ChongKleemanNoise`; their shared types
(:mod:`filters.types`): :class:`FeatureIds`, :class:`LandmarkEstimate`, :class:`GaussianMap`,
:class:`FusionReport`, :class:`SlamFilter`. Each name is imported from its module on first use,
so ``import filters`` (which ``policies`` does, for :mod:`filters.validation`) loads no filter.
"""

from typing import Any

__all__ = [
    "ESDF",
    "EKFSLAM",
    "ChongKleemanNoise",
    "ClutterModel",
    "DeadReckoning",
    "FastSLAM2",
    "FeatureIds",
    "FusionReport",
    "GaussianMap",
    "GlobalMap",
    "LandmarkEstimate",
    "ProportionalVelocityNoise",
    "RangeBearingSensor",
    "RelativeBackEnd",
    "RelativeESDF",
    "SlamFilter",
    "SubmapSLAM",
    "make_back_end",
]


def __getattr__(name: str) -> Any:
    if name == "DeadReckoning":
        from filters.dead_reckoning import DeadReckoning

        return DeadReckoning
    if name == "EKFSLAM":
        from filters.ekf_slam import EKFSLAM

        return EKFSLAM
    if name == "FastSLAM2":
        from filters.fastslam import FastSLAM2

        return FastSLAM2
    if name == "SubmapSLAM":
        from filters.submap import SubmapSLAM

        return SubmapSLAM
    if name in ("GlobalMap", "RelativeBackEnd", "make_back_end"):
        from filters import back_ends

        return getattr(back_ends, name)
    if name == "ESDF":
        from filters.esdf import ESDF

        return ESDF
    if name == "RelativeESDF":
        from filters.relative_esdf import RelativeESDF

        return RelativeESDF
    if name in ("RangeBearingSensor", "ClutterModel", "ProportionalVelocityNoise",
                "ChongKleemanNoise"):
        from filters import models

        return getattr(models, name)
    if name in ("FeatureIds", "LandmarkEstimate", "GaussianMap", "FusionReport", "SlamFilter"):
        from filters import types

        return getattr(types, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
