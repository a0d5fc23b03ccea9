"""Re-planning a survey's gaps as files: its coverage raster and area in, a mission over
what it missed out.

``replan_survey`` reads ``coverage.tif`` (``drivers.formats.results.read_coverage_tif``: band 3,
``meets_bar``, says which cells were seen well enough) and the area
(``drivers.formats.area.read_area``), finds the gaps (``planning.gaps``: the area, holes left
out, less the cells meeting the bar, each part of at least ``min_gap_m2``), plans lanes
over them (``planning.replan``) in the raster's UTM zone, and writes the four files
``seamap survey plan`` writes (``daemon.plan_files.write_plan_files``), the gaps added to
the GeoJSON and the picture. The boat starts from ``start`` (lat, lon), else from the last
row of the survey's ``trajectory.csv``, else from the area's first vertex.
"""

from __future__ import annotations

import csv
import math
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from daemon.config import SiteConfig
from daemon.coverage import COVERAGE_TIF
from daemon.plan_files import (
    DEFAULT_OVERLAP,
    check_settings,
    configured_swath,
    lane_spacing,
    mission_waypoints,
    write_plan_files,
)
from drivers.errors import SeamapError
from drivers.formats.area import SurveyArea, area_in, located_message, read_area
from drivers.formats.plan_export import plan_geojson
from drivers.formats.results import CoverageRaster, read_coverage_tif
from mapping.geo import LocalFrame
from planning.area import Area, PlanningError, validate_area
from planning.gaps import area_gaps, cells_geometry
from planning.plan import SurveyPlan
from planning.replan import plan_gaps
from planning.sweep import swath_cover

COMMAND = "survey replan"
TRAJECTORY_CSV = "trajectory.csv"
AREA_VERTEX = "the area's first vertex"
MAX_START_KM = 50.0
"""A start farther than this from the area is a mistake (latitude and longitude swapped,
another site's survey), not a boat about to re-survey it."""


