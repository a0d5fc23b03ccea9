"""Lawnmower survey planning: an area in local metres to lanes, a path and its estimates.

Frames and units: positions are metres east/north in the survey's local grid frame
(``mapping.geo.LocalFrame``); bearings are radians clockwise from grid north; widths and
distances are metres, areas square metres.

The plan is a boustrophedon (lawnmower) coverage path (the family is surveyed by Galceran &
Carreras 2013, doi:10.1016/j.robot.2013.09.004) for a boat that must not enter keep-outs:

- Each hole is grown by ``clearance`` into a *keep-out* of the hole's own shape
  (``planning.keepouts``); grown holes that overlap are one keep-out.
- Lanes are lines along ``bearing``, ``spacing`` apart across the area, centred on it, so
  each lane answers for a band of one spacing and the outermost lanes lie at most half a
  spacing inside the area's extreme points. The boat runs them in alternate directions.
- A lane is driven wherever it crosses the area less the keep-outs (shapely cuts the
  lines), from ``lead_in`` before the area's boundary to ``lead_in`` after it (the boat is
  straight and steady when it enters, and the turn lies outside the area); where a
  keep-out stops it, it ends on the keep-out's outline and goes on where it leaves it.
  Runs of one lane closer than twice the lead-in merge into one. A keep-out's concavity
  wider than twice the clearance gets lanes into it like any other water.
- Every leg between two runs is the shortest path that enters no keep-out: straight when
  it can be, else round the keep-outs through their corners (``Keepouts.route``: a
  visibility graph and Dijkstra), just clear of their outlines. The legs of a way round
  are *detours*, which map like lanes (the boat drives them straight). Between the runs
  of one lane across a concave notch of the area the straight way is the lane line itself
  (a *transit*): the outside of the area is not a keep-out (lead-ins and turns lie there
  anyway); draw what must be avoided as holes.
- *Once round*: the boat meets a keep-out where a lane stops at it or a way round bends at
  it. The first time it meets one it may go once round it along its outline, which maps
  the ring of water between the lanes' ends and the hole (lanes stop a clearance short of
  the hole and their swath has square ends). It does when that loop would map more than
  ``LOOP_MIN_M2`` of the area that the rest of the path leaves unmapped, judged with the
  sonar's usable half swath, keep-out by keep-out in the order the boat meets them, each
  loop kept counting as mapped for the next. Where the lanes and the ways round already
  map all round a hole, which the shortest ways round between lane ends along its
  outline mostly do, the loop would be time for nothing and is left out.

Coverage model (``planning.sweep``): the sonar's usable swath (``sonar_swath``) is a band
``half_width_m`` each side of every leg the boat drives straight while mapping, plus a disc
of that radius at each waypoint between two mapping legs. With a side overlap of at least
50% every seabed point is within the swath of two lanes run in opposite directions, and the
water round the holes, in their bays and between them is mapped by the lanes that reach
it, the ways round and the loops. What is left out: water the boat cannot enter (between
holes closer than twice the clearance, in a bay whose mouth is narrower than that, and
all that keep-outs close in) is mapped only as far as the swath reaches into it from
outside. The path is planned lane by lane: the runs of lanes into a bay are reached one
after another, each by a way round (no decomposition of the area into cells, each swept
on its own).

The lanes sweep any region, not only a whole area: ``planning.replan`` sweeps the gaps a
survey left (each grown a little and cut to the area) with these rules and its area's
keep-outs, the loops round keep-outs judged by what they map of the gaps.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import numpy.typing as npt
import shapely

from planning.area import EPS_M, Area, PlanningError, Point, validate_area
from planning.keepouts import Keepouts
from planning.plan import Leg, LegKind, Run, SurveyPlan
from planning.sweep import swath_cover

FloatArray = npt.NDArray[np.float64]

MIN_RUN_M = 1.0
"""An area whose longest lane run is shorter than this is too small for one lane (m)."""
MAX_LANES = 5000
LOOP_MIN_M2 = 0.05
"""Once round a keep-out is driven when it maps more of the area than this (m²) that the
rest of the path leaves unmapped; less is the swath's discs drawn as polygons, not water."""
ENTRY_CORNERS = ("nw", "ne", "sw", "se", "auto")

