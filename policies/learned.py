"""Learned interface policies: a stable-baselines3 model loaded from its zip (docs/ARCHITECTURE.md,
"Policies").

``LearnedPolicy(path=..., algo=...)`` loads a model saved by stable-baselines3 (``model.save``;
``slam-gym train`` writes one) and acts with ``model.predict(obs, deterministic=True)`` on the
env's observation vector, or, for a model whose config JSON lists ``feature_names`` (the shipped
one does), on those features read by name from ``info["features"]``, which it then requires;
``info["optimise_redundant"]`` gives a MaskablePPO model its mask (below). stable-baselines3 (and
torch) are imported only when a model is loaded, so ``import policies`` stays light.

Which model (:func:`resolve_model_path`): an explicit ``path`` wins; else the model shipped for
the ``env_id`` the policy acts in (``policies.make("learned", env_id=...)``; every command with
``--env ID`` passes its id): the ``*.zip`` of :data:`MODELS_DIR` whose config JSON records that
``env_id`` (or runs it as the system of a wrapped env: :func:`model_table`); else the default
model ``learned-default.zip``, with one WARNING per env id and process naming the env and the
env the default was trained on. Shipping a model for an env is dropping its zip and config JSON
in :data:`MODELS_DIR` (package data ``models/*.zip``, ``models/*.json``).

Algorithms: PPO (default of ``slam-gym train``), A2C, DQN and sb3-contrib's MaskablePPO
(``maskable-ppo``) and RecurrentPPO (``recurrent-ppo``; sb3-contrib is needed only to load such a
model). Without ``algo`` the algorithm is read from the zip's ``data`` entry: DQN saves a
``stable_baselines3.dqn`` policy class, MaskablePPO a ``sb3_contrib.common.maskable`` one,
RecurrentPPO a ``sb3_contrib.common.recurrent`` one, PPO is the actor-critic model with a
``clip_range``, A2C the one without. An explicit ``algo`` that contradicts the zip raises
``ValueError``.

Masks: a MaskablePPO model acts with the env's exact ``Discrete(4)`` mask at every decision, as
it was trained: "optimise only" is excluded when ``info["optimise_redundant"]`` says it would be
a no-op (:func:`policies.base.discrete_action_mask`), both for the mode and for sampled actions.
Without that key in ``info`` (an env of another kind) it acts unmasked.

History: a model whose config says ``frame_stack: K`` (K > 1) was trained on its last K
observations, oldest first, concatenated (Gymnasium's ``FrameStackObservation`` with its
default padding, the episode's first observation repeated, then ``FlattenObservation``); the
policy keeps the same history (:class:`ObservationHistory`), and ``reset()`` clears it. The
transform (``log1p``) applies to each observation, the normalisation to the stacked vector, as
in training.

Memory: a RecurrentPPO model carries its LSTM state from one decision to the next within an
episode (both for the mode and for sampled actions); ``reset()`` clears it, so every episode
starts from the zero state it was trained from.

Action spaces: a model trained on the env itself has ``MultiDiscrete([2, 2])`` and its action is
the (fuse, optimise) pair; a model trained through the env's ``Discrete(4)`` wrapper (DQN) acts in
``{0, 1, 2, 3}`` and is mapped by :func:`policies.base.discrete_to_multi` (``a = 2 fuse +
optimise``), the helper the wrapper itself uses.
"""

from __future__ import annotations

import hashlib
import json
import logging
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from filters.validation import require
from policies.base import (
    N_DISCRETE_ACTIONS,
    Policy,
    discrete_action_mask,
    discrete_to_multi,
)
from policies.heuristics import AGE_TOLERANCE_S

logger = logging.getLogger(__name__)

MODELS_DIR = Path(__file__).resolve().parent / "models"
"""Directory of the models shipped with the package (package data ``models/*.zip`` and
``models/*.json``): every ``*.zip`` in it is a shipped model, found by the ``env_id`` of the
config JSON beside it (:func:`model_table`)."""

DEFAULT_MODEL_NAME = "learned-default.zip"
"""File name of the default model in a models directory: the model ``learned`` falls back to."""

DEFAULT_MODEL_PATH = MODELS_DIR / DEFAULT_MODEL_NAME
"""The packaged default model: what ``policies.make("learned")`` loads without ``path`` and
``env_id``, and for an env id no shipped model is for (:func:`resolve_model_path`)."""

