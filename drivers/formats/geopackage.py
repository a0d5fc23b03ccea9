"""survey.gpkg: the survey's vectors in one GeoPackage (OGC 12-128r18) that QGIS opens in
one go, every layer in the mosaic's UTM CRS.

Layers: ``track`` (the optimised track, one LineString), ``poses`` (a point per mapped
frame with trajectory.csv's columns), ``area`` (the survey's area, one row a polygon),
``gaps`` (what the survey missed of it, as gaps.geojson numbers them) and ``coverage`` (a
table without geometry: report.json's coverage summary in one row). ``area`` and ``gaps``
are there only when the survey's area is known. Written through pyogrio (GDAL's OGR, raw
arrays, no geopandas) to a temporary name and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyogrio.raw
import shapely
from pyogrio.errors import DataLayerError, DataSourceError, FeatureError, FieldError
from shapely.geometry.polygon import orient

from drivers.formats.results import TRAJECTORY_COLUMNS, trajectory_table, write_error
from mapping.geo import LocalFrame

SURVEY_GPKG = "survey.gpkg"
AREA_DESCRIPTION = "The survey's area, one row a polygon (holes are not to be surveyed)"
GAPS_DESCRIPTION = "What the survey missed of its area (gaps.geojson): id 1 the largest, area_m2"

COVERAGE_FIELDS: dict[str, type] = {
    "cell_m": float,
    "min_passes": int,
    "cells_seen": int,
    "seen_m2": float,
    "covered_m2": float,
    "max_passes": int,
    "area_m2": float,
    "area_covered_m2": float,
    "covered_fraction": float,
    "gaps": int,
    "gaps_m2": float,
    "min_gap_m2": float,
}
"""The ``coverage`` layer's fields: report.json's ``coverage`` (``area_*`` and what follows
from its ``area`` object, NULL without an area)."""


@dataclass(frozen=True)
class _Layer:
    name: str
    description: str
    geometry_type: str | None
    geometry: npt.NDArray[np.object_] | None
    fields: dict[str, npt.NDArray[Any]]
    masks: dict[str, npt.NDArray[np.bool_]]


def coverage_row(coverage: Mapping[str, Any]) -> dict[str, float | int | None]:
    """report.json's ``coverage`` object as the ``coverage`` layer's one row (None: NULL)."""
    area = coverage.get("area") or {}
    row: dict[str, float | int | None] = {}
    for name in COVERAGE_FIELDS:
        if name == "area_covered_m2":
            value = area.get("covered_m2")
        elif name in ("area_m2", "covered_fraction", "gaps", "gaps_m2", "min_gap_m2"):
            value = area.get(name)
        else:
            value = coverage.get(name)
        row[name] = None if value is None else COVERAGE_FIELDS[name](value)
    return row


def write_survey_gpkg(
    path: Path,
    frame: LocalFrame,
    times: npt.NDArray[np.float64],
    poses: npt.NDArray[np.float64],
    coverage: Mapping[str, Any],
    area: Sequence[shapely.Polygon] | None = None,
    gaps: Sequence[shapely.Polygon] | None = None,
) -> list[str]:
    """Write survey.gpkg (see the module docstring): ``poses`` are local (x, y, grid
    heading in radians) of ``frame`` as ``write_trajectory`` takes them, ``area`` and
    ``gaps`` polygons in local metres of ``frame``, ``coverage`` report.json's coverage
    object. Returns the layers written; a write that fails is an OSError naming the file
    (``drivers.formats.results.write_error``)."""
    epsg = frame.epsg
    table = trajectory_table(frame, times, poses)
    layers = [_track(table), _poses(table)]
    if area is not None:
        layers.append(_polygons("area", AREA_DESCRIPTION, "part", area, frame))
    if gaps is not None:
        layers.append(_polygons("gaps", GAPS_DESCRIPTION, "id", gaps, frame))
    layers.append(_coverage(coverage))
    # GDAL's GPKG driver wants the .gpkg extension, hence the temporary name's order.
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        tmp.unlink(missing_ok=True)  # a temporary left by a write cut short
        for layer in layers:
            names = list(layer.fields)
            pyogrio.raw.write(
                tmp,
                layer.geometry,
                [layer.fields[n] for n in names],
                names,
                field_mask=[layer.masks.get(n) for n in names] if layer.masks else None,
                layer=layer.name,
                driver="GPKG",
                geometry_type=layer.geometry_type,
                crs=f"EPSG:{epsg}" if layer.geometry_type else None,
                layer_options={"DESCRIPTION": layer.description},
            )
        with open(tmp, "rb") as stream:
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except (DataSourceError, DataLayerError, FeatureError, FieldError, OSError) as exc:
        raise write_error(path, "GeoPackage", exc) from exc
    finally:
        tmp.unlink(missing_ok=True)
    return [layer.name for layer in layers]


def _wkb(
    geometries: Sequence[shapely.Geometry] | npt.NDArray[np.object_],
) -> npt.NDArray[np.object_]:
    geometry = np.empty(len(geometries), object)
    geometry[:] = list(geometries)
    return np.asarray(shapely.to_wkb(geometry), object)


def _track(table: dict[str, npt.NDArray[np.float64]]) -> _Layer:
    east, north, t = table["east"], table["north"], table["time"]
    line = [shapely.LineString(np.column_stack([east, north]))] if east.size >= 2 else []
    steps = np.hypot(np.diff(east), np.diff(north))
    fields: dict[str, npt.NDArray[Any]] = {
        "poses": np.array([east.size] * len(line), np.int64),
        "start_time": t[:1] if line else np.empty(0),
        "end_time": t[-1:] if line else np.empty(0),
        "length_m": np.array([steps.sum()] * len(line), float),
    }
    return _Layer(
        "track",
        "The optimised track of the vehicle reference point (GPS antenna), "
        "one vertex per mapped frame; times UNIX seconds",
        "LineString",
        _wkb(line),
        fields,
        {},
    )


def _poses(table: dict[str, npt.NDArray[np.float64]]) -> _Layer:
    points = np.asarray(shapely.points(np.column_stack([table["east"], table["north"]])), object)
    return _Layer(
        "poses",
        "The optimised pose at each mapped frame, trajectory.csv's columns: time "
        "(UNIX s), lat/lon (WGS84), east/north (this CRS), heading_deg (from true north)",
        "Point",
        _wkb(points),
        {name: table[name] for name in TRAJECTORY_COLUMNS},
        {},
    )


def _utm(polygon: shapely.Polygon, frame: LocalFrame) -> shapely.Polygon:
    """A polygon of local metres in the frame's UTM CRS (a shift: the turning sense stays)."""
    return shapely.transform(polygon, lambda xy: xy + np.array([frame.anchor_e, frame.anchor_n]))


