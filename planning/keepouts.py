"""Keep-outs: the area's holes grown by the clearance, and the shortest way round them.

Frames and units: metres east/north in the survey's local grid frame. A keep-out is a
shapely Polygon; ``Keepouts.rings`` gives each one's outline as a counter-clockwise (n, 2)
ring, not closed.

- Each hole is grown by the clearance, so a keep-out follows the hole's own shape,
  concavities included: the water in a C-shaped hole's bay stays open to the boat where
  it is wider than twice the clearance. The growth is the hole's Minkowski sum with a
  ``DISC_SIDES``-gon drawn *round* the clearance circle (shapely's convex hulls and
  union), so every point of a keep-out's outline is at least the clearance from its hole;
  ``shapely.buffer`` draws its round corners with chords inside the circle, of up to 1.5
  times its nominal angle, and comes 4 % closer at a corner of 30 degrees. Grown holes
  that overlap are one keep-out; water that keep-outs enclose all round is filled in
  (the boat could not reach it).
- The shortest way from one point to another that stays out of every keep-out is a path
  of straight legs through convex corners of the keep-outs (Lozano-Pérez & Wesley 1979,
  doi:10.1145/359156.359164): the *visibility graph* joins every two corners that see
  each other (the straight leg between them does not enter a keep-out), and Dijkstra's
  algorithm (1959, doi:10.1007/BF01386390) finds the shortest path through it. The
  corners are those of the keep-outs grown by another ``ROUTE_MARGIN_M``, so the path
  runs just clear of them instead of grazing them; reflex corners are left out (no
  shortest path bends at one). A leg *enters* a keep-out when it meets the keep-out shrunk
  by ``TOUCH_M``: a leg that starts or ends on an outline (a lane stopped by the keep-out)
  or runs along it is not an entry.
- ``Keepouts.loop`` is once round one keep-out along its outline, from a point on it.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt
import shapely
from shapely.geometry.polygon import orient

from planning.area import EPS_M, PlanningError, Point

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

DISC_SIDES = 16
"""Sides of the polygon drawn round the clearance circle that grows a hole."""
ROUTE_MARGIN_M = 0.01
"""How far outside the keep-outs a path round them runs (m)."""
_MEET_M = 5 * ROUTE_MARGIN_M + EPS_M  # a mitred corner stands off up to 5 margins (the limit)
TOUCH_M = 1e-4
"""A leg that reaches no deeper than this into a keep-out only touches it (m)."""


@dataclass(frozen=True, eq=False)
class Keepouts:
    """The keep-outs (disjoint shapely Polygons without holes, local metres) and the
    visibility graph round them, built once and used for every leg of a plan."""

    polygons: tuple[shapely.Polygon, ...]

    @classmethod
    def around(cls, holes: list[FloatArray], clearance_m: float) -> Keepouts:
        """The keep-outs round ``holes`` at ``clearance_m`` (see the module doc)."""
        if not holes:
            return cls(())
        grown = [_grown(h, clearance_m) for h in holes]
        parts = shapely.get_parts(shapely.union_all(grown))
        outlines = shapely.polygons(shapely.get_exterior_ring(parts))  # fills what they close in
        return cls(tuple(orient(p) for p in shapely.get_parts(shapely.union_all(outlines))))

    @cached_property
    def rings(self) -> tuple[FloatArray, ...]:
        """Each keep-out's outline, counter-clockwise, (n, 2), not closed."""
        return tuple(shapely.get_coordinates(p.exterior)[:-1] for p in self.polygons)

    @cached_property
    def geometry(self) -> shapely.Geometry:
        """All keep-outs as one geometry (empty without holes)."""
        return shapely.union_all(self.polygons)

    @cached_property
    def _inside(self) -> shapely.Geometry:
        """The keep-outs shrunk by ``TOUCH_M``: what a leg must not meet."""
        inside = shapely.buffer(self.geometry, -TOUCH_M)
        shapely.prepare(inside)
        return inside

    @cached_property
    def _corners(self) -> FloatArray:
        """(k, 2) convex corners of the keep-outs grown by ``ROUTE_MARGIN_M``: the nodes
        of the visibility graph."""
        corners = []
        for polygon in self.polygons:
            grown = orient(shapely.buffer(polygon, ROUTE_MARGIN_M, join_style="mitre"))
            ring = shapely.get_coordinates(grown.exterior)[:-1]
            before = ring - np.roll(ring, 1, axis=0)
            after = np.roll(ring, -1, axis=0) - ring
            turn = before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0]
            corners.append(ring[turn > 0])  # a left turn on a counter-clockwise ring
        return np.concatenate(corners) if corners else np.zeros((0, 2))

    @cached_property
    def _graph(self) -> FloatArray:
        """(k, k) lengths of the legs between corners that see each other, inf where the
        leg would enter a keep-out."""
        c = self._corners
        i, j = np.triu_indices(len(c), 1)
        free = self._free(c[i], c[j])
        graph = np.full((len(c), len(c)), np.inf)
        length = np.hypot(*(c[j] - c[i]).T)
        graph[i[free], j[free]] = length[free]
        graph[j[free], i[free]] = length[free]
        return graph

    def _free(self, a: FloatArray, b: FloatArray) -> BoolArray:
        """Which straight legs a[k] to b[k] ((n, 2) each) enter no keep-out."""
        if not self.polygons:
            return np.ones(len(a), bool)
        legs = shapely.linestrings(np.stack([a, b], axis=1))
        return ~np.asarray(shapely.intersects(legs, self._inside), bool)

    def blocks(self, start: Point, end: Point) -> bool:
        """Whether the straight leg from start to end enters a keep-out."""
        return not bool(self._free(np.array([start]), np.array([end]))[0])

    def route(self, start: Point, end: Point) -> list[Point]:
        """The corners the shortest path from start to end that enters no keep-out bends
        at (none if the straight leg is free); PlanningError if there is no such path."""
        if not self.blocks(start, end):
            return []
        c = self._corners
        k = len(c)
        from_start = np.where(
            self._free(np.repeat([start], k, axis=0), c), np.hypot(*(c - start).T), np.inf
        )
        to_end = np.where(
            self._free(c, np.repeat([end], k, axis=0)), np.hypot(*(c - end).T), np.inf
        )
        # Dijkstra over the corners, from the start (node k) to the end (node k + 1).
        distance = np.full(k + 2, np.inf)
        previous = np.full(k + 2, -1)
        distance[k] = 0.0
        queue: list[tuple[float, int]] = [(0.0, k)]
        done = np.zeros(k + 2, bool)
        while queue:
            d, node = heapq.heappop(queue)
            if done[node]:
                continue
            done[node] = True
            if node == k + 1:
                break
            if node == k:
                reach = np.append(from_start, [np.inf, np.inf])
            else:
                reach = np.append(self._graph[node], [np.inf, to_end[node]])
            better = np.flatnonzero(d + reach < distance)
            distance[better] = d + reach[better]
            previous[better] = node
            for nxt in better:
                heapq.heappush(queue, (float(distance[nxt]), int(nxt)))
        if not np.isfinite(distance[k + 1]):
            raise PlanningError("the keep-outs leave the boat no way on from here", start)
        path: list[Point] = []
        node = int(previous[k + 1])
        while node != k:
            path.append((float(c[node, 0]), float(c[node, 1])))
            node = int(previous[node])
        return path[::-1]

    def at(self, points: FloatArray) -> list[int | None]:
        """For each (n, 2) point, the keep-out it lies on or just outside (a few
        ``ROUTE_MARGIN_M``): where a lane stops or a way round bends; None elsewhere."""
        if not self.polygons:
            return [None] * len(points)
        distance = shapely.distance(
            np.asarray(shapely.points(points), object)[:, None],
            np.array(self.polygons, dtype=object)[None, :],
        )
        nearest = np.argmin(distance, axis=1)
        close = distance[np.arange(len(points)), nearest] <= _MEET_M
        return [int(i) if ok else None for i, ok in zip(nearest, close, strict=True)]

    def loop(self, index: int, start: Point, onward: Point) -> list[Point]:
        """Once round keep-out ``index`` along its outline, from ``start`` (on it) back to
        it: the points after ``start``, ending with ``start``. Of the two ways round, the
        one whose last leg points more towards ``onward``, where the boat goes next."""
        outline = self.polygons[index].exterior
        s = float(shapely.line_locate_point(outline, shapely.Point(start)))
        ring = self.rings[index]
        steps = np.hypot(*(np.roll(ring, -1, axis=0) - ring).T)
        along = (np.concatenate([[0.0], np.cumsum(steps[:-1])]) - s) % float(outline.length)
        order = np.argsort(along)
        ccw = [(float(x), float(y)) for x, y in ring[order] if math.dist((x, y), start) > EPS_M]
        here, there = np.array(start), np.array(onward) - np.array(start)

        def heading(last: Point) -> float:
            d = here - np.array(last)
            return float(d @ there / np.hypot(*d))

        arrive_ccw, arrive_cw = heading(ccw[-1]), heading(ccw[0])
        way = ccw if arrive_ccw >= arrive_cw else ccw[::-1]
        return [*way, start]


def _grown(hole: FloatArray, clearance_m: float) -> shapely.Geometry:
    """The hole grown by ``clearance_m``: its Minkowski sum with a ``DISC_SIDES``-gon drawn
    round the clearance circle, the hole and the sum of each edge with it (the convex hull
    of the edge's ends moved by every corner of the polygon)."""
    if clearance_m <= 0:
        return shapely.Polygon(hole)
    k = np.arange(DISC_SIDES) * 2 * math.pi / DISC_SIDES
    disc = clearance_m / math.cos(math.pi / DISC_SIDES) * np.column_stack([np.cos(k), np.sin(k)])
    ends = np.concatenate([hole[:, None, :], np.roll(hole, -1, axis=0)[:, None, :]], axis=1)
    points = (ends[:, :, None, :] + disc[None, None, :, :]).reshape(len(hole), -1, 2)
    hulls = np.asarray(shapely.convex_hull(shapely.multipoints(points)), object)
    return shapely.union_all([shapely.Polygon(hole), *hulls])
