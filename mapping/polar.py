"""Polar sonar frames to Cartesian ground images, through precomputed remap tables.

Geometry (metres, radians), the standard imaging-sonar model (e.g. Hurtós et al. 2015):
an echo at slant range r, bearing theta (positive to starboard) and unknown elevation phi
comes from r (cos phi cos theta, cos phi sin theta, sin phi) in the sonar frame, which is
the level frame pitched down by the tilt t. The sonar sits ``altitude_m`` above a flat
seabed, so a seabed point at (forward f, starboard s) of the point below the sonar is
seen at x_s = f cos t + h sin t, y_s = s, z_s = h cos t - f sin t: slant range |(f, s, h)|
and bearing atan2(y_s, x_s). With the altitude unknown (``altitude_m`` = 0) the slant
range is taken as ground range in the fan's plane.

The Cartesian image follows ``mapping.fmt.SonarGrid``: rows from far to near, columns from
port to starboard, in the sonar's level frame (forward along the boresight's azimuth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from mapping.fmt import SonarGrid


@dataclass(frozen=True, slots=True)
class FanGeometry:
    """What fixes the polar-to-Cartesian mapping of a sonar's frames.

    bearings_rad: (n_beams,) ascending; range_resolution_m: metres per bin, bin i at
    (i + 0.5) * range_resolution_m; altitude_m: sonar height above the seabed (0: unknown).
    """

    bearings_rad: tuple[float, ...]
    n_ranges: int
    range_resolution_m: float
    altitude_m: float
    tilt_rad: float = 0.0

    @property
    def max_range_m(self) -> float:
        return self.n_ranges * self.range_resolution_m

    @classmethod
    def of(
        cls,
        bearings_rad: npt.ArrayLike,
        n_ranges: int,
        range_resolution_m: float,
        altitude_m: float,
        tilt_rad: float = 0.0,
    ) -> FanGeometry:
        bearings = tuple(round(float(b), 7) for b in np.asarray(bearings_rad, float))
        resolution = round(float(range_resolution_m), 9)
        # Without an altitude the tilt has nothing to act on: slant range is ground range.
        tilt = tilt_rad if altitude_m > 0 else 0.0
        return cls(bearings, int(n_ranges), resolution, altitude_m, tilt)


@dataclass(frozen=True)
class CartesianTables:
    """Remap tables from a polar frame to a ``SonarGrid``, and the fan mask on that grid."""

    grid: SonarGrid
    map_beam: npt.NDArray[np.float32]  # fractional beam index per Cartesian pixel
    map_range: npt.NDArray[np.float32]  # fractional range-bin index per pixel
    mask: npt.NDArray[np.bool_]  # pixels inside the fan (and above the seabed)


def ground_to_polar(
    forward_m: npt.NDArray[np.float64],
    starboard_m: npt.NDArray[np.float64],
    altitude_m: float,
    tilt_rad: float = 0.0,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Slant range (m) and bearing (rad) of seabed points (sonar level frame); bearing NaN
    for points behind the sonar."""
    st, ct = math.sin(tilt_rad), math.cos(tilt_rad)
    x_s = forward_m * ct + altitude_m * st
    slant = np.sqrt(forward_m**2 + starboard_m**2 + altitude_m**2)
    bearing = np.where(x_s > 0, np.arctan2(starboard_m, x_s), np.nan)
    return slant, bearing


def polar_to_ground(
    slant_m: npt.NDArray[np.float64],
    bearing_rad: npt.NDArray[np.float64],
    altitude_m: float,
    tilt_rad: float = 0.0,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Seabed (forward, starboard) metres of echoes at slant range and bearing; NaN where
    the beam's vertical arc does not reach the seabed at that range.

    Solves sin(t) cos(theta) cos(phi) + cos(t) sin(phi) = h / r for the elevation phi.
    """
    st, ct = math.sin(tilt_rad), math.cos(tilt_rad)
    a = st * np.cos(bearing_rad)
    rho = np.hypot(a, ct)
    q = altitude_m / np.maximum(slant_m * rho, 1e-12)
    phi = np.arcsin(np.clip(q, -1.0, 1.0)) - np.arctan2(a, ct)
    x_s = slant_m * np.cos(phi) * np.cos(bearing_rad)
    y_s = slant_m * np.cos(phi) * np.sin(bearing_rad)
    z_s = slant_m * np.sin(phi)
    forward = np.where(q <= 1.0, ct * x_s - st * z_s, np.nan)
    return forward, y_s


def fan_grid(fan: FanGeometry, res_m: float, min_range_m: float = 0.0) -> SonarGrid:
    """The smallest ``SonarGrid`` at ``res_m`` holding the whole ground footprint."""
    bearings = np.asarray(fan.bearings_rad)
    slant = np.linspace(max(min_range_m, 0.0), fan.max_range_m, 64)
    r, b = np.meshgrid(slant, np.linspace(bearings[0], bearings[-1], 129))
    forward, starboard = polar_to_ground(r, b, fan.altitude_m, fan.tilt_rad)
    ok = np.isfinite(forward)
    f_max = float(np.max(forward[ok])) + res_m
    f_min = max(float(np.min(forward[ok])) - res_m, 0.0)
    s_max = float(np.max(np.abs(starboard[ok]))) + res_m
    rows = math.ceil((f_max - f_min) / res_m)
    cols = 2 * math.ceil(s_max / res_m)
    return SonarGrid((rows, cols), res_m, f_min + rows * res_m, -cols / 2 * res_m)


def cartesian_tables(
    fan: FanGeometry, grid: SonarGrid, min_range_m: float = 0.0
) -> CartesianTables:
    """Remap tables for ``cv2.remap`` from polar (rows = range bins, cols = beams)."""
    rows, cols = grid.shape
    r = grid.res_m
    forward = grid.forward_max_m - (np.arange(rows)[:, None] + 0.5) * r
    starboard = grid.starboard_min_m + (np.arange(cols)[None, :] + 0.5) * r
    forward, starboard = (
        np.asarray(a, np.float64) for a in np.broadcast_arrays(forward, starboard)
    )
    slant, bearing = ground_to_polar(forward, starboard, fan.altitude_m, fan.tilt_rad)
    bearings = np.asarray(fan.bearings_rad)
    # The bearing table is not evenly spaced: interpolate the beam index, never assume a step.
    beam = np.interp(bearing, bearings, np.arange(bearings.size), left=-1.0, right=-1.0)
    range_bin = slant / fan.range_resolution_m - 0.5
    mask = (
        np.isfinite(bearing)
        & (beam >= 0.0)
        & (beam <= bearings.size - 1)
        & (range_bin >= 0.0)
        & (range_bin <= fan.n_ranges - 1)
        & (slant >= min_range_m)
    )
    map_beam = np.where(mask, beam, -1.0).astype(np.float32)
    map_range = np.where(mask, range_bin, -1.0).astype(np.float32)
    return CartesianTables(grid, map_beam, map_range, mask)


def to_cartesian(
    polar: npt.NDArray[np.float32] | npt.NDArray[np.uint8], tables: CartesianTables
) -> npt.NDArray[np.float32]:
    """Resample a polar frame (n_ranges, n_beams) onto the tables' grid (0 outside the fan)."""
    out = cv2.remap(
        polar.astype(np.float32, copy=False),
        tables.map_beam,
        tables.map_range,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    out[~tables.mask] = 0.0
    return out
