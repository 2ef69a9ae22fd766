"""Provenance of learned models (issue 29 item 1): the system fingerprint, its comparison, the
fingerprint in model.json, the check on loading, `slam-gym fingerprint`, and the rows and tables
that mark a model trained on another system."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from slam_gym.cli import main
from slam_gym.envs.hybrid_slam import HybridSLAMEnv
from slam_gym.training import provenance
from slam_gym.training.provenance import (
    compare_fingerprints,
    scheduled_action,
    system_fingerprint,
    system_options,
)

CHEAP = {"n_particles": 50}  # the v1 rollout on world 5 fails early below ~50
"""Env options of a cheap rollout (the fingerprint is a function of the options)."""


@pytest.fixture
def fresh_cache(monkeypatch):
    """An empty fingerprint cache for the test (and the process's own afterwards)."""
    monkeypatch.setattr(provenance, "_CACHE", {})


def perturbed_step(monkeypatch, factor: float, feature: str | None = None) -> None:
    """Make the env's rewards (and one feature, or all) ``factor`` times what they are: float
    noise for a factor of 1 + 1e-9, a behaviour change for 1 + 1e-2."""
    original = HybridSLAMEnv.step

    def step(self, action):
        obs, reward, terminated, truncated, info = original(self, action)
        features = {k: (v * factor if feature in (None, k) and v is not None else v)
                    for k, v in info["features"].items()}
        return obs, reward * factor, terminated, truncated, dict(info, features=features)

    monkeypatch.setattr(HybridSLAMEnv, "step", step)


def test_the_fingerprint_repeats_and_exercises_fusion_and_the_optimiser():
    first = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP, cache=False)
    second = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP, cache=False)
    assert first["digest"] == second["digest"] and len(first["digest"]) == 64
    assert compare_fingerprints(first, second) == []
    summary = first["summary"]
    assert summary["decisions"] == provenance.ROLLOUT_DECISIONS and not summary["failed"]
    # fusion every 5 decisions, optimisation with every other and once between fusions
    assert summary["n_fusions"] == 12 and summary["n_optimisations"] == 7
    assert [scheduled_action(d).tolist() for d in (5, 10, 12, 37)] == [[1, 0], [1, 1], [0, 1],
                                                                      [0, 1]]
    assert first["env_options"] == CHEAP and first["env_id"] == "SlamGym/HybridSLAM-v1"
    assert "compute_price_per_s" in first["feature_names"]
    json.dumps(first, allow_nan=False)  # plain JSON, as model.json holds it


def test_the_cache_holds_one_fingerprint_per_system(fresh_cache):
    a = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP)
    # the same system by another id, and options the rollout sets itself: one computation
    b = system_fingerprint("SlamGym/HybridSLAM-Light-v1", {"n_particles": 50, "n_steps": 50,
                                                           "features": ["ess_ratio"]})
    assert len(provenance._CACHE) == 1 and a["digest"] == b["digest"]
    a["summary"]["return"] = 0.0  # callers get their own copy
    assert system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP)["summary"]["return"] != 0.0


def test_rounding_lets_float_noise_pass(fresh_cache, monkeypatch):
    clean = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP)
    perturbed_step(monkeypatch, 1.0 + 1e-9)
    noisy = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP, cache=False)
    assert noisy["digest"] == clean["digest"]
    assert compare_fingerprints(clean, noisy) == []
    assert provenance._fmt(1.234567e-3) == provenance._fmt(1.234567e-3 * (1 + 1e-12)) == "0.001235"
    assert provenance._fmt(-0.0) == provenance._fmt(0.0) == "0"


