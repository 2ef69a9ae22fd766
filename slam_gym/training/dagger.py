"""The distilled planner (issue 58): DAgger from the ``lookahead`` planner, started at a rule.

A learner that runs in real time learns the planner's choices on the states it visits itself
(Ross, Gordon and Bagnell, "A reduction of imitation learning and structured prediction to
no-regret online learning", AISTATS 2011: DAgger). One run, one seed, into one folder:

* **Round 0, behaviour cloning of the task's best rule.** The rule plays training worlds
  (seeds >= :data:`~slam_gym.envs.wrappers.TRAINING_WORLD_SEED_OFFSET`) for
  ``cloning_decisions`` decisions; the actor of an SB3 ``MlpPolicy`` is fitted to its actions
  (:func:`~slam_gym.training.imitation.clone_rule`). The observation normalisation (mean and
  variance of the stacked observations) is measured on these decisions and kept for the run.
* **Rounds 1..R, DAgger.** ``episodes_per_round`` episodes on fresh training worlds, each
  decision executed from the teacher with probability ``beta ** i`` and from the previous
  round's learner otherwise (per decision, the run's own generator). **Every state is
  labelled**: by the teacher (``lookahead``, which plans only where its base rule fuses) where
  the best rule fuses, and by the best rule elsewhere (both rules wait there: the rules of this
  family fuse on the same clock, :class:`policies.heuristics.ThresholdOptimise`). The labels of
  rounds 1..i (not the rule's demonstrations, which contradict the teacher where it plans) refit
  the learner, warm-started from round i-1's weights, with early stopping on held-out episodes
  (:func:`~slam_gym.training.imitation.fit_labels`). The planner's CPU is the teacher's: each
  round records the labels it took and their planning CPU.
* **Selection** (on training-time worlds only): every round's snapshot is run by the
  benchmark's own code (policy ``learned``) on ``selection_seeds`` at the task's levels; the
  snapshot with the highest success rate (ties: mean return) is the run's ``model.zip``.

* **The cost-weighted refit** (:func:`reweigh`, ``slam-gym distil --reweigh RUN``; issue 58's
  Learner 1b): round 0's learner refitted on a finished run's DAgger labels with the planner's
  departures from its base rule weighted, so its rare waits are not outvoted; no new labels.

The learner observes what :class:`policies.learned.LearnedPolicy` gives a model: the interface
features by name (``FEATURE_NAMES``, nothing of a task's zones), ``log1p``, the last
``frame_stack`` decisions stacked (:class:`policies.learned.ObservationHistory`, what
Gymnasium's ``FrameStackObservation`` gives), then the normalisation. The learner acting in the
rounds *is* a ``LearnedPolicy`` loaded from the previous snapshot, the code users run.

Resumable: a round whose ``model.json`` exists is not run again (its labels are read back from
``labels.npz``); a whole run is deterministic given its seed.

Files::

    round_<i>/labels.npz    observations (stacked, log1p, before normalisation), labels,
                            episode index, whether the teacher planned there
    round_<i>/model.zip     the snapshot after round i (+ model.json: LearnedPolicy's config)
    round_<i>/selection/    its benchmark rows on the selection worlds
    rounds.csv              per round: episodes, decisions, planner labels and their CPU, the
                            fit, the selection's figures
    model.zip, model.json   the selected snapshot
"""

from __future__ import annotations

import json
import logging
import platform
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from filters.validation import require

logger = logging.getLogger(__name__)

ROUND_FIELDS: tuple[str, ...] = (
    "round", "beta", "episodes", "decisions", "planner_labels", "planner_deviations",
    "teacher_executed", "planning_cpu_s", "env_cpu_s", "training_failures", "fit_epochs",
    "fit_best_epoch", "validation_nll", "validation_agreement", "training_agreement",
    "selection_success_rate", "selection_mean_return", "selection_n_optimisations",
    "selection_n_fusions", "selection_interface_cpu_s", "wall_s",
)
"""Columns of ``rounds.csv``."""

DEFAULT_SELECTION_SEEDS: tuple[int, ...] = tuple(range(900000, 900010))
"""The training-time worlds the snapshots are selected on (issue 58's declaration)."""


