"""The MRCLAM env (slam_gym.envs.mrclam): the interface env of HybridSLAMEnv on recorded data.

Uses MRCLAM Dataset 7 from tests/slam_gym/realdata.py (excerpts, or the whole recordings in
``$SLAM_GYM_DATA``).
"""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from realdata import MRCLAM_DIR

from slam_gym.datasets import load_mrclam
from slam_gym.envs.hybrid_slam import FEATURE_NAMES
from slam_gym.envs.mrclam import MRCLAMEnv, default_mrclam_dir, mrclam_stream
from slam_gym.metrics import nees

SMALL = {"data_dir": MRCLAM_DIR, "robot": 2, "n_particles": 10, "n_steps": 80}
ACTIONS = [np.array([i % 3 == 2, 0], dtype=np.int64) for i in range(10)]


def make(**kwargs):
    return MRCLAMEnv(**(SMALL | kwargs))


def rollout(env, seed, actions, options=None):
    obs, info = env.reset(seed=seed, options=options)
    out = [(obs, 0.0, info["nees"], info["pose_error_m"])]
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        out.append((obs, reward, info["nees"], info["pose_error_m"]))
        if terminated or truncated:
            break
    return out


def same(a, b) -> bool:
    return len(a) == len(b) and all(
        np.array_equal(oa, ob) and ra == rb and na == nb and pa == pb
        for (oa, ra, na, pa), (ob, rb, nb, pb) in zip(a, b, strict=True)
    )


def test_default_data_dir_comes_from_the_one_setting(monkeypatch, tmp_path):
    root = MRCLAM_DIR.parents[1]
    monkeypatch.setenv("SLAM_GYM_DATA", str(root))
    assert default_mrclam_dir().resolve() == MRCLAM_DIR.resolve()
    env = MRCLAMEnv(robot=3, n_particles=5, n_steps=20)
    assert env.data_dir.resolve() == MRCLAM_DIR.resolve() and env.robot == 3
    monkeypatch.setenv("SLAM_GYM_DATA", str(tmp_path))  # a root without the data set
    assert default_mrclam_dir() is None
    with pytest.raises(ValueError, match="SLAM_GYM_DATA"):
        MRCLAMEnv(robot=3)


def test_gymnasium_env_checker_without_warnings():
    from gymnasium.utils.env_checker import check_env

    env = gym.make("slam_gym:SlamGym/MRCLAM-v1", render_mode="rgb_array", **SMALL)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)  # with its render check of every declared mode
    env.close()


def test_sb3_env_checker_without_warnings():
    from stable_baselines3.common.env_checker import check_env

    env = make()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, warn=True)
    env.close()


def test_same_seed_same_episode_other_seed_differs_world_seed_selects_nothing():
    a = rollout(make(), 3, ACTIONS)
    b = rollout(make(), 3, ACTIONS)
    assert same(a, b)
    # the recording is fixed: a world seed changes nothing
    c = rollout(make(), 3, ACTIONS, options={"world_seed": 12345})
    assert same(a, c)
    # the filter seed changes the particles, hence the observation
    d = rollout(make(), 4, ACTIONS)
    assert any(not np.array_equal(x[0], y[0]) for x, y in zip(a, d, strict=False))


def test_stream_is_the_recording_cached_and_scored_against_motion_capture():
    env = make(n_steps=60, decision_interval=5)
    obs, info = env.reset(seed=0)
    stream = env.stream
    ref = load_mrclam(MRCLAM_DIR, 2, max_steps=60)
    assert stream.n_steps == 60 and stream.name == ref.name
    np.testing.assert_array_equal(stream.landmarks_true, ref.landmarks_true)
    assert stream.sensor == ref.sensor and stream.clutter == ref.clutter
    obs, reward, terminated, truncated, info = env.step(np.array([1, 0]))
    ep = env.unwrapped.episode
    truth = ep.last_step.truth.pose
    est, cov = env.system.pose()
    assert info["pose_error_m"] == pytest.approx(np.hypot(*(truth[:2] - est[:2])))
    assert np.all(np.isfinite(truth)) and info["nees"] == nees(truth, est, cov)
    c, w = info["reward_components"], env.config
    expected = -(w.w_nees * (c["nees_over"] + c["nees_under"]) + w.w_pose * c["pose_error_m"]
                 + w.w_map * c["map_ospa_m"] + w.w_compute * c["compute_s"]
                 + c["failure_charge"])
    assert reward == pytest.approx(expected)
    assert obs.shape == (len(FEATURE_NAMES),) and obs.dtype == np.float32
    env.reset(seed=1)
    assert env.stream is stream  # loaded once per (dir, robot, n_steps, noise scale)


