"""The sensor error models over long synthetic runs: the GNSS error's correlation time,
size and white part, the compass's bias and deviation, the magnetometer, the gyro bias."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tools.sim import resolve_scenario
from tools.sim.fieldday import draw_field_day
from tools.sim.scenarios import Scenario
from tools.sim.sensors import compass_errors, simulate_gps, simulate_heading, simulate_imu
from tools.sim.site import SiteFrame
from tools.sim.trajectory import Motion

START = 1.7e9


def field_day(seed: int) -> Scenario:
    s, _ = draw_field_day(resolve_scenario("quadrats"), np.random.default_rng(seed))
    return s


def synthetic_motion(duration_s: float, turn_period_s: float | None = None) -> Motion:
    """A boat holding still (or turning on the spot once every ``turn_period_s``), level,
    sampled at 10 Hz: local grid metres and radians."""
    t = np.arange(0.0, duration_s, 0.1)
    zero = np.zeros_like(t)
    rate = 0.0 if turn_period_s is None else 2 * math.pi / turn_period_s
    heading = rate * t
    return Motion(
        time=START + t, east=zero, north=zero, up=zero + 0.1, vel_east=zero, vel_north=zero,
        vel_up=zero, acc_east=zero, acc_north=zero, acc_up=zero, heading=heading, roll=zero,
        pitch=zero, heading_rate=zero + rate, roll_rate=zero, pitch_rate=zero, course=heading,
        path_s=zero,
    )  # fmt: skip


@pytest.fixture(scope="module")
def site() -> SiteFrame:
    s = resolve_scenario("quadrats")
    return SiteFrame.at(s.origin_lat_deg, s.origin_lon_deg)


@pytest.mark.parametrize("seed", [1, 2])
def test_gnss_error_has_the_drawn_correlation_time_and_white_part(site: SiteFrame, seed: int):
    """Measured from the error series alone (reported minus the antenna when the fix saw
    it) over 2 hours: the wandering part's size and correlation time, the white part's
    size, are the field day's u-blox M8N values."""
    s = field_day(seed)
    assert 1.0 <= s.gps_bias_sigma_m <= 1.5 and 20.0 <= s.gps_bias_tau_s <= 90.0
    assert 0.5 <= s.gps_noise_m <= 0.8 and 0.1 <= s.gps_lag_s <= 0.2
    motion = synthetic_motion(7200.0)
    times = np.arange(START + 0.13, START + 7200.0, 0.5)
    gps = simulate_gps(s, site, motion, times, np.random.default_rng(seed))
    err = np.stack([gps.error_east, gps.error_north])
    # Increments remove the slow level: E[(x[k+m] - x[k])^2] = 2 sigma^2 (1 - rho^m) + 2 w^2.
    lags = np.arange(1, 241)
    d = np.array([np.mean((err[:, m:] - err[:, :-m]) ** 2) for m in lags])
    variance = float(np.mean(err**2))
    white2 = float(np.mean((err[:, 1:] - err[:, :-1]) ** 2)) / 2  # the white part, mostly
    white2 -= (variance - white2) * (1 - math.exp(-0.5 / s.gps_bias_tau_s))
    wander2 = variance - white2
    rho = 1.0 - (d - 2 * white2) / (2 * wander2)
    usable = (rho > 0.2) & (rho < 0.9)
    tau = float(np.median(-0.5 * lags[usable] / np.log(rho[usable])))
    assert math.sqrt(wander2) == pytest.approx(s.gps_bias_sigma_m, rel=0.2)
    assert math.sqrt(white2) == pytest.approx(s.gps_noise_m, rel=0.1)
    assert tau == pytest.approx(s.gps_bias_tau_s, rel=0.35)
    # The white part is white, and h_acc reports the true 1-sigma per axis.
    white = np.stack([gps.error_east - gps.bias_east, gps.error_north - gps.bias_north])
    assert abs(np.mean(white[:, 1:] * white[:, :-1]) / np.mean(white**2)) < 0.05
    assert np.median(gps.h_acc) == pytest.approx(math.sqrt(variance), rel=0.15)


def test_gnss_fix_reports_the_antenna_a_lag_before_its_stamp(site: SiteFrame):
    """A boat at 0.4 m/s: the reported position trails the antenna at the stamp by
    speed x lag along the track."""
    s = resolve_scenario("quadrats", gps_bias_sigma_m=0.0, gps_noise_m=0.0, randomise=False)
    t = np.arange(0.0, 60.0, 0.1)
    zero = np.zeros_like(t)
    motion = Motion(
        time=START + t, east=zero, north=0.4 * t, up=zero + 0.1, vel_east=zero,
        vel_north=zero + 0.4, vel_up=zero, acc_east=zero, acc_north=zero, acc_up=zero,
        heading=zero, roll=zero, pitch=zero, heading_rate=zero, roll_rate=zero,
        pitch_rate=zero, course=zero, path_s=0.4 * t,
    )  # fmt: skip
    times = np.arange(START + 5.0, START + 55.0, 0.5)
    gps = simulate_gps(s, site, motion, times, np.random.default_rng(3))
    east, north = site.from_latlon(gps.lat, gps.lon)
    trail = 0.4 * (times - START) - north
    np.testing.assert_allclose(trail, 0.4 * s.gps_lag_s, atol=2e-3)
    np.testing.assert_allclose(east, 0.0, atol=2e-3)
    np.testing.assert_allclose(gps.antenna_time, times - s.gps_lag_s)


