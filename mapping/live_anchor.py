"""Where the live chain sits: a small Kalman filter that ties the registration chain to the
GNSS, the heading filter and the live loop closures without bending it to their wander.

The live map is the chain of registrations (bridged by the filter's dead reckoning where a
registration is missing). Left alone the chain drifts; pulled to every fix it copies the
receiver's wander, and two passes over the same seabed a minute apart then disagree by
the change of the GNSS bias (a metre). So the chain carries a correction whose model is
physical (Farrell, *Aided Navigation*, 2008, Sec. 4.9 and Ch. 11; an error-state
complementary filter whose gains come from the noise models):

- state ``(c_e, c_n, b_e, b_n, h, r, k)``: what to add to the chain's position (metres,
  east/north), the GNSS receiver's Gauss-Markov bias (metres), what to add to the chain's
  heading (radians, clockwise), that heading error's rate (a gyro bias the navigation
  filter has not fully found, rad/s), and the error of the registered steps' length (the
  chain's scale, dimensionless);
- the chain's own translation error is a slow random walk (``drift_density``); each
  chained step ``s`` (east, north) was laid at the heading then estimated, so an error
  ``dh`` of that heading adds ``(s_n, -s_e) dh`` to the position error, and a scale error
  ``k`` adds ``s k``: the position, heading and scale corrections are coupled, and their
  errors show as a growing position uncertainty between lanes (a 3 degree compass error
  over a 16 m lane is 0.8 m, a 2 % scale error 0.3 m along it, twice that between
  opposite lanes);
- a GNSS fix measures ``c + b`` plus white noise; the navigation filter's heading (its
  compass) measures ``h`` with a sigma that stands for its correlated deviation;
- a live loop closure measures ``c`` and ``h`` relative to the already-final map
  (``update_closure``): where a keyframe's final pose and the registration put the
  current frame, minus the chain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mapping.se2 import turn

Array = npt.NDArray[np.float64]

_C = slice(0, 2)  # correction of the chain's position (east, north)
_B = slice(2, 4)  # GNSS bias
_H = 4  # correction of the chain's heading
_R = 5  # its rate
_K = 6  # the chain's scale error
_N = 7
_CH = [0, 1, 4]  # what a closure measures


@dataclass(frozen=True, slots=True)
class AnchorParams:
    drift_density: float = 0.006
    """Random walk of the chain's position error, m/sqrt(s)."""
    initial_sigma_m: float = 3.0
    """Uncertainty of the first frame's position (the first fix and its bias)."""
    gnss_white_sigma_m: float = 0.6
    gnss_bias_sigma_m: float = 1.2
    gnss_bias_tau_s: float = 45.0
    heading_drift_density: float = math.radians(0.05)
    """Random walk of the chain's heading error, rad/sqrt(s)."""
    registered_heading_density: float = math.radians(0.2)
    """The same while the chain's heading comes from its registrations alone (the gyro
    silent: the autopilot link cut): 0.12 degrees a keyframe pair (``GraphParams``), one
    to three pairs a second. The heading rate error (a gyro bias residual) does not act
    then."""
    rate_sigma_rps: float = math.radians(0.1)
    """Initial sigma of the chain's heading rate error (a gyro bias residual)."""
    rate_walk: float = math.radians(0.002)
    """Its random walk, rad/s/sqrt(s)."""
    heading_sigma_rad: float = math.radians(3.0)
    """Error of the navigation filter's heading as the correction sees it (compass
    misalignment and deviation, correlated over minutes). Modelling the deviation (one-
    and two-cycle states, 1.5 degree updates every 5 s) was measured and made the live
    lanes worse on 2 of 4 surveys (quadrats seed 7 at 10 Hz: 21 -> 36 cm)."""
    heading_update_s: float = 1.0
    """Heading residuals are taken at most this often (their errors are correlated)."""
    initial_heading_sigma_rad: float = math.radians(10.0)
    scale_sigma: float = 0.03
    """Relative error of the registered steps' length (the chain's scale: slant to
    ground range through an uncertain altitude and tilt, the registration's pull of the
    static fan edge towards no motion): 1.5-4 % measured along lanes of simulated field
    days against the truth, before each ping was projected with the line array's cone
    beams and its own attitude and registered against a keyframe. Since, the chain's
    length over 20 s of straight travel errs by 0.15-0.43 % RMS (7 surveys at 2, 5 and
    10 Hz; the farm's p10/p90 -0.65/+0.47 %). A prior of 0.5-1 % was tried on two 2 Hz
    surveys: live lanes 15.5 -> 12.8-14.5 cm and 11.6 -> 11.2-11.4 cm, but on the first
    the live mosaic's quadrat spacing went from 1.3 to 11-17 cm; not taken until that is
    understood."""
    scale_walk: float = 0.0005
    """Its random walk, 1/sqrt(s) (the altitude changes over a survey)."""


