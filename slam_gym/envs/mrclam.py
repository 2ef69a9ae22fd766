"""``SlamGym/MRCLAM-v1``: the interface env of :mod:`slam_gym.envs.hybrid_slam` on recorded data.

:class:`MRCLAMEnv` plays one robot of a UTIAS MRCLAM data set (Leung et al., IJRR 2011) through
the same hybrid system, observation, action, reward and termination as
:class:`~slam_gym.envs.hybrid_slam.HybridSLAMEnv`; only the stream differs
(:meth:`MRCLAMEnv._make_stream` loads it with :func:`slam_gym.datasets.load_mrclam`). The reward
is computed against the motion-capture ground truth (pose every step, landmarks from
``Landmark_Groundtruth.dat``) by :class:`~slam_gym.episode.Episode`, exactly as in simulation.

Keyword arguments (besides those of :class:`~slam_gym.envs.hybrid_slam.HybridSLAMConfig`):

``data_dir``
    An MRCLAM data set directory (``Barcodes.dat``, ``Landmark_Groundtruth.dat``,
    ``RobotN_{Odometry,Measurement,Groundtruth}.dat``). Default: the copy of Dataset 7 in
    ``$SLAM_GYM_DATA/mrclam/MRCLAM_Dataset7``, or ``../shared/data/...`` beside the repository,
    when it exists.
``robot``
    1-5 (default 1).
``sensor_noise_scale``
    Factor (default 1.0) on the range and bearing std estimated by the loader from the
    residuals against the truth. The MRCLAM camera's errors are strongly correlated from one
    frame to the next (and its range error depends on the bearing), so a filter that takes them
    as white noise with the measured std becomes over-confident; a factor > 1 is the usual
    remedy (see ``slam-gym reproduce mrclam --noise-scale``).
``corrections``, ``calibration_s``, ``sensor_noise_window_s``, ``sensor_bias_correction``
    and ``motion_compensation``: the loader's calibration options
    (:func:`slam_gym.datasets.load_mrclam`). By default every correction the loader has is on,
    estimated on the first 300 s of the recording; ``corrections=False`` gives the plain
    stream (the noise the root mean square of the residuals). ``sensor_noise_window_s`` sets
    the window of the white-noise rule for the camera's time-correlated errors
    (:func:`slam_gym.datasets.estimators.correlated_noise_std`; default: one pass over a landmark,
    measured); ``sensor_noise_scale`` multiplies the result.
``front_end_options``
    Keyword options of the front-end filter (:class:`filters.fastslam.FastSLAM2` or
    :class:`filters.ekf_slam.EKFSLAM`), e.g. ``{"new_landmark_density_per_m2": 1e-4,
    "gate_chi2": 40.0}`` (default: none, the filters' defaults).
``terminate_on_failure``
    False (default): the episode runs the recording to its end; a failure by BB's criterion is
    flagged in ``info`` and charged ``failure_penalty`` once (the episode going on, ending early
    cannot pay). This is how ``reproduce mrclam`` compares policies with the systems over the
    whole run: at the defaults the filters cross BB's 10-sigma line within seconds on some
    robots, and an env that stopped there would play almost none of the recording. True: the
    episode ends at the failure, as in the simulated env (charged the remaining path's worst
    case).

``n_steps`` cuts the recording to its first ``n_steps`` filter iterations (0.1 s each).
The options that describe a *simulated* world (``scenario``, ``clutter_level``, ``alpha``,
``beta``, ``scenario_overrides``) do not apply and raise ``ValueError``: the recording fixes the
world, and the sensor, odometry and clutter models are estimated from it (the loader's
calibration, in ``env.stream.metadata["calibration"]``). The base config keeps its default
scenario fields, unused.

Seeding: the recording is fixed, so ``reset(options={"world_seed": s})`` selects nothing: it is
accepted (the evaluation code passes it) and dropped, so it changes nothing at all
(``info["world_seed"]`` is the base class's draw from the reset seed and only keys the filter's
numbers). ``reset(seed=s)`` seeds the filter (particles, data association sampling), so the
same seed gives the same episode bit for bit; in ``-v1`` the filter's numbers are keyed by that
draw, ``options["draw"]`` and the iteration (synchronised: two policies reset with the same seed
and draw receive the same numbers for the same purpose). The stream is loaded once per
(directory, robot, ``n_steps``, ``sensor_noise_scale``) and cached on the instance.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from filters.models import RangeBearingSensor
from filters.validation import check_range, require
from slam_gym.datasets.location import default_data_dir
from slam_gym.datasets.mrclam import DEFAULT_CALIBRATION_S, MrclamOptions
from slam_gym.envs.hybrid_slam import HybridSLAMEnv

MRCLAM_ROBOTS = (1, 2, 3, 4, 5)
#: base-config options that describe a simulated world and do not apply to recorded data
SIMULATION_ONLY_OPTIONS = ("scenario", "clutter_level", "alpha", "beta", "scenario_overrides")
def refuse_simulation_options(options) -> None:
    """``ValueError`` naming the first of :data:`SIMULATION_ONLY_OPTIONS` in ``options``: the
    recording fixes the world, the sensor and the clutter."""
    for name in SIMULATION_ONLY_OPTIONS:
        require(
            name not in options, name, options.get(name),
            "left out for MRCLAMEnv (the recording fixes the world, the sensor and the "
            "clutter; choose data_dir and robot)",
        )


MRCLAM_FILES = ("Barcodes.dat", "Landmark_Groundtruth.dat")
ROBOT_FILES = ("Odometry", "Measurement", "Groundtruth")


def default_mrclam_dir() -> Path | None:
    """``mrclam/MRCLAM_Dataset7`` of the data root (``$SLAM_GYM_DATA``, else ``../shared/data``
    beside the repository), if it exists."""
    return default_data_dir("mrclam", "MRCLAM_Dataset7")


def check_robot(robot) -> int:
    require(
        isinstance(robot, (int, np.integer)) and not isinstance(robot, bool)
        and int(robot) in MRCLAM_ROBOTS,
        "robot", robot, f"one of {list(MRCLAM_ROBOTS)}",
    )
    return int(robot)


def check_mrclam_dir(data_dir, robot: int) -> Path:
    """The resolved data directory; ``ValueError`` naming ``data_dir`` unless it holds the
    tables of ``robot``."""
    if data_dir is None:
        found = default_mrclam_dir()
        require(
            found is not None, "data_dir", None,
            "an MRCLAM data set directory (no default copy: set SLAM_GYM_DATA, or put "
            "shared/data/mrclam/MRCLAM_Dataset7 beside the repository)",
        )
        data_dir = found
    require(
        isinstance(data_dir, (str, Path)) and str(data_dir) != "", "data_dir", data_dir,
        "a directory path",
    )
    path = Path(data_dir).expanduser().resolve()
    require(path.is_dir(), "data_dir", str(data_dir), "an existing MRCLAM data set directory")
    needed = [*MRCLAM_FILES, *(f"Robot{robot}_{kind}.dat" for kind in ROBOT_FILES)]
    missing = [name for name in needed if not (path / name).is_file()]
    require(
        not missing, "data_dir", str(data_dir),
        f"an MRCLAM directory holding {', '.join(needed)} (missing: {', '.join(missing)})",
    )
    return path


def mrclam_stream(
    data_dir, robot: int, *, max_steps=None, sensor_noise_scale: float = 1.0,
    options: MrclamOptions | None = None,
):
    """The MRCLAM stream of ``robot`` with its range and bearing std scaled by
    ``sensor_noise_scale`` (the outlier labels, field of view and clutter rates stay those of
    the loader's calibration); shared by the env and ``reproduce mrclam`` so both play the same
    stream. ``options``: the loader's calibration options
    (:class:`slam_gym.datasets.mrclam.MrclamOptions`; None: its defaults, every correction on,
    calibrated on the first 300 s)."""
    from slam_gym.datasets import load_mrclam

    robot = check_robot(robot)
    check_range("sensor_noise_scale", sensor_noise_scale, 0.0, 1000.0, low_open=True)
    require(options is None or isinstance(options, MrclamOptions), "options", options,
            "None or a MrclamOptions")
    stream = load_mrclam(
        check_mrclam_dir(data_dir, robot), robot, max_steps=max_steps,
        **(options or MrclamOptions()).as_kwargs(),
    )
    if sensor_noise_scale == 1.0:
        return stream
    s = stream.sensor
    sensor = RangeBearingSensor(
        range_std_m=s.range_std_m * sensor_noise_scale,
        bearing_std_rad=s.bearing_std_rad * sensor_noise_scale,
        max_range_m=s.max_range_m,
        fov_rad=s.fov_rad,
    )
    metadata = {**stream.metadata, "sensor_noise_scale": float(sensor_noise_scale)}
    return dataclasses.replace(stream, sensor=sensor, metadata=metadata)


class MRCLAMEnv(HybridSLAMEnv):
    """The hybrid-SLAM interface env on one MRCLAM robot (see the module docstring)."""

    RESET_OPTIONS = ("world_seed", "draw", "n_steps", "max_decisions")

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        data_dir=None,
        robot: int = 1,
        sensor_noise_scale: float = 1.0,
        sensor_noise_window_s: float | None = None,
        sensor_bias_correction: bool | None = None,
        motion_compensation: bool | None = None,
        corrections: bool = True,
        calibration_s: float | None = DEFAULT_CALIBRATION_S,
        front_end_options: dict | None = None,
        terminate_on_failure: bool = False,
        **config,
    ):
        refuse_simulation_options(config)
        self.robot = check_robot(robot)
        self.data_dir = check_mrclam_dir(data_dir, self.robot)
        check_range("sensor_noise_scale", sensor_noise_scale, 0.0, 1000.0, low_open=True)
        self.sensor_noise_scale = float(sensor_noise_scale)
        options = MrclamOptions(
            corrections=corrections,
            calibration_s=calibration_s,
            noise_window_s=sensor_noise_window_s,
            sensor_bias_correction=sensor_bias_correction,
            motion_compensation=motion_compensation,
            names={"noise_window_s": "sensor_noise_window_s"},
        )
        self.stream_options = dataclasses.replace(
            options,
            calibration_s=None if calibration_s is None else float(calibration_s),
            noise_window_s=None if sensor_noise_window_s is None
            else float(sensor_noise_window_s),
        )
        require(
            front_end_options is None or isinstance(front_end_options, dict),
            "front_end_options", front_end_options, "a dict of front-end filter options or None",
        )
        self.front_end_options = dict(front_end_options or {})
        require(
            isinstance(terminate_on_failure, bool), "terminate_on_failure", terminate_on_failure,
            "a bool",
        )
        self.terminate_on_failure = terminate_on_failure
        self._streams: dict[tuple, object] = {}
        super().__init__(render_mode=render_mode, **config)

    @classmethod
    def resolved_kwargs(cls, **kwargs) -> dict:
        """Every option of an env made with ``kwargs``: this class's own (the recording, the
        robot, the sensor's treatment), then the system's (:class:`HybridSLAMConfig`'s, less
        the simulation's :data:`SIMULATION_ONLY_OPTIONS`), as plain JSON."""
        import inspect

        from slam_gym.envs.hybrid_slam import HybridSLAMConfig

        own = {name: p.default for name, p in inspect.signature(cls.__init__).parameters.items()
               if p.kind is inspect.Parameter.KEYWORD_ONLY}
        given = cls.DEFAULTS | kwargs
        refuse_simulation_options(given)
        config = {k: v for k, v in given.items() if k not in own}
        resolved = HybridSLAMConfig.from_kwargs(**config).as_kwargs()
        for name in SIMULATION_ONLY_OPTIONS:
            resolved.pop(name, None)
        check_robot(given.get("robot", own["robot"]))
        mine = own | {k: v for k, v in given.items() if k in own}
        if mine.get("data_dir") is not None:
            mine["data_dir"] = str(mine["data_dir"])
        return mine | resolved

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """As the base class; ``options["world_seed"]`` is accepted and ignored (one recording
        per robot), so it changes nothing at all (the base class would otherwise draw the
        filter's seed differently with and without it)."""
        options = {k: v for k, v in (options or {}).items() if k != "world_seed"}
        return super().reset(seed=seed, options=options)

    def _make_stream(self, world_seed: int):
        """The recording (``world_seed`` selects nothing: there is one recording per robot)."""
        key = (str(self.data_dir), self.robot, self.config.n_steps, self.sensor_noise_scale)
        if key not in self._streams:
            self._streams[key] = mrclam_stream(
                self.data_dir, self.robot, max_steps=self.config.n_steps,
                sensor_noise_scale=self.sensor_noise_scale, options=self.stream_options,
            )
        return self._streams[key]

    def _system_options(self) -> dict:
        """``front_end_options`` for the sub-map system's front-end (``front_`` prefix)."""
        return {f"front_{k}": v for k, v in self.front_end_options.items()}