@dataclass(frozen=True)
class DistillSetup:
    """One distillation run (module docstring); written into every snapshot's config."""

    env_id: str
    env_kwargs: dict[str, Any]
    best_rule: str
    seed: int = 0
    teacher: str = "lookahead"
    frame_stack: int = 4
    cloning_decisions: int = 20_000
    rounds: int = 4
    episodes_per_round: int = 30
    beta: float = 0.5
    max_episodes: int = 150
    max_planner_labels: int = 8_000
    selection_seeds: tuple[int, ...] = DEFAULT_SELECTION_SEEDS
    net_arch: tuple[int, ...] = (64, 64)
    selection_workers: int = 1
    command: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        import policies
        from slam_gym.envs.wrappers import TRAINING_WORLD_SEED_OFFSET
        from slam_gym.training.run import training_env

        training_env(self.env_id, self.env_kwargs)  # a simulated id and valid options
        for name in ("best_rule", "teacher"):
            try:
                policies.make(getattr(self, name))
            except ValueError as exc:
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid: {exc}") from exc
        for name in ("frame_stack", "cloning_decisions", "rounds", "episodes_per_round",
                     "max_episodes", "max_planner_labels", "selection_workers"):
            value = getattr(self, name)
            require(isinstance(value, int) and not isinstance(value, bool) and value >= 1,
                    name, value, "a positive integer")
        require(isinstance(self.seed, int) and 0 <= self.seed < 2**32, "seed", self.seed,
                "an integer in [0, 2**32)")
        require(0.0 <= self.beta <= 1.0, "beta", self.beta, "a probability in [0, 1]")
        require(bool(self.selection_seeds)
                and all(0 <= s < TRAINING_WORLD_SEED_OFFSET for s in self.selection_seeds),
                "selection_seeds", self.selection_seeds,
                f"seeds in [0, {TRAINING_WORLD_SEED_OFFSET}) (higher ones are training worlds)")
        require(bool(self.net_arch) and all(int(n) >= 1 for n in self.net_arch), "net_arch",
                self.net_arch, "positive layer widths")

    def env(self):
        """The task as a :class:`~slam_gym.envs.spec.ResolvedEnv` (the run's options)."""
        from slam_gym.training.run import training_env

        return training_env(self.env_id, self.env_kwargs)

    def selection_env(self):
        """The env the snapshots are selected in: the task with every feature observed (a
        model reads its own by name), at the task's clutter levels (an evaluation's env)."""
        from slam_gym.training.evaluation import evaluation_env

        return evaluation_env(self.env())


def _feature_names() -> tuple[str, ...]:
    from slam_gym.envs.hybrid_slam import FEATURE_NAMES

    return FEATURE_NAMES


def _observation(info, names) -> np.ndarray:
    """One decision's observation as the learner sees it before stacking: its features by
    name, ``log1p`` (:class:`policies.learned.LearnedPolicy`'s transform)."""
    return np.log1p(np.array([info["features"][n] for n in names], dtype=np.float32))


@dataclass
class Episodes:
    """Labelled decisions of some episodes (one round's, or the aggregate)."""

    observations: np.ndarray
    labels: np.ndarray
    episode: np.ndarray
    planned: np.ndarray

    @classmethod
    def concatenate(cls, parts: list[Episodes]) -> Episodes:
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("observations", "labels", "episode", "planned")))

    def save(self, path: Path) -> None:
        np.savez_compressed(path, observations=self.observations, labels=self.labels,
                            episode=self.episode, planned=self.planned)

    @classmethod
    def load(cls, path: Path) -> Episodes:
        with np.load(path) as data:
            return cls(data["observations"], data["labels"], data["episode"], data["planned"])


