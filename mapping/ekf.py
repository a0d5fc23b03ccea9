"""The paper's 8-state navigation EKF (Zhang et al., Sec. III.D, Eq. 2-3), with filterpy.

State x = [px, py, vx, vy, psi, b_omega, b_ax, b_ay]: position and velocity of the vehicle
reference point (the GPS antenna) in the local east-north frame (metres, m/s), heading psi
(radians clockwise from grid north), gyro yaw-rate bias (rad/s) and the forward and
starboard accelerometer biases (m/s^2).

- Predict with each IMU sample: body-frame specific force, levelled with the autopilot's
  roll and pitch when known (a 2 degree pitch would otherwise read as 0.34 m/s^2 of
  acceleration) and rotated by psi; yaw rate from the gyro through the Euler kinematics.
- Update with GNSS position (and, when the receiver reports it, its Doppler velocity) and
  with compass headings; the measurement matrices are linear in the state; heading
  residuals are wrapped.
- Outages dead-reckon: the covariance grows with the process noise, and the estimate
  carries that uncertainty on to the later stages.

``NavFilter`` is incremental (the streaming engine feeds it as samples arrive);
``smooth_trajectory`` runs it over a whole survey and adds a Rauch-Tung-Striebel backward
pass, which is what the paper's offline "EKF-smoothed" priors amount to.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mapping.se2 import wrap_pi

GRAVITY = 9.80665
STATE_SIZE = 8
PX, PY, VX, VY, PSI, BW, BAX, BAY = range(STATE_SIZE)

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class EkfParams:
    """Noise model. Densities are per sqrt(second); sigmas are one standard deviation."""

    accel_noise: float = 0.35
    """Unmodelled acceleration (waves, thrust changes), m/s^2/sqrt(Hz)."""
    gyro_noise: float = 0.02
    """Yaw-rate noise, rad/s/sqrt(Hz)."""
    gyro_bias_walk: float = 2e-4
    """rad/s^2/sqrt(Hz)."""
    accel_bias_walk: float = 5e-3
    """m/s^3/sqrt(Hz)."""
    position_sigma_m: float = 1.5
    """GNSS position sigma when the receiver reports neither h_acc nor HDOP."""
    hdop_to_sigma_m: float = 2.0
    """Metres of horizontal sigma per unit of HDOP (u-blox M8N class receivers)."""
    min_position_sigma_m: float = 0.3
    velocity_sigma_mps: float = 0.15
    """GNSS Doppler velocity sigma per axis; velocity updates are skipped below
    ``min_course_speed_mps``, where course over ground is noise."""
    min_course_speed_mps: float = 0.2
    heading_sigma_rad: float = math.radians(2.0)
    max_imu_gap_s: float = 0.25
    """Longer gaps between IMU samples are bridged with zero input and a larger noise."""
    initial_sigmas: tuple[float, ...] = (3.0, 3.0, 0.5, 0.5, math.radians(10), 0.01, 0.2, 0.2)


@dataclass(frozen=True, slots=True)
class ImuInput:
    """One IMU sample ready for prediction: levelled horizontal specific force (forward,
    starboard, m/s^2, gravity removed when attitude is known) and yaw rate (rad/s,
    clockwise positive)."""

    time: float
    forward_mps2: float
    starboard_mps2: float
    yaw_rate_rps: float


def level_imu(
    accel_frd: tuple[float, float, float],
    gyro_frd: tuple[float, float, float],
    roll_rad: float | None,
    pitch_rad: float | None,
) -> tuple[float, float, float]:
    """Horizontal acceleration (forward, starboard) and yaw rate from a body-frame sample.

    With roll/pitch: rotate the specific force to the level frame and add gravity back
    (f = a - g, z down); yaw rate = (q sin(roll) + r cos(roll)) / cos(pitch). Without:
    the raw x/y specific force (the bias states take up a steady tilt) and r.
    """
    fx, fy, fz = accel_frd
    _, q, r = gyro_frd
    if roll_rad is None or pitch_rad is None:
        return fx, fy, r
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    # Level-frame specific force: R_y(pitch) R_x(roll) f, then a = f + g (z down).
    forward = cp * fx + sp * sr * fy + sp * cr * fz
    starboard = cr * fy - sr * fz
    yaw_rate = (q * sr + r * cr) / max(cp, 1e-3)
    return forward, starboard, yaw_rate


@functools.cache
def _ekf_class() -> type:
    """filterpy's EKF with the nonlinear kinematic propagation of the paper's model, made
    on first use: filterpy's import brings SciPy's statistics with it (about half a
    second), which the worker processes that never run a filter need not pay."""
    from filterpy.kalman import ExtendedKalmanFilter

    class _Ekf(ExtendedKalmanFilter):
        def __init__(self) -> None:
            super().__init__(dim_x=STATE_SIZE, dim_z=1)
            self.u_dt: tuple[ImuInput | None, float] = (None, 0.0)

        def predict_x(self, u: object = 0) -> None:
            imu, dt = self.u_dt
            x = self.x[:, 0]
            psi = x[PSI]
            if imu is None:
                a_f = a_s = rate = 0.0
            else:
                a_f = imu.forward_mps2 - x[BAX]
                a_s = imu.starboard_mps2 - x[BAY]
                rate = imu.yaw_rate_rps - x[BW]
            s, c = math.sin(psi), math.cos(psi)
            a_e = a_f * s + a_s * c
            a_n = a_f * c - a_s * s
            x[PX] += x[VX] * dt + 0.5 * a_e * dt * dt
            x[PY] += x[VY] * dt + 0.5 * a_n * dt * dt
            x[VX] += a_e * dt
            x[VY] += a_n * dt
            x[PSI] = (psi + rate * dt) % (2 * math.pi)

    return _Ekf


def _heading_residual(a: Array, b: Array) -> Array:
    return np.asarray(wrap_pi(np.asarray(a - b, float)))


class NavFilter:
    """Incremental EKF. Feed samples in time order; read ``state()`` at any time reached.

    Positions are local east-north metres (``mapping.geo.LocalFrame``); headings are grid
    headings. ``transition`` accumulates the state-transition Jacobian since the last
    ``mark()``, which the smoother needs.
    """

    def __init__(self, params: EkfParams | None = None) -> None:
        self.params = params or EkfParams()
        self.ekf = _ekf_class()()
        self.time: float | None = None
        self.initialised = False
        self._last_imu: ImuInput | None = None
        self.transition: Array = np.eye(STATE_SIZE)
        self.imu_gaps = 0
        self.gyro_epoch = 0
        """Number of IMU gaps longer than ``max_imu_gap_s`` that have closed: two frames
        whose stamps share an epoch, each with a fresh IMU sample, have the gyro's turn
        between them in ``odometry`` (``gyro_epoch_at``)."""
        self.odometry: Array = np.zeros(3)
        """Sum of the predicted motion only (east, north metres; heading radians): the
        dead-reckoned path, free of the jumps that measurement updates make. Differences
        between two times are the filter's best estimate of the relative motion."""

    # -- initialisation --------------------------------------------------------------
    def initialise(
        self, time: float, x: float, y: float, heading: float, velocity: tuple[float, float]
    ) -> None:
        state = np.zeros((STATE_SIZE, 1))
        state[PX, 0], state[PY, 0], state[PSI, 0] = x, y, heading % (2 * math.pi)
        state[VX, 0], state[VY, 0] = velocity
        self.ekf.x = state
        self.ekf.P = np.diag(np.square(self.params.initial_sigmas))
        self.time = time
        self.initialised = True

    # -- prediction ------------------------------------------------------------------
    def _step(self, imu: ImuInput | None, dt: float, inflate: float = 1.0) -> None:
        if dt <= 0.0:
            return
        p = self.params
        x = self.ekf.x[:, 0]
        psi = x[PSI]
        s, c = math.sin(psi), math.cos(psi)
        if imu is None:
            a_f = a_s = 0.0
        else:
            a_f = imu.forward_mps2 - x[BAX]
            a_s = imu.starboard_mps2 - x[BAY]
        a_e = a_f * s + a_s * c
        a_n = a_f * c - a_s * s
        jac = np.eye(STATE_SIZE)
        jac[PX, VX] = jac[PY, VY] = dt
        # d(a_e)/d(psi) = a_n, d(a_n)/d(psi) = -a_e; biases enter with the rotation.
        d_ae = np.zeros(STATE_SIZE)
        d_an = np.zeros(STATE_SIZE)
        d_ae[PSI], d_an[PSI] = a_n, -a_e
        if imu is not None:
            d_ae[BAX], d_ae[BAY] = -s, -c
            d_an[BAX], d_an[BAY] = -c, s
            jac[PSI, BW] = -dt
        jac[PX] += 0.5 * dt * dt * d_ae
        jac[PY] += 0.5 * dt * dt * d_an
        jac[VX] += dt * d_ae
        jac[VY] += dt * d_an
        q = np.zeros((STATE_SIZE, STATE_SIZE))
        acc_var = (p.accel_noise * inflate) ** 2
        # Constant-acceleration-noise discretisation per axis.
        for pos, vel in ((PX, VX), (PY, VY)):
            q[pos, pos] = acc_var * dt**3 / 3.0
            q[pos, vel] = q[vel, pos] = acc_var * dt**2 / 2.0
            q[vel, vel] = acc_var * dt
        q[PSI, PSI] = (p.gyro_noise * inflate) ** 2 * dt
        q[BW, BW] = p.gyro_bias_walk**2 * dt
        q[BAX, BAX] = q[BAY, BAY] = p.accel_bias_walk**2 * dt
        self.ekf.F = jac
        self.ekf.Q = q
        self.ekf.u_dt = (imu, dt)
        before = self.ekf.x[[PX, PY, PSI], 0].copy()
        self.ekf.predict()
        step = self.ekf.x[[PX, PY, PSI], 0] - before
        step[2] = wrap_pi(step[2])
        self.odometry += step
        self.transition = jac @ self.transition

    def predict_to(self, time: float) -> None:
        """Propagate to ``time`` with the latest IMU sample held over the interval."""
        if self.time is None or time <= self.time:
            return
        dt = time - self.time
        imu = self._last_imu
        if imu is None or time - imu.time > self.params.max_imu_gap_s:
            # No fresh IMU: dead-reckon at constant velocity with inflated noise.
            if imu is not None:
                self.imu_gaps += 1
            remaining = dt
            while remaining > 1e-9:
                step = min(remaining, 0.1)
                self._step(None, step, inflate=3.0)
                remaining -= step
        else:
            self._step(imu, dt)
        self.time = time

    def add_imu(self, imu: ImuInput) -> None:
        """Integrate up to this sample's time with the previous sample, then hold this one."""
        if self.initialised:
            self.predict_to(imu.time)
        last = self._last_imu
        if last is not None and imu.time - last.time > self.params.max_imu_gap_s:
            self.gyro_epoch += 1
        self._last_imu = imu

    def gyro_epoch_at(self, time: float) -> int | None:
        """The gyro epoch at ``time`` (reached by the filter), None when the IMU has been
        silent for longer than ``max_imu_gap_s`` there: the filter then dead-reckons at a
        constant heading, and its odometry knows nothing of a turn."""
        last = self._last_imu
        if last is None or time - last.time > self.params.max_imu_gap_s:
            return None
        return self.gyro_epoch

    # -- updates ---------------------------------------------------------------------
    def update_position(self, time: float, x: float, y: float, sigma_m: float) -> None:
        self.predict_to(time)
        h = np.zeros((2, STATE_SIZE))
        h[0, PX] = h[1, PY] = 1.0
        self.ekf.update(
            np.array([[x], [y]]),
            lambda _s: h,
            lambda s: h @ s,
            R=np.eye(2) * sigma_m**2,
        )

    def update_velocity(self, time: float, vx: float, vy: float, sigma_mps: float) -> None:
        self.predict_to(time)
        h = np.zeros((2, STATE_SIZE))
        h[0, VX] = h[1, VY] = 1.0
        self.ekf.update(
            np.array([[vx], [vy]]), lambda _s: h, lambda s: h @ s, R=np.eye(2) * sigma_mps**2
        )

    def update_heading(self, time: float, heading: float, sigma_rad: float) -> None:
        self.predict_to(time)
        h = np.zeros((1, STATE_SIZE))
        h[0, PSI] = 1.0
        self.ekf.update(
            np.array([[heading]]),
            lambda _s: h,
            lambda s: h @ s,
            R=np.array([[sigma_rad**2]]),
            residual=_heading_residual,
        )
        self.ekf.x[PSI, 0] %= 2 * math.pi

    # -- read-out --------------------------------------------------------------------
    def state(self) -> tuple[Array, Array]:
        """Current (x (8,), P (8, 8)) copies."""
        return self.ekf.x[:, 0].copy(), self.ekf.P.copy()

    def mark(self) -> Array:
        """Return the transition accumulated since the previous mark and restart it."""
        transition, self.transition = self.transition, np.eye(STATE_SIZE)
        return transition
