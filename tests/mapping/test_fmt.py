"""FMT registration recovers known motions of sonar-like frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.fmt import FmtRegistrar
from mapping.se2 import RelativePose
from tests.mapping import synth
from tests.mapping import test_fmt_bed as bed


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, object, np.ndarray]:
    rng = np.random.default_rng(7)
    grid, mask = synth.fan()
    return synth.seabed(rng), grid, mask


def motions(seed: int, count: int) -> list[tuple[float, float, float]]:
    rng = np.random.default_rng(seed)
    return [
        (rng.uniform(-0.3, 0.3), rng.uniform(-0.15, 0.15), math.radians(rng.uniform(-4, 4)))
        for _ in range(count)
    ]


def frame_pair(scene, forward, starboard, yaw, heading, rng):
    world, grid, mask = scene
    e0, n0 = 8.0, 6.0
    s, c = math.sin(heading), math.cos(heading)
    e1 = e0 + forward * s + starboard * c
    n1 = n0 + forward * c - starboard * s
    a = synth.view(world, grid, mask, e0, n0, heading, rng)
    b = synth.view(world, grid, mask, e1, n1, heading + yaw, rng)
    return a, b


def test_recovers_known_shifts_and_rotations_within_a_pixel_and_a_tenth_of_a_degree(scene):
    _, grid, mask = scene
    registrar = FmtRegistrar(grid, mask)
    rng = np.random.default_rng(11)
    errors = []
    for forward, starboard, yaw in motions(3, 12):
        a, b = frame_pair(scene, forward, starboard, yaw, rng.uniform(0, 2 * math.pi), rng)
        result = registrar.register(registrar.prepare(a), registrar.prepare(b))
        rel = result.relative
        errors.append(
            (rel.forward_m - forward, rel.starboard_m - starboard, math.degrees(rel.yaw_rad - yaw))
        )
    err = np.abs(np.array(errors))
    assert err[:, 0].max() < grid.res_m, err[:, 0]
    assert err[:, 1].max() < grid.res_m, err[:, 1]
    assert err[:, 2].max() < 0.1, err[:, 2]


def test_a_prior_near_the_motion_finds_it(scene):
    _, grid, mask = scene
    registrar = FmtRegistrar(grid, mask)
    rng = np.random.default_rng(5)
    a, b = frame_pair(scene, 0.12, -0.05, math.radians(1.5), 0.7, rng)
    prior = RelativePose(0.10, -0.02, math.radians(1.0))
    result = registrar.register(
        registrar.prepare(a), registrar.prepare(b), prior, prior_sigma_m=0.1
    )
    assert abs(result.relative.forward_m - 0.12) < grid.res_m
    assert abs(result.relative.starboard_m + 0.05) < grid.res_m
    assert result.score > 0.05


def test_unrelated_frames_score_low(scene):
    world, grid, mask = scene
    registrar = FmtRegistrar(grid, mask)
    rng = np.random.default_rng(9)
    a = synth.view(world, grid, mask, 4.0, 3.0, 0.0, rng)
    b = synth.view(world, grid, mask, 12.0, 11.0, 2.0, rng)
    same = synth.view(world, grid, mask, 4.0, 3.0, 0.0, rng)
    unrelated = registrar.register(registrar.prepare(a), registrar.prepare(b))
    related = registrar.register(registrar.prepare(a), registrar.prepare(same))
    assert related.score > 3 * max(unrelated.score, 0.01)


@pytest.mark.parametrize("search", ["search_m", "prior_sigma_m"])
def test_a_prior_half_a_metre_and_a_degree_and_a_half_off_does_not_hide_the_motion(search):
    """The EKF's frame-to-frame yaw a degree and a half off puts the peak 0.4 m from where
    it predicts: the whole surface is searched, the prior only weighs the peaks (also
    when given the way callers used to give a search window)."""
    sonar = bed.Sonar()
    seabed = bed.make_seabed(np.random.default_rng(21))
    rng = np.random.default_rng(22)
    registrar = sonar.registrar()
    start = (7.0, 6.5, 0.4)
    truth = RelativePose(0.25, 0.04, math.radians(2.0))
    earlier = registrar.prepare(sonar.frame(seabed, start, rng))
    later = registrar.prepare(sonar.frame(seabed, bed.moved(start, truth), rng))
    # 0.4 m off where the fan is (3.7 m out): 0.33 m forward, 0.1 m and 1.5 degrees aside.
    prior = RelativePose(truth.forward_m - 0.33, truth.starboard_m + 0.1, truth.yaw_rad - 0.026)
    if search == "search_m":
        result = registrar.register(earlier, later, prior, 0.15)
    else:
        result = registrar.register(earlier, later, prior, prior_sigma_m=0.15)
    rel = result.relative
    assert abs(rel.forward_m - truth.forward_m) < 0.5 * sonar.grid.res_m
    assert abs(rel.starboard_m - truth.starboard_m) < 0.5 * sonar.grid.res_m
    assert abs(math.degrees(rel.yaw_rad - truth.yaw_rad)) < 0.1
    assert result.score > 0.2


def test_results_carry_a_covariance_and_themselves_as_the_first_hypothesis(scene):
    _, grid, mask = scene
    registrar = FmtRegistrar(grid, mask)
    rng = np.random.default_rng(5)
    a, b = frame_pair(scene, 0.12, -0.05, math.radians(1.5), 0.7, rng)
    result = registrar.register(registrar.prepare(a), registrar.prepare(b))
    assert result.covariance is not None and result.covariance.shape == (3, 3)
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)
    (only,) = result.hypotheses
    assert only.relative == result.relative and only.score == result.score