ALGORITHMS: tuple[str, ...] = ("ppo", "a2c", "dqn", "maskable-ppo", "recurrent-ppo")
"""Values of the ``algo`` option (case-insensitive)."""

_TRAIN_HINT = (
    "train one with `slam-gym train --algo ppo --timesteps N --out DIR` and pass "
    "path='DIR/model.zip' (or copy that file to {default})"
)


def check_env_id(env_id: Any) -> str | None:
    """``env_id`` (None, or an env id such as ``"SlamGym/HybridSLAM-Zones-v1"``; a
    ``module:`` prefix as ``gym.make`` takes it, ``slam_gym:SlamGym/...``, is dropped);
    ``ValueError`` naming ``env_id`` for anything else. Only the type is checked: which ids are
    registered is the env's to say (``slam_gym.envs.spec.check_env_id``), a floor above this
    package."""
    if env_id is None:
        return None
    require(isinstance(env_id, str) and env_id.strip() != "", "env_id", env_id,
            "an env id (a non-empty str such as 'SlamGym/HybridSLAM-v1') or None")
    return env_id.strip().rpartition(":")[2]


def _models_dir(models_dir: str | Path | None) -> Path:
    """``models_dir`` as a path, or the package's :data:`MODELS_DIR` (read at call time)."""
    if models_dir is None:
        return Path(MODELS_DIR)
    require(isinstance(models_dir, (str, Path)) and str(models_dir) != "", "models_dir",
            models_dir, "a directory path or None")
    return Path(models_dir).expanduser()


@dataclass(frozen=True)
class ShippedModel:
    """A model zip of a models directory and the env ids its config JSON records.

    ``env_id``: the env it was trained in (config ``env_id``; None: its config names none or it
    has no config); ``system_id``: the system that env runs (its ``fingerprint``'s ``env_id``,
    written by ``slam-gym train``): the same id, or for a wrapped env (one action per fusion,
    ``SlamGym/HybridSLAM-Interval-v1``) the id it wraps (``SlamGym/HybridSLAM-v1``), which the
    model acts in as well (:class:`LearnedPolicy` plans its intervals itself); ``has_config``:
    whether the config JSON is there (a zip without it names no env: no env id maps to it)."""

    path: Path
    env_id: str | None
    system_id: str | None
    has_config: bool

    @property
    def is_default(self) -> bool:
        """Whether this is its directory's default model (:data:`DEFAULT_MODEL_NAME`)."""
        return self.path.name == DEFAULT_MODEL_NAME


def shipped_models(models_dir: str | Path | None = None) -> list[ShippedModel]:
    """Every model of ``models_dir`` (None: :data:`MODELS_DIR`): each ``*.zip`` with the env ids
    of the config JSON beside it (same stem), sorted by file name; [] when the directory does
    not exist. A config that is not a JSON object is a ``ValueError`` naming it."""
    directory = _models_dir(models_dir)
    if not directory.is_dir():
        return []
    models = []
    for zip_path in sorted(directory.glob("*.zip")):
        config = read_model_config(zip_path)
        env_id = system_id = None
        if config is not None:
            env_id = config.get("env_id")
            fingerprint = config.get("fingerprint")
            system_id = fingerprint.get("env_id") if isinstance(fingerprint, dict) else None
        env_id = env_id if isinstance(env_id, str) and env_id else None
        system_id = system_id if isinstance(system_id, str) and system_id else None
        models.append(ShippedModel(zip_path, env_id, system_id, config is not None))
    return models


