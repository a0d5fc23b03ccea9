"""The quadrat locator finds the frames however far the georeferencing is off, and the
spacing error measures only the geometry between them."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tools.evaluation.metrics import (
    Quadrat,
    array_offsets,
    displacement_field,
    locate_quadrats,
    quadrat_spacing_error,
)

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


def array_layout(centre: tuple[float, float], bearing_deg: float, array: int) -> list[Quadrat]:
    """A 2 x 4 array like ``layout`` around ``centre``, tagged with its array index."""
    shift = np.array(centre) - 500.0
    return [
        Quadrat(
            q.east + shift[0],
            q.north + shift[1],
            q.side_m,
            q.row,
            q.index,
            q.orientation_rad,
            array,
        )
        for q in layout(bearing_deg)
    ]


def draw_at(
    quadrats: list[Quadrat],
    places: list[tuple[float, float]],
    bounds: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> tuple[np.ndarray, float, float]:
    """Quadrat outlines drawn centred at ``places`` (UTM) on noisy sand; bounds (west,
    south, east, north)."""
    west, south, east, north = bounds
    image = rng.normal(0.4, 0.08, (round((north - south) / RES), round((east - west) / RES)))
    image = image.astype(np.float32)
    for q, (pe, pn) in zip(quadrats, places, strict=True):
        along = np.array([math.sin(q.orientation_rad), math.cos(q.orientation_rad)])
        across = np.array([math.cos(q.orientation_rad), -math.sin(q.orientation_rad)])
        corners = []
        for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            p = np.array([pe, pn]) + q.side_m / 2 * (du * along + dv * across)
            corners.append([(p[0] - west) / RES - 0.5, (north - p[1]) / RES - 0.5])
        cv2.polylines(
            image, [np.round(np.array(corners) * 4).astype(np.int32)], True, 0.95, 2, cv2.LINE_AA, 2
        )
    return np.clip(image, 0, 1), west, north


def test_a_map_on_a_gnss_offset_scores_no_spacing_error_and_gives_the_offset_back() -> None:
    # 1.7 m along rows 1 m apart: the layout also fits 0.7 m and 2.7 m off, six frames of
    # eight; the frames' own matches must pick 1.7.
    quadrats = array_layout((500.0, 500.0), 90.0, 0)
    places = [(q.east + 1.7, q.north) for q in quadrats]
    image, west, north = draw_at(quadrats, places, (488, 490, 512, 510), np.random.default_rng(2))
    found = locate_quadrats(image, np.ones(image.shape, bool), west, north, RES, quadrats)
    spacing = quadrat_spacing_error(quadrats, found)
    assert spacing["located"] == 8 and spacing["rmse"] < 0.01
    (array,) = array_offsets(quadrats, found)
    assert array["offset_east_m"] == pytest.approx(1.7, abs=0.02)
    assert array["offset_north_m"] == pytest.approx(0.0, abs=0.02)
    assert array["offset_m"] == pytest.approx(1.7, abs=0.02)


def test_one_moved_quadrat_gives_its_spacing_error() -> None:
    quadrats = array_layout((500.0, 500.0), 78.0, 0)
    places = [(q.east - 1.2, q.north + 1.2) for q in quadrats]
    places[5] = (places[5][0] + 0.12, places[5][1] - 0.05)
    image, west, north = draw_at(quadrats, places, (488, 488, 512, 512), np.random.default_rng(3))
    found = locate_quadrats(image, np.ones(image.shape, bool), west, north, RES, quadrats)
    expected = quadrat_spacing_error(quadrats, [(e, n, 1.0) for e, n in places])
    got = quadrat_spacing_error(quadrats, found)
    assert expected["rmse"] > 0.04
    assert got["rmse"] == pytest.approx(expected["rmse"], abs=0.005)
    assert got["mae"] == pytest.approx(expected["mae"], abs=0.005)
    assert found[5] is not None
    assert found[5][0] == pytest.approx(places[5][0], abs=0.02)


def test_each_array_is_located_on_its_own_offset() -> None:
    quadrats = (
        array_layout((500.0, 500.0), 78.0, 0)
        + array_layout((512.0, 503.0), 0.0, 1)
        + array_layout((504.0, 489.0), 135.0, 2)
    )
    shifts = {0: (1.7, 0.0), 1: (-2.3, 1.1), 2: (0.6, 2.9)}
    places = [(q.east + shifts[q.array][0], q.north + shifts[q.array][1]) for q in quadrats]
    image, west, north = draw_at(quadrats, places, (490, 480, 522, 510), np.random.default_rng(4))
    found = locate_quadrats(image, np.ones(image.shape, bool), west, north, RES, quadrats)
    spacing = quadrat_spacing_error(quadrats, found)
    assert spacing["located"] == 24
    assert spacing["pairs"] == 3 * 28 and spacing["all_pairs"] == 24 * 23 / 2
    assert spacing["rmse"] < 0.01  # within each array: right
    assert spacing["all_rmse"] > 0.5  # across arrays: the different offsets show
    for entry in array_offsets(quadrats, found):
        east, north_m = shifts[int(entry["array"])]
        assert entry["offset_east_m"] == pytest.approx(east, abs=0.02)
        assert entry["offset_north_m"] == pytest.approx(north_m, abs=0.02)
        assert entry["rmse"] < 0.01 and entry["located"] == 8


def test_a_half_covered_array_is_not_placed_a_frame_off() -> None:
    # The mosaic stops short of the last column of frames: the layout one frame off along
    # the row matches as many frames as the right one, but its frames match worse.
    quadrats = array_layout((500.0, 500.0), 90.0, 0)
    places = [(q.east + 2.6, q.north - 0.8) for q in quadrats]
    image, west, north = draw_at(quadrats, places, (486, 490, 514, 510), np.random.default_rng(5))
    covered = np.ones(image.shape, bool)
    covered[:, round((504.0 - west) / RES) :] = False  # east of the third column
    found = locate_quadrats(image * covered, covered, west, north, RES, quadrats)
    located = [(q, f) for q, f in zip(quadrats, found, strict=True) if f is not None]
    assert len(located) >= 4
    for q, f in located:
        assert f[0] - q.east == pytest.approx(2.6, abs=0.03)
        assert f[1] - q.north == pytest.approx(-0.8, abs=0.03)


def _texture(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 2.0)


def test_a_turned_map_shows_its_turn_not_a_distortion() -> None:
    seabed = _texture(1024, 4)
    # The whole mosaic turned by 2 degrees about its centre and shifted: no internal error.
    turn = cv2.getRotationMatrix2D((512.0, 512.0), 2.0, 1.0)
    turn[:, 2] += (6.0, -4.0)
    mosaic = cv2.warpAffine(seabed, turn, (1024, 1024), flags=cv2.INTER_LINEAR)
    covered = np.zeros((1024, 1024), bool)
    covered[64:-64, 64:-64] = True
    field = displacement_field(mosaic, covered, seabed)
    assert field["patches"] >= 20
    # cv2 turns counter-clockwise on the image, rows downward: clockwise on the map.
    assert field["rotation_deg"] == pytest.approx(-2.0, abs=0.1)
    assert field["distortion_rms_px"] < 0.5
    # The raw shifts spread by the turn: what the old mean-only measure called distortion.
    assert field["rms_px"] > 5.0


def test_a_lane_drawn_twice_is_a_distortion() -> None:
    seabed = _texture(1024, 5)
    mosaic = seabed.copy()
    mosaic[:512] = np.roll(seabed[:512], 10, axis=1)  # the northern half 10 px east
    field = displacement_field(mosaic, np.ones_like(mosaic, bool), seabed)
    assert field["distortion_rms_px"] > 3.0
