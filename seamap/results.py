"""The contract's result folder: mosaic.tif, mosaic.png, trajectory.csv, report.json.

Written by replay, by the daemon at survey end and by the demo. Files are written to a
temporary name and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np
import numpy.typing as npt
import rasterio
from rasterio.transform import from_origin

from mapping.geo import LocalFrame


@contextmanager
def _atomic(path: Path, mode: str = "w") -> Iterator[IO[Any]]:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, mode, newline="" if "b" not in mode else None) as stream:
        yield stream
        stream.flush()
        os.fsync(stream.fileno())
    os.replace(tmp, path)


def write_geotiff(
    path: Path, image: npt.NDArray[np.uint8], west: float, north: float, res_m: float, epsg: int
) -> None:
    """Single-band uint8 north-up GeoTIFF, square pixels, 0 = no data."""
    tmp = path.with_name(f".{path.name}.tmp")
    profile = {
        "driver": "GTiff",
        "height": image.shape[0],
        "width": image.shape[1],
        "count": 1,
        "dtype": "uint8",
        "crs": f"EPSG:{epsg}",
        "transform": from_origin(west, north, res_m, res_m),
        "nodata": 0,
        "compress": "deflate",
    }
    if image.shape[0] >= 256 and image.shape[1] >= 256:
        profile.update(tiled=True, blockxsize=256, blockysize=256)
    with rasterio.open(tmp, "w", **profile) as dataset:
        dataset.write(image, 1)
    os.replace(tmp, path)


def write_png(path: Path, image: npt.NDArray[np.uint8]) -> None:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    with _atomic(path, "wb") as stream:
        stream.write(data.tobytes())


def write_trajectory(
    path: Path,
    frame: LocalFrame,
    times: npt.NDArray[np.float64],
    poses: npt.NDArray[np.float64],
) -> int:
    """One row per mapped frame (finite pose): the vehicle reference point's optimised pose,
    east/north in the mosaic's CRS, heading from true north. Returns the row count."""
    ok = np.all(np.isfinite(poses), axis=1)
    east, north = frame.to_utm(poses[ok, 0], poses[ok, 1])
    lat, lon = frame.to_latlon(poses[ok, 0], poses[ok, 1])
    rows = 0
    with _atomic(path) as stream:
        writer = csv.writer(stream)
        writer.writerow(["time", "lat", "lon", "east", "north", "heading_deg"])
        for t, la, lo, e, n, psi in zip(
            times[ok], lat, lon, east, north, poses[ok, 2], strict=True
        ):
            heading = math.degrees(frame.grid_to_true(float(psi), float(la), float(lo))) % 360.0
            writer.writerow(
                [f"{t:.6f}", f"{la:.9f}", f"{lo:.9f}", f"{e:.4f}", f"{n:.4f}", f"{heading:.4f}"]
            )
            rows += 1
    return rows


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