def model_table(models_dir: str | Path | None = None) -> dict[str, Path]:
    """Env id -> the model shipped for it in ``models_dir`` (None: :data:`MODELS_DIR`).

    A model is for the env id its config records (``env_id``) and, when its fingerprint names
    another (the system a wrapped env runs), for that id too. An id recorded as some model's own
    ``env_id`` goes to that model; an id only some models run as their system goes to the
    default model (:data:`DEFAULT_MODEL_NAME`) if it is one of them. Two models with the same
    claim on one id are a ``ValueError`` naming ``models_dir``, both files and the id: which
    one a run would load must not depend on the order of a directory listing.

    Shipping a model for an env is dropping its zip and config JSON (``"env_id": ID``, as
    ``slam-gym train`` writes it) in the directory."""
    directory = _models_dir(models_dir)
    own: dict[str, ShippedModel] = {}
    systems: dict[str, list[ShippedModel]] = {}
    for model in shipped_models(directory):
        if model.env_id is not None:
            if model.env_id in own:
                raise ValueError(
                    f"models_dir={str(directory)!r} is invalid: must hold one model per env id "
                    f"({own[model.env_id].path.name} and {model.path.name} are both for env_id "
                    f"{model.env_id!r})")
            own[model.env_id] = model
        if model.system_id is not None and model.system_id != model.env_id:
            systems.setdefault(model.system_id, []).append(model)
    table = {env_id: model.path for env_id, model in own.items()}
    for env_id, candidates in systems.items():
        if env_id in table:
            continue
        defaults = [m for m in candidates if m.is_default]
        chosen = defaults or candidates
        if len(chosen) > 1:
            raise ValueError(
                f"models_dir={str(directory)!r} is invalid: must hold one model per env id "
                f"({' and '.join(m.path.name for m in chosen)} all run {env_id!r} and none is "
                f"the default model {DEFAULT_MODEL_NAME}; record that env_id in one of them)")
        table[env_id] = chosen[0].path
    return table


_FALLBACK_WARNED: set[tuple[str, str]] = set()
"""(env id, default model) pairs whose fallback this process has warned about (once each)."""


def _warn_fallback(env_id: str, default: Path) -> None:
    """The one WARNING of this process that ``env_id`` runs the default model of another env."""
    key = (env_id, str(default))
    if key in _FALLBACK_WARNED:
        return
    _FALLBACK_WARNED.add(key)
    try:
        trained_on = (read_model_config(default) or {}).get("env_id") or "an env it does not name"
    except ValueError:
        trained_on = "an env its config does not name"
    logger.warning(
        "no learned model ships for env %s: it runs the default model %s, which was trained on "
        "another env (%s); ship one (a zip and its config JSON with \"env_id\": \"%s\" in %s) "
        "or pass the model's path", env_id, default.name, trained_on, env_id, default.parent)


def resolve_model_path(path: str | Path | None, env_id: str | None = None, *,
                       models_dir: str | Path | None = None, warn: bool = True) -> Path:
    """The model file ``learned`` loads. The rule: an explicit ``path`` wins (``.zip``
    appended if needed); else the model shipped for ``env_id`` (:func:`model_table` of
    ``models_dir``, None: :data:`MODELS_DIR`); else the directory's default model
    (:data:`DEFAULT_MODEL_NAME`), and, when ``env_id`` was given (an env with no model of its
    own), one WARNING per env id and process saying that the default model was trained on
    another env, naming both (``warn=False``: none, for a caller that has warned already, e.g. a
    worker running a job its parent made). ``FileNotFoundError`` when the file is missing;
    ``ValueError`` naming ``env_id`` or ``path`` for a bad value."""
    env_id = check_env_id(env_id)
    directory = _models_dir(models_dir)
    default = directory / DEFAULT_MODEL_NAME
    hint = _TRAIN_HINT.format(default=default)
    if path is None:
        if env_id is not None:
            shipped = model_table(directory).get(env_id)
            if shipped is not None:
                return shipped
        if not default.is_file():
            raise FileNotFoundError(
                f"no default learned model at {default} (none ships yet): {hint}"
            )
        if env_id is not None and warn:
            _warn_fallback(env_id, default)
        return default
    require(isinstance(path, (str, Path)) and str(path) != "", "path", path, "a file path")
    candidate = Path(path).expanduser()
    if not candidate.is_file() and candidate.suffix != ".zip":
        with_zip = candidate.with_name(candidate.name + ".zip")
        if with_zip.is_file():
            candidate = with_zip
    if not candidate.is_file():
        raise FileNotFoundError(f"no learned model at {candidate}: {hint}")
    return candidate


def model_digest(path: str | Path | None = None, env_id: str | None = None) -> str:
    """The first 16 hex digits of the SHA-256 of the model file ``learned`` loads for ``path``
    and ``env_id`` (:func:`resolve_model_path`; both None: the packaged default): what
    identifies a model in a benchmark's resumable job keys, so that results of a model are never
    reused for another one saved under the same name or shipped for another env."""
    resolved = resolve_model_path(path, env_id, warn=False)
    return hashlib.sha256(resolved.read_bytes()).hexdigest()[:16]


