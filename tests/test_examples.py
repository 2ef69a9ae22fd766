"""The examples run, at a reduced size (each states its full-size time in its docstring)."""

import os
import subprocess
import sys
from pathlib import Path

from slam_gym.evaluation import read_results

ROOT = Path(__file__).resolve().parents[1]
EXCERPT = ROOT / "tests" / "data" / "mrclam" / "MRCLAM_Dataset7"


def run_example(name, *args, cwd):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run([sys.executable, str(ROOT / "examples" / name), *map(str, args)],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_custom_policy_registers_a_rule_and_benchmarks_it_in_worker_processes(tmp_path):
    out = run_example("custom_policy.py", "--seeds", "1", "--particles", "10", "--n-steps",
                      "150", "--clutter-levels", "2", "--workers", "2", "--out", tmp_path,
                      cwd=tmp_path)
    rows = read_results(tmp_path / "results.jsonl")
    names = sorted(r.get("policy") or r.get("system") for r in rows)
    assert names == ["dead-reckoning", "distance-or-ambiguity", "fixed-10s",
                     "fixed-10s-optimise"]
    assert all(r["status"] == "ok" for r in rows), [r["error"] for r in rows]
    assert "| distance-or-ambiguity |" in out
    assert "figure success:" in out and (tmp_path / "success_rates.png").is_file()


def test_train_ppo_trains_evaluates_and_benchmarks_against_fixed_10s(tmp_path):
    out = run_example("train_ppo.py", "--timesteps", "32", "--particles", "10", "--n-steps",
                      "150", "--seeds", "1", "--workers", "1", "--out", tmp_path, cwd=tmp_path)
    assert "evaluation at 16 decisions" in out and "evaluation at 32 decisions" in out
    assert (tmp_path / "model.zip").is_file() and (tmp_path / "model.json").is_file()
    assert (tmp_path / "eval" / "evaluations.csv").is_file()
    rows = read_results(tmp_path / "benchmark" / "results.jsonl")
    assert sorted(r["policy"] for r in rows) == ["fixed-10s", "learned"]
    assert all(r["status"] == "ok" for r in rows), [r["error"] for r in rows]
    learned = next(r for r in rows if r["policy"] == "learned")
    assert learned["options"]["model_path"] == str(tmp_path / "model.zip")


def test_real_data_runs_a_rule_and_the_shipped_model_on_mrclam(tmp_path):
    out = run_example("real_data.py", "--data", EXCERPT, "--robots", "1", "--seconds", "8",
                      "--particles", "10", cwd=tmp_path)
    lines = [line for line in out.splitlines() if line.startswith("| 1 |")]
    assert [line.split("|")[2].strip() for line in lines] == ["fixed-10s", "learned"]
    for line in lines:
        cells = [c.strip() for c in line.split("|")[3:-1]]
        assert float(cells[1]) >= 0.0 and float(cells[2]) > 0.0  # pose error, ANEES
