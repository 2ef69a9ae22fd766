"""One env spec through every command (issue 55): ids and kwargs resolved once, jobs that build
``gym.make(id, **kwargs)``, rows that say what made them, names that parse back."""

import json
import logging
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from realdata import MRCLAM_DIR

import policies
from policies.heuristics import THRESHOLD_FEATURES, ThresholdOptimise
from slam_gym.cli import main
from slam_gym.envs.spec import (
    ALL_LEVELS,
    ResolvedEnv,
    check_env_id,
    parse_env_kwargs,
    registered_ids,
    resolve_env,
)
from slam_gym.envs.tasks import ZonesEnv, ZonesStarvedEnv
from slam_gym.evaluation import benchmark
from slam_gym.evaluation.compare import compare
from slam_gym.evaluation.results import read_results

REPO = Path(__file__).resolve().parents[2]
SIMULATED = [i for i in registered_ids() if "MRCLAM" not in i]
RECORDED = [i for i in registered_ids() if "MRCLAM" in i]
TINY = {"n_particles": 5, "n_steps": 30}
"""Small runs of any simulated id: few particles, a path cut to 30 iterations (3 decisions)."""


def tiny(env_id: str) -> dict:
    """Keyword arguments that keep a run of ``env_id`` to a fraction of a second."""
    if env_id in RECORDED:
        return {"data_dir": str(MRCLAM_DIR), "robot": 2, "n_particles": 5, "n_steps": 30}
    return dict(TINY)


class ConfigProbe:
    """A rule (BB's 10 s) that writes the options of the env it is bound to into ``path``, once
    per run: what a job built, seen from inside the worker."""

    name = "probe"

    def __init__(self, path: str):
        self.path = path
        self.rule = policies.make("fixed-10s")

    def bind_env(self, env) -> None:
        kwargs = type(env).resolved_kwargs(**_config_kwargs(env))
        with open(self.path, "a") as fh:
            fh.write(json.dumps({"class": type(env).__name__, "kwargs": kwargs}) + "\n")

    def reset(self) -> None:
        self.rule.reset()

    def act(self, obs, info):
        return self.rule.act(obs, info)


def _config_kwargs(env) -> dict:
    """The env's config as keyword arguments, and a recording's own options."""
    kwargs = env.config.as_kwargs()
    if hasattr(env, "robot"):
        from slam_gym.envs.mrclam import SIMULATION_ONLY_OPTIONS

        for name in SIMULATION_ONLY_OPTIONS:
            kwargs.pop(name, None)
        kwargs.update(robot=env.robot, data_dir=str(env.data_dir))
    return kwargs


def made_config(env_id: str, kwargs: dict) -> dict:
    """What ``gym.make(id, **kwargs)`` builds, as the probe sees it (before any reset)."""
    env = gym.make(env_id, **kwargs).unwrapped
    return {"class": type(env).__name__, "kwargs": type(env).resolved_kwargs(**_config_kwargs(env))}


def test_tasks_hold_their_defaults_and_the_registration_reads_them():
    assert ZonesEnv().config.scenario == "brooks-bailey-zones"
    assert ZonesStarvedEnv().config.n_particles == 150
    for env_id in ("SlamGym/HybridSLAM-Zones-v1", "SlamGym/HybridSLAM-ZonesStarved-v1",
                   "SlamGym/HybridSLAM-LongMission-v1"):
        spec = gym.spec(env_id)
        cls = gym.make(env_id).unwrapped.__class__
        assert dict(spec.kwargs) == cls.DEFAULTS
        assert gym.make(env_id).unwrapped.config == cls().config


def test_a_task_draws_its_clutter_level_per_episode_from_its_seed():
    env = gym.make("SlamGym/HybridSLAM-Zones-v1", n_steps=20, n_particles=5)
    levels = []
    for seed in range(40):
        env.reset(seed=seed)
        levels.append(env.unwrapped.config.clutter_level)
    assert set(levels) == set(ALL_LEVELS)  # 40 draws miss a level with probability < 4e-5
    again = []
    for seed in range(40):
        env.reset(seed=seed)
        again.append(env.unwrapped.config.clutter_level)
    assert again == levels
    env.reset(seed=3, options={"clutter_level": 1})
    assert env.unwrapped.config.clutter_level == 1
    env.reset(seed=3)  # a level given once does not stick: the next episode draws again
    assert env.unwrapped.config.clutter_level == levels[3]