def check_model_digest(path: str | Path | None, expected: str | None,
                       env_id: str | None = None) -> None:
    """``ValueError`` naming ``model_sha256`` if ``expected`` (None: no check) is not the
    :func:`model_digest` of ``path`` for ``env_id``: the model changed since the job naming it
    was made."""
    if expected is not None:
        found = model_digest(path, env_id)
        require(found == expected, "model_sha256", expected,
                f"the digest of the model file ({found}); the model changed since the job was made")


def detect_algorithm(path: str | Path) -> str:
    """Read which algorithm saved a stable-baselines3 zip: one of :data:`ALGORITHMS`."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError) as exc:
        raise ValueError(
            f"path={str(path)!r} is invalid: must be a stable-baselines3 model zip "
            f"(with a JSON 'data' entry): {exc}"
        ) from exc
    policy_class = data.get("policy_class", {})
    module = policy_class.get("__module__", "") if isinstance(policy_class, dict) else ""
    if ".dqn." in module or "exploration_final_eps" in data:
        return "dqn"
    if ".maskable." in module:
        return "maskable-ppo"
    if ".recurrent." in module:
        return "recurrent-ppo"
    if "clip_range" in data:
        return "ppo"
    if "gae_lambda" in data:
        return "a2c"
    raise ValueError(
        f"path={str(path)!r} is invalid: must be a model saved by one of "
        f"{', '.join(ALGORITHMS)} (could not tell the algorithm from its data)"
    )


OBSERVATION_TRANSFORMS: tuple[str, ...] = ("none", "log1p")
"""Transforms of the observation a model may have been trained behind."""


class ModelProvenanceWarning(UserWarning):
    """A learned model was trained on another system than the code that loads it (or records no
    fingerprint of the system it was trained on)."""


provenance_logger = logging.getLogger("policies.provenance")
"""Where a model whose fingerprint differs from the code's is reported (WARNING)."""


def read_model_config(model_path: Path) -> dict[str, Any] | None:
    """The config JSON beside the model (None: there is none)."""
    config = model_path.with_suffix(".json")
    if not config.is_file():
        return None
    try:
        data = json.loads(config.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"config {config} is invalid: must be a JSON object ({exc})") from exc
    require(isinstance(data, dict), "config", str(config), "a JSON object")
    return data


ProvenanceCheck = Callable[[Path, "dict[str, Any] | None"], dict[str, Any]]
"""``check(model_path, config) -> {"checked": True, "matches": bool, "differences": [...]}``:
compares a model (its zip and its config JSON, None when it has none) with the system it would
act in, and warns (:class:`ModelProvenanceWarning`) when they differ."""

_PROVENANCE_CHECK: list[ProvenanceCheck] = []
"""The check :func:`set_provenance_check` installed in this process (none, or one)."""

NOT_CHECKED: Mapping[str, Any] = MappingProxyType(
    {"checked": False, "matches": None, "differences": ()})
"""``policy.provenance`` of a model whose provenance was not checked."""


def set_provenance_check(check: ProvenanceCheck | None) -> None:
    """Install ``check`` as the provenance check of every :class:`LearnedPolicy` loaded in this
    process from now on (None: remove it), a process-wide hook like :func:`policies.register`.

    The system a model was trained on is the env, a floor above this package (imports run
    filters <- policies <- slam_gym), so the env fills the hook: ``import slam_gym`` (any of its
    modules) installs :func:`slam_gym.training.provenance.check_model_provenance`."""
    if check is not None and not callable(check):
        raise ValueError(f"check={check!r} is invalid: must be a callable "
                         "check(model_path, config) or None")
    _PROVENANCE_CHECK.clear()
    if check is not None:
        _PROVENANCE_CHECK.append(check)