def play_round(setup: DistillSetup, round_index: int, *, learner=None, beta: float = 1.0,
               episodes: int | None = None, decisions: int | None = None,
               planner_label_budget: int | None = None) -> tuple[Episodes, dict[str, Any]]:
    """Play training worlds and label every decision (module docstring).

    Round 0 (``learner`` None): the best rule plays and labels, for ``decisions`` decisions.
    Round i: ``episodes`` episodes, each decision executed from the label with probability
    ``beta`` and from ``learner`` otherwise, every label the teacher's where the best rule
    fuses; no more planner labels than ``planner_label_budget`` (the round stops at the
    episode that reaches it)."""
    import policies
    from policies.learned import ObservationHistory
    from slam_gym.envs.wrappers import TRAINING_WORLD_SEED_OFFSET

    names = _feature_names()
    env = setup.env().make()
    rule = policies.make(setup.best_rule)
    teacher = policies.make(setup.teacher) if learner is not None else None
    generator = np.random.default_rng([setup.seed, round_index, 58])
    history = ObservationHistory(setup.frame_stack)
    observations, labels, episode_index, planned = [], [], [], []
    stats = {"episodes": 0, "decisions": 0, "planner_labels": 0, "planner_deviations": 0,
             "teacher_executed": 0, "planning_cpu_s": 0.0, "training_failures": 0}
    start_cpu = time.process_time()
    while True:
        if learner is None and stats["decisions"] >= decisions:
            break
        if learner is not None and (stats["episodes"] >= episodes or (
                planner_label_budget is not None
                and stats["planner_labels"] >= planner_label_budget)):
            break
        world_seed = TRAINING_WORLD_SEED_OFFSET + int(generator.integers(0, 10**9))
        obs, info = env.reset(seed=world_seed, options={"world_seed": world_seed})
        for policy in (rule, teacher, learner):
            if policy is not None:
                policy.reset()
        if teacher is not None:
            teacher.bind_env(env)
        history.reset()
        done = False
        while not done:
            observations.append(history(_observation(info, names)))
            label = np.asarray(rule.act(obs, info), dtype=np.int64)
            plans = teacher is not None and bool(label[0])
            if plans:
                before = teacher.planning_cpu_s
                taught = np.asarray(teacher.act(obs, info), dtype=np.int64)
                stats["planning_cpu_s"] += teacher.planning_cpu_s - before
                stats["planner_labels"] += 1
                stats["planner_deviations"] += int(not np.array_equal(taught, label))
                label = taught
            action = label
            if learner is not None:
                learned = np.asarray(learner.act(obs, info), dtype=np.int64)
                if generator.random() >= beta:
                    action = learned
                else:
                    stats["teacher_executed"] += 1
            labels.append(label)
            episode_index.append(stats["episodes"])
            planned.append(plans)
            obs, _, terminated, truncated, info = env.step(action)
            stats["decisions"] += 1
            done = terminated or truncated
        stats["training_failures"] += int(bool(info.get("failed", False)))
        stats["episodes"] += 1
        logger.info("round %d: episode %d done (%d decisions, %d planner labels so far)",
                    round_index, stats["episodes"], stats["decisions"], stats["planner_labels"])
    env.close()
    stats["env_cpu_s"] = time.process_time() - start_cpu - stats["planning_cpu_s"]
    data = Episodes(np.asarray(observations, dtype=np.float32), np.asarray(labels),
                    np.asarray(episode_index), np.asarray(planned, dtype=bool))
    return data, stats


def new_model(setup: DistillSetup):
    """An SB3 PPO model whose policy network is the learner (its critic unused): the class
    :class:`policies.learned.LearnedPolicy` loads, for the stacked observation."""
    import gymnasium as gym
    from gymnasium import spaces
    from stable_baselines3 import PPO

    size = setup.frame_stack * len(_feature_names())

    class SpacesOnly(gym.Env):
        """The learner's spaces (PPO needs an env to read them from; it is never stepped)."""

        observation_space = spaces.Box(-np.inf, np.inf, (size,), np.float32)
        action_space = spaces.MultiDiscrete([2, 2])

    return PPO("MlpPolicy", SpacesOnly(), seed=setup.seed, device="cpu", verbose=0,
               policy_kwargs={"net_arch": list(setup.net_arch)})


def normalisation(observations: np.ndarray, clip: float = 10.0,
                  epsilon: float = 1e-8) -> dict[str, Any]:
    """The observation normalisation of a run (``VecNormalize``'s form, which
    :class:`policies.learned.LearnedPolicy` applies): mean and variance per component."""
    return {"mean": [float(v) for v in observations.mean(axis=0)],
            "var": [float(v) for v in observations.var(axis=0)],
            "clip": clip, "epsilon": epsilon}


def normalise(observations: np.ndarray, stats: dict[str, Any]) -> np.ndarray:
    mean, var = np.asarray(stats["mean"]), np.asarray(stats["var"])
    scaled = (observations - mean) / np.sqrt(var + stats["epsilon"])
    return np.clip(scaled, -stats["clip"], stats["clip"]).astype(np.float32)


