"""Survey planning: the lawnmower covers the area, keeps out of holes, and its files load
in the tools that will fly it (pymavlink's waypoint loader, MAVSDK's plan import)."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import shapely
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink
from scipy.sparse.csgraph import shortest_path

import planning.lawnmower
from daemon.config import SiteConfig, SonarConfig
from daemon.plan_files import DEFAULT_OVERLAP, read_plan, swath_from_config
from daemon.plan_files import plan_survey as plan_files
from drivers.errors import SeamapError
from drivers.formats.area import parse_area
from mapping.geo import LocalFrame
from planning import (
    Area,
    Keepouts,
    LegKind,
    PlanningError,
    Polygon,
    SurveyPlan,
    candidate_bearings,
    coverage,
    plan_path,
    plan_survey,
    sonar_swath,
    validate_area,
)

HALF = swath_from_config(SiteConfig()).half_width_m
SPACING = 2 * HALF * (1 - DEFAULT_OVERLAP)
LEAD_IN = 5.0
CLEARANCE = 2.0


def ring(*points: tuple[float, float]) -> np.ndarray:
    return np.array(points, np.float64)


RECTANGLE = Area((Polygon(ring((0, 0), (40, 0), (40, 30), (0, 30))),))
L_SHAPE = Area((Polygon(ring((0, 0), (36, 0), (36, 12), (12, 12), (12, 30), (0, 30))),))
U_SHAPE = Area(
    (Polygon(ring((0, 0), (38, 0), (38, 30), (26, 30), (26, 11), (12, 11), (12, 30), (0, 30))),)
)
WITH_HOLE = Area(
    (
        Polygon(
            ring((0, 0), (50, 0), (50, 36), (0, 36)),
            (ring((18, 12), (26, 9), (31, 17), (24, 24), (17, 20)),),
        ),
    )
)
SHAPES = {"rectangle": RECTANGLE, "L": L_SHAPE, "U": U_SHAPE, "hole": WITH_HOLE}


def plan_of(area: Area, bearing_deg: float | None = None) -> SurveyPlan:
    return plan_survey(
        area,
        spacing_m=SPACING,
        bearing_rad=None if bearing_deg is None else math.radians(bearing_deg),
        lead_in_m=LEAD_IN,
        clearance_m=CLEARANCE,
    )


def grid_inside(area: Area, step: float = 0.5) -> np.ndarray:
    e0, n0, e1, n1 = area.bounds
    east, north = np.meshgrid(np.arange(e0, e1 + 1e-9, step), np.arange(n0, n1 + 1e-9, step))
    inside = area.contains(east, north)
    return np.column_stack([east[inside], north[inside]])


def in_swath(plan: SurveyPlan, points: np.ndarray) -> np.ndarray:
    """Restates the coverage model independently of planning.lawnmower.swept: a point is
    mapped when it lies within the half swath of a mapping leg (lane, transit, detour),
    inside the leg's extent, or within the half swath of a waypoint where the boat turns
    from one mapping leg into the next."""
    hit = np.zeros(len(points), bool)
    mapping = [leg.kind is not LegKind.TURN for leg in plan.legs]
    for k, leg in enumerate(plan.legs):
        if not mapping[k]:
            continue
        a, b = np.array(leg.start), np.array(leg.end)
        d = b - a
        length = np.hypot(*d)
        rel = points - a
        along = rel @ d / length
        across = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]) / length
        hit |= (along >= 0) & (along <= length) & (across <= HALF)
        if k > 0 and mapping[k - 1]:
            hit |= np.hypot(*rel.T) <= HALF
    return hit


def distance_to_ring(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    a, b = poly, np.roll(poly, -1, axis=0)
    d = b - a
    rel = points[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("pij,ij->pi", rel, d) / np.einsum("ij,ij->i", d, d), 0, 1)
    nearest = a[None] + t[..., None] * d[None]
    return np.hypot(*(points[:, None, :] - nearest).transpose(2, 0, 1)).min(axis=1)


# --- swath and spacing ---


def test_default_swath_and_spacing_follow_the_sonar() -> None:
    swath = swath_from_config(SiteConfig())
    # 5 m range, 130-degree fan, 15 degrees tilt, 1 m altitude: the fan's ground footprint
    # is about 9 m wide; its thin outer edges are not usable.
    assert 7.5 < swath.width_m < 2 * swath.fan_half_width_m < 9.5
    assert pytest.approx(swath.width_m / 2) == SPACING
    assert 3.8 < SPACING < 4.4  # close to the simulator's 4 m lanes
    high = swath_from_config(SiteConfig(sonar=SonarConfig(frequency="high")))
    assert high.width_m < 0.6 * swath.width_m
    longer = swath_from_config(SiteConfig(sonar=SonarConfig(range_m=10.0)))
    assert longer.width_m > 1.8 * swath.width_m


def test_a_sonar_that_sees_no_seabed_is_refused() -> None:
    with pytest.raises(ValueError, match="sees no seabed"):
        sonar_swath(range_m=5.0, fan_deg=130.0, tilt_deg=15.0, altitude_m=3.0)


# --- the lawnmower ---


@pytest.mark.parametrize("name", list(SHAPES))
def test_every_point_of_the_area_is_in_the_swath(name: str) -> None:
    area = SHAPES[name]
    plan = plan_of(area)
    points = grid_inside(area)
    missed = points[~in_swath(plan, points)]
    assert len(missed) == 0, f"{len(missed)} points unmapped, e.g. {missed[:3].tolist()}"
    assert coverage(area, plan, HALF).fraction == pytest.approx(1.0)


def test_lanes_across_a_concave_notch_still_cover_it() -> None:
    plan = plan_of(U_SHAPE, bearing_deg=90.0)  # across the arms: two runs per lane up top
    assert any(leg.kind is LegKind.TRANSIT for leg in plan.legs)
    assert len(plan.runs) > plan.n_lanes
    points = grid_inside(U_SHAPE)
    assert in_swath(plan, points).all()


def test_no_leg_enters_a_hole_or_its_clearance() -> None:
    plan = plan_of(WITH_HOLE)
    hole = WITH_HOLE.polygons[0].holes[0]
    assert any(leg.kind is LegKind.DETOUR for leg in plan.legs)
    lanes_split = [r for r in plan.runs if r.ends_at_keepout or r.starts_at_keepout]
    assert lanes_split, "some lane must be split by the hole"
    for leg in plan.legs:
        t = np.linspace(0.0, 1.0, max(2, int(leg.length_m / 0.05)))[:, None]
        points = np.array(leg.start) + t * (np.array(leg.end) - np.array(leg.start))
        inside = Area((Polygon(hole),)).contains(points[:, 0], points[:, 1])
        assert not inside.any(), f"{leg.kind} leg enters the hole"
        assert distance_to_ring(points, hole).min() >= CLEARANCE - 1e-6


def test_lanes_alternate_direction() -> None:
    for area in SHAPES.values():
        plan = plan_of(area)
        direction: dict[int, np.ndarray] = {}
        for run in plan.runs:
            d = np.subtract(run.end, run.start)
            d /= np.hypot(*d)
            if run.lane in direction:
                assert direction[run.lane] @ d == pytest.approx(1.0)
            direction[run.lane] = d
        lanes = sorted(direction)
        assert lanes == list(range(len(lanes)))
        for a, b in itertools.pairwise(lanes):
            assert direction[a] @ direction[b] == pytest.approx(-1.0)


@pytest.mark.parametrize("name", list(SHAPES))
def test_each_run_starts_and_ends_lead_in_outside_the_area(name: str) -> None:
    area = SHAPES[name]
    plan = plan_of(area)
    outer = area.polygons[0].outer
    hulls = plan.keepouts
    for run in plan.runs:
        for waypoint, boundary, at_keepout in (
            (run.start, run.entry, run.starts_at_keepout),
            (run.end, run.exit, run.ends_at_keepout),
        ):
            point = np.array([waypoint])
            if at_keepout:  # a lane stopped by a keep-out ends on the hull, not in the hole
                assert min(distance_to_ring(point, h)[0] for h in hulls) < 1e-6
                continue
            assert math.dist(waypoint, boundary) == pytest.approx(LEAD_IN, abs=1e-6)
            assert not area.contains(point[:, 0], point[:, 1])[0]
            assert distance_to_ring(np.array([boundary]), outer)[0] < 1e-6


@pytest.mark.parametrize("bearing_deg", [30.0, 115.0, 172.0])
def test_a_long_thin_area_gets_lanes_along_its_long_side(bearing_deg: float) -> None:
    b = math.radians(bearing_deg)
    along, across = np.array([math.sin(b), math.cos(b)]), np.array([math.cos(b), -math.sin(b)])
    corners = [along * u + across * v for u, v in ((0, 0), (120, 0), (120, 12), (0, 12))]
    plan = plan_of(Area((Polygon(np.array(corners)),)))
    assert math.degrees(plan.bearing_rad) % 180 == pytest.approx(bearing_deg, abs=0.5)
    assert plan.n_lanes == 3


def test_candidate_bearings_include_every_hull_edge() -> None:
    found = np.degrees(candidate_bearings(L_SHAPE))
    # the L's hull has edges along 0 and 90 degrees and one diagonal
    diagonal = math.degrees(math.atan2(12 - 36, 30 - 12)) % 180
    for expected in (0.0, 90.0, diagonal):
        assert np.min(np.abs((found - expected + 90) % 180 - 90)) < 1e-6


@settings(max_examples=15, deadline=None)
@given(
    width=st.floats(6.0, 60.0),
    height=st.floats(6.0, 60.0),
    rotation=st.floats(0.0, 180.0),
    lanes=st.floats(0.0, 180.0),
)
def test_any_rectangle_at_any_lane_angle_is_covered(
    width: float, height: float, rotation: float, lanes: float
) -> None:
    r = math.radians(rotation)
    turn = np.array([[math.cos(r), -math.sin(r)], [math.sin(r), math.cos(r)]])
    corners = ring((0, 0), (width, 0), (width, height), (0, height)) @ turn.T
    area = Area((Polygon(corners),))
    plan = plan_of(area, bearing_deg=lanes)
    assert in_swath(plan, grid_inside(area, 0.7)).all()


# --- keep-outs of any shape ---

C_HOLE = Area(
    (
        Polygon(
            ring((0, 0), (60, 0), (60, 50), (0, 50)),
            # a C open to the west: its bay is 24 m deep and 14 m wide
            (ring((15, 12), (45, 12), (45, 38), (15, 38), (15, 32), (39, 32), (39, 18), (15, 18)),),
        ),
    )
)
# Two bars in an L, 3 m apart at the elbow (less than twice the clearance): grown by the
# clearance they are one keep-out, and the water inside the L opens out from the elbow.
TWO_BARS = Area(
    (
        Polygon(
            ring((0, 0), (60, 0), (60, 55), (0, 55)),
            (
                ring((10, 10), (40, 10), (40, 16), (10, 16)),
                ring((10, 19), (16, 19), (16, 45), (10, 45)),
            ),
        ),
    )
)
# A U-shaped lease with an L-shaped hole in one arm and a U-shaped hole in its base.
U_LEASE = Area(
    (
        Polygon(
            ring((0, 0), (80, 0), (80, 60), (55, 60), (55, 25), (25, 25), (25, 60), (0, 60)),
            (
                ring((4, 30), (21, 30), (21, 35), (10, 35), (10, 56), (4, 56)),
                ring((35, 4), (60, 4), (60, 20), (55, 20), (55, 9), (40, 9), (40, 20), (35, 20)),
            ),
        ),
    )
)


def grid_in(region: shapely.Geometry, step: float = 0.25) -> np.ndarray:
    e0, n0, e1, n1 = shapely.bounds(region)
    east, north = np.meshgrid(
        np.arange(e0, e1, step) + step / 2, np.arange(n0, n1, step) + step / 2
    )
    inside = shapely.contains_xy(region, east, north)
    return np.column_stack([east[inside], north[inside]])


def assert_clear_of_holes(plan: SurveyPlan, area: Area, clearance: float = CLEARANCE) -> None:
    """No leg comes within the clearance of a hole (less a millimetre), i.e. none meets
    the inside of a hole grown by the clearance, and none enters a keep-out deeper than a
    millimetre."""
    legs = shapely.linestrings([[leg.start, leg.end] for leg in plan.legs])
    for k, hole in enumerate(area.holes):
        gap = shapely.distance(legs, shapely.Polygon(hole))
        worst = int(np.argmin(gap))
        assert gap[worst] >= clearance - 1e-3, (
            f"{plan.legs[worst]} passes {gap[worst]:.3f} m from hole {k + 1}"
        )
    for keepout in plan.keepouts:
        inside = shapely.buffer(shapely.Polygon(keepout), -1e-3)
        assert not shapely.intersects(legs, inside).any()


@pytest.mark.parametrize("bearing_deg", [None, 0.0, 90.0])
def test_the_water_in_a_hole_s_bay_is_covered(bearing_deg: float | None) -> None:
    plan = plan_of(C_HOLE, bearing_deg)
    hole = shapely.Polygon(C_HOLE.holes[0])
    bay = shapely.difference(shapely.convex_hull(hole), hole)
    points = grid_in(bay)
    assert in_swath(plan, points).mean() >= 0.9
    # the boat goes into the bay, not round a hull that swallows it
    assert any(
        bay.contains(shapely.Point(run.entry)) or bay.contains(shapely.Point(run.exit))
        for run in plan.runs
    )
    assert_clear_of_holes(plan, C_HOLE)


def test_the_water_between_close_holes_is_covered_where_the_boat_fits() -> None:
    plan = plan_of(TWO_BARS)
    bars = [shapely.Polygon(h) for h in TWO_BARS.holes]
    assert shapely.distance(bars[0], bars[1]) < 2 * CLEARANCE and len(plan.keepouts) == 1
    holes = shapely.union_all(bars)
    between = shapely.difference(shapely.convex_hull(holes), holes)
    # The water the boat can come within the clearance of: wider there than twice the
    # clearance (at the elbow it is not; the swath from outside reaches in a little).
    open_water = shapely.difference(between, shapely.buffer(holes, CLEARANCE))
    reach = shapely.intersection(shapely.buffer(open_water, CLEARANCE), between)
    assert reach.area > 0.9 * between.area
    assert in_swath(plan, grid_in(reach)).mean() >= 0.99
    assert_clear_of_holes(plan, TWO_BARS)


def test_a_concave_lease_with_concave_holes_is_covered() -> None:
    plan = plan_of(U_LEASE)
    points = grid_inside(U_LEASE, 0.25)
    assert in_swath(plan, points).mean() >= 0.97
    assert coverage(U_LEASE, plan, HALF).fraction >= 0.97
    assert_clear_of_holes(plan, U_LEASE)


LOOPED = Area(
    (
        Polygon(
            ring((0, 0), (40, 0), (40, 30), (0, 30)),
            (ring((32, 15), (38, 15), (38, 17), (32, 17)),),
        ),
    )
)


def test_the_boat_goes_once_round_a_keepout_only_where_that_maps_water(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def loops(plan: SurveyPlan) -> int:
        """Stretches of detour legs that end where they began, once round a keep-out."""
        perimeter = shapely.Polygon(plan.keepouts[0]).length
        found = 0
        for kind, group in itertools.groupby(plan.legs, key=lambda leg: leg.kind):
            if kind is not LegKind.DETOUR:
                continue
            legs = list(group)
            points = [legs[0].start, *(leg.end for leg in legs)]
            along = np.cumsum([0.0, *(leg.length_m for leg in legs)])
            found += sum(
                1
                for i, j in itertools.combinations(range(len(points)), 2)
                if math.dist(points[i], points[j]) < 1e-9 and along[j] - along[i] > 0.9 * perimeter
            )
        return found

    # The lanes and the ways round the five-sided hole map all round it: no loop.
    assert loops(plan_of(WITH_HOLE)) == 0

    # Lanes at 30 degrees, swept from the west, stop at this hole near the east shore, and
    # nothing else passes between it and the shore: once round it maps that water.
    def lanes_at_30() -> SurveyPlan:
        return plan_path(
            LOOPED,
            bearing_rad=math.radians(30.0),
            spacing_m=SPACING,
            lead_in_m=LEAD_IN,
            clearance_m=CLEARANCE,
            half_width_m=HALF,
        )

    points = grid_inside(LOOPED)
    plan = lanes_at_30()
    assert loops(plan) == 1
    assert in_swath(plan, points).all()
    monkeypatch.setattr(planning.lawnmower, "LOOP_MIN_M2", math.inf)
    plan = lanes_at_30()
    assert loops(plan) == 0
    assert not in_swath(plan, points).all()


def test_the_way_round_a_keepout_is_the_shortest() -> None:
    # A square keep-out (no clearance), from 5 m west of it to 5 m east: over two corners.
    square = ring((0, 0), (10, 0), (10, 10), (0, 10))
    start, end = (-5.0, 5.0), (15.0, 5.0)
    path = [start, *Keepouts.around([square], 0.0).route(start, end), end]
    length = sum(math.dist(a, b) for a, b in itertools.pairwise(path))
    assert len(path) == 4
    assert length == pytest.approx(10 + 2 * math.hypot(5, 5), abs=0.05)  # 1 cm clear of it
    # Out of a C's bay to behind its back: out through the mouth and round an arm, as
    # short as the shortest path through the keep-out's own vertices (scipy's Dijkstra
    # over every pair of them that see each other), but for running 1 cm clear.
    c_keepouts = Keepouts.around(C_HOLE.holes, CLEARANCE)
    inside = shapely.buffer(c_keepouts.geometry, -1e-3)
    start, end = (30.0, 25.0), (52.0, 25.0)
    path = [start, *c_keepouts.route(start, end), end]
    legs = shapely.linestrings([[a, b] for a, b in itertools.pairwise(path)])
    assert not shapely.intersects(legs, inside).any()
    assert min(e for e, _ in path) < 15.0  # left the bay by its mouth
    nodes = np.vstack([[start, end], *c_keepouts.rings])
    i, j = np.triu_indices(len(nodes), 1)
    sight = ~shapely.intersects(shapely.linestrings(np.stack([nodes[i], nodes[j]], axis=1)), inside)
    graph = np.zeros((len(nodes), len(nodes)))
    graph[i[sight], j[sight]] = np.hypot(*(nodes[j] - nodes[i]).T)[sight]
    shortest = shortest_path(graph, directed=False, indices=0)[1]
    assert 0 <= sum(shapely.length(legs)) - shortest < 0.1


def star(centre: tuple[float, float], radii: list[float]) -> np.ndarray:
    angles = np.arange(len(radii)) * 2 * math.pi / len(radii)
    return np.column_stack([centre[0] + np.cos(angles) * radii, centre[1] + np.sin(angles) * radii])


@settings(max_examples=12, deadline=None)
@given(
    holes=st.lists(
        st.tuples(
            st.floats(12.0, 48.0),
            st.floats(10.0, 30.0),
            st.lists(st.floats(1.0, 7.0), min_size=3, max_size=9),
        ),
        min_size=1,
        max_size=3,
    ),
    clearance=st.sampled_from([0.0, 1.0, 2.0, 3.5]),
    lanes=st.floats(0.0, 180.0),
)
def test_no_leg_comes_within_the_clearance_of_any_hole(
    holes: list[tuple[float, float, list[float]]], clearance: float, lanes: float
) -> None:
    rings = [star((e, n), radii) for e, n, radii in holes]
    shapes = [shapely.Polygon(r) for r in rings]
    assume(all(not a.intersects(b) for a, b in itertools.combinations(shapes, 2)))
    area = Area((Polygon(ring((0, 0), (60, 0), (60, 40), (0, 40)), tuple(rings)),))
    plan = plan_survey(
        area,
        spacing_m=SPACING,
        bearing_rad=math.radians(lanes),
        lead_in_m=LEAD_IN,
        clearance_m=clearance,
    )
    assert_clear_of_holes(plan, area, clearance)


# --- validation ---

SQUARE = ring((0, 0), (40, 0), (40, 30), (0, 30))
INVALID = {
    "bowtie": (
        [ring((0, 0), (10, 10), (10, 0), (0, 10))],
        r"^polygon outer ring crosses itself \(edges 1 and 3\)$",
        (5.0, 5.0),
    ),
    "spike": (
        [ring((0, 0), (10, 0), (10, 10), (5, 10), (5, 15), (5, 10.01), (0, 10))],
        r"^polygon outer ring crosses itself \(edges 4 and 5\)$",
        (5.0, 15.0),
    ),
    "line": ([ring((0, 0), (1, 0), (2, 0))], r"has no area \(its points are in a line\)", None),
    "two points": ([ring((0, 0), (1, 0))], r"fewer than 3 distinct points \(2\)", None),
    "not a number": ([ring((0, 0), (1, 0), (math.nan, 1))], "not a number", None),
    "hole outside": (
        [SQUARE, ring((50, 5), (55, 5), (55, 10))],
        r"^polygon hole 1 is not inside its outer ring$",
        (53.75, 7.5),
    ),
    "hole across the shore": (
        [SQUARE, ring((35, 5), (45, 5), (45, 10), (35, 10))],
        r"^polygon hole 1 is not inside its outer ring$",
        (42.5, 7.5),
    ),
    "hole on the shore": (
        [SQUARE, ring((30, 5), (40, 5), (35, 10))],
        r"^polygon hole 1 is not inside its outer ring$",
        (40.0, 5.0),
    ),
    "holes overlapping": (
        [
            SQUARE,
            ring((5, 5), (15, 5), (15, 15), (5, 15)),
            ring((10, 10), (20, 10), (20, 20), (10, 20)),
        ],
        r"^polygon holes 1 and 2 overlap$",
        (12.5, 12.5),
    ),
    "hole in a hole": (
        [
            SQUARE,
            ring((5, 5), (25, 5), (25, 25), (5, 25)),
            ring((10, 10), (20, 10), (20, 20), (10, 20)),
        ],
        r"^polygon holes 1 and 2 overlap$",
        (15.0, 15.0),
    ),
    "hole crossing itself": (
        [SQUARE, ring((5, 5), (15, 15), (15, 5), (5, 15))],
        r"^polygon hole 1 crosses itself \(edges 1 and 3\)$",
        (10.0, 10.0),
    ),
}


@pytest.mark.parametrize("name", list(INVALID))
def test_invalid_areas_are_refused_saying_what_and_where(name: str) -> None:
    rings, message, where = INVALID[name]
    with pytest.raises(PlanningError, match=message) as caught:
        validate_area(Area((Polygon(rings[0], tuple(rings[1:])),)))
    assert "\n" not in str(caught.value)
    if where is None:
        assert caught.value.where is None
    else:
        assert caught.value.where == pytest.approx(where, abs=1e-6)


def test_the_second_polygon_is_named() -> None:
    bowtie = ring((50, 0), (60, 10), (60, 0), (50, 10))
    with pytest.raises(PlanningError, match=r"^polygon 2 outer ring crosses itself"):
        validate_area(Area((Polygon(SQUARE), Polygon(bowtie))))
    with pytest.raises(PlanningError, match=r"^no polygon$"):
        validate_area(Area(()))


# --- files ---


@pytest.fixture(scope="module")
def frame() -> LocalFrame:
    return LocalFrame.around(43.1, 5.9)


def write_area(path: Path, frame: LocalFrame, rings_local: list[np.ndarray]) -> Path:
    """A GeoJSON Feature with the rings (local metres) as a WGS84 polygon."""
    coordinates = []
    for local in rings_local:
        lat, lon = frame.to_latlon(local[:, 0], local[:, 1])
        positions = [[float(b), float(a)] for a, b in zip(lat, lon, strict=True)]
        coordinates.append([*positions, positions[0]])
    feature = {
        "type": "Feature",
        "properties": {"name": "test area"},
        "geometry": {"type": "Polygon", "coordinates": coordinates},
    }
    path.write_text(json.dumps(feature))
    return path


@pytest.fixture(scope="module")
def planned(tmp_path_factory: pytest.TempPathFactory, frame: LocalFrame) -> dict:
    folder = tmp_path_factory.mktemp("plan")
    poly = WITH_HOLE.polygons[0]
    area = write_area(folder / "area.geojson", frame, [poly.outer, *poly.holes])
    return plan_files(area, folder / "survey.plan", SiteConfig())


def test_plan_survey_writes_four_files_and_a_summary(planned: dict) -> None:
    names = [Path(f).name for f in planned["files"]]
    assert names == ["survey.plan", "survey.waypoints", "survey.geojson", "survey.png"]
    assert planned["spacing_m"] == pytest.approx(SPACING, abs=1e-3)
    assert planned["coverage"] == pytest.approx(1.0)
    assert planned["area_m2"] == pytest.approx(WITH_HOLE.area_m2, rel=1e-3)
    mission = read_plan(Path(planned["files"][0]))
    assert len(mission.waypoints) == planned["waypoints"]
    assert mission.speed_mps == 1.0 and mission.firmware == "ardupilot"
    # time = distance at speed plus turns: more than the distance alone, not absurdly more
    assert 1.0 < planned["duration_s"] / planned["distance_m"] < 1.5
    image = cv2.imread(planned["files"][3])
    assert image is not None and image.shape[0] > 300
    features = json.loads(Path(planned["files"][2]).read_text())["features"]
    roles = {f["properties"]["role"] for f in features}
    assert {"area", "keepout_hull", "lane", "detour", "turn", "waypoint"} <= roles
    points = [
        f["geometry"]["coordinates"] for f in features if f["properties"]["role"] == "waypoint"
    ]
    np.testing.assert_allclose(
        [[lat, lon] for lon, lat in points], [w[:2] for w in mission.waypoints], atol=1e-8
    )
    # The .plan carries the area for the daemon (``seamap survey start`` sends it), holes
    # kept, beside QGroundControl's keys; it reads back to the same area.
    doc = json.loads(Path(planned["files"][0]).read_text())
    assert set(doc) == {"fileType", "version", "groundStation", "mission", "geoFence",
                        "rallyPoints", "seamap"}  # fmt: skip
    carried = parse_area(json.dumps(doc["seamap"]["area"]), "plan")
    assert shapely.area(carried.area.geometry) == pytest.approx(WITH_HOLE.area_m2, rel=1e-3)
    assert len(doc["seamap"]["area"]["coordinates"][0]) == 2  # the outline and its hole


_LOAD_WAYPOINTS = """
import json, sys
from pymavlink import mavwp
loader = mavwp.MAVWPLoader()
count = loader.load(sys.argv[1])
print(json.dumps([[w.command, w.param2, w.x, w.y] for w in (loader.wp(k) for k in range(count))]))
"""


def test_the_mission_planner_file_loads_in_pymavlink(planned: dict) -> None:
    # In a fresh interpreter: mavwp builds MAVLink 1 or 2 items from MAVLINK20 as it is
    # when it runs, the dialect from MAVLINK20 as it was when pymavlink was first
    # imported; inside this test session the two can differ (drivers set MAVLINK20=1).
    mission = read_plan(Path(planned["files"][0]))
    done = subprocess.run(
        [sys.executable, "-c", _LOAD_WAYPOINTS, planned["files"][1]],
        capture_output=True, text=True, timeout=60, check=True,
    )  # fmt: skip
    items = json.loads(done.stdout)
    assert len(items) == 2 + len(mission.waypoints)  # home, speed, waypoints
    assert items[1][0] == mavlink.MAV_CMD_DO_CHANGE_SPEED
    assert items[1][1] == pytest.approx(1.0)
    assert all(item[0] == mavlink.MAV_CMD_NAV_WAYPOINT for item in items[2:])
    loaded = [(x, y) for _, _, x, y in items[2:]]
    np.testing.assert_allclose(loaded, [w[:2] for w in mission.waypoints], atol=1e-7)
    assert mission.home is not None
    assert tuple(items[0][2:]) == pytest.approx(mission.home[:2], abs=1e-7)


def import_with_mavsdk(plan: Path, autopilot: int) -> object:
    """MAVSDK's own QGroundControl import. MissionRaw needs a System, and a System
    appears when a heartbeat arrives: one HEARTBEAT of the given MAV_AUTOPILOT is handed
    to a "raw://" connection (no socket, no vehicle)."""
    from mavsdk.component_type import ComponentType
    from mavsdk.mavsdk import Configuration, Mavsdk
    from mavsdk.plugins.mission_raw import MissionRaw

    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        sdk.add_any_connection("raw://")
        sdk.subscribe_raw_bytes_to_be_sent(lambda data: None)  # nowhere to send: drop it
        encoder = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        heartbeat = encoder.heartbeat_encode(
            mavlink.MAV_TYPE_GROUND_ROVER, autopilot, 0, 0, mavlink.MAV_STATE_STANDBY
        )
        sdk.pass_received_raw_bytes(heartbeat.pack(encoder))
        system = sdk.first_autopilot(2.0)
        assert system is not None
        return MissionRaw(system).import_qgroundcontrol_mission(str(plan))
    finally:
        sdk.destroy()


def test_the_plan_round_trips_through_mavsdk(planned: dict, tmp_path: Path) -> None:
    path = Path(planned["files"][0])
    mission = read_plan(path)
    imported = import_with_mavsdk(path, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    items = imported.mission_items  # type: ignore[attr-defined]
    # ArduPilot: MAVSDK puts the planned home in as item 0, then our speed and waypoints
    assert len(items) == 2 + len(mission.waypoints)
    assert mission.home is not None
    assert (items[0].x / 1e7, items[0].y / 1e7) == pytest.approx(mission.home[:2], abs=1e-7)
    assert items[1].command == mavlink.MAV_CMD_DO_CHANGE_SPEED and items[1].param2 == 1.0
    waypoints = items[2:]
    assert all(i.command == mavlink.MAV_CMD_NAV_WAYPOINT and i.frame == 3 for i in waypoints)
    got = np.array([(i.x / 1e7, i.y / 1e7) for i in waypoints])
    np.testing.assert_allclose(got, [w[:2] for w in mission.waypoints], atol=1.01e-7)
    fence = imported.geofence_items  # type: ignore[attr-defined]
    assert len(fence) == len(WITH_HOLE.polygons[0].holes[0])  # the hole, as an exclusion

    px4 = plan_files(
        Path(planned["files"][0]).with_name("area.geojson"),
        tmp_path / "px4.plan",
        SiteConfig(),
        firmware="px4",
    )
    imported = import_with_mavsdk(Path(px4["files"][0]), mavlink.MAV_AUTOPILOT_PX4)
    items = imported.mission_items  # type: ignore[attr-defined]
    assert items[0].command == mavlink.MAV_CMD_DO_CHANGE_SPEED
    assert len(items) == 1 + px4["waypoints"]
    assert read_plan(Path(px4["files"][0])).firmware == "px4"


def test_angle_and_spacing_options_are_honoured(tmp_path: Path, frame: LocalFrame) -> None:
    # a 100 m x 15 m strip along 60 degrees grid; the summary speaks true bearings
    b = math.radians(60.0)
    along, across = np.array([math.sin(b), math.cos(b)]), np.array([math.cos(b), -math.sin(b)])
    corners = np.array([along * u + across * v for u, v in ((0, 0), (100, 0), (100, 15), (0, 15))])
    area = write_area(tmp_path / "strip.geojson", frame, [corners])
    lat, lon = frame.to_latlon(corners[:, 0].mean(), corners[:, 1].mean())
    true_deg = math.degrees(frame.grid_to_true(b, float(lat), float(lon)))
    auto = plan_files(area, tmp_path / "auto.plan", SiteConfig())
    assert auto["angle_deg"] == pytest.approx(true_deg, abs=0.5)
    assert auto["lanes"] == 4
    forced = plan_files(area, tmp_path / "forced", SiteConfig(), angle_deg=150.0, spacing_m=3.0)
    assert forced["angle_deg"] == pytest.approx(150.0, abs=1e-6)
    assert forced["spacing_m"] == 3.0
    assert forced["files"][0].endswith("forced.plan")
    assert forced["lanes"] > 25


def test_a_lat_lon_list_is_an_area(tmp_path: Path) -> None:
    text = "# harbour\nlat,lon\n43.1000,5.9000\n43.1000,5.9004\n43.1003,5.9004\n43.1003,5.9000\n"
    (tmp_path / "area.csv").write_text(text)
    summary = plan_files(tmp_path / "area.csv", tmp_path / "p.plan", SiteConfig(), entry="sw")
    assert summary["area_m2"] == pytest.approx(32.5 * 33.4, rel=0.03)
    first = read_plan(Path(summary["files"][0])).waypoints[0]
    assert first[0] < 43.10015 and first[1] < 5.9002  # starts at the south-west corner
    home = (43.1004, 5.9005)  # off the north-east corner
    summary = plan_files(tmp_path / "area.csv", tmp_path / "h.plan", SiteConfig(), home=home)
    mission = read_plan(Path(summary["files"][0]))
    assert mission.waypoints[0][0] > 43.10015 and mission.waypoints[0][1] > 5.9002
    assert mission.home == pytest.approx((*home, 0.0))


BAD_AREAS = {
    "invalid.geojson": ("{not json", "not GeoJSON"),
    "point.geojson": ('{"type": "Point", "coordinates": [5.9, 43.1]}', "no polygon"),
    "empty.geojson": ('{"type": "FeatureCollection", "features": []}', "no polygon"),
    "two.csv": ("43.1,5.9\n43.1,5.9004\n", "fewer than 3"),
    "bowtie.csv": (
        "43.1000,5.9000\n43.1003,5.9004\n43.1003,5.9000\n43.1000,5.9004\n",
        "crosses itself",
    ),
    "tiny.csv": ("43.1,5.9\n43.1,5.900005\n43.100005,5.9\n", "too small for one lane"),
    "range.geojson": (
        '{"type": "Polygon", "coordinates": [[[43.1, 95.0], [43.2, 95.0], [43.2, 95.1], '
        "[43.1, 95.0]]]}",
        "out of range",
    ),
    "words.txt": ("the harbour, please\n", "neither GeoJSON nor a lat,lon list"),
}


@pytest.mark.parametrize("name", list(BAD_AREAS))
def test_bad_areas_are_one_line_errors(tmp_path: Path, name: str) -> None:
    text, reason = BAD_AREAS[name]
    (tmp_path / name).write_text(text)
    with pytest.raises(SeamapError, match=reason) as caught:
        plan_files(tmp_path / name, tmp_path / "p.plan", SiteConfig())
    message = str(caught.value)
    assert "\n" not in message and name in message
    assert not (tmp_path / "p.plan").exists()


def test_bad_settings_are_one_line_errors(tmp_path: Path) -> None:
    area = tmp_path / "a.csv"
    area.write_text("43.1000,5.9000\n43.1000,5.9004\n43.1003,5.9004\n")
    for kwargs, reason in (
        ({"overlap": 1.0}, "overlap"),
        ({"speed_mps": 0.0}, "speed"),
        ({"entry": "north"}, "entry"),
        ({"firmware": "inav"}, "firmware"),
        ({"spacing_m": -1.0}, "spacing"),
    ):
        with pytest.raises(SeamapError, match=reason):
            plan_files(area, tmp_path / "p.plan", SiteConfig(), **kwargs)
    with pytest.raises(SeamapError, match="no such file"):
        plan_files(tmp_path / "missing.geojson", tmp_path / "p.plan", SiteConfig())
