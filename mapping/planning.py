"""Lawnmower survey planning: an area in local metres to lanes, a path and its estimates.

Frames and units: positions are metres east/north in the survey's local grid frame
(``mapping.geo.LocalFrame``); bearings are radians clockwise from grid north; widths and
distances are metres. No files and no projections here: ``seamap.plan_files`` reads the
area, converts to and from WGS84 and writes the mission files.

The plan is a boustrophedon (lawnmower) coverage path (the family is surveyed by Galceran &
Carreras 2013, doi:10.1016/j.robot.2013.09.004) for a boat that must not enter keep-outs:

- Lanes are lines along ``bearing``, ``spacing`` apart across the area, centred on it, so
  each lane answers for a band of one spacing and the outermost lanes lie at most half a
  spacing inside the area's extreme points. The boat runs them in alternate directions.
- A lane is driven wherever it crosses the area, from ``lead_in`` before the boundary to
  ``lead_in`` after it (the boat is straight and steady when it enters, and the turn lies
  outside the area). Runs of one lane closer than twice the lead-in merge into one.
- Each hole (keep-out) is grown into a *keep-out hull*: the convex hull of the hole grown
  by ``clearance`` (overlapping hulls are merged). A lane ends where it meets a hull and
  goes on from where it leaves it. The boat never crosses a hull: any leg that would is
  routed along the hull's outline, the shorter way round, and the first time the boat meets
  a hull it goes once all the way round it first, which maps the ring between the lanes'
  ends and the hole that no lane can reach.
- Between the runs of one lane across a concave notch of the area the boat keeps to the
  lane line (a *transit*): the outside of the area is not a keep-out (lead-ins and turns lie
  there anyway); draw what must be avoided as holes.

Coverage model: the sonar's usable swath (``sonar_swath``) is a band ``half_width_m`` each
side of every leg the boat drives straight while mapping (lanes, transits, detours; not the
turns between lanes), from the leg's start to its end, plus a disc of that radius at each
waypoint between two mapping legs, where the boat turns and the fan sweeps round. With a
side overlap of at least 50% every seabed point is within the swath of two lanes run in
opposite directions, and the whole area is covered when its holes are convex and far apart.
What the convex keep-out hulls give away: water in a hole's concavity, and between holes
closer than about twice the clearance (one hull takes in both), is not driven; the coverage
estimate counts it as not covered. Draw such holes convex, or as one hole.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from mapping.polar import ground_to_polar
from mapping.preprocess import PreprocessParams, lit_min_range

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
Point = tuple[float, float]

MIN_LOOK_M = 1.0
"""A seabed point is in the usable swath when the boat sees it over at least this much of
its run (m): at 1 m/s and 10 Hz that is ten pings to blend and to register."""
TURN_RATE_RAD_S = 0.5
"""Duration model: each change of course of theta radians adds theta / TURN_RATE_RAD_S
seconds (the boat slows to turn; a 180-degree turnaround costs about 6 s)."""
MIN_RUN_M = 1.0
"""An area whose longest lane run is shorter than this is too small for one lane (m)."""
MAX_LANES = 5000
_HULL_SIDES = 16  # polygon standing in for the clearance circle round each hole vertex
_EPS = 1e-6  # metres: runs, gaps and crossings shorter than this are numerical noise


class PlanningError(ValueError):
    """An area or setting that cannot be planned; the message is one line."""

    def __init__(self, message: str, where: Point | None = None) -> None:
        super().__init__(message)
        self.where = where
        """The local (east, north) point the problem is at, when there is one."""


class LegKind(StrEnum):
    LANE = "lane"  # a run of a lane, lead-in to run-out
    TRANSIT = "transit"  # along the lane line between two runs of one lane (concave notch)
    DETOUR = "detour"  # along a keep-out hull's outline
    TURN = "turn"  # from the end of one lane to the start of the next


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
    that end lies on a keep-out hull (no lead-in there) rather than ``lead_in`` beyond the
    area's boundary (a lead-in is also cut short where a hull is closer than that)."""

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
    ``spacing_m`` apart; its runs and the legs of the whole path in driving order."""

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


@dataclass(frozen=True)
class Coverage:
    area_m2: float
    covered_m2: float

    @property
    def fraction(self) -> float:
        return self.covered_m2 / self.area_m2 if self.area_m2 > 0 else 0.0


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
        with np.errstate(divide="ignore", invalid="ignore"):
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


# --- the sonar's swath ---


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


# --- lanes ---


def _axes(bearing_rad: float) -> tuple[FloatArray, FloatArray]:
    """Unit vectors (east, north) along the lanes and across them (to the right)."""
    along = np.array([math.sin(bearing_rad), math.cos(bearing_rad)])
    across = np.array([math.cos(bearing_rad), -math.sin(bearing_rad)])
    return along, across


def _line_crossings(ring_uv: FloatArray, offsets: FloatArray) -> list[FloatArray]:
    """For each lane (across offset v), the sorted along-coordinates where the lane line
    crosses the ring; pairs of them bound the inside. Half-open at the vertices, so a lane
    through a vertex counts it once."""
    u1, v1 = ring_uv[:, 0], ring_uv[:, 1]
    u2, v2 = np.roll(u1, -1), np.roll(v1, -1)
    c = offsets[:, None]
    hit = ((v1 <= c) & (c < v2)) | ((v2 <= c) & (c < v1))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = u1 + (c - v1) * (u2 - u1) / (v2 - v1)
    return [np.sort(u[k, hit[k]]) for k in range(len(offsets))]


def _union(intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    for a, b in sorted(intervals):
        if b - a <= _EPS:
            continue
        if out and a <= out[-1][1] + _EPS:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _subtract(
    keep: list[tuple[float, float]], cut: list[tuple[float, float]]
) -> list[tuple[float, float, bool, bool]]:
    """keep minus cut, each piece tagged with whether each end was made by a cut."""
    pieces: list[tuple[float, float, bool, bool]] = []
    for a, b in keep:
        parts = [(a, b, False, False)]
        for k0, k1 in cut:
            nxt: list[tuple[float, float, bool, bool]] = []
            for p0, p1, t0, t1 in parts:
                if k1 <= p0 or k0 >= p1:
                    nxt.append((p0, p1, t0, t1))
                    continue
                if k0 > p0:
                    nxt.append((p0, k0, t0, True))
                if k1 < p1:
                    nxt.append((k1, p1, True, t1))
            parts = nxt
        pieces.extend(p for p in parts if p[1] - p[0] > _EPS)
    return pieces


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


def keepout_hulls(holes: list[FloatArray], clearance_m: float) -> list[FloatArray]:
    """Each hole grown by ``clearance_m`` and made convex (CCW rings); hulls that touch
    are merged. The growth uses a polygon round the clearance circle, so the hull keeps at
    least ``clearance_m`` from its hole everywhere."""
    k = np.arange(_HULL_SIDES) * 2 * math.pi / _HULL_SIDES
    r = clearance_m / math.cos(math.pi / _HULL_SIDES)
    disc = r * np.column_stack([np.cos(k), np.sin(k)]) if clearance_m > 0 else np.zeros((1, 2))
    clouds = [(h[:, None, :] + disc[None, :, :]).reshape(-1, 2) for h in holes]
    merged = True
    while merged:
        merged = False
        hulls = [convex_hull(c) for c in clouds]
        for i in range(len(hulls)):
            for j in range(i):
                if _convex_overlap(hulls[i], hulls[j]):
                    clouds[j] = np.concatenate([clouds[j], clouds[i]])
                    del clouds[i]
                    merged = True
                    break
            if merged:
                break
    return [convex_hull(c) for c in clouds]


def _convex_overlap(a: FloatArray, b: FloatArray) -> bool:
    """Separating-axis test for two convex rings (touching counts as overlap)."""
    for ring in (a, b):
        edges = np.roll(ring, -1, axis=0) - ring
        normals = np.column_stack([edges[:, 1], -edges[:, 0]])
        pa, pb = a @ normals.T, b @ normals.T
        if np.any(
            (pa.max(axis=0) < pb.min(axis=0) - 1e-9) | (pb.max(axis=0) < pa.min(axis=0) - 1e-9)
        ):
            return False
    return True


def _clip_to_hull(
    x: FloatArray, y: FloatArray, hull: FloatArray
) -> tuple[float, float, int, int] | None:
    """Where segment x-y runs through the inside of a convex CCW hull (Cyrus-Beck): the
    parameters (t_in, t_out) and the hull edges it enters and leaves by; None if it only
    misses or grazes the hull."""
    d = y - x
    length = float(np.hypot(*d))
    if length < _EPS:
        return None
    edges = np.roll(hull, -1, axis=0) - hull
    normals = np.column_stack([edges[:, 1], -edges[:, 0]])  # outward for a CCW ring
    normals /= np.hypot(*normals.T)[:, None]
    num = np.einsum("ij,ij->i", normals, x[None, :] - hull)  # > 0: x outside that edge
    den = normals @ d
    parallel = np.abs(den) < 1e-12 * length
    if np.any(parallel & (num >= -1e-7)):
        return None  # parallel to an edge, on or outside it
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -num / den
    entering, leaving = ~parallel & (den < 0), ~parallel & (den > 0)
    if not entering.any() or not leaving.any():
        return None
    e_in = int(np.flatnonzero(entering)[np.argmax(t[entering])])
    e_out = int(np.flatnonzero(leaving)[np.argmin(t[leaving])])
    t_in, t_out = max(float(t[e_in]), 0.0), min(float(t[e_out]), 1.0)
    if (t_out - t_in) * length <= 1e-4:
        return None
    return t_in, t_out, e_in, e_out


def _around(
    p: FloatArray, q: FloatArray, e_in: int, e_out: int, hull: FloatArray, full_loop: bool
) -> list[Point]:
    """Vertices from p (on hull edge e_in) to q (on edge e_out) along the hull's outline,
    the shorter way; with ``full_loop`` once all the way round first."""
    n = len(hull)
    ccw = [hull[(e_in + 1 + k) % n] for k in range((e_out - e_in) % n)]
    cw = [hull[(e_in - k) % n] for k in range((e_in - e_out) % n)]

    def length(path: list[FloatArray]) -> float:
        pts = np.array([p, *path, q])
        return float(np.hypot(*np.diff(pts, axis=0).T).sum())

    way, step = (ccw, 1) if length(ccw) <= length(cw) else (cw, -1)
    if full_loop:
        start = e_in + 1 if step == 1 else e_in
        loop = [hull[(start + step * k) % n] for k in range(n)]
        way = loop + way
    return [(float(v[0]), float(v[1])) for v in way]


def _route(
    start: Point,
    end: Point,
    kind: LegKind,
    lane: int,
    hulls: list[FloatArray],
    visited: set[int],
) -> list[Leg]:
    """Legs from start to end: straight, or round every keep-out hull in the way."""
    legs: list[Leg] = []
    here = np.array(start)
    goal = np.array(end)
    for _ in range(4 * len(hulls) + 1):
        hits = [(clip, i) for i, h in enumerate(hulls) if (clip := _clip_to_hull(here, goal, h))]
        if not hits:
            break
        (t_in, t_out, e_in, e_out), i = min(hits, key=lambda hit: hit[0][0])
        p = here + t_in * (goal - here)
        q = here + t_out * (goal - here)
        if t_in * float(np.hypot(*(goal - here))) > _EPS:
            legs.append(Leg(kind, lane, _pt(here), _pt(p)))
        points = [_pt(p), *_around(p, q, e_in, e_out, hulls[i], i not in visited), _pt(q)]
        visited.add(i)
        legs.extend(
            Leg(LegKind.DETOUR, lane, a, b)
            for a, b in itertools.pairwise(points)
            if math.dist(a, b) > _EPS
        )
        here = q
    if float(np.hypot(*(goal - here))) > _EPS:
        legs.append(Leg(kind, lane, _pt(here), _pt(goal)))
    return legs


def _pt(v: FloatArray) -> Point:
    return (float(v[0]), float(v[1]))


def area_width(area: Area, bearing_rad: float) -> float:
    """Width (m) of the area across lanes along ``bearing_rad``."""
    _, across = _axes(bearing_rad)
    v = np.concatenate([p.outer for p in area.polygons]) @ across
    return float(v.max() - v.min())


def lane_offsets(area: Area, bearing_rad: float, spacing_m: float) -> FloatArray:
    """Across offsets (m, to the right of the lane direction) of the lanes: ceil(width /
    spacing) lanes, centred, so the outermost lie at most half a spacing inside."""
    _, across = _axes(bearing_rad)
    v = np.concatenate([p.outer for p in area.polygons]) @ across
    width = float(v.max() - v.min())
    n = max(1, math.ceil(width / spacing_m - 1e-9))
    if n > MAX_LANES:
        raise PlanningError(
            f"the area needs {n} lanes at {spacing_m:g} m spacing (more than {MAX_LANES})"
        )
    margin = (width - (n - 1) * spacing_m) / 2
    offsets: FloatArray = float(v.min()) + margin + spacing_m * np.arange(n, dtype=np.float64)
    return offsets


def plan_path(
    area: Area,
    *,
    bearing_rad: float,
    spacing_m: float,
    lead_in_m: float,
    clearance_m: float,
    reverse_sweep: bool = False,
    reverse_first: bool = False,
) -> SurveyPlan:
    """The lawnmower over ``area`` with lanes along ``bearing_rad`` (see module doc).

    reverse_sweep: take the lanes from the left (looking along the bearing) instead of the
    right; reverse_first: run the first lane against the bearing. Raises PlanningError if
    no lane runs at least ``MIN_RUN_M`` over the area.
    """
    along, across = _axes(bearing_rad)
    offsets = lane_offsets(area, bearing_rad, spacing_m)
    hulls = keepout_hulls(area.holes, clearance_m)
    to_uv = np.column_stack([along, across])

    inside: list[list[tuple[float, float]]] = [[] for _ in offsets]
    for poly in area.polygons:
        for k, u in enumerate(_line_crossings(poly.outer @ to_uv, offsets)):
            inside[k].extend(zip(u[0::2], u[1::2], strict=True))
    keepout: list[list[tuple[float, float]]] = [[] for _ in offsets]
    for hull in hulls:
        for k, u in enumerate(_line_crossings(hull @ to_uv, offsets)):
            keepout[k].extend(zip(u[0::2], u[1::2], strict=True))

    order = list(range(len(offsets)))
    if reverse_sweep:
        order.reverse()
    longest = 0.0
    lanes: list[tuple[float, list[tuple[float, float, float, float, bool, bool]]]] = []
    for k in order:
        cut = _union(keepout[k])
        pieces = _subtract(_union(inside[k]), cut)
        if not pieces:
            continue
        longest = max(longest, max(b - a for a, b, _, _ in pieces))
        runs: list[tuple[float, float, float, float, bool, bool]] = []
        for a, b, cut_a, cut_b in pieces:
            start = a if cut_a else max([a - lead_in_m] + [k1 for _, k1 in cut if k1 <= a + _EPS])
            end = b if cut_b else min([b + lead_in_m] + [k0 for k0, _ in cut if k0 >= b - _EPS])
            if runs and start <= runs[-1][1] + _EPS:
                s0, _, a0, _, c0, _ = runs[-1]
                runs[-1] = (s0, end, a0, b, c0, cut_b)
            else:
                runs.append((start, end, a, b, cut_a, cut_b))
        lanes.append((float(offsets[k]), runs))
    if longest < MIN_RUN_M:
        raise PlanningError(
            f"the area is too small for one lane: its longest run along the lanes is "
            f"{longest:.2f} m (at least {MIN_RUN_M:g} m needed)"
        )

    def point(u: float, v: float) -> Point:
        return _pt(u * along + v * across)

    plan_runs: list[Run] = []
    legs: list[Leg] = []
    visited: set[int] = set()
    for index, (v, runs) in enumerate(lanes):
        forward = (index % 2 == 0) != reverse_first
        ordered = runs if forward else runs[::-1]
        for j, (s, e, a, b, cut_a, cut_b) in enumerate(ordered):
            if forward:
                run = Run(index, point(s, v), point(e, v), point(a, v), point(b, v), cut_a, cut_b)
            else:
                run = Run(index, point(e, v), point(s, v), point(b, v), point(a, v), cut_b, cut_a)
            if legs:
                kind = LegKind.TRANSIT if j > 0 else LegKind.TURN
                legs.extend(
                    _route(legs[-1].end, run.start, kind, index if j else -1, hulls, visited)
                )
            legs.extend(_route(run.start, run.end, LegKind.LANE, index, hulls, visited))
            plan_runs.append(run)
    bearing = bearing_rad if not reverse_first else bearing_rad + math.pi
    return SurveyPlan(
        bearing_rad=bearing % (2 * math.pi),
        spacing_m=spacing_m,
        lead_in_m=lead_in_m,
        clearance_m=clearance_m,
        runs=tuple(plan_runs),
        legs=tuple(legs),
        keepouts=tuple(hulls),
    )


def candidate_bearings(area: Area, step_deg: float = 5.0) -> list[float]:
    """Lane bearings (radians, 0..pi) worth trying: along each edge of the area's convex
    hull (rotating calipers: the narrowest width lies across one of them) and every
    ``step_deg`` degrees."""
    hull = convex_hull(np.concatenate([p.outer for p in area.polygons]))
    d = np.roll(hull, -1, axis=0) - hull
    edges = np.arctan2(d[:, 0], d[:, 1]) % math.pi
    grid = np.radians(np.arange(0.0, 180.0, step_deg))
    out: list[float] = []
    for b in np.concatenate([edges, grid]):
        if all(abs(math.remainder(b - o, math.pi)) > math.radians(0.25) for o in out):
            out.append(float(b))
    return out


def choose_bearing(area: Area, *, spacing_m: float, lead_in_m: float, clearance_m: float) -> float:
    """The lane bearing (radians, 0..pi) with the fewest runs (each costs a turn), then the
    narrowest width across the lanes (fewest, longest lanes), among ``candidate_bearings``.

    Time alone is not the measure: a slightly skewed set of lanes that clips the corners
    of a rectangle is a little shorter, but no surveyor wants it."""
    best: tuple[tuple[int, float], float] | None = None
    failure: PlanningError | None = None
    for bearing in candidate_bearings(area):
        try:
            plan = plan_path(
                area,
                bearing_rad=bearing,
                spacing_m=spacing_m,
                lead_in_m=lead_in_m,
                clearance_m=clearance_m,
            )
        except PlanningError as exc:
            failure = exc
            continue
        cost = (len(plan.runs), round(area_width(area, bearing), 3))
        if best is None or cost < best[0]:
            best = (cost, bearing)
    if best is None:
        assert failure is not None
        raise failure
    return best[1]


ENTRY_CORNERS = ("nw", "ne", "sw", "se", "auto")


def plan_survey(
    area: Area,
    *,
    spacing_m: float,
    bearing_rad: float | None = None,
    lead_in_m: float = 5.0,
    clearance_m: float = 2.0,
    speed_mps: float = 1.0,
    entry: str = "auto",
    home: Point | None = None,
) -> SurveyPlan:
    """The whole plan: lane bearing (given, or ``choose_bearing``), then the lane order.

    entry: the corner of the area (grid north-west, ...) nearest which the path starts;
    "auto": nearest ``home`` if given, else the quickest of the four ways to sweep.
    """
    validate_area(area)
    if spacing_m <= 0:
        raise PlanningError(f"lane spacing must be positive, got {spacing_m:g} m")
    if lead_in_m < 0 or clearance_m < 0:
        raise PlanningError("lead-in and clearance must not be negative")
    if entry not in ENTRY_CORNERS:
        raise PlanningError(f"entry {entry!r} is not one of {', '.join(ENTRY_CORNERS)}")
    if bearing_rad is None:
        bearing_rad = choose_bearing(
            area,
            spacing_m=spacing_m,
            lead_in_m=lead_in_m,
            clearance_m=clearance_m,
        )
    options = [
        plan_path(
            area,
            bearing_rad=bearing_rad,
            spacing_m=spacing_m,
            lead_in_m=lead_in_m,
            clearance_m=clearance_m,
            reverse_sweep=sweep,
            reverse_first=first,
        )
        for sweep in (False, True)
        for first in (False, True)
    ]
    if entry == "auto" and home is None:
        return min(options, key=lambda plan: plan.duration_s(speed_mps))
    if entry == "auto":
        assert home is not None
        target = home
    else:
        e0, n0, e1, n1 = area.bounds
        target = (e0 if entry[1] == "w" else e1, n1 if entry[0] == "n" else n0)
    return min(options, key=lambda plan: math.dist(plan.legs[0].start, target))


# --- coverage ---


MAPPING_LEGS = (LegKind.LANE, LegKind.TRANSIT, LegKind.DETOUR)


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
        if length > _EPS:
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
