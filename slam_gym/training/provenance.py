"""Provenance of learned models: a fingerprint of the system a model was trained on (issue 29).

A model learns the env it was trained in: its features, its reward, the filters behind them. When
the code changes what the env shows or pays (a new term in the front-end, another reward weight),
a saved model keeps acting on the old meaning, and nothing else notices. The *system fingerprint*
is a short, fixed, seeded rollout of the env under the model's env options, summarised:

* the rollout: :data:`ROLLOUT_DECISIONS` decisions of ``HybridSLAMEnv`` (the model's env options,
  the path cut to that length, world and filter seed :data:`ROLLOUT_SEED`) under a fixed action
  schedule (:func:`scheduled_action`: fuse every 5 decisions, optimise at every other fusion, and
  two optimisation requests between fusions, one of them redundant), so the front-end, the
  fusion, the optimiser and the redundant-optimisation rule are all exercised;
* every decision's features (all of ``info["features"]``, by name), reward, reward components,
  fusion and optimisation counts and failure flag, each written with :data:`SIGNIFICANT_DIGITS`
  significant digits: float noise (a last bit from another BLAS) passes, a behaviour change does
  not;
* ``digest``: the SHA-256 of those rounded records; ``chunk_digests``: one per
  :data:`CHUNK_DECISIONS` decisions (where the rollouts part); ``summary``: readable numbers (the
  return, each reward component's sum, fusions, optimisations, the final map and pose error, the
  mean of every feature over the rollout), so a difference can be named
  (:func:`compare_fingerprints`).

The rollout costs about 1 s of CPU at 500 particles (``cpu_s`` in the fingerprint; measured 0.9-1.1
s on a 2-core machine shared with a training run) and is cached per env options within a process
(:func:`system_fingerprint`), so loading many models is cheap.

A value at a rounding boundary can still flip its last digit under float noise; the digest then
differs while every summary number agrees, and :func:`compare_fingerprints` says so.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

FINGERPRINT_VERSION = 1
"""Changes when the rollout, its schedule or its rounding change: fingerprints of different
versions cannot be compared."""

ROLLOUT_DECISIONS = 60
"""Decisions of the rollout (the path is cut to this many decision intervals)."""

ROLLOUT_SEED = 5
"""The env's ``reset`` seed and world seed of the rollout."""

SIGNIFICANT_DIGITS = 4
"""Every recorded number is written with this many significant digits."""

CHUNK_DECISIONS = 20
"""Decisions per chunk digest."""

DEFAULT_ENV_ID = "SlamGym/HybridSLAM-v0"
"""The env id of a model whose config names none (such configs predate ``-v1``)."""

PRE_STREAMS_OPTIONS = {"random_streams": "ordered"}
"""What a fingerprint that names no ``random_streams`` was made with: every fingerprint before
the synchronised streams of ``-v1`` (issue 46) was made on the ordered stream."""

IGNORED_OPTIONS = ("n_steps", "max_decisions", "features", "info_compute_time")
"""Env options the fingerprint sets itself (the rollout's length) or that do not change the
system (which features the observation selects: the rollout records all of them)."""

SCHEDULE = ("fuse at decisions 5, 10, 15, ...; optimise with every other fusion (10, 20, ...) "
            "and alone at decisions 12, 37, 62, ... (12 redundant: the fusion at 10 was "
            "optimised; 37 optimises the fusion at 35)")
"""The action schedule in words (:func:`scheduled_action`; decisions counted from 1)."""

_CACHE: dict[str, dict[str, Any]] = {}
"""Fingerprints computed in this process, by canonical env options."""


def scheduled_action(decision: int) -> np.ndarray:
    """The (fuse, optimise) action of decision ``decision`` (counted from 1) of the rollout."""
    fuse = decision % 5 == 0
    optimise = (fuse and decision % 10 == 0) or decision % 25 == 12
    return np.array([int(fuse), int(optimise)], dtype=np.int64)


