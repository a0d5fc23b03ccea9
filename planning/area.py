"""The survey area as polygons in local metres: its types, ring measures, validation and
convex hulls.

Frames and units: vertices are metres east/north in the survey's local grid frame
(``mapping.geo.LocalFrame``); areas are square metres. Rings are (n, 2) arrays, not closed
(the first vertex is not repeated). ``PlanningError``, the one error of survey planning,
is defined here, where an area is first found unusable; ``planning.swath`` and
``planning.lawnmower`` raise it too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

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

    @property
    def area_m2(self) -> float:
        return sum(
            abs(ring_area(p.outer)) - sum(abs(ring_area(h)) for h in p.holes) for p in self.polygons
        )

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
        inside = np.zeros(np.shape(east), bool)
        for p in self.polygons:
            here = _in_ring(p.outer, east, north)
            for h in p.holes:
                here &= ~_in_ring(h, east, north)
            inside |= here
        return inside


# --- rings ---


def ring_area(ring: FloatArray) -> float:
    """Signed area (m², counter-clockwise positive) of a ring (shoelace)."""
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def clean_ring(points: npt.ArrayLike) -> FloatArray:
    """(n, 2) vertices without the closing repeat and without consecutive repeats."""
    ring = np.asarray(points, np.float64).reshape(-1, 2)
    if len(ring) > 1 and np.allclose(ring[0], ring[-1], rtol=0, atol=1e-9):
        ring = ring[:-1]
    if len(ring) > 1:
        step = np.hypot(*(ring - np.roll(ring, 1, axis=0)).T)
        ring = ring[step > 1e-9]
    return ring


def _in_ring(ring: FloatArray, east: FloatArray, north: FloatArray) -> BoolArray:
    """Even-odd point-in-ring test, vectorised over the points."""
    inside = np.zeros(np.shape(east), bool)
    x2, y2 = ring[-1]
    for x1, y1 in ring:
        crosses = (y1 > north) != (y2 > north)
        # A near-horizontal edge overflows where it is not crossed (and not used).
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            x_at = x1 + (north - y1) * (x2 - x1) / (y2 - y1)
        inside ^= crosses & (east < x_at)
        x2, y2 = x1, y1
    return inside


def _edges_intersect(a: FloatArray, b: FloatArray, c: FloatArray, d: FloatArray) -> BoolArray:
    """Whether segments a-b and c-d (broadcast arrays of points) meet, touching included."""

    def orient(p: FloatArray, q: FloatArray, r: FloatArray) -> FloatArray:
        v = (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
            r[..., 0] - p[..., 0]
        )
        scale = np.hypot(*(q - p).T).T * np.hypot(*(r - p).T).T
        return np.where(np.abs(v) <= 1e-12 * np.maximum(scale, 1e-30), 0.0, np.sign(v))

    def on(p: FloatArray, q: FloatArray, r: FloatArray) -> BoolArray:
        """r within the bounding box of p-q (used when the three are collinear)."""
        return (
            (np.minimum(p[..., 0], q[..., 0]) - 1e-9 <= r[..., 0])
            & (r[..., 0] <= np.maximum(p[..., 0], q[..., 0]) + 1e-9)
            & (np.minimum(p[..., 1], q[..., 1]) - 1e-9 <= r[..., 1])
            & (r[..., 1] <= np.maximum(p[..., 1], q[..., 1]) + 1e-9)
        )

    o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
    proper = (o1 * o2 < 0) & (o3 * o4 < 0)
    touch = (
        ((o1 == 0) & on(a, b, c))
        | ((o2 == 0) & on(a, b, d))
        | ((o3 == 0) & on(c, d, a))
        | ((o4 == 0) & on(c, d, b))
    )
    result: BoolArray = proper | touch
    return result


def _first_crossing(ring_a: FloatArray, ring_b: FloatArray | None) -> tuple[int, int] | None:
    """Indices (i, j) of an edge of ring_a meeting an edge of ring_b, or of two
    non-adjacent edges of ring_a meeting each other when ring_b is None."""
    a0, a1 = ring_a, np.roll(ring_a, -1, axis=0)
    b0, b1 = (a0, a1) if ring_b is None else (ring_b, np.roll(ring_b, -1, axis=0))
    n, m = len(a0), len(b0)
    for start in range(0, n, 256):  # rows in chunks keep the n x m arrays small
        rows = slice(start, min(start + 256, n))
        hit = _edges_intersect(a0[rows, None, :], a1[rows, None, :], b0[None, :, :], b1[None, :, :])
        if ring_b is None:
            i = np.arange(start, rows.stop)[:, None]
            j = np.arange(m)[None, :]
            adjacent = (j <= i + 1) | ((i == 0) & (j == n - 1))
            hit &= ~adjacent
        found = np.argwhere(hit)
        if len(found):
            return int(found[0, 0]) + start, int(found[0, 1])
    if ring_b is None:
        # A spike: two adjacent edges folding back onto each other.
        e = a1 - a0
        nxt = np.roll(e, -1, axis=0)
        cross = e[:, 0] * nxt[:, 1] - e[:, 1] * nxt[:, 0]
        dot = np.einsum("ij,ij->i", e, nxt)
        scale = np.hypot(*e.T) * np.hypot(*nxt.T)
        fold = np.flatnonzero((np.abs(cross) <= 1e-12 * scale) & (dot < 0))
        if len(fold):
            return int(fold[0]), (int(fold[0]) + 1) % n
    return None


def validate_area(area: Area) -> None:
    """Raise PlanningError unless every ring has 3+ points and an area, does not cross
    itself, and every hole lies inside its polygon without touching another ring."""
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
            if abs(ring_area(ring)) < 1e-6:
                raise PlanningError(f"{label} has no area (its points are in a line)")
            crossing = _first_crossing(ring, None)
            if crossing is not None:
                i, j = crossing
                where = (float(ring[i, 0]), float(ring[i, 1]))
                raise PlanningError(f"{label} crosses itself (edges {i + 1} and {j + 1})", where)
        for i, hole in enumerate(poly.holes):
            if (
                _first_crossing(poly.outer, hole) is not None
                or not _in_ring(poly.outer, hole[:1, 0], hole[:1, 1]).all()
            ):
                where = (float(hole[0, 0]), float(hole[0, 1]))
                raise PlanningError(f"{name} hole {i + 1} is not inside its outer ring", where)
            for j in range(i):
                other = poly.holes[j]
                inside = (
                    _in_ring(other, hole[:1, 0], hole[:1, 1]).all()
                    or _in_ring(hole, other[:1, 0], other[:1, 1]).all()
                )
                if inside or _first_crossing(hole, other) is not None:
                    where = (float(hole[0, 0]), float(hole[0, 1]))
                    raise PlanningError(f"{name} holes {j + 1} and {i + 1} overlap", where)


def convex_hull(points: FloatArray) -> FloatArray:
    """Counter-clockwise convex hull (Andrew's monotone chain) of (n, 2) points."""
    pts = np.unique(np.round(points, 9), axis=0)
    if len(pts) < 3:
        return pts

    def half(seq: FloatArray) -> list[FloatArray]:
        chain: list[FloatArray] = []
        for p in seq:
            while len(chain) >= 2:
                o, a = chain[-2], chain[-1]
                if (a[0] - o[0]) * (p[1] - o[1]) - (a[1] - o[1]) * (p[0] - o[0]) > 1e-12:
                    break
                chain.pop()
            chain.append(p)
        return chain

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])
