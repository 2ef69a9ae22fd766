"""The simulator: sensor statistics, paths, odometry consistency, determinism, validation."""

import numpy as np
import pytest

from filters.dead_reckoning import DeadReckoning
from filters.models import observe
from slam_gym.metrics import nees, nees_band
from slam_gym.scenarios import CLUTTER_LEVELS, get_scenario, make_stream, scenario_names


def path_length(stream):
    poses = stream.metadata["true_poses"]
    return float(np.sum(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)))


@pytest.mark.parametrize("level", sorted(CLUTTER_LEVELS))
def test_sensor_statistics_match_alpha_beta_and_noise(level):
    alpha, beta = CLUTTER_LEVELS[level]
    visible = detected = false_alarms = 0
    range_err, bearing_err = [], []
    for seed in range(3):
        stream = make_stream("brooks-bailey", seed=seed, clutter_level=level, n_steps=1500)
        sensor = stream.sensor
        for step in stream:
            truth = step.truth
            visible += len(truth.visible_ids)
            ids = truth.landmark_ids
            true_ids = ids[ids >= 0]
            detected += len(true_ids)
            false_alarms += int(np.count_nonzero(ids < 0))
            assert set(true_ids) <= set(truth.visible_ids)
            z_true = observe(truth.pose, stream.landmarks_true[true_ids])
            assert np.all(z_true[:, 0] <= sensor.max_range_m)  # nothing beyond max range
            d = step.z[ids >= 0] - z_true
            d[:, 1] = (d[:, 1] + np.pi) % (2 * np.pi) - np.pi
            range_err.extend(d[:, 0])
            bearing_err.extend(d[:, 1])
            fa = step.z[ids < 0]
            assert np.all((fa[:, 0] >= 0) & (fa[:, 0] <= sensor.max_range_m))
    # binomial 5-sigma tolerances
    tol_alpha = 5 * np.sqrt(alpha * (1 - alpha) / visible) + 1e-9
    tol_beta = 5 * np.sqrt(beta * (1 - beta) / visible) + 1e-9
    assert detected / visible == pytest.approx(alpha, abs=tol_alpha)
    assert false_alarms / visible == pytest.approx(beta, abs=tol_beta)
    assert detected > 1000
    assert np.std(range_err) == pytest.approx(0.05, rel=0.1)
    assert np.std(bearing_err) == pytest.approx(np.deg2rad(1.0), rel=0.1)
    assert abs(np.mean(range_err)) < 5 * 0.05 / np.sqrt(detected)


def test_limited_field_of_view_is_respected():
    stream = make_stream("brooks-bailey", seed=4, n_steps=400, fov_rad=np.deg2rad(60))
    for step in stream:
        assert np.all(np.abs(step.z[:, 1]) <= np.deg2rad(30) + 1e-9 + 5 * np.deg2rad(1))
        z_true = observe(step.truth.pose, stream.landmarks_true[step.truth.visible_ids])
        assert np.all(np.abs(z_true[:, 1]) <= np.deg2rad(30) + 1e-12)


def test_brooks_bailey_paths_close_one_large_loop():
    lengths = []
    for seed in range(12):
        stream = make_stream("brooks-bailey", seed=seed)
        lengths.append(path_length(stream))
        poses = stream.metadata["true_poses"]
        assert np.all(poses[:, :2] >= 0) and np.all(poses[:, :2] <= 120)
        # the end re-observes what the start saw: landmarks in range of the start are seen last
        first = set()
        for step in stream:
            if step.index < 100:
                first.update(step.truth.visible_ids.tolist())
            last = step
        seen_at_end = set()
        for step in list(stream)[-150:]:
            seen_at_end.update(step.truth.visible_ids.tolist())
        assert first & seen_at_end, "the path's end must re-observe landmarks seen at the start"
        assert len(stream) == last.index + 1
    assert 350 <= min(lengths) and max(lengths) <= 450
    assert np.std(lengths) > 0.5  # randomly perturbed