class LiveAnchor:
    """Feed the chain's steps and residuals in time order; read ``correction`` and
    ``heading`` at any time reached."""

    def __init__(self, params: AnchorParams | None = None) -> None:
        self.params = params or AnchorParams()
        p = self.params
        self.x = np.zeros(_N)
        self.P = np.diag(
            [p.initial_sigma_m**2] * 2
            + [p.gnss_bias_sigma_m**2] * 2
            + [p.initial_heading_sigma_rad**2, p.rate_sigma_rps**2, p.scale_sigma**2]
        )
        self.time: float | None = None
        self._last_heading_update = -math.inf
        self.bends = np.zeros(3)
        """Sum of the map bends followed (``shift``): a frame drawn earlier keeps the
        correction of its own place on the map, not the bends met since."""

    # -- time and the chain ---------------------------------------------------------------
    def predict(self, time: float, gyro: bool = True) -> None:
        """Advance the state to ``time`` (s); earlier times leave it where it is.
        ``gyro``: the chain's heading came from the gyro since the state's time (else from
        the registrations: ``registered_heading_density``, no rate error)."""
        p = self.params
        if self.time is None:
            self.time = time
            return
        dt = time - self.time
        if dt <= 0:
            return
        phi = math.exp(-dt / p.gnss_bias_tau_s)
        f = np.eye(_N)
        f[2, 2] = f[3, 3] = phi
        f[_H, _R] = dt if gyro else 0.0
        heading_density = p.heading_drift_density if gyro else p.registered_heading_density
        q = np.diag(
            [p.drift_density**2 * dt] * 2
            + [p.gnss_bias_sigma_m**2 * (1 - phi * phi)] * 2
            + [heading_density**2 * dt, p.rate_walk**2 * dt, p.scale_walk**2 * dt]
        )
        self.x = f @ self.x
        self.P = f @ self.P @ f.T + q
        self.time = time

    def chain_step(
        self, step_en: tuple[float, float], sigma_m: float = 0.0, scaled: bool = True
    ) -> None:
        """The chain moved by ``step_en`` (east, north metres), laid at the heading and
        (``scaled``: a registered step) the scale the anchor estimates now: an error of
        that heading moves the position error by d(step)/d(heading) = (s_n, -s_e) per
        radian, an error of the scale by the step per unit. The estimate is unchanged
        (the step used it); the uncertainty grows with the distance along an uncertain
        heading and scale, and by ``sigma_m`` per axis for a step no registration
        measured (a bridge)."""
        f = np.eye(_N)
        f[0, _H] = step_en[1]
        f[1, _H] = -step_en[0]
        if scaled:
            f[0, _K] = step_en[0]
            f[1, _K] = step_en[1]
        self.P = f @ self.P @ f.T
        if sigma_m > 0:
            self.P[0, 0] += sigma_m**2
            self.P[1, 1] += sigma_m**2

    # -- measurements ---------------------------------------------------------------------
    def _update(self, h: Array, innovation: Array, r: Array) -> None:
        s = h @ self.P @ h.T + r
        gain = self.P @ h.T @ np.linalg.inv(s)
        self.x = self.x + gain @ innovation
        i_kh = np.eye(_N) - gain @ h
        # Joseph form: closures can be centimetres against metres of prior.
        self.P = i_kh @ self.P @ i_kh.T + gain @ r @ gain.T

    def update_position(self, time: float, residual_en: tuple[float, float]) -> None:
        """A fix minus the chain's position at the fix's time (east, north metres)."""
        self.predict(time)
        h = np.zeros((2, _N))
        h[0, 0] = h[1, 1] = h[0, 2] = h[1, 3] = 1.0
        r = np.eye(2) * self.params.gnss_white_sigma_m**2
        self._update(h, np.asarray(residual_en, float) - h @ self.x, r)

    def update_heading(self, time: float, residual_rad: float) -> None:
        """The navigation filter's heading minus the chain's (radians)."""
        p = self.params
        self.predict(time)
        if time - self._last_heading_update < p.heading_update_s:
            return
        self._last_heading_update = time
        h = np.zeros((1, _N))
        h[0, _H] = 1.0
        innovation = np.array([turn(residual_rad - float(h[0] @ self.x))])
        self._update(h, innovation, np.array([[p.heading_sigma_rad**2]]))

    def closure_innovation(self, measured: Array, covariance: Array) -> tuple[Array, Array]:
        """For a closure's measurement of (c_e, c_n, h) with its covariance (3 x 3): the
        innovation (heading wrapped) and its covariance against the current state."""
        nu = np.asarray(measured, float) - self.x[_CH]
        nu[2] = turn(float(nu[2]))
        s = self.P[np.ix_(_CH, _CH)] + covariance
        return nu, s

    def update_closure(self, measured: Array, covariance: Array) -> None:
        """Apply a closure's measurement of (c_e, c_n, h) (metres, radians) with its
        covariance (3 x 3), taken as of now."""
        h = np.zeros((3, _N))
        h[0, 0] = h[1, 1] = h[2, _H] = 1.0
        nu, _ = self.closure_innovation(measured, covariance)
        self._update(h, nu, np.asarray(covariance, float))

    def shift(self, offset: Array) -> None:
        """Move the correction (c_e, c_n, h) by a known ``offset`` (metres, radians),
        uncertainty unchanged: the final map the chain is tied to bends there (its own
        correction changed between two of its frames by this much)."""
        self.x[_CH] += np.asarray(offset, float)
        self.bends += np.asarray(offset, float)

    def inflate(self, covariance: Array) -> None:
        """Add ``covariance`` (3 x 3) to the uncertainty of (c_e, c_n, h): what the
        correction does not know about the part of the map it is about to be tied to."""
        self.P[np.ix_(_CH, _CH)] += np.asarray(covariance, float)

    def drift_covariance(self, dt: float, path_en: tuple[float, float]) -> Array:
        """How much the (c_e, c_n, h) error can change over ``dt`` seconds while the
        chain moves by ``path_en`` (east, north metres): the random walks, and the
        heading's uncertainty (with its rate's over ``dt``) turned into position by the
        path's lever (3 x 3)."""
        p = self.params
        heading_var = float(self.P[_H, _H]) + float(self.P[_R, _R]) * dt * dt
        lever = np.array([path_en[1], -path_en[0]])
        path = np.array(path_en, float)
        out = np.zeros((3, 3))
        out[:2, :2] = (
            p.drift_density**2 * dt * np.eye(2)
            + heading_var * np.outer(lever, lever)
            + float(self.P[_K, _K]) * np.outer(path, path)
        )
        out[2, 2] = p.heading_drift_density**2 * dt + float(self.P[_R, _R]) * dt * dt
        return out

    # -- what the chain gets ----------------------------------------------------------
    @property
    def scale(self) -> float:
        """What to multiply a registered step by, less one."""
        return float(self.x[_K])

    @property
    def heading(self) -> float:
        """What to add to the chain's heading (radians)."""
        return float(self.x[_H])

    @property
    def correction(self) -> tuple[float, float]:
        """What to add to the chain's position (east, north metres)."""
        return float(self.x[0]), float(self.x[1])

    def correction_covariance(self) -> Array:
        """Covariance of (c_e, c_n, h) (3 x 3)."""
        return np.asarray(self.P[np.ix_(_CH, _CH)], float)
