"""Re-planning what a survey missed: lanes over its gaps only, in the order that shortens
the way from where the boat is.

Frames and units: as ``planning.lawnmower``: metres east/north in the local grid frame,
bearings radians clockwise from grid north, durations seconds, areas square metres.

- *Targets*: each gap (``planning.gaps.area_gaps``) grown by ``margin_m`` (default
  ``GAP_MARGIN`` of the usable half swath, 0.41 m with the default sonar) and cut to the
  area, holes left out. The growth puts the lanes' ends and the outermost lanes a little
  beyond the gap's outline, which follows the coverage cells' edges, and gives a gap
  lying against a keep-out some water outside it for a lane.
- A group of targets is swept as ``planning.lawnmower`` sweeps an area, with its rules
  and the area's keep-outs: lanes ``spacing_m`` apart across the targets (not the water
  between them), each run a lead-in beyond a target's outline or stopped by a keep-out,
  runs of one lane closer than twice the lead-in merged, farther ones joined by a
  transit, ways round the keep-outs. Its bearing is the one with the fewest runs, then
  the narrowest width (``choose_bearing``), chosen for each group.
- *Groups*: each gap starts alone; pairs whose targets lie within ``join_m`` (default
  twice the lead-in plus the swath: closer, their lead-ins or swaths overlap) are tried
  as one, closest first, and joined when one sweep of both takes no longer than the two
  apart plus the straight way between them and maps as much of them (lanes laid across
  both can pass either side of a small gap that lanes of its own would cross). Gaps
  along one lane line so become one lane, a transit between; side by side, one set of
  lanes.
- *Order*: each group can be swept eight ways (from either side, the first lane either
  way, and each of those backwards). Greedy nearest-next from ``start``, then 2-opt
  (Croes 1958, doi:10.1287/opre.6.6.791: a stretch of the order reversed, each group in
  it swept backwards) and each group's way chosen again for its neighbours, until
  neither shortens the path. A heuristic, not the shortest order (a travelling salesman
  problem), and exact enough for the tens of gaps a survey leaves. The way from one
  group to the next is measured straight, or round the keep-outs where they block it.
- *Legs between groups* go by ``Keepouts.route`` (``lawnmower.connect``): straight when
  free, else round the keep-outs through their corners. The way from ``start`` to the
  first run is not part of the path (the boat is there), but the corners it bends at
  are: the path's first waypoints, so the autopilot's straight leg to its first
  waypoint enters no keep-out either (unless ``start`` lies in one: then straight out).
- *Once round*: on the whole path, the way from ``start`` counted (``lawnmower.once_round``):
  the boat goes once round a keep-out where it first meets it when that maps more than
  ``LOOP_MIN_M2`` of the gaps' targets the rest of the path leaves unmapped. On the whole
  path, not group by group: a group swept backwards ends where it began, and which
  keep-out the boat meets first is known only in the end.
- A gap no lane of ``MIN_RUN_M`` reaches (water within the clearance of a hole, which
  only the swath from outside can map) is *unreachable*: listed, not swept.

What the plan covers of the gaps is ``planning.sweep``'s swath model over the path.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import shapely

from planning.area import Area, PlanningError, Point, validate_area
from planning.keepouts import Keepouts
from planning.lawnmower import LOOP_MIN_M2, MIN_RUN_M, connect, once_round, sweep_options
from planning.plan import Leg, LegKind, Run, SurveyPlan
from planning.sweep import Coverage, swath_cover

GAP_MARGIN = 0.1
"""Each gap is grown by this fraction of the sonar's usable half swath into its target."""
MAX_ROUNDS = 100
"""Improvement rounds of the order at most (each shortens it; few are ever needed)."""

_WAYS = 4  # the lawnmower's ways to sweep a region; each also backwards: way k + _WAYS


@dataclass(frozen=True)
class GapGroup:
    """Gaps swept together: their indices into the gaps planned, the first lane's bearing
    as driven (radians, grid), and the group's lanes and runs."""

    gaps: tuple[int, ...]
    bearing_rad: float
    lanes: int
    runs: int