@pytest.mark.parametrize("name, length, speed", [
    ("conte-martinelli-1", 180.0, 1.0), ("conte-martinelli-2", 325.0, 1.2),
])
def test_conte_martinelli_lengths_and_speeds(name, length, speed):
    for seed in range(4):
        stream = make_stream(name, seed=seed)
        assert path_length(stream) == pytest.approx(length, rel=0.05)
        v = np.array([s.odometry[0] for s in stream])
        assert np.mean(v) == pytest.approx(speed, rel=0.01)
        scans = sum(1 for s in stream if s.truth.visible_ids is not None)
        assert scans == len(stream) // 50  # 0.2 Hz sensor in a 10 Hz filter
        assert len(stream.landmarks_true) == round(0.02 * 110 * 110)


@pytest.mark.parametrize("name", ["brooks-bailey", "conte-martinelli-1", "brooks-bailey-compass"])
def test_dead_reckoning_is_consistent(name):
    """ANEES of the final pose over many short runs inside the 95 % chi-square band."""
    runs = 40
    values = []
    for seed in range(runs):
        stream = make_stream(name, seed=seed, n_steps=250)
        f = DeadReckoning(stream.odometry_noise, stream.initial_pose)
        for step in stream:
            f.predict(step.odometry, step.dt_s)
            if step.compass_rad is not None:
                f.update_heading(step.compass_rad, stream.compass_std_rad)
        mean, cov = f.pose()
        values.append(nees(step.truth.pose, mean, cov))
    lo, hi = nees_band(runs)
    assert lo <= np.mean(values) <= hi


def test_same_seed_same_stream_bit_for_bit_and_different_seeds_differ():
    a = list(make_stream("brooks-bailey", seed=7, clutter_level=2, n_steps=300))
    b = list(make_stream("brooks-bailey", seed=7, clutter_level=2, n_steps=300))
    c = list(make_stream("brooks-bailey", seed=8, clutter_level=2, n_steps=300))
    for sa, sb in zip(a, b, strict=True):
        assert np.array_equal(sa.z, sb.z) and np.array_equal(sa.odometry, sb.odometry)
        assert np.array_equal(sa.truth.pose, sb.truth.pose)
        assert np.array_equal(sa.truth.landmark_ids, sb.truth.landmark_ids)
    assert any(not np.array_equal(sa.odometry, sc.odometry) for sa, sc in zip(a, c, strict=True))


def test_clutter_level_keeps_world_and_odometry():
    a = make_stream("brooks-bailey", seed=3, clutter_level=0, n_steps=200)
    b = make_stream("brooks-bailey", seed=3, clutter_level=3, n_steps=200)
    assert np.array_equal(a.landmarks_true, b.landmarks_true)
    for sa, sb in zip(a, b, strict=True):
        assert np.array_equal(sa.odometry, sb.odometry)


@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"clutter_level": 5}, "clutter_level"),
        ({"alpha": 0.0}, "alpha"),
        ({"beta": 1.5}, "beta"),
        ({"max_range_m": -3.0}, "max_range_m"),
        ({"speed_mps": 0.0}, "speed_mps"),
        ({"n_landmarks": -1}, "n_landmarks"),
        ({"path_length_m": 5000.0}, "path_length_m"),
        ({"odometry_rate_hz": 15.0}, "odometry_rate_hz"),
        ({"odometry_model": "magic"}, "odometry_model"),
        ({"no_such_field": 1}, "no_such_field"),
    ],
)
def test_bad_scenario_values_raise_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=field):
        get_scenario("brooks-bailey", **overrides)


def test_unknown_scenario_and_bad_seed():
    with pytest.raises(ValueError, match="scenario"):
        get_scenario("nowhere")
    with pytest.raises(ValueError, match="seed"):
        make_stream("brooks-bailey", seed=-1)


def test_scenario_presets():
    assert set(scenario_names()) == {
        "brooks-bailey", "brooks-bailey-compass", "conte-martinelli-1", "conte-martinelli-2",
    }
    bb = get_scenario("brooks-bailey", clutter_level=3)
    assert (bb.alpha, bb.beta) == (0.1, 0.06) and bb.max_range_m == 25.0
    assert get_scenario("brooks-bailey", alpha=0.5, beta=0.01).clutter_level is None
