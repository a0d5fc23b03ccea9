"""How much of the survey area a planned path maps: the swath swept by its mapping legs.

Coverage model: the sonar's usable swath (``planning.swath.sonar_swath``) is a band
``half_width_m`` each side of every leg the boat drives straight while mapping (lanes,
transits, detours; not the turns between lanes), from the leg's start to its end, plus a
disc of that radius at each waypoint between two mapping legs, where the boat turns and the
fan sweeps round. What this means for a lawnmower is in ``planning.lawnmower``'s module doc.
Positions are metres east/north in the survey's local grid frame; areas square metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from planning.area import EPS_M, Area
from planning.plan import Leg, LegKind, SurveyPlan

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

MAPPING_LEGS = (LegKind.LANE, LegKind.TRANSIT, LegKind.DETOUR)
"""The legs the boat maps along: everything but the turns between lanes."""


@dataclass(frozen=True)
class Coverage:
    area_m2: float
    covered_m2: float

    @property
    def fraction(self) -> float:
        return self.covered_m2 / self.area_m2 if self.area_m2 > 0 else 0.0


def swept(
    legs: tuple[Leg, ...] | list[Leg], half_width_m: float, east: FloatArray, north: FloatArray
) -> BoolArray:
    """Which points lie in the swath of the path's mapping legs (the module doc's model)."""
    hit = np.zeros(np.shape(east), bool)
    previous: Leg | None = None
    for leg in legs:
        if leg.kind not in MAPPING_LEGS:
            previous = None
            continue
        a = np.array(leg.start)
        d = np.array(leg.end) - a
        length = float(np.hypot(*d))
        if length > EPS_M:
            t = ((east - a[0]) * d[0] + (north - a[1]) * d[1]) / length
            off = np.abs((east - a[0]) * d[1] - (north - a[1]) * d[0]) / length
            hit |= (t >= 0) & (t <= length) & (off <= half_width_m)
        if previous is not None:  # the boat turns here: the fan sweeps round the waypoint
            hit |= np.hypot(east - a[0], north - a[1]) <= half_width_m
        previous = leg
    return hit


def coverage(
    area: Area, plan: SurveyPlan, half_width_m: float, res_m: float | None = None
) -> Coverage:
    """Area (m², exact) and the part of it within the swath (m², on a grid of ``res_m``;
    by default fine enough for about 250,000 cells)."""
    e0, n0, e1, n1 = area.bounds
    if res_m is None:
        res_m = max(0.05, math.sqrt((e1 - e0) * (n1 - n0) / 250_000))
    east, north = np.meshgrid(
        np.arange(e0, e1, res_m) + res_m / 2, np.arange(n0, n1, res_m) + res_m / 2
    )
    inside = area.contains(east, north)
    covered = swept(plan.legs, half_width_m, east[inside], north[inside])
    total = area.area_m2
    fraction = covered.mean() if covered.size else 0.0
    return Coverage(total, float(fraction) * total)
