"""``slam-gym speed``: iterations per second, ratio to real time, cost per particle-iteration,
the env's decisions per second (at 100 and 500 particles, resets included), the env's first
reset in a fresh process, and ESDF's per-update time as its state grows.

Times are CPU times of this process (``time.process_time``, one BLAS thread): the figures are
one core's throughput even when other work shares the machine. A system's time covers the whole
run (filter, fusions and the episode's metrics), so it slightly overstates the filter's own cost.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from slam_gym.commands.common import add_common_options, emit, out_dir, to_jsonable
from slam_gym.commands.runs import int_list, name_list

logger = logging.getLogger(__name__)

PARTICLE_SYSTEMS = ("fastslam", "hybrid")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "speed",
        help="measure filter and env throughput",
        description="Iterations per second and ratio to real time per system, particle count "
        "and clutter level on brooks-bailey; decisions per second of the env; ESDF update time "
        "against state size. One process, one core.",
    )
    p.add_argument("--systems", default="fastslam,ekf-submap,hybrid",
                   help="comma-separated systems to time (slam_gym.systems)")
    p.add_argument("--particles", default="100,500,2000", metavar="P,...",
                   help="comma-separated particle counts to time them at")
    p.add_argument("--clutter-levels", default="0,1,2,3", metavar="L,...",
                   help="comma-separated clutter levels to time them at")
    p.add_argument("--iterations", type=int, default=None,
                   help="iterations per measurement (default: the whole path)")
    p.add_argument("--seed", type=int, default=0, metavar="S",
                   help="the world's seed of the measurements")
    p.add_argument("--env-decisions", type=int, default=1000,
                   help="decisions for the env throughput at each --env-particles count, over "
                   "as many episodes as they take, resets included (0 to skip)")
    p.add_argument("--env-particles", default="100,500",
                   help="particle counts of the env throughput (default 100,500)")
    p.add_argument("--skip-first-reset", action="store_true",
                   help="skip timing the env's import and first reset in a fresh process")
    p.add_argument("--skip-paper-episode", action="store_true",
                   help="skip timing one whole env episode at the paper's 500 particles")
    p.add_argument("--skip-esdf", action="store_true",
                   help="skip timing the ESDF update against the state size")
    p.add_argument("--calibrate-compute", action="store_true",
                   help="only fit the env's compute-cost model (slam_gym.compute_cost) to "
                   "measured CPU time and print its coefficients and correlation")
    p.add_argument("--calibration-seeds", default="0,1",
                   help="worlds of the compute calibration (default 0,1)")
    p.add_argument("--env-schedules", default=",".join(ENV_SCHEDULES),
                   help="action schedules timed in the env at the paper's 500 particles, "
                   f"--env-decisions each (among {', '.join(ENV_SCHEDULES)}; '' to skip)")
    p.add_argument("--schedule-particles", type=int, default=500,
                   help="particles of the env schedules (default 500, the paper's)")
    p.add_argument("--full-path-episodes", type=int, default=2,
                   help="episodes that run the whole path (failed ones are left out and "
                   f"counted) timed under each of {', '.join(FULL_PATH_SCHEDULES)} at "
                   "--schedule-particles, with the CPU time of each one's last optimisation "
                   "(0 to skip)")
    p.add_argument("--optimise-counts", default="10,20,40,80",
                   help="stored sub-map counts at which optimise() is timed ('' to skip)")
    p.add_argument("--optimise-seeds", default="0,1,2",
                   help="worlds of the optimise() timing (default 0,1,2)")
    p.add_argument("--quick", action="store_true",
                   help="the regression check (<= 60 s): HYBRID at 500 particles, the four "
                   "env schedules on a few hundred decisions, optimise() at 10/20/40 sub-maps on "
                   "one world; writes speed_record.json")
    p.add_argument("--tasks", default="",
                   help="env ids (comma-separated; 'all' for issue 48's tasks, "
                   "TASK_ENV_VARIANTS) to time over one whole episode each under "
                   "fixed-10s-optimise's schedule on training-time world 900000: decisions/s, "
                   "the episode's CPU, and the CPU per decision by third of the episode against "
                   "the stored sub-maps; recorded in speed_record.json with --quick")
    p.add_argument("--env", default=None, metavar="ID",
                   help="an env id timed like --tasks' (one whole episode), with --env-kwargs")
    p.add_argument("--env-kwargs", nargs="+", default=None, metavar="KEY:VALUE",
                   help="keyword arguments of --env's gym.make over the id's own (KEY:VALUE, "
                   "VALUE read as JSON)")
    p.add_argument("--compare", metavar="BASELINE", default=None,
                   help="a speed record to compare with: prints every figure's speed ratio "
                   "and exits 1 when one falls below half of the baseline's")
    add_common_options(p, default_out="out/speed")
    p.set_defaults(run=run)


def measure_system(name, level, n_particles, seed, iterations):
    """Run ``name`` on BB's schedule without stopping at failure; timing of the filter only."""
    from slam_gym.evaluation.core import make_job_stream, run_system

    stream = make_job_stream("brooks-bailey", level, seed, n_steps=iterations)
    start, cpu_start = time.perf_counter(), time.process_time()
    episode = run_system(name, stream, seed, n_particles=n_particles, stop_on_failure=False)
    cpu_s = time.process_time() - cpu_start
    wall = time.perf_counter() - start
    iters = episode.iteration
    row = {
        "system": name,
        "clutter_level": level,
        "n_particles": n_particles if name in PARTICLE_SYSTEMS else None,
        "iterations": iters,
        "cpu_time_s": cpu_s,
        "wall_time_s": wall,
        "iterations_per_s": iters / cpu_s,
        "real_time_ratio": iters * stream.dt_s / cpu_s,
        "ms_per_iteration": 1e3 * cpu_s / iters,
    }
    if name in PARTICLE_SYSTEMS:
        row["us_per_particle_iteration"] = 1e6 * cpu_s / (iters * n_particles)
    return row