def replan_survey(
    area: Path,
    out: Path,
    config: SiteConfig,
    *,
    survey: Path | None = None,
    coverage: Path | None = None,
    min_gap_m2: float | None = None,
    spacing_m: float | None = None,
    speed_mps: float = 1.0,
    lead_in_m: float = 5.0,
    firmware: str = "ardupilot",
    clearance_m: float = 2.0,
    start: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Plan lanes over what the survey missed of the area and write GAPS.plan, .waypoints,
    .geojson and .png next to ``out``.

    survey: the survey's result folder (its coverage.tif and trajectory.csv), or
    coverage: a coverage.tif; exactly one. min_gap_m2: the smallest gap planned (default
    the config's ``[coverage] min_gap_m2``). spacing_m: between lanes (default the
    sonar's swath at ``survey plan``'s overlap); speed_mps, lead_in_m, firmware,
    clearance_m: as for ``survey plan``. start: where the boat is, (lat, lon) degrees.

    Returns the summary: ``survey plan``'s (``area_m2``, ``covered_m2`` and ``coverage``
    are the gaps', their part within the plan's swath and its fraction; ``angle_deg`` the
    first group's lanes, ``angles_deg`` every group's) and ``gaps`` (how many),
    ``groups``, ``unreachable`` (gaps no lane reaches) and their ``unreachable_m2``,
    ``min_gap_m2``, ``survey`` (the area's ``area_m2``, ``covered_m2`` and
    ``covered_fraction`` in the raster), ``start`` (lat, lon), ``start_from`` (what gave
    it), ``approach_m`` (from there to the first lane), ``coverage_file``. With no gap,
    ``gaps`` is 0 and ``files`` empty: nothing is written. Raises SeamapError (one line)
    for bad input; nothing is written then.
    """
    gap_floor = config.coverage.min_gap_m2 if min_gap_m2 is None else min_gap_m2
    check_settings(
        spacing_m, DEFAULT_OVERLAP, None, speed_mps, lead_in_m, "auto", firmware, clearance_m,
        COMMAND,
    )  # fmt: skip
    if not (math.isfinite(gap_floor) and gap_floor >= 0):
        raise SeamapError(f"{COMMAND}: min-gap {gap_floor!r} must be 0 m² or more")
    if (survey is None) == (coverage is None):
        raise SeamapError(f"{COMMAND}: give one of the survey folder and a coverage.tif")
    if survey is not None:
        if not Path(survey).is_dir():
            raise SeamapError(f"{survey}: no such survey folder")
        coverage = Path(survey) / COVERAGE_TIF
    assert coverage is not None
    raster = read_coverage_tif(Path(coverage))
    read = read_area(Path(area))
    frame = _raster_frame(raster)
    local = area_in(read, frame)
    try:
        validate_area(local)
    except PlanningError as exc:
        raise SeamapError(
            f"{area}: in {coverage}'s UTM zone, {located_message(exc, frame)}"
        ) from None
    if not shapely.intersects(shapely.box(*_extent(raster, frame)), local.geometry):
        if not raster.meets_bar.any():  # an empty survey's raster is one cell at 0, 0
            raise SeamapError(
                f"{coverage}: no cell meets the bar: the survey saw nothing well enough; "
                "plan the whole area with `seamap survey plan`"
            )
        raise SeamapError(
            f"{area}: the area does not overlap the coverage raster {coverage} "
            f"(EPSG:{raster.epsg}, {raster.meets_bar.shape[1]} x {raster.meets_bar.shape[0]} "
            f"cells of {raster.cell_m:g} m)"
        )
    the_area = SurveyArea(frame, local, read.polygons_latlon)
    covered = _covered(raster, frame, local.bounds)
    found = area_gaps(local, covered, gap_floor)
    summary: dict[str, Any] = {
        "gaps": len(found.gaps),
        "gaps_m2": round(found.gaps_m2, 1),
        "min_gap_m2": gap_floor,
        "survey": {
            "area_m2": round(found.area_m2, 1),
            "covered_m2": round(found.covered_m2, 1),
            "covered_fraction": round(found.fraction, 4),
        },
        "coverage_file": str(coverage),
        "epsg": frame.epsg,
        "files": [],
    }
    if not found.gaps:
        return summary

    swath = configured_swath(config, COMMAND)
    spacing = lane_spacing(swath, spacing_m, DEFAULT_OVERLAP)
    start_latlon, start_from = _start(start, survey, read)
    sx, sy = frame.to_local(start_latlon[0], start_latlon[1])
    here = (float(sx), float(sy))
    away_km = float(shapely.distance(shapely.Point(here), local.geometry)) / 1000.0
    if not away_km <= MAX_START_KM:
        lat, lon = start_latlon
        raise SeamapError(
            f"{COMMAND}: the start {lat:.7f},{lon:.7f} ({start_from}) is {away_km:.0f} km "
            f"from the area (more than {MAX_START_KM:g} km; LAT,LON in that order?)"
        )
    try:
        replan = plan_gaps(
            local,
            found.gaps,
            start=here,
            spacing_m=spacing,
            half_width_m=swath.half_width_m,
            lead_in_m=lead_in_m,
            clearance_m=clearance_m,
            speed_mps=speed_mps,
        )
    except PlanningError as exc:
        raise SeamapError(f"{area}: {located_message(exc, frame)}") from None
    plan = replan.plan
    waypoints = mission_waypoints(the_area, plan)
    angles = [_true_deg(frame, group.bearing_rad, local) for group in replan.groups]
    unreachable = [found.gaps[i] for i in replan.unreachable]
    summary.update(
        {
            "waypoints": len(waypoints),
            "lanes": plan.n_lanes,
            "runs": len(plan.runs),
            "groups": len(replan.groups),
            "unreachable": len(unreachable),
            "unreachable_m2": round(sum(g.area for g in unreachable), 1),
            "spacing_m": spacing,
            "swath_m": round(swath.width_m, 3),
            "overlap": round(1.0 - spacing / swath.width_m, 3),
            "angle_deg": angles[0],
            "angles_deg": angles,
            "lead_in_m": lead_in_m,
            "clearance_m": clearance_m,
            "speed_mps": speed_mps,
            "distance_m": round(plan.distance_m, 1),
            "duration_s": round(plan.duration_s(speed_mps), 1),
            "area_m2": round(replan.coverage.area_m2, 1),
            "covered_m2": round(replan.coverage.covered_m2, 1),
            "coverage": round(replan.coverage.fraction, 4),
            "start": [round(start_latlon[0], 8), round(start_latlon[1], 8)],
            "start_from": start_from,
            "approach_m": round(replan.approach_m, 1),
        }
    )
    gap_features = _gap_features(found.gaps, replan.unreachable, plan, swath.half_width_m)
    summary["files"] = write_plan_files(
        out,
        the_area,
        plan,
        swath,
        waypoints,
        speed_mps=speed_mps,
        home=start_latlon if start_from != AREA_VERTEX else None,
        firmware=firmware,
        geojson=plan_geojson(
            the_area, plan, summary, area_properties=summary["survey"], gaps=gap_features
        ),
        title=_title(summary),
        gaps=found.gaps,
    )
    return summary


def _raster_frame(raster: CoverageRaster) -> LocalFrame:
    """A local frame in the raster's UTM zone, anchored at a round point near its corner."""
    return LocalFrame(
        raster.epsg, round(raster.west_m / 100.0) * 100.0, round(raster.north_m / 100.0) * 100.0
    )


