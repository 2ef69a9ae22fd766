"""``slam-gym fingerprint``: does a learned model match the code it runs on? (issue 29, item 1)

Compares the system fingerprint a model records in its config JSON (``model.json``, written by
``slam-gym train``; :mod:`slam_gym.training.provenance`) with the current code's for the model's
env options, and prints whether they match and, if not, what differs. Exit status 0 when the
model matches, 1 when it does not (or records no fingerprint).

Which model: ``MODEL``; else, with ``--env ID``, the model ``learned`` runs in that env (the one
shipped for it, else the default: :func:`policies.learned.resolve_model_path`); else every
shipped model (each ``*.zip`` of ``policies/models``), each with the env id it was trained on
and the env ids it is the model of (:func:`policies.learned.model_table`), exit 1 when any of
them does not match.

``--stamp`` writes the current fingerprint into the model's JSON instead: for a model trained on
this very code whose JSON predates fingerprints (or was copied without one). Stamping asserts
that the model was trained on this code; the fingerprint then carries ``"stamped": true``.

A model trained on an env id's earlier version (``-v0``: the filter's random numbers in one
ordered stream) says so, with what its config's ``env_version_check`` records: whether it was
compared on the current version against its earlier self and re-stamped, or not and why
(issue 46). A model retrained on the current version says that it was, and which model it
replaced (recorded by ``scripts/tools/ship_model.py``).
"""

from __future__ import annotations

import json
import logging
import zipfile
from pathlib import Path

from slam_gym.commands.common import emit

