"""Navigation sensor models: GPS (u-blox M8N-like), compass heading, IMU and magnetometer.

All measurements are taken at autopilot times (UNIX seconds on the boat computer's clock;
the autopilot's clock is taken as synchronous with it). Frames: GPS errors in local grid
east/north (metres); headings in radians clockwise from TRUE north; IMU in body FRD:
accelerometer = specific force (m/s^2, -9.81 on z at rest), gyro = body rates (rad/s),
magnetometer = Earth's field in the body frame (gauss).

Models:
- GPS: truth + a first-order Gauss-Markov bias per axis (sigma ``gps_bias_sigma_m``,
  time constant ``gps_bias_tau_s``, started from its stationary distribution) + white
  noise (``gps_noise_m`` per axis). Reported h_acc is a pessimistic 1.5 x the model's
  1-sigma error per axis with a slow wobble; HDOP about 0.8-1.0; 12-14 satellites.
- Heading: true heading + bias (``compass_bias_deg`` + a Gauss-Markov wander) + white
  noise (``compass_noise_deg``). The same bias sits in the magnetometer: it is modelled
  as a mounting misalignment of the compass about the vertical, so a tilt-compensated
  heading from the raw field plus the declination shows it too.
- IMU: truth + constant bias (drawn once, sigma ``*_bias_sigma``) + slow Gauss-Markov
  wander (``imu_bias_wander`` x sigma, 300 s) + white noise; the IMU sits at the antenna
  (no lever arm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from tools.sim.scenarios import Scenario
from tools.sim.site import SiteFrame
from tools.sim.trajectory import Motion, body_rates, euler_to_matrix

FloatArray = npt.NDArray[np.float64]

GRAVITY_MPS2 = 9.80665
_IMU_BIAS_TAU_S = 300.0


def gauss_markov(
    rng: np.random.Generator,
    times: FloatArray,
    sigma: float,
    tau: float,
    shape: tuple[int, ...] = (),
) -> FloatArray:
    """A first-order Gauss-Markov process sampled at ``times`` (s), stationary from the
    start: x_k+1 = exp(-dt/tau) x_k + sigma sqrt(1 - exp(-2 dt/tau)) w_k."""
    n = len(times)
    out = np.empty((n, *shape))
    if n == 0:
        return out
    w = rng.standard_normal((n, *shape))
    out[0] = sigma * w[0]
    decay = np.exp(-np.diff(times) / tau)
    drive = sigma * np.sqrt(1.0 - decay**2)
    # The recursion is sequential (hundreds of thousands of IMU samples in a long survey):
    # run it on Python floats, one component at a time. Each step is the same IEEE
    # multiply, multiply, add as the array expression, so the values are bit-identical.
    flat_out = out.reshape(n, -1)
    flat_w = w.reshape(n, -1)
    step = list(zip(decay.tolist(), drive.tolist(), strict=True))
    for j in range(flat_out.shape[1]):
        x = float(flat_out[0, j])
        column = [x]
        for (d, g), wk in zip(step, flat_w[1:, j].tolist(), strict=True):
            x = d * x + g * wk
            column.append(x)
        flat_out[:, j] = column
    return out


@dataclass(frozen=True)
class GpsTrack:
    """GPS fixes at ``time`` (UNIX s). lat/lon degrees, alt metres MSL; bias/error in
    local grid east/north metres (error = bias + white noise); speed m/s; course radians
    clockwise from true north; h_acc metres."""

    time: FloatArray
    lat: FloatArray
    lon: FloatArray
    alt: FloatArray
    bias_east: FloatArray
    bias_north: FloatArray
    error_east: FloatArray
    error_north: FloatArray
    speed: FloatArray
    course_true: FloatArray
    h_acc: FloatArray
    hdop: FloatArray
    satellites: npt.NDArray[np.int64]


def simulate_gps(
    s: Scenario, site: SiteFrame, motion: Motion, times: FloatArray, rng: np.random.Generator
) -> GpsTrack:
    truth = motion.at(times)
    bias = gauss_markov(rng, times, s.gps_bias_sigma_m, s.gps_bias_tau_s, (3,))
    bias[:, 2] *= s.gps_vertical_sigma_m / max(s.gps_bias_sigma_m, 1e-9)
    noise = rng.normal(0.0, s.gps_noise_m, (len(times), 3))
    err_e = bias[:, 0] + noise[:, 0]
    err_n = bias[:, 1] + noise[:, 1]
    lat, lon = site.to_latlon(truth["east"] + err_e, truth["north"] + err_n)
    alt = truth["up"] + bias[:, 2] + 1.5 * noise[:, 2]
    vn, ve = site.rotate_grid_to_true(truth["vel_north"], truth["vel_east"])
    vn = vn + rng.normal(0.0, 0.03, len(times))
    ve = ve + rng.normal(0.0, 0.03, len(times))
    sigma = math.hypot(s.gps_bias_sigma_m, s.gps_noise_m)
    wobble = 1.0 + 0.15 * np.sin(2 * math.pi * (times - times[0]) / 97.0 + rng.uniform(0, 6.3))
    satellites = 12 + np.round(1.4 * (1 + np.sin(2 * math.pi * (times - times[0]) / 230.0))).astype(
        np.int64
    )
    return GpsTrack(
        time=times,
        lat=lat,
        lon=lon,
        alt=alt,
        bias_east=bias[:, 0],
        bias_north=bias[:, 1],
        error_east=err_e,
        error_north=err_n,
        speed=np.hypot(vn, ve),
        course_true=np.mod(np.arctan2(ve, vn), 2 * math.pi),
        h_acc=1.5 * sigma * wobble,
        hdop=0.9 + 0.5 * (wobble - 1.0) + rng.normal(0.0, 0.02, len(times)),
        satellites=satellites,
    )


@dataclass(frozen=True)
class HeadingTrack:
    """Attitude reports at ``time``: heading radians from TRUE north in [0, 2 pi) with its
    error (bias + noise); roll/pitch radians (FRD) with noise; body rates rad/s."""

    time: FloatArray
    heading_true: FloatArray
    bias: FloatArray
    roll: FloatArray
    pitch: FloatArray
    rollspeed: FloatArray
    pitchspeed: FloatArray
    yawspeed: FloatArray


def simulate_heading(
    s: Scenario, site: SiteFrame, motion: Motion, times: FloatArray, rng: np.random.Generator
) -> HeadingTrack:
    truth = motion.at(times)
    bias = math.radians(s.compass_bias_deg) + gauss_markov(
        rng, times, math.radians(s.compass_bias_wander_deg), s.compass_bias_tau_s
    )
    true_heading = site.grid_to_true(truth["heading"])
    measured = true_heading + bias + rng.normal(0.0, math.radians(s.compass_noise_deg), len(times))
    att_sigma = math.radians(s.attitude_noise_deg)
    p, q, r = body_rates(
        truth["roll"],
        truth["pitch"],
        truth["roll_rate"],
        truth["pitch_rate"],
        truth["heading_rate"],
    )
    return HeadingTrack(
        time=times,
        heading_true=np.mod(measured, 2 * math.pi),
        bias=bias,
        roll=truth["roll"] + rng.normal(0.0, att_sigma, len(times)),
        pitch=truth["pitch"] + rng.normal(0.0, att_sigma, len(times)),
        rollspeed=p + rng.normal(0.0, 0.005, len(times)),
        pitchspeed=q + rng.normal(0.0, 0.005, len(times)),
        yawspeed=r + rng.normal(0.0, 0.005, len(times)),
    )


@dataclass(frozen=True)
class ImuTrack:
    """IMU samples at ``time``: accel (n, 3) m/s^2 specific force FRD; gyro (n, 3) rad/s
    FRD; mag (n, 3) gauss FRD; the biases used: accel_bias (n, 3), gyro_bias (n, 3)."""

    time: FloatArray
    accel: FloatArray
    gyro: FloatArray
    mag: FloatArray
    accel_bias: FloatArray
    gyro_bias: FloatArray
    accel_bias_const: FloatArray
    gyro_bias_const: FloatArray


def earth_field_ned(s: Scenario) -> FloatArray:
    """Earth's magnetic field in true north/east/down (gauss)."""
    total = s.field_mgauss / 1000.0
    inc = math.radians(s.inclination_deg)
    dec = s.declination_rad
    horizontal = total * math.cos(inc)
    return np.array([horizontal * math.cos(dec), horizontal * math.sin(dec), total * math.sin(inc)])


