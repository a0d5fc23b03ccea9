"""The registration's covariance is calibrated: on pairs of known motion, errors over
the predicted sigma have an RMS near 1 (the pose graph weights each edge by it)."""

from __future__ import annotations

import math

import numpy as np

from mapping.se2 import RelativePose
from tests.mapping import test_fmt_bed as bed


def _pairs(count: int, seed: int) -> list[RelativePose]:
    """Consecutive-frame motions at 10 Hz and at 2 Hz, turning either way."""
    rng = np.random.default_rng(seed)
    motions = []
    for k in range(count):
        fast = k % 2 == 0
        forward = rng.uniform(0.02, 0.1) if fast else rng.uniform(0.1, 0.3)
        starboard = rng.uniform(-0.02, 0.02) if fast else rng.uniform(-0.05, 0.05)
        yaw = rng.uniform(0.1, 0.5) if fast else rng.uniform(1.0, 4.0)
        motions.append(RelativePose(forward, starboard, math.radians(yaw * rng.choice([-1, 1]))))
    return motions


def test_normalised_errors_have_an_rms_near_one() -> None:
    sonar = bed.Sonar()
    seabed = bed.make_seabed(np.random.default_rng(1))
    registrar = sonar.registrar()
    rng = np.random.default_rng(31)
    normalised, mahalanobis = [], []
    for truth in _pairs(40, 32):
        start = (rng.uniform(6.5, 7.5), rng.uniform(6.5, 7.5), rng.uniform(0, 2 * math.pi))
        earlier = registrar.prepare(sonar.frame(seabed, start, rng))
        later = registrar.prepare(sonar.frame(seabed, bed.moved(start, truth), rng))
        result = registrar.register(earlier, later, truth, prior_sigma_m=0.1)
        assert result.covariance is not None
        rel = result.relative
        error = np.array(
            [
                rel.forward_m - truth.forward_m,
                rel.starboard_m - truth.starboard_m,
                rel.yaw_rad - truth.yaw_rad,
            ]
        )
        normalised.append(error / np.sqrt(np.diag(result.covariance)))
        mahalanobis.append(float(error @ np.linalg.solve(result.covariance, error)))
    rms = np.sqrt(np.mean(np.square(normalised), axis=0))
    # Each axis within a factor 1.5 of calibrated, and jointly (3 degrees of freedom,
    # correlations included: yaw and starboard are strongly coupled at the sonar).
    assert np.all((rms > 1 / 1.5) & (rms < 1.5)), rms
    assert 3 / 1.5**2 < np.mean(mahalanobis) < 3 * 1.5**2, np.mean(mahalanobis)
