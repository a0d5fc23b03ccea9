"""The navigation EKF converges, tracks a boat, and carries its uncertainty through outages."""

from __future__ import annotations

import math

import numpy as np

from mapping.geo import LocalFrame
from mapping.navigation import estimate_at, prepare_inputs
from mapping.samples import AttitudeSample, GnssFix, GnssFixType, HeadingSample, ImuSample

LAT0, LON0 = 38.6, -76.1


def boat_run(seed: int, duration: float = 120.0, gps_outage: tuple[float, float] | None = None):
    """A boat doing a slow S-curve at ~1 m/s: truth and the sensor samples it gives."""
    rng = np.random.default_rng(seed)
    frame = LocalFrame.around(LAT0, LON0)
    dt = 1.0 / 55.0
    t = np.arange(0.0, duration, dt)
    speed = 1.0 + 0.2 * np.sin(2 * np.pi * t / 40.0)
    yaw_rate = 0.12 * np.sin(2 * np.pi * t / 60.0)
    heading = 0.5 + np.cumsum(yaw_rate) * dt
    ve, vn = speed * np.sin(heading), speed * np.cos(heading)
    x, y = np.cumsum(ve) * dt, np.cumsum(vn) * dt
    accel_fwd = np.gradient(speed, dt)
    accel_stbd = speed * yaw_rate  # centripetal, to starboard when turning right
    roll = 0.03 * np.sin(2 * np.pi * t / 3.0)
    pitch = 0.02 * np.sin(2 * np.pi * t / 4.0 + 1.0)
    t0 = 1.7e9
    imu, attitude = [], []
    bias_gyro, bias_acc = 0.004, (0.05, -0.03)
    for k in range(t.size):
        # Specific force in FRD with gravity through roll and pitch (small-angle body axes).
        sr, cr, sp, cp = (
            math.sin(roll[k]),
            math.cos(roll[k]),
            math.sin(pitch[k]),
            math.cos(pitch[k]),
        )
        a_level = np.array([accel_fwd[k], accel_stbd[k], -9.80665])
        # level -> body: (R_y(pitch) R_x(roll))^T
        ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        f = (ry @ rx).T @ a_level
        imu.append(
            ImuSample(
                t0 + t[k],
                (
                    f[0] + bias_acc[0] + rng.normal(0, 0.05),
                    f[1] + bias_acc[1] + rng.normal(0, 0.05),
                    f[2],
                ),
                (0.0, 0.0, yaw_rate[k] / cr + bias_gyro + rng.normal(0, 0.005)),
            )
        )
        if k % 11 == 0:
            attitude.append(AttitudeSample(t0 + t[k], roll[k], pitch[k], heading[k]))
    gnss, headings = [], []
    for k in range(0, t.size, 27):  # ~2 Hz
        if gps_outage and gps_outage[0] <= t[k] < gps_outage[1]:
            continue
        lat, lon = frame.to_latlon(x[k] + rng.normal(0, 0.3), y[k] + rng.normal(0, 0.3))
        course = frame.grid_to_true(math.atan2(ve[k], vn[k]), float(lat), float(lon))
        gnss.append(
            GnssFix(
                t0 + t[k],
                float(lat),
                float(lon),
                0.0,
                GnssFixType.FIX_3D,
                12,
                0.5,
                0.9,
                speed[k] + rng.normal(0, 0.05),
                course,
            )
        )
        true_heading = frame.grid_to_true(heading[k] + rng.normal(0, 0.02), float(lat), float(lon))
        headings.append(HeadingSample(t0 + t[k] + 0.01, true_heading))
    return (
        frame,
        t0 + t,
        np.column_stack([x, y, heading % (2 * math.pi)]),
        imu,
        gnss,
        headings,
        attitude,
    )


def heading_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * (a - b)))


def test_ekf_converges_and_tracks_a_boat() -> None:
    frame, times, truth, imu, gnss, headings, attitude = boat_run(1)
    inputs = prepare_inputs(frame, imu, gnss, headings, attitude)
    query = times[200::50]
    truth_q = truth[200::50]
    for smooth in (False, True):
        est = estimate_at(inputs, query, smooth=smooth)
        assert est.valid.all()
        settled = slice(10, None)  # after the first ~45 s
        pos_err = np.linalg.norm(est.poses[settled, :2] - truth_q[settled, :2], axis=1)
        assert np.sqrt(np.mean(pos_err**2)) < 0.25  # GPS noise is 0.3 m per axis
        head_err = heading_error(est.poses[settled, 2], truth_q[settled, 2])
        assert np.degrees(np.sqrt(np.mean(head_err**2))) < 1.0  # compass noise 1.1 deg


def test_gps_outage_dead_reckons_and_grows_the_covariance() -> None:
    frame, times, truth, imu, gnss, headings, attitude = boat_run(2, gps_outage=(60.0, 80.0))
    inputs = prepare_inputs(frame, imu, gnss, headings, attitude)
    before = times[(55 * 55)]
    inside = times[(78 * 55)]
    est = estimate_at(inputs, [before, inside], smooth=False)
    sigma = np.sqrt(est.covariances[:, 0, 0] + est.covariances[:, 1, 1])
    assert sigma[1] > 2 * sigma[0]
    k = 78 * 55
    # 18 s of dead reckoning on IMU and compass stays within a few metres.
    assert np.linalg.norm(est.poses[1, :2] - truth[k, :2]) < 3.0


def test_priors_weigh_less_where_the_filter_is_unsure() -> None:
    frame, times, _truth, imu, gnss, headings, attitude = boat_run(3, gps_outage=(60.0, 80.0))
    inputs = prepare_inputs(frame, imu, gnss, headings, attitude)
    query = times[::55]  # once a second
    est = estimate_at(inputs, query)
    weights = est.prior_weights()
    t = query - times[0]
    inside = (t > 66) & (t < 74)
    normal = (t > 20) & (t < 55)
    assert weights[normal, 0].mean() > 0.8
    assert weights[inside, 0].max() < 0.5 * weights[normal, 0].mean()
    assert np.all((weights >= 0) & (weights <= 1))
