"""The survey's world frame: its UTM zone and a local east-north frame anchored in it.

Inside the core, positions are metres east/north of a UTM anchor point (grid-aligned, so
a local coordinate plus the anchor *is* the UTM coordinate) and headings are radians
clockwise from UTM grid north. At the edges positions are WGS84 lat/lon or UTM, and
headings are from true north: the two norths differ by the meridian convergence, up to a
few degrees, and ``true_to_grid`` / ``grid_to_true`` convert where they meet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from pyproj import CRS, Transformer

from mapping.se2 import wrap_2pi


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS84 UTM zone containing a point (326xx north, 327xx south),
    honouring the Norway and Svalbard exceptions."""
    if not (-80.0 <= lat_deg <= 84.0):
        raise ValueError(f"latitude {lat_deg} is outside the UTM zones (-80..84)")
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    if 56.0 <= lat_deg < 64.0 and 3.0 <= lon_deg < 12.0:
        zone = 32
    elif 72.0 <= lat_deg < 84.0 and 0.0 <= lon_deg < 42.0:
        zone = 31 if lon_deg < 9.0 else 33 if lon_deg < 21.0 else 35 if lon_deg < 33.0 else 37
    return (32600 if lat_deg >= 0.0 else 32700) + zone


@dataclass(frozen=True)
class LocalFrame:
    """A local east-north frame: local (x, y) = UTM (easting, northing) - anchor.

    epsg: the UTM CRS; anchor_e / anchor_n: the anchor's UTM coordinates (metres).
    """

    epsg: int
    anchor_e: float
    anchor_n: float
    _forward: Transformer = field(init=False, repr=False, compare=False)
    _inverse: Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        crs = CRS.from_epsg(self.epsg)
        object.__setattr__(self, "_forward", Transformer.from_crs(4326, crs, always_xy=True))
        object.__setattr__(self, "_inverse", Transformer.from_crs(crs, 4326, always_xy=True))

    @classmethod
    def around(cls, lat_deg: float, lon_deg: float, *, round_to_m: float = 100.0) -> LocalFrame:
        """The frame of the UTM zone containing (lat, lon), anchored at the UTM point
        rounded to ``round_to_m`` (a round anchor keeps local coordinates readable)."""
        epsg = utm_epsg(lat_deg, lon_deg)
        e, n = Transformer.from_crs(4326, CRS.from_epsg(epsg), always_xy=True).transform(
            lon_deg, lat_deg
        )
        return cls(epsg, round(e / round_to_m) * round_to_m, round(n / round_to_m) * round_to_m)

    def to_local(
        self, lat_deg: npt.ArrayLike, lon_deg: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """WGS84 degrees to local (x east, y north) metres."""
        e, n = self._forward.transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
        return np.asarray(e) - self.anchor_e, np.asarray(n) - self.anchor_n

    def to_utm(
        self, x: npt.ArrayLike, y: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        return np.asarray(x, float) + self.anchor_e, np.asarray(y, float) + self.anchor_n

    def to_latlon(
        self, x: npt.ArrayLike, y: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Local metres to WGS84 (lat, lon) degrees."""
        lon, lat = self._inverse.transform(
            np.asarray(x, float) + self.anchor_e, np.asarray(y, float) + self.anchor_n
        )
        return np.asarray(lat), np.asarray(lon)

    def convergence_rad(self, lat_deg: float, lon_deg: float) -> float:
        """Grid azimuth of true north at a point (radians, clockwise from grid north).

        Measured from the projection itself (a short step north), which avoids the sign
        conventions of the closed-form meridian convergence.
        """
        step = 1e-4
        e0, n0 = self._forward.transform(lon_deg, lat_deg - step)
        e1, n1 = self._forward.transform(lon_deg, lat_deg + step)
        return math.atan2(e1 - e0, n1 - n0)

    def true_to_grid(self, heading_rad: float, lat_deg: float, lon_deg: float) -> float:
        """Heading from true north to heading from grid north (radians, [0, 2*pi))."""
        return wrap_2pi(heading_rad + self.convergence_rad(lat_deg, lon_deg))

    def grid_to_true(self, heading_rad: float, lat_deg: float, lon_deg: float) -> float:
        """Heading from grid north to heading from true north (radians, [0, 2*pi))."""
        return wrap_2pi(heading_rad - self.convergence_rad(lat_deg, lon_deg))
