"""Named scenarios (docs/ARCHITECTURE.md, "The data stream"): frozen, validated configurations of
the simulated world.

``brooks-bailey`` (BB 5.2): 120 m x 120 m, 35 uniform point landmarks, a random path near the
extremities closing one ~430 m loop (BB Fig. 4: the loop closes near iteration 4400, i.e. ~440 m at
1 m/s), 1 m/s, turn rate up to 100 deg/s, filter rate 10 Hz,
odometry noise std 0.25 v and 0.35 |omega|, 360-degree sensor of 25 m range with std 0.05 m and
1 deg, reliability (alpha, beta) by clutter level 0-3 (BB Table 1).
``brooks-bailey-compass`` (BB 5.5, Fig. 3): the same worlds and paths with an accurate heading
measurement every iteration.
``brooks-bailey-calibrated`` (issue 28): ``brooks-bailey`` with the waypoint jitter
(``path_perturbation_m``, the one scalar that sets the path's turning) fitted to BB Table 1's
EKF cell at clutter level 0: 0.625 m instead of 5 m, ~10 rad of turning instead of ~26; the same
landmarks and start turn per seed. Not the default (docs/RESULTS.md says why).
``brooks-bailey-zones`` (issue 48): ``brooks-bailey`` with zones along the loop, drawn per world
and never observed: feature-poor corridors, clutter bursts, dense landmark patches
(:data:`ZONES_OVERRIDES`; :func:`slam_gym.world.draw_zones`). The base world of seed ``s`` (its
landmarks before the zones, its path, its odometry) is ``brooks-bailey``'s world ``s``.
``long-mission`` (issue 48): BB's density, sensor and odometry on a 200 m world, a 450 m loop
driven 3.3 times (:data:`LONG_MISSION_OVERRIDES`).
``conte-martinelli-1`` / ``-2`` (CM IV.A): 110 m x 110 m, 0.02 landmarks per m^2, differential
drive with Chong-Kleeman wheel odometry (CM (14), K = 1e-5 m) at 100 Hz, 360-degree sensor of 12 m
range with std 1 cm and 1 deg at 0.2 Hz (the first scan at the start pose), no clutter (CM
assumes known association). Sim 1:
1 m/s over 180 m, one counter-clockwise loop that ends by re-observing the start; sim 2: 1.2 m/s
over 325 m, the loop and then a re-traversal of its first part.

BB's path, as BB describe it (#14). BB 5.2 and Fig. 2 give: a random path "near the extremities of
the environment, such that one significant loop closure had to be executed", 1 m/s, up to
100 deg/s; BB 5.5 adds "the vehicle is executing many uncertain turns (including one sharp turn
near the beginning of the trajectory)" and BB 5.4 names turns as where the EKF front-end fails;
BB Fig. 4 has the loop closure near iteration 4400. The figure itself is not in our text copy, so
the number of turns is read from the text, not counted. The generator's choices, fixed a priori
(nothing was tuned on the reported worlds or on any filter result):
* a square loop of side ``loop_fraction * path_length_m / 4`` = 0.9 * 440 / 4 = 99 m, i.e. ~10.5 m
  from the edges of the 120 m world (near the extremities), started mid-bottom, counter-clockwise;
* waypoints every 10 m along it (one heading change per ~10 s, i.e. about one per BB sub-map of
  10 s: "many uncertain turns"), each moved uniformly by up to 5 m in x and y and kept 2 m inside
  the world; the driven loop is ~430 m (the perturbation lengthens it), and the route always
  returns over the start (the one significant loop closure), then ends;
* the start faces away from the first waypoint by a uniform angle of up to 90 deg
  (``initial_heading_spread_rad``: "one sharp turn near the beginning");
* the heading controller (below) saturates at BB's 100 deg/s.
Over seeds 0-19 this gives 26 rad of total turning and 3.8 % of steps turning faster than
0.5 rad/s, against 9.8 rad and 1.3 % for the previous square loop with 22.5 m waypoint spacing
(docs/RESULTS.md, "BB's path"). The old path is still available as the overrides
:data:`SQUARE_LOOP_OVERRIDES` (``waypoint_spacing_m=22.5, path_length_m=400,
initial_heading_spread_rad=0``).

Choices the papers leave open (documented here, overridable):
* the path is a counter-clockwise square loop centred in the world whose perimeter is
  ``loop_fraction`` of the path length (BB: 90 % -> a 90 m square 15 m from the edges of the 120 m
  world; CM sim 2: 62 % -> a 200 m loop, then a re-traversal), with waypoints every
  ``waypoint_spacing_m`` moved uniformly by up to ``path_perturbation_m``; after the loop the
  robot drives on over the start up to ``path_length_m`` of waypoints, so the end re-observes the
  landmarks seen first; corners are cut, so the driven length is a few metres shorter;
* the controller steers toward the next waypoint with a proportional heading gain saturated at
  the turn-rate limit (CM's robot: 45 deg/s, our choice);
* BB's odometry noise vanishes when the commanded turn rate is zero, which leaves the pose
  covariance rank-deficient on straight segments (a 3-dof NEES is then meaningless); simulator and
  filters therefore share a small std floor of 0.005 m/s and 0.005 rad/s (0.03 rad of heading
  drift over a whole run, against ~0.2 rad per 90-degree turn from BB's model);
* the compass std is 0.5 deg; the filters run at 10 Hz in every scenario (CM's encoder ticks at
  100 Hz are summed into each 0.1 s step; CM (14)'s variance is linear in the travel, so the sum
  has exactly the per-step variance the filters assume).

CM choices in detail (``conte-martinelli-*``):
* **the first scan is taken at the start pose** (``scan_at_start``: a motionless step 0 at t = 0,
  then a scan every 5 s). CM measure map error in the global frame fixed by the known start pose
  (IV.B), and their hybrid's 0.15 m after the loop closure of sim 1 is only reachable if the first
  landmarks are tied to that pose by a scan there: with the first scan after 5 s of odometry, the
  heading error of that first observing pose rotates the whole map about the start, and no loop
  closure can undo it (it is relative to the start pose, which nothing but odometry observes);
* **wheel base 0.09 m: calibrated, not stated.** CM give K = 1e-5 m (CM (14)) but not the wheel
  base b, which sets the heading noise (variance 2 K / b^2 per metre of travel). b was chosen on
  a grid (0.06, 0.08, 0.09, 0.10, 0.12, 0.15 m) so that the mean ESDF map error just before the
  loop closure of sim 1 matches the 2.02 m CM report, over calibration worlds (seeds 100-119)
  disjoint from the reported ones (seeds 0-9); it gave 1.98 m. The same b serves sim 2 (one
  robot), whose numbers are therefore a check, not a fit. Read b as an effective parameter (the
  heading noise CM's drift implies: 2.8 deg per sqrt(m)), not as a claim about CM's robot.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from filters.validation import check_range, require

CLUTTER_LEVELS: dict[int, tuple[float, float]] = {
    0: (1.0, 0.00),
    1: (0.7, 0.02),
    2: (0.4, 0.04),
    3: (0.1, 0.06),
}
"""BB Table 1: (alpha, beta) for clutter levels 0-3."""

ODOMETRY_MODELS = ("proportional", "chong-kleeman")


@dataclass(frozen=True)
class Scenario:
    """Every parameter of a simulated run. Build with :func:`get_scenario` and override by name."""

    name: str
    world_size_m: float = 120.0
    n_landmarks: int = 35
    path_length_m: float = 400.0
    loop_fraction: float = 0.9
    path_perturbation_m: float = 5.0
    waypoint_spacing_m: float = 22.5
    speed_mps: float = 1.0
    max_turn_rate_radps: float = float(np.deg2rad(100.0))
    heading_gain: float = 2.0
    filter_rate_hz: float = 10.0
    odometry_rate_hz: float = 10.0
    sensor_rate_hz: float = 10.0
    odometry_model: str = "proportional"
    v_noise_fraction: float = 0.25
    omega_noise_fraction: float = 0.35
    v_noise_floor_mps: float = 0.005
    omega_noise_floor_radps: float = 0.005
    chong_kleeman_k_m: float = 1e-5
    wheel_base_m: float = 0.5
    range_std_m: float = 0.05
    bearing_std_rad: float = float(np.deg2rad(1.0))
    max_range_m: float = 25.0
    fov_rad: float = float(2.0 * np.pi)
    clutter_level: int | None = 0
    alpha: float = 1.0
    beta: float = 0.0
    compass_std_rad: float | None = None
    scan_at_start: bool = False
    initial_heading_spread_rad: float = 0.0
    n_steps: int | None = None
    zone_sectors: int = 0
    corridor_zones: int = 0
    burst_zones: int = 0
    patch_zones: int = 0
    corridor_clearance_m: float = 15.0
    burst_beta: float = 0.5
    burst_radius_m: float = 10.0
    patch_landmarks: int = 10
    patch_radius_m: float = 10.0

    def __post_init__(self):
        require(isinstance(self.name, str) and self.name != "", "name", self.name, "a string")
        check_range("world_size_m", self.world_size_m, 10.0, 10_000.0)
        require(
            isinstance(self.n_landmarks, (int, np.integer)) and 0 <= self.n_landmarks <= 100_000,
            "n_landmarks", self.n_landmarks, "an integer in [0, 100000]",
        )
        check_range("path_length_m", self.path_length_m, 10.0, 100_000.0)
        check_range("loop_fraction", self.loop_fraction, 0.1, 1.0)
        check_range("path_perturbation_m", self.path_perturbation_m, 0.0, 0.2 * self.world_size_m)
        check_range("waypoint_spacing_m", self.waypoint_spacing_m, 1.0, self.world_size_m)
        side = self.loop_side_m
        require(
            side + 2.0 * self.path_perturbation_m <= self.world_size_m,
            "path_length_m, path_perturbation_m", (self.path_length_m, self.path_perturbation_m),
            f"small enough that the loop (side loop_fraction * path_length_m / 4 = {side:.1f} m, "
            f"plus twice the perturbation) fits in world_size_m={self.world_size_m}",
        )
        check_range("speed_mps", self.speed_mps, 0.0, 50.0, low_open=True)
        check_range("max_turn_rate_radps", self.max_turn_rate_radps, 0.0, 20.0, low_open=True)
        check_range("heading_gain", self.heading_gain, 0.0, 100.0, low_open=True)
        check_range("filter_rate_hz", self.filter_rate_hz, 0.0, 1000.0, low_open=True)
        check_range("odometry_rate_hz", self.odometry_rate_hz, 0.0, 10_000.0, low_open=True)
        check_range("sensor_rate_hz", self.sensor_rate_hz, 0.0, self.filter_rate_hz, low_open=True)
        ticks = self.odometry_rate_hz / self.filter_rate_hz
        require(
            abs(ticks - round(ticks)) < 1e-9 and round(ticks) >= 1,
            "odometry_rate_hz", self.odometry_rate_hz,
            f"an integer multiple of filter_rate_hz={self.filter_rate_hz}",
        )
        require(
            self.odometry_model in ODOMETRY_MODELS,
            "odometry_model", self.odometry_model, f"one of {ODOMETRY_MODELS}",
        )
        check_range("v_noise_fraction", self.v_noise_fraction, 0.0, 5.0)
        check_range("omega_noise_fraction", self.omega_noise_fraction, 0.0, 5.0)
        check_range("v_noise_floor_mps", self.v_noise_floor_mps, 0.0, 10.0)
        check_range("omega_noise_floor_radps", self.omega_noise_floor_radps, 0.0, 10.0)
        check_range("chong_kleeman_k_m", self.chong_kleeman_k_m, 0.0, 1.0)
        check_range("wheel_base_m", self.wheel_base_m, 0.01, 10.0)
        check_range("range_std_m", self.range_std_m, 0.0, 10.0, low_open=True)
        check_range("bearing_std_rad", self.bearing_std_rad, 0.0, 1.0, low_open=True)
        check_range("max_range_m", self.max_range_m, 0.0, 1000.0, low_open=True)
        check_range("fov_rad", self.fov_rad, 0.0, 2.0 * np.pi, low_open=True)
        if self.clutter_level is not None:
            require(
                self.clutter_level in CLUTTER_LEVELS,
                "clutter_level", self.clutter_level, f"one of {sorted(CLUTTER_LEVELS)} or None",
            )
            require(
                (self.alpha, self.beta) == CLUTTER_LEVELS[self.clutter_level],
                "alpha, beta", (self.alpha, self.beta),
                f"{CLUTTER_LEVELS[self.clutter_level]} for clutter_level={self.clutter_level} "
                "(set clutter_level=None to give alpha and beta freely)",
            )
        check_range("alpha", self.alpha, 0.0, 1.0, low_open=True)
        check_range("beta", self.beta, 0.0, 1.0, high_open=True)
        if self.compass_std_rad is not None:
            check_range("compass_std_rad", self.compass_std_rad, 0.0, 1.0, low_open=True)
        require(
            isinstance(self.scan_at_start, (bool, np.bool_)),
            "scan_at_start", self.scan_at_start, "a bool",
        )
        check_range("initial_heading_spread_rad", self.initial_heading_spread_rad, 0.0, np.pi)
        if self.n_steps is not None:
            require(
                isinstance(self.n_steps, (int, np.integer)) and self.n_steps >= 1,
                "n_steps", self.n_steps, "a positive integer or None",
            )
        for field in ("zone_sectors", "corridor_zones", "burst_zones", "patch_zones",
                      "patch_landmarks"):
            value = getattr(self, field)
            require(isinstance(value, (int, np.integer)) and not isinstance(value, bool)
                    and 0 <= value <= 1000, field, value, "an integer in [0, 1000]")
        n_zones = self.corridor_zones + self.burst_zones + self.patch_zones
        require(
            n_zones == 0 or n_zones <= self.zone_sectors - 2,
            "zone_sectors", self.zone_sectors,
            f"at least corridor_zones + burst_zones + patch_zones + 2 = {n_zones + 2} (the "
            "loop's first and last sectors, where it starts and closes, carry no zone)",
        )
        if n_zones:  # the zones' sizes bind only a world that has zones
            check_range("corridor_clearance_m", self.corridor_clearance_m, 0.0,
                        self.world_size_m)
            check_range("burst_beta", self.burst_beta, 0.0, 1.0, high_open=True)
            check_range("burst_radius_m", self.burst_radius_m, 0.0, self.world_size_m)
            check_range("patch_radius_m", self.patch_radius_m, 0.0, self.world_size_m,
                        low_open=True)

    @property
    def has_zones(self) -> bool:
        """Whether the world has zones along its path (:func:`slam_gym.world.draw_zones`)."""
        return self.corridor_zones + self.burst_zones + self.patch_zones > 0

    @property
    def loop_side_m(self) -> float:
        """Side of the square loop: its perimeter is ``loop_fraction`` of the path length."""
        return self.loop_fraction * self.path_length_m / 4.0

    @property
    def dt_s(self) -> float:
        return 1.0 / self.filter_rate_hz

    @property
    def ticks_per_step(self) -> int:
        return int(round(self.odometry_rate_hz / self.filter_rate_hz))

    @property
    def steps_per_scan(self) -> int:
        """Filter steps between two sensor scans (1 = every step)."""
        return max(1, int(round(self.filter_rate_hz / self.sensor_rate_hz)))

    def replace(self, **overrides) -> Scenario:
        """A copy with fields overridden by name; ``clutter_level`` also sets alpha and beta."""
        unknown = set(overrides) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(
                f"unknown scenario field(s) {sorted(unknown)}; known fields: "
                f"{sorted(f.name for f in dataclasses.fields(self))}"
            )
        if "clutter_level" in overrides and overrides["clutter_level"] is not None:
            level = overrides["clutter_level"]
            require(
                level in CLUTTER_LEVELS, "clutter_level", level, f"one of {sorted(CLUTTER_LEVELS)}"
            )
            overrides.setdefault("alpha", CLUTTER_LEVELS[level][0])
            overrides.setdefault("beta", CLUTTER_LEVELS[level][1])
        elif ("alpha" in overrides or "beta" in overrides) and "clutter_level" not in overrides:
            overrides["clutter_level"] = None
        return dataclasses.replace(self, **overrides)


CALIBRATED_JITTER_M = 0.625
"""The waypoint jitter of ``brooks-bailey-calibrated``: fitted on EKF sub-mapping's success at
clutter level 0 (BB Table 1: 79 %) over worlds 0-99 by the procedure declared in docs/RESULTS.md
(issue 28); 74 / 100 there, the closest of the values tried (5, 2.5, 1.25, 0.625 m)."""

BB_COMPASS_STD_RAD = float(np.deg2rad(0.5))
"""The compass of ``brooks-bailey-compass`` (BB 5.5 gives none; our choice)."""

SQUARE_LOOP_OVERRIDES: dict = {
    "waypoint_spacing_m": 22.5, "path_length_m": 400.0, "initial_heading_spread_rad": 0.0,
}
"""Overrides that give ``brooks-bailey`` its path before #14 (a square loop, no first turn)."""


