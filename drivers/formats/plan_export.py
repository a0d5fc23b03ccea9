"""Survey plan exporters: a planned lawnmower (``planning.lawnmower``) as mission files and
pictures.

- ``qgc_plan``: a QGroundControl plan (JSON, fileType "Plan" version 1, mission version 2)
  that QGroundControl opens and MAVSDK's ``MissionRaw.import_qgroundcontrol_mission``
  reads: one DO_CHANGE_SPEED, then NAV_WAYPOINTs (frame GLOBAL_RELATIVE_ALT, altitude 0);
  the keep-out holes as exclusion geofence polygons. For ArduPilot, MAVSDK's import puts
  ``plannedHomePosition`` in as item 0, the home slot ArduPilot overwrites.
- ``mission_planner_waypoints``: the same mission for Mission Planner (``QGC WPL 110``,
  line 0 home).
- ``plan_geojson``: the area, keep-outs (role ``keepout_hull``, the name they kept from
  when they were convex hulls), legs (LineStrings) and waypoints (Points), WGS84 lon/lat,
  for QGIS; for a re-plan (``daemon.replan_files``) the gaps too (role ``gap``).
- ``write_png``: a picture of the plan over the area, with the swath (and the gaps).

The MAVLink numbers the files carry are here too; ``drivers.formats.qgc_plan`` reads the
plans back (``daemon.plan_files.read_plan`` through it).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import shapely
from shapely.geometry.polygon import orient

from drivers.formats.area import SurveyArea
from drivers.formats.qgc_plan import FIRMWARE_TYPES
from mapping.geo import LocalFrame
from planning.plan import LegKind, SurveyPlan
from planning.swath import Swath
from planning.sweep import MAPPING_LEGS

FloatArray = npt.NDArray[np.float64]

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


def qgc_plan(
    waypoints: list[tuple[float, float]],
    speed_mps: float,
    home: tuple[float, float],
    firmware: str = "ardupilot",
    keepouts: list[FloatArray] | None = None,
    area: dict[str, Any] | None = None,
) -> str:
    """A QGroundControl .plan (JSON text): DO_CHANGE_SPEED, then the waypoints (lat, lon
    degrees) at altitude 0 relative to home; keep-outs (rings of lat/lon) as exclusion
    fence polygons; ``area``, the GeoJSON geometry (WGS84) the mission is to cover, as
    ``"seamap": {"version": 1, "area": ...}`` beside QGroundControl's own keys (which
    QGroundControl and MAVSDK leave alone): ``seamap survey start`` hands it to the
    daemon for the survey's coverage. Not a fence: turns and lead-ins lie outside it."""
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
    if area is not None:
        plan["seamap"] = {"version": 1, "area": area}
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


PLAN_AREA_PROPERTIES = ("area_m2", "covered_m2", "coverage", "spacing_m", "angle_deg")
"""The summary's keys a plan's area feature carries."""


def plan_geojson(
    survey: SurveyArea,
    plan: SurveyPlan,
    summary: dict[str, Any],
    *,
    area_properties: dict[str, Any] | None = None,
    gaps: Sequence[tuple[shapely.Polygon, dict[str, Any]]] = (),
) -> str:
    """GeoJSON FeatureCollection (WGS84 lon/lat) of the area, keep-outs, the path's
    legs (consecutive legs of one kind and lane as one LineString) and the waypoints.

    area_properties: the area feature's (default the summary's ``PLAN_AREA_PROPERTIES``);
    gaps: polygons in the survey's local metres, each a feature of role ``gap`` with its
    properties."""
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
    if area_properties is None:
        area_properties = {k: summary[k] for k in PLAN_AREA_PROPERTIES}
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"role": "area", **area_properties},
            "geometry": area_geometry,
        }
    ]
    for gap, properties in gaps:
        oriented = orient(gap, 1.0)  # RFC 7946: outer rings counterclockwise, holes clockwise
        rings = [oriented.exterior, *oriented.interiors]
        features.append(
            {
                "type": "Feature",
                "properties": {"role": "gap", **properties},
                "geometry": {
                    "type": "Polygon",
                    "coordinates": [_lonlat(frame, np.asarray(r.coords)) for r in rings],
                },
            }
        )
    for keepout in plan.keepouts:
        features.append(
            {
                "type": "Feature",
                "properties": {"role": "keepout_hull", "clearance_m": plan.clearance_m},
                "geometry": {"type": "Polygon", "coordinates": [closed(_lonlat(frame, keepout))]},
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


def plan_title(summary: dict[str, Any]) -> str:
    """The picture's title for a survey plan: lanes, spacing, length, time, coverage."""
    return (
        f"{summary['lanes']} lanes at {summary['angle_deg']:.1f}° true, "
        f"{summary['spacing_m']:.2f} m apart (swath {summary['swath_m']:.1f} m); "
        f"{summary['distance_m'] / 1000:.2f} km, {summary['duration_s'] / 60:.0f} min, "
        f"coverage {100 * summary['coverage']:.1f}%"
    )


def write_png(
    path: Path,
    survey: SurveyArea,
    plan: SurveyPlan,
    swath: Swath,
    title: str,
    gaps: Sequence[shapely.Polygon] = (),
) -> None:
    """A picture of the plan in local grid metres: area, keep-outs, gaps, swath, path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon as PolygonPatch

    figure = Figure(figsize=(8, 8), dpi=110)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    for polygon in survey.area.polygons:
        axes.add_patch(PolygonPatch(polygon.outer, closed=True, fc="#e8f1e4", ec="#2f6b2f"))
    for gap in gaps:
        outline = np.asarray(gap.exterior.coords)
        axes.add_patch(PolygonPatch(outline, closed=True, fc="#fb923c", ec="#c2410c", alpha=0.6))
        for island in gap.interiors:  # seen well enough (or a hole): the area's colour again
            axes.add_patch(PolygonPatch(np.asarray(island.coords), closed=True, fc="#e8f1e4"))
    for polygon in survey.area.polygons:
        for hole in polygon.holes:
            axes.add_patch(PolygonPatch(hole, closed=True, fc="#f3c9c0", ec="#b91c1c", hatch="//"))
    for keepout in plan.keepouts:
        axes.add_patch(
            PolygonPatch(keepout, closed=True, fill=False, ec="#b91c1c", ls="--", lw=0.8)
        )
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
    axes.set_title(title, fontsize=9)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as stream:
        figure.savefig(stream, format="png")
    os.replace(tmp, path)
