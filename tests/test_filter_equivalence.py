"""scripts/results/filter_equivalence.py: two codes' rows compared with compare's statistics."""

import json

import numpy as np
import pytest
from script_loader import load_script

equivalence = load_script("results/filter_equivalence.py")


def write_rows(path, rows):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return str(path)


def runs(n_seeds: int, *, success_drop: float = 0.0, map_shift_m: float = 0.0, seed: int = 0):
    """Rows of ``fixed-10s`` on n_seeds x 4 levels x 2 draws; a code whose success is lower by
    ``success_drop`` (a share of its successes turned to failures) and whose map error is higher
    by ``map_shift_m``. The same ``seed`` gives the same base outcomes (the paired draws)."""
    rng = np.random.default_rng(seed)
    rows = []
    for s in range(n_seeds):
        for level in range(4):
            for draw in range(2):
                ok = bool(rng.random() < 0.7)
                lost = bool(rng.random() < success_drop)
                rows.append({"policy": "fixed-10s", "clutter_level": level, "seed": 100 + s,
                             "draw": draw, "status": "ok", "error": None,
                             "success": ok and not lost,
                             "map_error_m": 2.0 + rng.random() + map_shift_m,
                             "nees_in_band_fraction": 0.5 + 0.3 * rng.random(),
                             "anees": 3.0 + rng.random(), "interface_cpu_s": 0.1})
    return rows


def decisions(report):
    return {m: r.get("decision") for m, r in report["metrics"].items() if "decision" in r}


def test_identical_codes_are_not_worse_on_enough_seeds(tmp_path):
    """25 seeds x 4 levels: enough for 3 pp with no discordant world (the docstring's bound);
    24 are not."""
    ref = write_rows(tmp_path / "ref.jsonl", runs(25))
    new = write_rows(tmp_path / "new.jsonl", runs(25))
    (report,) = [equivalence.compare_codes(equivalence.read_rows(ref),
                                           equivalence.read_rows(new), "fixed-10s",
                                           equivalence.DEFAULT_MARGINS)]
    assert report["pairs"] == 200 and report["worlds"] == 100
    assert decisions(report) == {"success": "not worse", "map_error_m": "not worse",
                                 "nees_in_band_fraction": "not worse"}


def test_24_seeds_cannot_show_3_pp_on_success_however_alike(tmp_path):
    """The docstring's bound, on the script's own answer: identical codes on 24 seeds x 4
    levels (96 worlds) leave success undecided at 3 pp."""
    rows = write_rows(tmp_path / "rows.jsonl", runs(24))
    report = equivalence.compare_codes(equivalence.read_rows(rows), equivalence.read_rows(rows),
                                       "fixed-10s", equivalence.DEFAULT_MARGINS)
    assert decisions(report)["success"] == "undecided"


def test_a_worse_code_is_found_worse(tmp_path):
    ref = runs(24)
    new = runs(24, success_drop=0.4, map_shift_m=0.5)
    report = equivalence.compare_codes(
        equivalence.read_rows(write_rows(tmp_path / "ref.jsonl", ref)),
        equivalence.read_rows(write_rows(tmp_path / "new.jsonl", new)), "fixed-10s",
        equivalence.DEFAULT_MARGINS)
    got = decisions(report)
    assert got["success"] == "worse" and got["map_error_m"] == "worse"


def test_only_runs_both_codes_finished_are_paired(tmp_path):
    ref = runs(4)
    new = [r for r in runs(4) if r["draw"] == 0]
    new[0] = dict(new[0], status="error", error="boom")
    report = equivalence.compare_codes(
        equivalence.read_rows(write_rows(tmp_path / "ref.jsonl", ref)),
        equivalence.read_rows(write_rows(tmp_path / "new.jsonl", new)), "fixed-10s", {})
    assert report["pairs"] == 15 and report["worlds"] == 15


def test_bad_margins_name_the_option(capsys):
    with pytest.raises(SystemExit) as exc:
        equivalence.main(["a.jsonl", "b.jsonl", "--margins", "anees=1"])
    assert exc.value.code == 2
    assert "--margins" in capsys.readouterr().err
