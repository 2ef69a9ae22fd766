"""``slam-gym reproduce mrclam`` / ``reproduce victoria-park``: the systems on real data.

Both data sets are played as :class:`~slam_gym.stream.Stream` s (DESIGN section 2) through the
same systems (:func:`slam_gym.systems.make_system`) and the same evaluation machinery
(:func:`slam_gym.evaluation.run_jobs`: parallel, resumable, one ``results.jsonl`` row per run,
``summary.json`` and ``table.md``), plus a readable ``real_table.md`` and PNG maps.

Schedule: the sub-map systems (``ekf-submap``, ``hybrid``) fuse every 10 s (BB's rule, via
:func:`slam_gym.evaluation.core.run_system`) and by default never optimise (``--optimise``: one
of :data:`slam_gym.evaluation.core.OPTIMISE_MODES`). Particle filters use 200 particles
by default (``--particles``; BB used 500 in simulation; on MRCLAM's 15 landmarks 100-200 are
enough to show the behaviour and keep a robot under a minute). Runs do **not** stop at BB's
failure criterion (``stop_on_failure=False``): on real data the map and path errors over the
whole recording are the point; ``success`` / ``failure_iteration`` still report whether (and
when) the criterion was met.

MRCLAM (UTIAS, Leung et al. IJRR 2011), one job per (system, robot, association mode, seed):

* ``map_error_m`` -- CM's map error of the confirmed features (p(exists) >= 0.95) at the end,
  against ``Landmark_Groundtruth.dat`` (through the truth ids of the observations each feature
  absorbed, :class:`slam_gym.metrics.FeatureTruth`); ``n_spurious`` / ``n_missed`` features
  standing for no landmark / detected landmarks without a feature;
* ``pose_rmse_m`` -- root mean square position error against the motion capture over every
  step; ``anees``, ``nees_in_band_fraction`` -- 3-dof pose NEES;
* ``association`` -- ``"unknown"`` (the filters' own data association) or ``"known"`` (the truth
  ids are handed to the systems that have such a mode; with ``--known-association`` only; the
  loader's gated outliers are then *known* false alarms too). Which systems have the mode is
  probed, not hard-coded (:func:`supports_known_association`; today only ``fastslam``);
* the interface policies (``--policies``) drive HYBRID in :class:`slam_gym.envs.mrclam.MRCLAMEnv`
  (``terminate_on_failure=False``), one decision per second; rows have ``policy`` = the policy
  and ``driven_system`` = ``"hybrid"``. ``learned`` is skipped with a note when no model is
  installed (``policies.make("learned")`` raises ``FileNotFoundError``); ``--model-path`` gives
  one. Its rows carry ``model_matches_code`` and ``model_differences`` (the model's fingerprint
  against the code's, :mod:`slam_gym.training.provenance`); ``real_table.md`` marks a model that
  does not match with a footnote.
* ``--noise-scale`` multiplies the calibrated range and bearing std (see
  :func:`slam_gym.envs.mrclam.mrclam_stream`): MRCLAM's camera errors are strongly correlated in
  time, which white-noise filters do not model.

Calibration: the loader (:func:`slam_gym.datasets.load_mrclam`) estimates every model and
correction on the first ``--calibration-s`` seconds (default 300) of each robot's own recording
and nothing after; ``pose_rmse_held_out_m`` is the pose RMSE over the steps after that part.
By default it removes the odometry's delay (0.2-0.3 s) and speed errors (the robots slow
down in turns), the measurements' time stamp offset, the camera's range bias by bearing
(+0.1-0.25 m at the image centre, -0.2-0.3 m at its edges) and sets the filters' std for the
camera's time-correlated errors (white-noise rule over one pass over a landmark);
``--no-corrections`` gives the plain stream. ``completeness`` is the share of the landmarks the
robot saw that have a confirmed feature at the end. Dataset 7's 15 landmarks stand in clusters
of three, 0.18-0.25 m apart: seen from the *true* pose, 7-17 % of the landmark observations are
closer to a wrong landmark than to their own, so unknown association cannot match the barcodes
(known association) everywhere.

Victoria Park (ACFR, Guivant & Nebot 2001), one job per (system, seed):

* ``gps_rmse_m`` -- RMSE between the estimated path and the GPS fixes after the best rigid SE(2)
  alignment (:func:`slam_gym.datasets.align.path_error_after_alignment`; GPS jumps are not
  rejected, so ``gps_median_error_m`` is given too); ``final_pose_error_m`` = the aligned error
  at the last GPS fix inside the run;
* ``n_trees`` -- confirmed features (p(exists) >= 0.95) at the end;
* **undefined** there (no pose or landmark truth; :class:`~slam_gym.episode.Episode` skips NaN
  truth poses): ``success``, ``failure_iteration``, ``anees``, ``nees_in_band_fraction`` and
  ``map_error_m`` are null. (The generic ``table.md`` therefore shows a success rate of 0 for
  Victoria Park; ``real_table.md`` is the one to read.)

Run time: ``filter_time_s`` (predict/update/fuse only) and ``wall_time_s`` (the whole job, with
loading), and on Victoria Park ``real_time_factor`` = recording duration / filter time.
"""