def simulate_imu(
    s: Scenario, site: SiteFrame, motion: Motion, times: FloatArray, rng: np.random.Generator
) -> ImuTrack:
    truth = motion.at(times)
    n = len(times)
    heading_true = site.grid_to_true(truth["heading"])
    r_nb = euler_to_matrix(heading_true, truth["pitch"], truth["roll"])  # (n, 3, 3)
    acc_n, acc_e = site.rotate_grid_to_true(truth["acc_north"], truth["acc_east"])
    # NED acceleration minus gravity, seen in the body frame: what an accelerometer feels.
    specific = np.stack([acc_n, acc_e, -truth["acc_up"] - GRAVITY_MPS2], axis=1)
    accel_true = np.einsum("nji,nj->ni", r_nb, specific)
    p, q, r = body_rates(
        truth["roll"],
        truth["pitch"],
        truth["roll_rate"],
        truth["pitch_rate"],
        truth["heading_rate"],
    )
    gyro_true = np.stack([p, q, r], axis=1)

    acc_const = rng.normal(0.0, s.accel_bias_sigma_mps2, 3)
    gyro_const = rng.normal(0.0, math.radians(s.gyro_bias_sigma_dps), 3)
    acc_bias = acc_const + gauss_markov(
        rng, times, s.imu_bias_wander * s.accel_bias_sigma_mps2, _IMU_BIAS_TAU_S, (3,)
    )
    gyro_bias = gyro_const + gauss_markov(
        rng, times, s.imu_bias_wander * math.radians(s.gyro_bias_sigma_dps), _IMU_BIAS_TAU_S, (3,)
    )
    accel = accel_true + acc_bias + rng.normal(0.0, s.accel_noise_mps2, (n, 3))
    gyro = gyro_true + gyro_bias + rng.normal(0.0, math.radians(s.gyro_noise_dps), (n, 3))

    # The compass bias as a misalignment about the body z axis: the magnetometer's frame
    # is the body frame yawed by -bias, so the field it reports looks turned by +bias.
    field_ned = earth_field_ned(s)
    mag_body = np.einsum("nji,j->ni", r_nb, field_ned)
    b = math.radians(s.compass_bias_deg)
    cb, sb = math.cos(b), math.sin(b)
    mag = np.stack(
        [
            cb * mag_body[:, 0] + sb * mag_body[:, 1],
            -sb * mag_body[:, 0] + cb * mag_body[:, 1],
            mag_body[:, 2],
        ],
        axis=1,
    )
    mag += rng.normal(0.0, s.mag_noise_mgauss / 1000.0, (n, 3))
    return ImuTrack(times, accel, gyro, mag, acc_bias, gyro_bias, acc_const, gyro_const)
