"""Survey plans as files: the area in, the mission out.

``plan_survey`` reads the area, plans the lawnmower (``mapping.planning``) in the survey's
UTM frame (``mapping.geo.LocalFrame``) and writes four files next to ``out``:

- ``PLAN.plan``: a QGroundControl plan (JSON, fileType "Plan" version 1, mission version 2)
  that QGroundControl opens and MAVSDK's ``MissionRaw.import_qgroundcontrol_mission``
  reads: one DO_CHANGE_SPEED, then NAV_WAYPOINTs (frame GLOBAL_RELATIVE_ALT, altitude 0);
  the keep-out holes as exclusion geofence polygons. For ArduPilot, MAVSDK's import puts
  ``plannedHomePosition`` in as item 0, the home slot ArduPilot overwrites.
- ``PLAN.waypoints``: the same mission for Mission Planner (``QGC WPL 110``, line 0 home).
- ``PLAN.geojson``: the area, keep-out hulls, legs (LineStrings) and waypoints (Points),
  WGS84 lon/lat, for QGIS.
- ``PLAN.png``: a picture of the plan over the area, with the swath.

Area files are GeoJSON (RFC 7946: WGS84 [lon, lat]): a Polygon or MultiPolygon, bare, in a
Feature, or in a FeatureCollection holding exactly one polygon feature (others are
ignored); interior rings are keep-out holes; concave rings are fine. Or a vertex list
(``.csv``, ``.txt``, anything not starting with ``{``), one vertex per line::

    # comment lines and blank lines are ignored; an optional header "lat,lon"
    43.1234567,5.9012345
    43.1236000,5.9015000
    43.1231000,5.9017000

decimal degrees WGS84, latitude first, separated by a comma (or a semicolon, tab or
spaces); the ring closes itself (repeating the first vertex is allowed), no holes.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mapping.geo import LocalFrame
from mapping.planning import (
    MAPPING_LEGS,
    Area,
    LegKind,
    PlanningError,
    Polygon,
    SurveyPlan,
    Swath,
    clean_ring,
    coverage,
    sonar_swath,
    validate_area,
)
from mapping.planning import plan_survey as plan_lawnmower
from seamap.config import SiteConfig
from seamap.errors import SeamapError

FloatArray = npt.NDArray[np.float64]

FAN_DEG = {"low": 130.0, "high": 60.0}
"""Horizontal aperture of the M1200d's fan per operating frequency (degrees)."""

DEFAULT_OVERLAP = 0.5
"""Side overlap of adjacent lanes' usable swaths. At 50% every seabed point lies in the
swath of two lanes run in opposite directions: each strip of seabed is seen twice, from
either side, which gives the loop-closure registration between lanes (``[mapping]
loop_closures``) a band half a swath wide to match in, leaves room for the autopilot's
cross-track error and crabbing, and maps the edges of concave areas and the water round
keep-outs (``mapping.planning``). With the default sonar settings (5 m range, low
frequency, 15 degrees tilt, 1 m altitude) it gives about 4.1 m between lanes, the
spacing the simulator's scenarios use."""

FIRMWARE_TYPES = {"ardupilot": 3, "px4": 12}  # MAV_AUTOPILOT in the .plan's firmwareType
VEHICLE_TYPE = 10  # MAV_TYPE_GROUND_ROVER
MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_DO_CHANGE_SPEED = 178
MAV_FRAME_GLOBAL = 0
MAV_FRAME_MISSION = 2
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
ACCEPT_RADIUS_M = 2.0
"""NAV_WAYPOINT acceptance radius: ArduPilot Rover's default WP_RADIUS (whole metres:
ArduPilot keeps it in a byte). The lead-in leaves the boat straight for the rest."""
SPEED_TYPE_GROUND = 1  # DO_CHANGE_SPEED param1


@dataclass(frozen=True, eq=False)
class SurveyArea:
    """An area read from a file: its local frame, the area in local metres and its
    polygons in WGS84 as read (each a list of rings, outer first, (n, 2) lat/lon)."""

    frame: LocalFrame
    area: Area
    polygons_latlon: tuple[tuple[FloatArray, ...], ...]


