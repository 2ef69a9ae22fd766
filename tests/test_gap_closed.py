"""scripts/results/gap_closed.py: the fraction of the rule-to-lookahead gap a learner closes."""

import json
from pathlib import Path

import pytest
from script_loader import load_script

SCRIPT = "results/gap_closed.py"


def row(policy, seed, success, map_error, ret):
    return {"status": "ok", "policy": policy, "scenario": "brooks-bailey", "clutter_level": 0,
            "seed": seed, "success": success, "map_error_m": map_error, "fusion_cpu_s": 0.1,
            "optimise_cpu_s": 0.1, "return": ret, "compute_term_s": 1.0, "w_compute": 10.0,
            "n_fusions": 40, "n_optimisations": 40}


def write(path: Path, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_the_fraction_is_the_learners_paired_gain_over_the_lookaheads(tmp_path):
    seeds = range(4)
    rule_ret, rule_map = [-900.0, -1000.0, -1100.0, -1200.0], [2.0, 3.0, 1.0, 4.0]
    # the lookahead: +100 return and -1 m on every world (a gap whose interval excludes 0), the
    # same successes; the learner: +50 and -0.25 m against its own run's rule, one world fewer
    write(tmp_path / "ceiling" / "results.jsonl",
          [row("fixed-10s-optimise", s, True, rule_map[s], rule_ret[s]) for s in seeds]
          + [row("lookahead", s, True, rule_map[s] - 1.0, rule_ret[s] + 100.0) for s in seeds]
          + [row("fixed-10s-optimise", 9, True, 1.0, -1.0)])  # a world the front did not run
    write(tmp_path / "front" / "rules" / "results.jsonl",
          [row("fixed-10s-optimise", s, True, rule_map[s] + 0.5, rule_ret[s] - 7.0)
           for s in seeds])
    write(tmp_path / "front" / "learned-10" / "results.jsonl",
          [row("learned", s, s != 3, rule_map[s] + 0.25, rule_ret[s] + 43.0) for s in seeds])
    module = load_script(SCRIPT)
    doc = module.gap_closed(tmp_path / "front", tmp_path / "ceiling", 10.0)
    assert doc["n_worlds"] == 4
    ret, map_error, success = (doc["measures"][k] for k in ("return", "map error (m)",
                                                            "success (pp)"))
    assert ret["gap"] == pytest.approx(100.0) and ret["fraction_closed"] == pytest.approx(0.5)
    # map error over the worlds where the learner and its rule both succeeded: -0.25 m each
    assert map_error["learner_diff"] == pytest.approx(-0.25)
    assert map_error["fraction_closed"] == pytest.approx(0.25)
    # no success gap: no fraction, however the learner did
    # a mean of equal successes' differences (all 0): 1e-12 pp allows any summation order
    assert success["gap"] == pytest.approx(0.0, abs=1e-12) and success["fraction_closed"] is None
    assert success["learner_diff"] == pytest.approx(-25.0)


def test_a_front_without_the_ceilings_worlds_is_refused(tmp_path):
    write(tmp_path / "ceiling" / "results.jsonl",
          [row("fixed-10s-optimise", 1, True, 1.0, -1.0), row("lookahead", 1, True, 1.0, -1.0)])
    write(tmp_path / "front" / "rules" / "results.jsonl",
          [row("fixed-10s-optimise", 2, True, 1.0, -1.0)])
    write(tmp_path / "front" / "learned-10" / "results.jsonl", [row("learned", 2, True, 1, -1)])
    with pytest.raises(ValueError, match="front"):
        load_script(SCRIPT).gap_closed(tmp_path / "front", tmp_path / "ceiling", 10.0)


def test_the_command_reports_both_planners_in_one_output(tmp_path):
    seeds = range(3)
    write(tmp_path / "ceiling" / "results.jsonl",
          [row("fixed-10s-optimise", s, True, 2.0, -1000.0) for s in seeds]
          + [row("lookahead", s, True, 1.0, -900.0) for s in seeds]
          + [row("lookahead-privileged", s, True, 1.5, -800.0) for s in seeds])
    write(tmp_path / "front" / "rules" / "results.jsonl",
          [row("fixed-10s-optimise", s, True, 2.0, -1000.0) for s in seeds])
    write(tmp_path / "front" / "learned-10" / "results.jsonl",
          [row("learned", s, True, 1.5, -950.0) for s in seeds])
    module = load_script(SCRIPT)
    assert module.main(["--front", str(tmp_path / "front"), "--ceiling",
                        str(tmp_path / "ceiling")]) == 0
    doc = json.loads((tmp_path / "front" / "gap_closed.json").read_text())
    assert set(doc) == {"lookahead", "lookahead-privileged"}
    assert doc["lookahead"]["measures"]["return"]["gap"] == pytest.approx(100.0)
    assert doc["lookahead-privileged"]["measures"]["return"]["gap"] == pytest.approx(200.0)
    assert doc["lookahead-privileged"]["measures"]["return"]["fraction_closed"] == pytest.approx(
        0.25)
    text = (tmp_path / "front" / "gap_closed.md").read_text()
    assert "`lookahead` - rule" in text and "`lookahead-privileged` - rule" in text


def recorded(path: Path, worlds, price=10.0):
    path.write_text(json.dumps({"price": price, "worlds": worlds, "planners": {"lookahead": {
        "success (pp)": {"gap": 0.0, "gap_ci": [0.0, 0.0]},
        "map error (m)": {"gap": -1.0, "gap_ci": [-1.5, -0.5]},
        "return": {"gap": 100.0, "gap_ci": [50.0, 150.0]}}}}))
    return path


def test_a_recorded_gap_divides_the_learners_difference_on_its_worlds(tmp_path):
    seeds = range(3)
    write(tmp_path / "front" / "rules" / "results.jsonl",
          [row("fixed-10s-optimise", s, True, 2.0, -1000.0) for s in [*seeds, 7]])
    # +20 return and -0.5 m on the recorded worlds; world 7 (not recorded) would change both
    write(tmp_path / "front" / "learned-10" / "results.jsonl",
          [row("learned", s, True, 1.5, -980.0) for s in seeds]
          + [row("learned", 7, True, 9.0, -5000.0)])
    gap = recorded(tmp_path / "gap.json", [[0, s] for s in seeds])
    module = load_script(SCRIPT)
    doc = module.gap_closed(tmp_path / "front", gap, 10.0)
    assert doc["n_worlds"] == 3 and doc["gap_from"] == "recorded"
    assert doc["measures"]["return"]["learner_diff"] == pytest.approx(20.0)
    assert doc["measures"]["return"]["fraction_closed"] == pytest.approx(0.2)
    assert doc["measures"]["map error (m)"]["fraction_closed"] == pytest.approx(0.5)
    assert doc["measures"]["success (pp)"]["fraction_closed"] is None
    # a front missing one of the recorded worlds, another price, an unrecorded planner: refused
    with pytest.raises(ValueError, match="front"):
        module.gap_closed(tmp_path / "front", recorded(tmp_path / "more.json",
                                                       [[0, s] for s in range(4)]), 10.0)
    with pytest.raises(ValueError, match="price"):
        module.gap_closed(tmp_path / "front", gap, 1.0)
    with pytest.raises(ValueError, match="lookahead"):
        module.gap_closed(tmp_path / "front", gap, 10.0, "lookahead-privileged")


def test_the_recorded_round_three_ceiling_is_well_formed():
    path = Path(__file__).resolve().parents[1] / "docs" / "ceiling39_gap.json"
    module = load_script(SCRIPT)
    for planner in module.PLANNERS:
        worlds, gaps = module.recorded_gap(path, planner, 10.0)
        assert len(worlds) == 40 and {level for level, _ in worlds} == {0, 1, 2, 3}
        for key, ci_key, _ in module.MEASURES:
            assert gaps[ci_key][0] <= gaps[key] <= gaps[ci_key][1]
