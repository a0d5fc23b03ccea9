"""The usable ground swath of a forward-looking sonar on a boat running straight.

Frames and units: across-track offsets are metres to starboard of the GPS antenna's track,
along-track distances metres ahead of the antenna; angles are degrees. The footprint
follows ``mapping.preprocess`` (what a frame keeps) and ``mapping.polar`` (slant range and
bearing of a seabed point); survey planning (``planning.lawnmower``) spaces its lanes by it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapping.polar import ground_to_polar
from mapping.preprocess import PreprocessParams, lit_min_range
from planning.area import PlanningError

MIN_LOOK_M = 1.0
"""A seabed point is in the usable swath when the boat sees it over at least this much of
its run (m): at 1 m/s and 10 Hz that is ten pings to blend and to register."""


@dataclass(frozen=True)
class Swath:
    """The sonar's ground swath across the track (metres, from the GPS antenna's track).

    half_width_m: usable half width, each side; fan_half_width_m: the whole ground
    footprint's half width; ahead_min_m / ahead_max_m: how far ahead of the antenna the
    usable footprint begins and ends at the usable swath's edge.
    """

    half_width_m: float
    fan_half_width_m: float
    ahead_min_m: float
    ahead_max_m: float

    @property
    def width_m(self) -> float:
        return 2.0 * self.half_width_m

    def spacing_for(self, overlap: float) -> float:
        """Lane spacing (m) for a side overlap (0..1) of adjacent lanes' swaths."""
        return self.width_m * (1.0 - overlap)


def sonar_swath(
    *,
    range_m: float,
    fan_deg: float,
    tilt_deg: float,
    altitude_m: float,
    mount_forward_m: float = 0.0,
    mount_starboard_m: float = 0.0,
    mount_yaw_deg: float = 0.0,
    min_look_m: float = MIN_LOOK_M,
    params: PreprocessParams | None = None,
) -> Swath:
    """The usable ground swath of a forward-looking sonar on a boat running straight.

    The footprint is what ``mapping.preprocess`` keeps of a frame: slant ranges from the
    lit near edge (``lit_min_range``: the near field is masked) to the range or to where
    the upper edge of the vertical beam leaves the seabed, bearings within the fan, on a
    flat seabed ``altitude_m`` below the sonar tilted down by ``tilt_deg``
    (``mapping.polar``). A seabed point at a given offset across the track is mapped when
    the footprint sweeps over it; it is *usable* when the footprint is at least
    ``min_look_m`` deep along the track at that offset (several pings to blend and
    register, not one grazing fan edge). An off-centre sonar gets its narrower side's half
    width on both sides (lanes alternate direction).
    """
    p = params or PreprocessParams()
    if range_m <= 0 or not 0 < fan_deg < 180:
        raise PlanningError(f"sonar range {range_m} m and fan {fan_deg} degrees give no swath")
    near = lit_min_range(altitude_m, tilt_deg, p.vertical_aperture_deg, p.near_margin_deg)
    far = range_m
    upper = math.radians(tilt_deg - p.vertical_aperture_deg / 2.0)
    if altitude_m > 0 and upper > 0:
        far = min(far, altitude_m / math.sin(upper))
    if near >= far:
        raise PlanningError(
            f"the sonar sees no seabed: at altitude {altitude_m} m and tilt {tilt_deg} degrees "
            f"the lit band starts at {near:.1f} m, beyond the {far:.1f} m it reaches"
        )
    res = max(0.02, far / 250.0)
    reach = far + math.hypot(mount_forward_m, mount_starboard_m) + res
    x = np.arange(-reach, reach, res) + res / 2  # body frame: forward of the antenna
    y = np.arange(-reach, reach, res) + res / 2  # starboard of the antenna
    bx, by = np.meshgrid(x, y, indexing="ij")
    yaw = math.radians(mount_yaw_deg)
    dx, dy = bx - mount_forward_m, by - mount_starboard_m
    forward = dx * math.cos(yaw) + dy * math.sin(yaw)  # sonar level frame
    starboard = -dx * math.sin(yaw) + dy * math.cos(yaw)
    tilt = math.radians(tilt_deg) if altitude_m > 0 else 0.0
    slant, bearing = ground_to_polar(forward, starboard, max(altitude_m, 0.0), tilt)
    with np.errstate(invalid="ignore"):
        seen = (
            np.isfinite(bearing)
            & (np.abs(bearing) <= math.radians(fan_deg) / 2)
            & (slant >= near)
            & (slant <= far)
        )
    depth = seen.sum(axis=0) * res  # footprint depth along the track, per across offset
    usable = depth >= min_look_m
    if not usable[y > 0].any() or not usable[y < 0].any():
        raise PlanningError("the sonar's usable footprint does not reach both sides of the track")
    half = round(
        min(float(y[usable & (y > 0)].max()), float(-y[usable & (y < 0)].min())) + res / 2, 3
    )
    fan_half = round(float(np.abs(y[depth > 0]).max()) + res / 2, 3)
    edge = usable & (np.abs(np.abs(y) - half) <= res)
    rows = seen[:, edge]
    ahead = np.broadcast_to(x[:, None], rows.shape)
    return Swath(
        half_width_m=half,
        fan_half_width_m=fan_half,
        ahead_min_m=float(ahead[rows].min()),
        ahead_max_m=float(ahead[rows].max()),
    )
