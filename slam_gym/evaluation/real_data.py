"""The run functions of ``slam-gym reproduce mrclam`` / ``reproduce victoria-park``: one job of a
system (or of HYBRID driven by a policy in the env) over one recording, and its result row.

The command line is :mod:`slam_gym.commands.reproduce_real` (whose docstring defines the rows'
metrics), the tables and figures :mod:`slam_gym.commands.real_tables`; the generic run functions
of the simulated worlds are :mod:`slam_gym.evaluation.core`.
"""

from __future__ import annotations

import logging

import numpy as np

from filters.existence import CONFIRMED_PROBABILITY
from filters.validation import require
from slam_gym.datasets.mrclam import DEFAULT_CALIBRATION_S, MrclamOptions

logger = logging.getLogger(__name__)
DEFAULT_PARTICLES = 200
FUSION_INTERVAL_S = 10.0
DECISION_INTERVAL = 10
MRCLAM_PREFIX = "mrclam:robot"
VP_SCENARIO = "victoria-park"
#: figure data kept in the rows: one point per second of the path
PATH_EVERY_S = 1.0

POLICY_ONLY_OPTIONS = ("w_compute", "compute_clip_s")
"""MRCLAM job options that only a policy run takes."""

MRCLAM_STREAM_OPTIONS = (
    "noise_window_s", "sensor_bias_correction", "motion_compensation", "corrections",
    "calibration_s",
)
"""The fields of :class:`slam_gym.datasets.mrclam.MrclamOptions` (the loader's calibration)
that MRCLAM jobs take; their defaults are the options object's."""

MRCLAM_OPTIONS = {
    "data": None,
    "known_association": False,
    "n_particles": DEFAULT_PARTICLES,
    "max_steps": None,
    "noise_scale": 1.0,
    "fusion_interval_s": FUSION_INTERVAL_S,
    "decision_interval": DECISION_INTERVAL,
    "model_path": None,
    "model_sha256": None,
    **{name: getattr(MrclamOptions(), name) for name in MRCLAM_STREAM_OPTIONS},
    "landmark_density_per_m2": None,
    "gate_chi2": None,
    "optimise": "never",
    "robust_kernel": None,
    "w_compute": None,
    "compute_clip_s": None,
}
#: MRCLAM options of the FastSLAM filters (FASTSLAM, HYBRID's front-end) by filter keyword
MRCLAM_FASTSLAM_OPTIONS = {
    "landmark_density_per_m2": "new_landmark_density_per_m2",
    "gate_chi2": "gate_chi2",
}
VP_OPTIONS = {
    "data": None,
    "n_particles": DEFAULT_PARTICLES,
    "max_steps": None,
    "fusion_interval_s": FUSION_INTERVAL_S,
}



# --------------------------------------------------------------------------- the run function
def run_real_job(job) -> dict:
    """The run function of both targets (module level: it goes to worker processes).

    ``job.scenario`` is ``"mrclam:robotN"`` or ``"victoria-park"``; ``job.options`` carry the
    data directory (``data``), ``max_steps``, ``n_particles``, and for MRCLAM
    ``known_association``, ``noise_scale`` and (policies) ``decision_interval``, ``model_path``,
    ``model_sha256``.
    """
    if job.scenario.startswith(MRCLAM_PREFIX):
        robot = int(job.scenario[len(MRCLAM_PREFIX):])
        opts = _options(job.options_dict(), MRCLAM_OPTIONS)
        if job.kind == "policy":
            return run_mrclam_policy(job.name, robot, job.seed, **opts)
        for key in POLICY_ONLY_OPTIONS:  # the reward's price: a system run has no reward
            require(opts.pop(key) is None, key, job.options_dict().get(key),
                    "unset for a system run (it prices a policy's reward)")
        return run_mrclam_system(job.name, robot, job.seed, **opts)
    require(job.scenario == VP_SCENARIO, "scenario", job.scenario,
            f"'{MRCLAM_PREFIX}N' or '{VP_SCENARIO}'")
    require(job.kind == "system", "kind", job.kind, "'system' on Victoria Park")
    return run_victoria_park_system(job.name, job.seed,
                                    **_options(job.options_dict(), VP_OPTIONS))


