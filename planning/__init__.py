"""Survey planning: a lawnmower path over a survey area for the boat to drive, and what it
maps.

Frames and units: positions are metres east/north in the survey's local grid frame
(``mapping.geo.LocalFrame``); bearings are radians clockwise from grid north; widths and
distances are metres, areas square metres, durations seconds. No files and no projections
here: ``daemon.plan_files`` reads the area, converts to and from WGS84 and writes the
mission files.

- ``planning.area``: the area (polygons with keep-out holes), its validation;
- ``planning.keepouts``: the keep-outs round the holes and the way round them;
- ``planning.swath``: the sonar's usable swath, which spaces the lanes;
- ``planning.lawnmower``: the lanes over the area and the path (the rules are in its doc);
- ``planning.plan``: the planned path, its length and duration;
- ``planning.sweep``: how much of the area the path maps;
- ``planning.gaps``: what a survey missed of the area, from the cells it saw well enough;
- ``planning.replan``: lanes over those gaps, in the order that shortens the way there.

The public names of all eight are importable from here.
"""

from planning.area import Area, PlanningError, Polygon, clean_ring, validate_area
from planning.gaps import AreaCoverage, area_gaps, cells_geometry
from planning.keepouts import Keepouts
from planning.lawnmower import (
    ENTRY_CORNERS,
    LOOP_MIN_M2,
    MAX_LANES,
    MIN_RUN_M,
    Sweepable,
    area_width,
    candidate_bearings,
    choose_bearing,
    connect,
    lane_offsets,
    once_round,
    plan_path,
    plan_survey,
    sweep_options,
)
from planning.plan import TURN_RATE_RAD_S, Leg, LegKind, Run, SurveyPlan
from planning.replan import GAP_MARGIN, GapGroup, GapPlan, plan_gaps
from planning.swath import MIN_LOOK_M, Swath, sonar_swath
from planning.sweep import MAPPING_LEGS, Coverage, coverage, swath_cover

__all__ = [
    "ENTRY_CORNERS",
    "GAP_MARGIN",
    "LOOP_MIN_M2",
    "MAPPING_LEGS",
    "MAX_LANES",
    "MIN_LOOK_M",
    "MIN_RUN_M",
    "TURN_RATE_RAD_S",
    "Area",
    "AreaCoverage",
    "Coverage",
    "GapGroup",
    "GapPlan",
    "Keepouts",
    "Leg",
    "LegKind",
    "PlanningError",
    "Polygon",
    "Run",
    "SurveyPlan",
    "Swath",
    "Sweepable",
    "area_gaps",
    "area_width",
    "candidate_bearings",
    "cells_geometry",
    "choose_bearing",
    "clean_ring",
    "connect",
    "coverage",
    "lane_offsets",
    "once_round",
    "plan_gaps",
    "plan_path",
    "plan_survey",
    "sonar_swath",
    "swath_cover",
    "sweep_options",
    "validate_area",
]
