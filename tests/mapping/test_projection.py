"""Each ping projected onto the seabed at its own roll, pitch and altitude, through the
cone beam model: checked against the geometry written a second way (``Truth``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq, minimize_scalar
from scipy.spatial.transform import Rotation

from mapping.polar import (
    Attitude,
    FanGeometry,
    PingProjection,
    cartesian_tables,
    fan_grid,
    ground_to_polar,
    head_pose,
    polar_to_ground,
    polar_to_seabed,
    seabed_to_polar,
)
from mapping.preprocess import Preprocessor, PreprocessParams, lit_min_range

TILT = math.radians(15.0)
LEVER_ARM = (-0.45, 0.0, 0.3)  # the config's default mount


@dataclass(frozen=True)
class Truth:
    """The geometry composed in the heading-aligned level frame L with the GPS antenna at
    the origin (scipy rotations, intrinsic ZYX Euler), not in the ground image's frame as
    the mapper does: body R_LB = Rz(0) Ry(pitch) Rx(roll), sonar R_BS = Rz(mount_yaw)
    Ry(-tilt) at the lever arm m; the ground image sits at the level sonar position m,
    turned by Rz(mount_yaw), the seabed ``altitude_m`` below it. A beam at bearing theta is
    the cone sin(theta) = p_y / |p| about the array (sonar y) axis."""

    altitude_m: float
    tilt_rad: float
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mount_yaw_rad: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0

    def _frames(self) -> tuple[Rotation, Rotation, np.ndarray, np.ndarray]:
        body = Rotation.from_euler("ZYX", [0.0, self.pitch_rad, self.roll_rad])
        sonar = body * Rotation.from_euler("ZY", [self.mount_yaw_rad, -self.tilt_rad])
        level_head = np.asarray(self.lever_arm_m, float)
        return (
            sonar,
            Rotation.from_euler("Z", self.mount_yaw_rad),
            level_head,
            body.apply(level_head),
        )

    def polar(self, forward: float, starboard: float) -> tuple[float, float]:
        """Slant range (m) and cone bearing (rad) of a seabed point of the ground image."""
        sonar, image, level_head, head = self._frames()
        point = level_head + image.apply([forward, starboard, self.altitude_m])
        p = sonar.inv().apply(point - head)
        r = float(np.linalg.norm(p))
        return r, math.asin(p[1] / r)

    def ground(self, slant_m: float, bearing_rad: float) -> tuple[float, float]:
        """The seabed point (forward, starboard of the ground image) of an echo at a slant
        range and cone bearing: the elevation psi on the cone by root finding."""
        sonar, image, level_head, head = self._frames()

        def point(psi: float) -> np.ndarray:
            c = math.cos(bearing_rad)
            p = slant_m * np.array([c * math.cos(psi), math.sin(bearing_rad), c * math.sin(psi)])
            return image.inv().apply(head + sonar.apply(p) - level_head)

        def depth(psi: float) -> float:
            return float(point(psi)[2] - self.altitude_m)

        steepest = minimize_scalar(lambda psi: -depth(psi), bounds=(-1.5, 1.5), method="bounded")
        psi = brentq(depth, -1.5, steepest.x, xtol=1e-14)
        g = point(psi)
        return float(g[0]), float(g[1])


def bearing_table(n_beams: int = 256, fan_deg: float = 130.0) -> np.ndarray:
    """Uneven like the Oculus tables (wider at the edges), in steps of 1/100 degree."""
    u = np.linspace(-1.0, 1.0, n_beams)
    return np.radians(np.rint(fan_deg / 2 * (u + 0.1 * u**3) / 1.1 * 100) / 100)


def sonar_fan(**mount: float | tuple[float, float, float]) -> FanGeometry:
    return FanGeometry.of(bearing_table(), 500, 0.01, 1.0, TILT, **mount)  # type: ignore[arg-type]


# (a) The cone: an echo at 2.5 m, 60 degrees lands where the geometry puts it.


def test_an_echo_at_60_degrees_lands_on_its_cone_within_a_millimetre() -> None:
    truth = Truth(1.0, TILT)
    forward, starboard = truth.ground(2.5, math.radians(60))
    f, s = polar_to_ground(np.array([2.5]), np.array([math.radians(60)]), 1.0, TILT)
    assert math.hypot(f[0] - forward, s[0] - starboard) < 0.001
    # The ray model (bearing = atan2(y, x) in the sonar frame) put it 20 cm away.
    c, sn = math.cos(TILT), math.sin(TILT)
    phi = math.asin(1.0 / (2.5 * math.hypot(sn * math.cos(math.radians(60)), c)))
    phi -= math.atan2(sn * math.cos(math.radians(60)), c)
    x = 2.5 * math.cos(phi) * math.cos(math.radians(60))
    ray = (c * x - sn * 2.5 * math.sin(phi), 2.5 * math.cos(phi) * math.sin(math.radians(60)))
    assert math.hypot(ray[0] - forward, ray[1] - starboard) > 0.15


@pytest.mark.parametrize(
    ("roll_deg", "pitch_deg", "altitude_m", "mount_yaw_deg"),
    [(0, 0, None, 0), (3, -2, None, 0), (-3, 2.5, 1.1, 0), (2, 3, None, 25)],
)
def test_an_echo_lands_where_the_attitude_puts_it_within_a_millimetre(
    roll_deg: float, pitch_deg: float, altitude_m: float | None, mount_yaw_deg: float
) -> None:
    fan = sonar_fan(lever_arm_m=LEVER_ARM, mount_yaw_rad=math.radians(mount_yaw_deg))
    attitude = Attitude(math.radians(roll_deg), math.radians(pitch_deg), altitude_m)
    truth = Truth(
        altitude_m or 1.0, TILT, LEVER_ARM, math.radians(mount_yaw_deg), *attitude_rad(attitude)
    )
    head = head_pose(fan, attitude)
    for slant, bearing_deg in [(2.5, 60.0), (2.5, -60.0), (4.0, 10.0), (3.2, -35.0)]:
        forward, starboard = truth.ground(slant, math.radians(bearing_deg))
        f, s = polar_to_seabed(np.array([slant]), np.array([math.radians(bearing_deg)]), head)
        assert math.hypot(f[0] - forward, s[0] - starboard) < 0.001
        r, b, ahead = seabed_to_polar(np.array([forward]), np.array([starboard]), head)
        assert ahead[0]
        assert abs(r[0] - slant) < 1e-6 and abs(b[0] - math.radians(bearing_deg)) < 1e-6


def attitude_rad(attitude: Attitude) -> tuple[float, float]:
    return attitude.roll_rad, attitude.pitch_rad


@settings(max_examples=200)
@given(
    forward=st.floats(0.5, 5.0),
    starboard=st.floats(-4.0, 4.0),
    roll_deg=st.floats(-8.0, 8.0),
    pitch_deg=st.floats(-8.0, 8.0),
    altitude=st.floats(0.5, 3.0),
    mount_yaw_deg=st.floats(-30.0, 30.0),
)
def test_seabed_and_polar_round_trip_at_any_attitude(
    forward: float,
    starboard: float,
    roll_deg: float,
    pitch_deg: float,
    altitude: float,
    mount_yaw_deg: float,
) -> None:
    fan = sonar_fan(lever_arm_m=LEVER_ARM, mount_yaw_rad=math.radians(mount_yaw_deg))
    head = head_pose(fan, Attitude(math.radians(roll_deg), math.radians(pitch_deg), altitude))
    r, b, ahead = seabed_to_polar(np.array([forward]), np.array([starboard]), head)
    if not ahead[0]:
        return
    f2, s2 = polar_to_seabed(r, b, head)
    np.testing.assert_allclose([f2[0], s2[0]], [forward, starboard], atol=1e-9)


def test_without_attitude_the_level_functions_are_the_exact_model() -> None:
    fan = sonar_fan(lever_arm_m=LEVER_ARM, mount_yaw_rad=math.radians(20))
    forward, starboard = np.meshgrid(np.linspace(0.5, 4.5, 9), np.linspace(-4, 4, 9))
    level = ground_to_polar(forward, starboard, 1.0, TILT)
    exact = seabed_to_polar(forward, starboard, head_pose(fan, Attitude()))
    np.testing.assert_allclose(level[0], exact[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(level[1], np.where(exact[2], exact[1], np.nan), rtol=0, atol=1e-12)
    truth = Truth(1.0, TILT, LEVER_ARM, math.radians(20))
    for f, s, r, b in zip(
        forward.ravel(), starboard.ravel(), *(a.ravel() for a in level), strict=True
    ):
        assert np.allclose(truth.polar(f, s), (r, b), atol=1e-9)


# (b) A rendered ping: its bright targets land where the truth puts them.

TARGETS = [(2.8, -2.2), (3.4, 1.6), (1.6, 3.3), (1.4, -3.2), (4.2, 0.3), (3.0, 3.0), (2.2, -3.5)]


def render_targets(fan: FanGeometry, truth: Truth) -> np.ndarray:
    """A polar ping (n_ranges, n_beams) of dark seabed with a Gaussian blob per target,
    placed through ``truth``."""
    bearings = np.asarray(fan.bearings_rad)
    rows, cols = np.indices((fan.n_ranges, bearings.size), dtype=float)
    ping = np.zeros(rows.shape)
    for forward, starboard in TARGETS:
        slant, bearing = truth.polar(forward, starboard)
        row = slant / fan.range_resolution_m - 0.5
        col = np.interp(bearing, bearings, np.arange(bearings.size))
        ping += np.exp(-0.5 * (((rows - row) / 1.2) ** 2 + ((cols - col) / 1.0) ** 2))
    return np.clip(np.rint(250 * ping), 0, 255).astype(np.uint8)


def target_errors(image: np.ndarray, res_m: float, forward_max: float, starboard_min: float):
    """Distance (m) from each target to the centroid of the blob nearest it."""
    errors = []
    for forward, starboard in TARGETS:
        row = round((forward_max - forward) / res_m - 0.5)
        col = round((starboard - starboard_min) / res_m - 0.5)
        half = round(0.12 / res_m)
        window = image[row - half : row + half + 1, col - half : col + half + 1].astype(float)
        window = np.where(window > 0.3 * window.max(), window, 0.0)
        r, c = np.indices(window.shape)
        found_row = row - half + (r * window).sum() / window.sum()
        found_col = col - half + (c * window).sum() / window.sum()
        found = (forward_max - (found_row + 0.5) * res_m, starboard_min + (found_col + 0.5) * res_m)
        errors.append(math.hypot(found[0] - forward, found[1] - starboard))
    return np.array(errors)


@pytest.mark.parametrize("mount_yaw_deg", [0.0, 20.0])
def test_a_rolled_and_pitched_ping_puts_its_targets_where_they_are(mount_yaw_deg: float) -> None:
    yaw = math.radians(mount_yaw_deg)
    fan = sonar_fan(lever_arm_m=LEVER_ARM, mount_yaw_rad=yaw)
    attitude = Attitude(math.radians(3.0), math.radians(-2.0))
    ping = render_targets(fan, Truth(1.0, TILT, LEVER_ARM, yaw, *attitude_rad(attitude)))
    params = PreprocessParams(
        equalize_rows=False, histogram_match=False, clahe=False, res_m=0.01, registration_res_m=0.02
    )
    pre = Preprocessor(fan, 15.0, params)
    blend, coarse = pre.grid, pre.registration_grid
    assert blend is not None

    def errors(frame_image: np.ndarray, grid) -> np.ndarray:
        return target_errors(frame_image, grid.res_m, grid.forward_max_m, grid.starboard_min_m)

    projected = pre(ping, attitude)
    assert errors(projected.image, blend).max() < 0.5 * blend.res_m  # 1-2 mm
    assert errors(projected.coarse, coarse).max() < 0.5 * coarse.res_m
    # Projected level, every target is 4-15 cm off (3 degrees of roll at 1 m altitude
    # alone move the fan 5 cm to starboard).
    level = pre(ping)
    assert errors(level.image, blend).min() > 0.03


def test_a_level_ping_is_unchanged_by_a_level_attitude() -> None:
    fan = sonar_fan(lever_arm_m=LEVER_ARM)
    ping = render_targets(fan, Truth(1.0, TILT, LEVER_ARM))
    pre = Preprocessor(fan, 15.0)
    level, zero = pre(ping), pre(ping, Attitude(0.0, 0.0, 1.0))
    for a, b in zip(
        (level.image, level.mask, level.weight, level.coarse),
        (zero.image, zero.mask, zero.weight, zero.coarse),
        strict=True,
    ):
        np.testing.assert_array_equal(a, b)
    assert pre.projection.tables(Attitude()) is pre.tables


# (c) The per-ping tables against the exact ones, every pixel.


@pytest.mark.parametrize("res_m", [0.01, 0.02, 0.03])
@pytest.mark.parametrize(
    ("roll_deg", "pitch_deg", "altitude_m", "mount_yaw_deg", "slope"),
    [
        (3, -2, None, 0, (0.0, 0.0)),
        (-6, 6, 1.3, 0, (0.0, 0.0)),
        (10, 4, 0.7, 20, (0.0, 0.0)),
        (0, 0, 1.0 + 1e-9, 0, (0.0, 0.0)),
        (2, -3, 1.2, 0, (0.08, -0.05)),
        (-4, 2, 0.9, 25, (-0.1, 0.1)),
    ],
)
def test_the_per_ping_tables_are_the_exact_ones(
    res_m: float,
    roll_deg: float,
    pitch_deg: float,
    altitude_m: float | None,
    mount_yaw_deg: float,
    slope: tuple[float, float],
) -> None:
    fan = FanGeometry.of(
        bearing_table(512),
        500,
        0.01,
        1.0,
        TILT,
        lever_arm_m=LEVER_ARM,
        mount_yaw_rad=math.radians(mount_yaw_deg),
    )
    min_range = lit_min_range(1.0, 15.0, 20.0, 1.0)
    grid = fan_grid(fan, res_m, min_range)
    projection = PingProjection(fan, grid, min_range)
    attitude = Attitude(math.radians(roll_deg), math.radians(pitch_deg), altitude_m, *slope)
    fast = projection.tables(attitude)
    exact = cartesian_tables(fan, grid, min_range, attitude)
    assert fast.mask.sum() > 0.3 * fast.mask.size
    np.testing.assert_array_equal(fast.mask, exact.mask & projection.level.mask)
    # In beams and range bins (a Cartesian pixel spans about a beam and 1-3 bins here).
    beam_error = np.abs(fast.map_beam - exact.map_beam)[fast.mask].max()
    range_error = np.abs(fast.map_range - exact.map_range)[fast.mask].max()
    assert beam_error < 0.02 and range_error < 0.002
    assert projection.tables(attitude) is fast  # the same attitude again: nothing recomputed


# (d) Level: the tables are the exact cone tables; the mask varies per ping within them.


def test_the_level_tables_are_the_exact_cone_tables() -> None:
    fan = sonar_fan()
    pre = Preprocessor(fan, 15.0)
    assert pre.grid is not None
    exact = cartesian_tables(fan, pre.grid, pre.min_range_m)
    np.testing.assert_array_equal(pre.tables.map_beam, exact.map_beam)
    np.testing.assert_array_equal(pre.tables.map_range, exact.map_range)
    np.testing.assert_array_equal(pre.tables.mask, exact.mask)
    # Spot checks through the independent geometry.
    bearings = np.asarray(fan.bearings_rad)
    truth = Truth(1.0, TILT)
    rows, cols = np.nonzero(exact.mask)
    for i in np.random.default_rng(5).choice(rows.size, 50, replace=False):
        f = pre.grid.forward_max_m - (rows[i] + 0.5) * pre.grid.res_m
        s = pre.grid.starboard_min_m + (cols[i] + 0.5) * pre.grid.res_m
        slant, bearing = truth.polar(f, s)
        assert abs(exact.map_range[rows[i], cols[i]] - (slant / 0.01 - 0.5)) < 1e-3
        beam = np.interp(bearing, bearings, np.arange(bearings.size))
        assert abs(exact.map_beam[rows[i], cols[i]] - beam) < 1e-3


def test_a_tilted_ping_masks_out_what_its_fan_does_not_reach() -> None:
    fan = sonar_fan(lever_arm_m=LEVER_ARM)
    rng = np.random.default_rng(7)
    ping = rng.integers(20, 200, (500, 256)).astype(np.uint8)
    pre = Preprocessor(fan, 15.0, PreprocessParams(registration_res_m=0.03))
    frame = pre(ping, Attitude(math.radians(4), math.radians(-3), 1.05))
    assert (frame.mask & ~pre.tables.mask).sum() == 0
    lost = (pre.tables.mask & ~frame.mask).sum()
    assert 0 < lost < 0.05 * pre.tables.mask.sum()
    assert np.all(frame.image[~frame.mask] == 0.0)
    assert np.all(frame.weight[~frame.mask] == 0.0)
    np.testing.assert_array_equal(frame.weight[frame.mask], pre.weight[frame.mask])
    coarse_mask = pre.registration_projection.tables(
        Attitude(math.radians(4), math.radians(-3), 1.05)
    ).mask
    assert np.all(frame.coarse[~coarse_mask] == 0.0)


def test_an_attitude_that_is_not_finite_is_refused() -> None:
    with pytest.raises(ValueError, match="not finite"):
        Attitude(math.nan, 0.0)
    with pytest.raises(ValueError, match="above 0 m"):
        Attitude(0.0, 0.0, altitude_m=0.0)


def test_a_fan_without_altitude_ignores_the_attitude() -> None:
    fan = FanGeometry.of(bearing_table(), 500, 0.01, 0.0, TILT, lever_arm_m=LEVER_ARM)
    pre = Preprocessor(fan, 15.0)
    assert pre.projection.tables(Attitude(math.radians(3), math.radians(-2), 1.2)) is pre.tables
