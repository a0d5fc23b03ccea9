"""The mosaic on the contract's fixed UTM tile grid, and warping frames onto it.

Tile (col, row) covers easting [col*T, (col+1)*T) and northing [row*T, (row+1)*T),
T = tile_px * res_m, in the survey's UTM CRS. A tile image is north-up: its row 0 is the
northernmost line of pixels, column 0 the westernmost. Pixel (u, v) of the global grid
has its centre at easting (u + 0.5) * res_m, northing (v + 0.5) * res_m.

Frames are warped with one affine per tile (a rigid motion of the sonar's Cartesian
frame), intensity, score and fan mask together, so a tile gets exactly the pixels the
fan covers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from mapping.grid import SonarGrid

FloatImage = npt.NDArray[np.float32]
TileKey = tuple[int, int]


@dataclass(frozen=True, slots=True)
class SonarPose:
    """Pose of the sonar's level frame in UTM: easting, northing (m), yaw of the boresight
    (radians clockwise from grid north)."""

    east: float
    north: float
    yaw: float


@dataclass(frozen=True, slots=True)
class TileGrid:
    res_m: float = 0.02
    tile_px: int = 256

    @property
    def tile_m(self) -> float:
        return self.res_m * self.tile_px

    def tiles_covering(self, west: float, south: float, east: float, north: float) -> list[TileKey]:
        t = self.tile_m
        cols = range(math.floor(west / t), math.floor(east / t) + 1)
        rows = range(math.floor(south / t), math.floor(north / t) + 1)
        return [(c, r) for c in cols for r in rows]

    def tile_west_north(self, key: TileKey) -> tuple[float, float]:
        """UTM easting of the tile's west edge and northing of its north edge (m)."""
        col, row = key
        return col * self.tile_m, (row + 1) * self.tile_m

    def tile_pixel_to_utm(self, key: TileKey) -> npt.NDArray[np.float64]:
        """3x3 matrix taking tile pixel (x, y) (x east, y down from the north edge) to
        UTM (easting, northing) of its centre."""
        west, north = self.tile_west_north(key)
        r = self.res_m
        return np.array([[r, 0.0, west + 0.5 * r], [0.0, -r, north - 0.5 * r], [0.0, 0.0, 1.0]])


def sonar_to_utm(pose: SonarPose) -> npt.NDArray[np.float64]:
    """3x3 matrix taking sonar level-frame (forward, starboard) metres to UTM (E, N)."""
    s, c = math.sin(pose.yaw), math.cos(pose.yaw)
    # forward -> (sin yaw, cos yaw); starboard -> (cos yaw, -sin yaw)
    return np.array([[s, c, pose.east], [c, -s, pose.north], [0.0, 0.0, 1.0]])


def tile_box(
    tiles: TileGrid, key: TileKey, bounds: tuple[float, float, float, float]
) -> tuple[int, int, int, int] | None:
    """The (row0, row1, col0, col1) pixels of tile ``key`` inside UTM ``bounds``
    (west, south, east, north), or None when they do not meet."""
    west, north = tiles.tile_west_north(key)
    r = tiles.res_m
    size = tiles.tile_px
    c0 = max(0, math.floor((bounds[0] - west) / r))
    c1 = min(size, math.ceil((bounds[2] - west) / r))
    r0 = max(0, math.floor((north - bounds[3]) / r))
    r1 = min(size, math.ceil((north - bounds[1]) / r))
    return (r0, r1, c0, c1) if r1 > r0 and c1 > c0 else None


def _affine_inverse(m: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The inverse of a 3x3 2-D affine (last row 0, 0, 1), without a general inverse."""
    a, b, c, d = m[0, 0], m[0, 1], m[1, 0], m[1, 1]
    det = a * d - b * c
    ia, ib, ic, id_ = d / det, -b / det, -c / det, a / det
    tx, ty = m[0, 2], m[1, 2]
    return np.array(
        [[ia, ib, -(ia * tx + ib * ty)], [ic, id_, -(ic * tx + id_ * ty)], [0.0, 0.0, 1.0]]
    )


def warp_to_tile(
    layers: FloatImage,
    grid: SonarGrid,
    pose: SonarPose,
    tiles: TileGrid,
    key: TileKey,
    box: tuple[int, int, int, int] | None = None,
) -> FloatImage:
    """Warp a (rows, cols, channels) frame stack into tile ``key``: the whole tile
    (tile_px^2, channels), or only its pixels ``box`` = (row0, row1, col0, col1)."""
    r0, r1, c0, c1 = box if box is not None else (0, tiles.tile_px, 0, tiles.tile_px)
    # tile pixel -> UTM -> sonar metric -> sonar pixel, as one affine for cv2.
    to_sonar_pixel = (
        _affine_inverse(grid.pixel_to_metric())
        @ _affine_inverse(sonar_to_utm(pose))
        @ tiles.tile_pixel_to_utm(key)
        @ np.array([[1.0, 0.0, c0], [0.0, 1.0, r0], [0.0, 0.0, 1.0]])
    )
    warped = cv2.warpAffine(
        layers,
        to_sonar_pixel[:2],
        (c1 - c0, r1 - r0),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    return warped.reshape(r1 - r0, c1 - c0, -1)


def assemble(
    tiles: TileGrid, rendered: dict[TileKey, npt.NDArray[np.uint8]]
) -> tuple[npt.NDArray[np.uint8], tuple[float, float]]:
    """One north-up uint8 image of rendered tiles (0 = no data, data 1..255) and the UTM
    (west, north) of its top-left corner.

    The image spans the tiles that hold data: a tile without any (a fan that only grazed
    it, or one emptied when the survey-end pass placed the frames elsewhere) neither
    widens it nor shifts its corner, so the result folder's mosaic and a shore's mosaic
    of the same tiles have one extent whichever empty tiles either holds. Only when no
    tile holds data does the image span them all."""
    with_data = {key: values for key, values in rendered.items() if values.any()}
    rendered = with_data or rendered
    if not rendered:
        return np.zeros((0, 0), np.uint8), (0.0, 0.0)
    cols = [k[0] for k in rendered]
    rows = [k[1] for k in rendered]
    c0, c1, r0, r1 = min(cols), max(cols), min(rows), max(rows)
    size = tiles.tile_px
    canvas = np.zeros(((r1 - r0 + 1) * size, (c1 - c0 + 1) * size), np.uint8)
    for (col, row), values in rendered.items():
        y = (r1 - row) * size
        x = (col - c0) * size
        canvas[y : y + size, x : x + size] = values
    return canvas, (c0 * tiles.tile_m, (r1 + 1) * tiles.tile_m)