ENV_SCHEDULES = {
    "fixed-10s": "fuse every 10 s (BB), never optimise",
    "fixed-10s-optimise": "fuse every 10 s and optimise with every fusion",
    "optimise-every-decision": "fuse every 10 s, ask to optimise at every decision (9 in 10 "
    "redundant: nothing fused since the last)",
    "fuse-optimise-every-decision": "fuse and optimise at every decision: the costliest a "
    "policy can choose (the graph grows by one sub-map a second)",
}
"""The action schedules :func:`measure_env` times (the rules' decisions without their feature
logic, so only the env's own cost is measured)."""


def schedule_action(schedule: str, iteration: int) -> np.ndarray:
    at_fusion = int(iteration % 100 == 0)  # BB's 10 s at 10 Hz, decisions every 10 iterations
    return np.array({
        "fixed-10s": (at_fusion, 0),
        "fixed-10s-optimise": (at_fusion, at_fusion),
        "optimise-every-decision": (at_fusion, 1),
        "fuse-optimise-every-decision": (1, 1),
    }[schedule])


TASK_SEED = 900000
"""The training-time world :func:`measure_task` times each task on."""


TASK_CLUTTER_LEVEL = 2
"""The clutter level a task is timed at when its episodes draw one (the env's default level,
what the speed record has timed the tasks at since issue 47)."""


