"""Policies from outside the project: registry, references, entry points and the benchmark API.

The policies below are module-level so the process executor's workers can import them (pytest
puts this folder on ``sys.path``, which spawned workers inherit): the reference
``test_plugins:DistanceRule`` names one.
"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import policies
from policies.registry import PolicyRegistry
from slam_gym.cli import main
from slam_gym.evaluation import benchmark, read_results
from slam_gym.evaluation.core import run_policy_object

ROOT = Path(__file__).resolve().parents[2]
TINY = {"clutter_levels": [2], "env_kwargs": {"n_particles": 10, "n_steps": 150},
        "baselines": [], "figures": False}
"""A tiny benchmark: 15 s of BB's path at clutter level 2 with 10 particles (seed 0 runs all
14 decisions, seed 1 fails at its 4th)."""


class DistanceRule:
    """Fuse once the local map has travelled ``distance_m``; optimise after a loop closure."""

    name = "distance-rule"

    def __init__(self, distance_m: float = 3.0):
        self.distance_m = distance_m

    def reset(self):
        pass

    def act(self, obs, info):
        f = info["features"]
        fuse = f["local_map_distance_m"] >= self.distance_m
        return np.array([fuse, fuse and f["loop_closure_flag"] > 0], dtype=np.int64)


class RaisingRule(DistanceRule):
    name = "raising-rule"

    def act(self, obs, info):
        raise RuntimeError("this rule breaks at its first decision")


class FloatRule(DistanceRule):
    name = "float-rule"

    def act(self, obs, info):
        return np.array([1.0, 0.0])


def distance_rule_factory(distance_m: float = 3.0):
    return DistanceRule(distance_m=distance_m)


DETERMINISTIC_KEYS = ("success", "failure_iteration", "anees", "nees_in_band_fraction",
                      "map_error_m", "final_pose_error_m", "n_fusions", "n_optimisations",
                      "map_completeness", "return", "modelled_compute_s", "alpha", "beta",
                      "clutter_level", "seed", "scenario", "status")
"""Row fields that do not depend on the machine's timing (CPU seconds do)."""


def deterministic_part(rows):
    return [{k: r.get(k) for k in DETERMINISTIC_KEYS} for r in rows]


def test_registry_register_is_idempotent_and_refuses_a_conflicting_name():
    registry = PolicyRegistry({"fixed-10s": lambda: None}, group=None)
    registry.register("distance", DistanceRule)
    registry.register("distance", DistanceRule)  # the same factory again: nothing happens
    assert registry.available() == ["distance", "fixed-10s"]
    assert registry.make("distance", distance_m=3.0).distance_m == 3.0
    with pytest.raises(ValueError, match="name='distance'.*registered"):
        registry.register("distance", distance_rule_factory)
    with pytest.raises(ValueError, match="name='fixed-10s'.*built-in"):
        registry.register("fixed-10s", DistanceRule)
    for bad in ("a,b", "pkg:attr", "", " x"):
        with pytest.raises(ValueError, match="name="):
            registry.register(bad, DistanceRule)
    with pytest.raises(ValueError, match="option.*speed.*distance_m"):
        registry.make("distance", speed=1.0)
    registry.unregister("distance")
    with pytest.raises(ValueError, match="'distance'.*fixed-10s"):
        registry.make("distance")


def test_default_registry_names_references_and_objects():
    policies.register("distance-rule-test", distance_rule_factory)
    try:
        assert "distance-rule-test" in policies.available()
        assert policies.make("distance-rule-test", distance_m=2.0).distance_m == 2.0
    finally:
        policies.unregister("distance-rule-test")
    assert "distance-rule-test" not in policies.available()
    # references: a class (with options), a factory, and an object (copied, not shared)
    assert policies.make("test_plugins:DistanceRule", distance_m=4.0).distance_m == 4.0
    assert isinstance(policies.make("test_plugins:distance_rule_factory"), DistanceRule)
    for bad, what in (("no_such_module_xyz:Rule", "cannot import"),
                      ("test_plugins:NoSuchRule", "no attribute"),
                      ("test_plugins:DETERMINISTIC_KEYS", "policy")):
        with pytest.raises(ValueError, match=what):
            policies.make(bad)


def test_an_action_of_the_wrong_dtype_names_the_policy_and_the_value():
    from slam_gym.envs.spec import resolve_env

    global TINY_ENV
    TINY_ENV = resolve_env(None, {"n_particles": 10, "n_steps": 30})
    with pytest.raises(ValueError,
                       match=r"policy 'float-rule' returned action=array\(\[1., 0.\]\)"):
        run_policy_object(FloatRule(), TINY_ENV, 1, 0)
    with pytest.raises(ValueError, match="policy 'mine' returned action=.*shape \\(3,\\)"):
        run_policy_object(type("Three", (DistanceRule,), {"act": lambda s, o, i: [1, 0, 0]})(),
                          TINY_ENV, 1, 0, policy_name="mine")