def save_snapshot(model, setup: DistillSetup, stats: dict[str, Any], path: Path,
                  round_index: int, **extra) -> Path:
    """``path`` (.zip) and the config :class:`policies.learned.LearnedPolicy` reads beside it,
    with the fingerprint of the system it was trained on."""
    from slam_gym.envs import system_env_id
    from slam_gym.training.provenance import system_fingerprint
    from slam_gym.training.run import package_versions, registered_kwargs

    path.parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    options = {**registered_kwargs(setup.env_id), **setup.env_kwargs}
    config = {
        "command": setup.command,
        "algo": "ppo",
        "learner": "dagger",
        "env_id": setup.env_id,
        "env_options": options,
        "seed": setup.seed,
        "round": round_index,
        "feature_names": list(_feature_names()),
        "frame_stack": setup.frame_stack,
        "observation_transform": "log1p",
        "observation_normalisation": stats,
        "deterministic": True,
        "training_world_seeds": ">= 1000000",
        "distillation": {k: v for k, v in asdict(setup).items() if k != "extra"},
        "versions": {"python": platform.python_version(), **package_versions()},
        "fingerprint": system_fingerprint(system_env_id(setup.env_id), options),
        **extra,
    }
    path.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
    return path


def select_snapshot(setup: DistillSetup, snapshot: Path) -> dict[str, Any]:
    """The snapshot's figures on the selection worlds (benchmark rows in ``selection/``)."""
    from slam_gym.training.evaluation import evaluate_model_file, evaluation_record

    env = setup.selection_env()
    rows = evaluate_model_file(snapshot, snapshot.parent / "selection", env=env,
                               seeds=setup.selection_seeds, workers=setup.selection_workers)
    return evaluation_record(rows, env.levels)


def read_rounds(run_dir: Path) -> list[dict[str, float]]:
    """The rows of ``rounds.csv``, oldest round first."""
    from slam_gym.training.evaluation import read_csv_rows

    return read_csv_rows(Path(run_dir) / "rounds.csv")


ROUND_EPISODE_STRIDE = 100_000
""":func:`aggregate_rounds` numbers the k-th DAgger round's episodes from ``k`` times this."""


def aggregate_rounds(parts: list[Episodes]) -> Episodes:
    """The DAgger rounds' labels ``parts`` (oldest first) as one set, the k-th round's episodes
    numbered ``episode + ROUND_EPISODE_STRIDE k`` so an episode index names one episode."""
    return Episodes.concatenate(
        [Episodes(p.observations, p.labels, p.episode + ROUND_EPISODE_STRIDE * k, p.planned)
         for k, p in enumerate(parts)])


def distil(setup: DistillSetup, run_dir: str | Path) -> dict[str, Any]:
    """Run (or resume) the distillation into ``run_dir`` (module docstring); returns the
    selected snapshot's config."""
    import torch
    from stable_baselines3 import PPO

    from policies.learned import LearnedPolicy
    from slam_gym.training.evaluation import append_csv_row
    from slam_gym.training.imitation import clone_rule, fit_labels

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(setup.seed)
    torch.set_num_threads(1)  # one core a run: two seeds run side by side
    done_rounds = {int(r["round"]) for r in read_rounds(run_dir)}
    model, stats, parts = None, None, []
    episodes_used = planner_labels = 0
    for i in range(setup.rounds + 1):
        folder = run_dir / f"round_{i}"
        snapshot = folder / "model.zip"
        if i in done_rounds and snapshot.with_suffix(".json").is_file():
            data = Episodes.load(folder / "labels.npz")
            config = json.loads(snapshot.with_suffix(".json").read_text())
            stats = config["observation_normalisation"]
            model = PPO.load(snapshot, device="cpu")
            if i > 0:
                parts.append(data)
                episodes_used += int(config["round_stats"]["episodes"])
                planner_labels += int(config["round_stats"]["planner_labels"])
            logger.warning("%s: round %d is done; resumed", run_dir, i)
            continue
        started = time.perf_counter()
        beta = setup.beta ** i
        if i == 0:
            data, round_stats = play_round(setup, 0, decisions=setup.cloning_decisions)
            stats = normalisation(data.observations)
            model = new_model(setup)
            report = clone_rule(model, normalise(data.observations, stats), data.labels,
                                seed=setup.seed)
            fit = {"fit_epochs": report["epochs"], "training_agreement": report["agreement"]}
        else:
            episodes = min(setup.episodes_per_round, setup.max_episodes - episodes_used)
            budget = setup.max_planner_labels - planner_labels
            if episodes <= 0 or budget <= 0:
                logger.warning("%s: the budget is spent (%d episodes, %d planner labels): "
                               "round %d not run", run_dir, episodes_used, planner_labels, i)
                break
            learner = LearnedPolicy(path=run_dir / f"round_{i - 1}" / "model.zip")
            data, round_stats = play_round(setup, i, learner=learner, beta=beta,
                                           episodes=episodes, planner_label_budget=budget)
            parts.append(data)
            episodes_used += round_stats["episodes"]
            planner_labels += round_stats["planner_labels"]
            aggregate = aggregate_rounds(parts)
            report = fit_labels(model, normalise(aggregate.observations, stats),
                                aggregate.labels, aggregate.episode, seed=setup.seed + i)
            fit = {"fit_epochs": report["epochs"], "fit_best_epoch": report["best_epoch"],
                   "validation_nll": report["validation_nll"],
                   "validation_agreement": report["validation_agreement"],
                   "training_agreement": report["training_agreement"]}
        folder.mkdir(parents=True, exist_ok=True)
        data.save(folder / "labels.npz")
        round_stats = {**round_stats, "beta": beta}
        save_snapshot(model, setup, stats, snapshot, i, round_stats=round_stats, fit=fit)
        selection = select_snapshot(setup, snapshot)
        record = {"round": i, **round_stats, **fit,
                  **{f"selection_{k}": v for k, v in selection.items()},
                  "wall_s": time.perf_counter() - started}
        config = json.loads(snapshot.with_suffix(".json").read_text())
        config["selection"] = selection
        snapshot.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
        append_csv_row(run_dir / "rounds.csv", list(ROUND_FIELDS), record)
        logger.warning(
            "%s round %d (beta %.3f): %d episodes, %d planner labels (%.0f s planning CPU), "
            "selection success %.3f, return %.0f", run_dir.name, i, beta,
            round_stats["episodes"], round_stats["planner_labels"],
            round_stats["planning_cpu_s"], selection["success_rate"], selection["mean_return"])
    return choose(run_dir)