def measure_task(env_id: str, seed: int = TASK_SEED, schedule: str = "fixed-10s-optimise",
                 **config) -> dict:
    """One whole episode of env ``env_id`` (a registered simulated id such as an issue-48 task,
    or a :class:`~slam_gym.envs.spec.ResolvedEnv`; the id's options unless ``config`` says
    otherwise) on world ``seed`` under ``schedule`` (:data:`ENV_SCHEDULES`): decisions per CPU
    second (the reset included), the episode's CPU, and per third of the episode the mean CPU
    per decision and the stored sub-maps and global features at its end, so a cost per decision
    that grows faster than the map shows."""
    from slam_gym.envs.spec import ResolvedEnv, resolve_env

    spec = env_id if isinstance(env_id, ResolvedEnv) else resolve_env(env_id, config,
                                                                       per_decision=True)
    env_id = spec.env_id
    env = spec.make().unwrapped
    options = {"world_seed": int(seed)}
    if env.episode_levels is not None:
        options["clutter_level"] = TASK_CLUTTER_LEVEL
    start = time.process_time()
    env.reset(seed=int(seed), options=options)
    reset_s = time.process_time() - start
    step_s, submaps, features = [], [], []
    while True:
        t0 = time.process_time()
        _, _, terminated, truncated, info = env.step(
            schedule_action(schedule, env.episode.iteration))
        step_s.append(time.process_time() - t0)
        submaps.append(info["features"]["stored_submaps"])
        features.append(len(env.system.landmarks().ids))
        if terminated or truncated:
            break
    cpu_s = reset_s + float(np.sum(step_s))
    n = len(step_s)
    thirds = []
    for k in range(3):
        part = slice(k * n // 3, (k + 1) * n // 3)
        if part.stop > part.start:
            thirds.append({"ms_per_decision": 1e3 * float(np.mean(step_s[part])),
                           "stored_submaps_at_end": int(submaps[part.stop - 1]),
                           "global_features_at_end": int(features[part.stop - 1])})
    return {"env": env_id, "schedule": schedule, "seed": int(seed),
            "n_particles": env.config.n_particles, "clutter_level": env.config.clutter_level,
            "decisions": n, "failed": bool(env.episode.failure.failed), "reset_cpu_s": reset_s,
            "episode_cpu_s": cpu_s, "decisions_per_s": n / cpu_s, "thirds": thirds}


def measure_env(decisions, seed, schedule: str = "fixed-10s", **config):
    """Decisions per second of SlamGym/HybridSLAM-v1 (its defaults unless ``config`` says
    otherwise), resets included, deciding by ``schedule`` (:data:`ENV_SCHEDULES`);
    ``decisions=None`` runs exactly one whole episode. Resets draw new worlds (no world is
    replayed from the cache)."""
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    if schedule not in ENV_SCHEDULES:
        raise ValueError(f"schedule={schedule!r} is invalid: must be one of "
                         f"{tuple(ENV_SCHEDULES)}")
    env = HybridSLAMEnv(**config)
    start = time.process_time()
    env.reset(seed=seed)
    done_decisions, resets = 0, 1
    while decisions is None or done_decisions < decisions:
        action = schedule_action(schedule, env.episode.iteration)
        _, _, terminated, truncated, _ = env.step(action)
        done_decisions += 1
        if terminated or truncated:
            if decisions is None:
                break
            env.reset()
            resets += 1
    cpu = time.process_time() - start
    return {
        "env": "SlamGym/HybridSLAM-v1",
        "schedule": schedule,
        "n_particles": env.config.n_particles,
        "clutter_level": env.config.clutter_level,
        "decision_interval": env.config.decision_interval,
        "decisions": done_decisions,
        "resets": resets,
        "iterations": env.episode.iteration,
        "cpu_time_s": cpu,
        "decisions_per_s": done_decisions / cpu,
    }


FULL_PATH_SCHEDULES = ("fixed-10s", "fixed-10s-optimise")
"""The schedules :func:`measure_full_path` times (issue 40 item 4)."""

FULL_PATH_SEEDS = tuple(range(20))
"""Where :func:`measure_full_path` looks for episodes that run the whole path: ``reset(seed)``
for these in turn (at clutter level 2 and 500 particles most of them do)."""


def _snapshot_before_optimising(system, excluded_s: list):
    """Make ``system``'s estimator keep a copy of itself (its front-end shared: an optimisation
    does not touch it) before each optimisation, in ``system.snapshot``; the copying's CPU
    seconds are added to ``excluded_s[0]``."""
    estimator = system.estimator
    optimise = estimator.optimise

    def snapshotting_optimise(*args, **kwargs):
        start = time.process_time()
        snapshot = copy.deepcopy(estimator, {id(estimator.front_end): estimator.front_end})
        del snapshot.optimise  # the copy's own method, not this wrapper
        system.snapshot = snapshot
        excluded_s[0] += time.process_time() - start
        return optimise(*args, **kwargs)

    estimator.optimise = snapshotting_optimise


def measure_full_path(schedule: str, episodes: int, *, n_particles: int = 500,
                      seeds=FULL_PATH_SEEDS, repeats: int = 7, **config):
    """Decisions per second of SlamGym/HybridSLAM-v1 over ``episodes`` episodes that run the
    whole path under ``schedule`` (resets included; an episode that fails is left out and
    counted), where a learner's episodes spend most of their decisions: the graph and the
    back-end grow along the path, so the mixed figure of :func:`measure_env`, which includes
    short failed episodes, flatters them. With a schedule that optimises, also the CPU time of
    the last optimisation of the last whole path: the median of ``repeats`` reruns from a copy
    of the system taken just before it (the copies are not counted in the decisions' time).
    ``config``: other options of the env (e.g. ``n_steps`` in tests: then the cut path is the
    whole path)."""
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    env = HybridSLAMEnv(n_particles=n_particles, **config)
    full = failed = decisions = 0
    cpu_s = 0.0
    last = None
    for seed in seeds:
        if full == episodes:
            break
        excluded_s = [0.0]
        start = time.process_time()
        env.reset(seed=int(seed))
        _snapshot_before_optimising(env.system, excluded_s)
        n = 0
        while True:
            action = schedule_action(schedule, env.episode.iteration)
            _, _, terminated, truncated, _ = env.step(action)
            n += 1
            if terminated or truncated:
                break
        episode_cpu_s = time.process_time() - start - excluded_s[0]
        if env.episode.failure.failed:
            failed += 1
            continue
        full += 1
        decisions += n
        cpu_s += episode_cpu_s
        last = getattr(env.system, "snapshot", None)
    row = {
        "env": "SlamGym/HybridSLAM-v1", "schedule": schedule, "n_particles": n_particles,
        "clutter_level": env.config.clutter_level, "full_path_episodes": full,
        "failed_episodes": failed, "decisions": decisions, "cpu_time_s": cpu_s,
        "decisions_per_s": decisions / cpu_s if cpu_s > 0 else None,
        "last_optimisation_ms": None,
    }
    if last is not None:
        times = []
        for _ in range(repeats + 1):  # the first, untimed: the copy's caches as in the episode
            system = copy.deepcopy(last, {id(last.front_end): last.front_end})
            start = time.process_time()
            result = system.optimise()
            times.append(time.process_time() - start)
        n_features = len(result.warm_start["features"])
        row.update(
            last_optimisation_ms=1e3 * float(np.median(times[1:])),
            last_optimisation_repeats=repeats, last_optimisation_submaps=result.n_submaps,
            last_optimisation_variables=3 * result.n_submaps + 2 * n_features,
            last_optimisation_iterations=result.iterations,
        )
    return row


def measure_optimise(seeds, counts, steps_per_fusion: int = 50, n_particles: int = 100,
                     n_steps: int | None = None):
    """CPU time of ``optimise()`` against the number of stored sub-maps on BB's world.

    HYBRID (``n_particles``: the optimiser's cost does not depend on them) fuses every
    ``steps_per_fusion`` iterations (5 s, so that one path stores ~80 sub-maps) and optimises
    after every fusion, as ``fixed-10s-optimise`` does (each optimisation warm-started from the
    previous optimum); then once more with nothing fused (redundant). Returns per count ``n`` the
    median CPU ms, iterations and redundant-call microseconds of the optimisations with
    ``n - 2 .. n + 2`` sub-maps, over the worlds ``seeds`` (their first ``n_steps`` iterations
    if given)."""
    from slam_gym.systems import make_system
    from slam_gym.world import make_stream

    samples = []
    for seed in seeds:
        stream = make_stream("brooks-bailey", seed=int(seed), clutter_level=2, n_steps=n_steps)
        system = make_system("hybrid", stream, np.random.default_rng(int(seed)),
                             n_particles=n_particles).estimator
        for i, step in enumerate(stream):
            system.predict(step.odometry, step.dt_s)
            if step.scanned:
                system.update(step.z)
            if (i + 1) % steps_per_fusion == 0:
                system.fuse()
                start = time.process_time()
                result = system.optimise()
                cpu = time.process_time() - start
                start = time.process_time()
                again = system.optimise()
                redundant_cpu = time.process_time() - start
                assert again.redundant  # nothing fused since: the optimum already applied
                samples.append((len(system.submaps), cpu, result.iterations, redundant_cpu))
    rows = []
    for n in counts:
        near = [s for s in samples if abs(s[0] - n) <= 2]
        if not near:
            continue
        rows.append({
            "stored_submaps": int(n),
            "optimisations": len(near),
            "median_ms": 1e3 * float(np.median([s[1] for s in near])),
            "max_ms": 1e3 * float(np.max([s[1] for s in near])),
            "median_iterations": float(np.median([s[2] for s in near])),
            "redundant_median_us": 1e6 * float(np.median([s[3] for s in near])),
        })
    return rows


FIRST_RESET_SCRIPT = """
import json, time
wall, cpu = time.perf_counter(), time.process_time()
from slam_gym.envs.hybrid_slam import HybridSLAMEnv
import_wall, import_cpu = time.perf_counter() - wall, time.process_time() - cpu
env = HybridSLAMEnv(n_particles={n_particles})
env.reset(seed={seed})
print(json.dumps({{"import_wall_s": import_wall, "import_cpu_s": import_cpu,
                  "first_reset_wall_s": time.perf_counter() - wall - import_wall,
                  "first_reset_cpu_s": time.process_time() - cpu - import_cpu}}))
"""


def measure_first_reset(seed, n_particles=500):
    """Import and first reset of the env in a fresh Python process (wall and CPU seconds): what
    a new worker pays before its first decision. Compiled filter code comes from numba's cache
    (``__pycache__``) when an earlier process wrote it; the very first run compiles it."""
    import slam_gym

    code = FIRST_RESET_SCRIPT.format(n_particles=int(n_particles), seed=int(seed))
    root = str(Path(slam_gym.__file__).resolve().parents[1])  # this checkout, not another
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True, env={**os.environ, "PYTHONPATH": path})
    row = json.loads(done.stdout.strip().splitlines()[-1])
    row["n_particles"] = int(n_particles)
    return row


