"""How much of the survey area a planned path maps: the swath swept by its mapping legs.

Coverage model: the sonar's usable swath (``planning.swath.sonar_swath``) is a band
``half_width_m`` each side of every leg the boat drives straight while mapping (lanes,
transits, detours; not the turns between lanes), from the leg's start to its end (square
ends), plus a disc of that radius at each waypoint between two mapping legs, where the
boat turns and the fan sweeps round. The swept seabed is the union of those bands and
discs (shapely), and the covered area its intersection with the area: exact, but for the
discs, polygons of ``DISC_SIDES`` sides inside the circle (they miss at most
``half_width_m * (1 - cos(pi / DISC_SIDES))``, 5 mm of a 4 m half swath, at their rims).
What this means for a lawnmower is in ``planning.lawnmower``'s module doc. Positions are
metres east/north in the survey's local grid frame; areas square metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from planning.area import EPS_M, Area
from planning.plan import Leg, LegKind, SurveyPlan

MAPPING_LEGS = (LegKind.LANE, LegKind.TRANSIT, LegKind.DETOUR)
"""The legs the boat maps along: everything but the turns between lanes."""

DISC_SIDES = 64


@dataclass(frozen=True)
class Coverage:
    area_m2: float
    covered_m2: float

    @property
    def fraction(self) -> float:
        return self.covered_m2 / self.area_m2 if self.area_m2 > 0 else 0.0


def swath_cover(legs: tuple[Leg, ...] | list[Leg], half_width_m: float) -> shapely.Geometry:
    """The seabed the path's mapping legs sweep (the module doc's model), local metres."""
    mapping = np.array([leg.kind in MAPPING_LEGS for leg in legs], bool)
    ends = np.array([(leg.start, leg.end) for leg in legs], np.float64).reshape(-1, 2, 2)
    long = mapping & (np.array([leg.length_m for leg in legs]) > EPS_M)
    bands = shapely.buffer(shapely.linestrings(ends[long]), half_width_m, cap_style="flat")
    turns = mapping[1:] & mapping[:-1]  # the boat turns here: the fan sweeps round the waypoint
    discs = shapely.buffer(
        shapely.points(ends[1:, 0][turns]), half_width_m, quad_segs=DISC_SIDES // 4
    )
    return shapely.union_all(np.concatenate([bands, discs]))


def coverage(area: Area, plan: SurveyPlan, half_width_m: float) -> Coverage:
    """Area (m²) and the part of it within the swath of the plan's mapping legs (m²)."""
    covered = shapely.intersection(swath_cover(plan.legs, half_width_m), area.geometry)
    return Coverage(area.area_m2, float(shapely.area(covered)))