TEACHER_BASE_ACTION: tuple[int, int] = (1, 1)
"""What the teacher's base rule, ``fixed-10s-optimise``, does at every point the ``lookahead``
plans (it plans where the best rule fuses, on the base rule's clock): fuse and optimise."""


def departures(data: Episodes, base_action=TEACHER_BASE_ACTION) -> np.ndarray:
    """The decisions where the teacher planned and chose other than its base rule (a wait or a
    fusion without optimisation): the rare labels that carry the planner's gain."""
    return data.planned & np.any(data.labels != np.asarray(base_action), axis=1)


def setup_of(run_dir: Path) -> DistillSetup:
    """The :class:`DistillSetup` a run was made with (from its round 0 snapshot's config)."""
    config = json.loads((Path(run_dir) / "round_0" / "model.json").read_text())
    fields = dict(config["distillation"])
    for name in ("selection_seeds", "net_arch"):
        fields[name] = tuple(fields[name])
    return DistillSetup(**fields)


def dagger_labels(run_dir: str | Path) -> tuple[list[int], Episodes]:
    """The DAgger rounds of a distillation run (every round after 0, from its ``rounds.csv``)
    and their labelled decisions, as the run aggregated them (:func:`aggregate_rounds`)."""
    run_dir = Path(run_dir)
    rounds = sorted(int(r["round"]) for r in read_rounds(run_dir) if int(r["round"]) > 0)
    require(bool(rounds), "run_dir", str(run_dir), "a run with at least one DAgger round")
    return rounds, aggregate_rounds([Episodes.load(run_dir / f"round_{i}" / "labels.npz")
                                     for i in rounds])