def test_sensor_noise_scale_scales_only_the_noise():
    base = mrclam_stream(MRCLAM_DIR, 2, max_steps=10)
    scaled = mrclam_stream(MRCLAM_DIR, 2, max_steps=10, sensor_noise_scale=3.0)
    assert scaled.sensor.range_std_m == pytest.approx(3.0 * base.sensor.range_std_m)
    assert scaled.sensor.bearing_std_rad == pytest.approx(3.0 * base.sensor.bearing_std_rad)
    assert scaled.sensor.fov_rad == base.sensor.fov_rad
    assert scaled.sensor.max_range_m == base.sensor.max_range_m
    assert scaled.clutter == base.clutter and scaled.metadata["sensor_noise_scale"] == 3.0
    for s, t in zip(base, scaled, strict=True):
        np.testing.assert_array_equal(s.z, t.z)


def test_sensor_calibration_and_front_end_options_reach_stream_and_filter():
    env = make(sensor_noise_window_s=30.0, sensor_noise_scale=2.0,
               front_end_options={"new_landmark_density_per_m2": 1e-4, "gate_chi2": 40.0})
    env.reset(seed=0)
    ref = load_mrclam(MRCLAM_DIR, 2, max_steps=80, noise_window_s=30.0)
    assert env.stream.sensor.range_std_m == pytest.approx(2.0 * ref.sensor.range_std_m)
    assert env.stream.sensor.bearing_std_rad == pytest.approx(2.0 * ref.sensor.bearing_std_rad)
    front = env.system.front_end
    assert front.new_landmark_density == 1e-4 and front.gate_chi2 == 40.0
    env.close()
    with pytest.raises(ValueError, match="gate_chi2"):
        make(front_end_options={"gate_chi2": -1.0}).reset(seed=0)


def test_the_loader_corrections_are_the_env_default_and_can_be_switched_off():
    env = make()
    env.reset(seed=0)
    assert env.stream.metadata["corrections"] is True
    assert env.stream.metadata["calibration"]["calibration_s"] == 300.0
    assert env.stream.sensor == load_mrclam(MRCLAM_DIR, 2, max_steps=80).sensor
    env.close()
    plain = make(corrections=False, calibration_s=40.0)
    plain.reset(seed=0)
    ref = load_mrclam(MRCLAM_DIR, 2, max_steps=80, corrections=False, calibration_s=40.0)
    assert plain.stream.sensor == ref.sensor and plain.stream.odometry_noise == ref.odometry_noise
    assert plain.stream.metadata["sensor_bias_correction"] is False
    plain.close()


def test_episodes_run_the_recording_after_a_failure_by_default():
    # a tiny sensor noise makes the filter over-confident: BB's failure criterion triggers early
    kwargs = {"n_steps": 600, "sensor_noise_scale": 0.02, "n_particles": 5}
    stop = make(terminate_on_failure=True, **kwargs)
    stop.reset(seed=0)
    for _ in range(100):
        _, _, terminated, truncated, info = stop.step(np.array([0, 0]))
        if terminated or truncated:
            break
    assert terminated and info["failed"] and not stop.episode.done
    go_on = make(**kwargs)  # the default
    go_on.reset(seed=0)
    penalties = []
    for _ in range(100):
        _, _, terminated, truncated, info = go_on.step(np.array([0, 0]))
        penalties.append(info["reward_components"]["failure_charge"])
        if terminated or truncated:
            break
    assert terminated and info["failed"] and go_on.episode.done
    # charged the one-off penalty once, without the remaining path's worst case: it goes on
    assert go_on.episode.iteration == len(go_on.stream)  # the whole (cut) recording
    assert sum(penalties) == go_on.config.failure_penalty
    # ending at the failure charges the remaining path's worst case on top
    assert stop_charge(kwargs) > go_on.config.failure_penalty


