"""``slam-gym train --prices``: a sweep of seeds x prices as independent resumable jobs through the
benchmark's executors (process pool, a local Ray instance), per-price summaries, sweep.json/md
(issue 29 item 7)."""

import json

import pytest

from slam_gym.cli import main
from slam_gym.evaluation.results import read_results
from slam_gym.training.hyperparams import validate_hyperparams
from slam_gym.training.sweep import SweepSpec, parse_prices, price_label, run_sweep

TINY = ["--timesteps", "64", "--n-envs", "1", "--particles", "5", "--n-steps", "120",
        "--hp", "n_steps=32", "--hp", "batch_size=32", "--hp", "n_epochs=1",
        "--eval-every", "1000", "--eval-seeds", "3", "--eval-workers", "1",
        "--clutter-levels", "1", "--quiet"]


@pytest.mark.parametrize("text", ["", "1,x", "0,10", "-1", "10,10", "nan", "1e7"])
def test_bad_prices_raise_naming_prices(text):
    with pytest.raises(ValueError, match="prices"):
        parse_prices(text)
    assert main(["train", "--prices", text, "--out", "/nonexistent/never"]) == 2


def test_prices_parse_in_order_and_name_their_directories():
    assert parse_prices("1, 10,0.5") == [1.0, 10.0, 0.5]
    assert [price_label(p) for p in (1.0, 10.0, 0.5)] == ["price-1", "price-10", "price-0.5"]


def test_executor_options_without_prices_and_a_conditioned_sweep_raise(tmp_path, capsys):
    for option in (["--executor", "ray"], ["--workers", "2"], ["--ray-address", "auto"]):
        assert main(["train", *option, "--out", str(tmp_path)]) == 2
        assert f"{option[0]} {option[1]} is invalid" in capsys.readouterr().err
    assert main(["train", "--prices", "1", "--ray-address", "auto", "--out",
                 str(tmp_path)]) == 2
    assert "--ray-address auto is invalid" in capsys.readouterr().err
    params = validate_hyperparams("ppo", {"n_timesteps": 8, "n_envs": 1,
                                          "compute_price_range": [1, 100]})
    with pytest.raises(ValueError, match="prices"):
        SweepSpec("ppo", "SlamGym/HybridSLAM-v1", params, str(tmp_path))
    with pytest.raises(ValueError, match="compute_clip_s"):
        SweepSpec("ppo", "SlamGym/HybridSLAM-v1", {"n_timesteps": 8}, str(tmp_path),
                  compute_clip_s=-1.0)


def _mtimes(out):
    return {str(p.relative_to(out)): p.stat().st_mtime_ns
            for p in out.rglob("*") if p.is_file() and "seed-" in str(p)}


def test_a_process_sweep_trains_each_job_at_its_price_resumes_and_summarises(tmp_path, capsys):
    out = tmp_path / "sweep"
    command = ["train", *TINY, "--prices", "1,100", "--seeds", "0", "--compute-clip-s", "0.2",
               "--executor", "process", "--workers", "2", "--out", str(out), "--json"]
    assert main(command) == 0
    doc = json.loads(capsys.readouterr().out)["sweep"]
    rows = read_results(out)
    assert len(rows) == 2 and all(r["status"] == "ok" and r["training"] == "ppo" for r in rows)
    for price in (1, 100):
        run = out / f"price-{price}" / "seed-0"
        config = json.loads((run / "model.json").read_text())
        assert config["env_options"]["w_compute"] == price  # trained and evaluated at its price
        assert config["env_options"]["compute_clip_s"] == 0.2
        assert (out / f"price-{price}" / "model.zip").read_bytes() == \
            (run / "model.zip").read_bytes()  # the chosen (only) seed's model
        summary = json.loads((out / f"price-{price}" / "summary.json").read_text())
        assert summary["chosen_seed"] == 0
        row = next(r for r in rows if r["options"]["w_compute"] == price)
        assert row["mean_return"] == pytest.approx(
            summary["final_evaluation"]["0"]["mean_return"])
    assert sorted(doc["per_price"]) == ["price-1", "price-100"] and doc["n_errors"] == 0
    md = (out / "sweep.md").read_text()
    assert "| 1 | 0 | 0 |" in md and "| 100 | 0 | 0 |" in md
    # a rerun does nothing new: no job runs, no run directory is touched
    before = _mtimes(out)
    assert main(command) == 0
    capsys.readouterr()
    assert len(read_results(out)) == 2 and _mtimes(out) == before
    # other settings into the same directories: refused by each job, never trained over
    changed = [a if a != "64" else "96" for a in command]
    assert main([*changed[:-1]]) == 1
    errors = [r for r in read_results(out) if r["status"] == "error"]
    assert len(errors) == 2 and all("other settings" in r["error"] for r in errors)
    assert _mtimes(out) == before
    assert json.loads((out / "price-1" / "seed-0" / "model.json").read_text())["timesteps"] == 64


@pytest.mark.xdist_group("ray")  # one local Ray instance at a time (pytest -n)
def test_a_sweep_on_a_local_ray_instance(tmp_path):
    """Two jobs (prices 1 and 10, seed 0) through Ray on this machine: the same rows and run
    directories as the process pool makes, so a sweep runs on a cluster unchanged."""
    try:
        import ray  # noqa: F401
    except ImportError:
        pytest.fail("Ray is not installed: pip install slam-gym[ray] (this test is not skipped)")
    params = validate_hyperparams("ppo", {
        "n_timesteps": 32, "n_envs": 1, "env_kwargs": {"n_particles": 5, "n_steps": 60},
        "n_steps": 32, "batch_size": 32, "n_epochs": 1})
    spec = SweepSpec("ppo", "SlamGym/HybridSLAM-v1", params, str(tmp_path), clutter_levels=(1,),
                     eval_seeds=(3,), eval_every=1000, eval_workers=1, checkpoint_every=1000)
    doc = run_sweep(spec, [1.0, 10.0], [0], executor="ray", workers=2)
    rows = read_results(tmp_path)
    assert [r["status"] for r in rows] == ["ok", "ok"], [r["error"] for r in rows]
    assert sorted(r["options"]["run_dir"] for r in rows) == ["price-1/seed-0", "price-10/seed-0"]
    for label in ("price-1", "price-10"):
        assert (tmp_path / label / "model.zip").is_file()
        assert doc["per_price"][label]["chosen_seed"] == 0
    assert json.loads((tmp_path / "price-10" / "seed-0" / "model.json").read_text())[
        "env_options"]["w_compute"] == 10.0