def test_a_behaviour_change_changes_the_fingerprint_and_is_named(fresh_cache, monkeypatch):
    clean = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP)
    perturbed_step(monkeypatch, 1.01, feature="global_heading_std_rad")
    changed = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP, cache=False)
    assert changed["digest"] != clean["digest"]
    differences = compare_fingerprints(clean, changed)
    assert differences[0].startswith("digest: " + clean["digest"][:16])
    assert any(d.startswith("return: ") for d in differences)
    assert any(d.startswith("mean_global_heading_std_rad: ") for d in differences)
    assert not any(d.startswith("mean_ess_ratio") for d in differences)  # only what changed
    assert any("the rollouts part in decisions 1-20" in d for d in differences)


@pytest.mark.parametrize("options, named", [
    ({"n_particles": 51}, "n_particles"),
    ({"n_particles": 50, "w_map": 2.0}, "w_map"),
])
def test_another_system_has_another_fingerprint(options, named):
    base = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP)
    other = system_fingerprint("SlamGym/HybridSLAM-v1", options)
    assert other["digest"] != base["digest"]
    differences = compare_fingerprints(base, other)
    assert any(d.startswith("env options: ") and named in d for d in differences)
    assert any(d.startswith("return: ") for d in differences)


def test_comparisons_name_a_missing_fingerprint_another_version_and_features():
    current = system_fingerprint("SlamGym/HybridSLAM-v1", CHEAP)
    assert "no system fingerprint" in compare_fingerprints(None, current)[0]
    assert "version" in compare_fingerprints(dict(current, version=0), current)[0]
    fewer = dict(current, feature_names=current["feature_names"][:-1], digest="0" * 64)
    assert any("feature names: added ['compute_price_per_s']" in d
               for d in compare_fingerprints(fewer, current))
    # only the digest differs: said to be below the rounding
    assert "rounding" in compare_fingerprints(dict(current, digest="0" * 64), current)[-1]


@pytest.mark.parametrize("env_id, options, field", [
    ("SlamGym/MRCLAM-v1", {}, "env_id"),
    ("SlamGym/Nope-v1", {}, "env_id"),
    ("SlamGym/HybridSLAM-v1", {"n_particles": 0}, "n_particles"),
    ("SlamGym/HybridSLAM-v1", {"w_mapp": 1.0}, "w_mapp"),
    ("SlamGym/HybridSLAM-v1", [("n_particles", 5)], "env_options"),
])
def test_bad_systems_raise_naming_the_field(env_id, options, field):
    with pytest.raises(ValueError, match=field):
        system_options(env_id, options)


# ------------------------------------------------------------------------------------------------
# model.json, loading, the command, rows and tables
# ------------------------------------------------------------------------------------------------
def tiny_setup():
    from slam_gym.training.hyperparams import validate_hyperparams
    from slam_gym.training.run import TrainingSetup

    params = validate_hyperparams("ppo", {
        "n_timesteps": 64, "n_envs": 1, "normalize": False,
        "env_kwargs": {"n_particles": 5, "n_steps": 120},
        "n_steps": 32, "batch_size": 32, "n_epochs": 1, "policy_kwargs": {"net_arch": [8]},
    })
    return TrainingSetup("ppo", "SlamGym/HybridSLAM-v1", 0, params, clutter_levels=(2,),
                         eval_seeds=(7,))


def save_untrained(path):
    """An untrained PPO model of the env, saved as `slam-gym train` saves its models."""
    from stable_baselines3 import PPO

    from slam_gym.training.run import make_env_fn, save_model

    setup = tiny_setup()
    model = PPO("MlpPolicy", make_env_fn(setup, 0)(), n_steps=32, batch_size=32, seed=0,
                device="cpu", policy_kwargs={"net_arch": [8]})
    return save_model(model, model.get_env(), setup, path, 0)


@pytest.fixture
def model_zip(tmp_path):
    return save_untrained(tmp_path / "model.zip")


@pytest.fixture
def stale_zip(tmp_path, monkeypatch):
    """A model saved by 'older code': the same env with its rewards 1 % larger."""
    with monkeypatch.context() as patched:
        patched.setattr(provenance, "_CACHE", {})
        perturbed_step(patched, 1.01)
        path = save_untrained(tmp_path / "stale" / "model.zip")
    return path