PAPER_ENV_CONFIG = {"n_particles": 500}
"""BB's configuration in the env: 500 particles (the default clutter level 2, brooks-bailey)."""


ESDF_GROWTH_SCENARIO = {
    "world_size_m": 480.0,
    "n_landmarks": int(round(0.02 * 480.0**2)),
    "path_length_m": 1800.0,
    "loop_fraction": 1.0,
}
"""CM's world and sensor scaled up: one 1800 m loop (no revisits until its very end), so the
ESDF state grows about tenfold while the per-update work should stay the same."""


def measure_esdf(seed):
    """ESDF per-update time against state size, binned into five state-size ranges."""
    from filters.esdf import ESDF
    from slam_gym.world import make_stream

    stream = make_stream("conte-martinelli-1", seed=seed, **ESDF_GROWTH_SCENARIO)
    f = ESDF(stream.sensor, stream.clutter, stream.odometry_noise, initial_pose=stream.initial_pose)
    rows = []
    for step in stream:
        f.predict(step.odometry, step.dt_s)
        if len(step.z):
            start = time.process_time()
            f.update(step.z, ids=step.truth.landmark_ids)
            rows.append((f.state_size, time.process_time() - start))
    dims = np.array([d for d, _ in rows])
    times = np.array([t for _, t in rows])
    bins = np.quantile(dims, np.linspace(0.0, 1.0, 6))
    table = []
    for lo, hi in zip(bins[:-1], bins[1:], strict=True):
        sel = (dims >= lo) & (dims <= hi)
        table.append({
            "state_dim_min": int(lo),
            "state_dim_max": int(hi),
            "updates": int(sel.sum()),
            "ms_per_update_median": 1e3 * float(np.median(times[sel])),
            "ms_per_update_mean": 1e3 * float(np.mean(times[sel])),
        })
    return table