@pytest.mark.parametrize("seed", [3, 4])
def test_compass_bias_and_deviation_are_recovered(site: SiteFrame, seed: int):
    """A boat turning on the spot for 100 minutes: fitting the heading error against
    the magnetic heading gives back the day's bias and deviation (A sin psi + B cos psi
    + C sin 2 psi + D cos 2 psi); what is left is the correlated noise of the drawn size
    and correlation time."""
    s = field_day(seed)
    assert 1.0 <= abs(s.compass_bias_deg) <= 5.0
    assert 0.5 <= s.compass_deviation_1_deg <= 2.0 and 0.5 <= s.compass_deviation_2_deg <= 2.0
    motion = synthetic_motion(6000.0, turn_period_s=47.0)
    times = np.arange(START + 0.29, START + 5999.0, 0.5)
    compass = compass_errors(s, motion, np.random.default_rng(seed))
    track = simulate_heading(s, site, motion, times, np.random.default_rng(seed + 10), compass)
    true_heading = site.grid_to_true(motion.at(times)["heading"])
    err = np.degrees(np.angle(np.exp(1j * (track.heading_true - true_heading))))
    psi = true_heading - s.declination_rad
    design = np.stack(
        [np.ones_like(psi), np.sin(psi), np.cos(psi), np.sin(2 * psi), np.cos(2 * psi)], axis=1
    )
    fit = np.linalg.lstsq(design, err, rcond=None)[0]
    c = compass.coefficients_deg()
    expected = [s.compass_bias_deg, c["A_deg"], c["B_deg"], c["C_deg"], c["D_deg"]]
    np.testing.assert_allclose(fit, expected, atol=0.35)
    residual = err - design @ fit
    gm2, white2, wander2 = (
        s.compass_gm_sigma_deg**2, s.compass_noise_deg**2, s.compass_bias_wander_deg**2
    )  # fmt: skip
    assert np.std(residual) == pytest.approx(math.sqrt(gm2 + white2 + wander2), rel=0.25)
    # Correlated: after one correlation time it has kept about 1/e of itself (and the
    # slow wander all of itself).
    lag = round(s.compass_gm_tau_s / 0.5)
    corr = np.corrcoef(residual[:-lag], residual[lag:])[0, 1]
    expected_corr = (gm2 * math.exp(-lag * 0.5 / s.compass_gm_tau_s) + wander2) / (
        gm2 + white2 + wander2
    )
    assert corr == pytest.approx(expected_corr, abs=0.12)


def test_the_magnetometer_carries_the_same_bias_and_deviation(site: SiteFrame):
    """The heading from the raw field (level boat: atan2(-my, mx)) plus the declination
    is the true heading plus the compass's bias and deviation, whatever the heading."""
    s = field_day(5)
    motion = synthetic_motion(600.0, turn_period_s=31.0)
    times = np.arange(START + 0.004, START + 599.0, 0.2)
    compass = compass_errors(s, motion, np.random.default_rng(5))
    imu = simulate_imu(s, site, motion, times, np.random.default_rng(6), compass)
    true_heading = site.grid_to_true(motion.at(times)["heading"])
    seen = np.arctan2(-imu.mag[:, 1], imu.mag[:, 0]) + s.declination_rad
    err = np.angle(np.exp(1j * (seen - true_heading)))
    expected = compass.bias(times) + compass.deviation(true_heading)
    np.testing.assert_allclose(imu.mag_error, expected)
    left = np.degrees(np.angle(np.exp(1j * (err - expected))))
    assert abs(np.mean(left)) < 0.1 and np.std(left) < 1.0  # the field's white noise
    assert np.ptp(np.degrees(expected)) > 1.0  # the deviation shows as the boat turns


def test_gyro_bias_is_the_residual_of_a_boot_calibration(site: SiteFrame):
    """Holding still, the gyro reads its bias: the day's 0.05-0.3 degrees/s per axis."""
    s = field_day(7)
    drawn = np.array([s.gyro_bias_x_dps, s.gyro_bias_y_dps, s.gyro_bias_z_dps])
    assert np.all((np.abs(drawn) >= 0.05) & (np.abs(drawn) <= 0.3))
    motion = synthetic_motion(300.0)
    times = np.arange(START + 0.004, START + 299.0, 0.05)
    compass = compass_errors(s, motion, np.random.default_rng(7))
    imu = simulate_imu(s, site, motion, times, np.random.default_rng(8), compass)
    np.testing.assert_allclose(np.degrees(imu.gyro_bias_const), drawn)
    bias = np.degrees(imu.gyro_bias.mean(axis=0))
    np.testing.assert_allclose(np.degrees(imu.gyro.mean(axis=0)), bias, atol=0.01)
    # ...plus its slow wander (0.2 of 0.2 degrees/s, over minutes).
    np.testing.assert_allclose(bias, drawn, atol=0.12)
    assert np.all(np.std(np.degrees(imu.gyro_bias), axis=0) < 0.05)
