"""Navigation sensor models: GPS (u-blox M8N-like), compass heading, IMU and magnetometer.

All measurements are taken at autopilot times (UNIX seconds on the boat computer's clock;
the autopilot's clock is taken as synchronous with it). Frames: GPS errors in local grid
east/north (metres); headings in radians clockwise from TRUE north; IMU in body FRD:
accelerometer = specific force (m/s^2, -9.81 on z at rest), gyro = body rates (rad/s),
magnetometer = Earth's field in the body frame (gauss).

Models:
- GPS: a fix stamped t reports the antenna where it was at ``t - gps_lag_s`` (the
  receiver's solution and serial latency), plus a first-order Gauss-Markov error per
  axis (sigma ``gps_bias_sigma_m``, time constant ``gps_bias_tau_s``, started from its
  stationary distribution) plus white noise (``gps_noise_m`` per axis); the velocity is
  lagged the same way, with 5 cm/s of noise. Reported h_acc is the model's true 1-sigma
  per axis, ``hypot(sigma, white)``, with a +-15 % wobble; HDOP about 0.8-1.0; 12-14
  satellites. During an outage (``gps_outage_start_s``, ``gps_outage_duration_s``) the
  receiver reports no fix (fix_type 1), its last position, 0-3 satellites.
- RTK GNSS (``gnss_kind = "rtk"``, a dual-frequency receiver with a base nearby): fixed
  (fix_type 6) with white noise ``rtk_noise_m`` per axis, a Gauss-Markov wander
  ``rtk_bias_sigma_m`` over ``rtk_bias_tau_s`` (multipath, the base's error), vertical
  ``rtk_vertical_sigma_m``, fixes ``rtk_lag_s`` old; h_acc reported 10-20 mm (the model's
  1-sigma, +-15 %, within what such receivers say in a fix). Drops to RTK float
  (fix_type 5) for a few seconds every few minutes (``float_mask``): a 10 s Gauss-Markov
  error of ``rtk_float_sigma_m`` per axis, three times the white noise, h_acc to match
  (decimetres); 20-24 satellites (several constellations), HDOP about 0.6.
- Heading: true heading + bias (``compass_bias_deg`` + a slow Gauss-Markov wander) +
  deviation ``d1 sin(psi + p1) + d2 sin(2 psi + p2)`` of the magnetic heading psi (hard and
  soft iron) + correlated noise (Gauss-Markov, ``compass_gm_sigma_deg``,
  ``compass_gm_tau_s``: the fused heading's error) + white noise (``compass_noise_deg``).
  The bias, its wander and the deviation are the magnetometer's own: the raw field is the
  field seen from the attitude with the heading turned by them, so a tilt-compensated
  heading from it plus the declination shows them exactly; the correlated and white
  heading noise is the autopilot's fusion, not in the raw field.
- IMU: truth + constant bias (gyro: ``gyro_bias_*_dps``, the residual of the boot
  calibration; accelerometer: drawn once, sigma ``accel_bias_sigma_mps2``) + slow
  Gauss-Markov wander (``imu_bias_wander`` x the bias sigma, 300 s) + white noise; the IMU
  sits at the antenna (no lever arm).
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
_GPS_VELOCITY_NOISE_MPS = 0.05
_OUTAGE_H_ACC_M = 999.0  # what the receiver says of its accuracy without a fix
_COMPASS_WANDER_STEP_S = 1.0
_RTK_FLOAT_TAU_S = 10.0  # how fast a float solution wanders (s)
_RTK_FLOAT_NOISE = 3.0  # white noise in float, as a multiple of the fixed noise
_RTK_VELOCITY_NOISE_MPS = 0.02  # carrier-phase velocities are better than the M8N's
_RTK_H_ACC_M = (0.010, 0.020)  # what RTK receivers report in a fix (u-blox F9P: 10-14 mm)


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
    """GPS fixes at ``time`` (UNIX s, the fix's stamp). ``antenna_time`` = time - lag: when
    the antenna was where the fix says, ``antenna_east``/``antenna_north`` (local grid m);
    lat/lon degrees, alt metres MSL; bias/error in local grid east/north metres (error =
    bias + white noise, the reported position minus the antenna at ``antenna_time``);
    speed m/s; course radians clockwise from true north; h_acc metres; fix_type 3 (3-D)
    or 1 (no fix, during an outage)."""

    time: FloatArray
    antenna_time: FloatArray
    antenna_east: FloatArray
    antenna_north: FloatArray
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
    fix_type: npt.NDArray[np.int64]


def outage_mask(s: Scenario, start: float, times: FloatArray) -> npt.NDArray[np.bool_]:
    """Which of ``times`` (UNIX s) fall in the scenario's GNSS outage (``start``: the log
    start, UNIX s)."""
    if s.gps_outage_start_s is None:
        return np.zeros(len(times), bool)
    t0 = start + s.gps_outage_start_s
    return (times >= t0) & (times < t0 + s.gps_outage_duration_s)


def float_mask(
    s: Scenario, start: float, times: FloatArray, rng: np.random.Generator
) -> npt.NDArray[np.bool_]:
    """Which of ``times`` (UNIX s) an RTK receiver spends in RTK float: episodes whose
    gaps are exponential of mean ``rtk_float_interval_s`` and lengths uniform in 0.5-1.5
    times ``rtk_float_duration_s``, from the log ``start`` (UNIX s)."""
    mask = np.zeros(len(times), bool)
    if not len(times):
        return mask
    t = start + float(rng.exponential(s.rtk_float_interval_s))
    end = float(times[-1])
    while t < end:
        length = s.rtk_float_duration_s * float(rng.uniform(0.5, 1.5))
        mask |= (times >= t) & (times < t + length)
        t += length + float(rng.exponential(s.rtk_float_interval_s))
    return mask


def _simulate_rtk(
    s: Scenario, site: SiteFrame, motion: Motion, times: FloatArray, rng: np.random.Generator
) -> GpsTrack:
    """An RTK receiver (module doc): fixed (fix_type 6) with ``rtk_noise_m`` white noise
    and a ``rtk_bias_sigma_m`` Gauss-Markov wander, dropping to float (fix_type 5) now
    and then with a ``rtk_float_sigma_m`` error (a Gauss-Markov process of 10 s: each
    drop starts with a jump of decimetres, and the fix snaps back when it ends)."""
    n = len(times)
    seen = times - s.rtk_lag_s
    truth = motion.at(seen)
    bias = gauss_markov(rng, times, s.rtk_bias_sigma_m, s.rtk_bias_tau_s, (3,))
    bias[:, 2] *= s.rtk_vertical_sigma_m / max(s.rtk_bias_sigma_m, 1e-9)
    noise = rng.normal(0.0, s.rtk_noise_m, (n, 3))
    floating = float_mask(s, motion.start, times, rng)
    wander = gauss_markov(rng, times, s.rtk_float_sigma_m, _RTK_FLOAT_TAU_S, (3,))
    bias = np.where(floating[:, None], bias + wander, bias)
    noise = np.where(floating[:, None], noise * _RTK_FLOAT_NOISE, noise)
    err_e = bias[:, 0] + noise[:, 0]
    err_n = bias[:, 1] + noise[:, 1]
    lat, lon = site.to_latlon(truth["east"] + err_e, truth["north"] + err_n)
    alt = truth["up"] + bias[:, 2] + 2.0 * noise[:, 2]
    vn, ve = site.rotate_grid_to_true(truth["vel_north"], truth["vel_east"])
    vn = vn + rng.normal(0.0, _RTK_VELOCITY_NOISE_MPS, n)
    ve = ve + rng.normal(0.0, _RTK_VELOCITY_NOISE_MPS, n)
    wobble = 1.0 + 0.15 * np.sin(2 * math.pi * (times - times[0]) / 97.0 + rng.uniform(0, 6.3))
    fixed_acc = np.clip(math.hypot(s.rtk_bias_sigma_m, s.rtk_noise_m) * wobble, *_RTK_H_ACC_M)
    float_acc = math.hypot(s.rtk_float_sigma_m, s.rtk_noise_m * _RTK_FLOAT_NOISE) * wobble
    h_acc = np.where(floating, float_acc, fixed_acc)
    span = times - times[0]
    satellites = 22 + np.round(2.0 * np.sin(2 * math.pi * span / 230.0)).astype(np.int64)
    hdop = 0.6 + 0.3 * (wobble - 1.0) + rng.normal(0.0, 0.01, n)
    fix_type = np.where(floating, 5, 6).astype(np.int64)
    return _track(
        s,
        motion,
        times,
        rng,
        seen,
        truth,
        (lat, lon, alt),
        bias,
        (err_e, err_n),
        (vn, ve),
        h_acc,
        hdop,
        satellites,
        fix_type,
    )


def simulate_gps(
    s: Scenario, site: SiteFrame, motion: Motion, times: FloatArray, rng: np.random.Generator
) -> GpsTrack:
    """The GNSS fixes at ``times`` (module doc): the M8N's, or an RTK receiver's."""
    if s.gnss_kind == "rtk":
        return _simulate_rtk(s, site, motion, times, rng)
    seen = times - s.gps_lag_s
    truth = motion.at(seen)
    bias = gauss_markov(rng, times, s.gps_bias_sigma_m, s.gps_bias_tau_s, (3,))
    bias[:, 2] *= s.gps_vertical_sigma_m / max(s.gps_bias_sigma_m, 1e-9)
    noise = rng.normal(0.0, s.gps_noise_m, (len(times), 3))
    err_e = bias[:, 0] + noise[:, 0]
    err_n = bias[:, 1] + noise[:, 1]
    lat, lon = site.to_latlon(truth["east"] + err_e, truth["north"] + err_n)
    alt = truth["up"] + bias[:, 2] + 1.5 * noise[:, 2]
    vn, ve = site.rotate_grid_to_true(truth["vel_north"], truth["vel_east"])
    vn = vn + rng.normal(0.0, _GPS_VELOCITY_NOISE_MPS, len(times))
    ve = ve + rng.normal(0.0, _GPS_VELOCITY_NOISE_MPS, len(times))
    sigma = math.hypot(s.gps_bias_sigma_m, s.gps_noise_m)
    wobble = 1.0 + 0.15 * np.sin(2 * math.pi * (times - times[0]) / 97.0 + rng.uniform(0, 6.3))
    satellites = 12 + np.round(1.4 * (1 + np.sin(2 * math.pi * (times - times[0]) / 230.0))).astype(
        np.int64
    )
    hdop = 0.9 + 0.5 * (wobble - 1.0) + rng.normal(0.0, 0.02, len(times))
    h_acc = sigma * wobble
    fix_type = np.full(len(times), 3, np.int64)
    return _track(
        s,
        motion,
        times,
        rng,
        seen,
        truth,
        (lat, lon, alt),
        bias,
        (err_e, err_n),
        (vn, ve),
        h_acc,
        hdop,
        satellites,
        fix_type,
    )


def _track(
    s: Scenario,
    motion: Motion,
    times: FloatArray,
    rng: np.random.Generator,
    seen: FloatArray,
    truth: dict[str, FloatArray],
    position: tuple[FloatArray, FloatArray, FloatArray],
    bias: FloatArray,
    error: tuple[FloatArray, FloatArray],
    velocity: tuple[FloatArray, FloatArray],
    h_acc: FloatArray,
    hdop: FloatArray,
    satellites: npt.NDArray[np.int64],
    fix_type: npt.NDArray[np.int64],
) -> GpsTrack:
    """The receiver's fixes as a ``GpsTrack``, through a GNSS outage: no fix, the
    receiver repeats its last position (an outage starts after the first fix) and says
    so; the error is then that position's from the antenna."""
    lat, lon, alt = position
    err_e, err_n = error
    vn, ve = velocity
    speed = np.hypot(vn, ve)
    course = np.mod(np.arctan2(ve, vn), 2 * math.pi)
    lost = outage_mask(s, motion.start, times)
    if np.any(lost):
        last = np.maximum.accumulate(np.where(lost, 0, np.arange(len(times))))
        lat, lon, alt = lat[last], lon[last], alt[last]
        err_e = np.where(lost, truth["east"][last] + err_e[last] - truth["east"], err_e)
        err_n = np.where(lost, truth["north"][last] + err_n[last] - truth["north"], err_n)
        fix_type[lost] = 1
        satellites[lost] = rng.integers(0, 4, int(lost.sum()))
        hdop[lost] = 99.99
        h_acc[lost] = _OUTAGE_H_ACC_M
        speed[lost] = 0.0
        course[lost] = 0.0
    return GpsTrack(
        time=times,
        antenna_time=seen,
        antenna_east=truth["east"],
        antenna_north=truth["north"],
        lat=lat,
        lon=lon,
        alt=alt,
        bias_east=bias[:, 0],
        bias_north=bias[:, 1],
        error_east=err_e,
        error_north=err_n,
        speed=speed,
        course_true=course,
        h_acc=h_acc,
        hdop=hdop,
        satellites=satellites,
        fix_type=fix_type,
    )