Sweepable = Area | shapely.Geometry
"""What the lanes sweep: a survey area, or any shapely (Multi)Polygon in the same local
metres (a gap of a survey grown and cut to its area, ``planning.replan``), whose keep-outs
are then given."""

# A lane run: its start and end (along the lane, lead-ins included), where it enters and
# leaves the area, and whether the start and end were made by a keep-out.
_Run = tuple[float, float, float, float, bool, bool]


# --- lanes ---


def _axes(bearing_rad: float) -> tuple[FloatArray, FloatArray]:
    """Unit vectors (east, north) along the lanes and across them (to the right)."""
    along = np.array([math.sin(bearing_rad), math.cos(bearing_rad)])
    across = np.array([math.cos(bearing_rad), -math.sin(bearing_rad)])
    return along, across


def _lane_intervals(
    geometry: shapely.Geometry, along: FloatArray, across: FloatArray, offsets: FloatArray
) -> list[list[tuple[float, float]]]:
    """For each lane (across offset v), the (from, to) along-coordinates of the pieces of
    the lane line inside ``geometry`` (a point where it only touches is no piece)."""
    out: list[list[tuple[float, float]]] = [[] for _ in offsets]
    if shapely.is_empty(geometry):
        return out
    e0, n0, e1, n1 = shapely.bounds(geometry)
    corners = np.array([(e0, n0), (e0, n1), (e1, n0), (e1, n1)]) @ along
    u = np.array([corners.min() - 1.0, corners.max() + 1.0])
    ends = u[None, :, None] * along + offsets[:, None, None] * across  # (lane, end, east/north)
    pieces, lane = shapely.get_parts(
        shapely.intersection(shapely.linestrings(ends), geometry), return_index=True
    )
    line = shapely.get_type_id(pieces) == shapely.GeometryType.LINESTRING
    xy, piece = shapely.get_coordinates(pieces[line], return_index=True)
    position = xy @ along
    lo = np.full(int(line.sum()), np.inf)
    hi = np.full(int(line.sum()), -np.inf)
    np.minimum.at(lo, piece, position)
    np.maximum.at(hi, piece, position)
    for k, a, b in zip(lane[line], lo, hi, strict=True):
        out[int(k)].append((float(a), float(b)))
    return out


