"""Evaluation machinery: jobs, resumable parallel execution (process pool, Ray), summary, plots.

The run functions below are module-level so that they pickle to spawned workers and Ray workers.
Their metrics are simple functions of the seed, so every row can be checked exactly.
"""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from slam_gym.evaluation import (
    RESULT_KEYS,
    Job,
    expand_grid,
    markdown_table,
    read_results,
    run_jobs,
    summarise,
    wilson_interval,
    write_summary,
)
from slam_gym.evaluation.results import (
    REQUIRED_ROW_KEYS,
    RUN_TIME_KEYS,
    ResultsWriter,
    finished_keys,
)
from slam_gym.evaluation.summary import format_table

TEST_DIR = Path(__file__).resolve().parent
REPO = TEST_DIR.parents[1]
BAD_SEED = 3
KILL_SEED = 2
CLUTTER = {0: (1.0, 0.0), 1: (0.7, 0.02), 2: (0.4, 0.04), 3: (0.1, 0.06)}


def toy_metrics(job: Job) -> dict:
    """Metrics that are exact functions of the job (so rows can be checked by hand)."""
    alpha, beta = CLUTTER[job.clutter_level]
    success = job.seed % 2 == 0
    return {
        "alpha": alpha,
        "beta": beta,
        "success": success,
        "failure_iteration": None if success else 100 * job.seed,
        "anees": np.float64(3.0 + 0.5 * job.seed),  # numpy scalars must be written as numbers
        "nees_in_band_fraction": 0.9,
        "map_error_m": 0.1 * (job.seed + 1) + job.clutter_level,
        "final_pose_error_m": 0.01 * job.seed,
        "n_fusions": np.int64(job.seed + 10),
        "n_optimisations": 0,
        "trace": np.arange(3, dtype=float),  # an extra key is kept
    }


def toy_run(job: Job) -> dict:
    if job.seed == BAD_SEED:
        raise RuntimeError(f"toy failure for seed {job.seed}")
    return toy_metrics(job)


def fixed_run(job: Job) -> dict:
    return toy_metrics(job)


def slow_run(job: Job) -> dict:
    time.sleep(job.options_dict().get("sleep_s", 0.0))
    return toy_metrics(job)


def killer_run(job: Job) -> dict:
    if job.seed == KILL_SEED:
        os._exit(7)  # the worker process dies: no exception reaches the pool
    return toy_metrics(job)


def incomplete_run(job: Job) -> dict:
    metrics = toy_metrics(job)
    del metrics["anees"], metrics["map_error_m"]
    return metrics


def must_not_run(job: Job) -> dict:
    raise AssertionError(f"job {job.key} was run again although it is in results.jsonl")


def slow_jobs() -> list[Job]:
    return expand_grid(
        ["slow-a", "slow-b"], [0, 1], range(3), kind="system", options={"sleep_s": 0.4}
    )


def _stable(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in RUN_TIME_KEYS}


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


# ---------------------------------------------------------------------------------------------
# Jobs


def test_job_key_is_stable_hashable_and_validated():
    a = Job("policy", "fixed-10s", "brooks-bailey", 2, 7, options={"b": 1, "a": 0.5})
    b = Job("policy", "fixed-10s", "brooks-bailey", 2, 7, options=(("a", 0.5), ("b", 1)))
    assert a == b and hash(a) == hash(b) and a.key == b.key
    assert a.options == (("a", 0.5), ("b", 1))
    assert pickle.loads(pickle.dumps(a)).key == a.key
    assert json.loads(a.key) == ["policy", "fixed-10s", "brooks-bailey", 2, 7, {"a": 0.5, "b": 1}]
    assert Job.from_row(a.row_fields()) == a
    assert Job("policy", "fixed-10s", "brooks-bailey", 2, 8).key != a.key
    with pytest.raises(ValueError, match=r"kind='robot' is invalid: must be one of"):
        Job("robot", "x", "s", 0, 0)
    with pytest.raises(ValueError, match=r"seed=-1 is invalid: must be an int >= 0"):
        Job("system", "x", "s", 0, -1)
    with pytest.raises(ValueError, match=r"clutter_level=1.5 is invalid"):
        Job("system", "x", "s", 1.5, 0)
    with pytest.raises(ValueError, match=r"options\['p'\]"):
        Job("system", "x", "s", 0, 0, options={"p": [1, 2]})

    grid = expand_grid(["a", "b"], [0, 1, 2], range(4), kind="system", scenario="s")
    assert len(grid) == 24 and len({j.key for j in grid}) == 24
    assert [j.seed for j in grid[:6]] == [0] * 6  # seed-major
    with pytest.raises(ValueError, match=r"seeds=\[1, 1\] is invalid: must be distinct values"):
        expand_grid(["a"], [0], [1, 1])