from __future__ import annotations

import argparse
import logging
import math
import statistics
from pathlib import Path

import numpy as np

from filters.existence import CONFIRMED_PROBABILITY
from filters.validation import require
from slam_gym.commands.common import emit, out_dir
from slam_gym.commands.runs import (
    add_run_options,
    check_run_options,
    errors_exit_code,
    int_list,
    name_list,
    run_options,
)
from slam_gym.datasets.location import default_data_dir
from slam_gym.datasets.mrclam import DEFAULT_CALIBRATION_S
from slam_gym.evaluation.core import OPTIMISE_MODES

logger = logging.getLogger(__name__)

REAL_SYSTEMS = ("ekf-slam", "fastslam", "ekf-submap", "hybrid")
DEFAULT_POLICIES = ("fixed-10s", "esdf-innovation", "learned")
DEFAULT_PARTICLES = 200
FUSION_INTERVAL_S = 10.0
DECISION_INTERVAL = 10
MRCLAM_PREFIX = "mrclam:robot"
VP_SCENARIO = "victoria-park"
REAL_TABLE_FILENAME = "real_table.md"
#: figure data kept in the rows: one point per second of the path
PATH_EVERY_S = 1.0

POLICY_ONLY_OPTIONS = ("w_compute", "compute_clip_s")
"""MRCLAM job options that only a policy run takes."""

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
    "noise_window_s": None,
    "sensor_bias_correction": None,
    "motion_compensation": None,
    "corrections": True,
    "calibration_s": DEFAULT_CALIBRATION_S,
    "landmark_density_per_m2": None,
    "gate_chi2": None,
    "optimise": "never",
    "robust_kernel": None,
    "w_compute": None,
    "compute_clip_s": None,
}
#: MRCLAM options that change the stream (the loader's sensor calibration)
MRCLAM_STREAM_OPTIONS = (
    "noise_window_s", "sensor_bias_correction", "motion_compensation", "corrections",
    "calibration_s",
)
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


# --------------------------------------------------------------------------- command line
def _add_shared_options(parser, default_out: str) -> None:
    parser.add_argument(
        "--particles", type=int, default=DEFAULT_PARTICLES,
        help=f"particles of fastslam and hybrid (default {DEFAULT_PARTICLES})",
    )
    parser.add_argument(
        "--max-steps", type=int, default=None,
        help="cut each recording to its first N filter iterations (default: all)",
    )
    add_run_options(parser, default_out=default_out)
    parser.set_defaults(trials=1)


