"""``SlamGym/HybridSLAM-v0``: the local-to-global interface of hybrid SLAM as a Gymnasium env.

A FastSLAM 2.0 front-end (or an EKF one) builds local maps while the robot drives a simulated
scenario; the agent decides, every ``decision_interval`` filter iterations, whether to **fuse**
the local map into the global map now (BB section 4) and whether to run the **nonlinear
optimisation** now (CM III.C). Never fusing is pure FastSLAM; fusing every 10 s is BB's HYBRID.

Action space
    ``MultiDiscrete([2, 2])``: (fuse now?, optimise now?). Decisions apply at the current time,
    before the next ``decision_interval`` iterations run. :class:`DiscreteActions` wraps it as
    ``Discrete(4)`` with ``a = 2 * fuse + optimise`` for DQN.

Observation space
    ``Box(0, 1e6, (17,), float32)``: the interface features of :data:`FEATURE_NAMES`, none of
    which uses ground truth (local-map age and distance, effective sample size ratio, particle
    spread, local feature counts, vote margin, innovation ratio, global features in view, global
    pose uncertainty, time and fusions since the last optimisation, clutter rate, loop-closure
    flag, local-map budget ratio). ``info["features"]`` holds the same values by name.

Reward
    ``-(w_nees * nees_excess + w_pose * pose_error_m + w_map * map_error_m + fusion_cost * fused
    + optimise_cost * optimised + failure_penalty * failed)``, where over the decision interval
    ``nees_excess`` is the mean of ``max(0, NEES / chi2_0.975(3) - 1)`` (clipped at
    ``nees_excess_clip``), ``pose_error_m`` the mean position error, and ``map_error_m`` the map
    error (CM's definition) of the confirmed global map at the end of the interval. Every term is
    in ``info["reward_components"]``; the weights are :class:`HybridSLAMConfig` fields.

Episode end
    Terminated at the end of the path, or on failure by BB's criterion (true pose more than 10
    standard deviations from the estimate for more than 20 consecutive iterations); truncated
    after ``max_decisions`` decisions.

``info`` also carries ``nees``, ``pose_error_m``, ``map_error_m``, ``failed``, ``n_fusions``,
``n_optimisations`` and ``iteration``; with ``info_compute_time=True`` also ``filter_time_s``, the
filter's wall-clock time so far. It is off by default because a wall-clock time can never repeat,
and the same seed must give the same infos (Gymnasium's checker compares them); the time is always
in ``env.unwrapped.episode.compute_time_s`` and in every evaluation result.

Seeding: ``reset(seed=s)`` seeds ``self.np_random``; the world seed (unless given in
``options["world_seed"]``) and the filter's generator are drawn from it, so the same seed gives the
same episode bit for bit in any process.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from filters.interface_features import INTERFACE_FEATURE_NAMES
from filters.validation import check_range, require
from slam_gym.episode import Episode
from slam_gym.metrics import nees_band
from slam_gym.scenarios import CLUTTER_LEVELS, get_scenario, make_stream, scenario_names

logger = logging.getLogger(__name__)

FEATURE_NAMES: tuple[str, ...] = INTERFACE_FEATURE_NAMES
"""The observation's features, in order (the sub-map system's interface features)."""

OBSERVATION_MAX = 1e6
"""Observations are clipped to [0, OBSERVATION_MAX] (NaN -> 0): every feature is non-negative."""

FRONT_ENDS = ("fastslam", "ekf")
BACK_ENDS = ("ekf", "relative")


@dataclass(frozen=True)
class HybridSLAMConfig:
    """Every option of the env, with defaults; any field is a ``gym.make`` keyword argument.

    ``scenario``/``clutter_level``/``alpha``/``beta``/``scenario_overrides``: the simulated world
    (``clutter_level=None`` with ``alpha`` and ``beta`` for a custom sensor). ``front_end``:
    ``"fastslam"`` (HYBRID) or ``"ekf"`` (EKF sub-mapping); ``back_end``: ``"ekf"`` or
    ``"relative"``; ``n_particles``: FastSLAM particles (BB: 500; 100 by default for training
    speed). ``decision_interval``: filter iterations per decision (10 = 1 s). ``max_decisions``:
    truncation (None: until the end of the path). ``n_steps``: cut the path to this many
    iterations (None: the whole path). Reward weights: see the module docstring.
    """

    scenario: str = "brooks-bailey"
    clutter_level: int | None = 2
    alpha: float | None = None
    beta: float | None = None
    scenario_overrides: tuple = ()
    front_end: str = "fastslam"
    back_end: str = "ekf"
    n_particles: int = 100
    decision_interval: int = 10
    max_decisions: int | None = None
    n_steps: int | None = None
    w_nees: float = 1.0
    w_pose: float = 0.1
    w_map: float = 0.1
    fusion_cost: float = 0.02
    optimise_cost: float = 0.5
    failure_penalty: float = 100.0
    nees_excess_clip: float = 10.0
    info_compute_time: bool = False

    def __post_init__(self):
        require(
            self.scenario in scenario_names(), "scenario", self.scenario,
            f"one of {scenario_names()}",
        )
        if self.clutter_level is not None:
            require(
                self.clutter_level in CLUTTER_LEVELS, "clutter_level", self.clutter_level,
                f"one of {sorted(CLUTTER_LEVELS)} or None",
            )
            require(
                self.alpha is None and self.beta is None, "alpha, beta", (self.alpha, self.beta),
                "None when clutter_level is given (set clutter_level=None to give them)",
            )
        else:
            require(
                self.alpha is not None and self.beta is not None, "alpha, beta",
                (self.alpha, self.beta), "numbers when clutter_level is None",
            )
        require(self.front_end in FRONT_ENDS, "front_end", self.front_end, f"one of {FRONT_ENDS}")
        require(self.back_end in BACK_ENDS, "back_end", self.back_end, f"one of {BACK_ENDS}")
        for name, low in (("n_particles", 1), ("decision_interval", 1)):
            value = getattr(self, name)
            require(
                isinstance(value, (int, np.integer)) and not isinstance(value, bool)
                and low <= value <= 100_000,
                name, value, f"an integer in [{low}, 100000]",
            )
        for name in ("max_decisions", "n_steps"):
            value = getattr(self, name)
            require(
                value is None or (
                    isinstance(value, (int, np.integer)) and not isinstance(value, bool)
                    and value >= 1
                ),
                name, value, "a positive integer or None",
            )
        for name in (
            "w_nees", "w_pose", "w_map", "fusion_cost", "optimise_cost", "failure_penalty",
        ):
            check_range(name, getattr(self, name), 0.0, 1e6)
        check_range("nees_excess_clip", self.nees_excess_clip, 0.0, 1e6, low_open=True)
        require(
            isinstance(self.info_compute_time, bool), "info_compute_time",
            self.info_compute_time, "True or False",
        )
        # the scenario itself validates alpha/beta/overrides
        self.scenario_config()

    def scenario_config(self):
        overrides = dict(self.scenario_overrides)
        if self.clutter_level is not None:
            overrides["clutter_level"] = self.clutter_level
        else:
            overrides.update(clutter_level=None, alpha=self.alpha, beta=self.beta)
        if self.n_steps is not None:
            overrides["n_steps"] = self.n_steps
        return get_scenario(self.scenario, **overrides)

    @classmethod
    def from_kwargs(cls, **kwargs) -> HybridSLAMConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(kwargs) - known)
        if unknown:
            raise ValueError(f"unknown option(s) {unknown}: must be among {sorted(known)}")
        if isinstance(kwargs.get("scenario_overrides"), dict):
            kwargs["scenario_overrides"] = tuple(sorted(kwargs["scenario_overrides"].items()))
        given_rates = kwargs.get("alpha") is not None or kwargs.get("beta") is not None
        if given_rates and "clutter_level" not in kwargs:
            kwargs["clutter_level"] = None
        return cls(**kwargs)


class HybridSLAMEnv(gym.Env):
    """See the module docstring for spaces, reward and termination."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    #: options of ``reset(options=...)``: a world seed and fields of the config that may change
    #: between episodes without changing the spaces
    RESET_OPTIONS = ("world_seed", "clutter_level", "alpha", "beta", "n_steps", "max_decisions")

    def __init__(self, render_mode: str | None = None, **config):
        require(
            render_mode is None or render_mode in self.metadata["render_modes"],
            "render_mode", render_mode, f"None or one of {self.metadata['render_modes']}",
        )
        self.config = HybridSLAMConfig.from_kwargs(**config)
        self.render_mode = render_mode
        self.action_space = spaces.MultiDiscrete([2, 2])
        self.observation_space = spaces.Box(
            low=0.0, high=OBSERVATION_MAX, shape=(len(FEATURE_NAMES),), dtype=np.float32
        )
        self.episode: Episode | None = None
        self.stream = None
        self.n_decisions = 0
        self._nees_hi = nees_band(1)[1]
        self._figure = None

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = sorted(set(options) - set(self.RESET_OPTIONS))
        if unknown:
            raise ValueError(
                f"unknown reset option(s) {unknown}: must be among {list(self.RESET_OPTIONS)}"
            )
        world_seed = options.pop("world_seed", None)
        if options:
            merged = dataclasses.asdict(self.config)
            if "clutter_level" in options:
                merged.update(alpha=None, beta=None)
            merged.update(options)
            self.config = HybridSLAMConfig.from_kwargs(**merged)
        if world_seed is None:
            world_seed = int(self.np_random.integers(0, 2**31 - 1))
        filter_seed = int(self.np_random.integers(0, 2**63 - 1))
        self.stream = self._make_stream(int(world_seed))
        from slam_gym.systems import make_system

        self.system = make_system(
            "hybrid" if self.config.front_end == "fastslam" else "ekf-submap",
            self.stream,
            np.random.default_rng(filter_seed),
            n_particles=self.config.n_particles,
            back_end=self.config.back_end,
            **self._system_options(),
        )
        self.episode = Episode(self.system, self.stream)
        self.world_seed = int(world_seed)
        self.filter_seed = filter_seed
        self.n_decisions = 0
        # run the first interval so the observation describes a local map
        self._reset_nees, _ = self._run_interval()
        features = self._features()
        info = self._info(features, self._zero_components(), nees_values=self._reset_nees)
        return self._observation(features), info

    def step(self, action):
        if self.episode is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action).reshape(-1)
        if action.shape != (2,) or not self.action_space.contains(action.astype(np.int64)):
            raise ValueError(f"action={action!r} is invalid: must be in MultiDiscrete([2, 2])")
        fuse, optimise = bool(action[0]), bool(action[1])
        failed_before = self.episode.failure.failed
        self.system.start_interval()  # the next observation's events: this decision's and after
        if fuse:
            self.episode.fuse()
        if optimise:
            self.episode.optimise()
        nees_values, errors = self._run_interval()
        self.n_decisions += 1
        ep = self.episode
        failed = ep.failure.failed
        map_error = ep.map_score().map_error_m
        c = self.config
        excess = np.clip(np.asarray(nees_values) / self._nees_hi - 1.0, 0.0, c.nees_excess_clip)
        components = {
            "nees_excess": float(np.mean(excess)) if len(excess) else 0.0,
            "pose_error_m": float(np.mean(errors)) if len(errors) else 0.0,
            "map_error_m": 0.0 if not np.isfinite(map_error) else float(map_error),
            "fused": float(fuse),
            "optimised": float(optimise),
            "failed": float(failed and not failed_before),
        }
        reward = -(
            c.w_nees * components["nees_excess"]
            + c.w_pose * components["pose_error_m"]
            + c.w_map * components["map_error_m"]
            + c.fusion_cost * components["fused"]
            + c.optimise_cost * components["optimised"]
            + c.failure_penalty * components["failed"]
        )
        terminated = bool(ep.done or failed)
        truncated = bool(
            not terminated and c.max_decisions is not None and self.n_decisions >= c.max_decisions
        )
        features = self._features()
        info = self._info(features, components, nees_values)
        if self.render_mode == "human":
            self.render()
        return self._observation(features), float(reward), terminated, truncated, info

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode to gym.make")
            return None
        from slam_gym.envs.rendering import render_frame

        frame, self._figure = render_frame(self, self._figure, self.render_mode)
        return frame

    def close(self):
        if self._figure is not None:
            import matplotlib.pyplot as plt

            plt.close(self._figure)
            self._figure = None

    # ------------------------------------------------------------------ internals
    def _make_stream(self, world_seed: int):
        """The episode's stream: the configured scenario's world ``world_seed`` (subclasses
        playing recorded data override this)."""
        return make_stream(self.config.scenario_config(), seed=world_seed)

    terminate_on_failure = True
    """End the episode at BB's failure criterion (a subclass replaying recorded data may go on)."""

    def _system_options(self) -> dict:
        """Extra keyword options of :func:`slam_gym.systems.make_system` (none here; subclasses
        playing recorded data may tune the front-end to it)."""
        return {}

    def _run_interval(self):
        """Advance one decision interval; the NEES values and position errors it produced."""
        ep = self.episode
        nees_values, errors = [], []
        for _ in range(self.config.decision_interval):
            if ep.advance(1) == 0:
                break
            nees_values.append(ep.last_nees)
            errors.append(ep.last_position_error_m)
            if ep.failure.failed and self.terminate_on_failure:
                break
        return nees_values, errors

    def _features(self) -> dict[str, float]:
        raw = self.system.interface_features()
        missing = [n for n in FEATURE_NAMES if n not in raw]
        if missing:
            raise KeyError(f"the system did not report interface features {missing}")
        return {name: float(raw[name]) for name in FEATURE_NAMES}

    def _observation(self, features) -> np.ndarray:
        obs = np.array([features[n] for n in FEATURE_NAMES], dtype=np.float64)
        obs = np.nan_to_num(obs, nan=0.0, posinf=OBSERVATION_MAX, neginf=0.0)
        return np.clip(obs, 0.0, OBSERVATION_MAX).astype(np.float32)

    @staticmethod
    def _zero_components():
        return dict.fromkeys(
            ("nees_excess", "pose_error_m", "map_error_m", "fused", "optimised", "failed"), 0.0
        )

    def _info(self, features, components, nees_values) -> dict:
        ep = self.episode
        info = {
            "features": features,
            "reward_components": components,
            "nees": float(ep.last_nees),
            "nees_interval_mean": float(np.mean(nees_values)) if len(nees_values) else ep.last_nees,
            "pose_error_m": float(ep.last_position_error_m),
            "map_error_m": float(components["map_error_m"]),
            "failed": bool(ep.failure.failed),
            "n_fusions": ep.n_fusions,
            "n_optimisations": ep.n_optimisations,
            "iteration": ep.iteration,
            "world_seed": self.world_seed,
        }
        if self.config.info_compute_time:
            info["filter_time_s"] = float(ep.compute_time_s)
        return info