# ---------------------------------------------------------------------------------------------
# Execution


def test_process_pool_records_errors_and_resumes(tmp_path):
    jobs = expand_grid(["ekf", "hybrid"], [1], range(5), kind="system")
    rows = run_jobs(jobs, toy_run, tmp_path, workers=2, progress=False)
    path = tmp_path / "results.jsonl"
    assert [r["key"] for r in rows] == [j.key for j in jobs]
    assert read_results(path) and len(_lines(path)) == len(jobs)
    for job, row in zip(jobs, rows, strict=True):
        assert set(REQUIRED_ROW_KEYS) <= set(row) and row["system"] == job.name
        assert row["wall_time_s"] >= 0.0
        if job.seed == BAD_SEED:
            assert row["status"] == "error"
            assert row["error"] == "RuntimeError: toy failure for seed 3"
            assert "toy_run" in row["traceback"]
            assert all(row[k] is None for k in RESULT_KEYS)
        else:
            expected = json.loads(json.dumps(toy_metrics(job), default=lambda v: v.tolist()))
            assert {k: row[k] for k in expected} == expected
            assert row["status"] == "ok" and row["error"] is None
    summary = summarise(rows)
    assert [(g["system"], g["n"], g["n_errors"], g["n_ok"]) for g in summary] == [
        ("ekf", 5, 1, 4),
        ("hybrid", 5, 1, 4),
    ]
    # seeds 0, 2, 4 succeed; seed 3 errored and is not counted as a failure
    assert summary[0]["n_success"] == 3 and summary[0]["success_rate"] == pytest.approx(0.75)

    # rerun: nothing runs again, the file is unchanged, rows are returned from the file
    before = path.read_bytes()
    again = run_jobs(jobs, must_not_run, tmp_path, executor="serial", progress=False)
    assert path.read_bytes() == before and again == rows

    # retry_errors reruns only the error rows, still one row per job
    fixed = run_jobs(jobs, fixed_run, tmp_path, workers=2, progress=False, retry_errors=True)
    file_rows = read_results(path)
    assert sorted(r["key"] for r in file_rows) == sorted(j.key for j in jobs)
    assert all(r["status"] == "ok" for r in fixed)
    unchanged = [r for r in rows if r["status"] == "ok"]
    assert all(r in file_rows for r in unchanged)


