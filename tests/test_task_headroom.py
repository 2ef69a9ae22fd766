"""scripts/results/task_headroom.py: the paired intervals of issue 48's headroom table."""

import math

import numpy as np
import pytest
from script_loader import load_script

headroom = load_script("results/task_headroom.py")


def _row(policy, level, seed, success, map_error=1.0, draw=0, ret=-100.0):
    return {"policy": policy, "scenario": "brooks-bailey", "clutter_level": level, "seed": seed,
            "options": {"draw": draw}, "draw": draw,
            "status": "ok", "success": success, "map_error_m": map_error, "anees": 3.0,
            "nees_in_band_fraction": 0.9, "return": ret, "w_compute": 10.0,
            "compute_term_s": 1.0, "fusion_cpu_s": 0.1, "optimise_cpu_s": 0.1}


def test_success_interval_is_compares_and_valid_for_paired_zero_one_data():
    def rate(pairs):
        best = [_row("rule", i % 4, i // 4, bool(b)) for i, (_, b) in enumerate(pairs)]
        other = [_row("bound", i % 4, i // 4, bool(a)) for i, (a, _) in enumerate(pairs)]
        return headroom.paired_difference(other, best, "success", 10.0)

    # no discordant world: the difference is 0 and the interval is not degenerate
    out = rate([(1, 1)] * 30 + [(0, 0)] * 10)
    assert out["mean"] == 0.0 and out["lo"] < 0 < out["hi"]  # a mean of zeros is exactly 0
    # 8 worlds won, none lost, of 40 (10 seeds at 4 levels) on 8 seeds: a clear gain
    spread = [(1, 0) if i % 5 == 0 else (1, 1) for i in range(40)]
    out = rate(spread)
    assert out["mean"] == pytest.approx(0.2, abs=1e-12)  # 8 / 40 in floats: within rounding
    assert out["method"] == "bonett-price-cluster-cr1-t" and out["seeds"] == 10
    assert out["lo"] > 0
    # the same 8 worlds on 2 seeds (all four levels of each): the seed decided, not shown
    out = rate([(1, 0)] * 8 + [(1, 1)] * 32)
    assert out["lo"] < 0 < out["hi"]
    # one world won of 40: not distinguishable from 0
    out = rate([(1, 0)] + [(1, 1)] * 39)
    assert out["lo"] < 0 < out["hi"]


def test_continuous_interval_resamples_seeds_with_their_levels():
    """A difference that depends on the level only: every resampled seed brings its four levels,
    so there is no spread; a difference that depends on the seed only is resampled by seed."""
    best = [_row("rule", level, seed, True, 2.0) for level in range(4) for seed in range(10)]
    by_level = [_row("bound", level, seed, True, 2.0 - 0.1 * level)
                for level in range(4) for seed in range(10)]
    out = headroom.paired_difference(by_level, best, "map_error_m", 10.0)
    # means of 0.1-multiples over 40 worlds: equal to 1e-12 m whatever the summation order
    assert out["mean"] == pytest.approx(-0.15, abs=1e-12)
    assert out["lo"] == pytest.approx(-0.15, abs=1e-12)
    assert out["hi"] == pytest.approx(-0.15, abs=1e-12)
    rng = np.random.default_rng(1)
    effect = rng.normal(-1.0, 1.0, 10)
    by_seed = [_row("bound", level, seed, True, 2.0 + effect[seed])
               for level in range(4) for seed in range(10)]
    out = headroom.paired_difference(by_seed, best, "map_error_m", 10.0)
    assert out["lo"] < out["mean"] < out["hi"] and out["seeds"] == 10
    assert out["icc"] == pytest.approx(1.0, abs=1e-9)  # all variance between seeds
    assert out["effective_worlds"] == pytest.approx(10.0, abs=1e-6)


def test_draws_are_averaged_per_world_before_pairing():
    best = [_row("rule", 0, s, True, 2.0, d) for s in range(5) for d in range(3)]
    other = [_row("bound", 0, s, True, 2.0 - 0.1 * d, d) for s in range(5) for d in range(3)]
    out = headroom.paired_difference(other, best, "map_error_m", 10.0)
    assert out["worlds"] == 5
    assert out["mean"] == pytest.approx(-0.1, abs=1e-12)
    # a map error where either failed is not paired: world 0 keeps draws 1 and 2
    other[0]["success"] = False
    out = headroom.paired_difference(other, best, "map_error_m", 10.0)
    assert out["mean"] == pytest.approx((-0.15 + 4 * -0.1) / 5, abs=1e-12)


def test_summary_pairs_with_the_best_rule_and_normalises_only_where_the_bound_has_room():
    rows = []
    for s in range(40):
        rows.append(_row("fixed-10s-optimise", s % 4, s, s % 5 != 0, ret=-100.0))
        rows.append(_row("lookahead-privileged", s % 4, s, True, ret=-50.0))
        rows.append(_row("lookahead", s % 4, s, s % 10 != 0, ret=-75.0 + (s % 3)))
    doc = headroom.summarise(rows, "fixed-10s-optimise", 10.0)
    bound = doc["policies"]["lookahead-privileged"]
    assert bound["success_diff"][0] == pytest.approx(0.2) and bound["success_diff"][1] > 0
    assert doc["normalised_headroom"]["success"] == pytest.approx(0.5)
    assert doc["normalised_headroom"]["return"] == pytest.approx(
        doc["policies"]["lookahead"]["return_diff"][0] / 50.0)
    assert doc["normalised_headroom"]["map_error_m"] is None  # no room: equal map errors
    # a bound that is clearly worse on a measure (here: more interface CPU) has no room there
    for r in rows:
        if r["policy"] == "lookahead-privileged":
            r["fusion_cpu_s"] = 0.5
    doc = headroom.summarise(rows, "fixed-10s-optimise", 10.0)
    assert doc["policies"]["lookahead-privileged"]["interface_cpu_s_diff"][1] > 0
    assert doc["normalised_headroom"]["interface_cpu_s"] is None
    assert "best rule" in headroom.markdown(doc) and not math.isnan(bound["return_diff"][1])


def test_common_worlds_keeps_only_the_worlds_every_policy_finished():
    rows = [_row("rule", 0, s, True) for s in range(4)]
    rows += [_row("lookahead", 0, s, True) for s in (1, 3)]
    rows.append({**_row("lookahead", 0, 2, True), "status": "error"})  # unfinished
    kept = headroom.common_worlds(rows)
    assert {(r["policy"], r["seed"]) for r in kept if r["status"] == "ok"} == {
        ("rule", 1), ("rule", 3), ("lookahead", 1), ("lookahead", 3)}
    assert headroom.common_worlds([]) == []


def test_join_rows_keeps_each_run_once_and_the_first_groups_row():
    first = [{**_row("rule", 0, 0, True), "key": "a"}, {**_row("rule", 0, 1, True), "key": "b"}]
    second = [{**_row("rule", 0, 1, False), "key": "b"}, {**_row("rule", 1, 0, True), "key": "c"}]
    joined = headroom.join_rows(first, second)
    assert [r["key"] for r in joined] == ["a", "b", "c"]
    assert joined[1]["success"] is True
    # rows without a key are told apart by their job (policy, world, options: the draw)
    assert len(headroom.join_rows([_row("rule", 0, 0, True)], [_row("rule", 0, 0, True, draw=1)],
                                  [_row("rule", 0, 0, False)])) == 2


def test_report_only_joins_folders_and_restricts_to_common_worlds(tmp_path):
    import json

    halves = [tmp_path / "a", tmp_path / "b"]
    for half, seeds in zip(halves, (range(0, 3), range(3, 6)), strict=True):
        half.mkdir()
        rows = [_row("fixed-10s-optimise", 0, s, s % 2 == 0) for s in seeds]
        rows += [_row("lookahead-privileged", 0, s, True) for s in seeds if s != 5]
        (half / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "joined"
    args = ["--task", "SlamGym/HybridSLAM-ZonesStarved-v1", "--report-only", "--out", str(out),
            "--rows", str(halves[0]), "--rows", str(halves[1])]
    assert headroom.main([*args, "--best-rule", "fixed-10s-optimise"]) == 0
    doc = json.loads((out / "headroom.json").read_text())
    assert doc["worlds"] == 6 and doc["policies"]["fixed-10s-optimise"]["n_worlds"] == 6
    assert headroom.main([*args, "--best-rule", "fixed-10s-optimise", "--common-worlds"]) == 0
    doc = json.loads((out / "headroom.json").read_text())
    assert doc["worlds"] == 5 and doc["policies"]["fixed-10s-optimise"]["n_worlds"] == 5
    assert headroom.main([*args[:-1], str(tmp_path / "missing")]) == 2  # exit 2, one line


def test_headroom_table_has_a_bound_and_a_lookahead_row_per_task(tmp_path, capsys):
    import json

    rows = []
    for s in range(40):  # 10 seeds at four levels
        rows.append(_row("best-threshold", s % 4, s // 4, s % 5 != 0, ret=-100.0))
        rows.append(_row("lookahead-privileged", s % 4, s // 4, True, ret=-50.0))
        rows.append(_row("lookahead", s % 4, s // 4, s % 10 != 0, ret=-75.0))
    with_lookahead = headroom.summarise(rows, "best-threshold", 10.0) | {
        "task": "SlamGym/A-v1", "best_rule_label": "threshold-optimise[x>=1]"}
    without = headroom.summarise([r for r in rows if r["policy"] != "lookahead"],
                                 "best-threshold", 10.0) | {"task": "SlamGym/B-v1"}
    table = headroom.headroom_table([with_lookahead, without])
    rows_part, clustering = table.strip().split("\n\n")
    lines = rows_part.splitlines()
    assert len(lines) == 2 + 4
    assert "(32 worlds)" in lines[2]  # the map error: the 32 worlds where the best rule survived
    assert clustering.startswith("Success: the intraclass correlation") and "10 seeds" in clustering
    assert "`threshold-optimise[x>=1]`" in lines[2] and "| 80 % |" in lines[2]
    assert "+20 [" in lines[2] and "success 0.50" in lines[3]
    assert "| lookahead | not run |" in lines[5] and "`best-threshold`" in lines[4]
    files = []
    for i, doc in enumerate((with_lookahead, without)):
        files.append(tmp_path / f"{i}.json")
        files[-1].write_text(json.dumps(doc))
    assert headroom.main(["--table", str(files[0]), "--table", str(files[1])]) == 0
    assert capsys.readouterr().out == table
    assert headroom.main(["--table", str(files[0]), str(files[1])]) == 0
    assert capsys.readouterr().out == table
    assert headroom.main(["--report-only"]) == 2  # neither --table nor --task


def test_renamed_rows_are_reported_under_their_new_name_with_a_headroom_interval():
    """Issue 48's rows of the full planner (``lookahead``) read as ``lookahead-full`` beside the
    fast planner's own ``lookahead`` rows; each planner's normalised headroom has an interval
    around its point estimate, and none is given against itself."""
    rows, old = [], []
    for s in range(40):
        rows.append(_row("lookahead", s % 4, s, s % 10 != 0, ret=-60.0))
        old.append(_row("fixed-10s-optimise", s % 4, s, s % 5 != 0, ret=-100.0))
        old.append(_row("lookahead-privileged", s % 4, s, True, ret=-50.0 - (s % 7)))
        old.append(_row("lookahead", s % 4, s, s % 10 != 0 and s % 3 != 0, ret=-80.0))
    renamed = headroom.rename_policies(old, {"lookahead": "lookahead-full"})
    assert {r["policy"] for r in renamed} == {"fixed-10s-optimise", "lookahead-privileged",
                                              "lookahead-full"}
    joined = headroom.join_rows(rows, renamed)
    assert len(joined) == 160  # a renamed run never collides with the new name's own run
    doc = headroom.summarise(joined, "fixed-10s-optimise", 10.0)
    arms = doc["normalised_headroom_by_arm"]
    assert set(arms) == {"lookahead", "lookahead-full"}
    for arm in arms.values():
        lo, hi = arm["interval"]["success"]
        assert lo <= arm["point"]["success"] <= hi and lo < hi
    assert arms["lookahead"]["point"]["success"] > arms["lookahead-full"]["point"]["success"]
    assert doc["normalised_headroom"] == arms["lookahead"]["point"]
    against_full = headroom.summarise(joined, "lookahead-full", 10.0)
    assert set(against_full["normalised_headroom_by_arm"]) == {"lookahead"}


def test_a_learner_gets_the_gap_it_closes_to_each_planner_with_a_seed_bootstrap_interval():
    """(learner - best) / (planner - best) on success: 0.5 where the learner saves half the
    seeds the planner saves; no figure where the planner has no room (map error), none for a
    rule; the interval holds the point and is not a point itself."""
    from slam_gym.evaluation.headroom import gap_closed

    rows = []
    for s in range(40):
        rows.append(_row("fixed-10s-optimise", s % 4, s, s % 4 != 0, ret=-100.0))
        rows.append(_row("fixed-10s", s % 4, s, s % 4 != 0, ret=-100.0))
        rows.append(_row("lookahead", s % 4, s, True, ret=-60.0))
        rows.append(_row("learned", s % 4, s, s % 4 != 0 or s % 8 == 0, ret=-80.0))
    doc = headroom.summarise(rows, "fixed-10s-optimise", 10.0)
    assert set(doc["gap_closed"]) == {"learned"}  # neither the rules nor the planner
    gap = doc["gap_closed"]["learned"]["lookahead"]
    assert gap["point"]["success"] == pytest.approx(0.5)
    assert gap["point"]["return"] == pytest.approx(0.5)
    assert "map_error_m" not in gap["point"]  # the planner has no room there
    lo, hi = gap["interval"]["success"]
    assert lo < 0.5 < hi and hi - lo > 0.05
    assert gap == gap_closed(doc, {p: [r for r in rows if r["policy"] == p] for p in
                                   ("learned", "lookahead")},
                             [r for r in rows if r["policy"] == "fixed-10s-optimise"], 10.0)[
        "learned"]["lookahead"]
    assert "Gap closed (learned - best) / (lookahead - best)" in headroom.markdown(doc)


def test_rename_rows_renames_the_rows_folders_not_the_out_folders_own(tmp_path):
    """``--rename-rows lookahead=lookahead-full`` with the fast planner's rows in ``--out``
    (issue 57's command): both planners are reported, neither taken for the other."""
    import json as _json

    from slam_gym.cli import main

    out, old = tmp_path / "out", tmp_path / "old"
    for folder, rows in ((out, [_row("lookahead", s % 4, s, True) for s in range(8)]),
                         (old, [_row(p, s % 4, s, s % 2 == 0) for s in range(8)
                                for p in ("lookahead", "fixed-10s-optimise")])):
        folder.mkdir()
        (folder / "results.jsonl").write_text(
            "".join(_json.dumps(r) + "\n" for r in rows))
    code = main(["headroom", "--env", "SlamGym/HybridSLAM-Zones-v1", "--best-rule",
                 "fixed-10s-optimise", "--report-only", "--out", str(out), "--rows", str(old),
                 "--rename-rows", "lookahead=lookahead-full", "--seeds", "2"])
    assert code == 0
    doc = _json.loads((out / "headroom.json").read_text())
    assert doc["policies"]["lookahead"]["success"] == 1.0
    assert doc["policies"]["lookahead-full"]["success"] == 0.5
