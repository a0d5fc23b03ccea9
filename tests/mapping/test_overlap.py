"""Loop closures registered again on the seabed both frames share
(``mapping.overlap``): opposite views of a rippled bed, whose relief shades the other way
round, refine to the true pose from where the registrar left them."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from mapping.overlap import OverlapRefiner
from mapping.se2 import RelativePose, relative_pose
from tests.mapping import synth

F32 = npt.NDArray[np.float32]


def _relief_gradient(rng: np.random.Generator, size_px: int = 1600) -> tuple[F32, F32]:
    """East and north slopes of sand ripples (0.3 m, crests bent) at 1 cm."""
    y, x = np.mgrid[0:size_px, 0:size_px].astype(np.float32) * np.float32(synth.WORLD_RES_M)
    bend = cv2.resize(
        rng.standard_normal((10, 10)).astype(np.float32), (size_px, size_px), cv2.INTER_CUBIC
    )
    # Rows run from north to south in the world raster: north = size - y.
    north = size_px * synth.WORLD_RES_M - y
    height = 0.01 * np.sin(2 * np.pi * (0.6 * x + 0.8 * north + 0.05 * bend) / 0.3)
    slope_north, slope_east = np.gradient(height, synth.WORLD_RES_M)
    return slope_east.astype(np.float32), (-slope_north).astype(np.float32)


@pytest.fixture(scope="module")
def bed() -> tuple[F32, F32, F32]:
    rng = np.random.default_rng(11)
    reflectivity = synth.seabed(rng)
    east, north = _relief_gradient(rng)
    return reflectivity, east, north


def _frame(
    bed: tuple[F32, F32, F32], pose: tuple[float, float, float], rng: np.random.Generator
) -> F32:
    """Reflectivity plus the relief's slope along the look (Lambert shading), speckled."""
    reflectivity, slope_east, slope_north = bed
    grid, mask = synth.fan()
    albedo = synth.view(reflectivity, grid, mask, *pose)
    look = math.sin(pose[2]) * synth.view(slope_east, grid, mask, *pose) + math.cos(
        pose[2]
    ) * synth.view(slope_north, grid, mask, *pose)
    image = np.maximum(0.1 + albedo + 0.8 * look, 0.0)
    image = image * rng.gamma(10.0, 0.1, image.shape).astype(np.float32)
    # The beams' width and the preprocessing's denoising: speckle a pixel or two wide.
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    return np.where(mask, image, 0.0).astype(np.float32)


EARLIER = (8.0, 4.0, 0.0)  # looking north
LATER = (8.3, 11.0, math.pi + 0.03)  # seven metres on, looking back south


@pytest.mark.parametrize(
    "later",
    [LATER, (8.5, 10.7, math.pi - 0.02), (7.6, 11.2, math.pi + 0.05), (8.1, 4.4, 0.02)],
    ids=["opposite", "opposite-right", "opposite-left", "same-heading"],
)
@pytest.mark.parametrize(
    "start_error",
    [(0.07, 0.0, 0.0), (0.0, -0.07, 0.0), (0.05, 0.04, 0.6), (-0.04, 0.0, -0.8)],
    ids=["forward", "starboard", "both-and-yaw", "back-and-yaw"],
)
def test_a_closure_refines_to_the_true_pose(bed, later, start_error):
    rng = np.random.default_rng(5)
    grid, mask = synth.fan()
    earlier, moved = _frame(bed, EARLIER, rng), _frame(bed, later, rng)
    truth = relative_pose(np.array(EARLIER), np.array(later))
    start = RelativePose(
        truth.forward_m + start_error[0],
        truth.starboard_m + start_error[1],
        truth.yaw_rad + math.radians(start_error[2]),
    )
    refined = OverlapRefiner(grid, mask).refine(earlier, moved, start)
    assert refined is not None
    assert abs(refined.forward_m - truth.forward_m) < 0.012
    assert abs(refined.starboard_m - truth.starboard_m) < 0.012
    yaw_error = math.remainder(refined.yaw_rad - truth.yaw_rad, 2 * math.pi)
    assert abs(math.degrees(yaw_error)) < 0.2


def test_fans_that_share_too_little_seabed_are_left_as_they_are(bed):
    grid, mask = synth.fan()
    rng = np.random.default_rng(2)
    earlier = _frame(bed, EARLIER, rng)
    away = (8.0, 15.0, 0.0)
    later = _frame(bed, away, rng)
    far = relative_pose(np.array(EARLIER), np.array(away))
    assert OverlapRefiner(grid, mask).refine(earlier, later, far) is None