def _start_driver(out_dir: Path, kill_group: bool) -> subprocess.Popen:
    code = (
        "import signal, sys\n"
        # Ctrl-C raises KeyboardInterrupt even where the driver inherits an ignored SIGINT (a
        # background job of a non-interactive shell, as CI may start the tests)
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "from test_evaluation import slow_jobs, slow_run\n"
        "from slam_gym.evaluation import run_jobs\n"
        "run_jobs(slow_jobs(), slow_run, sys.argv[1], workers=2, progress=False)\n"
    )
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(TEST_DIR), env.get("PYTHONPATH", "")])
    return subprocess.Popen(
        [sys.executable, "-c", code, str(out_dir)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=kill_group,
    )


def _wait_for_rows(proc: subprocess.Popen, path: Path, n: int) -> None:
    deadline = time.monotonic() + 60.0  # hang guard only
    while time.monotonic() < deadline:
        if path.exists() and len(read_results(path)) >= n:
            return
        assert proc.poll() is None, proc.communicate()[1].decode()[-2000:]
        time.sleep(0.05)
    raise AssertionError("the benchmark wrote no rows within 60 s")


def test_killed_run_resumes_with_one_row_per_job(tmp_path):
    jobs = slow_jobs()
    path = tmp_path / "results.jsonl"
    proc = _start_driver(tmp_path, kill_group=True)
    try:
        _wait_for_rows(proc, path, 2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and its pool workers, mid-run
        proc.communicate()
    survivors = read_results(path)
    assert 2 <= len(survivors) < len(jobs)

    # a write cut short by the kill: a partial last line without newline
    with open(path, "ab") as f:
        f.write(b'{"system":"slow-a","scenario":"brooks-bea')
    assert read_results(path) == survivors

    rows = run_jobs(jobs, fixed_run, tmp_path, executor="serial", progress=False)
    file_rows = read_results(path)
    keys = [r["key"] for r in file_rows]
    assert len(keys) == len(set(keys)) == len(jobs)
    assert set(keys) == {j.key for j in jobs} == finished_keys(file_rows)
    assert file_rows[: len(survivors)] == survivors  # nothing written before the kill was lost
    assert path.read_bytes().endswith(b"\n") and all(json.loads(x) for x in _lines(path))
    assert all(r["status"] == "ok" for r in rows)


def test_ctrl_c_leaves_a_valid_file_and_reraises(tmp_path):
    jobs = slow_jobs()
    path = tmp_path / "results.jsonl"
    proc = _start_driver(tmp_path, kill_group=True)
    try:
        _wait_for_rows(proc, path, 1)
        os.kill(proc.pid, signal.SIGINT)  # the driver only: it must stop its own workers
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode != 0
    assert "KeyboardInterrupt" in err.decode()
    done = read_results(path)
    assert 1 <= len(done) < len(jobs)
    assert path.read_bytes().endswith(b"\n") and len(_lines(path)) == len(done)

    run_jobs(jobs, fixed_run, tmp_path, executor="serial", progress=False)
    keys = [r["key"] for r in read_results(path)]
    assert len(keys) == len(set(keys)) and set(keys) == {j.key for j in jobs}


def test_a_dying_worker_is_an_error_and_the_others_finish(tmp_path):
    jobs = expand_grid(["ekf"], [0], range(5), kind="system")
    rows = run_jobs(jobs, killer_run, tmp_path, workers=2, progress=False)
    by_seed = {r["seed"]: r for r in rows}
    assert by_seed[KILL_SEED]["status"] == "error"
    assert by_seed[KILL_SEED]["error"].startswith("BrokenProcessPool: the worker process")
    assert all(by_seed[s]["status"] == "ok" for s in range(5) if s != KILL_SEED)
    keys = [r["key"] for r in read_results(tmp_path / "results.jsonl")]
    assert sorted(keys) == sorted(j.key for j in jobs)


def test_invalid_results_and_arguments(tmp_path):
    jobs = expand_grid(["ekf"], [0], [0], kind="system")
    (row,) = run_jobs(jobs, incomplete_run, tmp_path, executor="serial", progress=False)
    assert row["status"] == "error"
    assert row["error"] == (
        "ResultError: run function result is missing required keys: anees, map_error_m"
    )
    assert summarise([row])[0]["n_errors"] == 1
    with pytest.raises(ValueError, match=r"run_fn=.* must pickle"):
        run_jobs(jobs, lambda job: {}, tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match=r"executor='dask' is invalid"):
        run_jobs(jobs, toy_run, tmp_path / "x", executor="dask", progress=False)
    with pytest.raises(ValueError, match=r"workers=0 is invalid: must be an int >= 1"):
        run_jobs(jobs, toy_run, tmp_path / "x", workers=0, progress=False)
    with pytest.raises(ValueError, match=r"jobs=.* distinct jobs"):
        run_jobs(jobs * 2, toy_run, tmp_path / "x", progress=False)
    # a second writer on the same file is refused
    with ResultsWriter(tmp_path / "results.jsonl"):
        with pytest.raises(RuntimeError, match="being written by another process"):
            run_jobs(jobs, toy_run, tmp_path, executor="serial", progress=False)
    # damage before the last line is not silently dropped
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"a": 1}\n{"a": \n{"a": 2}\n')
    with pytest.raises(ValueError, match=r"bad.jsonl:2: line is not a JSON object"):
        read_results(bad)


@pytest.mark.xdist_group("ray")  # one local Ray instance at a time (pytest -n)
def test_ray_gives_the_same_rows_as_the_process_pool(tmp_path):
    try:
        import ray  # noqa: F401
    except ImportError:
        pytest.fail("Ray is not installed: pip install slam-gym[ray] (this test is not skipped)")

    jobs = expand_grid(["ekf", "hybrid"], [0, 2], range(2, 5), kind="system")
    by_pool = run_jobs(jobs, toy_run, tmp_path / "pool", workers=2, progress=False)
    by_ray = run_jobs(jobs, toy_run, tmp_path / "ray", workers=2, executor="ray", progress=False)
    assert [_stable(r) for r in by_ray] == [_stable(r) for r in by_pool]
    assert sum(r["status"] == "error" for r in by_ray) == 4  # seed 3 in each (name, level)
    on_disk = sorted(json.dumps(_stable(r)) for r in read_results(tmp_path / "ray"))
    assert on_disk == sorted(json.dumps(_stable(r)) for r in by_pool)


# ---------------------------------------------------------------------------------------------
# Summary


def _row(name, level, seed, *, success=True, anees=3.0, map_error=1.0, status="ok"):
    job = Job("system", name, "brooks-bailey", level, seed)
    row = {**job.row_fields(), **dict.fromkeys(RESULT_KEYS), "status": status, "error": None}
    row.update(wall_time_s=2.0, traceback=None)
    if status == "ok":
        row.update(
            alpha=CLUTTER[level][0],
            beta=CLUTTER[level][1],
            success=success,
            anees=anees,
            nees_in_band_fraction=0.5,
            map_error_m=map_error,
            final_pose_error_m=0.2,
            n_fusions=seed,
            n_optimisations=1,
        )
    else:
        row["error"] = "RuntimeError: boom"
    return row


def test_summary_on_hand_made_results(tmp_path):
    map_errors = [0.5, 0.5, 0.6, 0.7, 1.0, 1.2, 2.0, 0.4, 0.3, 9.8]
    rows = [
        _row("ekf", 1, s, success=s < 8, anees=float(s + 1), map_error=m)
        for s, m in enumerate(map_errors)
    ]
    rows.append(_row("ekf", 1, 10, status="error"))
    rows += [_row("hybrid", 1, s) for s in range(10)]
    rows += [_row("hybrid", 2, s, success=False) for s in range(5)]
    rows += [_row("hybrid", 3, s, status="error") for s in range(2)]
    path = tmp_path / "results.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"system": "ek')

    paper = {"ekf": {1: 0.76}, "hybrid": {"1": 0.89, "2": 0.83}}
    doc = write_summary(tmp_path, read_results(path), paper=paper)
    assert doc["n_runs"] == 28 and doc["n_errors"] == 3
    assert json.loads((tmp_path / "summary.json").read_text()) == doc
    ekf, h1, h2, h3 = doc["groups"]
    assert (ekf["system"], ekf["clutter_level"], h3["clutter_level"]) == ("ekf", 1, 3)
    # 8 successes in 10 ok runs; the errored 11th run is counted apart
    assert (ekf["n"], ekf["n_ok"], ekf["n_errors"], ekf["n_success"]) == (11, 10, 1, 8)
    assert ekf["success_rate"] == pytest.approx(0.8)
    assert ekf["success_ci95"] == pytest.approx([0.4902, 0.9433], abs=5e-5)
    assert ekf["anees"] == pytest.approx(5.5)  # mean of 1..10
    assert ekf["map_error_m"]["mean"] == pytest.approx(1.7)  # 17.0 / 10
    assert ekf["map_error_m"]["median"] == pytest.approx(0.65)  # (0.6 + 0.7) / 2
    assert ekf["n_fusions"] == pytest.approx(4.5)
    assert (ekf["alpha"], ekf["beta"]) == (0.7, 0.02)
    assert h1["success_ci95"] == pytest.approx([0.7225, 1.0], abs=5e-5)  # 10/10: 1/(1+z^2/10)
    assert h1["success_ci95"][1] == 1.0
    assert h2["success_ci95"] == pytest.approx([0.0, 0.4345], abs=5e-5)  # 0/5: (z^2/5)/(1+z^2/5)
    assert h2["success_ci95"][0] == 0.0
    assert h3["n_errors"] == 2 and h3["success_rate"] is None and h3["anees"] is None
    assert (ekf["paper_success_rate"], h1["paper_success_rate"]) == (0.76, 0.89)
    assert h3["paper_success_rate"] is None

    table = (tmp_path / "table.md").read_text()
    assert "| ekf | 1 | 11 | 1 | 50 % | 5.50 | 1.70 / 0.65 | 80 % [49, 94] | 76 % |" in table
    assert "| hybrid | 2 | 5 | 0 |" in table and "| 0 % [0, 43] | 83 % |" in table
    assert "28 runs, 3 errored" in table
    text = format_table(doc, rich=False)
    assert "80 % [49, 94]" in text and "paper" in text.splitlines()[1]
    rich_table = format_table(doc)
    assert rich_table.row_count == 4 and len(rich_table.columns) == 12
    assert "options" not in text and "scenario" not in text

    # the same system with other options is a separate group, and the table says which is which
    other = {**_row("ekf", 1, 0), "options": {"n_particles": 50}}
    other["key"] = Job.from_row(other).key
    groups = summarise([*rows, other])
    assert [(g["system"], g["clutter_level"], g["options"], g["n"]) for g in groups[:2]] == [
        ("ekf", 1, {}, 11),
        ("ekf", 1, {"n_particles": 50}, 1),
    ]
    assert "| ekf | n_particles=50 | 1 | 1 | 0 |" in markdown_table(groups)
    assert "| 100 % [21, 100] |" in markdown_table(groups)


def test_success_rate_leaves_out_runs_where_success_is_undefined():
    """Real data without pose truth (Victoria Park) has success null: no rate, not 0 %."""
    rows = [_row("hybrid", 1, s, success=None) for s in range(3)]
    rows += [_row("ekf", 1, s, success=s == 0) for s in range(2)]
    rows.append(_row("ekf", 1, 9, success=None))
    undefined, ekf = summarise(rows)
    assert undefined["success_rate"] is None and undefined["success_ci95"] is None
    assert ekf["n_ok"] == 3 and ekf["n_success"] == 1 and ekf["success_rate"] == 0.5


def test_wilson_interval_properties():
    assert wilson_interval(3, 4) == pytest.approx((0.3006, 0.9544), abs=5e-5)
    for n in (1, 7, 50):
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0
    with pytest.raises(ValueError, match=r"n=0 is invalid: must be an int >= 1"):
        wilson_interval(0, 0)
    with pytest.raises(ValueError, match=r"successes=5 is invalid: must be an int in \[0, 4\]"):
        wilson_interval(5, 4)


# ---------------------------------------------------------------------------------------------
# Plots


def _check_png(path: Path, height: int, width: int) -> None:
    import matplotlib.image

    image = matplotlib.image.imread(path)
    assert image.shape == (height, width, 4)
    assert float(image[..., :3].std()) > 0.01  # something was drawn


def test_plots_write_pngs_of_the_expected_size(tmp_path):
    # imported here so that the workers which import this module for its run functions stay light
    from slam_gym.evaluation.plots import (
        nees_band,
        plot_nees,
        plot_run_map,
        plot_success_rates,
        plot_uncertainty_traces,
    )

    rows = [
        _row(n, lv, s, success=(s + lv) % 3 > 0)
        for n in ("ekf", "hybrid")
        for lv in range(4)
        for s in range(6)
    ]
    summary = summarise(rows)
    paper = {"ekf": {0: 0.79, 1: 0.76, 2: 0.72, 3: 0.30}, "hybrid": {0: 0.87, 1: 0.89}}
    p = plot_success_rates(summary, tmp_path / "success.png", paper=paper)
    _check_png(p, 540, 840)

    steps = np.arange(400)
    covs = np.einsum("t,ij->tij", 0.01 + 0.001 * steps, np.eye(3))
    p = plot_uncertainty_traces(
        {"hybrid": covs, "fastslam": 0.02 * np.exp(-steps / 100)}, tmp_path / "trace.png"
    )
    _check_png(p, 540, 840)

    rng = np.random.default_rng(0)
    nees = rng.chisquare(3, size=(2, 300))
    p = plot_nees({"ekf": nees[0], "hybrid": nees[1]}, tmp_path / "nees.png", dt_s=0.1)
    _check_png(p, 540, 840)
    lo, hi = nees_band(3)
    assert (lo, hi) == pytest.approx((0.2158, 9.3484), abs=1e-4)

    landmarks = rng.uniform(0, 120, size=(35, 2))
    t = np.linspace(0, 2 * np.pi, 200)
    path_true = np.column_stack([60 + 50 * np.cos(t), 60 + 50 * np.sin(t), t])
    a = rng.normal(size=(30, 2, 2))
    p = plot_run_map(
        tmp_path / "map.png",
        landmarks_true=landmarks,
        landmark_means=landmarks[:30] + rng.normal(0, 0.5, size=(30, 2)),
        landmark_covs=0.1 * a @ np.swapaxes(a, 1, 2) + 0.01 * np.eye(2),
        path_true=path_true,
        path_est=path_true[:, :2] + rng.normal(0, 0.3, size=(200, 2)),
        figsize=(6.5, 6.0),
    )
    _check_png(p, 720, 780)


def test_pareto_front_keeps_exactly_the_non_dominated_points():
    from slam_gym.evaluation import pareto_front

    points = [(1.0, 5.0), (2.0, 2.0), (3.0, 3.0), (4.0, 1.0), (2.0, 2.0), (5.0, float("nan"))]
    # (3, 3) is dominated by (2, 2); the two (2, 2) do not dominate each other; NaN never counts
    assert pareto_front(points) == [0, 1, 3, 4]
    assert pareto_front([(1.0, 1.0), (1.0, 2.0)]) == [0]


def test_mean_interval_is_students_t():
    import statistics

    from scipy.stats import t

    from slam_gym.evaluation.summary import mean_interval

    values = [1.0, 2.0, 4.0, 7.0]
    lo, hi = mean_interval(values)
    half = t.ppf(0.975, 3) * statistics.stdev(values) / 2.0
    assert (lo, hi) == pytest.approx((3.5 - half, 3.5 + half))
    assert mean_interval([1.0]) is None


def _children(pid: int) -> list[int]:
    """Pids of the live processes whose parent is ``pid`` (Linux /proc)."""
    from pathlib import Path

    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    from pathlib import Path

    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_pool_workers_end_when_the_benchmark_is_killed(tmp_path):
    """SIGKILL leaves the parent no chance to stop its pool: the workers must notice on their
    own (they watch their parent) and be gone a few seconds later."""
    import signal
    import subprocess
    import time

    argv = [sys.executable, "-m", "slam_gym.cli", "benchmark", "--policies", "always",
            "--clutter-levels", "0", "--seeds", "6", "--particles", "500", "--workers", "1",
            "--executor", "process", "--baselines", "", "--no-figures", "--quiet",
            "--out", str(tmp_path)]
    parent = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        workers = []
        while time.monotonic() < deadline and not workers:
            time.sleep(0.5)
            workers = [p for p in _children(parent.pid)
                       if b"spawn_main" in open(f"/proc/{p}/cmdline", "rb").read()]
        assert workers, "the benchmark started no pool worker"
        time.sleep(2.0)  # the worker is busy in its first run
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.2)
        assert not any(_alive(p) for p in workers), "a pool worker outlived its killed parent"
    finally:
        if parent.poll() is None:
            parent.kill()


def test_map_error_of_successful_runs_leaves_failed_runs_out():
    from slam_gym.evaluation import summarise

    rows = [
        {"policy": "p", "scenario": "s", "clutter_level": 0, "status": "ok", "success": ok,
         "map_error_m": err, "total_cpu_s": 1.0}
        for ok, err in ((True, 0.4), (True, 0.6), (False, 0.01))
    ]
    (group,) = summarise(rows)
    assert group["map_error_m"]["mean"] == pytest.approx(1.01 / 3)
    assert group["map_error_m_succeeded"] == pytest.approx(0.5)
    lo, hi = group["ci95"]["map_error_m_succeeded"]
    assert lo < 0.5 < hi


def test_decision_timeline_records_what_the_system_did():
    import policies
    from slam_gym.envs.spec import resolve_env
    from slam_gym.evaluation.timeline import decision_timeline, true_loop_closure_s

    # with BB's compass (Fig. 3) the run survives the cut path
    tl, episode, env = decision_timeline(policies.make("fixed-10s-optimise"),
                                         resolve_env("SlamGym/HybridSLAM-Compass-v1",
                                                     {"n_particles": 100, "n_steps": 400}),
                                         0, 3)
    assert not tl["failed"]
    t = tl["t_s"]
    assert np.all(np.diff(t) > 0) and t[-1] == pytest.approx(tl["end_s"])
    assert tl["fused"].sum() == episode.n_fusions == tl["n_fusions"] > 0
    assert tl["optimised"].sum() == episode.n_optimisations > 0
    # the rule fuses every 10 s and optimises right after each fusion
    np.testing.assert_array_equal(tl["fused"], tl["optimised"])
    assert np.allclose(np.diff(t[tl["fused"]]), 10.0)
    # the reward's compute term: positive at every decision, more where the system fused and
    # optimised than at the decision before it
    compute = tl["compute_s"]
    assert len(compute) == len(t) and np.all(compute > 0)
    acted = np.nonzero(tl["fused"])[0]
    acted = acted[acted > 0]
    assert np.all(compute[acted] > compute[acted - 1])
    # BB's whole path returns over its start once, in its second half
    from slam_gym.world import make_stream

    stream = make_stream("brooks-bailey", seed=3, clutter_level=0)
    closure = true_loop_closure_s(stream)
    end_s = max(step.t_s for step in stream)
    assert end_s / 2 < closure < end_s


def test_policy_runs_take_the_rewards_price_of_compute():
    """A policy trained under another price of compute is evaluated under it: the options reach
    the env's reward and change nothing else of the run."""
    from slam_gym.envs.spec import resolve_env
    from slam_gym.evaluation.core import run_job
    from slam_gym.evaluation.jobs import Job

    base = {"n_particles": 20, "n_steps": 120}
    default = run_job(Job.in_env("policy", "fixed-10s-optimise", resolve_env(None, base), 1, 3))
    pricier = run_job(Job.in_env("policy", "fixed-10s-optimise", resolve_env(
        None, base | {"w_compute": 50.0, "compute_clip_s": 0.5}), 1, 3))
    assert pricier["return"] < default["return"]
    for key in ("success", "n_fusions", "n_optimisations", "map_error_m", "anees"):
        assert pricier[key] == default[key]
    with pytest.raises(ValueError, match="w_compute"):
        resolve_env(None, base | {"w_compute": -1.0})
    with pytest.raises(ValueError, match="an env's options are keyword arguments"):
        run_job(Job.in_env("policy", "fixed-10s", resolve_env(None, base), 1, 3,
                           {"w_compute": 2.0}))


def test_play_decisions_goes_on_to_the_next_world_at_each_episodes_end():
    """On a 30-step path an episode lasts a few decisions (counted here first): twice that and
    one more play worlds 0, 1 and 2 (reset in that order, the policy with each) and stop inside
    world 2."""
    import policies
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv
    from slam_gym.evaluation.core import play_decisions

    env = HybridSLAMEnv(n_particles=5, clutter_level=0, n_steps=30)
    policy = policies.make("fixed-10s")
    obs, info = env.reset(seed=0)
    policy.reset()
    per_episode, done = 0, False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
        per_episode, done = per_episode + 1, terminated or truncated
    assert per_episode >= 2

    seeds, policy_resets = [], []
    reset_env, reset_policy = env.reset, policy.reset

    def spy_env_reset(*, seed=None, options=None):
        seeds.append(seed)
        return reset_env(seed=seed, options=options)

    def spy_policy_reset():
        policy_resets.append(len(seeds))
        reset_policy()

    env.reset, policy.reset = spy_env_reset, spy_policy_reset
    obs, info = env.reset(seed=0)
    policy.reset()
    assert play_decisions(env, policy, obs, info, 2 * per_episode + 1, seed=0) == 3
    assert seeds == [0, 1, 2] and policy_resets == [1, 1, 2]
