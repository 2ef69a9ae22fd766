"""``SlamGym/HybridSLAM-v1``: the local-to-global interface of hybrid SLAM as a Gymnasium env.

A FastSLAM 2.0 front-end (or an EKF one) builds local maps while the robot drives a simulated
scenario; the agent decides, every ``decision_interval`` filter iterations, whether to **fuse**
the local map into the global map now (BB section 4) and whether to run the **nonlinear
optimisation** now (CM III.C). Never fusing is pure FastSLAM; fusing every 10 s is BB's HYBRID.

Action space
    ``MultiDiscrete([2, 2])``: (fuse now?, optimise now?). Decisions apply at the current time,
    before the next ``decision_interval`` iterations run. :class:`DiscreteActions` wraps it as
    ``Discrete(4)`` with ``a = 2 * fuse + optimise`` for DQN and MaskablePPO. An optimisation
    with nothing fused since the last one (or before any fusion) is *redundant*: the optimum is
    the one already applied, so it changes nothing (not even the time since the last
    optimisation), is not counted in ``n_optimisations`` and costs nothing in ``compute_s``.

Action masks (sb3-contrib's ``MaskablePPO``; issue 29 item 2)
    ``env.optimisation_is_redundant()`` says, before a decision, whether optimising without
    fusing would be that no-op (the optimiser's own test, so it is exact); it is also
    ``info["optimise_redundant"]``. ``action_masks()`` (and ``info["action_mask"]``) is the mask
    of the env's own space in ``MaskablePPO``'s layout, one flag per value of each dimension:
    ``[fuse=0, fuse=1, optimise=0, optimise=1]``. That layout masks each dimension on its own,
    and "optimise" is a no-op only *without* a fusion (fuse-then-optimise always optimises the
    sub-map just fused), so the exact factorised mask is all True. The mask that bites is
    :class:`~slam_gym.envs.wrappers.DiscreteActions`' over ``Discrete(4)``: ``a = 1`` (optimise
    only) is masked exactly when it would be redundant; fusing is never a no-op (it always
    stores a sub-map and restarts the local map), so nothing else is ever masked.

Observation space
    ``Box(0, 1e6, (F,), float32)``: the interface features named by the ``features`` option
    (default all ``F = 19`` of :data:`FEATURE_NAMES`), none of which uses ground truth:
    local-map age and distance, effective sample size ratio, particle spread, local feature
    counts, vote margin, innovation ratio (the largest CM ratio ``||nu|| / (2 sigma)`` of the
    interval, metres), global features in view, global pose uncertainty, time and fusions since
    the last optimisation, clutter rate, loop-closure flag (the back-end's CM Definition 1 test
    found a closure in a fusion of the interval), local-map budget ratio, loop closures since the
    last optimisation and stored sub-maps. ``info["features"]`` holds all of them by name, and
    the env's own ``compute_price_per_s`` (= ``w_compute``), which ``features`` may also select:
    a policy conditioned on the price of compute observes it (``w_compute`` and
    ``compute_clip_s`` may change per episode through ``reset(options=...)``).

Reward (per decision; every term is in ``info["reward_components"]``)
    ``-(w_nees (nees_over + nees_under) + w_pose pose_error_m + w_map map_ospa_m
    + w_compute compute_s + failure_charge)``, where over the decision interval

    * ``nees_over`` / ``nees_under``: the mean over its iterations of
      ``max(0, NEES / chi2_0.975(3) - 1)`` (over-confidence) and of
      ``max(0, chi2_0.025(3) / NEES - 1)`` (under-confidence), each clipped at
      ``nees_excess_clip``: zero inside the 95 % band, growing either side of it;
    * ``pose_error_m``: the mean position error, clipped at ``pose_error_clip_m``;
    * ``map_ospa_m``: the OSPA distance (order 1, cut-off ``map_cutoff_m``) between the confirmed
      map and the landmarks detected so far: each missed landmark and each spurious or duplicate
      feature costs the cut-off, so an empty map costs the most, not nothing
      (:meth:`slam_gym.metrics.MapScore.ospa_m`);
    * ``compute_s``: the *modelled* CPU seconds of the interval's filtering and of this
      decision's fusion and (non-redundant) optimisation (:mod:`slam_gym.compute_cost`: an
      operation count calibrated against measured CPU time), clipped at ``compute_clip_s``;
      deterministic, so the same seed gives the same reward;
    * ``failure_charge``: 0, or at the decision where BB's failure criterion fires (and ends the
      episode) ``failure_penalty`` plus the worst case of the remaining path,
      ``remaining decisions x (w_nees nees_excess_clip + w_pose pose_error_clip_m + w_map
      map_cutoff_m + w_compute compute_clip_s)``. Every per-decision cost is bounded by that
      bracket, so no continuation of an episode can cost more than failing now: ending early
      never pays.

    Defaults and why: ``w_nees = 1`` per decision (a filter 10x over-confident for the whole
    interval costs 9), ``w_pose = 0.1 /m`` (pose error is also in the NEES; this only breaks
    ties), ``w_map = 1 /m`` (a metre of map error per decision weighs as much as a NEES at twice
    the band), ``w_compute = 1 /s`` (an optimisation of 0.1-0.4 s costs as much as 0.1-0.4 m of
    map error for one decision: worth it when it repairs the map for the rest of the path),
    ``failure_penalty = 100``, cut-offs ``nees_excess_clip = 10``, ``pose_error_clip_m = 20``,
    ``map_cutoff_m = 5`` (a quarter of the landmark spacing of BB's world: a feature further
    than that from its landmark is as useless as none), ``compute_clip_s = 2``.

Episode end
    Terminated at the end of the path, or on failure by BB's criterion (true pose more than 10
    standard deviations from the estimate for more than 20 consecutive iterations); truncated
    after ``max_decisions`` decisions. The registered ids also set ``max_episode_steps`` (1.5
    times the decisions of the scenario's nominal path at the default ``decision_interval``), so
    a ``gym.make`` with a shorter ``decision_interval`` should pass its own ``max_episode_steps``.
    After the episode ended (``terminated`` or ``truncated`` returned True), ``step()`` raises
    ``gymnasium.error.ResetNeeded`` until ``reset()``, like Gymnasium's order-enforcing wrapper
    before the first reset: a step past the end would fuse, optimise and charge reward on a
    finished episode and change its metrics and return. (SB3's vector envs reset on either flag.)

Rendering
    ``"rgb_array"`` returns the frame (truth, global and local map, particles); ``"human"`` draws
    it in a matplotlib window (an interactive backend is needed; on a headless machine it warns
    once and draws nothing) and returns None. ``metadata["render_fps"]`` is one frame per
    decision played in real time: ``1 / (decision_interval x the filter period)`` (1 fps at the
    defaults: one decision is 1 s of simulated time).

Which id to use
    ``SlamGym/HybridSLAM-v1`` is the paper's configuration (BB: 500 particles): the one to report.
    ``SlamGym/HybridSLAM-Light-v1`` runs 100 particles for quick training and smoke tests; at 100
    particles FastSLAM's local maps become over-confident within 10 s, so the task there mostly
    rewards fusing often.

``info`` also carries ``nees``, ``pose_error_m``, ``map_error_m`` (CM's map error of the matched
features; None while no feature stands for a landmark), ``map_completeness`` (None while no
landmark was detected), ``failed``, ``n_fusions``, ``n_optimisations``,
``iteration``, ``optimise_redundant`` and ``action_mask`` (above).
``env.episode_compute_term_s`` is the seconds of compute the episode's return charged so far:
the return at another ``w_compute`` (same ``compute_clip_s``) is
``episode_return + (w_compute - w') x episode_compute_term_s``, which is how a rule's return is
scored at several prices from one run. With ``info_compute_time=True`` also ``filter_time_s``,
the filter's wall-clock time so far. It is off by default because a wall-clock time can never
repeat, and the same seed must give the same infos (Gymnasium's checker compares them); the
time is always in ``env.unwrapped.episode.compute_time_s`` and in every evaluation result.

Seeding: ``reset(seed=s)`` seeds ``self.np_random``; the world seed (unless given in
``options["world_seed"]``) is drawn from it, so the same seed gives the same episode bit for bit
in any process. The world's path, landmarks, clutter and measurement noise come from the world
seed alone. The filter's random numbers (the DAS uniforms, the pose draws, the resampling
offsets) come from ``random_streams``:

* ``"synchronised"`` (``-v1``, the default): keyed by ``(world seed, draw, iteration,
  purpose)`` (:class:`filters.draws.SynchronisedDraws`). ``options["draw"]`` (default 0) chooses
  another draw of the filter's numbers on the same world. Two policies on the same world and
  draw receive the same numbers for the same purpose at every iteration, whatever either decided
  before: common random numbers, so a paired comparison sees the decisions' effect, not the
  filter's noise falling differently after the first decision that differs.
* ``"ordered"`` (``-v0``): one generator seeded from ``np_random`` (draw 0) or from the world
  and ``options["draw"]``, consumed in order of use: a different decision shifts every later
  draw.

Version History
    The id's version moves with every change to the reward, the observation or the dynamics
    (Gymnasium's convention); every id is registered at both versions, ``-v0`` being the same
    env with ``random_streams="ordered"``. A model's provenance fingerprint
    (:mod:`slam_gym.training.provenance`, issue 29) tells which a saved model was trained on.

    * v1, issue 46 (2026-11-28): synchronised random numbers (above, "Seeding"). The reward,
      the observation and the filters' equations are unchanged; every episode's filter draws
      differ from ``-v0``'s, so its bits do. ``-v0`` stays reachable (``random_streams=
      "ordered"``: the old draws; equal in distribution, not bits, since issue 47) for the rows
      and models made with it.

    * v0 (2026-11-21, aa8eb86): the first release. Reward ``-(w_nees nees_excess + w_pose
      pose_error_m + w_map map_error_m + fusion_cost fused + optimise_cost optimised +
      failure_penalty failed)``; observation: the sub-map system's interface features.
    * v0, issue 13 (2026-11-24, 85d2828 and ef8a992): the loop-closure features reach the
      observation; the reward stated under "Reward" replaces the first one: a failure charged
      the worst case of the remaining path, an OSPA map term, a two-sided NEES term, a
      deterministic compute term (:mod:`slam_gym.compute_cost`); 500 particles by default.
    * v0, issue 27 (2026-11-25, 725f6ef; 2026-11-26, ae61ce6): the compute model's costs
      refitted twice, so the compute term of the same decisions changed.
    * v0, issue 29 (2026-11-25, 9331d23 and e86c661): the price of compute per episode (reset
      option ``w_compute``, feature ``compute_price_per_s``) and the action masks
      (``info["optimise_redundant"]``, ``action_masks()``).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from filters.blas import check_blas_threads, limited_blas_threads
from filters.draws import SynchronisedDraws
from filters.interface_features import INTERFACE_FEATURE_NAMES
from filters.validation import check_range, require
from policies.base import check_action
from slam_gym.compute_cost import ComputeModel, filter_ops, fusion_ops, optimise_ops
from slam_gym.episode import Episode
from slam_gym.metrics import nees_band
from slam_gym.scenarios import CLUTTER_LEVELS, get_scenario, scenario_names
from slam_gym.world import make_stream

logger = logging.getLogger(__name__)

FEATURE_NAMES: tuple[str, ...] = INTERFACE_FEATURE_NAMES
"""The observation's default features, in order (the sub-map system's interface features)."""

ENV_FEATURE_NAMES: tuple[str, ...] = ("compute_price_per_s",)
"""Features of the env rather than of the filter, selectable with the ``features`` option and
always in ``info["features"]`` (after :data:`FEATURE_NAMES`): ``compute_price_per_s`` is the
reward's ``w_compute``, for a policy conditioned on the price of compute (issue 29)."""

