"""Real-data loaders (MRCLAM, Victoria Park) and SE(2) alignment.

The loaders are checked against the raw files, parsed here with numpy and with expected values
computed by explicit loops over the rows (not through the loaders' helpers). The data are the
excerpts in tests/data, or the whole recordings in ``$SLAM_GYM_DATA`` (tests/slam_gym/realdata.py).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest
from realdata import MRCLAM_DIR, VP_DIR, needs_full_data
from scipy.spatial import cKDTree

from filters.models import motion
from slam_gym.datasets import (
    UNKNOWN_LANDMARK_ID,
    calibrate_mrclam,
    fit_se2,
    hold_average,
    interpolate_poses,
    load_mrclam,
    load_victoria_park,
    path_error_after_alignment,
    read_mrclam,
)
from slam_gym.datasets.estimators import (
    correlated_noise_std,
    estimate_odometry_noise,
    estimate_sensor_bias,
    estimate_sensor_noise,
    true_velocities,
)
from slam_gym.datasets.mrclam import compensate_motion
from slam_gym.datasets.victoria_park import VehicleGeometry, laser_to_vehicle, read_geometry

# its module-scoped fixtures are built once: every test of this file on one worker (pytest -n)
pytestmark = pytest.mark.xdist_group("test_datasets")

ROBOT = 3  # has robot sightings and unknown barcodes (34, 52)
DT = 0.1
VP_DT = 0.025


def wrap(a):
    return (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def zoh_mean_loop(row_t, row_u, a, b):
    """Time-weighted mean over [a, b] of rows held until the next row: an explicit loop."""
    total = np.zeros(row_u.shape[1])
    for i in range(len(row_t)):
        start = row_t[i]
        end = row_t[i + 1] if i + 1 < len(row_t) else np.inf
        overlap = min(b, end) - max(a, start)
        if overlap > 0.0:
            total += row_u[i] * overlap
    return total / (b - a)


def gt_pose_loop(gt, tau):
    """Ground truth at time tau: bracketing rows found by search, heading on the short arc."""
    i = int(np.nonzero(gt[:, 0] <= tau)[0][-1])
    if gt[i, 0] == tau or i == len(gt) - 1:
        return gt[i, 1:4].copy()
    f = (tau - gt[i, 0]) / (gt[i + 1, 0] - gt[i, 0])
    x = gt[i, 1] + f * (gt[i + 1, 1] - gt[i, 1])
    y = gt[i, 2] + f * (gt[i + 1, 2] - gt[i, 2])
    dtheta = (gt[i + 1, 3] - gt[i, 3] + np.pi) % (2 * np.pi) - np.pi
    return np.array([x, y, wrap(gt[i, 3] + f * dtheta)])


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def raw():
    """Robot 3's files parsed directly."""
    load = lambda name: np.loadtxt(MRCLAM_DIR / name, comments="#", ndmin=2)  # noqa: E731
    barcodes = load("Barcodes.dat").astype(int)
    landmarks = load("Landmark_Groundtruth.dat")
    return {
        "barcode_to_subject": {int(b): int(s) for s, b in barcodes},
        "landmarks": landmarks[np.argsort(landmarks[:, 0])],
        "odometry": load(f"Robot{ROBOT}_Odometry.dat"),
        "groundtruth": load(f"Robot{ROBOT}_Groundtruth.dat"),
        "measurements": load(f"Robot{ROBOT}_Measurement.dat"),
    }


@pytest.fixture(scope="module")
def stream():
    """The plain stream (no corrections): its rows are the file's rows."""
    return load_mrclam(MRCLAM_DIR, ROBOT, dt_s=DT, corrections=False)


@pytest.fixture(scope="module")
def steps(stream):
    return list(stream)


@pytest.fixture(scope="module")
def vp():
    return load_victoria_park(VP_DIR, dt_s=VP_DT)


@pytest.fixture(scope="module")
def vp_steps(vp):
    return list(vp)


@pytest.fixture(scope="module")
def vp_raw():
    load = lambda name: np.loadtxt(VP_DIR / name, ndmin=2)  # noqa: E731
    return {n: load(f"{n}.dat") for n in ("inputs", "measurements", "gps")}


def t0_of(raw):
    return max(raw["odometry"][0, 0], raw["groundtruth"][0, 0])


def raw_rows_by_value(raw):
    """(range, bearing) -> list of [time, subject, used] for each measurement row."""
    table = defaultdict(list)
    for t, code, r, b in raw["measurements"]:
        subject = raw["barcode_to_subject"].get(int(code), -1)
        table[(r, b)].append([t, subject, False])
    return table


# --------------------------------------------------------------------------- MRCLAM
def test_mrclam_observations_are_exactly_the_landmark_rows(raw, stream, steps):
    """Every z row is a distinct landmark row of the file (robot sightings and unknown barcodes
    never reach a filter) and every landmark row inside the stream's span is in z once."""
    landmark_subjects = set(raw["landmarks"][:, 0].astype(int))
    t0 = t0_of(raw)
    table = raw_rows_by_value(raw)
    tol = 1e-6
    for step in steps:
        a, b = t0 + step.t_s - step.dt_s - tol, t0 + step.t_s + tol
        for r, brg in step.z:
            candidates = [
                row for row in table[(r, brg)]
                if not row[2] and a < row[0] <= b and row[1] in landmark_subjects
            ]
            assert candidates, f"z row {(r, brg)} at step {step.index} is not a landmark row"
            candidates[0][2] = True
    t_end = t0 + steps[-1].t_s
    codes = raw["measurements"][:, 1].astype(int)
    subjects = np.array([raw["barcode_to_subject"].get(c, -1) for c in codes])
    t = raw["measurements"][:, 0]
    in_span = (t > t0) & (t <= t_end)
    is_landmark = np.isin(subjects, list(landmark_subjects))
    n_used = sum(row[2] for rows in table.values() for row in rows)
    assert n_used == sum(len(s.z) for s in steps) == int((in_span & is_landmark).sum())
    # the test has teeth: other robots are a good share of the rows (21 % in Dataset 7)
    assert int((in_span & np.isin(subjects, [1, 2, 3, 4, 5])).sum()) > 0.1 * int(in_span.sum())
    assert int((in_span & (subjects < 0)).sum()) > 0
    assert stream.metadata["counts"]["unknown_barcode_rows"] == int((subjects < 0).sum())