def add_parser(targets) -> None:
    """Add the ``mrclam`` and ``victoria-park`` targets to ``slam-gym reproduce``."""
    mr = targets.add_parser(
        "mrclam",
        help="the systems and policies on UTIAS MRCLAM (motion-capture truth)",
        description="EKF-SLAM, FastSLAM, EKF sub-mapping and HYBRID (and HYBRID driven by the "
        "interface policies) on MRCLAM robots: map error against Landmark_Groundtruth, pose "
        "RMSE against motion capture, ANEES, spurious and missed landmarks, run time.",
    )
    mr.add_argument(
        "--data", default=None,
        help="MRCLAM data set directory (default $SLAM_GYM_DATA/mrclam/MRCLAM_Dataset7, else "
        "../shared/data/mrclam/MRCLAM_Dataset7 beside "
        "the repository, if it exists)",
    )
    mr.add_argument("--robots", default="1,2,3,4,5", help="comma-separated among 1-5")
    mr.add_argument("--systems", default=",".join(REAL_SYSTEMS),
                    help=f"comma-separated among {', '.join(REAL_SYSTEMS)} ('' for none)")
    mr.add_argument(
        "--policies", default=",".join(DEFAULT_POLICIES),
        help="interface policies driving HYBRID in the MRCLAM env ('' for none); learned is "
        "skipped if no model is installed",
    )
    mr.add_argument("--model-path", default=None, help="model zip for the learned policy")
    mr.add_argument("--w-compute", type=float, default=None,
                    help="the policies' price of compute per second (a policy conditioned on "
                    "the price observes it; default: the env's)")
    mr.add_argument("--compute-clip-s", type=float, default=None,
                    help="the reward's per-decision clip of compute (default: the env's)")
    mr.add_argument(
        "--known-association", action="store_true",
        help="also run each system with known association, where it has that mode",
    )
    mr.add_argument(
        "--noise-scale", type=float, default=1.0,
        help="factor on the calibrated range/bearing std (default 1)",
    )
    mr.add_argument(
        "--calibration-s", type=float, default=DEFAULT_CALIBRATION_S, metavar="SECONDS",
        help="the loader estimates every model and correction on this many first seconds of "
        f"each recording, never on the rest (default {DEFAULT_CALIBRATION_S:g})",
    )
    mr.add_argument(
        "--no-corrections", dest="corrections", action="store_false",
        help="the plain stream: no odometry delay/gain, time stamp, motion, camera bias or "
        "correlated-noise correction (the noise is the root mean square of the residuals)",
    )
    mr.add_argument(
        "--noise-window", type=float, default=None, metavar="SECONDS",
        help="window of the white-noise rule for the camera's time-correlated errors "
        "(default: the median pass over a landmark, measured on the calibration part)",
    )
    mr.add_argument(
        "--sensor-bias-correction", action=argparse.BooleanOptionalAction, default=None,
        help="subtract the camera's systematic range/bearing errors fitted against the truth "
        "(default: as --no-corrections says)",
    )
    mr.add_argument(
        "--motion-compensation", action=argparse.BooleanOptionalAction, default=None,
        help="move each measurement to the end of its filter step with the odometry "
        "(default: as --no-corrections says)",
    )
    mr.add_argument(
        "--landmark-density", type=float, default=None, metavar="PER_M2",
        help="FastSLAM's density of not-yet-mapped landmarks (FASTSLAM and HYBRID; default: "
        "the filter's, BB's 35 landmarks in 120 m x 120 m)",
    )
    mr.add_argument(
        "--gate-chi2", type=float, default=None,
        help="FastSLAM's association gate, chi-square with 2 dof (default: the filter's, "
        "13.8 = 99.9 %%)",
    )
    mr.add_argument(
        "--optimise", choices=list(OPTIMISE_MODES), default="never",
        help="optimise() schedule of the sub-map systems (ekf-submap, hybrid; default never)",
    )
    mr.add_argument(
        "--robust-kernel", choices=["huber", "cauchy"], default=None,
        help="robust kernel of the sub-map systems' optimise() (filters.optimiser; default "
        "none: CM (12) as it is)",
    )
    _add_shared_options(mr, "out/reproduce-mrclam")
    mr.set_defaults(run=run_mrclam)

    vp = targets.add_parser(
        "victoria-park",
        help="the systems on ACFR Victoria Park (GPS as the only truth)",
        description="EKF-SLAM, FastSLAM, EKF sub-mapping and HYBRID on Victoria Park: path "
        "error against GPS after a rigid SE(2) alignment, trees mapped, run time, a map PNG.",
    )
    vp.add_argument("--data", default=None,
                    help="Victoria Park directory (default $SLAM_GYM_DATA/victoria_park, else "
                    "../shared/data/victoria_park)")
    vp.add_argument("--systems", default=",".join(REAL_SYSTEMS),
                    help=f"comma-separated among {', '.join(REAL_SYSTEMS)}")
    _add_shared_options(vp, "out/reproduce-victoria-park")
    vp.set_defaults(run=run_victoria_park)


def _data_dir(given, *default_parts: str) -> Path:
    if given is None:
        found = default_data_dir(*default_parts)
        require(found is not None, "--data", None,
                f"a directory (no default copy: set SLAM_GYM_DATA or put "
                f"shared/data/{'/'.join(default_parts)} beside the repository)")
        return found.resolve()
    path = Path(given).expanduser().resolve()
    require(path.is_dir(), "--data", given, "an existing directory")
    return path


