"""Coverage: a cell counts the passes that saw it in the fan's lit band at a useful grazing
angle, and an area's gaps are the stripes no lane saw."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from hypothesis import given
from hypothesis import strategies as st

from mapping.coverage import (
    CoverageGrid,
    CoverageParams,
    SeabedCoverage,
    SonarFan,
    footprint,
)
from mapping.frames import SonarMount
from mapping.polar import ground_to_polar
from mapping.preprocess import lit_min_range
from planning import Area, Polygon, area_gaps, cells_geometry

ALTITUDE_M = 1.0
TILT = math.radians(15.0)
RANGE_M = 5.0
# The sonar at the antenna, so a lane's footprint is centred on its track.
MOUNT = SonarMount(0.0, 0.0, 0.0, 0.0, TILT, ALTITUDE_M)
FAN = SonarFan(math.radians(65.0), lit_min_range(ALTITUDE_M, 15.0, 20.0, 1.0), RANGE_M, TILT)

# Seen across a straight lane: the footprint's widest point is at its near edge, where the
# vertical beam first reaches the seabed (24 degrees down: 2.25 m ahead at 1 m altitude),
# out to the 5 m slant range: sqrt(5^2 - 1^2 - 2.25^2).
NEAR_M = ALTITUDE_M / math.tan(math.radians(24.0))
REACH_M = math.sqrt(RANGE_M**2 - ALTITUDE_M**2 - NEAR_M**2)


def lane(
    east: float, north0: float, north1: float, t0: float, speed: float = 0.5, rate: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """Times and vehicle poses of a straight run from north0 to north1 along ``east``."""
    n = int(abs(north1 - north0) / speed * rate) + 1
    north = np.linspace(north0, north1, n)
    heading = 0.0 if north1 > north0 else math.pi
    poses = np.column_stack([np.full(n, east), north, np.full(n, heading)])
    return t0 + np.arange(n) / rate, poses


def at(grid: CoverageGrid, east: float, north: float, layer: str = "passes") -> int:
    """The count of the cell holding a point (local = UTM here: no anchor)."""
    col = math.floor((east - grid.west_m) / grid.cell_m)
    row = math.floor((grid.north_m - north) / grid.cell_m)
    values = getattr(grid, layer)
    if not (0 <= row < values.shape[0] and 0 <= col < values.shape[1]):
        return 0
    return int(values[row, col])


def covered(times, poses, params: CoverageParams | None = None, altitudes=None) -> CoverageGrid:
    coverage = SeabedCoverage(MOUNT, FAN, params)
    coverage.add_frames(times, poses, altitudes)
    return coverage.grid()


def test_one_frame_sees_its_lit_band_ahead_and_nothing_behind() -> None:
    grid = covered([0.0], [[0.0, 0.0, 0.0]])  # at the origin, heading north
    assert at(grid, 0.1, 3.0) == 1
    assert at(grid, 0.1, 4.8) == 1
    assert at(grid, 0.1, NEAR_M - 0.3) == 0  # inside the unlit near field
    assert at(grid, 0.1, 5.1) == 0  # beyond the range
    assert at(grid, 0.1, -3.0) == 0  # behind
    assert at(grid, 3.0, 3.0) == 1  # 45 degrees to starboard, 4.2 m out


def test_a_narrow_fan_does_not_see_beyond_its_bearings() -> None:
    narrow = SeabedCoverage(MOUNT, SonarFan(math.radians(45.0), FAN.min_slant_m, RANGE_M, TILT))
    narrow.add(0.0, [0.0, 0.0, 0.0])
    grid = narrow.grid()
    # Cone bearing asin(s / slant): 34 degrees at (3.6, 2.6) in, 48 at (2.6, 3.1) out.
    assert at(grid, 2.6, 3.6) == 1
    assert at(grid, 3.1, 2.6) == 0
    assert at(grid, -3.1, 2.6) == 0


def test_a_straight_lane_sees_its_swath_once() -> None:
    times, poses = lane(0.0, 0.0, 40.0, 1000.0)
    grid = covered(times, poses)
    for east in (-REACH_M + 0.2, -2.0, 0.1, 2.0, REACH_M - 0.2):
        assert at(grid, east, 20.0) == 1
    for east in (-2.0, 0.1, 2.0):
        assert at(grid, east, 20.0, "hits") > 10  # many pings, one pass
    for east in (-REACH_M - 0.2, REACH_M + 0.2):
        assert at(grid, east, 20.0) == 0
    assert at(grid, 0.1, 1.0) == 0  # behind the start: the fan looks ahead
    assert at(grid, 0.1, 40.0 + 4.7) == 1  # ahead of the last frame, in range
    assert at(grid, 0.1, 40.0 + 5.2) == 0


def test_max_range_cuts_the_far_cells() -> None:
    times, poses = lane(0.0, 0.0, 40.0, 1000.0)
    grid = covered(times, poses, CoverageParams(max_range_m=3.0))
    reach = math.sqrt(3.0**2 - NEAR_M**2)  # 1.99 m
    assert at(grid, reach - 0.2, 20.0) == 1
    assert at(grid, reach + 0.3, 20.0) == 0
    assert at(grid, 0.1, 40.0 + 2.9) == 1
    assert at(grid, 0.1, 40.0 + 3.2) == 0


def test_lower_altitude_loses_the_far_cells_to_the_grazing_cut() -> None:
    times, poses = lane(0.0, 0.0, 40.0, 1000.0)
    high = covered(times, poses)
    low = covered(times, poses, altitudes=np.full(times.size, 0.5))
    ungated = covered(times, poses, CoverageParams(min_grazing_rad=0.0), np.full(times.size, 0.5))
    # 0.5 m up, 10 degrees grazing is 2.84 m out: the lane's swath shrinks to +-2.6 m.
    assert at(high, 3.5, 20.0) == 1
    assert at(low, 3.5, 20.0) == 0
    assert at(low, 2.0, 20.0) == 1
    assert at(ungated, 3.5, 20.0) == 1
    assert low.covered_m2(1) < 0.7 * high.covered_m2(1)


def test_two_lanes_count_two_passes_where_they_overlap() -> None:
    first = lane(0.0, 0.0, 40.0, 1000.0)
    second = lane(6.0, 40.0, 0.0, 1000.0 + 80.0 + 60.0)  # back the other way a minute later
    coverage = SeabedCoverage(MOUNT, FAN, CoverageParams(min_passes=2))
    coverage.add_frames(*first)
    coverage.add_frames(*second)
    grid = coverage.grid()
    assert at(grid, 3.0, 20.0) == 2  # both lanes' swaths
    assert at(grid, 0.0, 20.0) == 1  # seen by many consecutive pings of one lane
    assert at(grid, 0.0, 20.0, "hits") > 10
    assert at(grid, 6.0 - REACH_M + 0.2, 20.0) == 2
    assert at(grid, 6.0 - REACH_M - 0.2, 20.0) == 1
    bar = grid.meets(2)
    assert np.array_equal(bar, grid.passes >= 2)
    overlap = 2 * REACH_M - 6.0  # the strip both lanes see, 2.7 m wide
    middle = slice(round((grid.north_m - 30.0) / 0.25), round((grid.north_m - 10.0) / 0.25))
    widths = bar[middle].sum(axis=1) * grid.cell_m
    assert np.all(np.abs(widths - overlap) <= grid.cell_m)


def test_a_pause_shorter_than_the_pass_gap_is_still_one_pass() -> None:
    times, poses = lane(0.0, 0.0, 20.0, 1000.0)
    after = poses[:, 1] > 10.0
    held = covered(times + np.where(after, 5.0, 0.0), poses)  # 5 s held at 10 m
    assert np.max(held.passes) == 1
    left = covered(times + np.where(after, 25.0, 0.0), poses)  # 25 s: more than the gap
    # 13.5 m is seen from 8.6 to 11.25 m: before the pause and after it.
    assert at(left, 0.0, 13.5) == 2
    assert at(left, 0.0, 12.0) == 1  # from 7.1 to 9.75 m: before it only
    assert at(left, 0.0, 16.0) == 1  # from 11.1 to 13.75 m: after it only


def test_frames_one_by_one_in_batches_or_at_once_give_one_raster() -> None:
    times, poses = lane(0.0, 0.0, 60.0, 1000.0)
    back = lane(5.0, 60.0, 0.0, 1200.0)
    times, poses = np.concatenate([times, back[0]]), np.concatenate([poses, back[1]])
    whole = covered(times, poses)
    single = SeabedCoverage(MOUNT, FAN)
    for t, pose in zip(times, poses, strict=True):
        single.add(float(t), pose)
    batches = SeabedCoverage(MOUNT, FAN)
    for chunk in np.array_split(np.arange(times.size), 7):
        batches.add_frames(times[chunk], poses[chunk])
    for other in (single.grid(), batches.grid()):
        assert np.array_equal(other.passes, whole.passes)
        assert np.array_equal(other.hits, whole.hits)
        assert (other.west_m, other.north_m) == (whole.west_m, whole.north_m)


def test_cells_lie_on_the_utm_grid_and_grow_with_the_survey() -> None:
    anchor_e, anchor_n = 512_345.6, 4_812_345.7
    coverage = SeabedCoverage(MOUNT, FAN, anchor_e=anchor_e, anchor_n=anchor_n)
    times, poses = lane(0.3, 0.0, 300.0, 1000.0)  # across several 32 m tiles
    coverage.add_frames(times, poses)
    grid = coverage.grid()
    for edge in (grid.west_m, grid.north_m):
        assert edge / grid.cell_m == pytest.approx(round(edge / grid.cell_m), abs=1e-6)
    assert grid.north_m == pytest.approx(anchor_n + 300.0 + 4.9, abs=0.3)
    assert grid.west_m == pytest.approx(anchor_e + 0.3 - REACH_M, abs=0.3)
    # Every cell along the track, all 300 m of it, was seen by the one pass.
    col = math.floor((anchor_e + 0.3 - grid.west_m) / grid.cell_m)
    track = grid.passes[: -int(3.0 / grid.cell_m), col]
    assert np.all(track[int(6.0 / grid.cell_m) :] == 1)


def test_without_an_altitude_slant_range_is_ground_range() -> None:
    # As the mapper does with the altitude unknown: no vertical beam, no grazing angle.
    unknown = SeabedCoverage(SonarMount(0.0, 0.0, 0.0, 0.0, TILT, 0.0), SonarFan(1.1, 1.0, 5.0))
    unknown.add(0.0, [0.0, 0.0, 0.0])
    grid = unknown.grid()
    assert at(grid, 0.1, 1.2) == 1 and at(grid, 0.1, 4.8) == 1
    assert at(grid, 0.1, 0.8) == 0 and at(grid, 0.1, 5.2) == 0
    assert at(grid, 3.4, 3.4) == 1  # 45 degrees out at 4.8 m


def test_frames_without_a_pose_are_skipped() -> None:
    coverage = SeabedCoverage(MOUNT, FAN)
    coverage.add_frames([0.0, 0.1], [[np.nan, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert coverage.frames == 1
    assert coverage.grid().passes.sum() > 0
    assert SeabedCoverage(MOUNT, FAN).grid().passes.shape == (0, 0)


@given(
    forward=st.floats(0.05, 8.0),
    starboard=st.floats(-8.0, 8.0),
    altitude=st.floats(0.2, 3.0),
    tilt_deg=st.floats(5.0, 40.0),
    half_deg=st.floats(20.0, 70.0),
)
def test_what_a_frame_sees_agrees_with_the_sonars_polar_geometry(
    forward: float, starboard: float, altitude: float, tilt_deg: float, half_deg: float
) -> None:
    fan = SonarFan(
        math.radians(half_deg), lit_min_range(altitude, tilt_deg, 20.0, 1.0), 6.0,
        math.radians(tilt_deg),
    )  # fmt: skip
    fp = footprint(fan, CoverageParams(min_grazing_rad=math.radians(8.0)), altitude)
    seen = bool(fp.contains(np.array([forward]), np.array([starboard]))[0])
    slant, bearing = ground_to_polar(
        np.array([forward]), np.array([starboard]), altitude, math.radians(tilt_deg)
    )
    depression = math.degrees(math.atan2(altitude, forward))
    grazing = math.degrees(math.atan2(altitude, math.hypot(forward, starboard)))
    expected = (
        fan.min_slant_m <= slant[0] <= fan.max_slant_m
        and abs(math.degrees(bearing[0])) <= half_deg
        and tilt_deg - 10.0 <= depression <= tilt_deg + 10.0 - 1.0
        and grazing >= 8.0
    )
    margin = min(
        abs(slant[0] - fan.min_slant_m), abs(slant[0] - fan.max_slant_m),
        abs(abs(math.degrees(bearing[0])) - half_deg) / 50.0,
        abs(depression - tilt_deg + 10.0) / 50.0, abs(depression - tilt_deg - 9.0) / 50.0,
        abs(grazing - 8.0) / 50.0,
    )  # fmt: skip
    if margin > 1e-6:  # not on an edge, where rounding decides
        assert seen == expected


# A lawnmower over a 60 m x 40 m area, lanes 6 m apart run north and south in turn,
# each beyond the area's ends, one of them left out.
AREA = Area((Polygon(np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 40.0], [0.0, 40.0]])),))
LANES = [3.0 + 6.0 * k for k in range(10)]
SKIPPED = 27.0


def lawnmower(skip: float | None) -> tuple[np.ndarray, np.ndarray]:
    times, poses, t0 = [], [], 1000.0
    for k, east in enumerate(LANES):
        if east != skip:
            t, p = lane(east, -8.0, 48.0, t0) if k % 2 == 0 else lane(east, 48.0, -8.0, t0)
            times.append(t)
            poses.append(p)
        t0 += 56.0 / 0.5 + 30.0  # the lane, then a turn
    return np.concatenate(times), np.concatenate(poses)


def test_a_skipped_lane_is_the_gap() -> None:
    grid = covered(*lawnmower(SKIPPED))
    cells = cells_geometry(grid.meets(1), grid.west_m, grid.north_m, grid.cell_m)
    found = area_gaps(AREA, cells, min_gap_m2=1.0)
    stripe = shapely.box(SKIPPED - 6.0 + REACH_M, 0.0, SKIPPED + 6.0 - REACH_M, 40.0)
    assert len(found.gaps) == 1
    (gap,) = found.gaps
    # Within a cell of the stripe along both its 40 m sides.
    assert shapely.area(shapely.symmetric_difference(gap, stripe)) < 2 * 40.0 * grid.cell_m
    assert shapely.hausdorff_distance(gap, stripe) < grid.cell_m
    expected = 1.0 - stripe.area / AREA.area_m2  # 94.5 %
    assert found.fraction == pytest.approx(expected, abs=0.01)
    assert found.gaps_m2 == pytest.approx(stripe.area, rel=0.1)


def test_the_whole_lawnmower_leaves_no_gap_and_holes_are_not_gaps() -> None:
    grid = covered(*lawnmower(None))
    cells = cells_geometry(grid.meets(1), grid.west_m, grid.north_m, grid.cell_m)
    found = area_gaps(AREA, cells, min_gap_m2=1.0)
    assert found.gaps == ()
    assert found.fraction == pytest.approx(1.0, abs=1e-9)
    # A keep-out over the skipped stripe: the water outside it is the gap, the hole is not.
    hole = np.array([[24.0, 10.0], [30.0, 10.0], [30.0, 30.0], [24.0, 30.0]])
    holed = Area((Polygon(AREA.polygons[0].outer, (hole,)),))
    skipped = covered(*lawnmower(SKIPPED))
    cells = cells_geometry(skipped.meets(1), skipped.west_m, skipped.north_m, skipped.cell_m)
    found = area_gaps(holed, cells, min_gap_m2=1.0)
    assert found.area_m2 == pytest.approx(2400.0 - 120.0)
    assert len(found.gaps) == 2  # the stripe's two ends beyond the hole
    assert all(shapely.area(shapely.intersection(gap, shapely.box(24, 10, 30, 30))) < 1e-9
               for gap in found.gaps)  # fmt: skip
    assert found.gaps_m2 == pytest.approx(2 * 10.0 * (6.0 - 2 * (REACH_M - 3.0)), rel=0.1)
    small = area_gaps(holed, cells, min_gap_m2=1000.0)
    assert small.gaps == () and small.fraction == pytest.approx(found.fraction)


def test_cells_become_their_exact_union() -> None:
    cells = np.zeros((6, 8), bool)
    cells[1:5, 1:7] = True
    cells[2:4, 3:5] = False  # a hole
    cells[0, 0] = True  # a cell touching the block only at a corner
    geometry = cells_geometry(cells, 100.0, 50.0, 0.5)
    assert shapely.area(geometry) == pytest.approx(cells.sum() * 0.25)
    assert shapely.bounds(geometry).tolist() == [100.0, 47.5, 103.5, 50.0]
    assert shapely.is_empty(cells_geometry(np.zeros((3, 3), bool), 0.0, 0.0, 1.0))