@needs_full_data  # gated outliers are rare: the excerpt's minute holds none
def test_mrclam_truth_ids_name_the_barcode_landmark_or_a_gated_outlier(raw, stream, steps):
    """truth id >= 0: landmarks_true[id] is the landmark of the row's barcode and the residual
    is inside the 0.9999 chi-square gate; id -1: the residual is outside the gate."""
    t0 = t0_of(raw)
    table = raw_rows_by_value(raw)
    positions = {int(s): (x, y) for s, x, y, _, _ in raw["landmarks"]}
    sr, sb = stream.sensor.range_std_m, stream.sensor.bearing_std_rad
    gate2 = -2.0 * np.log(1e-4)
    n_outliers = 0
    for step in steps[::3]:
        pose = step.truth.pose
        for (r, brg), lid in zip(step.z, step.truth.landmark_ids, strict=True):
            row = next(
                row for row in table[(r, brg)]
                if abs(row[0] - (t0 + step.t_s)) <= DT + 1e-6 and row[1] in positions
            )
            mx, my = positions[row[1]]
            er = r - np.hypot(mx - pose[0], my - pose[1])
            eb = wrap(brg - (np.arctan2(my - pose[1], mx - pose[0]) - pose[2]))
            d2 = (er / sr) ** 2 + (eb / sb) ** 2
            if lid >= 0:
                np.testing.assert_array_equal(stream.landmarks_true[lid], (mx, my))
                assert d2 <= gate2 * (1 + 1e-9)
            else:
                n_outliers += 1
                assert d2 > gate2 * (1 - 1e-9)
    assert n_outliers > 0


def test_mrclam_robot_sightings_as_clutter_have_truth_minus_one(raw, stream):
    s = load_mrclam(MRCLAM_DIR, ROBOT, dt_s=DT, robot_sightings_as_clutter=True, max_steps=3000,
                    corrections=False)
    landmark_subjects = set(raw["landmarks"][:, 0].astype(int))
    t0 = t0_of(raw)
    table = raw_rows_by_value(raw)
    n_robot = 0
    for step in s:
        for (r, brg), lid in zip(step.z, step.truth.landmark_ids, strict=True):
            a, b = t0 + step.t_s - DT - 1e-6, t0 + step.t_s + 1e-6
            rows = [row for row in table[(r, brg)] if a < row[0] <= b]
            assert rows
            if all(row[1] not in landmark_subjects for row in rows):
                n_robot += 1
                assert lid == -1
    assert n_robot > 0.1 * sum(len(step.z) for step in s)
    assert s.metadata["robot_sightings"] == "clutter"
    assert s.clutter.beta > stream.clutter.beta


def test_mrclam_times_strictly_increasing(stream, steps):
    assert len(steps) == stream.n_steps == len(stream)
    t = np.array([s.t_s for s in steps])
    assert np.all(np.diff(t) > 0.0)
    np.testing.assert_allclose(np.diff(t), DT, atol=1e-9)
    assert [s.index for s in steps] == list(range(len(steps)))
    assert all(s.dt_s == DT and s.compass_rad is None for s in steps)


def test_mrclam_step_odometry_matches_the_rows(raw, steps):
    odo = raw["odometry"]
    t0 = t0_of(raw)
    chosen = {0, 1, len(steps) - 1, 1234, 4321}
    dup = np.nonzero(np.diff(odo[:, 0]) == 0.0)[0]
    gaps = np.nonzero(np.diff(odo[:, 0]) > 0.5)[0]
    assert dup.size and gaps.size
    for i in (*dup[:3], *gaps[:3]):
        chosen.add(int(np.ceil((odo[i, 0] - t0) / DT)) - 1)
    for k in sorted(c for c in chosen if 0 <= c < len(steps)):
        a, b = t0 + k * DT, t0 + (k + 1) * DT
        near = (odo[:, 0] > a - 5.0) & (odo[:, 0] < b + 5.0)
        expected = zoh_mean_loop(odo[near, 0], odo[near, 1:3], a, b)
        np.testing.assert_allclose(steps[k].odometry, expected, atol=1e-9, err_msg=f"step {k}")


def test_mrclam_truth_pose_interpolates_ground_truth(raw, stream, steps):
    gt = raw["groundtruth"]
    t0 = t0_of(raw)
    np.testing.assert_allclose(stream.initial_pose, gt_pose_loop(gt, t0), atol=1e-12)
    for k in (0, 17, len(steps) // 3, len(steps) // 2, len(steps) - 1):
        expected = gt_pose_loop(gt, t0 + (k + 1) * DT)
        got = steps[k].truth.pose
        np.testing.assert_allclose(got[:2], expected[:2], atol=1e-9)
        assert abs(wrap(got[2] - expected[2])) < 1e-9
        assert -np.pi <= got[2] < np.pi


def test_interpolate_poses_takes_the_short_arc_across_pi():
    rows_t = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0.0, 0.0, 3.1], [1.0, 2.0, -3.1], [2.0, 2.0, -3.0]])
    out = interpolate_poses(rows_t, poses, [0.5, 1.0, 1.5, 2.5])
    np.testing.assert_allclose(out[0, :2], [0.5, 1.0])
    assert abs(wrap(out[0, 2] - np.pi)) < 1e-12  # halfway on the short arc, not through 0
    np.testing.assert_allclose(out[1], poses[1])
    assert abs(out[2, 2] - (-3.05)) < 1e-12
    assert np.all(np.isnan(out[3]))


