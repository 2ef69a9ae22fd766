"""Issue 38: the command line under a user's edit-and-rerun loop, through ``slam_gym.cli.main``.

Results follow the code (a policy's rows are keyed by its source and options), failures fail
(exit codes), options are never overridden or dropped in silence, foreseeable failures print one
line, and a run that hangs is stopped. Every benchmark here is tiny: 15 s of BB's path at
clutter level 2 with 10 particles (seed 0 runs its 14 decisions, seed 1 fails at its 4th).
"""

import json
import sys
import time
import zipfile

import numpy as np
import pytest

from slam_gym.cli import main
from slam_gym.commands.runs import EXIT_RUN_ERRORS
from slam_gym.evaluation import read_results
from slam_gym.evaluation.results import ResultsWriter

TINY = ["--clutter-levels", "2", "--particles", "10", "--n-steps", "150", "--baselines", "",
        "--no-figures", "--quiet"]

RULE = '''
import numpy as np


class Rule:
    """Fuse (or not) at every decision."""

    def reset(self):
        pass

    def act(self, obs, info):
        return np.array([FUSE, 0], dtype=np.int64)
'''


def write_module(folder, name, text):
    (folder / f"{name}.py").write_text(text)
    sys.modules.pop(name, None)  # a new slam-gym process imports the file afresh


def benchmark_cli(out, policies, *extra):
    return main(["benchmark", "--policies", policies, *TINY, "--out", str(out), *extra])


