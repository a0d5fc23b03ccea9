"""The sonar mount moves a registration's covariance into the vehicle frame the way it
moves the registration itself."""

from __future__ import annotations

import math

import numpy as np

from mapping.frames import SonarMount
from mapping.se2 import RelativePose


def test_vehicle_covariance_matches_the_numerical_jacobian() -> None:
    mount = SonarMount(forward_m=-0.45, starboard_m=0.12, yaw_rad=math.radians(20.0))
    step = 1e-6
    jac = np.zeros((3, 3))
    base = mount.vehicle_relative(RelativePose(0.0, 0.0, 0.0))
    for k in range(3):
        d = np.zeros(3)
        d[k] = step
        moved = mount.vehicle_relative(RelativePose(*d))
        jac[:, k] = (
            np.array([moved.forward_m, moved.starboard_m, moved.yaw_rad])
            - np.array([base.forward_m, base.starboard_m, base.yaw_rad])
        ) / step
    cov = np.diag([0.008**2, 0.003**2, math.radians(0.1) ** 2])
    np.testing.assert_allclose(mount.vehicle_covariance(cov), jac @ cov @ jac.T, rtol=1e-4)
