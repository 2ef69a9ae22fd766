"""Ship the best of several ``slam-gym train`` outputs as the default learned policy (#15).

Usage: python scripts/tools/ship_model.py [--force] TRAIN_OUT [TRAIN_OUT ...]
e.g.   python scripts/tools/ship_model.py out/train15/ppo out/train15/a2c

Each TRAIN_OUT is the ``--out`` of one ``slam-gym train`` (one algorithm, several seeds): its
``summary.json`` names the seed chosen there and ``model.zip``/``model.json`` are that seed's
model. Among them the one with the highest mean return of its final evaluation on the
*training-time* evaluation worlds is copied to ``policies/models/learned-default.{zip,json}``
(success rate breaks ties), the same rule ``slam-gym train`` applies across seeds; nothing here
reads the reported (benchmark) worlds. The JSON gains ``chosen_among_algorithms``: every
candidate's algorithm, seed and final evaluation. Beside the model go its hyper-parameters as
the YAML entry it was trained with (``learned-default.yml``, rl-zoo3 layout: ``slam-gym train
--hyperparams`` reads it back) and its algorithm's training curves over every seed
(``learned-default_training_curves.png``); every candidate's curves are also copied to
``docs/figures/training_curves_<algo>.png``.

A model whose system fingerprint (its ``model.json``'s ``fingerprint``,
:mod:`slam_gym.training.provenance`) does not match the code it would ship with is refused,
naming what differs (exit 1): it was trained on another system. ``--force`` ships it anyway,
with a warning (the packaged-model test then fails until a matching model ships).

A model trained on a later env version than the one it replaces (``-v1`` after ``-v0``: issue
46) records so under ``env_version_check``: ``outcome`` "retrained on <id>", the replaced
model's env id and the ``git show`` that restores it, and why it was retrained (the replaced
model's own ``env_version_check``, when it has one). ``slam-gym fingerprint`` prints it.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

logger = logging.getLogger(__name__)
ROOT = Path(__file__).resolve().parents[2]
TARGET = ROOT / "policies" / "models" / "learned-default.zip"
FIGURES = ROOT / "docs" / "figures"


def candidates(outs: list[Path]) -> list[dict]:
    found = []
    for out in outs:
        summary_path, model = out / "summary.json", out / "model.zip"
        if not (summary_path.is_file() and model.is_file()):
            raise ValueError(f"TRAIN_OUT={str(out)!r} is invalid: it must hold the summary.json "
                             "and model.zip that `slam-gym train` writes")
        summary = json.loads(summary_path.read_text())
        seed = summary["chosen_seed"]
        final = summary["final_evaluation"][str(seed)]
        found.append({"out": str(out), "algo": summary["algo"], "seed": seed,
                      "mean_return": final["mean_return"], "success_rate": final["success_rate"],
                      "mode": final["mode"], "n_seeds": len(summary["seeds"])})
    return found


def provenance_differences(config: dict) -> list[str]:
    """What differs between the system a model config records and the current code's (empty: it
    matches)."""
    from slam_gym.training.provenance import compare_fingerprints, fingerprint_of_config

    return compare_fingerprints(config.get("fingerprint"), fingerprint_of_config(config))


def retraining_record(replaced: dict | None, shipped: dict) -> dict | None:
    """The ``env_version_check`` of a model that replaces one trained on an earlier env version
    (``None`` when there is no such model, or the versions are the same)."""
    from slam_gym.envs import env_version

    if not replaced or not replaced.get("env_id") or not shipped.get("env_id"):
        return None
    old_id, new_id = replaced["env_id"], shipped["env_id"]
    if env_version(new_id) <= env_version(old_id):
        return None
    old_check = replaced.get("env_version_check") or {}
    commit = head_commit()
    restore = f"git show {commit}:policies/models/{TARGET.name}" if commit else None
    return {"checked_on": new_id, "outcome": f"retrained on {new_id}",
            "why": (f"replaces a model trained on {old_id}"
                    + (f", whose check on {old_check.get('checked_on')} was: "
                       f"{old_check.get('outcome')}" if old_check else "")),
            "replaces": {"env_id": old_id, "command": replaced.get("command"),
                         "env_version_check": old_check or None, "restore": restore}}


def head_commit() -> str | None:
    """The repository's HEAD (short) when the packaged model there is the one in the working tree
    (so that ``git show HEAD:...`` restores it); ``None`` outside a git checkout or when the
    working tree's model differs from HEAD's."""
    try:
        done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=True,
                              capture_output=True, text=True)
        changed = subprocess.run(["git", "status", "--porcelain", "--", str(TARGET)], cwd=ROOT,
                                 check=True, capture_output=True, text=True)
    except (OSError, subprocess.CalledProcessError):
        return None
    if changed.stdout.strip():
        logger.warning("%s differs from the commit's: the record names no commit to restore it",
                       TARGET)
        return None
    return done.stdout.strip() or None


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("train_out", nargs="+", metavar="TRAIN_OUT",
                        help="the --out of one slam-gym train (one algorithm, several seeds)")
    parser.add_argument("--force", action="store_true",
                        help="ship a model whose fingerprint does not match the code")
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args = parse_args(argv)
    force = args.force
    argv = list(args.train_out)
    found = candidates([Path(a) for a in argv])
    best = max(found, key=lambda c: (c["mean_return"], c["success_rate"]))
    source = Path(best["out"]) / "model.zip"
    config = json.loads(source.with_suffix(".json").read_text())
    differences = provenance_differences(config)
    if differences:
        message = (f"{source} does not match the code it would ship with (trained on a different "
                   "system): " + "; ".join(differences))
        if not force:
            logger.error("%s\nnot shipped (retrain on this code, or --force)", message)
            return 1
        logger.warning("%s\nshipping it anyway (--force)", message)
    old_json = TARGET.with_suffix(".json")
    replaced = json.loads(old_json.read_text()) if old_json.is_file() else None
    record = retraining_record(replaced, config)
    if record is not None:
        config["env_version_check"] = record
        logger.info("%s; %s", record["outcome"], record["why"])
    shutil.copyfile(source, TARGET)
    config["chosen_among_algorithms"] = found
    config["shipped_by"] = "python scripts/tools/ship_model.py " + " ".join(argv)
    TARGET.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
    header = (f"# The hyper-parameters of policies/models/learned-default.zip ({best['algo']}, "
              f"seed {best['seed']}),\n# as trained by: {config['command']}\n")
    TARGET.with_suffix(".yml").write_text(
        header + yaml.safe_dump({config["env_id"]: config["hyperparams"]}, sort_keys=False))
    for c in found:
        curves = Path(c["out"]) / "training_curves.png"
        if curves.is_file():
            shutil.copyfile(curves, FIGURES / f"training_curves_{c['algo']}.png")
            if c is best:
                shutil.copyfile(curves, TARGET.parent / "learned-default_training_curves.png")
    for c in found:
        logger.info("%-4s seed %d (%d seeds, %s): mean return %.0f, success %.2f%s", c["algo"],
                    c["seed"], c["n_seeds"], c["mode"], c["mean_return"], c["success_rate"],
                    "   <- shipped" if c is best else "")
    logger.info("wrote %s (+ .json)", TARGET)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