@dataclass(frozen=True)
class CompassErrors:
    """The magnetometer's own heading errors over a survey (radians): the bias (constant
    plus a slow wander, tabulated at ``wander_time``, UNIX s) and the deviation's
    amplitudes and phases of the one- and two-cycle terms; ``declination`` turns true
    headings into the magnetic heading the deviation depends on."""

    bias_const: float
    wander_time: FloatArray
    wander: FloatArray
    deviation_1: float
    phase_1: float
    deviation_2: float
    phase_2: float
    declination: float

    def bias(self, times: FloatArray) -> FloatArray:
        """Constant bias plus wander at ``times`` (UNIX s), radians."""
        return self.bias_const + np.interp(times, self.wander_time, self.wander)

    def deviation(self, heading_true: FloatArray) -> FloatArray:
        """Deviation (radians) at true headings (radians): ``d1 sin(psi + p1) + d2 sin(2 psi
        + p2)``, psi the magnetic heading."""
        psi = np.asarray(heading_true) - self.declination
        return self.deviation_1 * np.sin(psi + self.phase_1) + self.deviation_2 * np.sin(
            2.0 * psi + self.phase_2
        )

    def coefficients_deg(self) -> dict[str, float]:
        """The deviation as ``A sin psi + B cos psi + C sin 2 psi + D cos 2 psi`` (degrees)."""
        d1, d2 = math.degrees(self.deviation_1), math.degrees(self.deviation_2)
        return {
            "A_deg": d1 * math.cos(self.phase_1),
            "B_deg": d1 * math.sin(self.phase_1),
            "C_deg": d2 * math.cos(self.phase_2),
            "D_deg": d2 * math.sin(self.phase_2),
        }


