"""The daemon's live coverage (``LiveCoverage``): how well each seabed cell was seen as the
live map places its frames, and its zenoh publications (``CoverageMessage``:
``drivers.zenoh_io``'s coverage keys), the final one read back from the result folder
(``final_message``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon.config import CoverageConfig
from daemon.coverage import (
    COVERAGE_PNG,
    COVERAGE_TIF,
    GAPS_GEOJSON,
    _area_report,
    area_coverage,
    coverage_params,
)
from drivers.errors import SeamapError
from drivers.formats.area import SurveyArea
from drivers.formats.results import (
    coverage_image,
    gaps_geojson,
    png_bytes,
    read_coverage_tif,
)
from drivers.zenoh_io import CoverageInfo
from mapping.coverage import CoverageGrid, CoverageParams, SeabedCoverage, SonarFan
from mapping.frames import SonarMount
from mapping.geo import LocalFrame

log = logging.getLogger(__name__)


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
