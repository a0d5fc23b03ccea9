"""A planned survey path: its legs and lane runs in driving order, with its length, turns
and duration.

Frames and units: positions are metres east/north in the survey's local grid frame;
bearings are radians clockwise from grid north; durations are seconds. How the legs are
laid out is ``planning.lawnmower``'s job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from planning.area import Point

FloatArray = npt.NDArray[np.float64]

TURN_RATE_RAD_S = 0.5
"""Duration model: each change of course of theta radians adds theta / TURN_RATE_RAD_S
seconds (the boat slows to turn; a 180-degree turnaround costs about 6 s)."""


class LegKind(StrEnum):
    LANE = "lane"  # a run of a lane, lead-in to run-out
    TRANSIT = "transit"  # along the lane line between two runs of one lane (concave notch)
    DETOUR = "detour"  # round a keep-out (its corners and outline)
    TURN = "turn"  # from the end of one lane to the start of the next


@dataclass(frozen=True)
class Leg:
    """One straight piece of the path, from ``start`` to ``end`` (local metres)."""

    kind: LegKind
    lane: int  # index of the lane in driving order (-1 for turns)
    start: Point
    end: Point

    @property
    def length_m(self) -> float:
        return math.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1])


@dataclass(frozen=True)
class Run:
    """One run of a lane: driven from ``start`` to ``end`` (its first and last waypoints),
    over the area from ``entry`` to ``exit``. ``starts_at_keepout`` / ``ends_at_keepout``:
    that end lies on a keep-out's outline (no lead-in there) rather than ``lead_in`` beyond
    the area's boundary (a lead-in is also cut short where a keep-out is closer than
    that)."""

    lane: int
    start: Point
    end: Point
    entry: Point
    exit: Point
    starts_at_keepout: bool
    ends_at_keepout: bool


@dataclass(frozen=True, eq=False)
class SurveyPlan:
    """A planned lawnmower: lanes along ``bearing_rad`` (grid, the first lane's direction),
    ``spacing_m`` apart; its runs and the legs of the whole path in driving order, and the
    outlines of the keep-outs it keeps out of (counter-clockwise (n, 2) rings)."""

    bearing_rad: float
    spacing_m: float
    lead_in_m: float
    clearance_m: float
    runs: tuple[Run, ...]
    legs: tuple[Leg, ...]
    keepouts: tuple[FloatArray, ...] = field(default=())

    @property
    def n_lanes(self) -> int:
        return len({r.lane for r in self.runs})

    @property
    def waypoints(self) -> FloatArray:
        """(n, 2) east/north of the path's vertices in driving order."""
        if not self.legs:
            return np.zeros((0, 2))
        return np.array([self.legs[0].start] + [leg.end for leg in self.legs])

    @property
    def distance_m(self) -> float:
        return float(sum(leg.length_m for leg in self.legs))

    @property
    def turn_rad(self) -> float:
        """Sum of the course changes at the waypoints (radians)."""
        w = self.waypoints
        if len(w) < 3:
            return 0.0
        d = np.diff(w, axis=0)
        course = np.arctan2(d[:, 0], d[:, 1])
        change = np.angle(np.exp(1j * np.diff(course)))
        return float(np.abs(change).sum())

    def duration_s(self, speed_mps: float) -> float:
        """Time to drive the path at ``speed_mps`` with ``TURN_RATE_RAD_S`` for the turns."""
        return self.distance_m / speed_mps + self.turn_rad / TURN_RATE_RAD_S