def compass_errors(s: Scenario, motion: Motion, rng: np.random.Generator) -> CompassErrors:
    """The survey's magnetometer errors (see ``CompassErrors``); the wander is drawn at
    1 s steps over the motion's span."""
    t = np.arange(motion.start - 1.0, motion.end + 2.0, _COMPASS_WANDER_STEP_S)
    wander = gauss_markov(rng, t, math.radians(s.compass_bias_wander_deg), s.compass_bias_tau_s)
    return CompassErrors(
        bias_const=math.radians(s.compass_bias_deg),
        wander_time=t,
        wander=wander,
        deviation_1=math.radians(s.compass_deviation_1_deg),
        phase_1=math.radians(s.compass_deviation_1_phase_deg),
        deviation_2=math.radians(s.compass_deviation_2_deg),
        phase_2=math.radians(s.compass_deviation_2_phase_deg),
        declination=s.declination_rad,
    )


@dataclass(frozen=True)
class HeadingTrack:
    """Attitude reports at ``time``: heading radians from TRUE north in [0, 2 pi); its
    error's parts (radians): ``bias`` (constant + wander), ``deviation``, ``noise``
    (correlated + white) and ``error`` (their sum: reported minus true heading); roll/pitch
    radians (FRD) with noise; body rates rad/s."""

    time: FloatArray
    heading_true: FloatArray
    bias: FloatArray
    deviation: FloatArray
    noise: FloatArray
    error: FloatArray
    roll: FloatArray
    pitch: FloatArray
    rollspeed: FloatArray
    pitchspeed: FloatArray
    yawspeed: FloatArray