def stop_charge(kwargs):
    env = make(terminate_on_failure=True, **kwargs)
    env.reset(seed=0)
    while True:
        _, _, terminated, truncated, info = env.step(np.array([0, 0]))
        if terminated or truncated:
            return info["reward_components"]["failure_charge"]


def test_env_pickles_and_the_copy_continues_identically():
    import pickle

    env = make()
    env.reset(seed=5)
    env.step(np.array([1, 0]))
    clone = pickle.loads(pickle.dumps(env))
    a = env.step(np.array([0, 1]))
    b = clone.step(np.array([0, 1]))
    assert np.array_equal(a[0], b[0]) and a[1] == b[1] and a[4]["nees"] == b[4]["nees"]


def test_truncation_by_decision_limit():
    env = make(max_decisions=2)
    env.reset(seed=0)
    assert [env.step(np.array([0, 0]))[3] for _ in range(2)] == [False, True]


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"data_dir": "/no/such/mrclam"}, "data_dir"),
        ({"data_dir": 42}, "data_dir"),
        ({"robot": 0}, "robot"),
        ({"robot": 6}, "robot"),
        ({"robot": "2"}, "robot"),
        ({"robot": True}, "robot"),
        ({"scenario": "brooks-bailey"}, "scenario"),
        ({"clutter_level": 1}, "clutter_level"),
        ({"alpha": 0.5}, "alpha"),
        ({"sensor_noise_scale": 0.0}, "sensor_noise_scale"),
        ({"sensor_noise_window_s": 0.0}, "sensor_noise_window_s"),
        ({"sensor_bias_correction": 1}, "sensor_bias_correction"),
        ({"corrections": "yes"}, "corrections"),
        ({"calibration_s": 1.0}, "calibration_s"),
        ({"front_end_options": [("gate_chi2", 40.0)]}, "front_end_options"),
        ({"terminate_on_failure": "no"}, "terminate_on_failure"),
        ({"n_particles": 0}, "n_particles"),
        ({"render_mode": "ascii"}, "render_mode"),
    ],
)
def test_bad_keyword_values_raise_value_error_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        make(**kwargs)


def test_data_dir_without_the_robot_files_names_data_dir(tmp_path):
    (tmp_path / "Barcodes.dat").write_text("# subject barcode\n1 5\n")
    with pytest.raises(ValueError, match="data_dir.*Robot2_Odometry.dat"):
        make(data_dir=tmp_path)


def test_simulation_reset_options_are_rejected():
    env = make()
    with pytest.raises(ValueError, match="clutter_level"):
        env.reset(seed=0, options={"clutter_level": 2})


def test_gym_make_registered_id():
    # passes once SlamGym/MRCLAM-v1 is registered (slam_gym.envs.register_envs)
    env = gym.make("slam_gym:SlamGym/MRCLAM-v1", data_dir=str(MRCLAM_DIR), robot=2,
                   n_particles=5, n_steps=30)
    obs, info = env.reset(seed=0)
    assert isinstance(env.unwrapped, MRCLAMEnv) and env.unwrapped.robot == 2
    assert obs.shape == (len(FEATURE_NAMES),) and np.isfinite(info["nees"])
    env.close()


def test_rgb_array_frame():
    # passes once slam_gym/envs/rendering.py tolerates streams without a simulated scenario
    env = make(render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.array([1, 0]))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.std() > 5  # something is drawn
    env.close()