def _union(intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    for a, b in sorted(intervals):
        if b - a <= EPS_M:
            continue
        if out and a <= out[-1][1] + EPS_M:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _geometry(area: Sweepable) -> shapely.Geometry:
    return area.geometry if isinstance(area, Area) else area


def _outline_points(area: Sweepable) -> FloatArray:
    """(n, 2) vertices whose extremes are the region's: an area's outer rings, or every
    vertex of a geometry (its interior rings lie inside)."""
    if isinstance(area, Area):
        return np.concatenate([p.outer for p in area.polygons])
    points: FloatArray = shapely.get_coordinates(area)
    return points


def area_width(area: Sweepable, bearing_rad: float) -> float:
    """Width (m) of the area across lanes along ``bearing_rad``."""
    _, across = _axes(bearing_rad)
    v = _outline_points(area) @ across
    return float(v.max() - v.min())


def lane_offsets(area: Sweepable, bearing_rad: float, spacing_m: float) -> FloatArray:
    """Across offsets (m, to the right of the lane direction) of the lanes: ceil(width /
    spacing) lanes, centred, so the outermost lie at most half a spacing inside."""
    _, across = _axes(bearing_rad)
    v = _outline_points(area) @ across
    width = float(v.max() - v.min())
    n = max(1, math.ceil(width / spacing_m - 1e-9))
    if n > MAX_LANES:
        raise PlanningError(
            f"the area needs {n} lanes at {spacing_m:g} m spacing (more than {MAX_LANES})"
        )
    margin = (width - (n - 1) * spacing_m) / 2
    offsets: FloatArray = float(v.min()) + margin + spacing_m * np.arange(n, dtype=np.float64)
    return offsets


def _lane_runs(
    area: Sweepable,
    keepouts: Keepouts,
    *,
    bearing_rad: float,
    spacing_m: float,
    lead_in_m: float,
    reverse_sweep: bool = False,
) -> list[tuple[float, list[_Run]]]:
    """The lanes in sweep order, each its across offset and its runs in the bearing's
    direction (the module doc's rules). Raises PlanningError if no lane runs at least
    ``MIN_RUN_M`` over the area."""
    along, across = _axes(bearing_rad)
    offsets = lane_offsets(area, bearing_rad, spacing_m)
    free = shapely.difference(_geometry(area), keepouts.geometry)
    inside = _lane_intervals(free, along, across, offsets)
    blocked = _lane_intervals(keepouts.geometry, along, across, offsets)
    order = range(len(offsets) - 1, -1, -1) if reverse_sweep else range(len(offsets))
    longest = 0.0
    lanes: list[tuple[float, list[_Run]]] = []
    for k in order:
        pieces = _union(inside[k])
        if not pieces:
            continue
        cut = _union(blocked[k])
        longest = max(longest, max(b - a for a, b in pieces))
        runs: list[_Run] = []
        for a, b in pieces:
            cut_a = any(abs(k1 - a) <= EPS_M for _, k1 in cut)
            cut_b = any(abs(k0 - b) <= EPS_M for k0, _ in cut)
            start = a if cut_a else max([a - lead_in_m] + [k1 for _, k1 in cut if k1 <= a])
            end = b if cut_b else min([b + lead_in_m] + [k0 for k0, _ in cut if k0 >= b])
            if runs and start <= runs[-1][1] + EPS_M:
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
    return lanes


# --- the path ---


def connect(start: Point, end: Point, kind: LegKind, lane: int, keepouts: Keepouts) -> list[Leg]:
    """Legs from start to end: one straight leg of ``kind``, or the way round the
    keep-outs in between (detours)."""
    bends = keepouts.route(start, end)
    if not bends:
        return [Leg(kind, lane, start, end)] if math.dist(start, end) > EPS_M else []
    return [
        Leg(LegKind.DETOUR, lane, a, b)
        for a, b in itertools.pairwise([start, *bends, end])
        if math.dist(a, b) > EPS_M
    ]


def once_round(
    legs: list[Leg], area: Sweepable, keepouts: Keepouts, half_width_m: float
) -> list[Leg]:
    """The path with a loop round each keep-out where the boat first meets it (at the end
    of a leg), for the keep-outs whose loop maps more than ``LOOP_MIN_M2`` of ``area`` the
    path leaves unmapped (the module doc's *once round*)."""
    if not legs or not keepouts.polygons:
        return legs
    first: dict[int, int] = {}  # keep-out: the leg at whose end the boat first meets it
    for i, k in enumerate(keepouts.at(np.array([leg.end for leg in legs]))):
        if k is not None and k not in first:
            first[k] = i
    region = _geometry(area)
    covered = shapely.intersection(swath_cover(legs, half_width_m), region)
    loops: dict[int, list[Leg]] = {}
    for k, i in sorted(first.items(), key=lambda item: item[1]):
        here = legs[i].end
        onward = legs[i + 1].end if i + 1 < len(legs) else here
        points = [here, *keepouts.loop(k, here, onward)]
        loop = [
            Leg(LegKind.DETOUR, legs[i].lane, a, b)
            for a, b in itertools.pairwise(points)
            if math.dist(a, b) > EPS_M
        ]
        mapped = shapely.intersection(swath_cover(loop, half_width_m), region)
        if shapely.area(shapely.difference(mapped, covered)) > LOOP_MIN_M2:
            loops[i] = loop
            covered = shapely.union(covered, mapped)
    return [step for i, leg in enumerate(legs) for step in [leg, *loops.get(i, [])]]


def plan_path(
    area: Sweepable,
    *,
    bearing_rad: float,
    spacing_m: float,
    lead_in_m: float,
    clearance_m: float,
    reverse_sweep: bool = False,
    reverse_first: bool = False,
    half_width_m: float | None = None,
    keepouts: Keepouts | None = None,
    loops: bool = True,
) -> SurveyPlan:
    """The lawnmower over ``area`` with lanes along ``bearing_rad`` (see module doc).

    reverse_sweep: take the lanes from the left (looking along the bearing) instead of the
    right; reverse_first: run the first lane against the bearing. half_width_m: the usable
    half swath the loops round keep-outs are judged by (default ``spacing_m``, as at 50 %
    side overlap). keepouts: ``Keepouts.around(area.holes, clearance_m)``, if already
    built; needed when ``area`` is a geometry (a gap), not an ``Area``. loops: go once
    round keep-outs (``once_round``); False leaves that to the caller, for the path it
    makes of this one (``planning.replan``). Raises PlanningError if no lane runs at
    least ``MIN_RUN_M`` over the area.
    """
    along, across = _axes(bearing_rad)
    keepouts = _keepouts_of(area, clearance_m, keepouts)
    lanes = _lane_runs(
        area,
        keepouts,
        bearing_rad=bearing_rad,
        spacing_m=spacing_m,
        lead_in_m=lead_in_m,
        reverse_sweep=reverse_sweep,
    )

    def point(u: float, v: float) -> Point:
        xy = u * along + v * across
        return (float(xy[0]), float(xy[1]))

    plan_runs: list[Run] = []
    legs: list[Leg] = []
    for index, (v, runs) in enumerate(lanes):
        forward = (index % 2 == 0) != reverse_first
        ordered = runs if forward else runs[::-1]
        for j, (s, e, a, b, cut_a, cut_b) in enumerate(ordered):
            if forward:
                run = Run(index, point(s, v), point(e, v), point(a, v), point(b, v), cut_a, cut_b)
            else:
                run = Run(index, point(e, v), point(s, v), point(b, v), point(a, v), cut_b, cut_a)
            if legs:
                kind, lane = (LegKind.TRANSIT, index) if j > 0 else (LegKind.TURN, -1)
                legs.extend(connect(legs[-1].end, run.start, kind, lane, keepouts))
            legs.append(Leg(LegKind.LANE, index, run.start, run.end))
            plan_runs.append(run)
    if loops:
        legs = once_round(legs, area, keepouts, spacing_m if half_width_m is None else half_width_m)
    bearing = bearing_rad if not reverse_first else bearing_rad + math.pi
    return SurveyPlan(
        bearing_rad=bearing % (2 * math.pi),
        spacing_m=spacing_m,
        lead_in_m=lead_in_m,
        clearance_m=clearance_m,
        runs=tuple(plan_runs),
        legs=tuple(legs),
        keepouts=keepouts.rings,
    )


def _keepouts_of(area: Sweepable, clearance_m: float, keepouts: Keepouts | None) -> Keepouts:
    if keepouts is not None:
        return keepouts
    if not isinstance(area, Area):
        raise TypeError("the keep-outs are needed to sweep a geometry other than an Area")
    return Keepouts.around(area.holes, clearance_m)


# --- the bearing and the whole plan ---


def candidate_bearings(area: Sweepable, step_deg: float = 5.0) -> list[float]:
    """Lane bearings (radians, 0..pi) worth trying: along each edge of the area's convex
    hull (rotating calipers: the narrowest width lies across one of them) and every
    ``step_deg`` degrees."""
    hull = shapely.convex_hull(shapely.multipoints(_outline_points(area)))
    ring = shapely.get_coordinates(hull)
    d = np.diff(ring, axis=0)
    edges = np.arctan2(d[:, 0], d[:, 1]) % math.pi
    grid = np.radians(np.arange(0.0, 180.0, step_deg))
    out: list[float] = []
    for b in np.concatenate([edges, grid]):
        if all(abs(math.remainder(b - o, math.pi)) > math.radians(0.25) for o in out):
            out.append(float(b))
    return out


def choose_bearing(
    area: Sweepable,
    *,
    spacing_m: float,
    lead_in_m: float,
    clearance_m: float,
    keepouts: Keepouts | None = None,
) -> float:
    """The lane bearing (radians, 0..pi) with the fewest runs (each costs a turn), then the
    narrowest width across the lanes (fewest, longest lanes), among ``candidate_bearings``.

    Time alone is not the measure: a slightly skewed set of lanes that clips the corners
    of a rectangle is a little shorter, but no surveyor wants it. keepouts: as for
    ``plan_path``."""
    keepouts = _keepouts_of(area, clearance_m, keepouts)
    best: tuple[tuple[int, float], float] | None = None
    failure: PlanningError | None = None
    for bearing in candidate_bearings(area):
        try:
            lanes = _lane_runs(
                area, keepouts, bearing_rad=bearing, spacing_m=spacing_m, lead_in_m=lead_in_m
            )
        except PlanningError as exc:
            failure = exc
            continue
        cost = (sum(len(runs) for _, runs in lanes), round(area_width(area, bearing), 3))
        if best is None or cost < best[0]:
            best = (cost, bearing)
    if best is None:
        assert failure is not None
        raise failure
    return best[1]


def sweep_options(
    area: Sweepable,
    *,
    spacing_m: float,
    bearing_rad: float | None = None,
    lead_in_m: float = 5.0,
    clearance_m: float = 2.0,
    half_width_m: float | None = None,
    keepouts: Keepouts | None = None,
    loops: bool = True,
) -> list[SurveyPlan]:
    """The four ways to sweep ``area`` (from either side, the first lane either way) with
    lanes along ``bearing_rad`` (given, or ``choose_bearing``'s). keepouts, loops: as for
    ``plan_path``. Raises PlanningError if no lane runs at least ``MIN_RUN_M`` over it."""
    keepouts = _keepouts_of(area, clearance_m, keepouts)
    if bearing_rad is None:
        bearing_rad = choose_bearing(
            area,
            spacing_m=spacing_m,
            lead_in_m=lead_in_m,
            clearance_m=clearance_m,
            keepouts=keepouts,
        )
    return [
        plan_path(
            area,
            bearing_rad=bearing_rad,
            spacing_m=spacing_m,
            lead_in_m=lead_in_m,
            clearance_m=clearance_m,
            reverse_sweep=sweep,
            reverse_first=first,
            half_width_m=half_width_m,
            keepouts=keepouts,
            loops=loops,
        )
        for sweep in (False, True)
        for first in (False, True)
    ]


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
    half_width_m: float | None = None,
) -> SurveyPlan:
    """The whole plan: lane bearing (given, or ``choose_bearing``), then the lane order.

    entry: the corner of the area (grid north-west, ...) nearest which the path starts;
    "auto": nearest ``home`` if given, else the quickest of the four ways to sweep.
    half_width_m: the sonar's usable half swath (default ``spacing_m``: 50 % overlap).
    """
    validate_area(area)
    if spacing_m <= 0:
        raise PlanningError(f"lane spacing must be positive, got {spacing_m:g} m")
    if lead_in_m < 0 or clearance_m < 0:
        raise PlanningError("lead-in and clearance must not be negative")
    if entry not in ENTRY_CORNERS:
        raise PlanningError(f"entry {entry!r} is not one of {', '.join(ENTRY_CORNERS)}")
    options = sweep_options(
        area,
        spacing_m=spacing_m,
        bearing_rad=bearing_rad,
        lead_in_m=lead_in_m,
        clearance_m=clearance_m,
        half_width_m=half_width_m,
    )
    if entry == "auto" and home is None:
        return min(options, key=lambda plan: plan.duration_s(speed_mps))
    if entry == "auto":
        assert home is not None
        target = home
    else:
        e0, n0, e1, n1 = area.bounds
        target = (e0 if entry[1] == "w" else e1, n1 if entry[0] == "n" else n0)
    return min(options, key=lambda plan: math.dist(plan.legs[0].start, target))
