"""The result folder's coverage: how well each seabed cell was seen (coverage.tif,
coverage.png) and, when the survey's area is known, what it missed (gaps.geojson), with
what report.json says of them. The daemon's live coverage is ``daemon.live_coverage``.

Glue between a mapped survey (``mapping.pipeline.SurveyResult``: vehicle poses in its
local frame), the coverage core (``mapping.coverage``), the gaps of an area
(``planning.gaps``) and the file writers (``drivers.formats.results``). Degrees and the file
names live here, at the edge; the core takes radians and metres.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from daemon.config import CoverageConfig
from drivers.formats.area import SurveyArea, area_in
from drivers.formats.results import (
    write_coverage_png,
    write_coverage_tif,
    write_gaps,
)
from mapping.coverage import CoverageGrid, CoverageParams, SeabedCoverage, SonarFan, footprint
from mapping.geo import LocalFrame
from mapping.pipeline import SurveyResult
from planning.gaps import AreaCoverage, area_gaps, cells_geometry

log = logging.getLogger(__name__)

COVERAGE_TIF = "coverage.tif"
COVERAGE_PNG = "coverage.png"
GAPS_GEOJSON = "gaps.geojson"


def coverage_params(config: CoverageConfig) -> CoverageParams:
    """The core's settings from the site config's [coverage] table."""
    return CoverageParams(
        cell_m=config.cell_m,
        min_passes=config.min_passes,
        min_range_m=config.min_range_m,
        max_range_m=config.max_range_m,
        min_grazing_rad=math.radians(config.min_grazing_deg),
        pass_gap_s=config.pass_gap_s,
    )


def survey_coverage(result: SurveyResult, fan: SonarFan, params: CoverageParams) -> CoverageGrid:
    """The coverage raster of a survey's mapped frames, on its UTM grid."""
    coverage = SeabedCoverage(
        result.mount,
        fan,
        params,
        anchor_e=result.frame.anchor_e,
        anchor_n=result.frame.anchor_n,
    )
    mapped = result.mapped
    coverage.add_frames(result.times[mapped], result.poses[mapped])
    return coverage.grid()


@dataclass(frozen=True)
class AreaSource:
    """A survey area as read (``drivers.formats.area.read_area``) and the file it came from."""

    path: Path
    area: SurveyArea


def area_coverage(
    grid: CoverageGrid, min_passes: int, frame: LocalFrame, area: SurveyArea, min_gap_m2: float
) -> AreaCoverage:
    """What of the area the raster's cells meeting the bar cover, and its gaps (local
    metres of ``frame``, the survey's)."""
    covered = cells_geometry(
        grid.meets(min_passes),
        grid.west_m - frame.anchor_e,
        grid.north_m - frame.anchor_n,
        grid.cell_m,
    )
    return area_gaps(area_in(area, frame), covered, min_gap_m2)


def _area_report(found: AreaCoverage, min_gap_m2: float) -> dict[str, Any]:
    return {
        "area_m2": round(found.area_m2, 3),
        "covered_m2": round(found.covered_m2, 3),
        "covered_fraction": round(found.fraction, 5),
        "gaps": len(found.gaps),
        "gaps_m2": round(found.gaps_m2, 3),
        "min_gap_m2": min_gap_m2,
    }


@dataclass(frozen=True)
class CoverageWritten:
    """What ``write_coverage`` wrote: report.json's "coverage" object, the files and,
    with an area, the area's polygons and its gaps (local metres of the survey's frame,
    gaps largest first, as gaps.geojson numbers them)."""

    report: dict[str, Any]
    files: list[str]
    area: tuple[shapely.Polygon, ...] | None = None
    gaps: tuple[shapely.Polygon, ...] | None = None


def write_coverage(
    out: Path,
    result: SurveyResult,
    fan: SonarFan,
    config: CoverageConfig,
    area: AreaSource | None = None,
) -> CoverageWritten:
    """Write coverage.tif, coverage.png and, with an area, gaps.geojson into ``out``
    (without one, a gaps.geojson left by an earlier run goes: it would not be this
    survey's)."""
    params = coverage_params(config)
    grid = survey_coverage(result, fan, params)
    epsg = result.frame.epsg
    write_coverage_tif(out / COVERAGE_TIF, grid, epsg, params.min_passes)
    write_coverage_png(out / COVERAGE_PNG, grid, params.min_passes)
    files = [COVERAGE_TIF, COVERAGE_PNG]
    band = footprint(fan, params, result.mount.altitude_m)  # at the mount's altitude
    seen = grid.passes > 0
    report: dict[str, Any] = {
        "cell_m": params.cell_m,
        "min_passes": params.min_passes,
        "pass_gap_s": params.pass_gap_s,
        "min_grazing_deg": config.min_grazing_deg,
        "half_fan_deg": round(math.degrees(fan.half_angle_rad), 3),
        "ground_range_m": [round(band.rho_min_m, 3), round(band.rho_max_m, 3)],
        "forward_min_m": round(band.forward_min_m, 3),
        "cells_seen": int(np.count_nonzero(seen)),
        "seen_m2": round(float(np.count_nonzero(seen)) * params.cell_m**2, 3),
        "covered_m2": round(grid.covered_m2(params.min_passes), 3),
        "max_passes": int(grid.passes.max()) if grid.passes.size else 0,
        "crs": {"epsg": epsg, "west": grid.west_m, "north": grid.north_m},
    }
    gaps_path = out / GAPS_GEOJSON
    if area is None:
        gaps_path.unlink(missing_ok=True)
        return CoverageWritten(report, files)
    found = area_coverage(grid, params.min_passes, result.frame, area.area, config.min_gap_m2)
    write_gaps(gaps_path, found.gaps, result.frame)
    files.append(GAPS_GEOJSON)
    report["area"] = {"file": str(area.path), **_area_report(found, config.min_gap_m2)}
    polygons = tuple(
        shapely.Polygon(p.outer, list(p.holes)) for p in area_in(area.area, result.frame).polygons
    )
    return CoverageWritten(report, files, polygons, found.gaps)