def check_model_provenance(path: str | Path | None = None,
                           config: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run the installed provenance check (:func:`set_provenance_check`) on the model at
    ``path``: ``{"checked": True, "matches": bool, "differences": [...]}``; a mismatch is warned
    by the check. ``config``: the model's config JSON when the caller has read it already (else
    it is read). Without an installed check (``slam_gym`` not imported) nothing is compared:
    :data:`NOT_CHECKED`, and an INFO on ``policies.provenance`` says so."""
    model_path = resolve_model_path(path)
    if not _PROVENANCE_CHECK:
        provenance_logger.info("learned model %s: provenance not checked (no check installed; "
                               "import slam_gym to install it)", model_path)
        return {**NOT_CHECKED, "differences": []}
    return _PROVENANCE_CHECK[0](model_path,
                                config if config is not None else read_model_config(model_path))


def _normalisation(stats: Any) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(mean, std, clip) of the config's ``observation_normalisation`` (VecNormalize's running
    statistics, saved by ``slam-gym train``), or None."""
    if stats is None:
        return None
    require(
        isinstance(stats, dict) and {"mean", "var", "clip", "epsilon"} <= set(stats),
        "observation_normalisation", stats,
        "a mapping with mean, var, clip and epsilon (written by slam-gym train)",
    )
    mean = np.asarray(stats["mean"], dtype=np.float64)
    var = np.asarray(stats["var"], dtype=np.float64)
    require(mean.shape == var.shape and mean.ndim == 1 and np.all(var >= 0),
            "observation_normalisation", {"mean": mean.shape, "var": var.shape},
            "1-D mean and non-negative var of the same length")
    return mean, np.sqrt(var + float(stats["epsilon"])), float(stats["clip"])


def algorithm_class(algo: str):
    """The stable-baselines3 (or sb3-contrib) class of ``algo``, one of :data:`ALGORITHMS`
    (imported here, lazily): the class a model is loaded with here and trained with by
    ``slam-gym train`` (:mod:`slam_gym.training.run`)."""
    import stable_baselines3

    if algo in ("maskable-ppo", "recurrent-ppo"):
        try:
            import sb3_contrib
        except ImportError as exc:
            raise ImportError(f"a {algo} model needs sb3-contrib: pip install "
                              "slam-gym[contrib] (or pip install sb3-contrib)") from exc
        return sb3_contrib.MaskablePPO if algo == "maskable-ppo" else sb3_contrib.RecurrentPPO
    classes = {
        "ppo": stable_baselines3.PPO,
        "a2c": stable_baselines3.A2C,
        "dqn": stable_baselines3.DQN,
    }
    return classes[algo]


def _load_model(algorithm: Any, model_path: Path, device: str) -> Any:
    """``algorithm.load`` of the zip; a file it cannot read (a damaged entry such as
    ``policy.pth``, another kind of file) is a ``ValueError`` naming the file. torch's own
    message is not repeated: for a damaged file it suggests loading with ``weights_only=False``,
    which would run arbitrary code from the file."""
    import warnings

    failure: Exception | None = None
    with warnings.catch_warnings(record=True) as caught:  # torch's warnings of a damaged file
        warnings.simplefilter("always")                    # also suggest unsafe loading
        try:
            model = algorithm.load(str(model_path), device=device)
        except ImportError:
            raise
        except Exception as exc:
            failure = exc
    if failure is not None:
        raise ValueError(
            f"model={str(model_path)!r} is invalid: stable-baselines3 cannot load it "
            f"({type(failure).__name__} while reading the saved policy; the file is damaged or "
            "is not a model saved by stable-baselines3). Replace it with an intact copy, or "
            "retrain it (slam-gym train)") from None
    for w in caught:  # the warnings of a good load are the user's to see
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return model


class ObservationHistory:
    """The last ``frame_stack`` observations, oldest first, as one flat vector: what
    ``FlattenObservation(FrameStackObservation(env, frame_stack))`` gives (the episode's first
    observation fills the history it does not have yet, Gymnasium's ``padding_type="reset"``).
    One history per episode: :meth:`reset` at its start."""

    def __init__(self, frame_stack: int) -> None:
        require(isinstance(frame_stack, int) and not isinstance(frame_stack, bool)
                and frame_stack >= 1, "frame_stack", frame_stack, "a positive integer")
        self.frame_stack = frame_stack
        self._frames: list[np.ndarray] = []

    def reset(self) -> None:
        self._frames = []

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        observation = np.asarray(observation, dtype=np.float32).reshape(-1)
        if not self._frames:
            self._frames = [observation] * self.frame_stack
        else:
            self._frames = self._frames[1:] + [observation]
        return np.concatenate(self._frames)