def simulate_heading(
    s: Scenario,
    site: SiteFrame,
    motion: Motion,
    times: FloatArray,
    rng: np.random.Generator,
    compass: CompassErrors,
) -> HeadingTrack:
    truth = motion.at(times)
    true_heading = site.grid_to_true(truth["heading"])
    bias = compass.bias(times)
    deviation = compass.deviation(true_heading)
    noise = gauss_markov(rng, times, math.radians(s.compass_gm_sigma_deg), s.compass_gm_tau_s)
    noise += rng.normal(0.0, math.radians(s.compass_noise_deg), len(times))
    error = bias + deviation + noise
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
        heading_true=np.mod(true_heading + error, 2 * math.pi),
        bias=bias,
        deviation=deviation,
        noise=noise,
        error=error,
        roll=truth["roll"] + rng.normal(0.0, att_sigma, len(times)),
        pitch=truth["pitch"] + rng.normal(0.0, att_sigma, len(times)),
        rollspeed=p + rng.normal(0.0, 0.005, len(times)),
        pitchspeed=q + rng.normal(0.0, 0.005, len(times)),
        yawspeed=r + rng.normal(0.0, 0.005, len(times)),
    )


@dataclass(frozen=True)
class ImuTrack:
    """IMU samples at ``time``: accel (n, 3) m/s^2 specific force FRD; gyro (n, 3) rad/s
    FRD; mag (n, 3) gauss FRD; the biases used: accel_bias (n, 3), gyro_bias (n, 3);
    ``mag_error`` (n,): the heading error the magnetometer carries (radians: bias, wander
    and deviation)."""

    time: FloatArray
    accel: FloatArray
    gyro: FloatArray
    mag: FloatArray
    accel_bias: FloatArray
    gyro_bias: FloatArray
    accel_bias_const: FloatArray
    gyro_bias_const: FloatArray
    mag_error: FloatArray