def _options(given: dict, defaults: dict) -> dict:
    unknown = sorted(set(given) - set(defaults))
    require(not unknown, "options", unknown, f"among {sorted(defaults)}")
    return defaults | given


def _rounded(a, decimals: int = 3) -> list:
    return np.round(np.asarray(a, dtype=float), decimals).tolist()


def mrclam_result(episode, stream, robot: int, association: str) -> dict:
    """The result row of an MRCLAM run: the episode's metrics
    (:func:`slam_gym.evaluation.core.episode_result`), the pose RMSE against motion capture (also
    after the calibration part), completeness and the traces of the figures."""
    from slam_gym.evaluation.core import episode_result

    row = episode_result(episode, stream)
    trace = episode.trace
    errors = np.asarray(trace.position_error_m, dtype=float)
    row["pose_rmse_m"] = float(np.sqrt(np.mean(errors**2))) if errors.size else float("nan")
    # held out: the steps after the part of the recording the loader calibrated on
    end = stream.metadata.get("calibration_end_s")
    late = errors[np.asarray(trace.t_s, dtype=float) > end] if end is not None else errors[:0]
    row["pose_rmse_held_out_m"] = float(np.sqrt(np.mean(late**2))) if late.size else None
    # completeness: the share of the landmarks the robot saw that have a confirmed feature
    seen = np.unique(stream.make_steps.landmark_ids[: stream.make_steps.bounds[len(stream)]])
    n_seen = int(np.count_nonzero(seen >= 0))
    missed = row.get("n_missed")
    row["n_landmarks_seen"] = n_seen
    row["completeness"] = (1.0 - missed / n_seen) if (n_seen and missed is not None) else None
    row.update(
        dataset="MRCLAM",
        robot=robot,
        association=association,
        n_steps=len(stream),
        range_std_m=stream.sensor.range_std_m,
        bearing_std_rad=stream.sensor.bearing_std_rad,
        sensor_noise_scale=float(stream.metadata.get("sensor_noise_scale", 1.0)),
    )
    every = max(1, round(PATH_EVERY_S / stream.dt_s))
    lm = episode.system.landmarks()
    keep = np.asarray(lm.existence) >= CONFIRMED_PROBABILITY
    row["figure"] = {
        "true_path_xy": _rounded(np.asarray(trace.true_poses)[::every, :2]),
        "est_path_xy": _rounded(np.asarray(trace.est_poses)[::every, :2]),
        "landmark_means": _rounded(np.asarray(lm.means).reshape(-1, 2)[keep]),
        "landmark_covs": _rounded(np.asarray(lm.covs).reshape(-1, 2, 2)[keep], 6),
    }
    return row


def fastslam_options(landmark_density_per_m2=None, gate_chi2=None) -> dict:
    """The FastSLAM2 keyword options of the MRCLAM options given (None = filter default)."""
    given = {"landmark_density_per_m2": landmark_density_per_m2, "gate_chi2": gate_chi2}
    return {MRCLAM_FASTSLAM_OPTIONS[k]: float(v) for k, v in given.items() if v is not None}


def _system_options(name: str, fs_options: dict) -> dict:
    if name == "fastslam":
        return dict(fs_options)
    if name == "hybrid":
        return {f"front_{k}": v for k, v in fs_options.items()}
    return {}  # the EKF filters keep their defaults


def _calibration_fields(opts: dict) -> dict:
    """The sensor-calibration and FastSLAM options of a run, for its result row."""
    return {k: opts[k] for k in (*MRCLAM_STREAM_OPTIONS, *MRCLAM_FASTSLAM_OPTIONS)}


