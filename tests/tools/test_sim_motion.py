"""The boat's true motion: the lawnmower, speed, crab in a current, waves."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tools.sim import resolve_scenario
from tools.sim.trajectory import lawnmower, simulate_motion


def _on_lanes(motion, speed_mps: float):
    """Samples in steady straight running (away from turns and the start and stop)."""
    turn_rate = np.abs(np.gradient(np.unwrap(motion.course), motion.time))
    speed = np.hypot(motion.vel_east, motion.vel_north)
    return (turn_rate < 0.02) & (speed > 0.8 * speed_mps)


def angle_diff_deg(a, b):
    return np.degrees(np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b)))))


def test_lawnmower_has_the_planned_lanes_and_turns():
    s = resolve_scenario("quadrats")
    path = lawnmower(s)
    assert len(path.lanes) == s.n_lanes
    for k, (e0, n0, e1, n1) in enumerate(path.lanes):
        assert math.hypot(e1 - e0, n1 - n0) == pytest.approx(s.lane_length_m)
        assert e0 == pytest.approx((k - (s.n_lanes - 1) / 2) * s.lane_spacing_m)
    turns = [seg for seg in path.segments if seg.turn != 0]
    assert all(seg.radius == pytest.approx(s.turn_radius_m) for seg in turns)
    # Right turn after the first lane, left after the second.
    assert [seg.turn for seg in turns] == [1, -1]


def test_boat_starts_and_ends_at_rest_and_surveys_at_speed():
    s = resolve_scenario("quadrats")
    _, motion = simulate_motion(s, np.random.default_rng(1))
    speed = np.hypot(motion.vel_east, motion.vel_north)
    assert speed[0] < 0.05 and speed[-1] < 0.05
    lanes = _on_lanes(motion, s.speed_mps)
    assert np.mean(speed[lanes]) == pytest.approx(s.speed_mps, rel=0.05)
    # The antenna height above water moves with the heave only.
    assert np.std(motion.up) == pytest.approx(s.heave_m, rel=0.5)


def test_heading_wobbles_a_few_degrees_and_roll_pitch_are_small():
    s = resolve_scenario("quadrats")
    _, motion = simulate_motion(s, np.random.default_rng(2))
    lanes = _on_lanes(motion, s.speed_mps)
    wobble = angle_diff_deg(motion.heading[lanes], motion.course[lanes])
    assert 0.8 < np.std(wobble) < 4.0
    assert 0.5 < np.degrees(np.std(motion.roll)) < 3.0
    assert np.degrees(np.max(np.abs(motion.pitch))) < 8.0


@pytest.mark.parametrize(("name", "crab_deg"), [("quadrats", 0.0), ("quadrats-current", 9.1)])
def test_in_a_cross_current_the_heading_differs_from_the_course(name, crab_deg):
    s = resolve_scenario(name)
    _, motion = simulate_motion(s, np.random.default_rng(3))
    lanes = _on_lanes(motion, s.speed_mps)
    # Lanes alternate direction, so the crab's sign alternates: look at its size per lane.
    northbound = lanes & (np.cos(motion.course) > 0.9)
    southbound = lanes & (np.cos(motion.course) < -0.9)
    for sel in (northbound, southbound):
        crab = abs(float(np.mean(angle_diff_deg(motion.heading[sel], motion.course[sel]))))
        assert crab == pytest.approx(crab_deg, abs=1.0)
    expected = math.degrees(math.atan2(s.current_mps, s.speed_mps))
    assert crab_deg == pytest.approx(expected, abs=0.5)