def _check_common(args) -> None:
    require(args.trials >= 1, "--trials", args.trials, "an integer >= 1")
    require(args.seed_start >= 0, "--seed-start", args.seed_start, "an integer >= 0")
    require(1 <= args.particles <= 100_000, "--particles", args.particles,
            "an integer in [1, 100000]")
    require(args.max_steps is None or args.max_steps >= 1, "--max-steps", args.max_steps,
            "an integer >= 1")


def _systems(text: str) -> list[str]:
    systems = name_list(text)
    bad = [s for s in systems if s not in REAL_SYSTEMS]
    require(not bad, "--systems", bad, f"among {list(REAL_SYSTEMS)}")
    require(len(set(systems)) == len(systems), "--systems", systems, "distinct names")
    return systems


def supports_known_association(name: str, stream) -> bool:
    """Whether system ``name`` accepts truth ids (``System.update(z, known_ids=...)``): probed
    on a throw-away instance with an empty scan."""
    from slam_gym.systems import make_system

    system = make_system(name, stream, np.random.default_rng(0), n_particles=1)
    try:
        system.update(np.zeros((0, 2)), known_ids=np.zeros(0, dtype=np.int64))
    except ValueError:
        return False
    return True


def available_policies(names, model_path=None) -> tuple[list[str], dict[str, str]]:
    """(usable policy names, {skipped name: reason}); ``learned`` without a model is skipped."""
    import policies

    usable, skipped = [], {}
    for name in names:
        kwargs = {"path": model_path} if (name == "learned" and model_path) else {}
        try:
            policies.make(name, **kwargs)
        except FileNotFoundError as exc:
            skipped[name] = str(exc)
            logger.warning("policy %s skipped: %s", name, exc)
            continue
        usable.append(name)
    return usable, skipped


def _execute(args, jobs, out):
    from slam_gym.evaluation import run_jobs

    check_run_options(args)
    return run_jobs(jobs, run_real_job, out, **run_options(args))


def run_mrclam(args) -> int:
    from slam_gym.envs.mrclam import check_mrclam_dir, check_robot, mrclam_stream
    from slam_gym.evaluation import Job, write_summary

    _check_common(args)
    data = _data_dir(args.data, "mrclam", "MRCLAM_Dataset7")
    robots = [check_robot(r) for r in int_list(args.robots)]
    require(bool(robots) and len(set(robots)) == len(robots), "--robots", args.robots,
            "distinct robots among 1-5")
    for r in robots:
        check_mrclam_dir(data, r)
    systems = _systems(args.systems)
    policy_names = name_list(args.policies)
    require(len(set(policy_names)) == len(policy_names), "--policies", policy_names,
            "distinct names")
    require(args.noise_scale > 0 and math.isfinite(args.noise_scale), "--noise-scale",
            args.noise_scale, "a number > 0")
    for flag, value in (("--noise-window", args.noise_window),
                        ("--landmark-density", args.landmark_density),
                        ("--gate-chi2", args.gate_chi2)):
        require(value is None or (value > 0 and math.isfinite(value)), flag, value,
                "a number > 0")
    usable, skipped = available_policies(policy_names, args.model_path)
    probe = mrclam_stream(data, robots[0], max_steps=10)
    known_capable = [s for s in systems if supports_known_association(s, probe)]
    no_known_mode = [s for s in systems if s not in known_capable]

    base = {"data": str(data), "max_steps": args.max_steps, "noise_scale": args.noise_scale}
    # calibration and filter options enter the job (and its resume key) only when given
    require(args.calibration_s >= 10.0 and math.isfinite(args.calibration_s), "--calibration-s",
            args.calibration_s, "a number of seconds >= 10")
    base |= {"corrections": args.corrections, "calibration_s": args.calibration_s}
    given = {
        "noise_window_s": args.noise_window,
        "sensor_bias_correction": args.sensor_bias_correction,
        "motion_compensation": args.motion_compensation,
        "landmark_density_per_m2": args.landmark_density,
        "gate_chi2": args.gate_chi2,
    }
    base |= {k: v for k, v in given.items() if v is not None}
    if "learned" in usable:
        from slam_gym.evaluation.core import learned_options

        learned = learned_options(str(Path(args.model_path).expanduser().resolve())
                                  if args.model_path else None)
    seeds = range(args.seed_start, args.seed_start + args.trials)
    jobs = []
    for seed in seeds:
        for robot in robots:
            scenario = f"{MRCLAM_PREFIX}{robot}"
            for s in systems:
                modes = [False, True] if (args.known_association and s in known_capable) else [
                    False]
                for known in modes:
                    opts = base | {"known_association": known,
                                   "fusion_interval_s": FUSION_INTERVAL_S}
                    if s in ("fastslam", "hybrid"):
                        opts["n_particles"] = args.particles
                    if s in ("ekf-submap", "hybrid") and args.optimise != "never":
                        opts["optimise"] = args.optimise  # in the resume key only when given
                    if s in ("ekf-submap", "hybrid") and args.robust_kernel is not None:
                        opts["robust_kernel"] = args.robust_kernel
                    jobs.append(Job("system", s, scenario, None, seed, opts))
            for p in usable:
                opts = base | {"n_particles": args.particles,
                               "decision_interval": DECISION_INTERVAL}
                if p == "learned":
                    opts |= learned
                opts |= {k: v for k, v in (("w_compute", args.w_compute),
                                           ("compute_clip_s", args.compute_clip_s))
                         if v is not None}
                jobs.append(Job("policy", p, scenario, None, seed, opts))
    require(bool(jobs), "--systems/--policies", "", "at least one system or usable policy")
    out = out_dir(args)
    rows = _execute(args, jobs, out)
    doc = write_summary(out, rows)
    notes = _mrclam_notes(args, skipped, no_known_mode, known_capable)
    table = write_real_table(out, rows, "mrclam", notes)
    figures = mrclam_figures(rows, data, out)
    compact = [_compact(r) for r in rows]
    emit(
        args,
        {"summary": doc, "rows": compact, "skipped_policies": skipped,
         "no_known_association_mode": no_known_mode, "figures": figures, "out": str(out)},
        [table, f"wrote {out / 'results.jsonl'}, summary.json, table.md, "
                f"{REAL_TABLE_FILENAME} and {len(figures)} figures"],
    )
    return errors_exit_code(args, rows)