def run_mrclam_system(
    name: str, robot: int, seed: int, *, data, known_association=False,
    n_particles=DEFAULT_PARTICLES, max_steps=None, noise_scale=1.0,
    fusion_interval_s=FUSION_INTERVAL_S, decision_interval=DECISION_INTERVAL, model_path=None,
    model_sha256=None, noise_window_s=None, sensor_bias_correction=None,
    motion_compensation=None, corrections=True, calibration_s=DEFAULT_CALIBRATION_S,
    landmark_density_per_m2=None, gate_chi2=None, optimise="never", robust_kernel=None,
) -> dict:
    """One system over one MRCLAM robot on BB's fixed schedule; the result row.

    ``optimise``: the sub-map systems' ``optimise()`` schedule
    (:data:`slam_gym.evaluation.core.OPTIMISE_MODES`); ``robust_kernel``: their optimiser's
    kernel (None, ``"huber"``, ``"cauchy"``; :mod:`filters.optimiser`).

    ``noise_window_s``, ``sensor_bias_correction``, ``motion_compensation``: the loader's sensor
    calibration (:func:`slam_gym.envs.mrclam.mrclam_stream`); ``landmark_density_per_m2``,
    ``gate_chi2``: options of the FastSLAM filters (FASTSLAM and HYBRID's front-end; the EKF
    filters keep their defaults). Known and unknown association get the same options."""
    from slam_gym.envs.mrclam import mrclam_stream
    from slam_gym.evaluation.core import run_system

    stream = mrclam_stream(
        data, robot, max_steps=max_steps, sensor_noise_scale=noise_scale,
        options=MrclamOptions(
            noise_window_s=noise_window_s, sensor_bias_correction=sensor_bias_correction,
            motion_compensation=motion_compensation, corrections=corrections,
            calibration_s=calibration_s,
        ),
    )
    fs_options = fastslam_options(landmark_density_per_m2, gate_chi2)
    system_options = _system_options(name, fs_options)
    if robust_kernel is not None:
        require(name in ("ekf-submap", "hybrid"), "robust_kernel", robust_kernel,
                "None for a system without sub-maps")
        system_options["back_robust_kernel"] = robust_kernel
    episode = run_system(
        name, stream, seed, n_particles=n_particles, fusion_interval_s=fusion_interval_s,
        known_association=known_association, stop_on_failure=False, record_trace=True,
        system_options=system_options, optimise=optimise,
    )
    row = mrclam_result(episode, stream, robot, "known" if known_association else "unknown")
    row.update(_calibration_fields(locals()))
    row["optimise"] = optimise
    row["robust_kernel"] = robust_kernel
    return row


def run_mrclam_policy(
    name: str, robot: int, seed: int, *, data, n_particles=DEFAULT_PARTICLES, max_steps=None,
    noise_scale=1.0, decision_interval=DECISION_INTERVAL, model_path=None, model_sha256=None,
    known_association=False, fusion_interval_s=FUSION_INTERVAL_S,
    noise_window_s=None, sensor_bias_correction=None, motion_compensation=None,
    corrections=True, calibration_s=DEFAULT_CALIBRATION_S, landmark_density_per_m2=None,
    gate_chi2=None, optimise="never", robust_kernel=None, w_compute=None, compute_clip_s=None,
) -> dict:
    """HYBRID driven by interface policy ``name`` in :class:`MRCLAMEnv` over one robot (the
    calibration and FastSLAM options as in :func:`run_mrclam_system`; the policy decides when
    to optimise, so ``optimise`` must stay ``"never"``). ``w_compute`` and ``compute_clip_s``
    (None: the env's defaults) set the reward's price of compute, which a policy conditioned on
    it observes (``compute_price_per_s``)."""
    from slam_gym.compute_cost import summarise_records
    from slam_gym.envs.mrclam import MRCLAMEnv
    from slam_gym.evaluation.core import make_policy, provenance_fields

    require(not known_association, "known_association", known_association,
            "False for policies (the env has no known-association mode)")
    require(optimise == "never", "optimise", optimise,
            "'never' for policies (the policy chooses when to optimise)")
    require(robust_kernel is None, "robust_kernel", robust_kernel,
            "None for policies (the env's optimiser has no kernel option)")
    policy = make_policy(name, model_path=model_path, model_sha256=model_sha256)
    env = MRCLAMEnv(
        data_dir=data, robot=robot, n_particles=n_particles,
        decision_interval=decision_interval, n_steps=max_steps,
        sensor_noise_scale=noise_scale, terminate_on_failure=False,
        sensor_noise_window_s=noise_window_s, sensor_bias_correction=sensor_bias_correction,
        motion_compensation=motion_compensation, corrections=corrections,
        calibration_s=calibration_s,
        front_end_options=fastslam_options(landmark_density_per_m2, gate_chi2),
        **{k: v for k, v in (("w_compute", w_compute), ("compute_clip_s", compute_clip_s))
           if v is not None},
    )
    policy.reset()
    obs, info = env.reset(seed=int(seed))
    while True:
        obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
        if terminated or truncated:
            break
    row = mrclam_result(env.episode, env.stream, robot, "unknown")
    row["driven_system"] = "hybrid"
    # the return and the interface's compute as the benchmark's policy rows carry them
    row["return"] = env.episode_return
    row["compute_term_s"] = env.episode_compute_term_s
    row["w_compute"] = env.config.w_compute
    row.update(summarise_records(env.compute_records, env.compute_model))
    row.update(_calibration_fields(locals()))
    row.update(provenance_fields(policy))
    env.close()
    return row


