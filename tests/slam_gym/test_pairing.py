"""slam_gym/evaluation/pairing.py: the one row pairing of compare, front and the headroom report
(issue 56 items 1, 3 and 4)."""

import numpy as np
import pytest
from script_loader import load_script

from slam_gym.evaluation import compare as cmp
from slam_gym.evaluation import front, paired, pairing

headroom = load_script("results/task_headroom.py")


def run(policy, level, seed, draw, success, map_error, *, status="ok", cpu=0.1):
    return {"policy": policy, "scenario": "brooks-bailey", "clutter_level": level, "seed": seed,
            "draw": draw, "options": {"draw": draw}, "status": status, "success": success,
            "map_error_m": map_error, "anees": 3.0, "nees_in_band_fraction": 0.9,
            "return": -100.0, "w_compute": 10.0, "compute_term_s": 1.0, "fusion_cpu_s": cpu,
            "optimise_cpu_s": 0.0, "n_fusions": 40, "n_optimisations": 0}


def test_the_map_error_pairs_the_draws_both_policies_survived():
    """World (0, 0): draw 0 both survived, draw 1 B failed: the world enters with draw 0 alone.
    World (0, 1): A failed in both draws: left out. World (1, 0): both survived both draws."""
    a = [run("A", 0, 0, 0, True, 2.0), run("A", 0, 0, 1, True, 4.0),
         run("A", 0, 1, 0, False, 1.0), run("A", 0, 1, 1, False, 1.0),
         run("A", 1, 0, 0, True, 3.0), run("A", 1, 0, 1, True, 5.0)]
    b = [run("B", 0, 0, 0, True, 1.0), run("B", 0, 0, 1, False, 9.0),
         run("B", 0, 1, 0, True, 1.0), run("B", 0, 1, 1, True, 1.0),
         run("B", 1, 0, 0, True, 2.0), run("B", 1, 0, 1, True, 2.0, status="error")]
    pw = pairing.paired_worlds(a, b, "map_error_m")
    assert len(pw) == 2 and pw.n_left_out == 1
    order = np.lexsort((pw.clusters, pw.strata))
    # means of one or two small floats: exact up to an ulp or two of the values (1e-12)
    assert pw.a[order] == pytest.approx([2.0, 3.0], abs=1e-12)  # (1, 0)'s draw 1: B errored
    assert pw.b[order] == pytest.approx([1.0, 2.0], abs=1e-12)
    assert pw.draws[order].tolist() == [1, 1]
    # the seed is the cluster: worlds (0, 0) and (1, 0) share seed 0
    assert pw.n_clusters == 1
    success = pairing.paired_worlds(a, b, "success")
    assert len(success) == 3 and success.n_clusters == 2


def test_compare_front_and_headroom_agree_on_the_paired_map_error():
    """The same rows (one draw: front's kind) give the same paired map error and world count in
    compare's metric report, front.compare and the headroom report."""
    rng = np.random.default_rng(3)
    ref, mine = [], []
    for level in range(4):
        for seed in range(6):
            ok_a, ok_b = rng.random() < 0.7, rng.random() < 0.6
            ref.append(run("rule", level, seed, 0, ok_a, float(rng.lognormal())))
            mine.append(run("learned", level, seed, 0, ok_b, float(rng.lognormal())))
    worlds = sorted({(r["clutter_level"], r["seed"]) for r in ref})
    report = cmp.metric_report(ref, mine, "map_error_m", worlds)
    by_front = front.compare(mine, ref, price=10.0)
    by_headroom = headroom.paired_difference(mine, ref, "map_error_m", 10.0)
    survived = sum(a["success"] and b["success"] for a, b in zip(ref, mine, strict=True))
    assert report["worlds"] == by_front["n_map_pairs"] == by_headroom["worlds"] == survived
    assert report["left_out"] == 24 - survived
    # three means of the same per-world differences, summed in other orders: 1e-12 m
    assert by_front["map_error_diff_m"] == pytest.approx(report["difference"], abs=1e-12)
    assert by_headroom["mean"] == pytest.approx(report["difference"], abs=1e-12)
    seeds = {a["seed"] for a, b in zip(ref, mine, strict=True) if a["success"] and b["success"]}
    assert report["seeds"] == by_headroom["seeds"] == by_front["n_map_seeds"] == len(seeds)
    assert report["paired_over"] == "pairs of draws where both policies survived"


def test_compare_looks_are_sequential_decisions_on_the_seeds():
    """One loop: compare's look at rows (seeds at two levels, 2 draws) decides and bounds
    exactly as paired.sequential_decisions on the per-seed means with the same looks."""
    rng = np.random.default_rng(8)
    a, b = [], []
    for seed in range(40):
        p_a, p_b = rng.choice([(0.9, 0.9), (0.2, 0.2), (0.2, 0.9), (0.9, 0.2)],
                              p=[0.4, 0.3, 0.2, 0.1])
        for level in (1, 2):
            for draw in range(2):
                u = rng.random()
                a.append(run("A", level, seed, draw, bool(u < p_a), 1.0))
                b.append(run("B", level, seed, draw, bool(u < p_b), 1.0))
    worlds = [(level, seed) for seed in range(40) for level in (1, 2)]
    seen: list[int] = []
    entries = []
    for batch in range(16, 41, 4):
        entry, seen = cmp.look(a, b, worlds[:2 * batch], "success", 5.0, alpha=0.05,
                               planned_seeds=40, look_seeds=seen)
        entries.append(entry)
    assert seen == list(range(16, 41, 4))
    d = pairing.paired_worlds(a, b, "success").differences()
    units = paired.cluster_means(d.differences, d.clusters)
    out = paired.sequential_decisions(units, margin=0.05, planned_worlds=40, rate=True,
                                      looks=seen, pseudo_units=0.5)  # two worlds a seed
    stop = next(i for i, e in enumerate(entries) if e["decision"] != "undecided"
                or i == len(entries) - 1)
    assert entries[stop]["decision"] == out.decision
    assert entries[stop]["oriented_ci"] == pytest.approx([100 * out.lo, 100 * out.hi],
                                                         rel=1e-12)
    assert entries[stop]["anytime_valid"] is True


def test_rows_of_one_arm_with_the_same_key_are_refused():
    with pytest.raises(ValueError, match="^rows_a="):
        pairing.pair_rows([run("A", 0, 0, 0, True, 1.0)] * 2, [], "success")
