"""Survey plans as files: the area in, the mission out, and a mission read back.

``plan_survey`` reads the area (``drivers.formats.area``: GeoJSON or a lat,lon list), plans the
lawnmower (``planning.lawnmower``) in the survey's UTM frame (``mapping.geo.LocalFrame``) and
writes four files next to ``out`` (``drivers.formats.plan_export``):

- ``PLAN.plan``: a QGroundControl plan, which QGroundControl opens and MAVSDK imports;
- ``PLAN.waypoints``: the same mission for Mission Planner (``QGC WPL 110``);
- ``PLAN.geojson``: the area, keep-outs, legs and waypoints (WGS84 lon/lat), for QGIS;
- ``PLAN.png``: a picture of the plan over the area, with the swath.

``write_plan_files`` writes them for any planned path (``daemon.replan_files`` writes a
re-plan of a survey's gaps through it); ``read_plan`` reads the waypoints, speed, home and
firmware back from a ``.plan``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from daemon.config import SiteConfig
from drivers.errors import SeamapError
from drivers.formats.area import SurveyArea, area_geojson, located_message, read_area
from drivers.formats.plan_export import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_NAV_WAYPOINT,
    mission_planner_waypoints,
    plan_geojson,
    plan_title,
    qgc_plan,
    write_png,
)
from drivers.formats.qgc_plan import FIRMWARE_TYPES, load_plan
from planning.area import PlanningError
from planning.lawnmower import plan_survey as plan_lawnmower
from planning.plan import SurveyPlan
from planning.swath import Swath, sonar_swath
from planning.sweep import coverage

FAN_DEG = {"low": 130.0, "high": 60.0}
"""Horizontal aperture of the M1200d's fan per operating frequency (degrees)."""

DEFAULT_OVERLAP = 0.5
"""Side overlap of adjacent lanes' usable swaths. At 50% every seabed point lies in the
swath of two lanes run in opposite directions: each strip of seabed is seen twice, from
either side, which gives the loop-closure registration between lanes (``[mapping]
loop_closures``) a band half a swath wide to match in, leaves room for the autopilot's
cross-track error and crabbing, and maps the edges of concave areas and the water round
keep-outs (``planning.lawnmower``). With the default sonar settings (5 m range, low
frequency, 15 degrees tilt, 1 m altitude) it gives about 4.1 m between lanes, the
spacing the simulator's scenarios use."""


@dataclass(frozen=True)
class PlanMission:
    """What ``read_plan`` finds in a .plan: the NAV_WAYPOINTs as (lat, lon, alt), the
    speed set by its DO_CHANGE_SPEED (m/s, None without one), the planned home
    (lat, lon, alt) and the firmware ("ardupilot", "px4" or "other")."""

    waypoints: list[tuple[float, float, float]]
    speed_mps: float | None
    home: tuple[float, float, float] | None
    firmware: str


# --- planning ---


def swath_from_config(config: SiteConfig) -> Swath:
    """The usable swath of the configured sonar (``planning.swath.sonar_swath``)."""
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


def check_settings(
    spacing_m: float | None,
    overlap: float,
    angle_deg: float | None,
    speed_mps: float,
    lead_in_m: float,
    entry: str,
    firmware: str,
    clearance_m: float,
    command: str = "survey plan",
) -> None:
    """SeamapError (one line, starting with ``command``) for a setting out of its range."""

    def bad(what: str, value: object, why: str) -> SeamapError:
        return SeamapError(f"{command}: {what} {value!r} {why}")

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
    check_settings(
        spacing_m, overlap, angle_deg, speed_mps, lead_in_m, entry, firmware, clearance_m
    )
    survey = read_area(Path(area))
    frame = survey.frame
    swath = configured_swath(config, "survey plan")
    spacing = lane_spacing(swath, spacing_m, overlap)
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
            half_width_m=swath.half_width_m,
        )
    except PlanningError as exc:
        raise SeamapError(f"{area}: {located_message(exc, frame)}") from None
    cover = coverage(survey.area, plan, swath.half_width_m)

    waypoints = mission_waypoints(survey, plan)
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
    summary["files"] = write_plan_files(
        out,
        survey,
        plan,
        swath,
        waypoints,
        speed_mps=speed_mps,
        home=home,
        firmware=firmware,
        geojson=plan_geojson(survey, plan, summary),
        title=plan_title(summary),
    )
    return summary