def run_victoria_park_system(
    name: str, seed: int, *, data, n_particles=DEFAULT_PARTICLES, max_steps=None,
    fusion_interval_s=FUSION_INTERVAL_S,
) -> dict:
    """One system over Victoria Park: path error against GPS after SE(2) alignment, trees.

    The same schedule as :func:`slam_gym.evaluation.core.run_system` (sub-map systems fuse
    every ``fusion_interval_s``), played step by step here because the estimated path must be
    recorded without pose truth (``Episode`` records its trace only where truth exists).
    """
    from slam_gym.datasets import load_victoria_park, path_error_after_alignment
    from slam_gym.episode import Episode
    from slam_gym.evaluation.core import filter_rng
    from slam_gym.systems import SUBMAP_SYSTEMS, make_system

    stream = load_victoria_park(data, max_steps=max_steps)
    system = make_system(name, stream, filter_rng(seed), n_particles=n_particles)
    episode = Episode(system, stream, record_trace=False)
    submap = name in SUBMAP_SYSTEMS
    every = max(1, round((fusion_interval_s if submap else 1.0) / stream.dt_s))
    t = np.empty(len(stream))
    xy = np.empty((len(stream), 2))
    k = 0
    while not episode.done:
        for _ in range(every):
            if episode.advance(1) == 0:
                break
            t[k] = episode.t_s
            xy[k] = system.pose()[0][:2]
            k += 1
        if submap:
            episode.fuse()
    t, xy = t[:k], xy[:k]
    gps = np.asarray(stream.metadata["gps"], dtype=float)
    fit = path_error_after_alignment(t, xy, gps[:, 0], gps[:, 1:3])
    lm = system.landmarks()
    trees = np.asarray(lm.means).reshape(-1, 2)[np.asarray(lm.existence) >= CONFIRMED_PROBABILITY]
    trees_aligned = trees @ fit.rotation.T + fit.translation
    duration = float(t[-1]) if k else 0.0
    filter_time = float(episode.compute_time_s)
    every_path = max(1, round(PATH_EVERY_S / stream.dt_s))
    return {
        "alpha": stream.clutter.alpha,
        "beta": stream.clutter.beta,
        "success": None,
        "failure_iteration": None,
        "anees": None,
        "nees_in_band_fraction": None,
        "map_error_m": None,
        "final_pose_error_m": float(fit.errors_m[-1]),
        "n_fusions": episode.n_fusions,
        "n_optimisations": episode.n_optimisations,
        "dataset": "Victoria Park",
        "gps_rmse_m": fit.rmse_m,
        "gps_median_error_m": float(np.median(fit.errors_m)),
        "gps_max_error_m": float(np.max(fit.errors_m)),
        "n_gps_fixes_used": int(fit.t_s.size),
        "n_trees": int(len(trees)),
        "n_features": int(len(lm.ids)),
        "iterations": episode.iteration,
        "n_steps": len(stream),
        "duration_s": duration,
        "filter_time_s": filter_time,
        "real_time_factor": duration / filter_time if filter_time > 0 else None,
        "figure": {
            "est_path_xy": _rounded(fit.aligned_path_xy[::every_path], 2),
            "trees_xy": _rounded(trees_aligned, 2),
            "gps_span_s": [float(t[0]), duration] if k else [0.0, 0.0],
        },
    }