ZONES_OVERRIDES: dict = {
    "zone_sectors": 8, "corridor_zones": 2, "burst_zones": 2, "patch_zones": 2,
    "corridor_clearance_m": 15.0, "burst_beta": 0.5, "burst_radius_m": 10.0,
    "patch_landmarks": 10, "patch_radius_m": 10.0,
}
"""``brooks-bailey-zones`` (issue 48, docs/RESULTS.md "Tasks where the interface decision
matters"): BB's world whose loop is cut into 8 sectors of ~50 m; the six inner sectors hold, in
an order drawn per world, two feature-poor corridors (no landmark within 15 m of the sector's
nominal path), two clutter bursts (each visible landmark triggers a false alarm with
probability 0.5 while the robot is within 10 m of the sector's path) and two dense patches (10
more landmarks in a 10 m disc on the sector's midpoint)."""

LONG_MISSION_OVERRIDES: dict = {
    "world_size_m": 200.0, "n_landmarks": 97, "path_length_m": 1500.0, "loop_fraction": 0.3,
}
"""``long-mission`` (issue 48): BB's landmark density (35 per 120 m x 120 m, so 97 in 200 m x
200 m), sensor, odometry and path generator, on a loop of ~450 m (side 0.3 x 1500 / 4 =
112.5 m) driven three and a third times: ~1500 s, ~150 of BB's 10 s sub-maps, a loop closure at
each return over the start, and a global map and an optimiser whose cost grow with the sub-maps
stored."""