SELECTABLE_FEATURES: tuple[str, ...] = FEATURE_NAMES + ENV_FEATURE_NAMES
"""Every name the ``features`` option accepts."""

OBSERVATION_MAX = 1e6
"""Observations are clipped to [0, OBSERVATION_MAX] (NaN -> 0): every feature is non-negative."""
WORLD_SEED_LIMIT = 2**63
"""World seeds are integers in [0, WORLD_SEED_LIMIT) (``reset(options={"world_seed": s})``)."""

FRONT_ENDS = ("fastslam", "ekf")
RANDOM_STREAMS = ("synchronised", "ordered")
"""The filter's random numbers: keyed by purpose and time (``-v1``) or one ordered stream
(``-v0``); :mod:`filters.draws`."""
BACK_ENDS = ("ekf", "relative")

REWARD_COMPONENTS: tuple[str, ...] = (
    "nees_over", "nees_under", "pose_error_m", "map_ospa_m", "compute_s", "failure_charge",
)
"""The terms of the reward, in ``info["reward_components"]`` (module docstring)."""


def ordered_filter_seed(np_random: np.random.Generator, world_seed: int, draw: int) -> int:
    """The seed of the ``-v0`` filter generator: draw 0 takes the next number of the env's
    ``np_random`` (as ``-v0`` always did); draw ``k > 0`` one derived from the world and ``k``,
    the generator that ``reset(seed=<derived>)`` on that world gave before draws were an option,
    so earlier rows of other draws are reproduced."""
    if draw == 0:
        return int(np_random.integers(0, 2**63 - 1))
    derived = np.random.SeedSequence([int(world_seed), int(draw), 104729]).generate_state(1)[0]
    return int(np.random.default_rng(int(derived)).integers(0, 2**63 - 1))


