"""The quadrat locator finds the frames however far the georeferencing is off, and the
spacing error measures only the geometry between them."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mapping.metrics import Quadrat, locate_quadrats, quadrat_spacing_error

RES = 0.02


def layout(bearing_deg: float) -> list[Quadrat]:
    """The paper's 2 x 4 array around (500, 500) m: 0.43 m and 0.62 m frames, 1 m apart
    in a row, rows 1.52 m apart between nearest sides."""
    b = math.radians(bearing_deg)
    along = np.array([math.sin(b), math.cos(b)])
    across = np.array([math.cos(b), -math.sin(b)])
    out = []
    gap = 1.52 + (0.43 + 0.62) / 2
    for row, side in enumerate((0.43, 0.62)):
        for i in range(4):
            centre = np.array([500.0, 500.0]) + (i - 1.5) * along + row * gap * across
            out.append(Quadrat(float(centre[0]), float(centre[1]), side, row, i, b))
    return out


def draw(quadrats: list[Quadrat], shift: tuple[float, float], rng: np.random.Generator):
    west, north = 490.0, 510.0
    size = round(20 / RES)
    image = rng.normal(0.4, 0.08, (size, size)).astype(np.float32)
    for q in quadrats:
        corners = []
        for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            along = np.array([math.sin(q.orientation_rad), math.cos(q.orientation_rad)])
            across = np.array([math.cos(q.orientation_rad), -math.sin(q.orientation_rad)])
            p = np.array([q.east, q.north]) + shift + q.side_m / 2 * (du * along + dv * across)
            corners.append([(p[0] - west) / RES - 0.5, (north - p[1]) / RES - 0.5])
        cv2.polylines(
            image, [np.round(np.array(corners) * 4).astype(np.int32)], True, 0.95, 2, cv2.LINE_AA, 2
        )
    return np.clip(image, 0, 1), west, north


@pytest.mark.parametrize("shift", [(0.3, -0.4), (2.6, 0.8), (-1.2, -3.1)])
def test_quadrats_are_found_whatever_the_offset(shift: tuple[float, float]) -> None:
    quadrats = layout(78.0)
    image, west, north = draw(quadrats, shift, np.random.default_rng(1))
    found = locate_quadrats(image, np.ones(image.shape, bool), west, north, RES, quadrats)
    assert all(f is not None for f in found)
    offsets = np.array(
        [(f[0] - q.east, f[1] - q.north) for q, f in zip(quadrats, found, strict=True) if f]
    )
    np.testing.assert_allclose(offsets.mean(axis=0), shift, atol=0.02)
    spacing = quadrat_spacing_error(quadrats, found)
    assert spacing["located"] == 8 and spacing["pairs"] == 28
    assert spacing["rmse"] < 0.01


def test_spacing_error_sees_a_misplaced_frame() -> None:
    quadrats = layout(0.0)
    found = [(q.east + 0.5, q.north - 0.2, 1.0) for q in quadrats]
    assert quadrat_spacing_error(quadrats, found)["rmse"] < 1e-9  # a common shift is no error
    found[3] = (found[3][0] + 0.1, found[3][1], 1.0)
    result = quadrat_spacing_error(quadrats, found)
    assert 0.02 < result["rmse"] < 0.1