def _presets() -> dict[str, Scenario]:
    bb = Scenario(
        name="brooks-bailey",
        path_length_m=440.0,
        waypoint_spacing_m=10.0,
        initial_heading_spread_rad=float(np.pi / 2),
    )
    cm = Scenario(
        name="conte-martinelli-1",
        world_size_m=110.0,
        n_landmarks=int(round(0.02 * 110.0 * 110.0)),
        path_length_m=180.0,
        loop_fraction=0.9,
        path_perturbation_m=2.0,
        waypoint_spacing_m=10.0,
        speed_mps=1.0,
        max_turn_rate_radps=float(np.deg2rad(45.0)),
        odometry_rate_hz=100.0,
        sensor_rate_hz=0.2,
        odometry_model="chong-kleeman",
        wheel_base_m=0.09,
        range_std_m=0.01,
        max_range_m=12.0,
        scan_at_start=True,
    )
    return {
        "brooks-bailey": bb,
        "brooks-bailey-calibrated": bb.replace(
            name="brooks-bailey-calibrated", path_perturbation_m=CALIBRATED_JITTER_M
        ),
        "brooks-bailey-compass": bb.replace(
            name="brooks-bailey-compass", compass_std_rad=BB_COMPASS_STD_RAD
        ),
        "brooks-bailey-zones": bb.replace(name="brooks-bailey-zones", **ZONES_OVERRIDES),
        "long-mission": bb.replace(name="long-mission", **LONG_MISSION_OVERRIDES),
        "conte-martinelli-1": cm,
        "conte-martinelli-2": cm.replace(
            name="conte-martinelli-2",
            path_length_m=325.0,
            loop_fraction=0.62,
            speed_mps=1.2,
        ),
    }


def scenario_names() -> list[str]:
    return sorted(_presets())


def get_scenario(name: str | Scenario, **overrides) -> Scenario:
    """The preset ``name`` with fields overridden by keyword (validated)."""
    if isinstance(name, Scenario):
        base = name
    else:
        presets = _presets()
        if name not in presets:
            raise ValueError(f"scenario={name!r} is unknown: must be one of {sorted(presets)}")
        base = presets[name]
    return base.replace(**overrides) if overrides else base
