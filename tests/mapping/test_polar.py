"""Polar-to-Cartesian geometry: echoes land where the seabed point is."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st

from mapping.polar import (
    FanGeometry,
    cartesian_tables,
    fan_grid,
    ground_to_polar,
    polar_to_ground,
    to_cartesian,
)


@given(
    forward=st.floats(0.5, 6.0),
    starboard=st.floats(-5.0, 5.0),
    altitude=st.floats(0.0, 3.0),
    tilt_deg=st.floats(0.0, 30.0),
)
def test_ground_and_polar_round_trip(
    forward: float, starboard: float, altitude: float, tilt_deg: float
) -> None:
    tilt = math.radians(tilt_deg)
    r, b = ground_to_polar(np.array([forward]), np.array([starboard]), altitude, tilt)
    f2, s2 = polar_to_ground(r, b, altitude, tilt)
    np.testing.assert_allclose([f2[0], s2[0]], [forward, starboard], atol=1e-9)


@given(
    slant=st.floats(0.2, 8.0),
    bearing_deg=st.floats(-70.0, 70.0),
    altitude=st.floats(0.1, 3.0),
    tilt_deg=st.floats(0.0, 40.0),
)
def test_a_beam_is_a_cone_about_the_array_whatever_the_tilt(
    slant: float, bearing_deg: float, altitude: float, tilt_deg: float
) -> None:
    """Level: the echo is r sin(theta) to starboard and sqrt(r^2 cos^2(theta) - h^2)
    forward, or nowhere on the seabed when the cone does not reach it."""
    theta = math.radians(bearing_deg)
    f, s = polar_to_ground(np.array([slant]), np.array([theta]), altitude, math.radians(tilt_deg))
    ground_sq = (slant * math.cos(theta)) ** 2 - altitude**2
    assume(abs(ground_sq) > 1e-6)  # grazing: the forward distance is ill-conditioned
    if ground_sq < 0:
        assert np.isnan(f[0])
        return
    np.testing.assert_allclose(
        [f[0], s[0]], [math.sqrt(ground_sq), slant * math.sin(theta)], atol=1e-9
    )


def test_a_bright_cell_appears_at_its_ground_position() -> None:
    bearings = np.radians(np.linspace(-65, 65, 256) + 3 * np.sin(np.linspace(-np.pi, np.pi, 256)))
    bearings.sort()
    fan = FanGeometry.of(bearings, 500, 0.01, altitude_m=1.0, tilt_rad=math.radians(15))
    grid = fan_grid(fan, 0.01)
    tables = cartesian_tables(fan, grid)
    polar = np.zeros((500, 256), np.float32)
    beam, bin_ = 200, 380
    polar[bin_, beam] = 1.0
    image = to_cartesian(polar, tables).astype(np.float64)
    rows, cols = np.indices(image.shape)
    row = (rows * image).sum() / image.sum()
    col = (cols * image).sum() / image.sum()
    found_forward = grid.forward_max_m - (row + 0.5) * grid.res_m
    found_starboard = grid.starboard_min_m + (col + 0.5) * grid.res_m
    f, s = polar_to_ground(
        np.array([(bin_ + 0.5) * 0.01]), np.array([bearings[beam]]), 1.0, math.radians(15)
    )
    assert abs(found_forward - f[0]) <= 0.5 * grid.res_m
    assert abs(found_starboard - s[0]) <= 0.5 * grid.res_m


def test_the_near_field_and_the_outside_of_the_fan_are_masked() -> None:
    fan = FanGeometry.of(np.radians(np.linspace(-30, 30, 64)), 200, 0.02, 1.0, math.radians(15))
    grid = fan_grid(fan, 0.02, min_range_m=2.0)
    tables = cartesian_tables(fan, grid, min_range_m=2.0)
    rows, cols = grid.shape
    forward = grid.forward_max_m - (np.arange(rows)[:, None] + 0.5) * grid.res_m
    starboard = grid.starboard_min_m + (np.arange(cols)[None, :] + 0.5) * grid.res_m
    slant, bearing = ground_to_polar(
        np.broadcast_to(forward, grid.shape),
        np.broadcast_to(starboard, grid.shape),
        1.0,
        math.radians(15),
    )
    assert not tables.mask[slant < 1.99].any()
    assert not tables.mask[np.abs(bearing) > math.radians(30.01)].any()
    assert tables.mask.sum() > 0.3 * tables.mask.size