@dataclass(frozen=True, eq=False)
class GapPlan:
    """The re-plan: the whole path (``plan``: lanes numbered in driving order across the
    groups), its groups in driving order, the gaps no lane reaches, the length (m) of the
    way from the start to the first run, and how much of the gaps (all of them) the path
    maps."""

    plan: SurveyPlan
    groups: tuple[GapGroup, ...]
    unreachable: tuple[int, ...]
    approach_m: float
    coverage: Coverage


def plan_gaps(
    area: Area,
    gaps: Sequence[shapely.Polygon],
    *,
    start: Point,
    spacing_m: float,
    half_width_m: float,
    lead_in_m: float = 5.0,
    clearance_m: float = 2.0,
    speed_mps: float = 1.0,
    margin_m: float | None = None,
    join_m: float | None = None,
) -> GapPlan:
    """Lanes over ``gaps`` (polygons in ``area``'s local metres) from ``start`` (see the
    module doc). spacing_m: between lanes; half_width_m: the sonar's usable half swath;
    lead_in_m, clearance_m: as for ``plan_survey``; speed_mps: for the durations that
    decide groups and order. Raises PlanningError if there is no gap or no lane reaches
    any."""
    validate_area(area)
    if not (spacing_m > 0 and half_width_m > 0 and speed_mps > 0):
        raise PlanningError("lane spacing, swath and speed must be positive")
    if lead_in_m < 0 or clearance_m < 0:
        raise PlanningError("lead-in and clearance must not be negative")
    if not gaps:
        raise PlanningError("no gap to plan")
    keepouts = Keepouts.around(area.holes, clearance_m)
    margin = GAP_MARGIN * half_width_m if margin_m is None else margin_m
    join = 2 * lead_in_m + 2 * half_width_m if join_m is None else join_m
    targets = [shapely.intersection(shapely.buffer(gap, margin), area.geometry) for gap in gaps]

    def sweeps(members: frozenset[int]) -> list[SurveyPlan] | None:
        region = shapely.union_all([targets[i] for i in sorted(members)])
        try:
            ways = sweep_options(
                region,
                spacing_m=spacing_m,
                lead_in_m=lead_in_m,
                clearance_m=clearance_m,
                half_width_m=half_width_m,
                keepouts=keepouts,
                loops=False,
            )
        except PlanningError:
            return None
        return ways + [_backwards(way) for way in ways]

    groups, unreachable = _groups(gaps, targets, sweeps, join, speed_mps, half_width_m)
    if not groups:
        raise PlanningError(
            f"no lane reaches any of the {len(gaps)} gaps: they lie within the clearance "
            f"({clearance_m:g} m) of a hole, or are too small for a run of {MIN_RUN_M:g} m"
        )
    transit = _transit(keepouts)
    ways = list(groups.values())
    order = _order(ways, start, transit, speed_mps)
    legs, runs, numbered, approach_m = _assemble(ways, order, start, keepouts)
    region = shapely.union_all([targets[i] for group in groups for i in group])
    legs = _once_round(legs, start, region, keepouts, half_width_m)
    first = ways[order[0][0]][order[0][1]]
    plan = SurveyPlan(
        bearing_rad=first.bearing_rad,
        spacing_m=spacing_m,
        lead_in_m=lead_in_m,
        clearance_m=clearance_m,
        runs=tuple(runs),
        legs=tuple(legs),
        keepouts=keepouts.rings,
    )
    members = list(groups)
    found = tuple(
        GapGroup(tuple(sorted(members[g])), ways[g][k].bearing_rad, lanes, len(ways[g][k].runs))
        for (g, k), lanes in zip(order, numbered, strict=True)
    )
    missed = shapely.union_all(list(gaps))
    mapped = shapely.intersection(swath_cover(plan.legs, half_width_m), missed)
    cover = Coverage(float(shapely.area(missed)), float(shapely.area(mapped)))
    return GapPlan(plan, found, tuple(unreachable), approach_m, cover)


# --- groups ---