CALIBRATION_RUNS: tuple[tuple[str, str, dict], ...] = (
    ("SlamGym/HybridSLAM-v1", "fixed-interval", {"interval_s": 10.0, "optimise": "every-fusion"}),
    ("SlamGym/HybridSLAM-v1", "always", {"optimise": "never"}),
    ("SlamGym/HybridSLAM-Relative-v1", "fixed-interval",
     {"interval_s": 10.0, "optimise": "every-fusion"}),
    ("SlamGym/HybridSLAM-Relative-v1", "always", {"optimise": "never"}),
    ("SlamGym/EKFSubmap-v1", "fixed-interval", {"interval_s": 10.0, "optimise": "every-fusion"}),
)
"""(env id, policy, options) whose episodes the calibration times: every kind of work, over the
sizes an episode reaches (optimising at every fusion makes the graph grow to the whole path)."""


def collect_records(seeds, n_particles: int = 500, progress=None) -> list[tuple[str, float, float]]:
    """Run :data:`CALIBRATION_RUNS` on worlds ``seeds`` and return the env's ``(kind, ops,
    measured CPU s)`` records. ``progress``: an optional callable run once per episode."""
    import gymnasium as gym

    import policies

    records = []
    for env_id, name, options in CALIBRATION_RUNS:
        for seed in seeds:
            env = gym.make(f"slam_gym:{env_id}", n_particles=n_particles)
            policy = policies.make(name, **options)
            obs, info = env.reset(seed=int(seed))
            policy.reset()
            done = False
            while not done:
                obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
                done = terminated or truncated
            records.extend(env.unwrapped.compute_records)
            env.close()
            if progress is not None:
                progress()
    return records


