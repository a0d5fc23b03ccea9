"""The contract's result folder: mosaic.tif, mosaic.png, trajectory.csv, report.json,
coverage.tif, coverage.png and, when the survey's area is known, gaps.geojson.

Written by replay, by the daemon at survey end and by the demo. Files are written to a
temporary name and renamed, so a reader never sees half a file. ``read_coverage_tif``
reads coverage.tif back (``seamap survey replan``).
"""

from __future__ import annotations

import csv
import json
import math
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np
import numpy.typing as npt
import rasterio
import rasterio.shutil
import shapely
from rasterio.errors import RasterioError
from rasterio.transform import from_origin
from shapely.geometry.polygon import orient

from drivers.errors import SeamapError
from mapping.coverage import CoverageGrid
from mapping.geo import LocalFrame


@contextmanager
def _atomic(path: Path, mode: str = "w") -> Iterator[IO[Any]]:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, mode, newline="" if "b" not in mode else None) as stream:
        yield stream
        stream.flush()
        os.fsync(stream.fileno())
    os.replace(tmp, path)


def write_error(path: Path, what: str, exc: Exception) -> OSError:
    """An OSError in one line naming the file and GDAL's reason, with the errno of the
    error below when it had one (a full disk stays ENOSPC): the writers' callers handle
    write failures as OSError, as they do a failed open()."""
    reason = (str(exc).splitlines() or [type(exc).__name__])[0]
    message = f"{path}: cannot write the {what} ({reason})"
    if isinstance(exc, OSError) and exc.errno is not None:
        return OSError(exc.errno, message)
    return OSError(message)


COG_BLOCK_PX = 512
"""Tile side of mosaic.tif and coverage.tif (GDAL's COG default). Overviews halve the
image until one fits in a tile. On a 5000 x 5000 px mosaic 256 px tiles were as large
and as fast to write; 512 px asks a remote reader for a quarter as many ranges."""


def _write_cog(
    path: Path,
    bands: npt.NDArray[Any],
    profile: dict[str, Any],
    resampling: str,
    descriptions: tuple[str, ...] = (),
    tags: dict[str, str] | None = None,
) -> None:
    """``bands`` (count, rows, cols) as a Cloud-Optimized GeoTIFF (GDAL's COG driver:
    tiled, the overviews' IFDs and tiles laid out so that a reader fetching byte ranges
    gets the header first and the coarsest level before the finer ones), deflate
    compressed, written to a temporary name and renamed.

    The COG driver only copies a dataset, so the bands go first into an uncompressed
    tiled GTiff beside the output (on disk, not in memory: a mosaic of a long survey
    already fills a good part of the boat computer's memory once). ``resampling`` is
    GDAL's name of the overviews' resampling; it honours the nodata value of
    ``profile``: averaging leaves no-data pixels out. A write that fails is an OSError
    naming the file (``write_error``)."""
    source = path.with_name(f".{path.name}.src.tmp")
    tmp = path.with_name(f".{path.name}.tmp")
    count, rows, cols = bands.shape
    try:
        with rasterio.open(
            source, "w", driver="GTiff", count=count, height=rows, width=cols,
            tiled=True, blockxsize=COG_BLOCK_PX, blockysize=COG_BLOCK_PX, **profile,
        ) as staged:  # fmt: skip
            staged.write(bands)
            for index, name in enumerate(descriptions, start=1):
                staged.set_band_description(index, name)
            if tags:
                staged.update_tags(**tags)
        with rasterio.open(source) as staged:
            # Deflate as before; no predictor: on sonar speckle the horizontal
            # differencing made the file 4 % larger (5000 x 5000 px test mosaic).
            rasterio.shutil.copy(
                staged, tmp, driver="COG", compress="DEFLATE", predictor="NO",
                blocksize=COG_BLOCK_PX, overviews="AUTO", resampling=resampling,
            )  # fmt: skip
        os.replace(tmp, path)
    except (RasterioError, OSError) as exc:
        raise write_error(path, "GeoTIFF", exc) from exc
    finally:
        source.unlink(missing_ok=True)
        tmp.unlink(missing_ok=True)


def write_geotiff(
    path: Path, image: npt.NDArray[np.uint8], west: float, north: float, res_m: float, epsg: int
) -> None:
    """Single-band uint8 north-up Cloud-Optimized GeoTIFF, square pixels, 0 = no data,
    with overviews down to one tile: each overview pixel is the mean of the four below
    it that hold data (no data where none does)."""
    profile = {
        "dtype": "uint8",
        "crs": f"EPSG:{epsg}",
        "transform": from_origin(west, north, res_m, res_m),
        "nodata": 0,
    }
    # Intensities average; the nodata value keeps the mosaic's edges from darkening.
    _write_cog(path, image[np.newaxis], profile, resampling="AVERAGE")