@dataclass(frozen=True)
class PlanMission:
    """What ``read_plan`` finds in a .plan: the NAV_WAYPOINTs as (lat, lon, alt), the
    speed set by its DO_CHANGE_SPEED (m/s, None without one), the planned home
    (lat, lon, alt) and the firmware ("ardupilot", "px4" or "other")."""

    waypoints: list[tuple[float, float, float]]
    speed_mps: float | None
    home: tuple[float, float, float] | None
    firmware: str


# --- reading the area ---


def read_area(path: Path) -> SurveyArea:
    """The area of a GeoJSON or lat,lon file in its UTM frame; SeamapError (one line,
    naming the file) if it is not a usable survey area."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SeamapError(f"{path}: cannot read the area ({exc})") from None
    try:
        if path.suffix.lower() in (".geojson", ".json") or text.lstrip().startswith("{"):
            polygons = _geojson_polygons(text)
        else:
            polygons = _latlon_polygon(text)
        return _to_local(polygons)
    except (SeamapError, PlanningError) as exc:
        raise SeamapError(f"{path}: {exc}") from None


def _geojson_polygons(text: str) -> list[list[FloatArray]]:
    """Rings (outer first) of each polygon, as (n, 2) lat/lon arrays."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SeamapError(f"not GeoJSON (invalid JSON: {exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("type"), str):
        raise SeamapError('not GeoJSON (no "type" member)')
    _check_crs(doc)
    kind = doc["type"]
    if kind == "FeatureCollection":
        features = doc.get("features")
        if not isinstance(features, list):
            raise SeamapError('not GeoJSON (a FeatureCollection without a "features" list)')
        found = [
            f["geometry"]
            for f in features
            if isinstance(f, dict)
            and isinstance(f.get("geometry"), dict)
            and f["geometry"].get("type") in ("Polygon", "MultiPolygon")
        ]
        if not found:
            raise SeamapError("no polygon in the FeatureCollection")
        if len(found) > 1:
            raise SeamapError(
                f"{len(found)} polygon features; expected one (make one MultiPolygon of them)"
            )
        geometry = found[0]
    elif kind == "Feature":
        geometry = doc.get("geometry")
        if not isinstance(geometry, dict):
            raise SeamapError("no polygon (the Feature has no geometry)")
    else:
        geometry = doc
    gtype = geometry.get("type")
    if gtype not in ("Polygon", "MultiPolygon"):
        raise SeamapError(f"no polygon (the geometry is a {gtype})")
    coords = geometry.get("coordinates")
    polygons = [coords] if gtype == "Polygon" else coords
    if not isinstance(polygons, list) or not polygons:
        raise SeamapError(f"not GeoJSON (a {gtype} without coordinates)")
    out: list[list[FloatArray]] = []
    for k, rings in enumerate(polygons):
        if not isinstance(rings, list) or not rings:
            raise SeamapError(f"not GeoJSON (polygon {k + 1} has no rings)")
        out.append([_position_list(ring, k, i) for i, ring in enumerate(rings)])
    return out


def _check_crs(doc: dict[str, Any]) -> None:
    """Old GeoJSON (2008) named its CRS; only WGS84 lon/lat is accepted."""
    crs = doc.get("crs")
    if crs is None:
        return
    name = str(crs.get("properties", {}).get("name", "")) if isinstance(crs, dict) else ""
    if not re.search(r"CRS84$|EPSG:{1,2}4326$", name):
        raise SeamapError(f"the GeoJSON's crs {name or crs!r} is not WGS84 longitude/latitude")


def _position_list(ring: Any, polygon: int, index: int) -> FloatArray:
    """A GeoJSON ring ([lon, lat, (alt)] positions) as (n, 2) lat/lon."""
    where = f"polygon {polygon + 1} ring {index + 1}"
    if not isinstance(ring, list):
        raise SeamapError(f"not GeoJSON ({where} is not a list of positions)")
    latlon: list[tuple[float, float]] = []
    for position in ring:
        if (
            not isinstance(position, list)
            or len(position) < 2
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in position)
        ):
            raise SeamapError(f"not GeoJSON ({where} has a position {position!r})")
        latlon.append((float(position[1]), float(position[0])))
    return np.array(latlon, np.float64).reshape(-1, 2)