def system_options(env_id: str | None = None,
                   env_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The options of the rollout's env: ``env_id``'s registered keyword arguments, then
    ``env_options``, without :data:`IGNORED_OPTIONS`; ``ValueError`` naming ``env_id`` or the
    option when the env cannot be fingerprinted."""
    from slam_gym.envs.hybrid_slam import HybridSLAMConfig
    from slam_gym.envs.spec import check_env_id, registered_kwargs, resolve_env, system_id

    env_id = system_id(check_env_id(DEFAULT_ENV_ID if env_id is None else env_id, "env_id"))
    if env_options is not None and not isinstance(env_options, Mapping):
        raise ValueError(f"env_options={env_options!r} is invalid: must be a mapping of env "
                         "options")
    if resolve_env(env_id).scenario == "recorded":
        raise ValueError(f"env_id={env_id!r} is invalid: must be a simulated env (recorded "
                         "data has no fixed rollout)")
    options = {**registered_kwargs(env_id), **dict(env_options or {})}
    for key in IGNORED_OPTIONS:
        options.pop(key, None)
    HybridSLAMConfig.from_kwargs(**options)  # ValueError naming an unknown or bad option
    return json.loads(json.dumps(options, sort_keys=True))  # plain JSON, as model.json holds it


def _fmt(value: Any) -> str:
    """A number with :data:`SIGNIFICANT_DIGITS` significant digits (None, bools and NaN named)."""
    if value is None:
        return "none"
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    x = float(value)
    if not math.isfinite(x):
        return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if x == 0.0:
        return "0"  # no -0
    return f"{x:.{SIGNIFICANT_DIGITS}g}"


def _rounded(value: Any) -> float | str | None:
    """:func:`_fmt`'s number as JSON: a float, None, or the text of a non-finite value (so that
    equal fingerprints compare equal: NaN != NaN)."""
    text = _fmt(value)
    if text == "none":
        return None
    return text if text in ("nan", "inf", "-inf", "true", "false") else float(text)


def rollout(options: Mapping[str, Any], decisions: int = ROLLOUT_DECISIONS,
            seed: int = ROLLOUT_SEED) -> dict[str, Any]:
    """Run the fixed rollout under env ``options`` (:func:`system_options`) and fingerprint it
    (without the options; :func:`system_fingerprint` adds them)."""
    from slam_gym.envs.hybrid_slam import REWARD_COMPONENTS, HybridSLAMEnv

    if not (isinstance(decisions, int) and not isinstance(decisions, bool) and decisions >= 1):
        raise ValueError(f"decisions={decisions!r} is invalid: must be a positive integer")
    cpu0 = time.process_time()
    config = dict(options)
    interval = int(config.get("decision_interval", 10))
    # the reset runs the first interval: one more, so the path holds all the decisions
    env = HybridSLAMEnv(**config, n_steps=(decisions + 1) * interval)
    _, info = env.reset(seed=seed, options={"world_seed": seed})
    feature_names = list(info["features"])
    digest = hashlib.sha256()
    chunk = hashlib.sha256()
    chunk_digests: list[str] = []
    feature_sums = dict.fromkeys(feature_names, 0.0)
    component_sums = dict.fromkeys(REWARD_COMPONENTS, 0.0)
    total_reward = 0.0
    n = 0
    terminated = truncated = False
    while n < decisions and not (terminated or truncated):
        n += 1
        _, reward, terminated, truncated, info = env.step(scheduled_action(n))
        features = info["features"]
        record = [_fmt(features.get(name)) for name in feature_names]
        record += [_fmt(reward)]
        record += [_fmt(info["reward_components"][c]) for c in REWARD_COMPONENTS]
        record += [str(info["n_fusions"]), str(info["n_optimisations"]), _fmt(info["failed"]),
                   _fmt(terminated), _fmt(truncated)]
        line = (",".join(record) + "\n").encode()
        digest.update(line)
        chunk.update(line)
        if n % CHUNK_DECISIONS == 0:
            chunk_digests.append(chunk.hexdigest()[:12])
            chunk = hashlib.sha256()
        total_reward += float(reward)
        for name in feature_names:
            value = features.get(name)
            feature_sums[name] += float(value) if value is not None else 0.0
        for c in REWARD_COMPONENTS:
            component_sums[c] += float(info["reward_components"][c])
    if n % CHUNK_DECISIONS:
        chunk_digests.append(chunk.hexdigest()[:12])
    summary: dict[str, Any] = {
        "decisions": n,
        "failed": bool(info["failed"]),
        "n_fusions": int(info["n_fusions"]),
        "n_optimisations": int(info["n_optimisations"]),
        "return": _rounded(total_reward),
        **{f"reward_{c}": _rounded(v) for c, v in component_sums.items()},
        "final_pose_error_m": _rounded(info.get("pose_error_m")),
        "final_map_error_m": _rounded(info.get("map_error_m")),
        "final_map_completeness": _rounded(info.get("map_completeness")),
        **{f"mean_{name}": _rounded(v / n) for name, v in feature_sums.items()},
    }
    env.close()
    return {
        "version": FINGERPRINT_VERSION,
        "digest": digest.hexdigest(),
        "chunk_digests": chunk_digests,
        "decisions": decisions,
        "chunk_decisions": CHUNK_DECISIONS,
        "seed": seed,
        "significant_digits": SIGNIFICANT_DIGITS,
        "schedule": SCHEDULE,
        "feature_names": feature_names,
        "summary": summary,
        "cpu_s": round(time.process_time() - cpu0, 3),
    }


def system_fingerprint(env_id: str | None = None, env_options: Mapping[str, Any] | None = None,
                       *, cache: bool = True) -> dict[str, Any]:
    """The fingerprint of the system ``env_id`` (None: :data:`DEFAULT_ENV_ID`) with
    ``env_options`` (e.g. a model's ``env_options``): a JSON-able dict (module docstring) with
    ``env_id`` and the ``env_options`` it was computed under. Cached per options in this process
    (``cache=False`` recomputes); the caller gets its own copy."""
    options = system_options(env_id, env_options)
    key = json.dumps(options, sort_keys=True)
    if not cache or key not in _CACHE:
        fingerprint = rollout(options)
        logger.debug("system fingerprint of %s: %s (%.2f s CPU)", key, fingerprint["digest"][:16],
                     fingerprint["cpu_s"])
        _CACHE[key] = fingerprint
    return {"env_id": DEFAULT_ENV_ID if env_id is None else env_id, "env_options": options,
            **copy.deepcopy(_CACHE[key])}


def fingerprint_of_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """The current fingerprint for a model config (``model.json``): its ``env_id`` and
    ``env_options`` (those of its saved fingerprint when it has one: the options it was
    computed under)."""
    saved = config.get("fingerprint")
    if isinstance(saved, Mapping) and "env_options" in saved:
        return system_fingerprint(saved.get("env_id"), saved.get("env_options"))
    return system_fingerprint(config.get("env_id"), config.get("env_options"))


def _num_text(value: Any) -> str:
    return "missing" if value is None else str(value)


def compare_fingerprints(saved: Mapping[str, Any] | None,
                         current: Mapping[str, Any]) -> list[str]:
    """Human-readable differences between a model's ``saved`` fingerprint and the ``current``
    one (empty: the model matches the code). Names the digest, the env options, the feature
    names, every summary number that differs and the first decisions where the rollouts part."""
    if not isinstance(saved, Mapping) or "digest" not in saved:
        return ["the model records no system fingerprint (saved before provenance existed, or "
                "not by slam-gym train): the system it was trained on is unknown"]
    if saved.get("version") != current.get("version"):
        return [f"fingerprint version {saved.get('version')} (model) != "
                f"{current.get('version')} (code): the rollouts differ, so the systems cannot "
                "be compared; stamp the model on the code it was trained on"]
    out: list[str] = []
    for key in ("decisions", "seed", "significant_digits"):
        if saved.get(key) != current.get(key):
            out.append(f"rollout {key}: {saved.get(key)} (model) != {current.get(key)} (code)")
    saved_options, current_options = saved.get("env_options") or {}, current.get("env_options")
    if "random_streams" not in saved_options and "random_streams" in (current_options or {}):
        saved_options = PRE_STREAMS_OPTIONS | dict(saved_options)
    if saved_options != current_options:
        keys = sorted(set(saved_options) | set(current_options or {}))
        diff = [f"{k}={saved_options.get(k)!r} -> {(current_options or {}).get(k)!r}"
                for k in keys if saved_options.get(k) != (current_options or {}).get(k)]
        out.append("env options: " + ", ".join(diff) + " (model -> code)")
    if saved.get("digest") == current.get("digest") and not out:
        return []
    if saved.get("digest") != current.get("digest"):
        out.insert(0, f"digest: {str(saved.get('digest'))[:16]} (model) != "
                      f"{str(current.get('digest'))[:16]} (code)")
    names_saved, names_now = list(saved.get("feature_names") or []), list(
        current.get("feature_names") or [])
    if names_saved != names_now:
        added = [n for n in names_now if n not in names_saved]
        removed = [n for n in names_saved if n not in names_now]
        parts = ([f"added {added}"] if added else []) + ([f"removed {removed}"] if removed else [])
        out.append("feature names: " + ("; ".join(parts) if parts else "reordered"))
    chunks_saved, chunks_now = saved.get("chunk_digests") or [], current.get("chunk_digests") or []
    for i, (a, b) in enumerate(zip(chunks_saved, chunks_now, strict=False)):
        if a != b:
            first = i * int(saved.get("chunk_decisions", CHUNK_DECISIONS)) + 1
            out.append(f"the rollouts part in decisions {first}-{first + CHUNK_DECISIONS - 1}")
            break
    summary_saved, summary_now = saved.get("summary") or {}, current.get("summary") or {}
    named = 0
    for key in list(summary_saved) + [k for k in summary_now if k not in summary_saved]:
        a, b = summary_saved.get(key), summary_now.get(key)
        if a != b:
            named += 1
            out.append(f"{key}: {_num_text(a)} (model) -> {_num_text(b)} (code)")
    if saved.get("digest") != current.get("digest") and not named and names_saved == names_now:
        out.append("every summary number agrees: a change below the rounding or float noise at "
                   "a rounding boundary")
    return out


def check_model_provenance(model_path: Path, config: Mapping[str, Any] | None) -> dict[str, Any]:
    """Compare the fingerprint a model records (its config JSON's ``fingerprint``) with the
    current code's for the same env options (computed once per env options in a process);
    ``{"checked": True, "matches": bool, "differences": [...]}``. A mismatch, or a model that
    records no fingerprint, is logged as a WARNING on ``policies.provenance`` and warned as
    :class:`policies.learned.ModelProvenanceWarning`, naming what differs.

    Every :class:`policies.learned.LearnedPolicy` loaded in a process that imported ``slam_gym``
    runs this check (``slam_gym/__init__.py`` installs it:
    :func:`policies.learned.set_provenance_check`)."""
    import warnings

    from policies.learned import ModelProvenanceWarning, provenance_logger

    result = model_provenance(config)
    provenance = {"checked": True, "matches": bool(result["matches"]),
                  "differences": list(result["differences"])}
    if not provenance["matches"]:
        message = (f"learned model {model_path} does not match the code it runs on (it was "
                   "trained on a different system; its decisions may not mean what they did): "
                   + "; ".join(provenance["differences"]))
        provenance_logger.warning("%s", message)
        # attributed to the caller of LearnedPolicy(...), as before the check moved here
        warnings.warn(message, ModelProvenanceWarning, stacklevel=4)
    return provenance


def model_provenance(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """``{"matches": bool, "differences": [...], "fingerprint": current or None}`` for a model
    config (``model.json``; None: the model has none). The current fingerprint is computed only
    when the model records one to compare with."""
    saved = None if config is None else config.get("fingerprint")
    if not isinstance(saved, Mapping) or "digest" not in saved:
        return {"matches": False, "differences": compare_fingerprints(None, {}),
                "fingerprint": None}
    current = fingerprint_of_config(config)
    differences = compare_fingerprints(saved, current)
    return {"matches": not differences, "differences": differences, "fingerprint": current}