COVERAGE_BANDS = ("passes", "hits", "meets_bar")
"""coverage.tif's bands, in order."""


def write_coverage_tif(path: Path, grid: CoverageGrid, epsg: int, min_passes: int) -> None:
    """Three-band uint16 north-up Cloud-Optimized GeoTIFF on the grid's UTM cells: passes,
    hits (both saturating at 65535) and 1 where passes >= ``min_passes`` else 0. GeoTIFF
    bands share one type, so the bar is uint16 too. No nodata: every cell holds a count,
    0 = not seen. The bar, the cell and the bands' names are in the file's tags. Its
    overviews show one cell of each block of four (nearest)."""
    rows, cols = grid.passes.shape
    profile: dict[str, Any] = {
        "dtype": "uint16",
        "crs": f"EPSG:{epsg}",
        "transform": from_origin(grid.west_m, grid.north_m, grid.cell_m, grid.cell_m),
    }
    bands = np.zeros((len(COVERAGE_BANDS), max(rows, 1), max(cols, 1)), np.uint16)
    bands[0, :rows, :cols] = grid.passes
    bands[1, :rows, :cols] = grid.hits
    bands[2, :rows, :cols] = grid.meets(min_passes)
    # Counts and a flag: an average would show 1.5 passes or half a bar met, values no
    # cell holds (rounded, a bar met where it is not); nearest keeps a real cell's value.
    _write_cog(
        path, bands, profile, resampling="NEAREST", descriptions=COVERAGE_BANDS,
        tags={"min_passes": str(min_passes), "cell_m": repr(grid.cell_m)},
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class CoverageRaster:
    """coverage.tif as read back: ``meets_bar`` per cell (north-up, row 0 northernmost),
    the UTM easting and northing of its top-left corner, the cell side (m), the EPSG code
    and the bar (``min_passes``, None when the file does not say)."""

    meets_bar: npt.NDArray[np.bool_]
    west_m: float
    north_m: float
    cell_m: float
    epsg: int
    min_passes: int | None


def read_coverage_tif(path: Path) -> CoverageRaster:
    """Read a coverage.tif that ``write_coverage_tif`` wrote; SeamapError (one line, naming
    the file) unless it is one: a GeoTIFF of the three bands by name, a UTM CRS, north-up
    square cells."""
    path = Path(path)
    if not path.exists():
        raise SeamapError(f"{path}: no such file")
    if path.is_dir():
        raise SeamapError(f"{path}: is a directory, not a coverage raster")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # NotGeoreferencedWarning: the checks below say it
        try:
            with rasterio.open(path) as dataset:
                bands = tuple(dataset.descriptions)
                crs = dataset.crs
                transform = dataset.transform
                tags = dataset.tags()
                meets = dataset.read(3) > 0 if bands == COVERAGE_BANDS else None
        except RasterioError as exc:
            reason = (str(exc).splitlines() or ["unreadable"])[0]
            raise SeamapError(f"{path}: not a GeoTIFF ({reason})") from None
    if meets is None:
        names = ", ".join(str(b) for b in bands)
        raise SeamapError(
            f"{path}: not a seamap coverage raster (bands {names}; expected "
            f"{', '.join(COVERAGE_BANDS)})"
        )
    epsg = crs.to_epsg() if crs is not None else None
    if epsg is None or not (32601 <= epsg <= 32660 or 32701 <= epsg <= 32760):
        raise SeamapError(
            f"{path}: not a seamap coverage raster (its CRS {crs or 'is missing'}"
            f"{'' if crs is None else ' is not UTM'})"
        )
    cell = float(transform.a)
    if not (cell > 0 and transform.b == 0 and transform.d == 0 and transform.e == -cell):
        raise SeamapError(
            f"{path}: not a seamap coverage raster (its cells are not north-up squares)"
        )
    bar = tags.get("min_passes", "")
    return CoverageRaster(
        meets_bar=meets,
        west_m=float(transform.c),
        north_m=float(transform.f),
        cell_m=cell,
        epsg=int(epsg),
        min_passes=int(bar) if bar.isdigit() else None,
    )


COVERAGE_COLOURS = {
    "below_bar": (43, 142, 242),  # BGR: orange, seen by fewer passes than the bar
    "at_bar": (106, 217, 166),  # light green: exactly the bar's passes
    "above_bar": (65, 150, 26),  # green: more passes than the bar
}


def coverage_image(passes: npt.NDArray[np.uint16], min_passes: int) -> npt.NDArray[np.uint8]:
    """The coverage for eyes (BGRA, OpenCV's order), one pixel a cell: transparent where no
    pass saw the cell, orange below the bar, light green at it, green above it."""
    image = np.zeros((*passes.shape, 4), np.uint8)
    seen = passes > 0
    for name, where in (
        ("below_bar", seen & (passes < min_passes)),
        ("at_bar", passes == min_passes),
        ("above_bar", passes > min_passes),
    ):
        image[where] = (*COVERAGE_COLOURS[name], 255)
    return image if image.size else np.zeros((1, 1, 4), np.uint8)


def write_coverage_png(path: Path, grid: CoverageGrid, min_passes: int) -> None:
    """``coverage_image`` of the raster as a PNG (RGBA), north-up."""
    write_png(path, coverage_image(grid.passes, min_passes))


def gaps_geojson(gaps: tuple[shapely.Polygon, ...], frame: LocalFrame) -> dict[str, Any]:
    """The gaps (local metres) as a GeoJSON FeatureCollection of WGS84 polygons (RFC 7946:
    [longitude, latitude], outer rings counterclockwise, holes clockwise), each with its
    ``id`` (1 the largest) and ``area_m2``."""
    features = []
    for number, gap in enumerate(gaps, start=1):
        # UTM keeps a ring's turning sense: oriented in metres, oriented in degrees.
        oriented = orient(gap, 1.0)
        coordinates = []
        for ring in (oriented.exterior, *oriented.interiors):
            xy = np.asarray(ring.coords)
            lat, lon = frame.to_latlon(xy[:, 0], xy[:, 1])
            # 1e-8 degrees is a millimetre: far finer than the cells.
            coordinates.append(np.round(np.column_stack([lon, lat]), 8).tolist())
        features.append(
            {
                "type": "Feature",
                "id": number,
                "properties": {"id": number, "area_m2": round(float(gap.area), 3)},
                "geometry": {"type": "Polygon", "coordinates": coordinates},
            }
        )
    return {"type": "FeatureCollection", "features": features}


def write_gaps(path: Path, gaps: tuple[shapely.Polygon, ...], frame: LocalFrame) -> None:
    """``gaps_geojson`` as a file."""
    with _atomic(path) as stream:
        json.dump(gaps_geojson(gaps, frame), stream)
        stream.write("\n")


def png_bytes(image: npt.NDArray[np.uint8]) -> bytes:
    """An image (grey, BGR or BGRA, OpenCV's order) as PNG bytes."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(data.tobytes())


def write_png(path: Path, image: npt.NDArray[np.uint8]) -> None:
    try:
        data = png_bytes(image)
    except ValueError:
        raise OSError(f"{path}: PNG encoding failed") from None
    with _atomic(path, "wb") as stream:
        stream.write(data)


TRAJECTORY_COLUMNS = ("time", "lat", "lon", "east", "north", "heading_deg")
"""trajectory.csv's columns (and survey.gpkg's ``poses`` fields), in order."""


def trajectory_table(
    frame: LocalFrame, times: npt.NDArray[np.float64], poses: npt.NDArray[np.float64]
) -> dict[str, npt.NDArray[np.float64]]:
    """``TRAJECTORY_COLUMNS`` of the mapped frames (finite pose): the vehicle reference
    point's optimised pose, lat/lon (degrees, WGS84), east/north in the mosaic's UTM CRS
    (metres), heading in degrees clockwise from true north, 0..360; ``poses`` are local
    (x, y, grid heading in radians) of ``frame``."""
    ok = np.all(np.isfinite(poses), axis=1)
    east, north = frame.to_utm(poses[ok, 0], poses[ok, 1])
    lat, lon = frame.to_latlon(poses[ok, 0], poses[ok, 1])
    heading = np.array(
        [
            math.degrees(frame.grid_to_true(float(psi), float(la), float(lo))) % 360.0
            for psi, la, lo in zip(poses[ok, 2], lat, lon, strict=True)
        ],
        float,
    )
    columns = (np.asarray(times, float)[ok], lat, lon, east, north, heading)
    return {name: np.asarray(c, float) for name, c in zip(TRAJECTORY_COLUMNS, columns, strict=True)}


def write_trajectory(
    path: Path,
    frame: LocalFrame,
    times: npt.NDArray[np.float64],
    poses: npt.NDArray[np.float64],
) -> int:
    """One row per mapped frame (finite pose): the vehicle reference point's optimised pose,
    east/north in the mosaic's CRS, heading from true north. Returns the row count."""
    table = trajectory_table(frame, times, poses)
    with _atomic(path) as stream:
        writer = csv.writer(stream)
        writer.writerow(TRAJECTORY_COLUMNS)
        for t, la, lo, e, n, heading in zip(*table.values(), strict=True):
            writer.writerow(
                [f"{t:.6f}", f"{la:.9f}", f"{lo:.9f}", f"{e:.4f}", f"{n:.4f}", f"{heading:.4f}"]
            )
    return int(table["time"].size)


def write_report(path: Path, report: dict[str, Any]) -> None:
    with _atomic(path) as stream:
        json.dump(report, stream, indent=2, sort_keys=True, default=_json_default)
        stream.write("\n")


def _json_default(value: object) -> object:
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
