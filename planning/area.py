"""The survey area as polygons in local metres: its types and its validation.

Frames and units: vertices are metres east/north in the survey's local grid frame
(``mapping.geo.LocalFrame``); areas are square metres. Rings are (n, 2) arrays, not closed
(the first vertex is not repeated). ``Area.geometry`` is the area as one shapely geometry,
what the lanes and the swath are cut with. ``PlanningError``, the one error of survey
planning, is defined here, where an area is first found unusable; the rest of
``planning`` raises it too.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt
import shapely

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
Point = tuple[float, float]

EPS_M = 1e-6
"""Metres: runs, gaps and crossings shorter than this are numerical noise."""


class PlanningError(ValueError):
    """An area or setting that cannot be planned; the message is one line."""

    def __init__(self, message: str, where: Point | None = None) -> None:
        super().__init__(message)
        self.where = where
        """The local (east, north) point the problem is at, when there is one."""


@dataclass(frozen=True, eq=False)
class Polygon:
    """One polygon: ``outer`` ring and keep-out ``holes``, each (n, 2) east/north metres,
    not closed (the first vertex is not repeated)."""

    outer: FloatArray
    holes: tuple[FloatArray, ...] = ()


@dataclass(frozen=True, eq=False)
class Area:
    """The survey area: the union of its polygons, less their holes (local metres)."""

    polygons: tuple[Polygon, ...]

    @cached_property
    def geometry(self) -> shapely.Geometry:
        """The area as one shapely (Multi)Polygon (of a valid area: ``validate_area``)."""
        return shapely.union_all(
            [shapely.Polygon(p.outer, [h for h in p.holes]) for p in self.polygons]
        )

    @property
    def area_m2(self) -> float:
        return float(shapely.area(self.geometry))

    @property
    def holes(self) -> list[FloatArray]:
        return [h for p in self.polygons for h in p.holes]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(east_min, north_min, east_max, north_max) of the outer rings."""
        pts = np.concatenate([p.outer for p in self.polygons])
        return (
            float(pts[:, 0].min()),
            float(pts[:, 1].min()),
            float(pts[:, 0].max()),
            float(pts[:, 1].max()),
        )

    def contains(self, east: FloatArray, north: FloatArray) -> BoolArray:
        """Which points lie inside the area (inside an outer ring, outside its holes)."""
        inside: BoolArray = shapely.contains_xy(self.geometry, east, north)
        return inside


def clean_ring(points: npt.ArrayLike) -> FloatArray:
    """(n, 2) vertices without the closing repeat and without consecutive repeats."""
    ring = np.asarray(points, np.float64).reshape(-1, 2)
    if len(ring) > 1 and np.allclose(ring[0], ring[-1], rtol=0, atol=1e-9):
        ring = ring[:-1]
    if len(ring) > 1:
        step = np.hypot(*(ring - np.roll(ring, 1, axis=0)).T)
        ring = ring[step > 1e-9]
    return ring


# GEOS's validity reasons end with the place, e.g. "Self-intersection[12.5 3]".
_REASON = re.compile(r"^(?P<what>.*)\[(?P<east>\S+) (?P<north>\S+)\]$")


def _self_crossing(ring: FloatArray) -> tuple[int, int, Point] | None:
    """Where a ring crosses or touches itself (GEOS's ``is_valid_reason``): the 0-based
    indices of two edges there (non-adjacent where they exist; edge i runs from vertex i
    to vertex i + 1) and the place; None if the ring is simple."""
    reason = shapely.is_valid_reason(shapely.Polygon(ring))
    found = _REASON.match(reason)
    if reason == "Valid Geometry" or found is None:
        return None
    where = (float(found["east"]), float(found["north"]))
    edges = shapely.linestrings(np.stack([ring, np.roll(ring, -1, axis=0)], axis=1))
    scale = max(1.0, float(np.abs(ring).max()))
    near = np.flatnonzero(shapely.distance(edges, shapely.Point(where)) <= 1e-9 * scale)
    n = len(ring)
    first = int(near[0]) if len(near) else 0
    others = [int(j) for j in near[1:] if (j - first) % n not in (1, n - 1)]
    other = others[0] if others else (first + 1) % n
    return first, other, where


def validate_area(area: Area) -> None:
    """Raise PlanningError unless every ring has 3+ points and an area and does not cross
    itself, and every hole lies inside its outer ring without touching another ring. The
    message names the ring and what is wrong with it; ``where`` is the place when GEOS
    (``shapely.is_valid_reason``) or the overlap found it."""
    if not area.polygons:
        raise PlanningError("no polygon")
    for k, poly in enumerate(area.polygons):
        name = "polygon" if len(area.polygons) == 1 else f"polygon {k + 1}"
        rings = [(f"{name} outer ring", poly.outer)] + [
            (f"{name} hole {i + 1}", h) for i, h in enumerate(poly.holes)
        ]
        for label, ring in rings:
            if len(ring) < 3:
                raise PlanningError(f"{label} has fewer than 3 distinct points ({len(ring)})")
            if not np.all(np.isfinite(ring)):
                raise PlanningError(f"{label} has a coordinate that is not a number")
            # The hull, not the ring: a figure-of-eight's two lobes cancel in the ring's
            # signed area, and it should be told that it crosses itself.
            if shapely.area(shapely.convex_hull(shapely.multipoints(ring))) < 1e-6:
                raise PlanningError(f"{label} has no area (its points are in a line)")
            crossing = _self_crossing(ring)
            if crossing is not None:
                i, j, where = crossing
                raise PlanningError(
                    f"{label} crosses itself (edges {min(i, j) + 1} and {max(i, j) + 1})", where
                )
        outer = shapely.Polygon(poly.outer)
        holes = [shapely.Polygon(h) for h in poly.holes]
        for i, hole in enumerate(holes):
            if not outer.contains_properly(hole):
                out = shapely.difference(hole, outer)
                if out.is_empty:  # inside, but touching the outer ring
                    out = shapely.intersection(hole.boundary, outer.boundary)
                raise PlanningError(
                    f"{name} hole {i + 1} is not inside its outer ring", _place(out)
                )
            for j in range(i):
                if hole.intersects(holes[j]):
                    raise PlanningError(
                        f"{name} holes {j + 1} and {i + 1} overlap",
                        _place(shapely.intersection(hole, holes[j])),
                    )


def _place(geometry: shapely.Geometry) -> Point:
    """A point on a (non-empty) geometry, for an error's ``where``."""
    point = shapely.point_on_surface(geometry)
    return (float(point.x), float(point.y))