def _polygons(
    name: str, description: str, key: str, polygons: Sequence[shapely.Polygon], frame: LocalFrame
) -> _Layer:
    """A polygon layer in the frame's UTM CRS, numbered from 1 in ``key``, with each
    polygon's area (m2)."""
    utm = [orient(_utm(polygon, frame), 1.0) for polygon in polygons]
    return _Layer(
        name,
        description,
        "Polygon",
        _wkb(utm),
        {
            key: np.arange(1, len(utm) + 1, dtype=np.int64),
            # Measured in local metres: UTM's seven-digit northings cost the area digits.
            "area_m2": np.array([round(float(p.area), 3) for p in polygons], float),
        },
        {},
    )


def _coverage(coverage: Mapping[str, Any]) -> _Layer:
    row = coverage_row(coverage)
    fields: dict[str, npt.NDArray[Any]] = {}
    masks: dict[str, npt.NDArray[np.bool_]] = {}
    for name, kind in COVERAGE_FIELDS.items():
        value = row[name]
        fields[name] = np.array([0 if value is None else value], np.int64 if kind is int else float)
        masks[name] = np.array([value is None])
    return _Layer(
        "coverage",
        "The survey's coverage as report.json gives it, one row: cells seen and meeting "
        "the bar (min_passes), and with the area its covered fraction and gaps",
        None,
        None,
        fields,
        masks,
    )