def test_a_saved_model_records_the_fingerprint_of_its_system(model_zip):
    config = json.loads(model_zip.with_suffix(".json").read_text())
    saved = config["fingerprint"]
    assert saved["env_id"] == "SlamGym/HybridSLAM-v1"
    assert saved["env_options"] == {"n_particles": 5}  # n_steps is the rollout's own
    assert saved == system_fingerprint("SlamGym/HybridSLAM-v1", config["env_options"])


def test_loading_a_matching_model_is_silent(model_zip, caplog):
    import policies

    with caplog.at_level(logging.WARNING, logger="policies.provenance"):
        policy = policies.make("learned", path=str(model_zip))
    assert policy.provenance == {"checked": True, "matches": True, "differences": []}
    assert not [r for r in caplog.records if r.name == "policies.provenance"]


def test_loading_a_model_of_another_system_warns_naming_the_difference(stale_zip, caplog):
    import policies
    from policies.learned import ModelProvenanceWarning

    with caplog.at_level(logging.WARNING, logger="policies.provenance"), \
            pytest.warns(ModelProvenanceWarning, match="does not match the code"):
        policy = policies.make("learned", path=str(stale_zip))
    assert policy.provenance["matches"] is False
    assert any(d.startswith("return: ") for d in policy.provenance["differences"])
    logged = [r.getMessage() for r in caplog.records if r.name == "policies.provenance"]
    assert len(logged) == 1 and str(stale_zip) in logged[0] and "return: " in logged[0]
    unchecked = policies.make("learned", path=str(stale_zip), check_provenance=False)
    assert unchecked.provenance == {"checked": False, "matches": None, "differences": []}
    with pytest.raises(ValueError, match="check_provenance"):
        policies.make("learned", path=str(stale_zip), check_provenance="no")


def test_a_model_without_a_fingerprint_warns(model_zip):
    import policies
    from policies.learned import ModelProvenanceWarning

    config = json.loads(model_zip.with_suffix(".json").read_text())
    del config["fingerprint"]
    model_zip.with_suffix(".json").write_text(json.dumps(config))
    with pytest.warns(ModelProvenanceWarning, match="no system fingerprint"):
        policy = policies.make("learned", path=str(model_zip))
    assert policy.provenance["matches"] is False


def test_the_fingerprint_command_reports_and_stamps(stale_zip, tmp_path, capsys):
    assert main(["fingerprint", str(stale_zip)]) == 1
    out = capsys.readouterr().out
    assert "does NOT match the code" in out and "  - return: " in out
    assert main(["fingerprint", str(stale_zip), "--json"]) == 1
    payload = json.loads(capsys.readouterr().out)
    assert payload["matches"] is False and payload["differences"][0].startswith("digest: ")
    # a model trained on this code whose JSON predates fingerprints: stamp it, then it matches
    assert main(["fingerprint", str(stale_zip), "--stamp"]) == 0
    assert "stamped" in capsys.readouterr().out
    stamped = json.loads(stale_zip.with_suffix(".json").read_text())["fingerprint"]
    assert stamped["stamped"] is True and stamped["env_options"] == {"n_particles": 5}
    assert main(["fingerprint", str(stale_zip)]) == 0
    assert "matches the code" in capsys.readouterr().out
    bare = tmp_path / "bare.zip"
    bare.write_bytes(stale_zip.read_bytes())
    assert main(["fingerprint", str(bare)]) == 2
    assert "MODEL" in capsys.readouterr().err
    assert main(["fingerprint", str(tmp_path / "missing.zip")]) == 2