def run_victoria_park(args) -> int:
    from slam_gym.evaluation import Job, write_summary

    _check_common(args)
    data = _data_dir(args.data, "victoria_park")
    systems = _systems(args.systems)
    require(bool(systems), "--systems", args.systems, "at least one system")
    opts = {"data": str(data), "max_steps": args.max_steps,
            "fusion_interval_s": FUSION_INTERVAL_S}
    jobs = [
        Job("system", s, VP_SCENARIO, None, seed,
            opts | ({"n_particles": args.particles} if s in ("fastslam", "hybrid") else {}))
        for seed in range(args.seed_start, args.seed_start + args.trials)
        for s in systems
    ]
    out = out_dir(args)
    rows = _execute(args, jobs, out)
    doc = write_summary(out, rows)
    notes = [
        "Path error: RMSE between the estimated path (interpolated at the GPS times) and the "
        "GPS fixes after the best rigid SE(2) fit; GPS jumps are not rejected (median given).",
        "Trees: confirmed features (p(exists) >= 0.95) at the end. NEES, success and map "
        "error are undefined (no pose or landmark truth) and left out.",
        f"Sub-map systems fuse every {FUSION_INTERVAL_S:g} s (BB); particles: "
        f"{args.particles}.",
    ]
    table = write_real_table(out, rows, "victoria-park", notes)
    figures = victoria_park_figures(rows, data, out)
    emit(
        args,
        {"summary": doc, "rows": [_compact(r) for r in rows], "figures": figures,
         "out": str(out)},
        [table, f"wrote {out / 'results.jsonl'}, summary.json, table.md, "
                f"{REAL_TABLE_FILENAME} and {len(figures)} figures"],
    )
    return errors_exit_code(args, rows)