def reweigh(run_dir: str | Path, departure_weight: float, dest: str | Path, *,
            command: str = "") -> dict[str, Any]:
    """Learner 1b (issue 58, amendment 2): the cost-weighted distilled planner, from a finished
    distillation run and no new planner labels.

    The learner of the run's round 0 (the cloned best rule) is refitted on the run's DAgger
    labels (every round after 0) by :func:`~slam_gym.training.imitation.fit_labels` with each
    :func:`departures` decision weighted ``departure_weight`` and every other decision 1 (the
    weighted negative log-likelihood, the same held-out episodes and early stopping), so the
    planner's rare departures are not outvoted by its majority. The snapshot goes to
    ``dest/round_<R>/`` (R the run's last round, whose aggregate it fits), is selected on the
    run's selection worlds, and ``dest/rounds.csv`` holds its one row, so ``--select-from``
    compares it with any other run's snapshots; ``dest/model.zip`` is it. Resumable: a
    finished ``dest`` is returned as is."""
    import torch
    from stable_baselines3 import PPO

    import policies
    from slam_gym.training.evaluation import append_csv_row
    from slam_gym.training.imitation import fit_labels

    require(isinstance(departure_weight, (int, float)) and not isinstance(departure_weight, bool)
            and np.isfinite(departure_weight) and departure_weight > 0, "departure_weight",
            departure_weight, "a positive number")
    run_dir, dest = Path(run_dir), Path(dest)
    require((run_dir / "round_0" / "model.json").is_file(), "run_dir", str(run_dir),
            "a distillation run (with round_0/model.json)")
    setup = setup_of(run_dir)
    teacher_base = getattr(policies.make(setup.teacher), "base", None)
    require(repr(teacher_base) == repr(policies.make("fixed-10s-optimise")), "teacher",
            setup.teacher, "the lookahead on its default base rule fixed-10s-optimise (whose "
            "action where it plans defines a departure)")
    rounds, data = dagger_labels(run_dir)
    if read_rounds(dest):
        logger.warning("%s: done; resumed", dest)
        return choose(dest)
    started = time.perf_counter()
    torch.manual_seed(setup.seed)
    torch.set_num_threads(1)
    config0 = json.loads((run_dir / "round_0" / "model.json").read_text())
    stats = config0["observation_normalisation"]
    model = PPO.load(run_dir / "round_0" / "model.zip", device="cpu")
    departed = departures(data)
    weights = np.where(departed, float(departure_weight), 1.0)
    report = fit_labels(model, normalise(data.observations, stats), data.labels, data.episode,
                        seed=setup.seed + rounds[-1], weights=weights)
    fit = {"fit_epochs": report["epochs"], "fit_best_epoch": report["best_epoch"],
           "validation_nll": report["validation_nll"],
           "validation_agreement": report["validation_agreement"],
           "training_agreement": report["training_agreement"]}
    snapshot = dest / f"round_{rounds[-1]}" / "model.zip"
    provenance = {"from": str(run_dir), "rounds": rounds,
                  "departure_weight": float(departure_weight),
                  "decisions": int(len(data.labels)), "departures": int(departed.sum()),
                  "command": command}
    save_snapshot(model, setup, stats, snapshot, rounds[-1], learner="dagger-weighted",
                  reweighted=provenance, fit=fit)
    selection = select_snapshot(setup, snapshot)
    config = json.loads(snapshot.with_suffix(".json").read_text())
    config["selection"] = selection
    snapshot.with_suffix(".json").write_text(json.dumps(config, indent=2) + "\n")
    record = {"round": rounds[-1], "beta": "", "decisions": len(data.labels),
              "planner_labels": int(data.planned.sum()), "planner_deviations": "", **fit,
              **{f"selection_{k}": v for k, v in selection.items()},
              "wall_s": time.perf_counter() - started}
    append_csv_row(dest / "rounds.csv", list(ROUND_FIELDS), record)
    logger.warning("%s: %d departures of %d labels weighted %g; selection success %.3f, "
                   "return %.0f", dest.name, provenance["departures"], provenance["decisions"],
                   departure_weight, selection["success_rate"], selection["mean_return"])
    return choose(dest)


def choose(run_dir: Path) -> dict[str, Any]:
    """Copy the snapshot with the highest selection success (ties: mean return) to
    ``run_dir/model.zip``; its config."""
    return select_runs([run_dir], run_dir)


def select_runs(run_dirs: list[str | Path], dest: str | Path) -> dict[str, Any]:
    """The snapshot with the highest selection success (ties: mean return) among every round
    of ``run_dirs`` (the seeds of a learner, issue 58's selection), copied with its config to
    ``dest/model.zip``; the config, with ``selected_round`` and ``selected_from``."""
    candidates = []
    for run_dir in run_dirs:
        rounds = read_rounds(Path(run_dir))
        require(bool(rounds), "run_dir", str(run_dir), "a distillation run with rounds.csv")
        candidates += [(r["selection_success_rate"], r["selection_mean_return"], str(run_dir),
                        int(r["round"])) for r in rounds]
    # the first of equals (the earlier seed, then the earlier round): fewer labels, same figures
    _, _, run_dir, round_index = max(candidates, key=lambda c: (c[0], c[1]))
    source = Path(run_dir) / f"round_{round_index}" / "model.zip"
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source, dest / "model.zip")
    config = json.loads(source.with_suffix(".json").read_text())
    config["selected_round"] = round_index
    config["selected_from"] = str(run_dir)
    config["candidates"] = [{"run": c[2], "round": c[3], "selection_success_rate": c[0],
                             "selection_mean_return": c[1]} for c in candidates]
    (dest / "model.json").write_text(json.dumps(config, indent=2) + "\n")
    return config
