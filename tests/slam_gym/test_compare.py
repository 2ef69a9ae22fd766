"""``slam-gym compare A B``: paired by world on common random numbers, sequential, resumable."""

import json

import numpy as np
import pytest

from slam_gym.cli import main
from slam_gym.evaluation.compare import compare

TINY = ["--particles", "15", "--n-steps", "120", "--clutter-levels", "1,2",
        "--executor", "serial", "--quiet"]


SMALL = {"n_particles": 15, "n_steps": 120}
"""A world of 12 s at 15 particles: small comparisons."""


def run_cli(capsys, *argv):
    code = main(["compare", *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_a_policy_against_itself_is_not_worse_and_runs_once(tmp_path):
    result = compare("fixed-10s", "fixed-10s", metric="success", margin=40, draws=2,
                     max_worlds=40, batch_seeds=2, clutter_levels=[1, 2], env_kwargs=SMALL,
                     executor="serial", out=tmp_path / "c")
    assert result.decision == "not worse"
    assert result.worlds < 40  # decided before the last batch
    for name, m in result.metrics.items():  # the same runs on both sides: no difference
        if m["difference"] is not None:
            # the two arms' means are sums of the same floats: equal up to the rounding of a
            # sum of ~100 values (1e-12 of the mean's size), whatever order numpy sums them in
            assert m["difference"] == pytest.approx(0.0, abs=1e-12 * max(1.0, abs(m["a"]))), name
    lines = (tmp_path / "c" / "results.jsonl").read_text().splitlines()
    assert len(lines) == result.worlds * 2  # one arm's runs (2 draws a world), not two
    assert {json.loads(line)["draw"] for line in lines} == {0, 1}


def test_group_sequential_design_is_planned_for_max_worlds(tmp_path, capsys):
    """The same question under the group-sequential design: its looks' intervals are the
    repeated confidence intervals of a design planned for --max-worlds (16 seeds at one clutter
    level: the seed is the unit, no look before paired.MIN_SEEDS seeds), narrower than the
    confidence sequence's on the same rows (the design's reason), and the JSON names it; every
    metric of a sequential run says its interval holds at the stop."""
    argv = ["fixed-10s", "fixed-10s", "--metric", "success", "--margin", "40", "--draws", "1",
            "--max-worlds", "16", "--batch-seeds", "16", "--json", "--out", str(tmp_path / "g"),
            *TINY, "--clutter-levels", "1"]
    code, out, _ = run_cli(capsys, *argv, "--design", "group-sequential")
    assert code == 0
    gsd = json.loads(out)
    assert gsd["question"]["design"] == "group-sequential"
    assert gsd["looks"][-1]["method"] == "group-sequential-rci"
    assert gsd["metrics"]["success"]["method"] == "group-sequential-rci"
    for name, m in gsd["metrics"].items():
        assert m["anytime_valid"] is True, name
    code, out, _ = run_cli(capsys, *argv)  # the same rows, not rerun, under the sequence
    cs = json.loads(out)
    assert cs["question"]["design"] == "confidence-sequence"
    lo_g, hi_g = gsd["looks"][-1]["oriented_ci"]
    lo_c, hi_c = cs["looks"][-1]["oriented_ci"]
    assert lo_c < lo_g <= hi_g < hi_c


def test_the_printed_level_follows_alpha_and_every_metric_names_its_method(tmp_path, capsys):
    """--alpha 0.1: the summary and the question print 90 % intervals, and the JSON's metrics
    carry level 0.9, their method, anytime_valid false (a fixed design) and the seeds."""
    argv = ["fixed-10s", "fixed-10s-optimise", "--metric", "success", "--margin", "5",
            "--seeds", "2", "--draws", "1", "--alpha", "0.1", "--out", str(tmp_path / "a"),
            *TINY]
    code = main(["compare", *argv[:-1]])  # without --quiet: the text report
    text = capsys.readouterr().out
    assert code == 0
    assert "90 % fixed-sample intervals" in text and "95 %" not in text
    assert "90 % interval of the gain" in text
    doc = json.loads((tmp_path / "a" / "compare.json").read_text())
    assert doc["level"] == pytest.approx(0.9)
    for name, m in doc["metrics"].items():
        if m["ci"] is not None:
            assert m["level"] == pytest.approx(0.9) and m["anytime_valid"] is False, name
            assert m["method"] and m["seeds"] == 2, name
    assert doc["metrics"]["success"]["method"].startswith("bonett-price-cluster")


def test_json_names_the_decision_worlds_draws_and_each_metric(tmp_path, capsys):
    code, out, _ = run_cli(capsys, "fixed-10s", "always", "--metric", "map_error_m", "--margin",
                           "0.5", "--seeds", "2", "--draws", "2", "--json", "--out",
                           str(tmp_path / "j"), *TINY)
    assert code == 0
    doc = json.loads(out)
    assert doc["decision"] in ("better", "not worse", "worse", "undecided")
    assert doc["worlds"] == 4 and doc["draws"] == 2
    for name in ("success", "nees_in_band_fraction", "anees", "map_error_m", "interface_cpu_s",
                 "return"):
        m = doc["metrics"][name]
        assert set(m) >= {"a", "b", "difference", "ci"}
    cpu = doc["metrics"]["interface_cpu_s"]
    assert cpu["difference"] == pytest.approx(cpu["b"] - cpu["a"])
    assert cpu["b"] > cpu["a"]  # fusing at every decision costs more than every 10 s
    assert (tmp_path / "j" / "compare.json").is_file()


def test_a_killed_comparison_resumes_without_rerunning_finished_worlds(tmp_path, capsys):
    out = tmp_path / "r"
    argv = ["fixed-10s", "fixed-10s-optimise", "--seeds", "2", "--draws", "1", "--out",
            str(out), *TINY]
    assert run_cli(capsys, *argv)[0] == 0
    path = out / "results.jsonl"
    lines = path.read_text().splitlines()
    assert len(lines) == 8  # 2 seeds x 2 levels x 2 policies
    path.write_text("\n".join(lines[:3]) + "\n" + lines[3][:20])  # killed while writing
    assert run_cli(capsys, *argv)[0] == 0
    again = path.read_text().splitlines()
    assert again[:3] == lines[:3]  # kept as they were (their times too): not rerun
    assert len(again) == 8
    assert sorted(json.loads(x)["key"] for x in again) == sorted(json.loads(x)["key"]
                                                                for x in lines)


@pytest.mark.parametrize("argv, says", [
    (["fixed-10s", "no-such-rule"], "no-such-rule"),
    (["fixed-10s", "always", "--margin", "5"], "--margin"),
    (["fixed-10s", "always", "--draws", "0"], "--draws"),
    (["fixed-10s", "always", "--metric", "success", "--margin", "5", "--max-worlds", "3"],
     "--max-worlds"),
    (["fixed-10s", "always", "--metric", "success", "--margin", "-1"], "--margin"),
    (["fixed-10s", "always", "--seeds", "1"], "--seeds"),
    (["fixed-10s", "always", "--metric", "map_error_m", "--margin", "1", "--max-worlds", "16",
      "--design", "group-sequential"], "--design"),
    (["fixed-10s", "always", "--metric", "success", "--margin", "5",
      "--design", "group-sequential"], "--design"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, says):
    code, out, err = run_cli(capsys, *argv, "--out", str(tmp_path / "bad"), *TINY)
    assert code == 2
    assert says in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "bad" / "results.jsonl").exists()  # checked before any run


def test_plan_prints_the_worlds_a_margin_needs(tmp_path, capsys):
    code, out, _ = run_cli(capsys, "fixed-10s", "fixed-10s-optimise", "--metric", "success",
                           "--margin", "10", "--plan", "--seeds", "2", "--json", "--out",
                           str(tmp_path / "p"), *TINY)
    assert code == 0
    plan = json.loads(out)["plan"]
    assert plan["pilot_worlds"] == 4
    assert plan["sequential"]["worlds"] >= plan["fixed"]["worlds"] >= 2


def test_a_policy_object_that_cannot_reach_a_worker_is_refused_before_any_run(tmp_path):
    class LocalRule:  # defined in a function: does not pickle to a worker process
        name = "local-rule"

        def reset(self):
            pass

        def act(self, obs, info):
            return np.zeros(2, dtype=np.int64)

    with pytest.raises(ValueError, match="policy 'local-rule' is invalid for executor='process'"):
        compare("fixed-10s", LocalRule(), seeds=2, clutter_levels=[1], env_kwargs=SMALL,
                executor="process", out=tmp_path / "c")
    assert not (tmp_path / "c").exists()  # refused before the output folder was made


class BreaksFromSeed16:
    """Fuses every 10 s on worlds 0-15 and raises on every later world (a batch of failed
    runs)."""

    name = "breaks-from-seed-16"

    def reset(self):
        pass

    def act(self, obs, info):
        if info["world_seed"] >= 16:
            raise RuntimeError("broken from the second batch on")
        return np.array([info["features"]["local_map_age_s"] >= 10.0, 0], dtype=np.int64)


def test_a_batch_that_adds_no_world_is_no_new_look(tmp_path):
    """B's second batch fails in every run: the group-sequential design does not look again at
    the same 16 seeds (its looks must add units), and the comparison ends undecided with the
    failed runs counted, instead of stopping on an error."""
    result = compare("fixed-10s", BreaksFromSeed16(), metric="success", margin=1,
                     draws=1, max_worlds=32, batch_seeds=16, design="group-sequential",
                     clutter_levels=[1], env_kwargs=SMALL, executor="serial",
                     out=tmp_path / "c")
    assert result.decision == "undecided"
    assert [look["worlds"] for look in result.looks] == [16, 32]
    assert result.looks[0]["oriented_ci"] is not None
    assert result.looks[1]["oriented_ci"] is None
    assert result.n_errors == 16
