"""``slam-gym reproduce mrclam`` / ``reproduce victoria-park``: the systems on real data.

Both data sets are played as :class:`~slam_gym.stream.Stream` s (docs/ARCHITECTURE.md, "The data
stream") through the
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
from pathlib import Path

import numpy as np

from filters.validation import require
from slam_gym.commands.common import emit, out_dir
from slam_gym.commands.real_tables import (
    REAL_TABLE_FILENAME,
    compact_row,
    mrclam_figures,
    victoria_park_figures,
    write_real_table,
)
from slam_gym.commands.runs import (
    add_run_options,
    check_run_options,
    errors_exit_code,
    int_list,
    name_list,
    run_options,
)
from slam_gym.datasets.location import default_data_dir
from slam_gym.datasets.mrclam import DEFAULT_CALIBRATION_S, MrclamOptions
from slam_gym.evaluation.core import OPTIMISE_MODES
from slam_gym.evaluation.real_data import (
    DECISION_INTERVAL,
    DEFAULT_PARTICLES,
    FUSION_INTERVAL_S,
    MRCLAM_PREFIX,
    VP_SCENARIO,
    run_real_job,
)

logger = logging.getLogger(__name__)
REAL_SYSTEMS = ("ekf-slam", "fastslam", "ekf-submap", "hybrid")
DEFAULT_POLICIES = ("fixed-10s", "esdf-innovation", "learned")


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
    robots = [check_robot(r) for r in int_list(args.robots, "robots")]
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
    # the calibration options, validated as the loader and the env validate them
    MrclamOptions(calibration_s=args.calibration_s, noise_window_s=args.noise_window,
                  corrections=args.corrections,
                  sensor_bias_correction=args.sensor_bias_correction,
                  motion_compensation=args.motion_compensation,
                  names={"calibration_s": "--calibration-s", "noise_window_s": "--noise-window",
                         "corrections": "--no-corrections",
                         "sensor_bias_correction": "--sensor-bias-correction",
                         "motion_compensation": "--motion-compensation"})
    for flag, value in (("--landmark-density", args.landmark_density),
                        ("--gate-chi2", args.gate_chi2)):
        require(value is None or (value > 0 and math.isfinite(value)), flag, value,
                "a number > 0")
    usable, skipped = available_policies(policy_names, args.model_path)
    probe = mrclam_stream(data, robots[0], max_steps=10)
    known_capable = [s for s in systems if supports_known_association(s, probe)]
    no_known_mode = [s for s in systems if s not in known_capable]

    base = {"data": str(data), "max_steps": args.max_steps, "noise_scale": args.noise_scale}
    # calibration and filter options enter the job (and its resume key) only when given
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
    compact = [compact_row(r) for r in rows]
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
        {"summary": doc, "rows": [compact_row(r) for r in rows], "figures": figures,
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
