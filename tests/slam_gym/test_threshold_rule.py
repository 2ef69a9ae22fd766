"""``slam-gym threshold-rule``: the family of threshold rules, scored at several prices from one
run each, and the best chosen per price (issue 29 item 3)."""

import json

import pytest

from slam_gym.cli import main
from slam_gym.commands.threshold_rule import DEFAULT_GRID
from slam_gym.evaluation.front import return_at_price


def test_every_rule_runs_once_and_the_best_is_chosen_per_price(tmp_path):
    out = tmp_path / "tr"
    code = main(["threshold-rule", "--seeds", "3", "--clutter-levels", "0", "--n-steps", "400",
                 "--particles", "30", "--workers", "1", "--prices", "1,50", "--quiet",
                 "--out", str(out)])
    assert code == 0
    doc = json.loads((out / "chosen.json").read_text())
    n_rules = 2 + sum(len(v) for v in DEFAULT_GRID.values())
    assert len(doc["candidates"]) == n_rules
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(rows) == n_rules and all(r["w_compute"] == 10.0 for r in rows)
    for price in ("1", "50"):
        key = f"mean_return_at_{price}"
        best = max(c[key] for c in doc["candidates"])
        assert doc["chosen"][price]["mean_return"] == best
        chosen = next(c for c in doc["candidates"] if c["rule"] == doc["chosen"][price]["rule"])
        row = next(r for r in rows if r["policy"] == chosen["rule"])
        assert chosen[key] == pytest.approx(return_at_price(row, float(price)))
    assert "| rule |" in (out / "candidates.md").read_text()


def test_training_worlds_are_refused(tmp_path, capsys):
    assert main(["threshold-rule", "--seeds", "1000000", "--quiet", "--out", str(tmp_path)]) == 2
    assert "seeds" in capsys.readouterr().err


def test_the_rule_is_chosen_on_the_named_scenarios_worlds(tmp_path):
    """Issue 48: a task's best rule is chosen on its own scenario's training-time worlds."""
    out = tmp_path / "tr"
    code = main(["threshold-rule", "--scenario", "brooks-bailey-zones", "--seeds", "3",
                 "--clutter-levels", "0", "--n-steps", "200", "--particles", "30",
                 "--workers", "1", "--prices", "10", "--quiet", "--out", str(out)])
    assert code == 0
    doc = json.loads((out / "chosen.json").read_text())
    assert doc["scenario"] == "brooks-bailey-zones" and doc["particles"] == 30
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert rows and all(r["scenario"] == "brooks-bailey-zones" for r in rows)
