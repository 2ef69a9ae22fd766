"""scripts/results/select_snapshot.py: a training run's snapshot chosen under a limit on
interface CPU, on the training-time worlds only."""

import csv
import json
from pathlib import Path

import pytest
from script_loader import load_script

SCRIPT = "results/select_snapshot.py"
FIELDS = ("success_rate", "mean_return", "n_fusions", "n_optimisations", "interface_cpu_s")


def make_run(tmp_path: Path, evaluations: dict[int, tuple[tuple, tuple]]) -> Path:
    """A run directory whose eval.csv has, per decision count, the (deterministic, sampled)
    figures (success, return, fusions, optimisations, CPU) and whose snapshots exist."""
    run = tmp_path / "seed-1"
    run.mkdir()
    header = ["timesteps", *FIELDS, *("sampled_" + f for f in FIELDS)]
    with (run / "eval.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for t, (det, sampled) in evaluations.items():
            writer.writerow([t, *det, *sampled])
            snapshot = run / "evals" / f"t{t}"
            snapshot.mkdir(parents=True)
            (snapshot / "model.zip").write_bytes(f"weights at {t}".encode())
            (snapshot / "model.json").write_text(json.dumps({"timesteps": t}))
    return run


def make_baseline(tmp_path: Path, cpu_s: float = 0.3, successes=(True, True, True, False)):
    out = tmp_path / "baseline"
    out.mkdir()
    rows = [{"status": "ok", "policy": "fixed-10s-optimise", "clutter_level": 0, "seed": i,
             "success": ok, "return": -2000.0, "fusion_cpu_s": cpu_s / 2,
             "optimise_cpu_s": cpu_s / 2} for i, ok in enumerate(successes)]
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return out


def test_the_best_return_within_the_cpu_limit_is_chosen_with_its_mode(tmp_path, capsys):
    script = load_script(SCRIPT)
    run = make_run(tmp_path, {
        # the best return of all, but 3 times the rule's CPU; sampled: within 2x, but success
        # below the rule's: neither eligible
        100: ((1.0, -1400.0, 80, 80, 0.9), (0.5, -1500.0, 60, 50, 0.45)),
        # sampled: within 2x (0.45 / 0.3 = 1.5), success 0.75 = the rule's -> chosen
        200: ((0.75, -2100.0, 40, 40, 0.3), (0.75, -1700.0, 55, 45, 0.45)),
        # better return than 200-sampled but success below the rule's: not eligible
        300: ((0.5, -1600.0, 40, 40, 0.3), (0.7, -1650.0, 40, 40, 0.3)),
    })
    out = tmp_path / "chosen"
    assert script.main([str(run), "--baseline", str(make_baseline(tmp_path)),
                        "--out", str(out)]) == 0
    assert (out / "model.zip").read_bytes() == b"weights at 200"
    config = json.loads((out / "model.json").read_text())
    assert config["timesteps"] == 200 and config["deterministic"] is False
    selection = config["selection"]
    assert selection["chosen"]["timesteps"] == 200 and selection["chosen"]["mode"] == "sampled"
    assert selection["fixed_10s_optimise"]["interface_cpu_s"] == pytest.approx(0.3)
    assert selection["fixed_10s_optimise"]["success_rate"] == pytest.approx(0.75)
    eligible = {(c["timesteps"], c["mode"]) for c in selection["candidates"] if c["eligible"]}
    assert eligible == {(200, "deterministic"), (200, "sampled")}
    assert "**chosen**" in capsys.readouterr().out


def test_the_limit_is_an_option_and_none_eligible_exits_1(tmp_path):
    script = load_script(SCRIPT)
    run = make_run(tmp_path, {100: ((1.0, -1400.0, 80, 80, 0.9), (1.0, -1500.0, 80, 80, 0.9))})
    baseline = make_baseline(tmp_path)
    out = tmp_path / "chosen"
    assert script.main([str(run), "--baseline", str(baseline), "--out", str(out)]) == 1
    assert not (out / "model.zip").exists()
    assert script.main([str(run), "--baseline", str(baseline), "--max-cpu-ratio", "3",
                        "--out", str(out)]) == 0


def test_bad_input_names_the_field(tmp_path):
    script = load_script(SCRIPT)
    run = make_run(tmp_path, {100: ((1.0, -1400.0, 80, 80, 0.9), (1.0, -1500.0, 80, 80, 0.9))})
    with pytest.raises(SystemExit):
        script.parse_args([str(tmp_path / "nowhere"), "--baseline", str(tmp_path)])
    with pytest.raises(SystemExit):
        script.parse_args([str(run), "--baseline", str(tmp_path), "--max-cpu-ratio", "0"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="baseline"):
        script.main([str(run), "--baseline", str(tmp_path / "empty")])
