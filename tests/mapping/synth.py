"""Sonar-like test scenes: a textured seabed seen through a fan, with speckle."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from mapping.grid import SonarGrid

WORLD_RES_M = 0.01


def seabed(rng: np.random.Generator, size_px: int = 1600) -> npt.NDArray[np.float32]:
    """Multi-scale texture in [0, 1] at 1 cm (16 m square for the default size)."""
    texture = np.zeros((size_px, size_px), np.float32)
    for scale, amplitude in ((3, 1.0), (9, 0.7), (31, 0.5), (101, 0.4)):
        noise = rng.standard_normal((size_px // scale + 2, size_px // scale + 2)).astype(np.float32)
        texture += amplitude * cv2.resize(noise, (size_px, size_px), interpolation=cv2.INTER_CUBIC)
    return ((texture - texture.min()) / (texture.max() - texture.min())).astype(np.float32)


def fan(res_m: float = 0.02) -> tuple[SonarGrid, npt.NDArray[np.bool_]]:
    """A 130 degree fan lit from 2.2 m to 4.9 m on a grid at ``res_m``."""
    grid = SonarGrid(shape=(175, 450), res_m=res_m, forward_max_m=5.0, starboard_min_m=-4.5)
    forward, starboard = grid_coordinates(grid)
    r = np.hypot(forward, starboard)
    b = np.arctan2(starboard, forward)
    mask = (r > 2.2) & (r < 4.9) & (np.abs(b) < math.radians(64))
    return grid, mask


def grid_coordinates(grid: SonarGrid) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    rows, cols = grid.shape
    forward = grid.forward_max_m - (np.arange(rows)[:, None] + 0.5) * grid.res_m
    starboard = grid.starboard_min_m + (np.arange(cols)[None, :] + 0.5) * grid.res_m
    return np.broadcast_arrays(forward, starboard)  # type: ignore[return-value]


def view(
    world: npt.NDArray[np.float32],
    grid: SonarGrid,
    mask: npt.NDArray[np.bool_],
    east: float,
    north: float,
    heading: float,
    rng: np.random.Generator | None = None,
    speckle_shape: float = 4.0,
) -> npt.NDArray[np.float32]:
    """The fan of a sonar at (east, north) m (world origin at its south-west corner)
    looking along ``heading`` (radians clockwise from north), with gamma speckle."""
    forward, starboard = grid_coordinates(grid)
    s, c = math.sin(heading), math.cos(heading)
    e = east + forward * s + starboard * c
    n = north + forward * c - starboard * s
    map_x = (e / WORLD_RES_M - 0.5).astype(np.float32)
    map_y = (world.shape[0] - n / WORLD_RES_M - 0.5).astype(np.float32)
    image = cv2.remap(world, map_x, map_y, cv2.INTER_LINEAR)
    if rng is not None:
        image = image * rng.gamma(speckle_shape, 1.0 / speckle_shape, image.shape).astype(
            np.float32
        )
    return np.where(mask, image, 0.0).astype(np.float32)