def _latlon_polygon(text: str) -> list[list[FloatArray]]:
    points: list[tuple[float, float]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f for f in re.split(r"[,;\s]+", line) if f]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if not points and re.fullmatch(r"[A-Za-z_ ,;\t]+", line):
                continue  # a header such as "lat,lon"
            raise SeamapError(
                f"neither GeoJSON nor a lat,lon list (line {number}: {line[:40]!r})"
            ) from None
        if len(values) != 2:
            raise SeamapError(f"line {number}: expected 'lat,lon', got {line[:40]!r}")
        points.append((values[0], values[1]))
    if not points:
        raise SeamapError("neither GeoJSON nor a lat,lon list (no points)")
    return [[np.array(points, np.float64)]]


def _to_local(polygons: list[list[FloatArray]]) -> SurveyArea:
    rings = [ring for polygon in polygons for ring in polygon]
    for ring in rings:
        bad = ~(
            np.isfinite(ring).all(axis=1) & (np.abs(ring[:, 0]) <= 90) & (np.abs(ring[:, 1]) <= 180)
        )
        if bad.any():
            lat, lon = ring[np.argmax(bad)]
            raise SeamapError(
                f"coordinates out of range: latitude {lat:g}, longitude {lon:g} "
                "(GeoJSON positions are [longitude, latitude]; the list format is lat,lon)"
            )
        outside = (ring[:, 0] < -80) | (ring[:, 0] > 84)
        if outside.any():
            raise SeamapError(
                f"coordinates out of range: latitude {ring[np.argmax(outside), 0]:g} is "
                "outside the UTM zones (-80..84)"
            )
    outer = np.concatenate([polygon[0] for polygon in polygons])
    lat0, lon0 = float(outer[:, 0].mean()), float(outer[:, 1].mean())
    frame = LocalFrame.around(lat0, lon0)
    local = []
    for polygon in polygons:
        metric = []
        for ring in polygon:
            x, y = frame.to_local(ring[:, 0], ring[:, 1])
            metric.append(clean_ring(np.column_stack([x, y])))
        local.append(Polygon(metric[0], tuple(metric[1:])))
    area = Area(tuple(local))
    try:
        validate_area(area)
    except PlanningError as exc:
        raise SeamapError(_located(exc, frame)) from None
    latlon = tuple(tuple(clean_ring(r) for r in polygon) for polygon in polygons)
    return SurveyArea(frame, area, latlon)


def _located(exc: PlanningError, frame: LocalFrame) -> str:
    if exc.where is None:
        return str(exc)
    lat, lon = frame.to_latlon(exc.where[0], exc.where[1])
    return f"{exc} near {float(lat):.7f},{float(lon):.7f}"


# --- planning ---


def swath_from_config(config: SiteConfig) -> Swath:
    """The usable swath of the configured sonar (``mapping.planning.sonar_swath``)."""
    sonar = config.sonar
    return sonar_swath(
        range_m=sonar.range_m,
        fan_deg=FAN_DEG[sonar.frequency],
        tilt_deg=sonar.tilt_deg,
        altitude_m=sonar.altitude_m,
        mount_forward_m=sonar.mount_x_m,
        mount_starboard_m=sonar.mount_y_m,
        mount_yaw_deg=sonar.mount_yaw_deg,
    )


def _check_settings(
    spacing_m: float | None,
    overlap: float,
    angle_deg: float | None,
    speed_mps: float,
    lead_in_m: float,
    entry: str,
    firmware: str,
    clearance_m: float,
) -> None:
    def bad(what: str, value: object, why: str) -> SeamapError:
        return SeamapError(f"survey plan: {what} {value!r} {why}")

    if spacing_m is not None and not (math.isfinite(spacing_m) and 0.1 <= spacing_m <= 1000):
        raise bad("spacing", spacing_m, "must be 0.1..1000 m")
    if not (math.isfinite(overlap) and 0.0 <= overlap <= 0.9):
        raise bad("overlap", overlap, "must be 0..0.9")
    if angle_deg is not None and not math.isfinite(angle_deg):
        raise bad("angle", angle_deg, "must be a number of degrees")
    if not (math.isfinite(speed_mps) and 0.05 <= speed_mps <= 20):
        raise bad("speed", speed_mps, "must be 0.05..20 m/s")
    if not (math.isfinite(lead_in_m) and 0 <= lead_in_m <= 200):
        raise bad("lead-in", lead_in_m, "must be 0..200 m")
    if not (math.isfinite(clearance_m) and 0 <= clearance_m <= 200):
        raise bad("clearance", clearance_m, "must be 0..200 m")
    if entry not in ("nw", "ne", "sw", "se", "auto"):
        raise bad("entry", entry, "is not one of nw, ne, sw, se, auto")
    if firmware not in FIRMWARE_TYPES:
        raise bad("firmware", firmware, f"is not one of {', '.join(FIRMWARE_TYPES)}")


