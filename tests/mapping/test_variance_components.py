"""The GNSS fixes' Doppler velocity in the survey-wide fusion, and variance components,
on the synthetic lawnmower of ``test_fusion``:

- the velocity (the course over the ground, free of the position's wander) fixes the
  map's heading, and checks each registration's translation;
- a group of measurements whose residuals scatter more than their covariances say is
  widened to what they say (registrations stated at millimetres that are a fifth short
  of the way travelled give way); one as good as it says keeps its weight."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import replace

import numpy as np

from mapping.fusion import Fusion
from mapping.single_stage import _widen_to_residuals
from tests.mapping.test_fusion import _path, _survey

LAG_S = 0.15  # the synthetic receiver's lag (test_fusion)


def _rms(est: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((est[:, :2] - truth[:, :2]) ** 2, axis=1))))


def _short(constraints, factor: float):
    return [
        replace(c, forward_m=c.forward_m * factor, starboard_m=c.starboard_m * factor)
        for c in constraints
    ]


def _with_velocity(data, noise_mps: float = 0.05, seed: int = 7):
    """The fixes with a Doppler velocity: the antenna's at the fix's lagged time plus
    white noise (a u-blox M8N states 0.05 m/s)."""
    rng = np.random.default_rng(seed)
    t = data.gnss_times
    step = 0.01
    before = _path(t - LAG_S - step)[:, :2]
    after = _path(t - LAG_S + step)[:, :2]
    velocity = (after - before) / (2 * step) + rng.normal(0.0, noise_mps, (t.size, 2))
    return dataclasses.replace(data, gnss_velocity=velocity)


def test_the_doppler_velocity_finds_the_heading_the_compass_is_off_by() -> None:
    """A lawnmower with the compass 4 degrees off and its GNSS positions wandering by a
    metre: from the positions alone the map's heading is found to 2-3 degrees; with each
    fix's Doppler velocity (the course over the ground, free of the wander) the
    registrations' direction of travel pins it to a few tenths."""
    for seed in (3, 4, 5):
        times, truth, data, constraints, initial = _survey(5.0, seed=seed)
        errors = []
        for d in (data, _with_velocity(data, seed=seed)):
            solution, _ = Fusion(times, d).solve(initial, constraints)
            e = (solution.poses[:, 2] - truth[:, 2] + math.pi) % (2 * math.pi) - math.pi
            errors.append(math.degrees(float(np.sqrt(np.mean(e**2)))))
        assert errors[0] > 1.5
        assert errors[1] < 0.5


def test_measurements_as_good_as_they_say_keep_their_weight() -> None:
    times, _, data, constraints, initial = _survey(5.0)
    data = _with_velocity(data)
    fusion = Fusion(times, data)
    stated, _ = fusion.solve(initial, constraints)
    chain, factors, solved = _widen_to_residuals(fusion, initial, list(constraints), 4)
    assert all(v == 1.0 for k, v in factors.items() if k != "rounds")
    assert all(a is b for a, b in zip(chain, constraints, strict=True))
    if solved is not None:  # a group narrowed on the way, and was put back
        assert np.allclose(solved[0].poses, stated.poses, atol=1e-6)


def test_registrations_short_of_the_way_travelled_give_way() -> None:
    """Registrations a fifth short of the way travelled (locked towards no motion on a
    faint bottom) but stated at 3 mm: the fixes' velocities say otherwise; the
    translations' factor grows and the map moves towards the truth."""
    times, truth, data, constraints, initial = _survey(5.0)
    data = _with_velocity(data)
    short = _short(constraints, 0.8)
    fusion = Fusion(times, data)
    believed, _ = fusion.solve(initial, short)
    chain, factors, solved = _widen_to_residuals(fusion, initial, list(short), 4)
    assert solved is not None
    widened, _ = solved
    assert factors["translation"] > 2.0
    assert factors["yaw"] == 1.0
    assert _rms(widened.poses, truth) < _rms(believed.poses, truth) - 0.03
    ratio = math.sqrt(factors["translation"])
    for a, b in zip(chain, short, strict=True):
        assert np.allclose(a.sqrt_info[:, :2] * ratio, b.sqrt_info[:, :2])
        assert np.allclose(a.sqrt_info[:, 2], b.sqrt_info[:, 2])