def test_the_fingerprint_command_lists_every_shipped_model_with_its_env(tmp_path, monkeypatch,
                                                                        capsys):
    """Without MODEL, every model of the models directory: the env it was trained on, the env
    ids it is the model of, whether it matches the code; exit 1 when one does not. With
    ``--env ID`` and no MODEL, the model shipped for that env."""
    import zipfile

    from shipped_models import ship_copy

    import policies.learned as learned

    interval, zones = "SlamGym/HybridSLAM-Interval-v1", "SlamGym/HybridSLAM-Zones-v1"
    directory = tmp_path / "models"
    ship_copy(directory, "learned-default.zip", interval)
    zones_zip = ship_copy(directory, "learned-zones.zip", zones)
    monkeypatch.setattr(learned, "MODELS_DIR", directory)
    assert main(["fingerprint"]) == 0
    out = capsys.readouterr().out
    assert (f"learned-default.zip: trained on {interval} (the default model); the model of "
            f"{interval}, SlamGym/HybridSLAM-v1") in out
    assert f"learned-zones.zip: trained on {zones}; the model of {zones}\n" in out
    assert out.count(": matches the code") == 2
    assert main(["fingerprint", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["matches"] is True
    assert [(m["model"], m["env_id"], m["serves"], m["matches"]) for m in doc["models"]] == [
        (str(directory / "learned-default.zip"), interval, [interval, "SlamGym/HybridSLAM-v1"],
         True),
        (str(zones_zip), zones, [zones], True)]
    # --env without MODEL: the model that env runs
    assert main(["fingerprint", "--env", zones, "--json"]) == 1  # weights of BB's system
    assert json.loads(capsys.readouterr().out)["model"] == str(zones_zip)
    # a shipped model of another system, and a zip without its config: listed, exit 1
    saved = json.loads(zones_zip.with_suffix(".json").read_text())["fingerprint"]
    other = dict(saved, digest="0" * 64, summary=dict(saved["summary"], **{"return": 1.0}))
    ship_copy(directory, "learned-long.zip", "SlamGym/HybridSLAM-LongMission-v1",
              fingerprint=other)
    with zipfile.ZipFile(directory / "learned-bare.zip", "w") as bare:
        bare.writestr("data", "{}")
    assert main(["fingerprint", "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    verdicts = {m["model"].rsplit("/", 1)[1]: (m["env_id"], m["matches"]) for m in doc["models"]}
    assert verdicts == {"learned-bare.zip": (None, False), "learned-default.zip": (interval, True),
                        "learned-long.zip": ("SlamGym/HybridSLAM-LongMission-v1", False),
                        "learned-zones.zip": (zones, True)}
    assert main(["fingerprint"]) == 1
    out = capsys.readouterr().out
    assert "learned-long.zip: trained on SlamGym/HybridSLAM-LongMission-v1" in out
    assert "does NOT match the code" in out and "return: 1.0 (model)" in out
    assert "learned-bare.zip: trained on an env it does not name" in out and "config JSON" in out


def test_benchmark_rows_carry_whether_the_model_matches_the_code(model_zip, stale_zip):
    from slam_gym.evaluation import Job
    from slam_gym.evaluation.core import learned_options, run_job

    def row(policy, **options):
        from slam_gym.envs.spec import resolve_env

        env = resolve_env(None, {"n_particles": 5, "n_steps": 40})
        return run_job(Job.in_env("policy", policy, env, 2, 3, options))

    matching = row("learned", **learned_options(str(model_zip)))
    assert matching["model_matches_code"] is True and matching["model_differences"] == []
    with pytest.warns(UserWarning):
        stale = row("learned", **learned_options(str(stale_zip)))
    assert stale["model_matches_code"] is False
    assert any(d.startswith("return: ") for d in stale["model_differences"])
    assert "model_matches_code" not in row("fixed-10s")


def test_reproduce_mrclam_rows_carry_whether_the_model_matches_the_code(stale_zip):
    from realdata import MRCLAM_DIR

    from slam_gym.evaluation.real_data import run_mrclam_policy

    with pytest.warns(UserWarning):
        row = run_mrclam_policy("learned", 5, 0, data=str(MRCLAM_DIR), max_steps=50,
                                n_particles=20, model_path=str(stale_zip))
    assert row["model_matches_code"] is False
    assert any(d.startswith("return: ") for d in row["model_differences"])
    rule = run_mrclam_policy("fixed-10s", 5, 0, data=str(MRCLAM_DIR), max_steps=50,
                             n_particles=20)
    assert "model_matches_code" not in rule


def _row(policy, matches, level=0, differences=()):
    row = {"policy": policy, "scenario": "brooks-bailey", "clutter_level": level, "seed": 1,
           "status": "ok", "success": True, "map_error_m": 1.0, "n_fusions": 3}
    if matches is not None or differences:
        row.update(model_matches_code=matches, model_differences=list(differences))
    return row


def test_tables_mark_a_learned_row_whose_model_does_not_match():
    from slam_gym.evaluation import summarise
    from slam_gym.evaluation.summary import markdown_table

    rows = [_row("fixed-10s", None), _row("learned", False, differences=["return: 1 -> 2"]),
            _row("learned", True, level=1)]
    groups = summarise(rows)
    assert "model_matches_code" not in groups[0]
    assert groups[1]["model_matches_code"] is False and groups[2]["model_matches_code"] is True
    table = markdown_table(groups)
    assert "| learned † | 0 |" in table and "| learned | 1 |" in table
    assert "| fixed-10s | 0 |" in table
    footnote = table.strip().splitlines()[-1]
    assert footnote.startswith("† the model was trained on a different system")
    assert "return: 1 -> 2" in footnote
    assert "†" not in markdown_table(summarise([rows[0], rows[2]]))


def test_the_mrclam_table_marks_a_model_that_does_not_match():
    from slam_gym.commands.real_tables import mrclam_table

    rows = [dict(_row("learned", False, differences=["digest: a != b"]), robot=1,
                 association="unknown", driven_system="hybrid"),
            dict(_row("fixed-10s", None), robot=1, association="unknown",
                 driven_system="hybrid")]
    table = mrclam_table(rows)
    assert "| hybrid + learned † | 1 |" in table and "| hybrid + fixed-10s | 1 |" in table
    assert "† the model was trained on a different system" in table
    assert "†" not in mrclam_table(rows[1:])


def test_the_front_table_marks_a_model_that_does_not_match():
    from slam_gym.commands.front import _markdown

    r = {"success_rate": 0.5, "success_diff_pp": 0.0, "success_diff_ci_pp": None,
         "map_error_m": 1.0, "map_error_diff_m": 0.0, "map_error_diff_ci_m": None,
         "interface_cpu_s": 1.0, "interface_cpu_ratio": 1.0, "n_optimisations": 2.0,
         "mean_return": -10.0, "return_diff": 0.0, "return_diff_ci": None}
    table = {"fixed-10s": r, "learned @ 1/s": r}
    assert "| learned @ 1/s † |" in _markdown(table, marked={"learned @ 1/s"})
    assert "†" not in _markdown(table)


@pytest.fixture
def ship(tmp_path, monkeypatch):
    """scripts/tools/ship_model.py, shipping into tmp_path/shipped (figures into tmp_path)."""
    from script_loader import load_script

    ship = load_script("tools/ship_model.py")
    monkeypatch.setattr(ship, "TARGET", tmp_path / "shipped" / "learned-default.zip")
    monkeypatch.setattr(ship, "FIGURES", tmp_path / "figures")
    (tmp_path / "shipped").mkdir()
    return ship


def _one_seed_train_out(model_zip):
    """The folder of ``model_zip`` made a one-seed ``slam-gym train`` output (its summary)."""
    out = model_zip.parent
    (out / "summary.json").write_text(json.dumps({
        "chosen_seed": 0, "algo": "ppo", "seeds": [0],
        "final_evaluation": {"0": {"mean_return": -1.0, "success_rate": 1.0, "mode": "sampled"}},
    }))
    return out


def test_ship_model_refuses_a_model_of_another_system(stale_zip, ship):
    out = _one_seed_train_out(stale_zip)
    assert ship.main([str(out)]) == 1
    assert not ship.TARGET.exists()
    assert ship.main(["--force", str(out)]) == 0
    assert ship.TARGET.is_file()
    assert np.isfinite(json.loads(ship.TARGET.with_suffix(".json").read_text())["timesteps"])


def test_fingerprint_says_which_env_version_a_model_was_trained_on_and_what_was_done():
    from slam_gym.commands.fingerprint import env_version_lines

    lines, version = env_version_lines({"env_id": "SlamGym/HybridSLAM-Interval-v0"})
    assert version["trained_on_version"] == 0
    assert version["current_id"] == "SlamGym/HybridSLAM-Interval-v1"
    assert "trained on v0" in lines[0] and "not compared" in lines[1]
    assert "--env SlamGym/HybridSLAM-v0" in lines[1]  # the system the wrapper runs
    check = {"checked_on": "SlamGym/HybridSLAM-Interval-v1", "outcome": "not re-stamped",
             "why": "undecided at 40 worlds"}
    lines, _ = env_version_lines({"env_id": "SlamGym/HybridSLAM-Interval-v0",
                                  "env_version_check": check})
    assert "not re-stamped - undecided at 40 worlds" in lines[1]
    lines, version = env_version_lines({"env_id": "SlamGym/HybridSLAM-v1"})
    assert version["trained_on_version"] == 1 and "the current version" in lines[0]
    with pytest.raises(ValueError, match="env_id="):
        env_version_lines({"env_id": "SlamGym/HybridSLAM"})


def test_shipping_a_model_of_a_later_env_version_records_that_it_was_retrained(
        model_zip, ship, monkeypatch):
    from slam_gym.commands.fingerprint import env_version_lines

    monkeypatch.setattr(ship, "head_commit", lambda: "abc1234")
    old_check = {"checked_on": "SlamGym/HybridSLAM-v1", "outcome": "not re-stamped",
                 "why": "undecided at 40 worlds"}
    ship.TARGET.with_suffix(".json").write_text(json.dumps(
        {"env_id": "SlamGym/HybridSLAM-v0", "command": "slam-gym train --env v0",
         "env_version_check": old_check}))
    out = _one_seed_train_out(model_zip)
    assert ship.main([str(out)]) == 0
    shipped = json.loads(ship.TARGET.with_suffix(".json").read_text())
    check = shipped["env_version_check"]
    assert check["outcome"] == "retrained on SlamGym/HybridSLAM-v1"
    assert "replaces a model trained on SlamGym/HybridSLAM-v0" in check["why"]
    assert "whose check on SlamGym/HybridSLAM-v1 was: not re-stamped" in check["why"]
    assert check["replaces"]["env_version_check"] == old_check
    assert check["replaces"]["restore"] == "git show abc1234:policies/models/learned-default.zip"
    lines, version = env_version_lines(shipped)
    assert version["trained_on_version"] == 1 and "the current version" in lines[0]
    assert "retrained on SlamGym/HybridSLAM-v1" in lines[1] and "git show abc1234" in lines[1]
    # shipping it again over itself (same version) records no retraining
    assert ship.retraining_record(shipped, shipped) is None
    assert ship.retraining_record(None, shipped) is None


def test_the_restore_command_names_a_commit_only_when_it_holds_the_replaced_model(
        ship, tmp_path, monkeypatch):
    import subprocess

    repo = tmp_path / "repo"
    (repo / "models").mkdir(parents=True)
    target = repo / "models" / "learned-default.zip"
    target.write_bytes(b"old model")
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "model"], check=True)
    monkeypatch.setattr(ship, "ROOT", repo)
    monkeypatch.setattr(ship, "TARGET", target)
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], check=True,
                          capture_output=True, text=True).stdout.strip()
    assert ship.head_commit() == head
    target.write_bytes(b"a model not committed")
    assert ship.head_commit() is None
    monkeypatch.setattr(ship, "ROOT", tmp_path)  # not a checkout
    assert ship.head_commit() is None