@pytest.mark.parametrize("env_id", registered_ids())
def test_every_id_resolves_to_what_gym_make_builds(env_id):
    kwargs = tiny(env_id)
    env = resolve_env(env_id, kwargs)
    expected_id = env_id  # resolve_env only maps wrapped ids when asked (per_decision)
    assert env.env_id == expected_id
    made = env.make().unwrapped
    assert made.config == gym.make(env_id, **kwargs).unwrapped.config
    assert env == ResolvedEnv.of(env.env_id, env.kwargs)  # kwargs survive JSON


@pytest.mark.parametrize("env_id", registered_ids())
def test_benchmark_and_compare_jobs_build_gym_makes_env_for_every_id(env_id, tmp_path):
    """Each job's env, seen from inside the run, has the configuration of ``gym.make(id)`` with
    the same keyword arguments: nothing of the id is dropped on the way."""
    kwargs = tiny(env_id)
    probe = tmp_path / "probe.jsonl"
    spec = resolve_env(env_id, kwargs, per_decision=True)
    level = None if spec.levels == (None,) else spec.levels[0]
    result = benchmark({"probe": ConfigProbe(str(probe))}, env=env_id, env_kwargs=kwargs,
                       clutter_levels=None if level is None else [level], seeds=1,
                       baselines=[], figures=False, out=tmp_path / "b", executor="serial")
    assert all(r["status"] == "ok" for r in result.rows), result.rows[0].get("error")
    compare("fixed-10s", ConfigProbe(str(probe)), env=env_id, env_kwargs=kwargs,
            clutter_levels=None if level is None else [level], seeds=2, draws=1,
            out=tmp_path / "c", executor="serial")
    seen = [json.loads(line) for line in probe.read_text().splitlines()]
    assert len(seen) == 3  # one benchmark run, two compare worlds of B
    want = made_config(spec.env_id, kwargs)
    for entry in seen:
        got = dict(entry["kwargs"])
        if level is not None:  # the world's level is a reset option: the rest is gym.make's
            got["clutter_level"] = want["kwargs"]["clutter_level"]
        assert entry["class"] == want["class"]
        assert got == want["kwargs"]
    row = result.rows[0]
    assert row["env_id"] == spec.env_id and row["env_kwargs"] == spec.kwargs


@pytest.mark.parametrize(("env_id", "scenario", "particles"), [
    ("SlamGym/HybridSLAM-ZonesStarved-v1", "brooks-bailey-zones", 150),
    ("SlamGym/HybridSLAM-Light-v1", "brooks-bailey", 100),
])
def test_the_benchmark_command_keeps_what_the_id_says(env_id, scenario, particles, tmp_path):
    out = tmp_path / "b"
    assert main(["benchmark", "--env", env_id, "--policies", "fixed-10s", "--seeds", "1",
                 "--clutter-levels", "2", "--n-steps", "30", "--baselines", "", "--no-figures",
                 "--executor", "serial", "--out", str(out), "--quiet"]) == 0
    (row,) = read_results(out)
    assert row["scenario"] == scenario and row["env_kwargs"]["n_particles"] == particles
    assert row["env_id"] == env_id
    assert row["code"]["commit"] is None or len(row["code"]["commit"]) == 40
    assert isinstance(row["code"]["dirty"], (bool, type(None)))
    assert row["code"]["version"] and row["finished_at"].endswith("+00:00")


def test_an_option_that_contradicts_the_id_overrides_it_in_one_line(caplog):
    with caplog.at_level(logging.WARNING, logger="slam_gym.envs.spec"):
        env = resolve_env("SlamGym/HybridSLAM-Light-v1", shorthands={"n_particles": 200})
    assert env.get("n_particles") == 200
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "n_particles=200 overrides the id's n_particles=100" in lines[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="slam_gym.envs.spec"):
        resolve_env("SlamGym/HybridSLAM-Light-v1", {"n_particles": 100})  # agrees: no line
    assert not caplog.records
    with pytest.raises(ValueError, match="n_particles=200 is invalid.*given twice"):
        resolve_env(None, {"n_particles": 100}, shorthands={"n_particles": 200})
    with pytest.raises(ValueError, match="n_particles=0 is invalid"):
        resolve_env(None, shorthands={"n_particles": 0})
    with pytest.raises(ValueError, match="unknown option"):
        resolve_env(None, {"n_particle": 10})


def test_an_unknown_id_gets_one_line_naming_the_closest():
    with pytest.raises(ValueError) as info:
        check_env_id("SlamGym/HybridSLAM-Zone-v1")
    message = str(info.value)
    assert "\n" not in message and len(message) < 300
    assert "did you mean SlamGym/HybridSLAM-Zones-v1" in message
    with pytest.raises(ValueError) as far:  # nothing close: how to list them, as a command
        check_env_id("Foo")
    command = str(far.value).split('python -c "')[1].split('"')[0]
    listed = subprocess.run([sys.executable, "-c", command], capture_output=True, text=True,
                            cwd=REPO, check=True).stdout
    assert "SlamGym/HybridSLAM-Zones-v1" in listed