class LearnedPolicy(Policy):
    """A stable-baselines3 model as an interface policy: ``act(obs, info)`` reads ``obs``, or
    ``info["features"]`` when the model's config lists ``feature_names`` (below).

    A config JSON beside the zip may list ``feature_names``: the interface features the model was
    trained on, in order; the policy then builds its input from ``info["features"]`` by name, so
    a model keeps working when the env's observation gains features.

    Options: ``path`` (model zip; default: the model shipped for ``env_id``, else
    :data:`DEFAULT_MODEL_PATH`: :func:`resolve_model_path`), ``env_id`` (the env the policy acts
    in, e.g. ``"SlamGym/HybridSLAM-Zones-v1"``: it chooses the shipped model when ``path`` is not
    given; an env with no model of its own runs the default model, with one WARNING naming
    both envs), ``algo`` (one of
    :data:`ALGORITHMS`; default: detected from the zip), ``deterministic`` (True: the mode of
    the policy's action distribution / the greedy Q action; False (PPO, A2C): a draw from the
    distribution with the policy's own generator, seeded with ``sample_seed`` (default 0) at every
    ``reset()``, so an episode repeats bit for bit; default: the config JSON's ``deterministic``,
    else True), ``device`` (default
    ``"cpu"``), ``observation_transform`` (``"none"`` or ``"log1p"``, the transform the model was
    trained behind; default: the ``observation_transform`` of the config JSON that ``slam-gym
    train`` saves beside the zip with the same stem, else ``"none"``). After the transform, the
    config's ``observation_normalisation`` (the ``VecNormalize`` statistics the model was trained
    with: ``clip((x - mean) / sqrt(var + epsilon), -clip, clip)``) is applied when present. The
    model is loaded on
    construction, so a missing file or a model with the wrong spaces fails at ``policies.make``
    rather than mid-episode.

    Provenance: on loading (``check_provenance=True``, the default) the fingerprint of the
    system the model was trained on (its config's ``fingerprint``, written by ``slam-gym
    train``) is compared with the current code's for the model's env options
    (:func:`check_model_provenance`, the check ``import slam_gym`` installs); a difference, or a
    model without a fingerprint, is warned naming what differs. ``policy.provenance`` holds
    ``checked``, ``matches`` (None when not checked) and ``differences``.
    """

    name = "learned"

    def __init__(
        self,
        *,
        path: str | Path | None = None,
        env_id: str | None = None,
        algo: str | None = None,
        deterministic: bool | None = None,
        sample_seed: int = 0,
        device: str = "cpu",
        observation_transform: str | None = None,
        check_provenance: bool = True,
    ) -> None:
        super().__init__()
        require(isinstance(check_provenance, bool), "check_provenance", check_provenance,
                "True or False")
        require(
            isinstance(sample_seed, int) and not isinstance(sample_seed, bool) and sample_seed >= 0,
            "sample_seed", sample_seed, "a non-negative integer",
        )
        require(isinstance(device, str) and device != "", "device", device, "a torch device name")
        env_id = check_env_id(env_id)
        model_path = resolve_model_path(path, env_id)
        config = read_model_config(model_path) or {}  # read once: every setting below comes from it
        detected = detect_algorithm(model_path)
        if algo is None:
            algo = detected
        else:
            require(
                isinstance(algo, str) and algo.lower() in ALGORITHMS,
                "algo",
                algo,
                "one of " + ", ".join(repr(a) for a in ALGORITHMS),
            )
            algo = algo.lower()
            require(
                algo == detected,
                "algo",
                algo,
                f"{detected!r}, the algorithm that saved {model_path}",
            )
        if observation_transform is None:
            observation_transform = config.get("observation_transform", "none")
        feature_names = config.get("feature_names", None)
        require(
            feature_names is None
            or (isinstance(feature_names, list) and all(isinstance(n, str) for n in feature_names)),
            "feature_names",
            feature_names,
            "a list of interface feature names (in the model's config JSON)",
        )
        self.feature_names = None if feature_names is None else tuple(feature_names)
        require(
            observation_transform in OBSERVATION_TRANSFORMS,
            "observation_transform",
            observation_transform,
            f"one of {OBSERVATION_TRANSFORMS}",
        )
        self.observation_transform = observation_transform
        self.normalisation = _normalisation(
            config.get("observation_normalisation", None)
        )
        self.path = model_path
        self.env_id = env_id  # the env the model was resolved for (None: not given)
        self.algo = algo
        if deterministic is None:
            deterministic = config.get("deterministic", True)
        require(isinstance(deterministic, bool), "deterministic", deterministic, "True or False")
        require(deterministic or algo != "dqn", "deterministic", deterministic,
                "True for a DQN model (its only stochastic mode is epsilon-greedy exploration)")
        self.deterministic = deterministic
        self.sample_seed = sample_seed
        self._rng = np.random.default_rng(sample_seed)
        self._lstm_state = None  # RecurrentPPO memory (reset() clears it)
        self.model = _load_model(algorithm_class(algo), model_path, device)
        intervals = config.get("fusion_intervals_s")
        require(intervals is None or (isinstance(intervals, list) and len(intervals) > 0
                                      and all(isinstance(v, (int, float)) and v > 0
                                              for v in intervals)),
                "fusion_intervals_s", intervals,
                "a list of positive times (s) in the model's config JSON")
        self.fusion_intervals_s = None if intervals is None else tuple(float(v) for v in intervals)
        self._pending: tuple[float, int] | None = None  # interval model: the fusion planned
        frame_stack = config.get("frame_stack", 1)
        self.history = ObservationHistory(frame_stack)
        self._check_spaces()
        require(self.observation_shape[0] % frame_stack == 0, "frame_stack", frame_stack,
                f"a divisor of the model's observation size {self.observation_shape[0]}")
        self.frame_shape: tuple[int, ...] = (self.observation_shape[0] // frame_stack,)
        self.options = {
            "path": str(model_path),
            "env_id": env_id,
            "algo": algo,
            "deterministic": deterministic,
            "sample_seed": sample_seed,
            "device": device,
            "observation_transform": observation_transform,
        }
        if self.feature_names is not None:
            require(
                len(self.feature_names) == self.frame_shape[0],
                "feature_names",
                len(self.feature_names),
                f"{self.frame_shape[0]} names, the model's observation size "
                f"{self.observation_shape[0]} over its frame_stack {frame_stack}",
            )
        self.provenance: dict[str, Any] = (
            check_model_provenance(model_path, config or None) if check_provenance
            else {**NOT_CHECKED, "differences": []})
        logger.info("loaded %s model from %s", algo.upper(), model_path)

    def reset(self) -> None:
        self._rng = np.random.default_rng(self.sample_seed)
        self._lstm_state = None  # RecurrentPPO: zero state, as at the start of a training episode
        self._pending = None
        self.history.reset()

    @property
    def recurrent(self) -> bool:
        """Whether the model keeps a memory between decisions (RecurrentPPO)."""
        return self.algo == "recurrent-ppo"

    @property
    def maskable(self) -> bool:
        """Whether the model acts with action masks (MaskablePPO)."""
        return self.algo == "maskable-ppo"

    def action_mask(self, info: Mapping[str, Any] | None) -> np.ndarray | None:
        """The ``Discrete(4)`` mask a MaskablePPO model acts with at this decision (module
        docstring), or None (another algorithm, or no ``optimise_redundant`` in ``info``)."""
        if not self.maskable or info is None or "optimise_redundant" not in info:
            return None
        return discrete_action_mask(bool(info["optimise_redundant"]))

    def _sample(self, x: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        """A draw of (fuse, optimise) from the policy's distribution with the own generator
        (MaskablePPO: the distribution with ``mask`` applied)."""
        import torch

        with torch.no_grad():
            obs, _ = self.model.policy.obs_to_tensor(x)
            if self.maskable:
                dist = self.model.policy.get_distribution(obs, action_masks=mask)
            elif self.recurrent:
                dist = self._recurrent_distribution(obs)
            else:
                dist = self.model.policy.get_distribution(obs)
            heads = dist.distribution
        heads = heads if isinstance(heads, list) else [heads]
        draws = [self._rng.choice(len(p), p=p / p.sum())
                 for p in (h.probs[0].numpy().astype(np.float64) for h in heads)]
        if self.discrete:
            return discrete_to_multi(draws[0])
        return np.asarray(draws, dtype=np.int64).reshape(2)

    def _recurrent_distribution(self, obs):
        """RecurrentPPO's action distribution at ``obs`` from the carried LSTM state, which it
        advances (the zero state at an episode's first decision)."""
        import torch

        policy = self.model.policy
        if self._lstm_state is None:
            zeros = np.zeros(policy.lstm_hidden_state_shape, dtype=np.float32)
            self._lstm_state = (zeros, zeros)
        state = tuple(torch.as_tensor(a) for a in self._lstm_state)
        dist, new_state = policy.get_distribution(obs, state, torch.zeros(1))
        self._lstm_state = tuple(t.numpy() for t in new_state)
        return dist

    def _check_spaces(self) -> None:
        from gymnasium import spaces

        obs_space = self.model.observation_space
        require(
            isinstance(obs_space, spaces.Box) and len(obs_space.shape) == 1,
            "model observation_space",
            obs_space,
            "a 1-D Box (the env's interface-feature vector)",
        )
        act_space = self.model.action_space
        multi = isinstance(act_space, spaces.MultiDiscrete) and list(act_space.nvec) == [2, 2]
        flat = isinstance(act_space, spaces.Discrete) and int(act_space.n) == N_DISCRETE_ACTIONS
        interval = (self.fusion_intervals_s is not None
                    and isinstance(act_space, spaces.MultiDiscrete)
                    and list(act_space.nvec) == [len(self.fusion_intervals_s), 2])
        require(
            multi or flat or interval,
            "model action_space",
            act_space,
            f"MultiDiscrete([2, 2]) or Discrete({N_DISCRETE_ACTIONS}), or MultiDiscrete([n, 2]) "
            "with n the fusion_intervals_s of its config (a model of the interval env)",
        )
        self.interval = interval
        self.observation_shape: tuple[int, ...] = tuple(obs_space.shape)
        self.discrete = flat

    def act(self, obs: Any, info: Mapping[str, Any] | None = None) -> np.ndarray:
        if not self.interval:
            return self._model_action(obs, info)
        # a model of the interval env chooses, at the first decision after a fusion (or the
        # start), the time to the next fusion and whether to optimise at it; the decisions in
        # between fuse nothing, as in the env it was trained in (slam_gym.envs.interval)
        if self._pending is None:
            index, optimise = (int(v) for v in self._model_action(obs, info))
            self._pending = (self.fusion_intervals_s[index], optimise)
        require(info is not None and "local_map_age_s" in info.get("features", {}), "info", info,
                "a dict with 'features' holding local_map_age_s (an interval model reads it)")
        interval_s, optimise = self._pending
        if float(info["features"]["local_map_age_s"]) + AGE_TOLERANCE_S < interval_s:
            return np.zeros(2, dtype=np.int64)
        self._pending = None
        return np.array([1, optimise], dtype=np.int64)

    def _model_action(self, obs: Any, info: Mapping[str, Any] | None) -> np.ndarray:
        """The model's own action at ``obs`` (or at its features by name from ``info``)."""
        if self.feature_names is not None:
            # a model trained on another feature set: its features, by name, from the info
            require(
                info is not None and "features" in info,
                "info",
                None if info is None else sorted(info),
                "a dict with 'features' (the model reads its features by name)",
            )
            missing = [n for n in self.feature_names if n not in info["features"]]
            require(not missing, "info['features']", sorted(info["features"]),
                    f"to include the model's features {missing}")
            obs = [info["features"][n] for n in self.feature_names]
        x = np.asarray(obs, dtype=np.float32)
        require(
            x.shape == self.frame_shape,
            "obs shape",
            x.shape,
            f"{self.frame_shape}, the observation shape the model was trained on",
        )
        if self.observation_transform == "log1p":
            x = np.log1p(x).astype(np.float32)
        x = self.history(x)
        if self.normalisation is not None:
            mean, std, clip = self.normalisation
            x = np.clip((x - mean) / std, -clip, clip).astype(np.float32)
        mask = self.action_mask(info)
        if not self.deterministic:
            return self._sample(x, mask)
        if self.maskable:
            action, _ = self.model.predict(x, deterministic=True, action_masks=mask)
        elif self.recurrent:
            action, self._lstm_state = self.model.predict(
                x, state=self._lstm_state, episode_start=np.zeros(1, dtype=bool),
                deterministic=True)
        else:
            action, _ = self.model.predict(x, deterministic=True)
        if self.discrete:
            return discrete_to_multi(action)
        return np.asarray(action, dtype=np.int64).reshape(2)