@dataclass(frozen=True)
class HybridSLAMConfig:
    """Every option of the env, with defaults; any field is a ``gym.make`` keyword argument.

    ``scenario``/``clutter_level``/``alpha``/``beta``/``scenario_overrides``: the simulated world
    (``clutter_level=None`` with ``alpha`` and ``beta`` for a custom sensor; a tuple of levels
    draws one per episode from the env's generator, after the world seed, unless ``reset``
    names one: the tasks of :mod:`slam_gym.envs.tasks`). ``front_end``:
    ``"fastslam"`` (HYBRID) or ``"ekf"`` (EKF sub-mapping); ``back_end``: ``"ekf"`` or
    ``"relative"``; ``n_particles``: FastSLAM particles (BB: 500, the default).
    ``decision_interval``: filter iterations per decision (10 = 1 s). ``max_decisions``:
    truncation (None: until the end of the path). ``n_steps``: cut the path to this many
    iterations (None: the whole path). ``features``: the observation's interface features, in
    order (None: all of :data:`FEATURE_NAMES`). Reward weights and cut-offs: see the module
    docstring. ``blas_threads``: the BLAS threads of the env's linear algebra (default 1, set
    for each ``reset``/``step`` and restored after it; None: the process's own setting;
    :mod:`filters.blas`). ``random_streams``: where the filter's random numbers come from
    (module docstring, "Seeding"): ``"synchronised"`` (keyed by world, draw, iteration and
    purpose; the ``-v1`` ids) or ``"ordered"`` (one stream in order of use; the ``-v0`` ids).
    """

    scenario: str = "brooks-bailey"
    clutter_level: int | tuple | None = 2
    alpha: float | None = None
    beta: float | None = None
    scenario_overrides: tuple = ()
    front_end: str = "fastslam"
    back_end: str = "ekf"
    n_particles: int = 500
    decision_interval: int = 10
    max_decisions: int | None = None
    n_steps: int | None = None
    features: tuple | None = None
    w_nees: float = 1.0
    w_pose: float = 0.1
    w_map: float = 1.0
    w_compute: float = 1.0
    failure_penalty: float = 100.0
    nees_excess_clip: float = 10.0
    pose_error_clip_m: float = 20.0
    map_cutoff_m: float = 5.0
    compute_clip_s: float = 2.0
    info_compute_time: bool = False
    blas_threads: int | None = 1
    random_streams: str = "synchronised"

    def __post_init__(self):
        require(
            self.scenario in scenario_names(), "scenario", self.scenario,
            f"one of {scenario_names()}",
        )
        if self.clutter_level is not None:
            levels = self.episode_levels or (self.clutter_level,)
            require(
                len(levels) > 0 and len(set(levels)) == len(levels)
                and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool)
                        and v in CLUTTER_LEVELS for v in levels),
                "clutter_level", self.clutter_level,
                f"one of {sorted(CLUTTER_LEVELS)}, a tuple of distinct levels (one drawn per "
                "episode), or None",
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
        require(self.random_streams in RANDOM_STREAMS, "random_streams", self.random_streams,
                f"one of {RANDOM_STREAMS}")
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
        for name in ("w_nees", "w_pose", "w_map", "w_compute", "failure_penalty"):
            check_range(name, getattr(self, name), 0.0, 1e6)
        for name in ("nees_excess_clip", "pose_error_clip_m", "map_cutoff_m", "compute_clip_s"):
            check_range(name, getattr(self, name), 0.0, 1e6, low_open=True)
        if self.features is not None:
            names = tuple(self.features)
            unknown = [n for n in names if n not in SELECTABLE_FEATURES]
            require(
                len(names) > 0 and not unknown and len(set(names)) == len(names),
                "features", self.features,
                f"None or distinct names among {list(SELECTABLE_FEATURES)}"
                + (f" (unknown: {unknown})" if unknown else ""),
            )
        require(
            isinstance(self.info_compute_time, bool), "info_compute_time",
            self.info_compute_time, "True or False",
        )
        check_blas_threads(self.blas_threads)
        # the scenario itself validates alpha/beta/overrides
        self.scenario_config()

    @property
    def episode_levels(self) -> tuple[int, ...] | None:
        """The clutter levels an episode's level is drawn from (``clutter_level`` a tuple: the
        tasks of :mod:`slam_gym.envs.tasks`), or None when the level is fixed."""
        return tuple(self.clutter_level) if isinstance(self.clutter_level, tuple) else None

    def as_kwargs(self) -> dict:
        """Every field as a ``gym.make`` keyword argument in plain JSON types (tuples as lists):
        :meth:`from_kwargs` of it is this config again."""
        def plain(value):
            return [plain(v) for v in value] if isinstance(value, (tuple, list)) else value

        return {f.name: plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @property
    def observation_features(self) -> tuple[str, ...]:
        return FEATURE_NAMES if self.features is None else tuple(self.features)

    @property
    def max_decision_cost(self) -> float:
        """The largest cost one decision can have without failing (module docstring)."""
        return (
            self.w_nees * self.nees_excess_clip + self.w_pose * self.pose_error_clip_m
            + self.w_map * self.map_cutoff_m + self.w_compute * self.compute_clip_s
        )

    def reward_weights(self) -> dict[str, float]:
        """Component -> weight: ``reward = -sum(weight * component)``."""
        return {
            "nees_over": self.w_nees, "nees_under": self.w_nees, "pose_error_m": self.w_pose,
            "map_ospa_m": self.w_map, "compute_s": self.w_compute, "failure_charge": 1.0,
        }

    def scenario_config(self):
        overrides = dict(self.scenario_overrides)
        if self.episode_levels is not None:  # the path and rates do not depend on the level
            overrides["clutter_level"] = self.episode_levels[0]
        elif self.clutter_level is not None:
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
        elif isinstance(kwargs.get("scenario_overrides"), list):  # as_kwargs' JSON form
            kwargs["scenario_overrides"] = tuple(
                tuple(pair) if isinstance(pair, list) else pair
                for pair in kwargs["scenario_overrides"])
        if isinstance(kwargs.get("features"), (list, tuple)):
            kwargs["features"] = tuple(kwargs["features"])
        if isinstance(kwargs.get("clutter_level"), list):
            kwargs["clutter_level"] = tuple(kwargs["clutter_level"])
        given_rates = kwargs.get("alpha") is not None or kwargs.get("beta") is not None
        if given_rates and "clutter_level" not in kwargs:
            kwargs["clutter_level"] = None
        return cls(**kwargs)


class HybridSLAMEnv(gym.Env):
    """See the module docstring for spaces, reward and termination."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 1.0}

    #: the defaults of this class's options over :class:`HybridSLAMConfig`'s (a task's world:
    #: :mod:`slam_gym.envs.tasks`); the registration of a class's id reads them
    DEFAULTS: dict = {}

    #: options of ``reset(options=...)``: a world seed and fields of the config that may change
    #: between episodes without changing the spaces
    RESET_OPTIONS = ("world_seed", "draw", "clutter_level", "alpha", "beta", "n_steps",
                     "max_decisions", "w_compute", "compute_clip_s")

    def __init__(self, render_mode: str | None = None, **config):
        require(
            render_mode is None or render_mode in self.metadata["render_modes"],
            "render_mode", render_mode, f"None or one of {self.metadata['render_modes']}",
        )
        self.config = HybridSLAMConfig.from_kwargs(**(type(self).DEFAULTS | config))
        #: the clutter levels an episode's level is drawn from when reset names none (None: the
        #: configured level; :attr:`HybridSLAMConfig.episode_levels`)
        self.episode_levels = self.config.episode_levels
        self.render_mode = render_mode
        period_s = 1.0 / self.config.scenario_config().filter_rate_hz
        self.metadata = {
            **self.metadata, "render_fps": 1.0 / (self.config.decision_interval * period_s)
        }
        self.action_space = spaces.MultiDiscrete([2, 2])
        self.observation_space = spaces.Box(
            low=0.0, high=OBSERVATION_MAX, shape=(len(self.config.observation_features),),
            dtype=np.float32,
        )
        self.compute_model = ComputeModel()
        self.compute_records: list[tuple[str, float, float]] = []
        self.episode: Episode | None = None
        self.episode_return = 0.0
        self.episode_compute_term_s = 0.0
        self.stream = None
        self.n_decisions = 0
        self.filter_rng: np.random.Generator | None = None
        self.filter_draws: SynchronisedDraws | None = None
        self.episode_ended: str | None = None
        """``"terminated"`` or ``"truncated"`` once the episode ended (then :meth:`step`
        raises), None while it runs."""
        self._nees_band = nees_band(1)
        self._figure = None
        self._warned_headless = False

    @classmethod
    def resolved_kwargs(cls, **kwargs) -> dict:
        """Every option of an env of this class made with ``kwargs`` (the class's
        :attr:`DEFAULTS` under them, then :class:`HybridSLAMConfig`'s), as plain JSON
        (``ValueError`` naming an invalid option): ``cls(**resolved)`` is the same env."""
        return HybridSLAMConfig.from_kwargs(**(cls.DEFAULTS | kwargs)).as_kwargs()

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        with limited_blas_threads(self.config.blas_threads):
            return self._reset(seed, options)

    def step(self, action):
        with limited_blas_threads(self.config.blas_threads):
            return self._step(action)

    def _reset(self, seed, options):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = sorted(set(options) - set(self.RESET_OPTIONS))
        if unknown:
            raise ValueError(
                f"unknown reset option(s) {unknown}: must be among {list(self.RESET_OPTIONS)}"
            )
        world_seed = options.pop("world_seed", None)
        require(world_seed is None or (isinstance(world_seed, (int, np.integer))
                                       and not isinstance(world_seed, bool)
                                       and 0 <= world_seed < WORLD_SEED_LIMIT),
                "world_seed", world_seed, "None or an integer in [0, 2**63)")
        draw = options.pop("draw", 0)
        require(isinstance(draw, (int, np.integer)) and not isinstance(draw, bool)
                and 0 <= draw < 2**31, "draw", draw, "an integer in [0, 2**31)")
        if world_seed is None:
            world_seed = int(self.np_random.integers(0, 2**31 - 1))
        if self.episode_levels is not None and "clutter_level" not in options \
                and "alpha" not in options and "beta" not in options:
            # a task's episode draws its level (after its world seed) from the env's generator
            options["clutter_level"] = int(
                self.episode_levels[self.np_random.integers(len(self.episode_levels))])
        if options:
            merged = dataclasses.asdict(self.config)
            if "clutter_level" in options:
                merged.update(alpha=None, beta=None)
            merged.update(options)
            self.config = HybridSLAMConfig.from_kwargs(**merged)
        self.stream = self._make_stream(int(world_seed))
        from slam_gym.systems import make_system

        if self.config.random_streams == "synchronised":
            #: the filters' random numbers, keyed by world, draw, iteration and purpose
            self.filter_draws = SynchronisedDraws((int(world_seed), int(draw)))
            self.filter_rng, self.filter_seed = None, None
            source = self.filter_draws
        else:
            #: the one generator every draw of the filters comes from, in order of use
            self.filter_seed = ordered_filter_seed(self.np_random, int(world_seed), int(draw))
            self.filter_rng = np.random.default_rng(self.filter_seed)
            self.filter_draws = None
            source = self.filter_rng
        self.system = make_system(
            "hybrid" if self.config.front_end == "fastslam" else "ekf-submap",
            self.stream,
            source,
            n_particles=self.config.n_particles,
            back_end=self.config.back_end,
            back_blas_threads=self.config.blas_threads,
            **self._system_options(),
        )
        self.episode = Episode(self.system, self.stream, draws=self.filter_draws)
        self.world_seed = int(world_seed)
        self.draw = int(draw)
        self.n_decisions = 0
        self.episode_return = 0.0
        self.episode_compute_term_s = 0.0
        self.compute_records = []
        self.episode_ended = None
        # run the first interval so the observation describes a local map
        self._reset_nees, _ = self._run_interval()
        features = self._features()
        info = self._info(features, dict.fromkeys(REWARD_COMPONENTS, 0.0), self._reset_nees)
        return self._observation(features), info

    def _step(self, action):
        if self.episode is None:
            raise RuntimeError("call reset() before step()")
        if self.episode_ended is not None:
            raise gym.error.ResetNeeded(
                f"step() after the episode ended ({self.episode_ended}=True at decision "
                f"{self.n_decisions}): call reset() to start a new one (module docstring, "
                "Episode end)")
        action = check_action(action)  # ValueError naming the action
        fuse, optimise = bool(action[0]), bool(action[1])
        ep, c = self.episode, self.config
        failed_before = ep.failure.failed
        self.system.start_interval()  # the next observation's events: this decision's and after
        modelled_s = 0.0
        # the CPU clock is read at the decision's start and once after each component: each
        # reading ends one component's record and starts the next's
        cpu_s = time.process_time()
        if fuse:
            report = ep.fuse()
            cpu_s, seconds = self._record(fusion_ops(self.system, report), cpu_s)
            modelled_s += seconds
        if optimise:
            result = ep.optimise()
            if not result.redundant:  # nothing fused since the optimum applied: free (#27)
                cpu_s, seconds = self._record(optimise_ops(self.system, result), cpu_s)
                modelled_s += seconds
            else:
                cpu_s = time.process_time()
        nees_values, errors = self._run_interval()
        features = self._features()
        kind, ops = filter_ops(c.front_end, c.n_particles, features["local_feature_count"])
        modelled_s += self._record((kind, ops * len(nees_values)), cpu_s)[1]
        self.n_decisions += 1
        failed = ep.failure.failed
        score = ep.map_score()
        nees = np.asarray(nees_values, dtype=float)
        lo, hi = self._nees_band
        with np.errstate(divide="ignore"):
            over = np.clip(nees / hi - 1.0, 0.0, c.nees_excess_clip)
            under = np.clip(lo / nees - 1.0, 0.0, c.nees_excess_clip)
        new_failure = failed and not failed_before
        ends_here = new_failure and self.terminate_on_failure
        components = {
            "nees_over": float(np.mean(over)) if len(over) else 0.0,
            "nees_under": float(np.mean(under)) if len(under) else 0.0,
            "pose_error_m": float(np.mean(np.minimum(errors, c.pose_error_clip_m)))
            if len(errors) else 0.0,
            "map_ospa_m": score.ospa_m(c.map_cutoff_m),
            "compute_s": min(modelled_s, c.compute_clip_s),
            "failure_charge": (
                c.failure_penalty
                + (self._remaining_decisions() * c.max_decision_cost if ends_here else 0.0)
            ) if new_failure else 0.0,
        }
        reward = -sum(w * components[k] for k, w in c.reward_weights().items())
        self.episode_return += reward
        # what the return charges at w_compute per second: the decision's clipped compute and,
        # at a failure that ends the episode, the clip for every remaining decision
        self.episode_compute_term_s += components["compute_s"] + (
            self._remaining_decisions() * c.compute_clip_s if ends_here else 0.0)
        terminated = bool(ep.done or (failed and self.terminate_on_failure))
        truncated = bool(
            not terminated and c.max_decisions is not None and self.n_decisions >= c.max_decisions
        )
        if terminated or truncated:
            self.episode_ended = "terminated" if terminated else "truncated"
        info = self._info(features, components, nees_values, score)
        if self.render_mode == "human":
            self.render()
        return self._observation(features), float(reward), terminated, truncated, info

    def optimisation_is_redundant(self) -> bool:
        """Whether optimising now without fusing would be a redundant no-op (nothing fused since
        the optimum applied last, or nothing fused yet): no change of state, no count, no charge
        (module docstring). False before :meth:`reset`."""
        return self.episode is not None and self.system.optimisation_is_redundant()

    def action_masks(self) -> np.ndarray:
        """The valid actions in ``MaskablePPO``'s layout for ``MultiDiscrete([2, 2])``:
        ``[fuse=0, fuse=1, optimise=0, optimise=1]``, all True (module docstring: a factorised
        mask cannot forbid "optimise" without forbidding "fuse and optimise", which is never a
        no-op; :class:`~slam_gym.envs.wrappers.DiscreteActions` masks exactly)."""
        return np.ones(4, dtype=bool)

    # ------------------------------------------------------------------ copies (issue 39)
    def clone(self) -> HybridSLAMEnv:
        """An independent copy of this env, mid-episode, that continues exactly as this one
        would: the same actions give the same observations, rewards and infos, bit for bit.

        Only the mutable state is copied (the filters, the episode's counters and traces, the
        generators); the world, which nothing changes, is shared read-only. That makes a copy
        cost a few milliseconds where ``copy.deepcopy`` of the env costs about a hundred times
        more (docs/PERFORMANCE.md). A copy renders nothing: its ``render_mode`` is None.
        """
        if self.episode is None:
            raise RuntimeError("call reset() before clone()")
        stream = self.stream
        memo = {id(stream): stream}
        steps = getattr(stream.make_steps, "steps", None)
        if steps is not None:
            memo[id(steps)] = steps
        if self._figure is not None:
            memo[id(self._figure)] = None
        # calibration records are tuples of a string and floats: a new list, the same tuples
        memo[id(self.compute_records)] = list(self.compute_records)
        copied = copy.deepcopy(self, memo)
        copied.render_mode = None
        return copied

    def reseed_future(self, seed: int) -> None:
        """Draw the rest of the episode's measurement noise and the filter's random draws anew
        from ``seed`` (a non-negative integer), keeping the world's path and landmarks and
        everything that already happened: one of the futures the episode could have, which
        ``seed`` chooses. Meant for a :meth:`clone` (a lookahead's imagined future), never for
        the episode being scored. The scans to come are redrawn as
        :class:`slam_gym.world.RedrawnFuture` states (the odometry is kept); a recorded data set
        has no model to redraw from and raises ``ValueError``."""
        if self.episode is None:
            raise RuntimeError("call reset() before reseed_future()")
        require(
            isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0,
            "seed", seed, "a non-negative integer",
        )
        self.episode.redraw_future(int(seed))
        if self.filter_draws is not None:
            self.filter_draws.iteration = self.episode.iteration
            self.filter_draws.rekey(int(seed))
            return
        drawn = np.random.default_rng(np.random.SeedSequence([int(seed), self.episode.iteration]))
        self.filter_rng.bit_generator.state = drawn.bit_generator.state

    def _record(self, kind_ops, cpu_start_s: float) -> tuple[float, float]:
        """Keep ``(kind, ops, measured CPU s)`` for calibration, the CPU measured from
        ``cpu_start_s`` to a reading of the clock taken here; return that reading (where the
        next component's record starts) and the modelled seconds."""
        kind, ops = kind_ops
        cpu_s = time.process_time()
        self.compute_records.append((kind, float(ops), cpu_s - cpu_start_s))
        return cpu_s, self.compute_model.seconds(kind, ops)

    def _remaining_decisions(self) -> int:
        """Decisions left on the path (and before truncation) after the current one."""
        left = math.ceil(max(len(self.stream) - self.episode.iteration, 0)
                         / self.config.decision_interval)
        if self.config.max_decisions is not None:
            left = min(left, self.config.max_decisions - self.n_decisions)
        return max(left, 0)

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode to gym.make")
            return None
        from slam_gym.envs.rendering import render_frame, show_in_window

        frame, self._figure = render_frame(self, self._figure, self.render_mode)
        if self.render_mode != "human":
            return frame
        if not show_in_window(self._figure) and not self._warned_headless:
            self._warned_headless = True
            logger.warning("render_mode='human' needs an interactive matplotlib backend "
                           "(MPLBACKEND); no window is shown: use render_mode='rgb_array'")
        return None

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
        features = {name: float(raw[name]) for name in FEATURE_NAMES}
        features["compute_price_per_s"] = float(self.config.w_compute)
        return features

    def _observation(self, features) -> np.ndarray:
        obs = np.array([features[n] for n in self.config.observation_features], dtype=np.float64)
        obs = np.nan_to_num(obs, nan=0.0, posinf=OBSERVATION_MAX, neginf=0.0)
        return np.clip(obs, 0.0, OBSERVATION_MAX).astype(np.float32)

    def _info(self, features, components, nees_values, score=None) -> dict:
        ep = self.episode
        score = ep.map_score() if score is None else score
        info = {
            "features": features,
            "reward_components": components,
            "nees": float(ep.last_nees),
            "nees_interval_mean": float(np.mean(nees_values)) if len(nees_values) else ep.last_nees,
            "pose_error_m": float(ep.last_position_error_m),
            "map_error_m": _defined(score.map_error_m),
            "map_completeness": _defined(score.completeness),
            "failed": bool(ep.failure.failed),
            "n_fusions": ep.n_fusions,
            "n_optimisations": ep.n_optimisations,
            "iteration": ep.iteration,
            "world_seed": self.world_seed,
            "optimise_redundant": self.optimisation_is_redundant(),
            "action_mask": self.action_masks(),
        }
        if self.config.info_compute_time:
            info["filter_time_s"] = float(ep.compute_time_s)
        return info


def _defined(value: float) -> float | None:
    """``value``, or None where it is undefined (NaN): infos of one seed must compare equal."""
    value = float(value)
    return None if math.isnan(value) else value