logger = logging.getLogger(__name__)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fingerprint",
        help="whether a learned model matches the code (its system fingerprint); --stamp it")
    p.add_argument("model", nargs="?", default=None,
                   help="model zip (default: the model shipped for --env; without --env every "
                   "shipped model, each with its env id; --stamp: learned-default.zip)")
    p.add_argument("--stamp", action="store_true",
                   help="write the current fingerprint into the model's JSON (only for a model "
                        "trained on this code)")
    p.add_argument("--env", default=None, metavar="ID",
                   help="check the model against this env's system (default: the env its "
                   "config records), e.g. before running it with --env ID elsewhere")
    p.add_argument("--env-kwargs", nargs="+", default=None, metavar="KEY:VALUE",
                   help="keyword arguments of --env over the id's own (KEY:VALUE, VALUE as "
                   "JSON)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(run=run)


def env_to_check(args, config: dict) -> tuple[str | None, dict | None]:
    """The env id and options the current fingerprint is computed for: ``--env`` with
    ``--env-kwargs`` (checked like every command's), else those the model records."""
    from slam_gym.envs.spec import check_env_id, parse_env_kwargs, resolve_env, system_id

    if args.env is None:
        if args.env_kwargs:
            raise ValueError(f"env_kwargs={args.env_kwargs!r} is invalid without --env: they "
                             "are options of the env --env names")
        saved = config.get("fingerprint")
        if isinstance(saved, dict) and "env_options" in saved:
            return saved.get("env_id"), saved.get("env_options")
        env_id = config.get("env_id")
        return (None if env_id is None else system_id(env_id)), config.get("env_options")
    env_id = system_id(check_env_id(args.env))
    kwargs = parse_env_kwargs(args.env_kwargs)
    resolve_env(env_id, kwargs)  # every option checked
    return env_id, kwargs


def env_version_lines(config: dict) -> tuple[list[str], dict]:
    """What the model's env version is, against the current one, and what was done about it."""
    from slam_gym.envs import env_version, system_env_id

    env_id = config.get("env_id") or "SlamGym/HybridSLAM-v0"
    trained = env_version(env_id)
    current_id = env_id.rpartition("-v")[0] + "-v1"
    check = config.get("env_version_check")
    version = {"env_id": env_id, "trained_on_version": trained, "current_id": current_id,
               "check": check}
    if trained >= 1:
        lines = [f"  env {env_id}: the current version"]
        if isinstance(check, dict):
            replaces = check.get("replaces") or {}
            lines.append(f"  {check.get('outcome', '?')} - {check.get('why', '')}"
                         + (f"; restore the replaced model with `{replaces['restore']}`"
                            if replaces.get("restore") else ""))
        return lines, version
    lines = [f"  env {env_id}: trained on v{trained} (the filter's random numbers in one ordered "
             f"stream); the current version is {current_id} (synchronised numbers)"]
    if not isinstance(check, dict):
        lines.append("  not compared on the current version: benchmark it with "
                     f"`--env {system_env_id(env_id)}` to play it as trained, or retrain it on "
                     f"{current_id}")
        return lines, version
    lines.append(f"  on {check.get('checked_on', current_id)}: {check.get('outcome', '?')} - "
                 f"{check.get('why', '')}")
    return lines, version


def check_model(args, path: Path, config: dict) -> tuple[dict, list[str]]:
    """The report of one model (its JSON object and its lines): whether its fingerprint matches
    the code's for the env :func:`env_to_check` chooses, what differs, and its env version."""
    from slam_gym.training.provenance import compare_fingerprints, system_fingerprint

    saved = config.get("fingerprint")
    current = system_fingerprint(*env_to_check(args, config))
    differences = compare_fingerprints(saved, current)
    matches = not differences
    if matches:
        lines = [f"{path}: matches the code (fingerprint {current['digest'][:16]}, env options "
                 f"{current['env_options']})"]
    else:
        lines = [f"{path}: does NOT match the code (trained on a different system):",
                 *(f"  - {d}" for d in differences)]
    version_lines, version = env_version_lines(config)
    return ({"model": str(path), "matches": matches, "differences": differences,
             "fingerprint": current, "saved_fingerprint": saved, "env_version": version},
            lines + version_lines)


def model_file(path: Path, given: str) -> tuple[Path, dict]:
    """The model zip at ``path`` and its config JSON; ``ValueError`` naming ``given`` (the
    ``MODEL`` argument, or the shipped file) when it is not a zip or has no config."""
    from policies.learned import read_model_config

    if not zipfile.is_zipfile(path):
        raise ValueError(f"{given}={str(path)!r} is invalid: it is not a zip file (a model is the "
                         "zip that slam-gym train writes, with its config JSON beside it)")
    config = read_model_config(path)
    if config is None:
        raise ValueError(f"{given}={str(path)!r} is invalid: it has no config JSON "
                         f"({path.with_suffix('.json').name}, written by slam-gym train), so "
                         "the env options it was trained under are unknown")
    return path, config


def run_shipped(args) -> int:
    """Every shipped model, each with the env id it was trained on, the env ids it is the model
    of, and whether it matches the code; exit 1 when any does not (or cannot be read)."""
    from policies.learned import MODELS_DIR, model_table, shipped_models

    models = shipped_models()
    if not models:
        raise ValueError(f"MODEL=None is invalid: no model ships in {MODELS_DIR} (give a model "
                         "zip)")
    table = model_table()
    docs, lines = [], []
    for model in models:
        serves = sorted(env_id for env_id, path in table.items() if path == model.path)
        head = {"env_id": model.env_id, "serves": serves, "default": model.is_default}
        lines.append(f"{model.path.name}: trained on {model.env_id or 'an env it does not name'}"
                     + (" (the default model)" if model.is_default else "")
                     + "; the model of " + (", ".join(serves) if serves else "no env id"))
        try:
            doc, model_lines = check_model(args, *model_file(model.path, "model"))
        except ValueError as exc:
            doc = {"model": str(model.path), "matches": False, "differences": [str(exc)]}
            model_lines = [f"{model.path}: does NOT match the code: {exc}"]
        docs.append(head | doc)
        lines += [f"  {line}" for line in model_lines]
    matches = all(d["matches"] for d in docs)
    emit(args, {"models": docs, "matches": matches}, lines)
    return 0 if matches else 1


def run(args) -> int:
    from policies.learned import resolve_model_path
    from slam_gym.envs.spec import check_env_id
    from slam_gym.training.provenance import compare_fingerprints, system_fingerprint

    if args.model is None and args.env is None and not args.stamp:
        return run_shipped(args)
    if args.env is not None:
        check_env_id(args.env)  # before resolving: a typo is named, not a model's fallback
    try:
        path = resolve_model_path(args.model, None if args.model is not None or args.stamp
                                  else args.env)
    except FileNotFoundError as exc:
        raise ValueError(f"MODEL={args.model!r} is invalid: {exc}") from exc
    path, config = model_file(path, "MODEL")
    saved = config.get("fingerprint")
    if args.stamp:
        from slam_gym.envs import system_env_id

        if args.env is not None:
            raise ValueError(f"env={args.env!r} is invalid with --stamp: a model is stamped "
                             "with the env its config records")
        env_id = config.get("env_id")
        current = system_fingerprint(None if env_id is None else system_env_id(env_id),
                                     config.get("env_options"))
        current["stamped"] = True
        replaced = compare_fingerprints(saved, current) if saved is not None else []
        if replaced:
            logger.warning("%s: replacing a fingerprint that differs from the code's: %s", path,
                           "; ".join(replaced))
        config["fingerprint"] = current
        target = path.with_suffix(".json")
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(config, indent=2) + "\n")
        tmp.replace(target)
        emit(args, {"model": str(path), "stamped": True, "fingerprint": current,
                    "replaced_differences": replaced},
             [f"{path}: stamped with the current fingerprint {current['digest'][:16]} "
              f"(env options {current['env_options']}; {current['cpu_s']:.2f} s CPU)"])
        return 0
    doc, lines = check_model(args, path, config)
    emit(args, doc, lines)
    return 0 if doc["matches"] else 1