def one_line(err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    folder = tmp_path / "user"
    folder.mkdir()
    monkeypatch.syspath_prepend(str(folder))
    return folder


def test_an_edited_policy_is_never_reported_with_its_old_rows(user_dir, tmp_path, capsys):
    """The issue's probe: a rule returning [0, 0] benchmarked into --out, edited to fuse, the
    same command again. It refuses (exit 2, naming the policy and the ways on); with
    --rerun-changed its rows are the edited rule's, and the old rows are gone from the file."""
    out = tmp_path / "out"
    write_module(user_dir, "edit_rule", RULE.replace("FUSE", "0"))
    assert benchmark_cli(out, "edit_rule:Rule", "--seeds", "2", "--executor", "serial") == 0
    before = read_results(out)
    assert [r["n_fusions"] for r in before] == [0, 0]
    digest = before[0]["options"]["policy_sha256"]
    capsys.readouterr()

    write_module(user_dir, "edit_rule", RULE.replace("FUSE", "1"))
    assert benchmark_cli(out, "edit_rule:Rule", "--seeds", "2", "--executor", "serial") == 2
    err = one_line(capsys.readouterr().err)
    assert "'edit_rule:Rule' (2 run(s))" in err and "--rerun-changed" in err and "--out" in err
    assert read_results(out) == before  # nothing ran, nothing dropped

    assert benchmark_cli(out, "edit_rule:Rule", "--seeds", "2", "--executor", "serial",
                         "--rerun-changed", "--json") == 0
    doc = json.loads(capsys.readouterr().out)
    after = read_results(out)
    assert len(after) == 2 and all(r["options"]["policy_sha256"] != digest for r in after)
    assert all(r["n_fusions"] >= 1 for r in after)  # the edited rule fused
    assert doc["summary"]["groups"][0]["n_fusions"] > 0.0
    # an unchanged rerun resumes: nothing to run, the same rows
    assert benchmark_cli(out, "edit_rule:Rule", "--seeds", "2", "--executor", "serial") == 0
    assert read_results(out) == after


def test_a_policy_objects_options_are_in_its_key(tmp_path):
    from test_plugins import DistanceRule

    from slam_gym.evaluation import benchmark

    tiny = {"clutter_levels": [2], "env_kwargs": {"n_particles": 10, "n_steps": 150},
            "baselines": [],
            "figures": False, "executor": "serial", "seeds": 1, "out": tmp_path}
    first = benchmark({"rule": DistanceRule(3.0)}, **tiny)
    assert benchmark({"rule": DistanceRule(3.0)}, **tiny).rows == first.rows  # resumed
    with pytest.raises(ValueError, match="policy 'rule' \\(1 run\\(s\\)\\) changed"):
        benchmark({"rule": DistanceRule(50.0)}, **tiny)
    again = benchmark({"rule": DistanceRule(50.0)}, rerun_changed=True, **tiny)
    assert again.rows[0]["n_fusions"] < first.rows[0]["n_fusions"]  # fuses after 50 m, not 3 m


RAISING = '''
import numpy as np


class Rule:
    def reset(self):
        pass

    def act(self, obs, info):
        BODY
        return np.array([1, 0], dtype=np.int64)
'''


def test_a_fixed_policy_reruns_its_error_rows_and_errors_exit_3(user_dir, tmp_path, capsys):
    """A raising rule: every run an error row, exit 3 with the summary printed; fixed, the same
    command reruns its error rows (their code changed) and exits 0."""
    out = tmp_path / "out"
    write_module(user_dir, "fix_rule", RAISING.replace("BODY", "raise KeyError('speed')"))
    assert benchmark_cli(out, "fix_rule:Rule", "--seeds", "2", "--executor", "serial") \
        == EXIT_RUN_ERRORS
    captured = capsys.readouterr()
    assert "fix_rule:Rule" in captured.out and "wrote" in captured.out  # the summary printed
    err = captured.err.strip().splitlines()[-1]  # after a warning line per failed run
    assert "2 of 2 runs failed" in err and "KeyError" in err and "--retry-errors" in err
    assert [r["status"] for r in read_results(out)] == ["error", "error"]

    write_module(user_dir, "fix_rule", RAISING.replace("BODY", "pass"))
    assert benchmark_cli(out, "fix_rule:Rule", "--seeds", "2", "--executor", "serial") == 0
    rows = read_results(out)
    assert [r["status"] for r in rows] == ["ok", "ok"] and rows[0]["n_fusions"] >= 1


def test_retry_errors_reruns_error_rows_of_unchanged_code_and_allow_errors_exits_0(
        user_dir, tmp_path, capsys):
    """A rule that fails while a file exists (a cause outside its code): its error rows stay
    (exit 3 again) until --retry-errors; --allow-errors exits 0 with the error rows."""
    flag = tmp_path / "broken"
    flag.write_text("")
    body = f"import os\n        assert not os.path.exists({str(flag)!r}), 'the data is broken'"
    write_module(user_dir, "flaky_rule", RAISING.replace("BODY", body))
    out = tmp_path / "out"
    args = ("--seeds", "1", "--executor", "serial")
    assert benchmark_cli(out, "flaky_rule:Rule", *args) == EXIT_RUN_ERRORS
    assert benchmark_cli(out, "flaky_rule:Rule", *args, "--allow-errors") == 0
    assert "--allow-errors" in capsys.readouterr().err
    flag.unlink()
    assert benchmark_cli(out, "flaky_rule:Rule", *args) == EXIT_RUN_ERRORS  # not retried
    assert benchmark_cli(out, "flaky_rule:Rule", *args, "--retry-errors") == 0
    assert [r["status"] for r in read_results(out)] == ["ok"]


@pytest.mark.parametrize("option, field", [
    (["--particles", "-3"], "--particles -3 is invalid: must be an integer in [1,"),
    (["--n-steps", "0"], "--n-steps 0 is invalid"),
    (["--clutter-levels", "0,5"], "--clutter-levels 0,5 is invalid: must be levels among"),
    (["--clutter-levels", "2,2"], "--clutter-levels 2,2 is invalid: must be distinct levels"),
    (["--clutter-levels", "two"], "--clutter-levels two is invalid: must be comma-separated "
     "integers"),
    (["--seeds", "0"], "--seeds 0 is invalid"),
    (["--seeds", str(10**12)], f"--seeds {10**12} is invalid: must be at most 20000 runs"),
    (["--seed-start", str(2**70)], f"--seed-start {2**70} is invalid: must be an integer in "
     f"[0, {2**63 - 1}]"),
    (["--seed-start", "-1"], "--seed-start -1 is invalid"),
    (["--run-timeout-s", "0"], "--run-timeout-s 0 is invalid: must be a number of seconds > 0"),
    (["--ray-address", "auto"], "--ray-address auto is invalid with --executor process"),
    (["--workers", "4", "--executor", "serial"], "--workers 4 is invalid with --executor serial"),
    (["--model", "m.zip"], "--model m.zip is invalid: must be given only with policy 'learned'"),
    (["--quick", "--policies", "never"], "--quick is invalid with --policies"),
    (["--policies", "json:dumps"], "policy 'json:dumps' is invalid"),
    (["--particles", "many"], "argument --particles: invalid int value: 'many'"),
])
def test_invalid_and_conflicting_options_exit_2_before_any_run(tmp_path, capsys, option, field):
    """Each bad option: exit 2 and one line naming the option as typed, before any run."""
    out = tmp_path / "out"
    argv = ["benchmark", *TINY, "--seeds", "1", "--out", str(out), *option]
    if "--policies" not in option:
        argv[1:1] = ["--policies", "never"]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    assert code == 2
    assert field in one_line(capsys.readouterr().err)
    assert not (out / "results.jsonl").exists()


def test_sizes_are_bounded_before_any_job_is_built(tmp_path, capsys):
    """A million seeds of the default eight rules and a baseline at four levels are refused at
    once (not after minutes of building jobs), naming the number of runs and the ways on."""
    t0 = time.monotonic()
    argv = ["benchmark", "--seeds", "1000000", "--baselines", "dead-reckoning", "--quiet",
            "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = one_line(capsys.readouterr().err)
    assert time.monotonic() - t0 < 30
    assert "--seeds 1000000 is invalid" in err and "36000000" in err
    assert "--seed-start" in err and "--executor ray" in err
    from slam_gym.evaluation import benchmark

    with pytest.raises(ValueError, match="seed_start=9223372036854775807 is invalid"):
        benchmark(["never"], seeds=2, seed_start=2**63 - 1, out=tmp_path / "py")
    with pytest.raises(ValueError, match="seeds=.* is invalid: must be distinct seeds"):
        benchmark(["never"], seeds=[1, 1], out=tmp_path / "py")


def test_quick_keeps_explicit_seeds_and_particles():
    from slam_gym.cli import build_parser
    from slam_gym.commands.benchmark import QUICK, apply_quick
    from slam_gym.commands.envargs import env_from_args

    args = build_parser().parse_args(["benchmark", "--quick", "--seeds", "1", "--particles",
                                      "100"])
    apply_quick(args)
    assert (args.trials, args.env_n_particles) == (1, 100)
    assert args.policies == QUICK["policies"] and args.clutter_levels is None
    args = build_parser().parse_args(["benchmark", "--quick"])
    apply_quick(args)
    env = env_from_args(args)  # BB's four levels at BB's 500 particles: the env's own
    assert (args.trials, env.get("n_particles"), env.levels) == (QUICK["seeds"], 500,
                                                                 (0, 1, 2, 3))


def test_a_module_with_a_syntax_error_is_named(user_dir, tmp_path, capsys):
    write_module(user_dir, "broken_rule", "class Rule:\n    def act(self, obs info):\n")
    assert benchmark_cli(tmp_path / "out", "broken_rule:Rule", "--seeds", "1") == 2
    err = one_line(capsys.readouterr().err)
    assert "policy reference='broken_rule:Rule' is invalid" in err and "SyntaxError" in err


def test_output_directory_problems_are_one_line(tmp_path, capsys):
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    for out in (a_file, a_file / "below"):
        assert benchmark_cli(out, "never", "--seeds", "1", "--executor", "serial") == 2
        err = one_line(capsys.readouterr().err)
        assert f"--out {out} is invalid" in err and "output directory" in err


def test_a_locked_output_is_one_line_and_exits_1(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    with ResultsWriter(out / "results.jsonl"):  # another benchmark writing into --out
        assert benchmark_cli(out, "never", "--seeds", "1", "--executor", "serial") == 1
    err = one_line(capsys.readouterr().err)
    assert "being written by another process" in err and "another output directory" in err


def test_a_missing_optional_dependency_names_its_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    assert benchmark_cli(tmp_path / "out", "never", "--seeds", "1", "--executor", "ray") == 1
    assert "pip install slam-gym[ray]" in one_line(capsys.readouterr().err)


INTERRUPTING = '''
import numpy as np


class Rule:
    def reset(self):
        pass

    def act(self, obs, info):
        if info["world_seed"] == 1:
            raise KeyboardInterrupt  # Ctrl-C during the second run
        return np.array([0, 0], dtype=np.int64)
'''


def test_ctrl_c_keeps_the_finished_runs_and_says_how_to_resume(user_dir, tmp_path, capsys):
    write_module(user_dir, "ctrl_c_rule", INTERRUPTING)
    out = tmp_path / "out"
    assert benchmark_cli(out, "ctrl_c_rule:Rule", "--seeds", "2", "--executor", "serial") == 130
    err = one_line(capsys.readouterr().err)
    assert "the 1 finished run(s) of 2 are kept" in err and "rerun the same command" in err
    assert [r["seed"] for r in read_results(out)] == [0]
    with pytest.raises(KeyboardInterrupt):  # --debug: the exception itself, with its traceback
        main(["--debug", "benchmark", "--policies", "ctrl_c_rule:Rule", *TINY, "--seeds", "2",
              "--executor", "serial", "--out", str(out)])


def test_a_corrupt_model_names_the_file_and_never_suggests_unsafe_loading(tmp_path, capsys,
                                                                          recwarn):
    from policies.learned import DEFAULT_MODEL_PATH

    model = tmp_path / "model.zip"
    with zipfile.ZipFile(DEFAULT_MODEL_PATH) as src, zipfile.ZipFile(model, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            dst.writestr(item, b"\x80not a torch file" if item.filename == "policy.pth" else data)
    argv = ["benchmark", "--policies", "learned", "--model", str(model), *TINY, "--seeds", "1",
            "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = one_line(capsys.readouterr().err)
    assert f"--model {model} is invalid" in err and "weights_only" not in err
    assert not [w for w in recwarn if "weights_only" in str(w.message)]  # nor torch's warning
    with pytest.raises(ValueError, match="cannot load it"):
        main(["--debug", *argv])


def test_distinct_long_policy_names_stay_distinct_in_the_console_table():
    import io

    from rich.console import Console

    from slam_gym.evaluation.summary import format_table, summary_document

    def row(name, seed):
        return {"policy": name, "scenario": "brooks-bailey", "clutter_level": 2, "seed": seed,
                "options": {}, "status": "ok", "error": None, "alpha": 0.4, "beta": 0.04,
                "success": True, "failure_iteration": None, "anees": 3.0,
                "nees_in_band_fraction": 0.9, "map_error_m": 1.0, "final_pose_error_m": 1.0,
                "n_fusions": 10, "n_optimisations": 1, "wall_time_s": 1.0,
                "map_completeness": 1.0, "return": -100.0, "fusion_cpu_s": 0.1,
                "optimise_cpu_s": 0.1, "filter_cpu_s": 1.0, "total_cpu_s": 1.2}

    names = ["a_long_package.its_rules_module:RaisesX",
             "a_long_package.its_rules_module:ReturnsNone"]
    doc = summary_document([row(n, s) for n in names for s in (0, 1)])
    console = Console(width=160, file=io.StringIO(), record=True)
    console.print(format_table(doc))
    text = console.export_text()
    assert all(name in text for name in names), text


def test_world_seed_must_be_a_non_negative_integer():
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    env = HybridSLAMEnv(n_particles=5, n_steps=30)
    for bad in (1.7, "abc", float("nan"), -1, True):
        with pytest.raises(ValueError, match="world_seed="):
            env.reset(seed=0, options={"world_seed": bad})
    _, info = env.reset(seed=0, options={"world_seed": np.int64(3)})
    assert info["world_seed"] == 3


def test_step_after_the_end_raises_until_reset():
    """Issue 38: a step past the end would fuse, optimise and charge reward on a finished
    episode; it raises gymnasium.error.ResetNeeded and changes nothing, and reset() starts anew."""
    import gymnasium as gym

    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    env = HybridSLAMEnv(n_particles=5, n_steps=35)  # 3.5 s: reset's second and 3 decisions
    env.reset(seed=0)
    terminated = truncated = False
    while not (terminated or truncated):
        _, _, terminated, truncated, _ = env.step(np.array([1, 1]))
    assert terminated
    metrics, ret, fused = repr(env.episode.metrics()), env.episode_return, env.episode.n_fusions
    with pytest.raises(gym.error.ResetNeeded, match="terminated=True"):
        env.step(np.array([1, 1]))
    assert env.episode_return == ret and env.episode.n_fusions == fused
    assert repr(env.episode.metrics()) == metrics
    env.reset(seed=1)
    env.step(np.array([0, 0]))  # a new episode steps again

    truncating = HybridSLAMEnv(n_particles=20, n_steps=200, max_decisions=2)
    truncating.reset(seed=0)
    truncating.step(np.array([0, 0]))
    assert truncating.step(np.array([0, 0]))[3] is True
    with pytest.raises(gym.error.ResetNeeded, match="truncated=True"):
        truncating.step(np.array([0, 0]))


SLEEPING = '''
import time

import numpy as np


class Rule:
    def reset(self):
        pass

    def act(self, obs, info):
        if info["world_seed"] == 1:
            time.sleep(600)  # a policy that hangs
        return np.array([0, 0], dtype=np.int64)
'''


@pytest.mark.parametrize("executor, limit_s", [("serial", 3), ("process", 25)])
def test_a_run_over_its_time_limit_becomes_an_error_row(user_dir, tmp_path, capsys, executor,
                                                         limit_s):
    """The run that sleeps is stopped after --run-timeout-s (the process executor's limit
    includes starting its worker, hence the longer one), recorded as an error that says so, and
    the benchmark completes its other runs; with the process executor its worker is replaced
    and the next run goes on in a new one."""
    write_module(user_dir, "sleepy_rule", SLEEPING)
    out = tmp_path / "out"
    t0 = time.monotonic()
    code = benchmark_cli(out, "sleepy_rule:Rule", "--seeds", "3", "--executor", executor,
                         "--run-timeout-s", str(limit_s),
                         *(["--workers", "1"] if executor == "process" else []))
    elapsed = time.monotonic() - t0
    assert code == EXIT_RUN_ERRORS
    rows = {r["seed"]: r for r in read_results(out)}
    assert sorted(rows) == [0, 1, 2]
    assert rows[0]["status"] == rows[2]["status"] == "ok"
    assert rows[1]["status"] == "error"
    assert f"per-run limit of {limit_s} s" in rows[1]["error"]
    assert rows[1]["wall_time_s"] >= limit_s
    assert elapsed < 600 / 2  # not the sleep
    assert "1 of 3 runs failed" in capsys.readouterr().err


def test_intervals_of_non_negative_quantities_stay_within_the_runs():
    """Three runs 0.1, 0.2 and 30: the t-interval of their mean reaches far below 0; the
    bootstrap interval the summary gives such quantities stays within [0.1, 30]."""
    from slam_gym.evaluation.summary import interval, mean_interval

    values = [0.1, 0.2, 30.0]
    assert mean_interval(values)[0] < -20.0
    for key in ("map_error_m", "interface_cpu_s", "anees", "map_completeness"):
        lo, hi = interval(key, values)
        assert 0.1 <= lo < np.mean(values) < hi <= 30.0
    assert interval("return", values) == list(mean_interval(values))  # may be negative


def test_the_benchmark_figures_stay_within_their_quantities_bounds(tmp_path, capsys):
    """A small benchmark's Pareto figure: a logarithmic CPU axis, every error bar at CPU > 0 and
    map error >= 0, axes in words with units, and the runs behind each point written beside it."""
    from matplotlib.collections import LineCollection

    from slam_gym.evaluation.plots import pareto_figure

    out = tmp_path / "out"
    # level 0 at 20 particles: both rules survive two of these three worlds (a Pareto point
    # needs successful runs)
    assert main(["benchmark", "--policies", "fixed-10s,fixed-10s-optimise", "--seeds", "3",
                 "--clutter-levels", "0", "--particles", "20", "--n-steps", "150",
                 "--baselines", "", "--quiet", "--executor", "serial",
                 "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)["summary"]
    assert (out / "pareto_interface.png").stat().st_size > 10_000
    for x in ("interface_cpu_s", "total_cpu_s"):
        fig = pareto_figure(doc, x=x)
        ax = fig.axes[0]
        assert ax.get_xscale() == "log" and "(s, log scale)" in fig.get_supxlabel()
        assert ax.get_ylabel() == "map error of the successful runs (m)"
        assert ax.get_ylim()[0] >= 0.0
        segments = [s for c in ax.collections if isinstance(c, LineCollection)
                    for s in c.get_segments()]
        assert len(segments) >= 2  # both policies' intervals are drawn
        points = np.concatenate(segments)
        # a run without a fusion has no interface CPU: a lower bound may be 0 (drawn to the
        # log axis's edge), never below
        assert np.all(points[:, 0] >= 0.0) and np.all(points[:, 1] >= 0.0)
        assert all(x_ > 0.0 for x_, _ in (line.get_xydata()[0] for line in ax.lines
                                           if line.get_marker() == "o"))
        groups = [g for g in doc["groups"] if g.get("map_error_m_succeeded") is not None]
        written = sorted(t.get_text() for t in ax.texts)
        counts = [(g["n_values"]["map_error_m_succeeded"], g["n_values"][x]) for g in groups]
        assert written == sorted(str(a) if a == b else f"{a}/{b}" for a, b in counts)
        assert any(b == 3 for _, b in counts)  # the CPU time of all 3 runs


@pytest.mark.xdist_group("ray")  # one local Ray instance at a time (pytest -n)
def test_the_ray_executor_stops_a_run_over_its_time_limit(tmp_path):
    """Ray runs each job in a worker process's main thread, where the time limit's timer
    interrupts it: the sleeping run is an error row saying so, the other one completes."""
    from test_evaluation import slow_run

    from slam_gym.evaluation import Job, run_jobs

    jobs = [Job("policy", "toy", "brooks-bailey", 0, seed, {"sleep_s": sleep_s})
            for seed, sleep_s in ((0, 0.0), (1, 600.0))]
    t0 = time.monotonic()
    rows = run_jobs(jobs, slow_run, tmp_path, workers=2, executor="ray", progress=False,
                    run_timeout_s=5)
    assert time.monotonic() - t0 < 300
    assert [r["status"] for r in rows] == ["ok", "error"]
    assert "per-run limit of 5 s" in rows[1]["error"]


# slam-gym front and slam-gym threshold-rule: the same exit codes as slam-gym benchmark.

FRONT_TINY = ["--prices", "10", "--seeds", "1", "--clutter-levels", "2", "--particles", "10",
              "--n-steps", "150", "--executor", "serial", "--quiet"]
THRESHOLD_TINY = ["--seeds", "0", "--clutter-levels", "2", "--particles", "10", "--n-steps",
                  "150", "--executor", "serial", "--prices", "1,50", "--quiet"]


def front_argv(out, rules="fixed-10s-optimise"):
    from policies.learned import DEFAULT_MODEL_PATH

    return ["front", "--model", str(DEFAULT_MODEL_PATH), "--rules", rules, *FRONT_TINY,
            "--out", str(out)]


def threshold_rule_argv(out):
    return ["threshold-rule", *THRESHOLD_TINY, "--out", str(out)]


def test_front_with_error_rows_prints_its_tables_and_exits_3_or_0_with_allow_errors(
        user_dir, tmp_path, capsys):
    """A raising rule beside the reference: its run is an error row, it is left out of the
    comparison (the reference and the learned policy are still paired), the tables print, and
    the command exits 3; the same command with --allow-errors exits 0."""
    write_module(user_dir, "front_rule", RAISING.replace("BODY", "raise KeyError('speed')"))
    out = tmp_path / "front"
    argv = front_argv(out, rules="fixed-10s-optimise,front_rule:Rule")
    assert main(argv) == EXIT_RUN_ERRORS
    captured = capsys.readouterr()
    assert "not compared" in captured.out and "front_rule:Rule" in captured.out
    assert "wrote" in captured.out  # the summary printed
    err = captured.err.strip().splitlines()[-1]
    assert "1 of 3 runs failed" in err and "KeyError" in err and "--allow-errors" in err
    doc = json.loads((out / "front.json").read_text())
    assert doc["by_price"]["10"]["not_compared"] == ["front_rule:Rule"]
    assert set(doc["by_price"]["10"]["policies"]) == {"fixed-10s-optimise", "learned @ 10/s"}
    assert [r["status"] for r in read_results(out / "rules")] == ["ok", "error"]

    assert main([*argv, "--allow-errors"]) == 0
    assert "exit 0 (--allow-errors)" in capsys.readouterr().err


def test_threshold_rule_with_error_rows_chooses_among_finished_rules_and_exits_3(
        user_dir, tmp_path, capsys, monkeypatch):
    """A candidate that raises (the grid cut to the family's two ends and that rule): it is
    neither scored nor chosen, the table and choice print, and the command exits 3; with
    --allow-errors, 0."""
    import policies
    from slam_gym.commands import threshold_rule

    write_module(user_dir, "threshold_raising", RAISING.replace("BODY", "raise KeyError('x')"))
    names = ("fixed-10s", "fixed-10s-optimise", "threshold_raising:Rule")
    monkeypatch.setattr(threshold_rule, "candidates",
                        lambda: {name: policies.make(name) for name in names})
    out = tmp_path / "tr"
    assert main(threshold_rule_argv(out)) == EXIT_RUN_ERRORS
    captured = capsys.readouterr()
    assert "not scored (rules with error rows): threshold_raising:Rule (1)" in captured.out
    assert "price 50:" in captured.out and "wrote" in captured.out
    assert "1 of 3 runs failed" in captured.err.strip().splitlines()[-1]
    doc = json.loads((out / "chosen.json").read_text())
    assert doc["not_scored"] == {"threshold_raising:Rule": 1}
    assert [c["rule"] for c in doc["candidates"]] == ["fixed-10s", "fixed-10s-optimise"]
    assert {c["rule"] for c in doc["chosen"].values()} <= {"fixed-10s", "fixed-10s-optimise"}

    assert main([*threshold_rule_argv(out), "--allow-errors"]) == 0
    assert "exit 0 (--allow-errors)" in capsys.readouterr().err


@pytest.mark.parametrize("argv_of, option, field", [
    (front_argv, ["--particles", "-3"], "--particles -3 is invalid"),
    (front_argv, ["--seeds", "0"], "--seeds 0 is invalid"),
    (front_argv, ["--run-timeout-s", "0"], "--run-timeout-s 0 is invalid"),
    (front_argv, ["--workers", "4"], "--workers 4 is invalid with --executor serial"),
    (front_argv, ["--compare-model", "no-such-model.zip"],
     "--compare-model no-such-model.zip is invalid"),
    (front_argv, ["--prices", "abc"], "--prices abc is invalid: must be comma-separated numbers"),
    (front_argv, ["--clutter-levels", "2,2"], "--clutter-levels 2,2 is invalid: must be "
     "distinct levels"),
    (threshold_rule_argv, ["--particles", "-3"], "--particles -3 is invalid"),
    (threshold_rule_argv, ["--n-steps", "0"], "--n-steps 0 is invalid"),
    (threshold_rule_argv, ["--run-timeout-s", "0"], "--run-timeout-s 0 is invalid"),
    (threshold_rule_argv, ["--prices", "1,x"], "--prices 1,x is invalid: must be "
     "comma-separated numbers"),
    (threshold_rule_argv, ["--workers", "4"], "--workers 4 is invalid with --executor serial"),
    (threshold_rule_argv, ["--ray-address", "auto"],
     "--ray-address auto is invalid with --executor serial"),
])
def test_front_and_threshold_rule_reject_invalid_options_with_exit_2_before_any_run(
        tmp_path, capsys, argv_of, option, field):
    out = tmp_path / "out"
    assert main([*argv_of(out), *option]) == 2
    assert field in one_line(capsys.readouterr().err)
    assert not list(out.rglob("results.jsonl"))


def test_a_missing_model_file_is_one_line_naming_it_and_exits_2(tmp_path, capsys):
    from slam_gym.cli import main

    code = main(["benchmark", "--policies", "learned", "--model", str(tmp_path / "nope.zip"),
                 "--seeds", "1", "--n-steps", "30", "--particles", "5", "--clutter-levels", "0",
                 "--baselines", "", "--quiet", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    assert "nope.zip" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
