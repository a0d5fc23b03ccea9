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

Coverage model (``planning.coverage``): the sonar's usable swath (``sonar_swath``) is a band
``half_width_m`` each side of every leg the boat drives straight while mapping, plus a disc
of that radius at each waypoint between two mapping legs. With a side overlap of at least
50% every seabed point is within the swath of two lanes run in opposite directions, and the
whole area is covered when its holes are convex and far apart.
What the convex keep-out hulls give away: water in a hole's concavity, and between holes
closer than about twice the clearance (one hull takes in both), is not driven; the coverage
estimate counts it as not covered. Draw such holes convex, or as one hole.

This module lays the lanes over the area and routes the path; what it builds on lives
beside it: ``planning.area`` (the area, its validation, convex hulls),
``planning.keepouts`` (keep-out hulls and the way round them), ``planning.swath`` (the sonar's
usable swath), ``planning.plan`` (the planned path, its length and duration) and
``planning.coverage`` (the coverage estimate). Their public names are importable from here
too, so ``planning.lawnmower`` is the one import for survey planning.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import numpy.typing as npt

from planning.area import (
    EPS_M,
    Area,
    PlanningError,
    Point,
    Polygon,
    clean_ring,
    convex_hull,
    ring_area,
    validate_area,
)
from planning.coverage import MAPPING_LEGS, Coverage, coverage, swept
from planning.keepouts import around_hull, clip_to_hull, keepout_hulls
from planning.plan import TURN_RATE_RAD_S, Leg, LegKind, Run, SurveyPlan
from planning.swath import MIN_LOOK_M, Swath, sonar_swath

__all__ = [
    "ENTRY_CORNERS",
    "MAPPING_LEGS",
    "MAX_LANES",
    "MIN_LOOK_M",
    "MIN_RUN_M",
    "TURN_RATE_RAD_S",
    "Area",
    "Coverage",
    "Leg",
    "LegKind",
    "PlanningError",
    "Polygon",
    "Run",
    "SurveyPlan",
    "Swath",
    "area_width",
    "candidate_bearings",
    "choose_bearing",
    "clean_ring",
    "convex_hull",
    "coverage",
    "keepout_hulls",
    "lane_offsets",
    "plan_path",
    "plan_survey",
    "ring_area",
    "sonar_swath",
    "swept",
    "validate_area",
]

FloatArray = npt.NDArray[np.float64]

MIN_RUN_M = 1.0
"""An area whose longest lane run is shorter than this is too small for one lane (m)."""
MAX_LANES = 5000


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
        if b - a <= EPS_M:
            continue
        if out and a <= out[-1][1] + EPS_M:
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
        pieces.extend(p for p in parts if p[1] - p[0] > EPS_M)
    return pieces


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
        hits = [(clip, i) for i, h in enumerate(hulls) if (clip := clip_to_hull(here, goal, h))]
        if not hits:
            break
        (t_in, t_out, e_in, e_out), i = min(hits, key=lambda hit: hit[0][0])
        p = here + t_in * (goal - here)
        q = here + t_out * (goal - here)
        if t_in * float(np.hypot(*(goal - here))) > EPS_M:
            legs.append(Leg(kind, lane, _pt(here), _pt(p)))
        points = [_pt(p), *around_hull(p, q, e_in, e_out, hulls[i], i not in visited), _pt(q)]
        visited.add(i)
        legs.extend(
            Leg(LegKind.DETOUR, lane, a, b)
            for a, b in itertools.pairwise(points)
            if math.dist(a, b) > EPS_M
        )
        here = q
    if float(np.hypot(*(goal - here))) > EPS_M:
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
            start = a if cut_a else max([a - lead_in_m] + [k1 for _, k1 in cut if k1 <= a + EPS_M])
            end = b if cut_b else min([b + lead_in_m] + [k0 for k0, _ in cut if k0 >= b - EPS_M])
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
