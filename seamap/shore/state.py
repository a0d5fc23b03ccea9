"""What the shore station holds of the boats it follows, and the files it keeps it in.

``ShoreState`` holds, per vehicle (``HeldVehicle``), whether its liveliness token is up,
every pose received (its track), its latest status and, per survey (``HeldSurvey``), its
tiles with their versions and its latest coverage (``HeldCoverage``: the summary and the
raster). Its ``take_*`` methods validate a payload as received and apply it; one that
cannot be used raises ``BadPayload`` and changes nothing held. A tile, a coverage summary
or a coverage raster replaces the one held only if its version is higher, so a late
``get`` reply never undoes a newer live one.

The writers (each atomic, so a reader never sees half a file):

- ``write_mosaic``: ``mosaic.tif`` and ``mosaic.png``, a survey's tiles assembled north-up
  on its UTM grid, 0 = no data (the result folder's format);
- ``write_track``: ``track.csv`` and ``track.geojson``, every pose received (poses carry
  no survey id, so the track is the vehicle's);
- ``write_status``: ``status.json``, the latest status, as received;
- ``write_coverage_summary``: ``coverage.json`` (the summary without its gaps) and, when
  the survey's area is known, ``gaps.geojson`` (the summary's gaps, WGS84);
- ``write_coverage_raster``: ``coverage.png``, the raster as received, and its world file
  ``coverage.pgw`` (the raster's UTM placement, which the PNG cannot carry).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image

from drivers.formats.results import write_geotiff, write_png
from drivers.zenoh_io import (
    CoverageInfo,
    CoverageKeyParts,
    TileInfo,
    TileKeyParts,
    decode_tile,
    id_problem,
    json_bytes,
    parse_coverage_summary,
)
from mapping.mosaic import TileGrid, assemble

TRACK_HEADER = ("time", "lat", "lon", "east", "north", "heading_deg")


class BadPayload(Exception):
    """A payload that cannot be used (bad PNG, attachment, JSON, size, id); says why."""


@dataclass(frozen=True, slots=True)
class TrackPoint:
    """One pose as received: UNIX s, WGS84 degrees, UTM metres, degrees from true north."""

    time: float
    lat: float
    lon: float
    east: float
    north: float
    heading_deg: float


MAX_REFINED = 5000
"""Refined poses taken from one pose message at most."""


@dataclass(frozen=True, slots=True)
class TakenPose:
    """What a pose message changed: the pose (the boat's newest) and the track's points it
    moved (refinements of earlier frames, by their time)."""

    point: TrackPoint
    refined: tuple[TrackPoint, ...] = ()


@dataclass(frozen=True, slots=True)
class HeldTile:
    info: TileInfo
    values: npt.NDArray[np.uint8]
    """size_px x size_px, north-up, 0 = no data."""


@dataclass(frozen=True)
class Mosaic:
    """A survey's tiles as one north-up image; (west, north) is its top-left corner (UTM m)."""

    image: npt.NDArray[np.uint8]
    west: float
    north: float
    res_m: float
    epsg: int


@dataclass
class HeldCoverage:
    """A survey's latest coverage as published by its boat, each part at its newest
    version: the summary (``parse_coverage_summary``; areas in m², gaps as WGS84 GeoJSON)
    and the raster (PNG as received, one pixel a cell, north-up, placed by ``raster_info``
    on the survey's UTM grid)."""

    summary: dict[str, Any] | None = None
    summary_changed: bool = False
    """Taken since ``coverage.json`` and ``gaps.geojson`` were last written."""
    raster: bytes = b""
    raster_info: CoverageInfo | None = None
    raster_changed: bool = False
    """Taken since ``coverage.png`` was last written."""


@dataclass
class HeldSurvey:
    tiles: dict[tuple[int, int], HeldTile] = field(default_factory=dict)
    """By (col, row)."""
    changed: bool = False
    """Tiles taken since the mosaic was last written."""
    too_big_told: bool = False
    coverage: HeldCoverage = field(default_factory=HeldCoverage)

    def mosaic_px(self) -> int:
        """Pixels of the mosaic (0 without tiles), before assembling it: like the mosaic,
        it spans the tiles that hold data (all of them when none does)."""
        if not self.tiles:
            return 0
        keys = [key for key, tile in self.tiles.items() if tile.values.any()] or list(self.tiles)
        cols = [key[0] for key in keys]
        rows = [key[1] for key in keys]
        size = next(iter(self.tiles.values())).info.size_px
        return (max(cols) - min(cols) + 1) * (max(rows) - min(rows) + 1) * size * size

    def mosaic(self) -> Mosaic | None:
        """The tiles as one image spanning those with data (``mapping.mosaic.assemble``;
        an empty tile is the boat saying a live tile holds nothing any more); None
        without tiles."""
        if not self.tiles:
            return None
        info = next(iter(self.tiles.values())).info
        grid = TileGrid(res_m=info.res_m, tile_px=info.size_px)
        image, (west, north) = assemble(grid, {key: t.values for key, t in self.tiles.items()})
        return Mosaic(image, west, north, info.res_m, info.epsg)


@dataclass
class HeldVehicle:
    alive: bool | None = None
    """Whether its liveliness token is up (None: never seen)."""
    track: list[TrackPoint] = field(default_factory=list)
    track_index: dict[float, int] = field(default_factory=dict)
    """By pose time (a frame's stamp, which its refinements keep): its place in ``track``."""
    track_changed: bool = False
    status: dict[str, Any] | None = None
    status_raw: bytes = b""
    status_changed: bool = False
    surveys: dict[str, HeldSurvey] = field(default_factory=dict)
    latest_survey: str | None = None
    """The survey of the latest tile taken (before any tile: of the first coverage)."""


class ShoreState:
    """Every vehicle's liveliness, track, status and tiles, by vehicle id. A vehicle is
    held from its first liveliness change or usable payload on."""

    def __init__(self) -> None:
        self.vehicles: dict[str, HeldVehicle] = {}

    def vehicle(self, vehicle: str) -> HeldVehicle:
        """The vehicle held, held from now on if it was not."""
        return self.vehicles.setdefault(vehicle, HeldVehicle())

    # --- taking what arrives ------------------------------------------------------------------

    def take_liveliness(self, vehicle: str, alive: bool) -> None:
        self.vehicle(vehicle).alive = alive

    def take_pose(self, vehicle: str, payload: bytes) -> TakenPose:
        """Take a pose (JSON with the ``TRACK_HEADER`` fields): appended to the vehicle's
        track, or in place of the point of the same time (the boat sent that frame's pose
        again). Its optional ``refined`` list (rows of ``TRACK_HEADER`` values: frames the
        boat's live map placed anew since its last pose) moves the track's points of those
        times; rows for times not held, or unusable, are left out."""
        try:
            raw = json.loads(payload)
            point = _track_point([raw[name] for name in TRACK_HEADER])
        except (ValueError, KeyError, TypeError) as exc:
            raise BadPayload(f"not a pose ({type(exc).__name__}: {exc})") from None
        held = self.vehicle(vehicle)
        at = held.track_index.get(point.time)
        if at is None:
            held.track_index[point.time] = len(held.track)
            held.track.append(point)
        else:
            held.track[at] = point
        refined = []
        rows = raw.get("refined") if isinstance(raw, dict) else None
        for row in rows[:MAX_REFINED] if isinstance(rows, list) else []:
            try:
                moved = _track_point(row)
            except (ValueError, TypeError):
                continue
            at = held.track_index.get(moved.time)
            if at is not None:
                held.track[at] = moved
                refined.append(moved)
        held.track_changed = True
        return TakenPose(point, tuple(refined))

    def take_status(self, vehicle: str, payload: bytes) -> None:
        """Hold a status (a JSON object) in place of the vehicle's last one."""
        try:
            status = json.loads(payload)
        except ValueError as exc:
            raise BadPayload(f"status is not JSON ({exc})") from None
        if not isinstance(status, dict):
            raise BadPayload("status is not a JSON object")
        held = self.vehicle(vehicle)
        held.status, held.status_raw, held.status_changed = status, payload, True

    def take_tile(self, where: TileKeyParts, payload: bytes, attachment: bytes | None) -> bool:
        """Hold a tile (PNG, with its ``TileInfo`` as attachment) published at ``where``;
        True when taken, False when not newer than the one held (dropped)."""
        if id_problem(where.vehicle) or id_problem(where.survey):
            raise BadPayload("vehicle or survey id unusable as a folder name")
        if attachment is None:
            raise BadPayload("tile without attachment")
        try:
            info = TileInfo.from_json(attachment)
        except ValueError as exc:
            raise BadPayload(str(exc)) from None
        key = (where.col, where.row)
        if info.key() != key:
            raise BadPayload(f"attachment places the tile at {info.key()}, not {key}")
        vehicle = self.vehicles.get(where.vehicle)
        survey = vehicle.surveys.get(where.survey) if vehicle is not None else None
        held = survey.tiles.get(key) if survey is not None else None
        if held is not None and info.version <= held.info.version:
            return False
        if survey is not None and survey.tiles:
            grid = next(iter(survey.tiles.values())).info
            if (info.epsg, info.size_px) != (grid.epsg, grid.size_px) or not math.isclose(
                info.res_m, grid.res_m, rel_tol=1e-9
            ):
                raise BadPayload("tile grid (epsg, res_m, size_px) differs from the survey's")
        try:
            values = decode_tile(payload)
        except ValueError as exc:
            raise BadPayload(str(exc)) from None
        if values.shape != (info.size_px, info.size_px):
            raise BadPayload(f"tile is {values.shape}, attachment says {info.size_px} px")
        vehicle = self.vehicle(where.vehicle)
        survey = vehicle.surveys.setdefault(where.survey, HeldSurvey())
        survey.tiles[key] = HeldTile(info, values)
        survey.changed = True
        vehicle.latest_survey = where.survey
        return True

    def take_coverage_summary(self, where: CoverageKeyParts, payload: bytes) -> bool:
        """Hold a coverage summary (JSON, ``parse_coverage_summary``) published at ``where``;
        True when taken, False when its ``version`` is not newer than the one held."""
        survey = self._coverage_survey(where)
        try:
            summary = parse_coverage_summary(payload, where.survey)
        except ValueError as exc:
            raise BadPayload(str(exc)) from None
        try:  # the files and the page are strict JSON
            json_bytes(summary)
        except (ValueError, TypeError):
            raise BadPayload("coverage summary: holds NaN or Infinity") from None
        held = survey.coverage.summary if survey is not None else None
        if held is not None and summary["version"] <= held["version"]:
            return False
        coverage = self._hold_survey(where).coverage
        coverage.summary, coverage.summary_changed = summary, True
        return True

    def take_coverage_raster(
        self, where: CoverageKeyParts, payload: bytes, attachment: bytes | None
    ) -> bool:
        """Hold a coverage raster (PNG, with its ``CoverageInfo`` as attachment) published
        at ``where``; True when taken, False when not newer than the one held."""
        survey = self._coverage_survey(where)
        if attachment is None:
            raise BadPayload("coverage raster without attachment")
        try:
            info = CoverageInfo.from_json(attachment)
        except ValueError as exc:
            raise BadPayload(str(exc)) from None
        held = survey.coverage.raster_info if survey is not None else None
        if held is not None and info.version <= held.version:
            return False
        size = _png_size(payload)
        if size != (info.cols, info.rows):
            raise BadPayload(
                f"coverage raster is {size[0]} x {size[1]} px, attachment says "
                f"{info.cols} x {info.rows} cells"
            )
        coverage = self._hold_survey(where).coverage
        coverage.raster, coverage.raster_info, coverage.raster_changed = payload, info, True
        return True

    def _coverage_survey(self, where: CoverageKeyParts) -> HeldSurvey | None:
        """The survey held for a coverage key (None if not held yet); BadPayload for ids
        that cannot name folders."""
        if id_problem(where.vehicle) or id_problem(where.survey):
            raise BadPayload("vehicle or survey id unusable as a folder name")
        vehicle = self.vehicles.get(where.vehicle)
        return vehicle.surveys.get(where.survey) if vehicle is not None else None

    def _hold_survey(self, where: CoverageKeyParts) -> HeldSurvey:
        vehicle = self.vehicle(where.vehicle)
        if vehicle.latest_survey is None:
            vehicle.latest_survey = where.survey
        return vehicle.surveys.setdefault(where.survey, HeldSurvey())

    # --- reading what it holds ----------------------------------------------------------------

    def tiles(self, vehicle: str, survey: str) -> dict[tuple[int, int], HeldTile]:
        """The tiles held for one survey, by (col, row)."""
        held = self.vehicles.get(vehicle)
        if held is None or survey not in held.surveys:
            return {}
        return dict(held.surveys[survey].tiles)

    def mosaic(self, vehicle: str, survey: str) -> Mosaic | None:
        """The survey's tiles as one image spanning those with data (None without tiles)."""
        held = self.vehicles.get(vehicle)
        if held is None or survey not in held.surveys:
            return None
        return held.surveys[survey].mosaic()

    def coverage(self, vehicle: str, survey: str) -> HeldCoverage | None:
        """The survey's latest coverage (None when neither its summary nor raster came)."""
        held = self.vehicles.get(vehicle)
        coverage = held.surveys[survey].coverage if held and survey in held.surveys else None
        if coverage is None or (coverage.summary is None and coverage.raster_info is None):
            return None
        return coverage

    def track(self, vehicle: str) -> list[TrackPoint]:
        held = self.vehicles.get(vehicle)
        return list(held.track) if held is not None else []

    def status(self, vehicle: str) -> dict[str, Any] | None:
        held = self.vehicles.get(vehicle)
        return held.status if held is not None else None

    def alive(self, vehicle: str) -> bool | None:
        """Whether the vehicle's liveliness token is up (None: never seen)."""
        held = self.vehicles.get(vehicle)
        return held.alive if held is not None else None


def _track_point(values: Any) -> TrackPoint:
    """A ``TrackPoint`` from the ``TRACK_HEADER`` values; ValueError or TypeError when
    they are not six finite numbers with lat/lon in range."""
    if not isinstance(values, list | tuple) or len(values) != len(TRACK_HEADER):
        raise ValueError("not the six values of a pose")
    if any(isinstance(v, bool) or not isinstance(v, int | float) for v in values):
        raise TypeError("pose values must be numbers")
    point = TrackPoint(*(float(v) for v in values))
    if not all(math.isfinite(v) for v in values) or abs(point.lat) > 90 or abs(point.lon) > 180:
        raise ValueError("pose not finite or out of range")
    return point


def _png_size(payload: bytes) -> tuple[int, int]:
    """The (width, height) of a PNG, decoded whole so a truncated one is refused;
    BadPayload if it is not a PNG."""
    try:
        with Image.open(io.BytesIO(payload)) as image:
            if image.format != "PNG":
                raise ValueError(f"a {image.format} image")
            image.load()
            return image.size
    except Exception as exc:  # PIL raises many kinds (and DecompressionBombError)
        raise BadPayload(f"coverage raster is not a PNG ({exc})") from None


# --- the files ----------------------------------------------------------------------------


def atomic_write(path: Path, data: bytes) -> None:
    """Write to a temporary name and rename, so a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as stream:
        stream.write(data)
        stream.flush()
        os.fsync(stream.fileno())
    os.replace(tmp, path)


def write_mosaic(folder: Path, mosaic: Mosaic) -> None:
    """``folder/mosaic.tif`` (GeoTIFF on the survey's UTM grid) and ``folder/mosaic.png``."""
    folder.mkdir(parents=True, exist_ok=True)
    write_geotiff(
        folder / "mosaic.tif", mosaic.image, mosaic.west, mosaic.north,
        mosaic.res_m, mosaic.epsg,
    )  # fmt: skip
    write_png(folder / "mosaic.png", mosaic.image)


def write_track(folder: Path, track: list[TrackPoint]) -> None:
    """``folder/track.csv`` (the result folder's trajectory columns) and
    ``folder/track.geojson`` (one LineString, WGS84 lon/lat, RFC 7946; no feature until
    two poses). ``folder`` is named after the vehicle."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(TRACK_HEADER)
    for p in track:
        writer.writerow(
            [f"{p.time:.6f}", f"{p.lat:.9f}", f"{p.lon:.9f}", f"{p.east:.4f}",
             f"{p.north:.4f}", f"{p.heading_deg:.4f}"]
        )  # fmt: skip
    atomic_write(folder / "track.csv", text.getvalue().encode())
    features = []
    if len(track) >= 2:
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "LineString",
                    "coordinates": [[round(p.lon, 9), round(p.lat, 9)] for p in track],
                },
                "properties": {
                    "vehicle": folder.name,
                    "poses": len(track),
                    "start_time": track[0].time,
                    "end_time": track[-1].time,
                },
            }
        )
    collection = {"type": "FeatureCollection", "features": features}
    atomic_write(folder / "track.geojson", json.dumps(collection).encode())


def write_status(folder: Path, status_raw: bytes) -> None:
    """``folder/status.json``: the status as received."""
    atomic_write(folder / "status.json", status_raw)


def write_coverage_summary(folder: Path, summary: dict[str, Any]) -> None:
    """``folder/coverage.json``: the summary without its gaps; ``folder/gaps.geojson``:
    its gaps (a FeatureCollection of WGS84 [lon, lat] polygons, RFC 7946) when the
    survey's area is known. Without an area there are no gaps to tell (an empty
    collection would read as "nothing missed"): a ``gaps.geojson`` written before goes."""
    rest = {key: value for key, value in summary.items() if key != "gaps"}
    atomic_write(folder / "coverage.json", json.dumps(rest, indent=2).encode() + b"\n")
    gaps = folder / "gaps.geojson"
    if summary["area"] is not None:
        atomic_write(gaps, json.dumps(summary["gaps"]).encode() + b"\n")
    else:
        gaps.unlink(missing_ok=True)


def write_coverage_raster(folder: Path, png: bytes, info: CoverageInfo) -> None:
    """``folder/coverage.png``: the coverage raster as received (RGBA, one pixel a cell,
    north-up), and ``folder/coverage.pgw``, its world file (ESRI: cell width, two zero
    rotations, minus the cell height, the UTM easting and northing of the top-left cell's
    centre, metres; the CRS is ``coverage.json``'s ``epsg``). The world file goes first:
    a reader that sees the new PNG finds where it lies."""
    half = info.cell_m / 2
    lines = [info.cell_m, 0.0, 0.0, -info.cell_m, info.west + half, info.north - half]
    atomic_write(folder / "coverage.pgw", "".join(f"{v:.4f}\n" for v in lines).encode())
    atomic_write(folder / "coverage.png", png)


__all__ = [
    "TRACK_HEADER",
    "BadPayload",
    "HeldCoverage",
    "HeldSurvey",
    "HeldTile",
    "HeldVehicle",
    "Mosaic",
    "ShoreState",
    "TakenPose",
    "TrackPoint",
    "atomic_write",
    "write_coverage_raster",
    "write_coverage_summary",
    "write_mosaic",
    "write_status",
    "write_track",
]


@dataclass(frozen=True, slots=True)
class ShoreEvent:
    """One item the station applied, for its ``on_event`` listener.

    ``kind`` is "tile" (``survey``, ``col``, ``row``, ``info`` and the PNG as received in
    ``payload``), "pose" (``point``, ``refined`` and the pose JSON as received in
    ``payload``), "status"
    (``status``), "alive" (``alive``: the liveliness token appeared or went), "coverage"
    (``survey`` and its newer ``summary``) or "coverage_raster" (``survey``,
    ``coverage_info`` and the PNG as received in ``payload``)."""

    kind: str
    vehicle: str
    survey: str = ""
    col: int = 0
    row: int = 0
    info: TileInfo | None = None
    payload: bytes = b""
    point: TrackPoint | None = None
    refined: tuple[TrackPoint, ...] = ()
    """With a pose: the track's points it moved (earlier frames placed anew)."""
    status: dict[str, Any] | None = None
    alive: bool | None = None
    summary: dict[str, Any] | None = None
    coverage_info: CoverageInfo | None = None