def configured_swath(config: SiteConfig, command: str) -> Swath:
    """The configured sonar's usable swath; SeamapError (one line) if it has none."""
    try:
        return swath_from_config(config)
    except PlanningError as exc:
        raise SeamapError(f"{command}: {exc}") from None


def lane_spacing(swath: Swath, spacing_m: float | None, overlap: float) -> float:
    """The lanes' spacing (m): as given, else the swath's at ``overlap``; to the mm."""
    return round(spacing_m if spacing_m is not None else swath.spacing_for(overlap), 3)


def mission_waypoints(survey: SurveyArea, plan: SurveyPlan) -> list[tuple[float, float]]:
    """The path's waypoints as (lat, lon) degrees."""
    xy = plan.waypoints
    lat, lon = survey.frame.to_latlon(xy[:, 0], xy[:, 1])
    return [(float(a), float(b)) for a, b in zip(lat, lon, strict=True)]


def write_plan_files(
    out: Path,
    survey: SurveyArea,
    plan: SurveyPlan,
    swath: Swath,
    waypoints: list[tuple[float, float]],
    *,
    speed_mps: float,
    home: tuple[float, float] | None,
    firmware: str,
    geojson: str,
    title: str,
    gaps: Sequence[shapely.Polygon] = (),
) -> list[str]:
    """Write PLAN.plan, .waypoints, .geojson (``geojson``, the text) and .png (``title``,
    ``gaps`` drawn) next to ``out``; the planned home is ``home`` (lat, lon), else the
    first waypoint. The .plan carries what the mission is to cover (``qgc_plan``'s
    ``area``): the gaps when given, else the area. Returns the four paths; SeamapError
    (one line) if they cannot be written."""
    base = Path(out)
    if base.suffix.lower() == ".plan":
        base = base.with_suffix("")
    paths = [base.with_name(base.name + ext) for ext in (".plan", ".waypoints", ".geojson", ".png")]
    holes = [ring for polygon in survey.polygons_latlon for ring in polygon[1:]]
    home_latlon = home if home is not None else waypoints[0]
    target = _gaps_geometry(gaps, survey) if gaps else area_geojson(survey)
    try:
        base.parent.mkdir(parents=True, exist_ok=True)
        _write_text(paths[0], qgc_plan(waypoints, speed_mps, home_latlon, firmware, holes, target))
        _write_text(paths[1], mission_planner_waypoints(waypoints, speed_mps, home_latlon))
        _write_text(paths[2], geojson)
        write_png(paths[3], survey, plan, swath, title, gaps)
    except OSError as exc:
        raise SeamapError(f"{out}: cannot write the plan ({exc})") from None
    return [str(p) for p in paths]


def _gaps_geometry(gaps: Sequence[shapely.Polygon], survey: SurveyArea) -> dict[str, Any]:
    """The gaps (local metres of the area's frame) as a GeoJSON MultiPolygon (WGS84)."""
    frame = survey.frame
    polygons = []
    for gap in gaps:
        oriented = shapely.geometry.polygon.orient(gap, 1.0)
        rings = []
        for ring in (oriented.exterior, *oriented.interiors):
            xy = np.asarray(ring.coords)
            lat, lon = frame.to_latlon(xy[:, 0], xy[:, 1])
            rings.append(np.round(np.column_stack([lon, lat]), 9).tolist())
        polygons.append(rings)
    return {"type": "MultiPolygon", "coordinates": polygons}


def _centre(survey: SurveyArea) -> tuple[float, float]:
    e0, n0, e1, n1 = survey.area.bounds
    lat, lon = survey.frame.to_latlon((e0 + e1) / 2, (n0 + n1) / 2)
    return float(lat), float(lon)


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


# --- reading a plan back ---


def read_plan(path: Path) -> PlanMission:
    """The waypoints, speed, home and firmware of a QGroundControl .plan, read by the one
    .plan reader (``drivers.formats.qgc_plan.load_plan``); SeamapError (one line) if it is
    not one."""
    plan = load_plan(path)
    waypoints: list[tuple[float, float, float]] = []
    speed: float | None = None
    for item in plan.items:
        if item.command == MAV_CMD_NAV_WAYPOINT:
            lat, lon, alt = item.params[4:7]
            waypoints.append((lat, lon, alt if math.isfinite(alt) else 0.0))
        elif item.command == MAV_CMD_DO_CHANGE_SPEED and speed is None:
            speed = item.params[1]
    firmware = plan.firmware.value if plan.firmware is not None else "other"
    return PlanMission(waypoints, speed, plan.home, firmware)