def _groups(
    gaps: Sequence[shapely.Polygon],
    targets: Sequence[shapely.Geometry],
    sweeps: Callable[[frozenset[int]], list[SurveyPlan] | None],
    join_m: float,
    speed_mps: float,
    half_width_m: float,
) -> tuple[dict[frozenset[int], list[SurveyPlan]], list[int]]:
    """The groups (their gaps: their ways to sweep) and the unreachable gaps. Two groups
    are joined when one sweep of both takes no longer than the two apart and the way
    between, and maps as much of their gaps (less ``LOOP_MIN_M2``): lanes laid across
    both can pass either side of a small gap that lanes of its own would cross."""
    group_of: dict[int, frozenset[int]] = {}
    ways: dict[frozenset[int], list[SurveyPlan]] = {}
    mapped: dict[frozenset[int], float] = {}
    unreachable: list[int] = []

    def mapping(group: frozenset[int], found: list[SurveyPlan]) -> float:
        # Without loops, the four ways (and their backwards) drive the same mapping legs.
        swept = swath_cover(found[0].legs, half_width_m)
        missed = shapely.union_all([gaps[i] for i in sorted(group)])
        return float(shapely.area(shapely.intersection(swept, missed)))

    for i in range(len(targets)):
        alone = frozenset((i,))
        found = sweeps(alone)
        if found is None:
            unreachable.append(i)
        else:
            group_of[i], ways[alone], mapped[alone] = alone, found, mapping(alone, found)

    def duration(group: frozenset[int]) -> float:
        return min(way.duration_s(speed_mps) for way in ways[group])

    def region(group: frozenset[int]) -> shapely.Geometry:
        return shapely.union_all([targets[i] for i in sorted(group)])

    left, right = shapely.STRtree(targets).query(targets, predicate="dwithin", distance=join_m)
    pairs = sorted(
        (float(shapely.distance(targets[i], targets[j])), int(i), int(j))
        for i, j in zip(left, right, strict=True)
        if i < j and i in group_of and j in group_of
    )
    for _, i, j in pairs:
        a, b = group_of[i], group_of[j]
        if a == b:
            continue
        both = a | b
        found = sweeps(both)
        if found is None:
            continue
        apart = (
            duration(a) + duration(b) + float(shapely.distance(region(a), region(b))) / speed_mps
        )
        if min(way.duration_s(speed_mps) for way in found) > apart:
            continue
        maps = mapping(both, found)
        if maps >= mapped[a] + mapped[b] - LOOP_MIN_M2:
            del ways[a], ways[b], mapped[a], mapped[b]
            ways[both], mapped[both] = found, maps
            group_of.update(dict.fromkeys(both, both))
    return ways, unreachable


def _backwards(plan: SurveyPlan) -> SurveyPlan:
    """The same sweep driven from its end to its start."""
    legs = tuple(Leg(leg.kind, leg.lane, leg.end, leg.start) for leg in reversed(plan.legs))
    runs = tuple(
        Run(r.lane, r.end, r.start, r.exit, r.entry, r.ends_at_keepout, r.starts_at_keepout)
        for r in reversed(plan.runs)
    )
    first = runs[0]
    bearing = math.atan2(first.end[0] - first.start[0], first.end[1] - first.start[1])
    return replace(plan, bearing_rad=bearing % (2 * math.pi), legs=legs, runs=runs)


# --- order ---


def _transit(keepouts: Keepouts) -> Callable[[Point, Point], float]:
    """The length (m) of the way between two points: straight, or round the keep-outs
    where they block it (straight if no way round is found: a point inside a keep-out).
    Remembered both ways round, so the length from a to b is the length from b to a."""
    known: dict[tuple[Point, Point], float] = {}

    def length(a: Point, b: Point) -> float:
        key = (a, b) if a <= b else (b, a)
        if key not in known:
            try:
                points = [key[0], *keepouts.route(*key), key[1]]
            except PlanningError:
                points = [key[0], key[1]]
            known[key] = sum(math.dist(p, q) for p, q in itertools.pairwise(points))
        return known[key]

    return length