def _mrclam_notes(args, skipped, no_known_mode, known_capable) -> list[str]:
    notes = [
        "Map error: mean distance of the confirmed features (p(exists) >= 0.95) at the end to "
        "the Landmark_Groundtruth positions they stand for (CM); pose RMSE over every step "
        "against motion capture, and over the steps after the calibration part only (held "
        "out); ANEES of the 3-dof pose (consistent: about 3).",
        f"Sub-map systems fuse every {FUSION_INTERVAL_S:g} s (BB); particles: {args.particles}; "
        f"sensor noise scale: {args.noise_scale:g}; runs go on after BB's failure criterion "
        "(success = never met).",
        f"Calibration: every model estimated on the first {args.calibration_s:g} s of each "
        "recording; corrections "
        + ("on (odometry delay and gains, time stamps, motion, camera bias, correlated noise)"
           if args.corrections else "off (plain stream, noise = RMS of the residuals)")
        + ("" if args.noise_window is None
           else f"; white-noise rule over {args.noise_window:g} s windows")
        + {True: "; camera bias corrected", False: "; camera bias not corrected",
           None: ""}[args.sensor_bias_correction]
        + {True: "; measurements moved to the step end", False: "; no motion compensation",
           None: ""}[args.motion_compensation]
        + ". FastSLAM (FASTSLAM, HYBRID): landmark density "
        + ("default" if args.landmark_density is None else f"{args.landmark_density:g} /m^2")
        + ", gate " + ("default" if args.gate_chi2 is None else f"chi2 {args.gate_chi2:g}")
        + ".",
    ]
    if args.known_association:
        notes.append(
            f"Known association: {', '.join(known_capable) or 'no system'}; without such a "
            f"mode: {', '.join(no_known_mode) or 'none'}."
        )
    for name, reason in skipped.items():
        notes.append(f"Policy {name} skipped: {reason}")
    return notes


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


def _mrclam_result(episode, stream, robot: int, association: str) -> dict:
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
        noise_window_s=noise_window_s, sensor_bias_correction=sensor_bias_correction,
        motion_compensation=motion_compensation, corrections=corrections,
        calibration_s=calibration_s,
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
    row = _mrclam_result(episode, stream, robot, "known" if known_association else "unknown")
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
    row = _mrclam_result(env.episode, env.stream, robot, "unknown")
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
    from slam_gym.evaluation.core import _seeds
    from slam_gym.systems import SUBMAP_SYSTEMS, make_system

    stream = load_victoria_park(data, max_steps=max_steps)
    system = make_system(name, stream, _seeds(seed), n_particles=n_particles)
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


# --------------------------------------------------------------------------- tables
def _compact(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in ("figure", "traceback")}


def _label(row: dict) -> str:
    if row.get("policy") is not None:
        return f"{row.get('driven_system') or 'hybrid'} + {row['policy']}"
    return str(row.get("system"))


def _mean(rows, key):
    values = [float(r[key]) for r in rows
              if isinstance(r.get(key), (int, float)) and not isinstance(r.get(key), bool)
              and math.isfinite(float(r[key]))]
    return statistics.fmean(values) if values else None


