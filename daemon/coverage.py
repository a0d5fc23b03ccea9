"""The result folder's coverage: how well each seabed cell was seen (coverage.tif,
coverage.png) and, when the survey's area is known, what it missed (gaps.geojson), with
what report.json says of them; and the daemon's live coverage (``LiveCoverage``) with its
zenoh publications (``CoverageMessage``: ``drivers.zenoh_io``'s coverage keys).

Glue between a mapped survey (``mapping.pipeline.SurveyResult``: vehicle poses in its
local frame), the coverage core (``mapping.coverage``), the gaps of an area
(``planning.gaps``) and the file writers (``drivers.formats.results``). Degrees and the file
names live here, at the edge; the core takes radians and metres.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon.config import CoverageConfig
from drivers.errors import SeamapError
from drivers.formats.area import SurveyArea, area_in
from drivers.formats.results import (
    coverage_image,
    gaps_geojson,
    png_bytes,
    read_coverage_tif,
    write_coverage_png,
    write_coverage_tif,
    write_gaps,
)
from drivers.zenoh_io import CoverageInfo
from mapping.coverage import CoverageGrid, CoverageParams, SeabedCoverage, SonarFan, footprint
from mapping.frames import SonarMount
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


def write_coverage(
    out: Path,
    result: SurveyResult,
    fan: SonarFan,
    config: CoverageConfig,
    area: AreaSource | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """Write coverage.tif, coverage.png and, with an area, gaps.geojson into ``out``
    (without one, a gaps.geojson left by an earlier run goes: it would not be this
    survey's); returns report.json's "coverage" object and the files written."""
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
        return report, files
    found = area_coverage(grid, params.min_passes, result.frame, area.area, config.min_gap_m2)
    write_gaps(gaps_path, found.gaps, result.frame)
    files.append(GAPS_GEOJSON)
    report["area"] = {"file": str(area.path), **_area_report(found, config.min_gap_m2)}
    return report, files


# --- live: the daemon's coverage as the live map places its frames -------------------------


@dataclass(frozen=True)
class CoverageMessage:
    """One coverage publication (``drivers.zenoh_io``'s coverage keys): the summary (JSON
    object, gaps included), the raster as PNG and its attachment."""

    summary: dict[str, Any]
    png: bytes
    info: CoverageInfo

    def status(self) -> dict[str, Any]:
        """The summary without its gaps' outlines (for the daemon's status)."""
        return {k: v for k, v in self.summary.items() if k != "gaps"}


def coverage_message(
    survey: str,
    grid: CoverageGrid,
    params: CoverageParams,
    frame: LocalFrame,
    area: SurveyArea | None,
    min_gap_m2: float,
    *,
    final: bool,
    version: int,
) -> CoverageMessage:
    """The publication of a coverage raster (UTM, on ``frame``'s grid) and, with the
    survey's area, its covered fraction and gaps."""
    seen = int(np.count_nonzero(grid.passes > 0))
    area_part: dict[str, Any] | None = None
    gaps: dict[str, Any] = {"type": "FeatureCollection", "features": []}
    if area is not None:
        found = area_coverage(grid, params.min_passes, frame, area, min_gap_m2)
        report = _area_report(found, min_gap_m2)
        area_part = _area_message(report)
        gaps = gaps_geojson(found.gaps, frame)
    rows, cols = grid.passes.shape
    summary = _summary(
        survey, final, version, frame.epsg, grid.cell_m, params.min_passes,
        round(seen * grid.cell_m**2, 3), round(grid.covered_m2(params.min_passes), 3),
        area_part, gaps,
    )  # fmt: skip
    info = CoverageInfo(
        frame.epsg, grid.cell_m, grid.west_m, grid.north_m, max(cols, 1), max(rows, 1), version
    )
    return CoverageMessage(summary, png_bytes(coverage_image(grid.passes, params.min_passes)), info)


def _area_message(area: dict[str, Any]) -> dict[str, Any]:
    """The summary's ``area`` from report.json's ``coverage.area``."""
    return {
        "area_m2": area["area_m2"],
        "covered_m2": area["covered_m2"],
        "fraction": area["covered_fraction"],
        "gaps": area["gaps"],
        "gaps_m2": area["gaps_m2"],
        "min_gap_m2": area["min_gap_m2"],
    }


def _summary(
    survey: str, final: bool, version: int, epsg: int, cell_m: float, min_passes: int,
    seen_m2: float, covered_m2: float, area: dict[str, Any] | None, gaps: dict[str, Any],
) -> dict[str, Any]:  # fmt: skip
    """A coverage summary (``drivers.zenoh_io.parse_coverage_summary``'s keys)."""
    return {
        "survey": survey,
        "time": round(time.time(), 3),
        "final": final,
        "version": version,
        "epsg": epsg,
        "cell_m": cell_m,
        "min_passes": min_passes,
        "seen_m2": seen_m2,
        "covered_m2": covered_m2,
        "area": area,
        "gaps": gaps,
    }


def final_message(survey_dir: Path, survey: str, version: int) -> CoverageMessage | None:
    """The final publication of a mapped survey, from its result folder (report.json's
    coverage, gaps.geojson and coverage.png); None when the folder has no coverage."""
    try:
        report = json.loads((survey_dir / "report.json").read_text(encoding="utf-8"))
        cover = report["coverage"]
        png = (survey_dir / COVERAGE_PNG).read_bytes()
        raster = read_coverage_tif(survey_dir / COVERAGE_TIF)
        area = cover.get("area")
        gaps: dict[str, Any] = {"type": "FeatureCollection", "features": []}
        if area is not None:
            gaps = json.loads((survey_dir / GAPS_GEOJSON).read_text(encoding="utf-8"))
        rows, cols = raster.meets_bar.shape
        summary = _summary(
            survey, True, version, raster.epsg, raster.cell_m, cover["min_passes"],
            cover["seen_m2"], cover["covered_m2"], None if area is None else _area_message(area),
            gaps,
        )  # fmt: skip
        info = CoverageInfo(
            raster.epsg, raster.cell_m, raster.west_m, raster.north_m, cols, rows, version
        )
    except (OSError, ValueError, KeyError, TypeError, SeamapError) as exc:
        log.debug("no final coverage in %s: %s", survey_dir, exc)
        return None
    return CoverageMessage(summary, png, info)


class LiveCoverage:
    """A survey's coverage as the live map places its frames (the daemon's).

    The mapping thread gives each frame once, when its live pose first becomes final
    (``add``; later refinements of a frame do not move its cells: the live count is what
    the boat saw where it then thought it was); the event loop asks for a publication
    every few seconds (``message``, in a worker thread: the gaps take tens of
    milliseconds on a hectare). The cells lie on the UTM grid, in the local frame of the
    first live engine's; an engine started afresh (after a failure) may anchor its
    frame elsewhere in the zone, and its poses are moved onto the first frame (a frame in
    another UTM zone is not counted). The fan comes from the first ping (``set_fan``),
    as the survey-end pass takes it.
    """

    def __init__(
        self, mount: SonarMount, config: CoverageConfig, area: SurveyArea | None = None
    ) -> None:
        self.mount = mount
        self.params = coverage_params(config)
        self.min_gap_m2 = config.min_gap_m2
        self.area = area
        self.frames = 0
        """Frames counted."""
        self.other_zone = 0
        """Frames not counted: their engine's frame lay in another UTM zone."""
        self._lock = threading.Lock()
        self._fan: SonarFan | None = None
        self._frame: LocalFrame | None = None
        self._coverage: SeabedCoverage | None = None
        self._version = 0

    @property
    def fan(self) -> SonarFan | None:
        return self._fan

    def set_fan(self, fan: SonarFan) -> None:
        """The sonar's fan (the first one given stays)."""
        with self._lock:
            if self._fan is None:
                self._fan = fan

    def add(self, frame: LocalFrame, time_s: float, pose: npt.ArrayLike) -> None:
        """One frame (mapping thread): its time (s) and the vehicle's pose (x, y metres,
        grid heading radians) in ``frame``, its engine's local frame."""
        with self._lock:
            if self._fan is None:
                return
            if self._coverage is None:
                self._frame = frame
                self._coverage = SeabedCoverage(
                    self.mount,
                    self._fan,
                    self.params,
                    anchor_e=frame.anchor_e,
                    anchor_n=frame.anchor_n,
                )
            assert self._frame is not None
            xyh = np.array(pose, float)
            if frame is not self._frame:
                if frame.epsg != self._frame.epsg:
                    self.other_zone += 1
                    return
                xyh[0] += frame.anchor_e - self._frame.anchor_e
                xyh[1] += frame.anchor_n - self._frame.anchor_n
            self._coverage.add(time_s, xyh)
            self.frames += 1

    def message(self, survey: str) -> CoverageMessage | None:
        """The publication of what was seen so far (None before the first frame); each
        gets a newer version (ms UNIX time, forced to grow)."""
        with self._lock:
            if self._coverage is None or self._frame is None:
                return None
            grid = self._coverage.grid()
            frame = self._frame
            self._version = max(int(time.time() * 1000), self._version + 1)
            version = self._version
        return coverage_message(
            survey, grid, self.params, frame, self.area, self.min_gap_m2,
            final=False, version=version,
        )  # fmt: skip