def earth_field_ned(s: Scenario) -> FloatArray:
    """Earth's magnetic field in true north/east/down (gauss)."""
    total = s.field_mgauss / 1000.0
    inc = math.radians(s.inclination_deg)
    dec = s.declination_rad
    horizontal = total * math.cos(inc)
    return np.array([horizontal * math.cos(dec), horizontal * math.sin(dec), total * math.sin(inc)])


def simulate_imu(
    s: Scenario,
    site: SiteFrame,
    motion: Motion,
    times: FloatArray,
    rng: np.random.Generator,
    compass: CompassErrors,
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
    gyro_const = np.radians([s.gyro_bias_x_dps, s.gyro_bias_y_dps, s.gyro_bias_z_dps])
    acc_bias = acc_const + gauss_markov(
        rng, times, s.imu_bias_wander * s.accel_bias_sigma_mps2, _IMU_BIAS_TAU_S, (3,)
    )
    gyro_bias = gyro_const + gauss_markov(
        rng, times, s.imu_bias_wander * math.radians(s.gyro_bias_sigma_dps), _IMU_BIAS_TAU_S, (3,)
    )
    accel = accel_true + acc_bias + rng.normal(0.0, s.accel_noise_mps2, (n, 3))
    gyro = gyro_true + gyro_bias + rng.normal(0.0, math.radians(s.gyro_noise_dps), (n, 3))

    # The magnetometer's errors turn the heading it sees: the field it reports is Earth's
    # field seen from the attitude with the heading turned by them (roll and pitch true),
    # so a tilt-compensated heading from it carries them whatever the boat's attitude.
    mag_error = compass.bias(times) + compass.deviation(heading_true)
    r_seen = euler_to_matrix(heading_true + mag_error, truth["pitch"], truth["roll"])
    mag = np.einsum("nji,j->ni", r_seen, earth_field_ned(s))
    mag += rng.normal(0.0, s.mag_noise_mgauss / 1000.0, (n, 3))
    return ImuTrack(times, accel, gyro, mag, acc_bias, gyro_bias, acc_const, gyro_const, mag_error)