def test_hold_average_with_duplicate_times_and_gaps():
    rows_t = np.array([0.0, 1.0, 1.0, 3.0])
    rows = np.array([[1.0], [5.0], [2.0], [4.0]])  # the second row holds for zero seconds
    got = hold_average(rows_t, rows, np.array([0.0, 0.5, 2.0, 4.0]))
    np.testing.assert_allclose(got[:, 0], [1.0, (0.5 * 1 + 1 * 2) / 1.5, (1 * 2 + 1 * 4) / 2])
    with pytest.raises(ValueError, match="t="):
        hold_average(rows_t, rows, np.array([-1.0, 1.0]))


def test_mrclam_landmarks_and_visibility(raw, stream, steps):
    np.testing.assert_array_equal(stream.landmarks_true, raw["landmarks"][:, 1:3])
    assert stream.metadata["landmark_subjects"] == tuple(range(6, 21))
    sensor = stream.sensor
    for k in (10, len(steps) // 3, len(steps) - 1):
        pose = steps[k].truth.pose
        d = stream.landmarks_true - pose[:2]
        rng = np.hypot(d[:, 0], d[:, 1])
        brg = wrap(np.arctan2(d[:, 1], d[:, 0]) - pose[2])
        expected = np.nonzero((rng <= sensor.max_range_m) & (np.abs(brg) <= sensor.fov_rad / 2))[0]
        np.testing.assert_array_equal(steps[k].truth.visible_ids, expected)
    # the detection rates count the calibration part only
    end = stream.metadata["calibration_end_s"]
    n_visible = sum(len(s.truth.visible_ids) for s in steps if s.t_s <= end + 1e-9)
    assert n_visible == stream.metadata["calibration"]["n_in_view"]


def test_mrclam_models_come_from_the_data(stream):
    cal = stream.metadata["calibration"]
    s = stream.sensor
    assert (s.range_std_m, s.bearing_std_rad) == (cal["range_std_m"], cal["bearing_std_rad"])
    assert (s.max_range_m, s.fov_rad) == (cal["max_range_m"], cal["fov_rad"])
    assert 0.8 < s.fov_rad < 1.4  # the camera sees about +-0.6 rad
    assert 5.0 < s.max_range_m < 9.0
    assert 0.0 < stream.clutter.alpha < 1.0 and 0.0 < stream.clutter.beta < 0.05
    assert stream.clutter.alpha == cal["alpha"]
    noise = stream.odometry_noise
    assert noise.v_fraction == cal["odometry_v_fraction"]
    assert noise.omega_floor_radps == cal["odometry_omega_floor_radps"] >= 1e-3
    assert stream.metadata["known_association"] is False
    assert load_mrclam(MRCLAM_DIR, ROBOT, known_association=True, max_steps=5).metadata[
        "known_association"
    ]


def test_mrclam_is_deterministic(steps):
    again = list(load_mrclam(MRCLAM_DIR, ROBOT, dt_s=DT, max_steps=800, corrections=False))
    for a, b in zip(steps[:800], again, strict=True):
        np.testing.assert_array_equal(a.odometry, b.odometry)
        np.testing.assert_array_equal(a.z, b.z)
        np.testing.assert_array_equal(a.truth.pose, b.truth.pose)
        np.testing.assert_array_equal(a.truth.landmark_ids, b.truth.landmark_ids)


def test_mrclam_bad_arguments_name_the_field(tmp_path):
    with pytest.raises(ValueError, match="robot=6"):
        load_mrclam(MRCLAM_DIR, 6)
    with pytest.raises(ValueError, match="dt_s=0"):
        load_mrclam(MRCLAM_DIR, 1, dt_s=0.0)
    with pytest.raises(ValueError, match="directory="):
        load_mrclam(tmp_path / "missing", 1)
    with pytest.raises(ValueError, match="directory="):
        load_mrclam(tmp_path, 1)
    with pytest.raises(ValueError, match="max_steps=0"):
        load_mrclam(MRCLAM_DIR, 1, max_steps=0)


# --------------------------------------------------------------------------- estimators
def test_estimate_sensor_noise_recovers_synthetic_noise_and_outliers():
    rng = np.random.default_rng(7)
    n, n_bad = 6000, 120
    e = rng.normal(size=(n, 2)) * [0.15, 0.012]
    bad = rng.choice(n, n_bad, replace=False)
    gross = rng.uniform(-1, 1, size=(n_bad, 2)) * [4.0, 1.5]
    e[bad] = gross + np.sign(gross) * [1.0, 0.2]  # at least 1 m or 0.2 rad off
    est = estimate_sensor_noise(e, gate_probability=0.9999)
    assert abs(est.range_std_m / 0.15 - 1) < 0.05
    assert abs(est.bearing_std_rad / 0.012 - 1) < 0.05
    assert np.all(~est.inlier[bad])
    assert est.n_outliers - n_bad < 0.002 * n
    with pytest.raises(ValueError, match="residuals"):
        estimate_sensor_noise(np.zeros((5, 3)))


def _synthetic_odometry(seed, T=1200.0, dt=0.1, fv=0.3, flv=0.01, fw=0.4, flw=0.05):
    """Exact unicycle ground truth under piecewise-constant controls, noisy odometry rows."""
    rng = np.random.default_rng(seed)
    n, seg = int(round(T / dt)), int(round(5.0 / dt))
    v = np.repeat(rng.choice([0.0, 0.08, 0.2], n // seg + 1), seg)[:n]
    w = np.repeat(rng.choice([-0.3, 0.0, 0.3], n // seg + 1), seg)[:n]
    theta = np.concatenate([[0.0], np.cumsum(w * dt)])
    mid = theta[:-1] + 0.5 * w * dt
    chord = v * dt * np.sinc(0.5 * w * dt / np.pi)
    x = np.concatenate([[0.0], np.cumsum(chord * np.cos(mid))])
    y = np.concatenate([[0.0], np.cumsum(chord * np.sin(mid))])
    gt = np.column_stack([dt * np.arange(n + 1), x, y, wrap(theta)])
    std = np.column_stack([np.hypot(fv * v, flv), np.hypot(fw * w, flw)])
    measured = np.column_stack([v, w]) + std * rng.normal(size=(n, 2))
    odo = np.column_stack([dt * np.arange(n), measured])
    return odo, gt


def test_estimate_odometry_noise_recovers_synthetic_noise():
    odo, gt = _synthetic_odometry(3)
    est = estimate_odometry_noise(odo, gt, 0.0, odo[-1, 0], dt_s=0.1, window_s=1.0)
    model = est.model()
    expected = [np.hypot(0.3 * 0.2, 0.01), np.hypot(0.4 * 0.3, 0.05)]
    np.testing.assert_allclose(model.std([0.2, 0.3]), expected, rtol=0.15)
    np.testing.assert_allclose(model.std([0.0, 0.0]), [0.01, 0.05], rtol=0.6)
    assert abs(est.v_bias_mps) < 0.01 and abs(est.omega_bias_radps) < 0.02
    # white errors: the loader's 10 s window finds the same per-step noise (120 windows here)
    est10 = estimate_odometry_noise(odo, gt, 0.0, odo[-1, 0], dt_s=0.1, window_s=10.0)
    np.testing.assert_allclose(est10.model().std([0.2, 0.3]), expected, rtol=0.2)


def test_true_velocities_over_long_windows_follow_the_path():
    """Over 10 s windows that hold turns of 0.3 rad/s for 5 s, the mean true (v, omega) summed over
    0.1 s parts is the mean of the exact controls; one arc per window (the chord through a
    varying turn) misreads the speed by centimetres per second."""
    odo, gt = _synthetic_odometry(3, T=600.0, fv=0.0, flv=0.0, fw=0.0, flw=0.0)
    grid = np.arange(0.0, 590.0, 10.0)
    exact = hold_average(odo[:, 0], odo[:, 1:3], grid)
    fine = true_velocities(gt[:, 0], gt[:, 1:4], grid, sub_steps=100)
    np.testing.assert_allclose(fine, exact, atol=1e-9)
    coarse = true_velocities(gt[:, 0], gt[:, 1:4], grid)
    assert np.abs(coarse[:, 0] - exact[:, 0]).max() > 0.03
    with pytest.raises(ValueError, match="sub_steps"):
        true_velocities(gt[:, 0], gt[:, 1:4], grid, sub_steps=2.5)


@pytest.mark.parametrize("window_s", [1.0, 10.0])
def test_estimate_odometry_noise_matches_correlated_error_growth_over_its_window(window_s):
    """Odometry errors constant over each 5 s (std 0.01 m/s, 0.03 rad/s) plus a little white
    noise: the fitted per-step std is the white noise whose mean over one window has the
    errors' variance, n sigma_w^2 with sigma_w^2 = sigma^2 (one block per 1 s window) or
    sigma^2 / 2 (two blocks per 10 s window), so the 10 s window's std is sqrt(5) times the 1 s
    window's: a filter given the 1 s fit under-states the error growth over a 10 s local map."""
    odo, gt = _synthetic_odometry(3, fv=0.0, flv=0.0, fw=0.0, flw=0.0)
    rng = np.random.default_rng(7)
    n, seg = len(odo), 50
    block_std = np.array([0.01, 0.03])
    blocks = np.repeat(rng.normal(size=(n // seg + 1, 2)) * block_std, seg, axis=0)[:n]
    odo[:, 1:3] += blocks + rng.normal(size=(n, 2)) * [0.002, 0.005]
    est = estimate_odometry_noise(odo, gt, 0.0, odo[-1, 0], dt_s=0.1, window_s=window_s)
    steps_per_window = window_s / 0.1
    blocks_per_window = max(1.0, window_s / 5.0)
    expected = block_std * np.sqrt(steps_per_window / blocks_per_window)
    fitted = np.sqrt(np.mean(est.model().std(odo[:, 1:3]) ** 2, axis=0))
    np.testing.assert_allclose(fitted, expected, rtol=0.2)


def test_compensate_motion_hand_computed():
    # straight at 1 m/s for 0.5 s: a landmark 5 m ahead is 4.5 m ahead at the step's end
    np.testing.assert_allclose(compensate_motion([[5.0, 0.0]], [[1.0, 0.0]], [0.5]), [[4.5, 0.0]])
    # turning on the spot at 1 rad/s for 0.1 s: bearings decrease by 0.1 rad, ranges unchanged
    np.testing.assert_allclose(
        compensate_motion([[2.0, 0.3], [3.0, -0.2]], [[0.0, 1.0]] * 2, [0.1, 0.1]),
        [[2.0, 0.2], [3.0, -0.3]],
    )
    # no time left to the step's end: unchanged; and the general case against motion()
    z, u, tau = np.array([[4.0, 0.5]]), np.array([[0.3, -0.6]]), np.array([0.07])
    np.testing.assert_allclose(compensate_motion(z, u, [0.0]), z)
    end = motion(np.zeros(3), u[0], tau[0])
    point = z[0, 0] * np.array([np.cos(z[0, 1]), np.sin(z[0, 1])])
    rel = point - end[:2]
    expected = [np.hypot(*rel), wrap(np.arctan2(rel[1], rel[0]) - end[2])]
    np.testing.assert_allclose(compensate_motion(z, u, tau)[0], expected)


def test_estimate_sensor_bias_recovers_synthetic_camera_errors():
    rng = np.random.default_rng(5)
    z = np.column_stack([rng.uniform(1.0, 7.0, 4000), rng.uniform(-0.55, 0.55, 4000)])
    c, d = (0.2, -0.03, 0.05, -1.8), (-0.01, 0.02)
    e = np.column_stack([
        c[0] + c[1] * z[:, 0] + c[2] * z[:, 1] + c[3] * z[:, 1] ** 2,
        d[0] + d[1] * z[:, 1],
    ]) + rng.normal(size=z.shape) * [0.05, 0.01]
    model = estimate_sensor_bias(z, e)
    np.testing.assert_allclose(model.range_coef, c, atol=0.02)
    np.testing.assert_allclose(model.bearing_coef, d, atol=0.002)
    corrected = model.correct(z) - (z - e)  # the residuals after the correction
    np.testing.assert_allclose(np.sqrt(np.mean(corrected**2, axis=0)), [0.05, 0.01], rtol=0.05)
    with pytest.raises(ValueError, match="residuals"):
        estimate_sensor_bias(z, e[:10])


def test_correlated_noise_std_white_and_correlated_errors():
    rng = np.random.default_rng(6)
    t = np.tile(np.arange(0.0, 600.0, 0.25), 3)  # 3 landmarks, a sighting every 0.25 s
    groups = np.repeat([0, 1, 2], len(t) // 3)
    white = rng.normal(size=(len(t), 2)) * [0.1, 0.01]
    for window in (0.1, 2.0, 10.0):  # white errors: the std itself, whatever the window
        np.testing.assert_allclose(
            correlated_noise_std(white, t, groups, window), [0.1, 0.01], rtol=0.1
        )
    # an error constant over each 2 s (8 sightings): its window means are not averaged down,
    # so the white-noise equivalent std is sqrt(8) times the std of one sighting
    blocks = np.floor(t / 2.0).astype(int) + 1000 * groups
    _, inverse = np.unique(blocks, return_inverse=True)
    held = (rng.normal(size=(inverse.max() + 1, 2)) * [0.1, 0.01])[inverse]
    np.testing.assert_allclose(
        correlated_noise_std(held, t, groups, 2.0), np.sqrt(8) * np.array([0.1, 0.01]),
        rtol=0.1,
    )
    np.testing.assert_allclose(correlated_noise_std(held, t, groups, 0.1), [0.1, 0.01], rtol=0.1)


def test_mrclam_sensor_calibration_options(raw, stream):
    """Bias-corrected, motion-compensated stream: the noise is re-estimated on the corrected
    residuals (smaller), the observations are the raw rows moved and corrected, the truth ids
    and steps are those of the plain stream."""
    cal = load_mrclam(MRCLAM_DIR, ROBOT, dt_s=DT, corrections=False, motion_compensation=True,
                      sensor_bias_correction=True, noise_window_s=2.0, max_steps=3000)
    meta = cal.metadata["calibration"]
    plain = stream.metadata["calibration"]
    assert cal.metadata["motion_compensation"] and cal.metadata["sensor_bias_correction"]
    assert meta["range_std_m"] < 0.5 * plain["range_std_m"]  # the b^2 term dominates
    assert meta["bearing_std_rad"] < plain["bearing_std_rad"]
    assert meta["range_bias_c3"] < -1.0  # ranges read long at the image centre
    # the filters' std by the white-noise rule over 2 s is larger than the white root mean
    # square (the errors of successive sightings are correlated)
    assert cal.sensor.range_std_m == meta["filter_range_std_m"] > meta["range_std_m"]
    assert cal.sensor.bearing_std_rad == meta["filter_bearing_std_rad"] > meta["bearing_std_rad"]
    c = [meta[f"range_bias_c{i}"] for i in range(4)]
    d = [meta[f"bearing_bias_d{i}"] for i in range(2)]
    # every observation: the raw row moved to its step's end with the step's odometry, then
    # corrected by the fitted bias
    t0 = t0_of(raw)
    by_value = raw_rows_by_value(raw)
    plain_steps = list(load_mrclam(MRCLAM_DIR, ROBOT, dt_s=DT, max_steps=3000,
                                   corrections=False))
    checked = 0
    for step, ref in zip(cal, plain_steps, strict=True):
        assert len(step.z) == len(ref.z)
        for z_cal, z_raw in zip(step.z, ref.z, strict=True):
            times = [t - t0 for t, _, _ in by_value[(z_raw[0], z_raw[1])]
                     if step.t_s - DT < t - t0 <= step.t_s + 1e-9]
            tau = step.t_s - times[0]
            moved = compensate_motion([z_raw], [step.odometry], [tau])[0]
            r, b = moved
            expected = [r - (c[0] + c[1] * r + c[2] * b + c[3] * b * b), b - (d[0] + d[1] * b)]
            np.testing.assert_allclose(z_cal, expected, rtol=0, atol=1e-6)  # Unix-time round-off
            checked += 1
        if checked > 200:
            break
    assert checked > 200


# --------------------------------------------------------------------------- Victoria Park
def test_vp_geometry_from_info_txt():
    g = read_geometry(VP_DIR / "info.txt")
    assert (g.a_m, g.b_m, g.h_m, g.l_m) == (0.95, 0.5, 0.76, 2.83)
    np.testing.assert_allclose(g.laser_xy, [3.78, 0.5])


def test_vp_bearing_convention_and_offset_hand_computed():
    g = VehicleGeometry()
    z = laser_to_vehicle([10.0, 10.0, 10.0], [np.pi / 2, 0.0, np.pi], g)
    np.testing.assert_allclose(z[0], [np.hypot(13.78, 0.5), np.arctan2(0.5, 13.78)])  # ahead
    np.testing.assert_allclose(z[1], [np.hypot(3.78, 9.5), -np.arctan2(9.5, 3.78)])  # right
    np.testing.assert_allclose(z[2], [np.hypot(3.78, 10.5), np.arctan2(10.5, 3.78)])  # left


def test_vp_stream_rows_are_the_transformed_file_rows(vp, vp_steps, vp_raw):
    m = vp_raw["measurements"]
    t0 = vp_raw["inputs"][0, 0]
    assert vp.metadata["t0_s"] == t0
    expected = []
    for t, r, b, _ in m:
        beta = b - np.pi / 2
        x, y = 2.83 + 0.95 + r * np.cos(beta), 0.5 + r * np.sin(beta)
        if t0 < t <= t0 + vp_steps[-1].t_s and np.hypot(x, y) <= 30.0:
            expected.append((t, np.hypot(x, y), np.arctan2(y, x)))
    expected = np.array(expected)
    got = np.array([(s.t_s, *zz) for s in vp_steps for zz in s.z])
    assert got.shape == expected.shape
    np.testing.assert_allclose(got[:, 1:], expected[:, 1:], atol=1e-12)
    lag = t0 + got[:, 0] - expected[:, 0]  # a row is used at the end of its step
    assert np.all((lag >= -1e-9) & (lag < VP_DT + 1e-9))
    assert np.all(np.abs(got[:, 2]) < np.pi / 2)


def test_vp_step_odometry_is_the_ackermann_rear_axle_velocity(vp_steps, vp_raw):
    inp = vp_raw["inputs"]
    t0 = inp[0, 0]
    turning = np.nonzero((np.abs(inp[:, 2]) > 0.2) & (inp[:, 1] > 2.0))[0]
    assert turning.size
    for k in (0, len(vp_steps) // 2, int(turning[0]), int(turning[len(turning) // 2]),
              len(vp_steps) - 1):
        a, b = t0 + k * VP_DT, t0 + (k + 1) * VP_DT
        near = np.nonzero((inp[:, 0] > a - 1.0) & (inp[:, 0] < b + 1.0))[0]
        u = []
        for i in near:
            v_c = inp[i, 1] / (1.0 - np.tan(inp[i, 2]) * 0.76 / 2.83)
            u.append((v_c, v_c * np.tan(inp[i, 2]) / 2.83))
        expected = zoh_mean_loop(inp[near, 0], np.array(u), a, b)
        np.testing.assert_allclose(vp_steps[k].odometry, expected, atol=1e-9, err_msg=f"step {k}")


def test_vp_has_no_truth_but_gps_in_metadata(vp, vp_steps, vp_raw):
    assert vp.landmarks_true.shape == (0, 2)
    assert all(np.all(np.isnan(s.truth.pose)) for s in vp_steps[::97])
    ids = np.concatenate([s.truth.landmark_ids for s in vp_steps])
    # most detections are kept (the loader drops those beyond the laser's 30 m)
    assert ids.size > 0.5 * len(vp_raw["measurements"]) and np.all(ids == UNKNOWN_LANDMARK_ID)
    gps = vp.metadata["gps"]
    np.testing.assert_allclose(gps[:, 1:], vp_raw["gps"][:, 1:])
    np.testing.assert_allclose(gps[:, 0], vp_raw["gps"][:, 0] - vp_raw["inputs"][0, 0])
    t = np.array([s.t_s for s in vp_steps])
    assert np.all(np.diff(t) > 0.0) and len(vp_steps) == vp.n_steps
    duration = vp_raw["inputs"][-1, 0] - vp_raw["inputs"][0, 0]
    assert vp.n_steps == int(np.floor(duration / VP_DT + 1e-9))
    assert vp.sensor.max_range_m == 30.0 and vp.sensor.fov_rad == np.pi
    assert 0.0 < vp.clutter.beta < vp.clutter.alpha < 1.0


def test_vp_bearings_turn_with_the_odometry(vp, vp_steps):
    """Dead-reckoned over 1-4 s, detections of the same trees coincide: the bearing sign and the
    steering sign agree. Mirroring the bearings breaks it."""
    n = int(300.0 / VP_DT)
    pose = vp.initial_pose.copy()
    world, world_mirrored, scan_t = [], [], []
    for s in vp_steps[:n]:
        pose = motion(pose, s.odometry, s.dt_s)
        for sign, out in ((1.0, world), (-1.0, world_mirrored)):
            a = pose[2] + sign * s.z[:, 1]
            r = s.z[:, 0]
            out.append(np.column_stack([pose[0] + r * np.cos(a), pose[1] + r * np.sin(a)]))
        scan_t.append(np.full(len(s.z), s.t_s))
    t = np.concatenate(scan_t)

    def median_gap(points):
        points = np.concatenate(points)
        gaps = []
        for t_scan in np.unique(t)[::10]:
            later = (t > t_scan + 1.0) & (t <= t_scan + 4.0)
            if later.any():
                gaps.append(cKDTree(points[later]).query(points[t == t_scan])[0])
        return float(np.median(np.concatenate(gaps)))

    good, mirrored = median_gap(world), median_gap(world_mirrored)
    assert good < 0.5 and mirrored > 3.0 * good


def test_vp_bad_arguments_name_the_field(tmp_path):
    with pytest.raises(ValueError, match="max_range_m=-1"):
        load_victoria_park(VP_DIR, max_range_m=-1.0)
    with pytest.raises(ValueError, match="directory="):
        load_victoria_park(tmp_path)


# --------------------------------------------------------------------------- alignment
@pytest.mark.parametrize("angle", [0.0, 0.7, -2.5, 3.1])
def test_fit_se2_recovers_a_known_transform_exactly(angle):
    rng = np.random.default_rng(11)
    e = rng.uniform(-50, 50, size=(40, 2))
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    t = np.array([3.0, -7.5])
    R_fit, t_fit = fit_se2(e, e @ R.T + t)
    np.testing.assert_allclose(R_fit, R, atol=1e-12)
    np.testing.assert_allclose(t_fit, t, atol=1e-10)
    assert abs(np.linalg.det(R_fit) - 1.0) < 1e-12


def test_fit_se2_is_the_least_squares_optimum():
    rng = np.random.default_rng(5)
    e = rng.uniform(-10, 10, size=(30, 2))
    R = np.array([[0.0, -1.0], [1.0, 0.0]])
    r = e @ R.T + [1.0, 2.0] + rng.normal(scale=0.3, size=e.shape)
    R_fit, t_fit = fit_se2(e, r)
    best = np.sum((e @ R_fit.T + t_fit - r) ** 2)
    for d in (0.01, -0.01):
        c, s = np.cos(d), np.sin(d)
        Rd = R_fit @ np.array([[c, -s], [s, c]])
        td = r.mean(0) - Rd @ e.mean(0)
        assert best < np.sum((e @ Rd.T + td - r) ** 2)
    assert best < np.sum((e @ R.T + [1.0, 2.0] - r) ** 2)
    with pytest.raises(ValueError, match="reference_xy"):
        fit_se2(e, r[:-1])


def test_path_error_after_alignment():
    ref_t = np.arange(0.0, 61.0, 1.0)
    ref_xy = np.column_stack([np.cos(ref_t / 10.0) * 20, ref_t * 0.5])
    est_t = np.arange(0.0, 50.25, 0.25)  # contains every reference time up to 50 s
    est_ref = np.column_stack(
        [np.interp(est_t, ref_t, ref_xy[:, 0]), np.interp(est_t, ref_t, ref_xy[:, 1])]
    )
    c, s = np.cos(1.2), np.sin(1.2)
    R = np.array([[c, -s], [s, c]])
    est_xy = (est_ref - [4.0, 1.0]) @ R  # the reference seen in another frame
    out = path_error_after_alignment(est_t, est_xy, ref_t, ref_xy)
    assert out.rmse_m < 1e-9
    np.testing.assert_array_equal(out.t_s, ref_t[ref_t <= 50.0])
    np.testing.assert_allclose(out.aligned_xy, ref_xy[:51], atol=1e-9)
    np.testing.assert_allclose(out.aligned_path_xy, est_ref, atol=1e-9)
    bent = est_xy.copy()
    bent[est_t == 20.0] += [3.0, 0.0]
    assert path_error_after_alignment(est_t, bent, ref_t, ref_xy).rmse_m > 0.1
    with pytest.raises(ValueError, match="ref_t"):
        path_error_after_alignment(est_t, est_xy, ref_t + 100.0, ref_xy)


# --------------------------------------------------------------------------- MRCLAM calibration
# A recording written by the simulator in MRCLAM's format (tests/slam_gym/mrclam_sim.py), with
# known noise and known systematic errors of the size measured on Dataset 7 (odometry 0.2 s
# late and reading fast, more so in turns, measurements stamped 0.05 s late, ranges 0.2 m long
# at the image centre and short at its edges).
SIM_ERRORS = {
    "odometry_delay_s": 0.2, "v_gain": 0.95, "v_turn_s_per_rad": 0.5, "omega_gain": 0.93,
    "measurement_delay_s": -0.05,
    "range_bias": (0.2, -1.8), "bearing_bias_rad": 0.01,
}


def test_mrclam_calibration_recovers_simulated_noise_and_errors(tmp_path):
    """Tolerances: delays within 0.03 s (the simulated robot turns only now and then, and the
    truth is logged at 10 Hz); gains within 3 %, the slow-down in turns within 0.15 s/rad;
    camera bias within 0.04 m (c0), 0.15 m/rad^2 (c3), 0.003 rad (d0); the white noise std,
    once the bias is removed, within 10 %; the odometry noise within 25 %."""
    from mrclam_sim import write_simulated_mrclam

    truth = write_simulated_mrclam(tmp_path, **SIM_ERRORS)
    stream = load_mrclam(tmp_path, 1)
    cal = stream.metadata["calibration"]
    assert cal["calibration_s"] == 300.0
    assert stream.metadata["calibration_end_s"] == pytest.approx(300.0, abs=0.5)
    assert abs(cal["odometry_delay_s"] - SIM_ERRORS["odometry_delay_s"]) <= 0.03
    assert abs(cal["measurement_delay_s"] - SIM_ERRORS["measurement_delay_s"]) <= 0.03
    assert cal["odometry_v_gain"] == pytest.approx(SIM_ERRORS["v_gain"], rel=0.03)
    assert cal["odometry_v_turn_s_per_rad"] == pytest.approx(0.5, abs=0.15)
    assert cal["odometry_omega_gain"] == pytest.approx(SIM_ERRORS["omega_gain"], rel=0.03)
    assert cal["range_bias_c0"] == pytest.approx(0.2, abs=0.04)
    assert cal["range_bias_c3"] == pytest.approx(-1.8, abs=0.15)
    assert cal["bearing_bias_d0"] == pytest.approx(0.01, abs=0.003)
    assert cal["range_std_m"] == pytest.approx(truth["range_std_m"], rel=0.1)
    assert cal["bearing_std_rad"] == pytest.approx(truth["bearing_std_rad"], rel=0.1)
    assert stream.sensor.range_std_m == cal["filter_range_std_m"]
    # the filters' std (the white-noise rule over one pass, 15-40 s here: 100-400 sightings)
    # is at least the white std and grows with any error shared by a pass: one pass's mean
    # error of 1/sqrt(n) of the std doubles its variance; the simulated passes keep a few
    # millimetres of such error (the camera bias fitted over 300 s does not match each pass)
    for std, key in (("range_std_m", "filter_range_std_m"),
                     ("bearing_std_rad", "filter_bearing_std_rad")):
        assert 0.9 * truth[std] <= cal[key] <= 1.8 * truth[std]
    # odometry noise at the simulated speed (constant: fraction and floor are not separable).
    # The simulated errors are white, so any window recovers them; over 1 s windows (300 of
    # them) within 25 %. The default 10 s window (30 windows) also counts the residual of the
    # corrections (the delay is found 0.01 s off) that grows over a window: at least the white
    # noise, and not more than half as much again.
    v = truth["speed_mps"]
    one_second = load_mrclam(tmp_path, 1, odometry_window_s=1.0).metadata["calibration"]
    for c, low, high in ((one_second, 0.75, 1.25), (cal, 0.9, 1.5)):
        v_std = np.hypot(c["odometry_v_fraction"] * v, c["odometry_v_floor_mps"])
        assert low * truth["v_noise_fraction"] * v <= v_std <= high * truth["v_noise_fraction"] * v
        omega_fraction = c["odometry_omega_fraction"]
        assert low * truth["omega_noise_fraction"] <= omega_fraction <= (
            high * truth["omega_noise_fraction"])
    # the public calibration entry point gives the stream's numbers
    assert calibrate_mrclam(read_mrclam(tmp_path, 1)).as_dict() == cal
    # without corrections the bias stays in the noise (the filters would see 0.2 m range std)
    plain = load_mrclam(tmp_path, 1, corrections=False).metadata["calibration"]
    assert plain["range_std_m"] > 1.5 * truth["range_std_m"]
    assert plain.get("odometry_delay_s") is None and plain["measurement_delay_s"] is None


def test_mrclam_calibration_reads_nothing_after_its_part(tmp_path):
    """A different camera bias after 300 s changes the stream but not one calibrated number;
    calibrating on the whole recording does see it."""
    from mrclam_sim import write_simulated_mrclam

    same = write_simulated_mrclam(tmp_path / "a", **SIM_ERRORS)
    write_simulated_mrclam(tmp_path / "b", **SIM_ERRORS, bias_after_s=300.0,
                           range_bias_after=(-0.3, 1.0))
    a, b = load_mrclam(tmp_path / "a", 1), load_mrclam(tmp_path / "b", 1)
    assert a.metadata["calibration"] == b.metadata["calibration"]
    assert a.sensor == b.sensor and a.odometry_noise == b.odometry_noise
    assert len(a) == len(b) == same["n_steps"] - 1
    late = [k for k in range(len(a)) if a.make_steps.t_s[k + 1] > 310.0]
    assert not np.allclose(a.make_steps.z[a.make_steps.bounds[late[0]]:],
                           b.make_steps.z[b.make_steps.bounds[late[0]]:])
    whole_a = load_mrclam(tmp_path / "a", 1, calibration_s=None).metadata["calibration"]
    whole_b = load_mrclam(tmp_path / "b", 1, calibration_s=None).metadata["calibration"]
    assert whole_a["range_std_m"] < whole_b["range_std_m"]


def test_mrclam_calibration_options_name_the_field(tmp_path):
    from mrclam_sim import write_simulated_mrclam

    write_simulated_mrclam(tmp_path)
    for kwargs, field in (({"calibration_s": 5.0}, "calibration_s"),
                          ({"corrections": 1}, "corrections"),
                          ({"odometry_correction": "yes"}, "odometry_correction"),
                          ({"noise_window_s": 0.0}, "noise_window_s")):
        with pytest.raises(ValueError, match=field):
            load_mrclam(tmp_path, 1, **kwargs)


def test_short_calibration_part_shortens_the_odometry_window_and_says_so(caplog):
    """10 s of calibration hold one 10 s window: the odometry noise is fitted over four windows
    of (at most) 2.5 s instead, whole steps, reported in the calibration and logged (not an
    error)."""
    import logging

    with caplog.at_level(logging.WARNING, logger="slam_gym.datasets.mrclam"):
        stream = load_mrclam(MRCLAM_DIR, 1, max_steps=200, calibration_s=10.0)
    window = stream.metadata["calibration"]["odometry_window_s"]
    assert 2.0 <= window <= 2.5 and round(window / 0.1, 9) == round(window / 0.1)
    assert f"odometry noise fitted over {window:g} s windows" in caplog.text
    assert load_mrclam(MRCLAM_DIR, 1, max_steps=200).metadata["calibration"][
        "odometry_window_s"] == 10.0


def test_the_mrclam_options_object_validates_once_for_every_user():
    """One validated options object (issue 37 item 2): the loader, the calibration, the env and
    ``reproduce mrclam`` build it, so a bad value names the field the user wrote."""
    from slam_gym.datasets.mrclam import CORRECTION_SWITCHES, MrclamOptions

    defaults = MrclamOptions()
    assert defaults.switches() == dict.fromkeys(CORRECTION_SWITCHES, True)
    off = MrclamOptions(corrections=False, timing_correction=True)
    assert off.switches() == {**dict.fromkeys(CORRECTION_SWITCHES, False),
                              "timing_correction": True}
    assert set(defaults.as_kwargs()) == {"calibration_s", "corrections", "noise_window_s",
                                         *CORRECTION_SWITCHES}
    for kwargs, field in (({"calibration_s": 5.0}, "calibration_s"),
                          ({"corrections": 1}, "corrections"),
                          ({"correlated_noise": "yes"}, "correlated_noise"),
                          ({"noise_window_s": 0.0}, "noise_window_s")):
        with pytest.raises(ValueError, match=f"^{field}="):
            MrclamOptions(**kwargs)
    with pytest.raises(ValueError, match="^sensor_noise_window_s="):
        MrclamOptions(noise_window_s=-1.0, names={"noise_window_s": "sensor_noise_window_s"})