def calibrate_compute(args) -> int:
    """Fit the compute-cost model; write ``compute_calibration.json`` and print the fit."""
    from tqdm import tqdm

    from slam_gym.compute_cost import calibrate

    seeds = int_list(args.calibration_seeds, "calibration_seeds")
    bar = tqdm(total=len(CALIBRATION_RUNS) * len(seeds), desc="calibration episodes",
               disable=args.quiet or args.json)
    records = collect_records(seeds, progress=bar.update)
    bar.close()
    fit = calibrate(records)
    result = {
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "seeds": seeds,
        "costs": {k: {"intercept_s": c.intercept_s, "seconds_per_op": c.seconds_per_op}
                  for k, c in fit.costs.items()},
        "n_samples": fit.n_samples,
        "correlation": fit.correlation,
        "overall_correlation": fit.overall_correlation,
        "measured_total_s": {k: float(sum(r[2] for r in records if r[0] == k))
                             for k in fit.costs},
    }
    out = out_dir(args)
    (out / "compute_calibration.json").write_text(json.dumps(to_jsonable(result), indent=2) + "\n")
    lines = [f"{'kind':<17}{'n':>6}{'intercept (s)':>15}{'s per op':>12}{'r':>7}"]
    for k, c in fit.costs.items():
        lines.append(f"{k:<17}{fit.n_samples[k]:>6}{c.intercept_s:>15.2e}{c.seconds_per_op:>12.2e}"
                     f"{fit.correlation[k]:>7.3f}")
    lines.append(f"correlation of modelled and measured CPU time over all records: "
                 f"{fit.overall_correlation:.3f}")
    emit(args, result, lines)
    return 0


QUICK = {
    "systems": "hybrid", "particles": "500", "clutter_levels": "2", "iterations": 2500,
    "env_decisions": 250, "env_particles": "", "worst_case_decisions": 150,
    "schedule_particles": 500, "optimise_counts": "10,20,40", "optimise_seeds": "0",
    "full_path_episodes": 1,
}
"""What ``--quick`` measures (about 30 s of CPU on this project's machines)."""


def record_figures(result) -> dict:
    """The figures of a speed record (:mod:`slam_gym.commands.speed_record`) from a result."""
    from slam_gym.commands.speed_record import figure

    out = {}
    for r in result.get("systems", []):
        key = f"{r['system']}_{r['n_particles'] or 0}p_level{r['clutter_level']}"
        out[f"{key}_iterations_per_s"] = figure(r["iterations_per_s"], "iterations/s", True)
    for e in result.get("env_schedules", []):
        key = e["schedule"].replace("-", "_")
        out[f"env_{key}_decisions_per_s"] = figure(e["decisions_per_s"], "decisions/s", True)
    for e in result.get("env_full_path", []):
        if e["full_path_episodes"] == 0:
            continue  # no episode ran the whole path: the figure is missing from the record
        key = e["schedule"].replace("-", "_")
        out[f"env_full_path_{key}_decisions_per_s"] = figure(e["decisions_per_s"],
                                                             "decisions/s", True)
        if e.get("last_optimisation_ms") is not None:
            out["optimise_last_full_path_ms"] = figure(e["last_optimisation_ms"], "ms", False)
    for r in result.get("optimise", []):
        out[f"optimise_{r['stored_submaps']}_submaps_ms"] = figure(r["median_ms"], "ms", False)
    for t in result.get("tasks", []):
        key = "task_" + t["env"].split("/")[-1].replace("-", "_").lower()
        out[f"{key}_decisions_per_s"] = figure(t["decisions_per_s"], "decisions/s", True)
        out[f"{key}_episode_cpu_s"] = figure(t["episode_cpu_s"], "s", False)
    if result.get("optimise"):
        out["optimise_redundant_us"] = figure(
            float(np.median([r["redundant_median_us"] for r in result["optimise"]])), "us", False)
    return out


def check_timed_envs(args) -> list:
    """The envs ``--tasks`` and ``--env`` name, resolved (``ValueError`` naming the option and
    the closest ids for an unknown one), before any measurement."""
    from slam_gym.envs import TASK_ENV_VARIANTS
    from slam_gym.envs.spec import check_env_id, parse_env_kwargs, resolve_env

    tasks = sorted(TASK_ENV_VARIANTS) if args.tasks == "all" else name_list(args.tasks)
    envs = [resolve_env(check_env_id(t, "tasks"), per_decision=True) for t in tasks]
    if args.env is not None:
        envs.append(resolve_env(check_env_id(args.env), parse_env_kwargs(args.env_kwargs),
                                per_decision=True))
    elif args.env_kwargs:
        raise ValueError(f"env_kwargs={args.env_kwargs!r} is invalid without --env: they are "
                         "options of the env --env names")
    for spec in envs:
        if spec.scenario == "recorded":
            raise ValueError(f"env={spec.env_id!r} is invalid: a simulated env (a recording's "
                             "speed is timed by slam-gym reproduce mrclam)")
    return envs