def test_env_kwargs_parse_as_json_else_text():
    assert parse_env_kwargs(["n_particles:150", "scenario:brooks-bailey-zones",
                             "features:[\"ess_ratio\"]", "clutter_level:null"]) == {
        "n_particles": 150, "scenario": "brooks-bailey-zones", "features": ["ess_ratio"],
        "clutter_level": None}
    with pytest.raises(ValueError, match="env_kwargs"):
        parse_env_kwargs(["n_particles=150"])
    with pytest.raises(ValueError, match="given twice"):
        parse_env_kwargs(["n_steps:1", "n_steps:2"])


def test_resume_keys_on_the_resolved_env(tmp_path):
    def run(**kwargs):
        return benchmark(["fixed-10s"], env="SlamGym/HybridSLAM-v1", env_kwargs=kwargs,
                         clutter_levels=[1], seeds=1, baselines=[], figures=False,
                         out=tmp_path, executor="serial").rows

    first = run(**TINY)
    assert run(**TINY) == first  # the same env: the row is reused
    other = run(**(TINY | {"n_particles": 6}))
    assert other[0]["key"] != first[0]["key"] and other[0]["env_kwargs"]["n_particles"] == 6
    assert len(read_results(tmp_path)) == 2


def every_printable_threshold_name():
    """Names of the threshold family as ``slam-gym threshold-rule`` and the headroom report
    print them: the declared grid, its ends, and thresholds whose shortest form loses digits."""
    from slam_gym.commands.threshold_rule import DEFAULT_GRID, rule_name

    names = [rule_name(f, t) for f, ts in DEFAULT_GRID.items() for t in ts]
    rng = np.random.default_rng(55)
    for feature in THRESHOLD_FEATURES:
        for threshold in (0.0, 1.0, 0.1 + 0.2, float(rng.uniform(0, 100)), 1e-7, 3e5):
            names.append(rule_name(feature, threshold))
            names.append(ThresholdOptimise.format_name(feature, threshold, interval_s=7.5))
    return names


@pytest.mark.parametrize("name", every_printable_threshold_name())
def test_every_printed_threshold_name_parses_back_to_its_rule(name):
    rule = policies.make(name)
    assert rule.name == name  # it prints the name it was made from
    again = ThresholdOptimise.format_name(rule.feature, rule.threshold, rule.interval_s)
    assert again == name
    assert policies.REGISTRY.digest(name) is None  # the project's own code


def test_the_headroom_tables_best_rule_is_accepted_by_every_command(tmp_path):
    name = "threshold-optimise[global_position_std_m>=2]"
    rule = policies.make(name)
    assert (rule.feature, rule.threshold) == ("global_position_std_m", 2.0)
    result = compare(name, "fixed-10s-optimise", env_kwargs=TINY, clutter_levels=[1], seeds=2,
                     draws=1, out=tmp_path, executor="serial")
    assert result.a == name
    with pytest.raises(ValueError, match="without brackets"):
        policies.make("fixed-10s[global_position_std_m>=2]")
    with pytest.raises(ValueError, match="FEATURE>=THRESHOLD"):
        policies.make("threshold-optimise[global_position_std_m<2]")


def test_compare_refuses_a_group_sequential_design_without_max_worlds_in_the_library(tmp_path):
    with pytest.raises(ValueError, match="design='group-sequential' is invalid"):
        compare("fixed-10s", "fixed-10s-optimise", metric="success", design="group-sequential",
                out=tmp_path)
    assert main(["compare", "fixed-10s", "fixed-10s-optimise", "--metric", "success",
                 "--design", "group-sequential", "--out", str(tmp_path)]) == 2


def test_train_refuses_bad_seeds_and_particles_before_writing_anything(tmp_path, capsys):
    out = tmp_path / "train"
    assert main(["train", "--seeds", "-1", "--out", str(out)]) == 2
    assert main(["train", "--particles", "0", "--out", str(out)]) == 2
    assert main(["train", "--env", "SlamGym/HybridSLAM-Zone-v1", "--out", str(out)]) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert "training" not in err
    assert "--particles 0 is invalid" in err and "did you mean" in err