def _extent(raster: CoverageRaster, frame: LocalFrame) -> tuple[float, float, float, float]:
    """The raster's (west, south, east, north) in the frame's local metres."""
    rows, cols = raster.meets_bar.shape
    west = raster.west_m - frame.anchor_e
    north = raster.north_m - frame.anchor_n
    return west, north - rows * raster.cell_m, west + cols * raster.cell_m, north


def _covered(
    raster: CoverageRaster, frame: LocalFrame, bounds: tuple[float, float, float, float]
) -> shapely.Geometry:
    """The cells meeting the bar within ``bounds`` (local east/north min/max, metres) and
    a cell round them, as one geometry in local metres: no need to trace the rest."""
    west, _, _, north = _extent(raster, frame)
    c = raster.cell_m
    e0, n0, e1, n1 = bounds
    rows, cols = raster.meets_bar.shape
    col0 = int(np.clip(math.floor((e0 - west) / c) - 1, 0, cols))
    col1 = int(np.clip(math.ceil((e1 - west) / c) + 1, 0, cols))
    row0 = int(np.clip(math.floor((north - n1) / c) - 1, 0, rows))
    row1 = int(np.clip(math.ceil((north - n0) / c) + 1, 0, rows))
    cells = raster.meets_bar[row0:row1, col0:col1]
    return cells_geometry(cells, west + col0 * c, north - row0 * c, c)


def _start(
    start: tuple[float, float] | None, survey: Path | None, area: SurveyArea
) -> tuple[tuple[float, float], str]:
    """Where the boat starts, (lat, lon), and what said so."""
    if start is not None:
        lat, lon = start
        if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
            raise SeamapError(f"{COMMAND}: --from {lat:g},{lon:g} is not a latitude,longitude")
        return (lat, lon), "--from"
    if survey is not None and (Path(survey) / TRAJECTORY_CSV).is_file():
        return last_position(Path(survey) / TRAJECTORY_CSV), TRAJECTORY_CSV
    lat, lon = area.polygons_latlon[0][0][0]
    return (float(lat), float(lon)), AREA_VERTEX


def last_position(path: Path) -> tuple[float, float]:
    """The (lat, lon) of a trajectory.csv's last row; SeamapError (one line) if it has
    none or is not one."""
    try:
        with open(path, newline="", encoding="utf-8") as stream:
            reader = csv.DictReader(stream)
            if not reader.fieldnames or not {"lat", "lon"} <= set(reader.fieldnames):
                raise SeamapError(f"{path}: not a trajectory.csv (no lat and lon columns)")
            rows = deque(reader, maxlen=1)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise SeamapError(f"{path}: cannot read the trajectory ({exc})") from None
    if not rows:
        raise SeamapError(f"{path}: the trajectory has no row")
    last = rows[0]
    try:
        lat, lon = float(last["lat"]), float(last["lon"])
    except (TypeError, ValueError):
        raise SeamapError(f"{path}: its last row has no position") from None
    if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
        raise SeamapError(f"{path}: its last row has no position")
    return lat, lon


def _true_deg(frame: LocalFrame, bearing_rad: float, area: Area) -> float:
    """A lane axis (grid radians) as degrees from true north, 0..180, at the area's centre."""
    e0, n0, e1, n1 = area.bounds
    lat, lon = frame.to_latlon((e0 + e1) / 2, (n0 + n1) / 2)
    return round(math.degrees(frame.grid_to_true(bearing_rad, float(lat), float(lon))) % 180.0, 2)


def _gap_features(
    gaps: tuple[shapely.Polygon, ...],
    unreachable: tuple[int, ...],
    plan: SurveyPlan,
    half_width_m: float,
) -> list[tuple[shapely.Polygon, dict[str, Any]]]:
    """Each gap with its id (1 the largest, as gaps.geojson numbers them), area, the part
    the plan's swath covers and whether a lane reaches it."""
    swept = swath_cover(plan.legs, half_width_m)
    return [
        (
            gap,
            {
                "id": number,
                "area_m2": round(float(gap.area), 3),
                "covered_m2": round(float(shapely.area(shapely.intersection(gap, swept))), 3),
                "reached": k not in unreachable,
            },
        )
        for k, (number, gap) in enumerate(enumerate(gaps, start=1))
    ]


def _title(summary: dict[str, Any]) -> str:
    """The picture's title: gaps, lanes, length, time and how much of the gaps it maps."""
    return (
        f"{summary['gaps']} gaps ({summary['gaps_m2']:.0f} m²): {summary['lanes']} lanes, "
        f"{summary['spacing_m']:.2f} m apart; {summary['distance_m'] / 1000:.2f} km, "
        f"{summary['duration_s'] / 60:.0f} min; maps {100 * summary['coverage']:.1f}% of the gaps"
    )