def _fmt(x, digits=2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _group(rows, key_fn) -> dict:
    groups: dict = {}
    for row in rows:
        groups.setdefault(key_fn(row), []).append(row)
    return groups


def _md(header, body) -> str:
    def line(cells):
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    align = "|" + "|".join(["---"] * 3 + ["---:"] * (len(header) - 3)) + "|"
    return "\n".join([line(header), align, *map(line, body)])


def mrclam_table(rows) -> str:
    """Per (system or policy, robot, association): the MRCLAM metrics (means over seeds),
    then the means over robots. A policy whose model does not match the code (rows'
    ``model_matches_code``) is marked with a footnote."""
    from slam_gym.evaluation.summary import MISMATCH_MARK, group_provenance, provenance_footnote

    ok = [r for r in rows if r.get("status") == "ok"]
    header = ["system", "robot", "association", "n", "map error (m)", "pose RMSE (m)",
              "pose RMSE held out (m)", "ANEES", "NEES in band", "BB success", "features",
              "spurious", "missed", "completeness", "fusions", "filter time (s)", "wall time (s)"]

    def cells(label, robot, assoc, members):
        successes = [bool(r["success"]) for r in members if r.get("success") is not None]
        if any(r.get("model_matches_code") is False for r in members):
            label = f"{label} {MISMATCH_MARK}"
        return [
            label, robot, assoc, len(members),
            _fmt(_mean(members, "map_error_m")), _fmt(_mean(members, "pose_rmse_m")),
            _fmt(_mean(members, "pose_rmse_held_out_m")),
            _fmt(_mean(members, "anees"), 1),
            "–" if _mean(members, "nees_in_band_fraction") is None
            else f"{100 * _mean(members, 'nees_in_band_fraction'):.0f} %",
            f"{sum(successes)}/{len(successes)}",
            _fmt(_mean(members, "n_features"), 1), _fmt(_mean(members, "n_spurious"), 1),
            _fmt(_mean(members, "n_missed"), 1), _fmt(_mean(members, "completeness")),
            _fmt(_mean(members, "n_fusions"), 0),
            _fmt(_mean(members, "filter_time_s"), 1), _fmt(_mean(members, "wall_time_s"), 1),
        ]

    per_robot = _group(ok, lambda r: (_label(r), r.get("robot"), r.get("association")))
    body = [cells(lab, rob, assoc, m) for (lab, rob, assoc), m in per_robot.items()]
    overall = _group(ok, lambda r: (_label(r), r.get("association")))
    body_all = [cells(lab, "all", assoc, m) for (lab, assoc), m in overall.items()]
    errors = [r for r in rows if r.get("status") != "ok"]
    parts = ["## Per robot", "", _md(header, body), "", "## Mean over robots", "",
             _md(header, body_all)]
    footnote = provenance_footnote([group_provenance(m) for m in overall.values()])
    if footnote:
        parts += ["", footnote]
    if errors:
        parts += ["", f"{len(errors)} runs errored (excluded): "
                  + "; ".join(f"{_label(r)} {r.get('scenario')}: {r.get('error')}"
                              for r in errors[:5])]
    return "\n".join(parts)


def victoria_park_table(rows) -> str:
    """Per system: path error against GPS after SE(2) alignment, trees, run time."""
    ok = [r for r in rows if r.get("status") == "ok"]
    header = ["system", "steps", "seeds", "path RMSE vs GPS (m)", "median (m)",
              "final error (m)", "trees mapped", "fusions", "filter time (s)",
              "real-time factor", "wall time (s)"]
    body = []
    for label, members in _group(ok, _label).items():
        body.append([
            label, _fmt(_mean(members, "iterations"), 0), len(members),
            _fmt(_mean(members, "gps_rmse_m")), _fmt(_mean(members, "gps_median_error_m")),
            _fmt(_mean(members, "final_pose_error_m")), _fmt(_mean(members, "n_trees"), 0),
            _fmt(_mean(members, "n_fusions"), 0), _fmt(_mean(members, "filter_time_s"), 1),
            _fmt(_mean(members, "real_time_factor"), 1), _fmt(_mean(members, "wall_time_s"), 1),
        ])
    out = _md(header, body)
    errors = [r for r in rows if r.get("status") != "ok"]
    if errors:
        out += "\n\n" + f"{len(errors)} runs errored (excluded): " + "; ".join(
            f"{_label(r)}: {r.get('error')}" for r in errors[:5])
    return out


PAIRED_REFERENCE = "fixed-10s-optimise"


def mrclam_paired_table(rows) -> str | None:
    """Every interface policy against ``fixed-10s-optimise`` on the same robots and seeds (all
    runs, BB's failure rule or not): map error, pose RMSE and interface CPU, each the paired
    difference with its t 95 % interval (:func:`slam_gym.evaluation.front.compare_all_runs`).
    None when the reference did not run or any policy run did not finish."""
    from slam_gym.evaluation.front import compare_all_runs

    policy_rows = [r for r in rows if r.get("driven_system") == "hybrid"]
    if any(r.get("status") != "ok" for r in policy_rows):
        return None
    by_policy: dict[str, list] = {}
    for r in policy_rows:
        by_policy.setdefault(r["policy"], []).append(r)
    reference = by_policy.get(PAIRED_REFERENCE)
    if reference is None:
        return None

    def ci(c, key, digits):
        lo, hi = c[f"{key}_diff_ci"] or (math.nan, math.nan)
        return f"{c[f'{key}_diff']:+.{digits}f} [{lo:+.{digits}f}, {hi:+.{digits}f}]"

    lines = [f"Paired against `{PAIRED_REFERENCE}` (same robot and seed; every run):", "",
             "| policy | runs | map error (m) | diff (m) | pose RMSE (m) | diff (m) "
             "| interface CPU (s) | CPU ratio | fusions | optimisations |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, members in by_policy.items():
        try:
            c = compare_all_runs(members, reference)
        except ValueError:  # not the reference's runs (an interrupted run): no pairing
            continue
        lines.append(
            f"| {name} | {c['n_runs']} | {c['map_error_m']:.2f} | {ci(c, 'map_error_m', 2)} "
            f"| {c['pose_rmse_m']:.2f} | {ci(c, 'pose_rmse_m', 2)} | {c['interface_cpu_s']:.2f} "
            f"| {c['interface_cpu_ratio']:.2f} | {c['n_fusions']:.0f} "
            f"| {c['n_optimisations']:.0f} |")
    return "\n".join(lines)


def write_real_table(out, rows, target: str, notes) -> str:
    """Write ``real_table.md`` (title, table, the policies paired with
    ``fixed-10s-optimise`` when it ran, notes); returns its text."""
    if target == "mrclam":
        title, table = "# MRCLAM: systems on real data", mrclam_table(rows)
        paired = mrclam_paired_table(rows)
        if paired:
            table = f"{table}\n\n{paired}"
    else:
        title, table = "# Victoria Park: systems on real data", victoria_park_table(rows)
    text = "\n".join([title, "", table, "", *(f"- {n}" for n in notes), ""])
    path = Path(out) / REAL_TABLE_FILENAME
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return text


# --------------------------------------------------------------------------- figures
def mrclam_figures(rows, data, out) -> dict:
    """One map per system/policy (unknown association, first seed) on the first robot run."""
    from slam_gym.datasets import read_mrclam
    from slam_gym.evaluation import plot_run_map

    figures = {}
    ok = [r for r in rows if r.get("status") == "ok" and r.get("figure")
          and r.get("association") == "unknown"]
    if not ok:
        return figures
    robot = ok[0]["robot"]
    landmarks = read_mrclam(data, robot).landmarks_xy
    for row in ok:
        label = _label(row)
        key = f"{label} robot{robot}"
        if row["robot"] != robot or key in figures:
            continue
        fig = row["figure"]
        safe = label.replace(" + ", "_").replace(" ", "_")
        figures[key] = str(plot_run_map(
            Path(out) / f"mrclam_map_{safe}_robot{robot}.png",
            landmarks_true=landmarks,
            landmark_means=np.asarray(fig["landmark_means"]).reshape(-1, 2),
            landmark_covs=np.asarray(fig["landmark_covs"]).reshape(-1, 2, 2),
            path_true=np.asarray(fig["true_path_xy"]).reshape(-1, 2),
            path_est=np.asarray(fig["est_path_xy"]).reshape(-1, 2),
            title=f"MRCLAM robot {robot}: {label} (map error "
                  f"{_fmt(row.get('map_error_m'))} m)",
        ))
    return figures


def plot_victoria_park_map(path, *, gps_xy, est_path_xy, trees_xy, title=None) -> Path:
    """The estimated map (trees) and path over the GPS fixes, in the GPS frame (after the SE(2)
    alignment); headless (Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 7.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    gps_xy = np.asarray(gps_xy, dtype=float).reshape(-1, 2)
    est = np.asarray(est_path_xy, dtype=float).reshape(-1, 2)
    trees = np.asarray(trees_xy, dtype=float).reshape(-1, 2)
    ax.scatter(gps_xy[:, 0], gps_xy[:, 1], s=3, color="0.55", label="GPS fixes", zorder=2)
    ax.plot(est[:, 0], est[:, 1], color="#1f77b4", lw=0.9, label="estimated path (aligned)",
            zorder=3)
    ax.scatter(trees[:, 0], trees[:, 1], marker="^", s=12, color="#2ca02c",
               label=f"mapped trees ({len(trees)})", zorder=4)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3, linewidth=0.6)
    ax.set_xlabel("x (m, GPS frame)")
    ax.set_ylabel("y (m, GPS frame)")
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def victoria_park_figures(rows, data, out) -> dict:
    """One PNG per system (first seed): the map over the GPS track."""
    from slam_gym.datasets import read_victoria_park

    gps = None
    figures = {}
    for row in rows:
        if row.get("status") != "ok" or not row.get("figure") or row["system"] in figures:
            continue
        if gps is None:
            rec = read_victoria_park(data)
            gps = rec.gps.copy()
            gps[:, 0] -= rec.inputs[0, 0]
        t0, t1 = row["figure"]["gps_span_s"]
        inside = (gps[:, 0] >= t0) & (gps[:, 0] <= t1)
        figures[row["system"]] = str(plot_victoria_park_map(
            Path(out) / f"victoria_park_map_{row['system']}.png",
            gps_xy=gps[inside, 1:3],
            est_path_xy=row["figure"]["est_path_xy"],
            trees_xy=row["figure"]["trees_xy"],
            title=f"Victoria Park: {row['system']}, path RMSE vs GPS "
                  f"{_fmt(row.get('gps_rmse_m'))} m, {row.get('n_trees')} trees",
        ))
    return figures
