"""The site's frames: WGS84, its UTM zone, and the local grid-aligned east/north frame.

The local frame is UTM shifted to a whole-metre UTM point near the scenario's origin:
``east_utm = utm_east0 + local_east``, ``north_utm = utm_north0 + local_north``. It is
grid-aligned, so local bearings are grid bearings. A true heading (clockwise from true
north) becomes a grid heading by subtracting the meridian convergence:
``grid = true - convergence`` (pyproj's ``meridian_convergence``; west of the central
meridian in the northern hemisphere it is negative, i.e. true north lies east of grid
north).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from pyproj import CRS, Proj, Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SiteFrame:
    """WGS84 <-> UTM <-> local conversions for one site."""

    origin_lat_deg: float
    origin_lon_deg: float
    epsg: int
    utm_east0: float
    utm_north0: float
    convergence_deg: float
    """Meridian convergence at the origin (degrees): grid heading = true heading - this."""
    _to_utm: Transformer = field(repr=False, compare=False)
    _to_wgs84: Transformer = field(repr=False, compare=False)

    @classmethod
    def at(cls, lat_deg: float, lon_deg: float) -> SiteFrame:
        """The frame of a site whose origin is near (lat, lon); the UTM origin is rounded to
        whole metres so that map pixels can sit on a whole-metre UTM grid."""
        infos = query_utm_crs_info(
            datum_name="WGS 84",
            area_of_interest=AreaOfInterest(lon_deg, lat_deg, lon_deg, lat_deg),
        )
        # Several zones can cover a boundary point; the one whose code matches the
        # longitude's own zone is the conventional choice.
        zone = int((lon_deg + 180.0) // 6.0) + 1
        want = (32600 if lat_deg >= 0 else 32700) + zone
        codes = [int(info.code) for info in infos]
        epsg = want if want in codes or not codes else codes[0]
        crs = CRS.from_epsg(epsg)
        to_utm = Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True)
        to_wgs84 = Transformer.from_crs(crs, CRS.from_epsg(4326), always_xy=True)
        east, north = to_utm.transform(lon_deg, lat_deg)
        convergence = float(Proj(crs).get_factors(lon_deg, lat_deg).meridian_convergence)
        return cls(
            lat_deg,
            lon_deg,
            epsg,
            float(round(east)),
            float(round(north)),
            convergence,
            to_utm,
            to_wgs84,
        )

    @property
    def convergence_rad(self) -> float:
        return math.radians(self.convergence_deg)

    def to_utm(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Local east/north (m) -> UTM easting/northing (m)."""
        return np.asarray(east) + self.utm_east0, np.asarray(north) + self.utm_north0

    def to_latlon(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Local east/north (m) -> WGS84 latitude, longitude (degrees)."""
        e, n = self.to_utm(east, north)
        lon, lat = self._to_wgs84.transform(e, n)
        return np.asarray(lat, np.float64), np.asarray(lon, np.float64)

    def from_latlon(self, lat: FloatArray, lon: FloatArray) -> tuple[FloatArray, FloatArray]:
        """WGS84 latitude, longitude (degrees) -> local east/north (m)."""
        e, n = self._to_utm.transform(np.asarray(lon), np.asarray(lat))
        return np.asarray(e) - self.utm_east0, np.asarray(n) - self.utm_north0

    def grid_to_true(self, grid_rad: FloatArray) -> FloatArray:
        """Grid heading -> true heading (radians, clockwise)."""
        return np.asarray(grid_rad) + self.convergence_rad

    def rotate_grid_to_true(
        self, north: FloatArray, east: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """A horizontal vector's grid (north, east) components -> true (north, east)."""
        c, s = math.cos(self.convergence_rad), math.sin(self.convergence_rad)
        # A grid bearing b is the true bearing b + convergence: rotate clockwise.
        north = np.asarray(north)
        east = np.asarray(east)
        return north * c - east * s, north * s + east * c
