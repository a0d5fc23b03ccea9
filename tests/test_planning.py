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
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from mapping.geo import LocalFrame
from planning import (
    Area,
    LegKind,
    Polygon,
    SurveyPlan,
    candidate_bearings,
    coverage,
    plan_survey,
    sonar_swath,
)
from seamap.config import SiteConfig, SonarConfig
from seamap.errors import SeamapError
from seamap.plan_files import DEFAULT_OVERLAP, read_plan, swath_from_config
from seamap.plan_files import plan_survey as plan_files

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
