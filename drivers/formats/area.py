"""Survey areas from files: a polygon in WGS84 in, the area in its UTM frame out.

``read_area`` reads the file, puts the area in local metres in the frame of the UTM zone
it lies in (``mapping.geo.LocalFrame``, anchored near the mean of its outer vertices) and
checks it (``planning.area.validate_area``).

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
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.errors import SeamapError
from mapping.geo import LocalFrame
from planning.area import Area, PlanningError, Polygon, clean_ring, validate_area

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class SurveyArea:
    """An area read from a file: its local frame, the area in local metres and its
    polygons in WGS84 as read (each a list of rings, outer first, (n, 2) lat/lon)."""

    frame: LocalFrame
    area: Area
    polygons_latlon: tuple[tuple[FloatArray, ...], ...]


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
    geojson = path.suffix.lower() in (".geojson", ".json") or text.lstrip().startswith("{")
    return parse_area(text, str(path), geojson=geojson)


def parse_area(text: str, name: str, *, geojson: bool = True) -> SurveyArea:
    """The area in ``text`` (GeoJSON, or a lat,lon list when not ``geojson``) in its UTM
    frame; SeamapError (one line, starting with ``name``) if it is not a usable area."""
    try:
        polygons = _geojson_polygons(text) if geojson else _latlon_polygon(text)
        return _to_local(polygons)
    except (SeamapError, PlanningError) as exc:
        raise SeamapError(f"{name}: {exc}") from None


def area_geojson(survey: SurveyArea) -> dict[str, Any]:
    """The area as a GeoJSON MultiPolygon geometry (WGS84 [lon, lat], holes kept), as read:
    what ``parse_area`` reads back to the same area."""
    return {
        "type": "MultiPolygon",
        "coordinates": [
            [[[float(lon), float(lat)] for lat, lon in _closed(ring)] for ring in rings]
            for rings in survey.polygons_latlon
        ],
    }


def _closed(ring: FloatArray) -> FloatArray:
    if len(ring) and not np.array_equal(ring[0], ring[-1]):
        return np.vstack([ring, ring[:1]])
    return ring


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
        raise SeamapError(located_message(exc, frame)) from None
    latlon = tuple(tuple(clean_ring(r) for r in polygon) for polygon in polygons)
    return SurveyArea(frame, area, latlon)


def located_message(exc: PlanningError, frame: LocalFrame) -> str:
    """The error's message, with where it is as lat,lon when it says where."""
    if exc.where is None:
        return str(exc)
    lat, lon = frame.to_latlon(exc.where[0], exc.where[1])
    return f"{exc} near {float(lat):.7f},{float(lon):.7f}"


def area_in(survey: SurveyArea, frame: LocalFrame) -> Area:
    """The area in another local frame (a survey's, anchored at its first fix, perhaps in
    the next UTM zone): its WGS84 vertices projected afresh, holes kept."""
    polygons = []
    for rings in survey.polygons_latlon:
        metric = []
        for ring in rings:
            x, y = frame.to_local(ring[:, 0], ring[:, 1])
            metric.append(np.column_stack([x, y]))
        polygons.append(Polygon(metric[0], tuple(metric[1:])))
    return Area(tuple(polygons))