def run(args) -> int:
    from tqdm import tqdm

    if args.calibrate_compute:
        return calibrate_compute(args)
    baseline = None
    if args.compare is not None:
        from slam_gym.commands.speed_record import load_record

        try:
            baseline = load_record(args.compare)
        except ValueError as exc:
            logger.error("%s", exc)
            return 2
    timed_envs = check_timed_envs(args)  # every id before any measurement
    worst_case_decisions = args.env_decisions
    optimise_steps = args.iterations
    if args.quick:
        for name, value in QUICK.items():
            if name not in ("worst_case_decisions", "iterations"):
                setattr(args, name, value)
        args.iterations = QUICK["iterations"]  # the system's; optimise() runs the whole path
        optimise_steps = None
        worst_case_decisions = QUICK["worst_case_decisions"]
        args.skip_first_reset = args.skip_paper_episode = args.skip_esdf = True
    # untimed: load the compiled functions from numba's cache (~1 s of CPU), which the first
    # timed figure would otherwise carry (a fresh process's first reset is timed on its own)
    measure_system("hybrid", 2, 50, args.seed, 50)
    # (fusing and optimising at every decision: three decisions of fixed-10s-optimise never
    # reached a fusion, so the optimiser's functions loaded, or compiled after an edit, in the
    # first timed optimisation: 16.6 instead of 142 decisions/s in one record)
    measure_env(3, args.seed + 999, schedule="fuse-optimise-every-decision", n_particles=50)
    record_wanted = args.quick or baseline is not None
    if record_wanted:  # the machine's own speed, before and after the figures (speed_record)
        from slam_gym.commands.speed_record import machine_reference

        references_s = [machine_reference()]
    schedules = name_list(args.env_schedules)
    bad = [s for s in schedules if s not in ENV_SCHEDULES]
    if bad:
        logger.error("--env-schedules=%s is invalid: must be among %s", ",".join(bad),
                     ", ".join(ENV_SCHEDULES))
        return 2

    systems = name_list(args.systems)
    particles = int_list(args.particles, "particles")
    levels = int_list(args.clutter_levels, "clutter_levels")
    configs = [
        (s, level, p)
        for s in systems
        for level in levels
        for p in (particles if s in PARTICLE_SYSTEMS else [particles[0]])
    ]
    rows = []
    for s, level, p in tqdm(configs, desc="speed", disable=args.quiet or args.json):
        rows.append(measure_system(s, level, p, args.seed, args.iterations))
    result = {
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "python": platform.python_version()},
        "systems": rows,
    }
    if args.env_decisions > 0 and args.env_particles:
        result["env_runs"] = [
            measure_env(args.env_decisions, args.seed, n_particles=n)
            for n in int_list(args.env_particles, "env_particles")
        ]
        result["env"] = result["env_runs"][-1]
    if args.env_decisions > 0 and schedules:
        # each schedule its own worlds: the process remembers recent worlds, and a replayed
        # one would spare the schedules after the first their simulation
        result["env_schedules"] = [
            measure_env(
                worst_case_decisions if s == "fuse-optimise-every-decision" else
                args.env_decisions, args.seed + 1000 * (1 + list(ENV_SCHEDULES).index(s)),
                schedule=s, n_particles=args.schedule_particles)
            for s in tqdm(schedules, desc="env schedules", disable=args.quiet or args.json)
        ]
    if args.full_path_episodes > 0:
        result["env_full_path"] = [
            measure_full_path(s, args.full_path_episodes, n_particles=args.schedule_particles)
            for s in tqdm(FULL_PATH_SCHEDULES, desc="full paths", disable=args.quiet or args.json)
        ]
    counts = int_list(args.optimise_counts, "optimise_counts")
    if counts:
        result["optimise"] = measure_optimise(int_list(args.optimise_seeds, "optimise_seeds"),
                                              counts, n_steps=optimise_steps)
    if timed_envs:
        result["tasks"] = [measure_task(t) for t in tqdm(timed_envs, desc="tasks",
                                                         disable=args.quiet or args.json)]
    if not args.skip_first_reset:
        result["env_first_reset"] = measure_first_reset(args.seed)
    if args.env_decisions > 0 and not args.skip_paper_episode:
        result["env_paper_episode"] = measure_env(None, args.seed, **PAPER_ENV_CONFIG)
    if not args.skip_esdf:
        result["esdf"] = measure_esdf(args.seed)
    if record_wanted:
        references_s.append(machine_reference())
        result["machine_reference_s"] = references_s
    out = out_dir(args)
    (out / "speed.json").write_text(json.dumps(to_jsonable(result), indent=2) + "\n")
    lines = [f"{'system':<12}{'clutter':>8}{'particles':>10}{'it/s':>10}{'x real time':>13}"
             f"{'ms/it':>9}{'us/particle-it':>16}"]
    for r in rows:
        per = r.get("us_per_particle_iteration")
        lines.append(
            f"{r['system']:<12}{r['clutter_level']:>8}{str(r['n_particles'] or '-'):>10}"
            f"{r['iterations_per_s']:>10.0f}{r['real_time_ratio']:>13.1f}"
            f"{r['ms_per_iteration']:>9.2f}{(f'{per:.2f}' if per else '-'):>16}"
        )
    for e in result.get("env_runs", []):
        lines.append(f"env {e['env']} ({e['n_particles']} particles, interval "
                     f"{e['decision_interval']}): {e['decisions_per_s']:.0f} decisions/s "
                     f"({e['decisions']} decisions, {e['resets']} resets included)")
    for e in result.get("env_schedules", []):
        lines.append(f"env {e['n_particles']} particles, {e['schedule']}: "
                     f"{e['decisions_per_s']:.0f} decisions/s ({e['decisions']} decisions, "
                     f"{e['resets']} resets included)")
    for e in result.get("env_full_path", []):
        line = (f"env {e['n_particles']} particles, {e['schedule']}, whole paths only: "
                f"{e['decisions_per_s']:.0f} decisions/s ({e['full_path_episodes']} episodes "
                f"of {e['decisions']} decisions; {e['failed_episodes']} failed ones left out)")
        if e.get("last_optimisation_ms") is not None:
            line += (f"; its last optimisation {e['last_optimisation_ms']:.2f} ms (median of "
                     f"{e['last_optimisation_repeats']}, {e['last_optimisation_submaps']} "
                     f"sub-maps, {e['last_optimisation_variables']} variables, "
                     f"{e['last_optimisation_iterations']} iterations)")
        lines.append(line)
    for r in result.get("optimise", []):
        lines.append(f"optimise() at {r['stored_submaps']} stored sub-maps: median "
                     f"{r['median_ms']:.1f} ms (max {r['max_ms']:.1f}, {r['optimisations']} "
                     f"optimisations, {r['median_iterations']:.0f} iterations); redundant "
                     f"{r['redundant_median_us']:.0f} us")
    for t in result.get("tasks", []):
        lines.append(f"task {t['env']} ({t['n_particles']} particles, level "
                     f"{t['clutter_level']}, world {t['seed']}, {t['schedule']}): "
                     f"{t['decisions_per_s']:.0f} decisions/s, one episode of {t['decisions']} "
                     f"decisions {t['episode_cpu_s']:.1f} s CPU; ms per decision by third: "
                     + ", ".join(f"{p['ms_per_decision']:.1f} (to {p['stored_submaps_at_end']}"
                                 f" sub-maps, {p['global_features_at_end']} features)"
                                 for p in t["thirds"]))
    if "env_first_reset" in result:
        e = result["env_first_reset"]
        lines.append(f"env in a fresh process: import {e['import_cpu_s']:.2f} s, first reset "
                     f"{e['first_reset_cpu_s']:.2f} s CPU ({e['import_wall_s']:.2f} s and "
                     f"{e['first_reset_wall_s']:.2f} s wall)")
    if "env_paper_episode" in result:
        e = result["env_paper_episode"]
        lines.append(f"env paper configuration ({e['n_particles']} particles): one whole episode "
                     f"of {e['decisions']} decisions in {e['cpu_time_s']:.1f} s")
    for r in result.get("esdf", []):
        lines.append(f"ESDF state {r['state_dim_min']}-{r['state_dim_max']}: median "
                     f"{r['ms_per_update_median']:.3f} ms, mean {r['ms_per_update_mean']:.3f} ms "
                     f"per update ({r['updates']} updates)")
    lines.append(f"wrote {out / 'speed.json'}")
    status = 0
    if record_wanted:
        from slam_gym.commands.speed_record import compare, comparison_lines, make_record

        record = make_record(record_figures(result), Path(__file__).resolve().parents[2],
                             float(np.mean(references_s)))
        (out / "speed_record.json").write_text(json.dumps(to_jsonable(record), indent=2) + "\n")
        result["record"] = record
        lines.append(f"wrote {out / 'speed_record.json'}")
        if baseline is not None:
            rows_cmp, ok = compare(record, baseline)
            result["comparison"] = {"baseline": args.compare, "passed": ok, "rows": rows_cmp}
            lines += comparison_lines(rows_cmp, record, baseline)
            lines.append("speed check passed" if ok else
                         "speed check FAILED: a figure fell below half of the baseline's")
            status = 0 if ok else 1
    emit(args, result, lines)
    return status