def _order(
    ways: list[list[SurveyPlan]],
    start: Point,
    transit: Callable[[Point, Point], float],
    speed_mps: float,
) -> list[tuple[int, int]]:
    """(group, way) in driving order (the module doc's heuristic)."""

    def begin(item: tuple[int, int]) -> Point:
        return ways[item[0]][item[1]].legs[0].start

    def end(item: tuple[int, int]) -> Point:
        return ways[item[0]][item[1]].legs[-1].end

    def seconds(item: tuple[int, int]) -> float:
        return ways[item[0]][item[1]].duration_s(speed_mps)

    order: list[tuple[int, int]] = []
    here = start
    left = set(range(len(ways)))
    while left:
        nearest = min(
            ((g, k) for g in sorted(left) for k in range(len(ways[g]))),
            key=lambda item: (transit(here, begin(item)), seconds(item)),
        )
        order.append(nearest)
        left.discard(nearest[0])
        here = end(nearest)

    n = len(order)

    def before(i: int) -> Point:
        return start if i == 0 else end(order[i - 1])

    def link(a: Point, i: int) -> float:
        """Seconds from a to the start of order[i] (none past the last)."""
        return transit(a, begin(order[i])) / speed_mps if i < n else 0.0

    def tail(b: Point, i: int) -> float:
        return transit(b, begin(order[i + 1])) / speed_mps if i + 1 < n else 0.0

    for _ in range(MAX_ROUNDS):
        better = False
        for i, j in itertools.combinations(range(n), 2):
            old = link(before(i), i) + tail(end(order[j]), j)
            new = transit(before(i), end(order[j])) / speed_mps + tail(begin(order[i]), j)
            if new < old - 1e-9:
                order[i : j + 1] = [
                    (g, (k + _WAYS) % (2 * _WAYS)) for g, k in reversed(order[i : j + 1])
                ]
                better = True
        for i, (g, k) in enumerate(order):

            def cost(way: int, i: int = i, g: int = g) -> float:
                item = (g, way)
                return (
                    transit(before(i), begin(item)) / speed_mps + seconds(item) + tail(end(item), i)
                )

            best = min(range(len(ways[g])), key=cost)
            if cost(best) < cost(k) - 1e-9:
                order[i] = (g, best)
                better = True
        if not better:
            break
    return order


# --- the path ---


def _once_round(
    legs: list[Leg], start: Point, region: shapely.Geometry, keepouts: Keepouts, half_width_m: float
) -> list[Leg]:
    """``once_round`` on the path with the way to it from ``start`` (a turn: not mapping),
    so a keep-out the path begins at is met there too."""
    if math.dist(start, legs[0].start) <= 1e-9:
        return once_round(legs, region, keepouts, half_width_m)
    approach = Leg(LegKind.TURN, -1, start, legs[0].start)
    return once_round([approach, *legs], region, keepouts, half_width_m)[1:]


def _assemble(
    ways: list[list[SurveyPlan]],
    order: list[tuple[int, int]],
    start: Point,
    keepouts: Keepouts,
) -> tuple[list[Leg], list[Run], list[int], float]:
    """The legs and runs of the groups in order, lanes numbered in driving order, joined
    by the ways round the keep-outs; the lanes of each group; the approach's length."""
    legs: list[Leg] = []
    runs: list[Run] = []
    lanes: list[int] = []
    here = start
    approach_m = 0.0
    for g, k in order:
        way = ways[g][k]
        if legs:
            joint = connect(here, way.legs[0].start, LegKind.TURN, -1, keepouts)
        else:
            try:
                joint = connect(here, way.legs[0].start, LegKind.TURN, -1, keepouts)
            except PlanningError:  # the start lies in a keep-out: straight out of it
                joint = [Leg(LegKind.TURN, -1, here, way.legs[0].start)]
            approach_m = float(sum(leg.length_m for leg in joint))
            joint = joint[1:]  # the boat is at the start: from there to the first corner
        legs.extend(joint)
        number: dict[int, int] = {}
        for leg in way.legs:
            if leg.lane >= 0:
                number.setdefault(leg.lane, sum(lanes) + len(number))
        legs.extend(
            replace(leg, lane=number[leg.lane]) if leg.lane >= 0 else leg for leg in way.legs
        )
        runs.extend(replace(run, lane=number[run.lane]) for run in way.runs)
        lanes.append(len(number))
        here = way.legs[-1].end
    return legs, runs, lanes, approach_m
