"""The live anchor: the chain's heading and scale errors show as position uncertainty
where the chain goes, a bridge adds its own, and a closure pulls the correction onto the
map while the GNSS bias takes what the receiver said instead."""

from __future__ import annotations

import math

import numpy as np

from mapping.live_anchor import AnchorParams, LiveAnchor


def settled(seconds: int = 300) -> LiveAnchor:
    """An anchor after ``seconds`` of 1 Hz fixes and compass at rest."""
    rng = np.random.default_rng(1)
    anchor = LiveAnchor(AnchorParams())
    for t in range(seconds):
        fix = rng.normal(0.0, 0.6, 2)
        anchor.update_position(float(t), (float(fix[0]), float(fix[1])))
        anchor.update_heading(float(t), float(rng.normal(0.0, math.radians(1.0))))
    return anchor


def test_a_lane_north_grows_the_uncertainty_across_it_by_the_heading_along_by_the_scale() -> None:
    anchor = settled()
    before = anchor.correction_covariance()
    heading_var = float(before[2, 2])
    scale_var = float(anchor.P[6, 6])
    for _ in range(80):  # 16 m north in 0.2 m steps, no time passing
        anchor.chain_step((0.0, 0.2))
    after = anchor.correction_covariance()
    # Across the lane (east): the heading's lever; along it (north): the scale's.
    np.testing.assert_allclose(after[0, 0] - before[0, 0], 16.0**2 * heading_var, rtol=0.05)
    np.testing.assert_allclose(after[1, 1] - before[1, 1], 16.0**2 * scale_var, rtol=0.05)


def test_a_bridge_adds_its_own_uncertainty() -> None:
    anchor = settled()
    before = anchor.correction_covariance()
    anchor.chain_step((0.0, 0.0), sigma_m=0.12)
    after = anchor.correction_covariance()
    np.testing.assert_allclose(np.diag(after - before)[:2], [0.12**2] * 2, rtol=1e-9)


def test_a_closure_pulls_the_correction_and_the_bias_takes_the_fixes() -> None:
    anchor = settled()
    c_before = np.array(anchor.correction)
    gnss_before = anchor.x[0:2] + anchor.x[2:4]  # what the anchor expects a fix to say
    target = c_before + np.array([0.6, -0.4])
    covariance = np.diag([0.03**2, 0.03**2, math.radians(0.5) ** 2])
    anchor.update_closure(np.array([*target, anchor.heading]), covariance)
    # The correction goes (nearly) all the way: the map is centimetres, the anchor's own
    # knowledge of where the chain sits decimetres.
    np.testing.assert_allclose(anchor.correction, target, atol=0.02)
    # The receiver did not change its mind: the bias took the difference.
    gnss_after = anchor.x[0:2] + anchor.x[2:4]
    assert np.linalg.norm(gnss_after - gnss_before) < 0.25 * np.linalg.norm(target - c_before)
    assert np.sqrt(anchor.correction_covariance()[0, 0]) < 0.035