def test_speed_checks_its_ids_before_measuring(tmp_path, capsys):
    assert main(["speed", "--tasks", "SlamGym/HybridSLAM-Zonez-v1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "did you mean SlamGym/HybridSLAM-Zones-v1" in err
    assert not (tmp_path / "speed.json").exists()


def test_a_closed_pipe_ends_quietly(tmp_path):
    """``slam-gym compare ... | head -1``: the reader has gone; the command ends as a Unix tool
    does (exit 141, no traceback). The read end is closed before the command writes, so every
    write meets the closed pipe (as it does once head has its line)."""
    import os

    read_end, write_end = os.pipe()
    os.close(read_end)
    command = [sys.executable, "-m", "slam_gym.cli", "compare", "fixed-10s", "fixed-10s-optimise",
               "--n-steps", "30", "--particles", "5", "--seeds", "2", "--draws", "1",
               "--clutter-levels", "1", "--executor", "serial", "--quiet",
               "--out", str(tmp_path)]
    done = subprocess.run(command, stdout=write_end, stderr=subprocess.PIPE, cwd=REPO,
                          timeout=300, check=False)
    os.close(write_end)
    assert b"Traceback" not in done.stderr and b"BrokenPipeError" not in done.stderr
    assert done.returncode == 141
    assert (tmp_path / "compare.json").is_file()  # the work was done and kept


def test_train_on_a_task_evaluates_on_its_worlds_and_its_model_names_the_task(tmp_path, capsys):
    """``slam-gym train --env SlamGym/HybridSLAM-Zones-v1`` at a tiny size: the training, its
    evaluations and the model's record are the task's, and the model matches the code."""
    task = "SlamGym/HybridSLAM-Zones-v1"
    out = tmp_path / "train"
    assert main(["train", "--env", task, "--timesteps", "64", "--n-envs", "1", "--particles",
                 "5", "--n-steps", "120", "--hp", "n_steps=32", "--hp", "batch_size=32",
                 "--hp", "n_epochs=1", "--seeds", "0", "--eval-every", "1000", "--eval-seeds",
                 "3", "--eval-workers", "1", "--clutter-levels", "1", "--baseline", "none",
                 "--out", str(out), "--json"]) == 0
    capsys.readouterr()
    config = json.loads((out / "model.json").read_text())
    assert config["env_id"] == task
    assert config["fingerprint"]["env_id"] == task
    assert config["fingerprint"]["env_options"]["scenario"] == "brooks-bailey-zones"
    evaluated = [r for p in (out / "seed-0" / "evals").glob("*/results.jsonl")
                 for r in read_results(p.parent)]
    assert evaluated and {r["scenario"] for r in evaluated} == {"brooks-bailey-zones"}
    assert {r["env_id"] for r in evaluated} == {task}
    assert {r["clutter_level"] for r in evaluated} == {1}
    assert main(["fingerprint", str(out / "model.zip"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["matches"] and doc["fingerprint"]["env_id"] == task


def test_the_headroom_command_runs_a_task_and_refuses_a_rule_chosen_elsewhere(tmp_path, capsys):
    """``slam-gym headroom --env ID`` at a tiny size: rows of the task's env, a report whose
    best rule is the threshold rule under its own name, and ``--table`` over the report; a
    ``chosen.json`` made in another env is refused before any run."""
    task = "SlamGym/HybridSLAM-ZonesStarved-v1"
    name = "threshold-optimise[global_position_std_m>=2]"
    chosen = {"env_id": task, "env_kwargs": {"scenario": "brooks-bailey-zones",
                                             "n_particles": 150},
              "chosen": {"10": {"rule": name, "feature": "global_position_std_m",
                                "threshold": 2.0}}}
    (tmp_path / "chosen.json").write_text(json.dumps(chosen))
    out = tmp_path / "h"
    assert main(["headroom", "--env", task, "--seeds", "2", "--seed-start", "0",
                 "--clutter-levels", "1", "--n-steps", "30", "--policies", "fixed-10s",
                 "--threshold-rule", str(tmp_path / "chosen.json"), "--executor", "serial",
                 "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "headroom.json").read_text())
    assert doc["best_rule"] == name and doc["task"] == task
    assert doc["clutter_levels"] == [1] and doc["env_kwargs"]["n_particles"] == 150
    assert {r["env_id"] for r in read_results(out)} == {task}
    assert policies.make(doc["best_rule"]).threshold == 2.0  # the name it prints types back
    capsys.readouterr()
    assert main(["headroom", "--table", str(out / "headroom.json")]) == 0
    assert f"`{name}`" in capsys.readouterr().out
    other = tmp_path / "other"
    assert main(["headroom", "--env", "SlamGym/HybridSLAM-Zones-v1", "--seeds", "2",
                 "--threshold-rule", str(tmp_path / "chosen.json"), "--out", str(other)]) == 2
    assert "chosen in another env" in capsys.readouterr().err and not other.exists()