def plan_survey(
    area: Path,
    out: Path,
    config: SiteConfig,
    *,
    spacing_m: float | None = None,
    overlap: float = DEFAULT_OVERLAP,
    angle_deg: float | None = None,
    speed_mps: float = 1.0,
    lead_in_m: float = 5.0,
    entry: str = "auto",
    firmware: str = "ardupilot",
    clearance_m: float = 2.0,
    home: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Plan a lawnmower over the area file and write PLAN.plan, .waypoints, .geojson, .png.

    spacing_m: between lanes (m); default from the sonar's usable swath and ``overlap``
    (0..0.9). angle_deg: lane direction, degrees clockwise from true north; default the
    one with the fewest runs and narrowest width across. speed_mps: survey speed.
    lead_in_m: straight run before and after the area on each lane. entry: the corner to
    start at (nw, ne, sw, se, or auto: nearest ``home`` (lat, lon) if given, else the
    quickest). firmware: "ardupilot" or "px4" (the .plan's firmwareType). clearance_m:
    distance kept from keep-out holes.

    Returns the summary: waypoints (NAV_WAYPOINTs in the mission), lanes, runs, spacing_m,
    swath_m (usable swath width), overlap (the one the spacing gives), angle_deg (lane
    axis, true, 0..180), lead_in_m, clearance_m, speed_mps, distance_m, duration_s (at
    speed, with turns), area_m2, covered_m2 (within the swath), coverage (their ratio),
    epsg (the UTM zone planned in) and files (the four paths). Raises SeamapError (one
    line) for bad input; nothing is written then.
    """
    _check_settings(
        spacing_m, overlap, angle_deg, speed_mps, lead_in_m, entry, firmware, clearance_m
    )
    survey = read_area(Path(area))
    frame = survey.frame
    try:
        swath = swath_from_config(config)
    except PlanningError as exc:
        raise SeamapError(f"survey plan: {exc}") from None
    spacing = spacing_m if spacing_m is not None else swath.spacing_for(overlap)
    spacing = round(spacing, 3)
    lat0, lon0 = _centre(survey)
    bearing = None
    if angle_deg is not None:
        bearing = frame.true_to_grid(math.radians(angle_deg), lat0, lon0)
    home_local = None
    if home is not None:
        hx, hy = frame.to_local(home[0], home[1])
        home_local = (float(hx), float(hy))
    try:
        plan = plan_lawnmower(
            survey.area,
            spacing_m=spacing,
            bearing_rad=bearing,
            lead_in_m=lead_in_m,
            clearance_m=clearance_m,
            speed_mps=speed_mps,
            entry=entry,
            home=home_local,
        )
    except PlanningError as exc:
        raise SeamapError(f"{area}: {_located(exc, frame)}") from None
    cover = coverage(survey.area, plan, swath.half_width_m)

    xy = plan.waypoints
    lat, lon = frame.to_latlon(xy[:, 0], xy[:, 1])
    waypoints = [(float(a), float(b)) for a, b in zip(lat, lon, strict=True)]
    home_latlon = home if home is not None else waypoints[0]
    true_axis = math.degrees(frame.grid_to_true(plan.bearing_rad, lat0, lon0)) % 180.0
    summary: dict[str, Any] = {
        "waypoints": len(waypoints),
        "lanes": plan.n_lanes,
        "runs": len(plan.runs),
        "spacing_m": spacing,
        "swath_m": round(swath.width_m, 3),
        "overlap": round(1.0 - spacing / swath.width_m, 3),
        "angle_deg": round(true_axis, 2),
        "lead_in_m": lead_in_m,
        "clearance_m": clearance_m,
        "speed_mps": speed_mps,
        "distance_m": round(plan.distance_m, 1),
        "duration_s": round(plan.duration_s(speed_mps), 1),
        "area_m2": round(cover.area_m2, 1),
        "covered_m2": round(cover.covered_m2, 1),
        "coverage": round(cover.fraction, 4),
        "epsg": frame.epsg,
    }

    base = Path(out)
    if base.suffix.lower() == ".plan":
        base = base.with_suffix("")
    paths = [base.with_name(base.name + ext) for ext in (".plan", ".waypoints", ".geojson", ".png")]
    holes = [ring for polygon in survey.polygons_latlon for ring in polygon[1:]]
    try:
        base.parent.mkdir(parents=True, exist_ok=True)
        _write_text(paths[0], qgc_plan(waypoints, speed_mps, home_latlon, firmware, holes))
        _write_text(paths[1], mission_planner_waypoints(waypoints, speed_mps, home_latlon))
        _write_text(paths[2], plan_geojson(survey, plan, summary))
        write_png(paths[3], survey, plan, swath, summary)
    except OSError as exc:
        raise SeamapError(f"{out}: cannot write the plan ({exc})") from None
    summary["files"] = [str(p) for p in paths]
    return summary


def _centre(survey: SurveyArea) -> tuple[float, float]:
    e0, n0, e1, n1 = survey.area.bounds
    lat, lon = survey.frame.to_latlon((e0 + e1) / 2, (n0 + n1) / 2)
    return float(lat), float(lon)


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


# --- writers ---


def qgc_plan(
    waypoints: list[tuple[float, float]],
    speed_mps: float,
    home: tuple[float, float],
    firmware: str = "ardupilot",
    keepouts: list[FloatArray] | None = None,
) -> str:
    """A QGroundControl .plan (JSON text): DO_CHANGE_SPEED, then the waypoints (lat, lon
    degrees) at altitude 0 relative to home; keep-outs (rings of lat/lon) as exclusion
    fence polygons."""
    items: list[dict[str, Any]] = [
        {
            "type": "SimpleItem",
            "autoContinue": True,
            "command": MAV_CMD_DO_CHANGE_SPEED,
            "doJumpId": 1,
            "frame": MAV_FRAME_MISSION,
            "params": [SPEED_TYPE_GROUND, speed_mps, -1, 0, 0, 0, 0],
        }
    ]
    for k, (lat, lon) in enumerate(waypoints):
        items.append(
            {
                "type": "SimpleItem",
                "AMSLAltAboveTerrain": None,
                "Altitude": 0,
                "AltitudeMode": 1,
                "autoContinue": True,
                "command": MAV_CMD_NAV_WAYPOINT,
                "doJumpId": k + 2,
                "frame": MAV_FRAME_GLOBAL_RELATIVE_ALT,
                # hold, acceptance radius, pass radius, yaw (null: unchanged), lat, lon, alt
                "params": [0, ACCEPT_RADIUS_M, 0, None, lat, lon, 0],
            }
        )
    fences = [
        {
            "inclusion": False,
            "polygon": [[float(lat), float(lon)] for lat, lon in ring],
            "version": 1,
        }
        for ring in keepouts or []
    ]
    plan = {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "seamap",
        "mission": {
            "version": 2,
            "firmwareType": FIRMWARE_TYPES[firmware],
            "vehicleType": VEHICLE_TYPE,
            "cruiseSpeed": speed_mps,
            "hoverSpeed": speed_mps,
            "plannedHomePosition": [home[0], home[1], 0],
            "items": items,
        },
        "geoFence": {"version": 2, "circles": [], "polygons": fences},
        "rallyPoints": {"version": 2, "points": []},
    }
    return json.dumps(plan, indent=2) + "\n"


def mission_planner_waypoints(
    waypoints: list[tuple[float, float]], speed_mps: float, home: tuple[float, float]
) -> str:
    """Mission Planner's ``QGC WPL 110`` text: line 0 home, then DO_CHANGE_SPEED and the
    waypoints (tab-separated: seq, current, frame, command, param1..4, lat, lon, alt,
    autocontinue)."""

    def line(seq: int, current: int, frame: int, command: int, params: list[float]) -> str:
        p1, p2, p3, p4, lat, lon, alt = params
        return (
            f"{seq}\t{current}\t{frame}\t{command}\t{p1:.6f}\t{p2:.6f}\t{p3:.6f}\t{p4:.6f}"
            f"\t{lat:.8f}\t{lon:.8f}\t{alt:.6f}\t1"
        )

    lines = [
        "QGC WPL 110",
        line(0, 1, MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT, [0, 0, 0, 0, home[0], home[1], 0]),
        line(
            1,
            0,
            MAV_FRAME_GLOBAL_RELATIVE_ALT,
            MAV_CMD_DO_CHANGE_SPEED,
            [SPEED_TYPE_GROUND, speed_mps, -1, 0, 0, 0, 0],
        ),
    ]
    for k, (lat, lon) in enumerate(waypoints):
        lines.append(
            line(
                k + 2,
                0,
                MAV_FRAME_GLOBAL_RELATIVE_ALT,
                MAV_CMD_NAV_WAYPOINT,
                [0, ACCEPT_RADIUS_M, 0, 0, lat, lon, 0],
            )
        )
    return "\n".join(lines) + "\n"


def _lonlat(frame: LocalFrame, xy: FloatArray) -> list[list[float]]:
    lat, lon = frame.to_latlon(xy[:, 0], xy[:, 1])
    return [[round(float(b), 8), round(float(a), 8)] for a, b in zip(lat, lon, strict=True)]


def plan_geojson(survey: SurveyArea, plan: SurveyPlan, summary: dict[str, Any]) -> str:
    """GeoJSON FeatureCollection (WGS84 lon/lat) of the area, keep-out hulls, the path's
    legs (consecutive legs of one kind and lane as one LineString) and the waypoints."""
    frame = survey.frame

    def closed(ring: list[list[float]]) -> list[list[float]]:
        return [*ring, ring[0]]

    polygons = [
        [closed([[round(float(lon), 8), round(float(lat), 8)] for lat, lon in r]) for r in p]
        for p in survey.polygons_latlon
    ]
    area_geometry = (
        {"type": "Polygon", "coordinates": polygons[0]}
        if len(polygons) == 1
        else {"type": "MultiPolygon", "coordinates": polygons}
    )
    area_props = {
        k: summary[k] for k in ("area_m2", "covered_m2", "coverage", "spacing_m", "angle_deg")
    }
    features: list[dict[str, Any]] = [
        {"type": "Feature", "properties": {"role": "area", **area_props}, "geometry": area_geometry}
    ]
    for hull in plan.keepouts:
        features.append(
            {
                "type": "Feature",
                "properties": {"role": "keepout_hull", "clearance_m": plan.clearance_m},
                "geometry": {"type": "Polygon", "coordinates": [closed(_lonlat(frame, hull))]},
            }
        )
    groups: list[tuple[LegKind, int, list[tuple[float, float]]]] = []
    for leg in plan.legs:
        if groups and groups[-1][0] == leg.kind and groups[-1][1] == leg.lane:
            groups[-1][2].append(leg.end)
        else:
            groups.append((leg.kind, leg.lane, [leg.start, leg.end]))
    for kind, lane, points in groups:
        xy = np.array(points)
        length = float(np.hypot(*np.diff(xy, axis=0).T).sum())
        features.append(
            {
                "type": "Feature",
                "properties": {
                    "role": str(kind),
                    "lane": lane,
                    "mapping": kind in MAPPING_LEGS,
                    "length_m": round(length, 2),
                },
                "geometry": {"type": "LineString", "coordinates": _lonlat(frame, xy)},
            }
        )
    for k, position in enumerate(_lonlat(frame, plan.waypoints)):
        features.append(
            {
                "type": "Feature",
                "properties": {"role": "waypoint", "index": k + 1},
                "geometry": {"type": "Point", "coordinates": position},
            }
        )
    return json.dumps({"type": "FeatureCollection", "features": features}) + "\n"


_LEG_STYLE = {
    LegKind.LANE: ("#1f4e9c", "-"),
    LegKind.TRANSIT: ("#1f4e9c", ":"),
    LegKind.DETOUR: ("#c2410c", "-"),
    LegKind.TURN: ("#6b7280", "--"),
}


def write_png(
    path: Path, survey: SurveyArea, plan: SurveyPlan, swath: Swath, summary: dict[str, Any]
) -> None:
    """A picture of the plan in local grid metres: area, keep-outs, swath, path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon as PolygonPatch

    figure = Figure(figsize=(8, 8), dpi=110)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    for polygon in survey.area.polygons:
        axes.add_patch(PolygonPatch(polygon.outer, closed=True, fc="#e8f1e4", ec="#2f6b2f"))
        for hole in polygon.holes:
            axes.add_patch(PolygonPatch(hole, closed=True, fc="#f3c9c0", ec="#b91c1c", hatch="//"))
    for hull in plan.keepouts:
        axes.add_patch(PolygonPatch(hull, closed=True, fill=False, ec="#b91c1c", ls="--", lw=0.8))
    bands = []
    hw = swath.half_width_m
    for leg in plan.legs:
        if leg.kind not in MAPPING_LEGS or leg.length_m <= 0:
            continue
        a, b = np.array(leg.start), np.array(leg.end)
        d = (b - a) / leg.length_m
        n = np.array([d[1], -d[0]]) * hw
        bands.append([a + n, b + n, b - n, a - n])
    axes.add_collection(PolyCollection(bands, facecolors="#60a5fa", edgecolors="none", alpha=0.12))
    for leg in plan.legs:
        colour, style = _LEG_STYLE[leg.kind]
        axes.plot(*zip(leg.start, leg.end, strict=True), color=colour, ls=style, lw=1.2)
    w = plan.waypoints
    axes.plot(w[:, 0], w[:, 1], ".", color="#111827", ms=3)
    axes.plot(*w[0], marker="^", color="#15803d", ms=10, label="start")
    axes.plot(*w[-1], marker="s", color="#b91c1c", ms=8, label="end")
    axes.set_aspect("equal")
    axes.autoscale_view()
    axes.set_xlabel("east (m, UTM grid, local)")
    axes.set_ylabel("north (m)")
    axes.grid(True, lw=0.3)
    axes.legend(loc="upper right", fontsize=8)
    axes.set_title(
        f"{summary['lanes']} lanes at {summary['angle_deg']:.1f}° true, "
        f"{summary['spacing_m']:.2f} m apart (swath {summary['swath_m']:.1f} m); "
        f"{summary['distance_m'] / 1000:.2f} km, {summary['duration_s'] / 60:.0f} min, "
        f"coverage {100 * summary['coverage']:.1f}%",
        fontsize=9,
    )
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as stream:
        figure.savefig(stream, format="png")
    os.replace(tmp, path)


# --- reading a plan back ---


def read_plan(path: Path) -> PlanMission:
    """The waypoints, speed, home and firmware of a QGroundControl .plan (SimpleItems
    only); SeamapError (one line) if it is not one."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SeamapError(f"{path}: cannot read the plan ({exc})") from None
    except json.JSONDecodeError as exc:
        raise SeamapError(f"{path}: not a QGroundControl plan (invalid JSON: {exc})") from None
    if not isinstance(doc, dict) or doc.get("fileType") != "Plan":
        raise SeamapError(f'{path}: not a QGroundControl plan (no "fileType": "Plan")')
    mission = doc.get("mission")
    if not isinstance(mission, dict) or not isinstance(mission.get("items"), list):
        raise SeamapError(f"{path}: the plan has no mission items")
    waypoints: list[tuple[float, float, float]] = []
    speed: float | None = None
    for k, item in enumerate(mission["items"]):
        if not isinstance(item, dict) or item.get("type") != "SimpleItem":
            kind = item.get("type") if isinstance(item, dict) else type(item).__name__
            raise SeamapError(f"{path}: mission item {k + 1} is a {kind}, not a SimpleItem")
        params = item.get("params")
        if not isinstance(params, list) or len(params) != 7:
            raise SeamapError(f"{path}: mission item {k + 1} does not have 7 params")
        try:
            if item.get("command") == MAV_CMD_NAV_WAYPOINT:
                waypoints.append((float(params[4]), float(params[5]), float(params[6] or 0.0)))
            elif item.get("command") == MAV_CMD_DO_CHANGE_SPEED and speed is None:
                speed = float(params[1])
        except (TypeError, ValueError):
            raise SeamapError(f"{path}: mission item {k + 1} has a bad position") from None
    home_raw = mission.get("plannedHomePosition")
    home = None
    if isinstance(home_raw, list) and len(home_raw) == 3:
        home = (float(home_raw[0]), float(home_raw[1]), float(home_raw[2] or 0.0))
    names = {v: k for k, v in FIRMWARE_TYPES.items()}
    firmware_type = mission.get("firmwareType")
    firmware = names.get(firmware_type, "other") if isinstance(firmware_type, int) else "other"
    return PlanMission(waypoints, speed, home, firmware)