def test_the_command_and_the_api_give_the_same_rows(tmp_path, capsys):
    """A rule of this module by reference through the command (serial) and as an object and a
    registered name through the API (process executor, 2 workers): the same rows."""
    assert main(["benchmark", "--policies", "test_plugins:DistanceRule", "--clutter-levels", "2",
                 "--seeds", "2", "--particles", "10", "--n-steps", "150", "--baselines", "",
                 "--no-figures", "--executor", "serial", "--out", str(tmp_path / "cli"),
                 "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    cli_rows = read_results(tmp_path / "cli" / "results.jsonl")
    assert [r["policy"] for r in cli_rows] == ["test_plugins:DistanceRule"] * 2
    assert all(r["status"] == "ok" for r in cli_rows)
    assert {r["n_fusions"] for r in cli_rows} != {0}  # the rule did fuse

    policies.register("distance-registered", DistanceRule)
    try:
        api = benchmark([DistanceRule(), "distance-registered"], seeds=2, workers=2,
                        executor="process", out=tmp_path / "api", **TINY)
    finally:
        policies.unregister("distance-registered")
    by_name = {}
    for row in api.rows:
        by_name.setdefault(row["policy"], []).append(row)
    assert set(by_name) == {"distance-rule", "distance-registered"}
    for rows in by_name.values():
        assert deterministic_part(rows) == deterministic_part(cli_rows)
    assert api.summary["n_runs"] == 4 and api.summary["n_errors"] == 0
    assert cli["summary"]["groups"][0]["n_fusions"] == api.summary["groups"][0]["n_fusions"]
    assert (api.out / "summary.json").exists() and (api.out / "table.md").exists()


def test_a_raising_policy_gives_error_rows_and_the_rest_completes(tmp_path):
    result = benchmark([RaisingRule(), FloatRule(), DistanceRule()], seeds=1, executor="serial",
                       out=tmp_path, **TINY)
    status = {r["policy"]: r for r in result.rows}
    assert status["distance-rule"]["status"] == "ok"
    assert status["distance-rule"]["n_fusions"] >= 1
    assert status["raising-rule"]["status"] == "error"
    assert "RuntimeError: this rule breaks" in status["raising-rule"]["error"]
    assert status["float-rule"]["status"] == "error"
    assert "policy 'float-rule' returned action=" in status["float-rule"]["error"]
    assert result.summary["n_errors"] == 2 and result.summary["n_ok"] == 1


def test_the_api_refuses_what_cannot_reach_a_worker(tmp_path):
    class LocalRule(DistanceRule):  # defined in a function: does not pickle
        name = "local-rule"

    with pytest.raises(ValueError, match="policy 'local-rule' is invalid for executor='process'"):
        benchmark([LocalRule()], seeds=1, executor="process", out=tmp_path, **TINY)
    with pytest.raises(ValueError, match="distinct names"):
        benchmark([DistanceRule(), DistanceRule(3.0)], seeds=1, out=tmp_path, **TINY)
    with pytest.raises(ValueError, match="policies\\[0\\]"):
        benchmark([42], seeds=1, out=tmp_path, **TINY)
    with pytest.raises(ValueError, match="policy name='no-such-rule'"):
        benchmark(["no-such-rule"], seeds=1, out=tmp_path, **TINY)
    assert not (tmp_path / "results.jsonl").exists()  # nothing ran


PLUGIN_MODULE = '''
import numpy as np


class EveryNDecisions:
    """A plug-in's rule: fuse at every n-th decision."""

    name = "every-n"

    def __init__(self, n=3):
        self.n = n
        self.count = 0

    def reset(self):
        self.count = 0

    def act(self, obs, info):
        self.count += 1
        return np.array([self.count % self.n == 0, 0], dtype=np.int64)
'''


def test_an_installed_plugin_appears_in_available_and_runs_in_worker_processes(tmp_path):
    """A distribution on sys.path (a dist-info folder with entry_points.txt, as pip installs
    one) declares policy ``every-n``: a fresh interpreter lists it and benchmarks it through the
    command with 2 worker processes, which find it by the same entry point."""
    site = tmp_path / "site"
    (site / "demo_plugin").mkdir(parents=True)
    (site / "demo_plugin" / "__init__.py").write_text(PLUGIN_MODULE)
    info = site / "demo_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: demo-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[slam_gym.policies]\nevery-n = demo_plugin:EveryNDecisions\n")
    script = textwrap.dedent(f"""
        import json, policies
        from slam_gym.cli import main
        assert "every-n" in policies.available(), policies.available()
        assert policies.make("every-n", n=5).n == 5
        code = main(["benchmark", "--policies", "every-n,fixed-10s", "--clutter-levels", "2",
                     "--seeds", "2", "--particles", "10", "--n-steps", "150", "--baselines", "",
                     "--no-figures", "--workers", "2", "--executor", "process", "--quiet",
                     "--out", {str(tmp_path / 'out')!r}])
        raise SystemExit(code)
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = read_results(tmp_path / "out" / "results.jsonl")
    assert sorted(r["policy"] for r in rows) == ["every-n", "every-n", "fixed-10s", "fixed-10s"]
    assert all(r["status"] == "ok" for r in rows), [r["error"] for r in rows]
    # one world runs the 14 decisions of its 15 s (the first second is reset's): every third
    # decision fuses, 4 times; the other fails at its 4th decision, after 1 fusion
    fusions = {r["seed"]: r["n_fusions"] for r in rows if r["policy"] == "every-n"}
    # (which of the two -v1 worlds fails is the draws', not the plug-in's)
    assert sorted(fusions.values()) == [1, 4]
