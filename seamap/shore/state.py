"""What the shore station holds of the boats it follows, and the files it keeps it in.

``ShoreState`` holds, per vehicle (``HeldVehicle``), whether its liveliness token is up,
every pose received (its track), its latest status and, per survey (``HeldSurvey``), its
tiles with their versions. Its ``take_*`` methods validate a payload as received and apply
it; one that cannot be used raises ``BadPayload`` and changes nothing held. A tile
replaces the one held only if its attachment's version is higher, so a late ``get`` reply
never undoes a newer live tile.

The writers (each atomic, so a reader never sees half a file):

- ``write_mosaic``: ``mosaic.tif`` and ``mosaic.png``, a survey's tiles assembled north-up
  on its UTM grid, 0 = no data (the result folder's format);
- ``write_track``: ``track.csv`` and ``track.geojson``, every pose received (poses carry
  no survey id, so the track is the vehicle's);
- ``write_status``: ``status.json``, the latest status, as received.
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

from mapping.mosaic import TileGrid, assemble
from seamap.results import write_geotiff, write_png
from seamap.zenoh_io import TileInfo, TileKeyParts, decode_tile

TRACK_HEADER = ("time", "lat", "lon", "east", "north", "heading_deg")


def id_problem(value: str) -> str | None:
    """Why ``value`` cannot be a vehicle or survey id (a key chunk and a folder name)."""
    if not value or value in (".", ".."):
        return "not an id"
    if any(c in value for c in "/*?#$") or any(c.isspace() for c in value):
        return "an id holds no '/', '*', '?', '#', '$' or spaces"
    return None


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
class HeldSurvey:
    tiles: dict[tuple[int, int], HeldTile] = field(default_factory=dict)
    """By (col, row)."""
    changed: bool = False
    """Tiles taken since the mosaic was last written."""
    too_big_told: bool = False

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
    track_changed: bool = False
    status: dict[str, Any] | None = None
    status_raw: bytes = b""
    status_changed: bool = False
    surveys: dict[str, HeldSurvey] = field(default_factory=dict)
    latest_survey: str | None = None
    """The survey of the latest tile taken."""


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

    def take_pose(self, vehicle: str, payload: bytes) -> None:
        """Append a pose (JSON with the ``TRACK_HEADER`` fields) to the vehicle's track."""
        try:
            raw = json.loads(payload)
            point = TrackPoint(*(float(raw[name]) for name in TRACK_HEADER))
        except (ValueError, KeyError, TypeError) as exc:
            raise BadPayload(f"not a pose ({type(exc).__name__}: {exc})") from None
        values = (point.time, point.lat, point.lon, point.east, point.north, point.heading_deg)
        if not all(math.isfinite(v) for v in values) or abs(point.lat) > 90 or abs(point.lon) > 180:
            raise BadPayload("pose not finite or out of range")
        held = self.vehicle(vehicle)
        held.track.append(point)
        held.track_changed = True

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


__all__ = [
    "TRACK_HEADER",
    "BadPayload",
    "HeldSurvey",
    "HeldTile",
    "HeldVehicle",
    "Mosaic",
    "ShoreState",
    "TrackPoint",
    "atomic_write",
    "id_problem",
    "write_mosaic",
    "write_status",
    "write_track",
]
