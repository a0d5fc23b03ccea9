"""The boat's true motion: the lawnmower, speed, revisits, crab in a current, waves."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tools.sim import resolve_scenario
from tools.sim.fieldday import draw_field_day
from tools.sim.trajectory import DENSE_RATE_HZ, lawnmower, simulate_motion, wave_components


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


@pytest.mark.parametrize("seed", [1, 2])
def test_a_light_chop_rolls_and_pitches_a_small_boat(seed: int):
    """The field day's waves: roll and pitch 2-3 degrees RMS, heave a few cm, from
    sinusoids of 1.5-4 s periods."""
    s, _ = draw_field_day(resolve_scenario("quadrats"), np.random.default_rng(seed))
    assert 2.0 <= s.roll_deg <= 3.0 and 2.0 <= s.pitch_deg <= 3.0
    assert 0.02 <= s.heave_m <= 0.05
    periods = wave_components(s)
    assert np.all((periods >= 1.5) & (periods <= 4.0))
    _, motion = simulate_motion(s, np.random.default_rng(seed))
    roll = np.degrees(motion.roll)
    assert np.std(roll) == pytest.approx(s.roll_deg, rel=0.3)
    trim = s.trim_deg * (np.hypot(motion.vel_east, motion.vel_north) / s.speed_mps) ** 2
    assert np.std(np.degrees(motion.pitch) - trim) == pytest.approx(s.pitch_deg, rel=0.3)
    assert np.std(motion.up) == pytest.approx(s.heave_m, rel=0.3)
    spectrum = np.abs(np.fft.rfft(roll - roll.mean())) ** 2
    freq = np.fft.rfftfreq(len(roll), 1.0 / DENSE_RATE_HZ)
    peak = 1.0 / freq[1 + int(np.argmax(spectrum[1:]))]
    assert 1.5 <= peak <= 4.0


@pytest.mark.parametrize(("name", "longest_s"), [("quadrats", 300.0), ("farm", 1200.0)])
def test_slow_surveys_revisit_the_neighbouring_lane_within_two_minutes(name, longest_s):
    """0.3-0.5 m/s, and the seabed under the middle of a lane is seen again from the next
    lane 30-120 s later; the quadrats survey takes under 5 minutes."""
    s = resolve_scenario(name)
    assert 0.3 <= s.speed_mps <= 0.5
    path, motion = simulate_motion(s, np.random.default_rng(4))
    assert motion.end - motion.start < longest_s
    passes = []
    for e0, n0, e1, n1 in path.lanes:
        middle = np.hypot(motion.east - (e0 + e1) / 2, motion.north - (n0 + n1) / 2)
        passes.append(float(motion.time[int(np.argmin(middle))]))
    revisits = np.diff(passes)
    assert np.all((revisits > 30.0) & (revisits < 120.0)), revisits
