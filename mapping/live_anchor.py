"""Where the live chain sits: a small Kalman filter that ties the registration chain to the
GNSS and the heading filter without bending it to their wander.

The live map is the chain of registrations (bridged by the filter's dead reckoning where a
registration is missing). Left alone the chain drifts; pulled to every fix it copies the
receiver's wander, and two passes over the same seabed a minute apart then disagree by
the change of the GNSS bias (a metre). So the chain carries a correction whose model is
physical (Farrell, *Aided Navigation*, 2008, Sec. 4.9; a complementary filter whose gain
comes from the noise models): the chain's own drift is a slow random walk
(``drift_density``), the GNSS error a first-order Gauss-Markov bias (sigma, tau) plus
white noise. Each fix's residual against the chain updates both; the correction takes up
only what is slower than the bias, so the live map keeps the chain's shape between lanes.

Translation: states (c_e, c_n, b_e, b_n), metres. Heading: the chain's heading error and
its rate (a gyro bias the navigation filter has not fully found), against the filter's
heading (whose own error, a compass bias and its wander, is correlated too: its sigma
stands for that).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


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
    rate_sigma_rps: float = math.radians(0.1)
    """Initial sigma of the chain's heading rate error (a gyro bias residual)."""
    rate_walk: float = math.radians(0.002)
    """Its random walk, rad/s/sqrt(s)."""
    heading_sigma_rad: float = math.radians(3.0)
    """Error of the navigation filter's heading as the correction sees it (compass
    misalignment and deviation, correlated over minutes)."""
    heading_update_s: float = 1.0
    """Heading residuals are taken at most this often (their errors are correlated)."""


class LiveAnchor:
    """Feed the chain's residuals in time order; read ``correction`` at any time reached."""

    def __init__(self, params: AnchorParams | None = None) -> None:
        self.params = params or AnchorParams()
        p = self.params
        self.x = np.zeros(4)
        self.P = np.diag([p.initial_sigma_m**2] * 2 + [p.gnss_bias_sigma_m**2] * 2)
        self.time: float | None = None
        # Heading: the chain's heading error and its rate (what is left of the gyro bias
        # after the navigation filter's estimate of it turns the chain steadily).
        self.heading_x = np.zeros(2)
        self.heading_P = np.diag([math.radians(10.0) ** 2, p.rate_sigma_rps**2])
        self._heading_time: float | None = None
        self._last_heading_update = -math.inf

    def _predict(self, time: float) -> None:
        p = self.params
        if self.time is None:
            self.time = time
            return
        dt = time - self.time
        if dt <= 0:
            return
        phi = math.exp(-dt / p.gnss_bias_tau_s)
        f = np.diag([1.0, 1.0, phi, phi])
        q = np.diag([p.drift_density**2 * dt] * 2 + [p.gnss_bias_sigma_m**2 * (1 - phi * phi)] * 2)
        self.x = f @ self.x
        self.P = f @ self.P @ f.T + q
        self.time = time

    def update_position(self, time: float, residual_en: tuple[float, float]) -> None:
        """A fix minus the chain's position at the fix's time (east, north metres)."""
        self._predict(time)
        h = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]])
        r = np.eye(2) * self.params.gnss_white_sigma_m**2
        s = h @ self.P @ h.T + r
        gain = self.P @ h.T @ np.linalg.inv(s)
        self.x = self.x + gain @ (np.asarray(residual_en, float) - h @ self.x)
        self.P = (np.eye(4) - gain @ h) @ self.P

    def update_heading(self, time: float, residual_rad: float) -> None:
        """The navigation filter's heading minus the chain's (radians)."""
        p = self.params
        if self._heading_time is not None:
            dt = max(time - self._heading_time, 0.0)
            f = np.array([[1.0, dt], [0.0, 1.0]])
            q = np.diag([p.heading_drift_density**2 * dt, p.rate_walk**2 * dt])
            self.heading_x = f @ self.heading_x
            self.heading_P = f @ self.heading_P @ f.T + q
        self._heading_time = time
        if time - self._last_heading_update < p.heading_update_s:
            return
        self._last_heading_update = time
        innovation = math.remainder(residual_rad - float(self.heading_x[0]), 2 * math.pi)
        s = float(self.heading_P[0, 0]) + p.heading_sigma_rad**2
        gain = self.heading_P[:, 0] / s
        self.heading_x = self.heading_x + gain * innovation
        self.heading_P = self.heading_P - np.outer(gain, self.heading_P[0, :])

    @property
    def heading(self) -> float:
        """What to add to the chain's heading (radians)."""
        return float(self.heading_x[0])

    @property
    def correction(self) -> tuple[float, float]:
        """What to add to the chain's position (east, north metres)."""
        return float(self.x[0]), float(self.x[1])
