"""Lane disagreement: how doubled a map is, measured on the seabed itself.

A seabed point seen on two passes (two lanes, or a lane and a turn) is drawn where each
pass's estimated poses put it. For every point (a 1 m grid over the surveyed area, and
each quadrat centre) the frames whose TRUE fan saw it (``tools.footprint``) are split
into passes (runs of frames less than ``gap_s`` apart); each frame places the point at
``T_est o T_true^-1 (p)`` (``tools.se2.placement_shift``: its body-frame position is the
same in both, so the sonar mount cancels); a pass's placement is the mean over its
mapped frames; the disagreement of two passes is the distance between their placements.
With the true poses every placement is the point itself: zero.

Positions are UTM metres; times UNIX seconds; poses (east, north, grid heading rad).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from tools.footprint import Fan, Heads, fan_hits
from tools.se2 import placement_shift

Array = npt.NDArray[np.float64]

PASS_GAP_S = 2.0
GRID_STEP_M = 1.0


def survey_grid(heads: Heads, reach_m: float, step_m: float = GRID_STEP_M) -> tuple[Array, Array]:
    """Points on a ``step_m`` grid (whole multiples of it, UTM) over everything within
    ``reach_m`` of the sonar head's track; flattened (east, north)."""
    ok = np.isfinite(heads.east) & np.isfinite(heads.north)
    if not ok.any():
        return np.zeros(0), np.zeros(0)
    e0 = math.floor((float(heads.east[ok].min()) - reach_m) / step_m) * step_m
    e1 = math.ceil((float(heads.east[ok].max()) + reach_m) / step_m) * step_m
    n0 = math.floor((float(heads.north[ok].min()) - reach_m) / step_m) * step_m
    n1 = math.ceil((float(heads.north[ok].max()) + reach_m) / step_m) * step_m
    east, north = np.meshgrid(
        np.arange(e0, e1 + step_m / 2, step_m), np.arange(n0, n1 + step_m / 2, step_m)
    )
    return east.ravel(), north.ravel()


def pass_disagreements(
    frames: npt.NDArray[np.int64],
    points: npt.NDArray[np.int64],
    times: Array,
    true: Array,
    estimate: Array,
    east: Array,
    north: Array,
    gap_s: float = PASS_GAP_S,
) -> tuple[Array, npt.NDArray[np.int64]]:
    """The distance (metres) between the placements of every pair of passes over the
    same point, and the point of each pair.

    ``frames``/``points``: the (frame, point) pairs a true fan saw; ``times``, ``true``,
    ``estimate``: per frame (``estimate`` NaN where the frame was not mapped: it splits no
    pass but places nothing)."""
    empty = (np.zeros(0), np.zeros(0, np.int64))
    if frames.size == 0:
        return empty
    order = np.lexsort((times[frames], points))
    frames, points = frames[order], points[order]
    t = times[frames]
    new_pass = np.ones(frames.size, bool)
    new_pass[1:] = (points[1:] != points[:-1]) | (np.diff(t) >= gap_s)
    pass_id = np.cumsum(new_pass) - 1
    mapped = np.all(np.isfinite(estimate[frames]), axis=1)
    if not mapped.any():
        return empty
    frames, points, pass_id = frames[mapped], points[mapped], pass_id[mapped]
    shift = placement_shift(true[frames], estimate[frames], east[points], north[points])
    n_pass = int(pass_id.max()) + 1
    count = np.bincount(pass_id, minlength=n_pass)
    used = count > 0
    mean = (
        np.stack([np.bincount(pass_id, shift[:, k], minlength=n_pass) for k in (0, 1)], axis=1)[
            used
        ]
        / count[used, None]
    )
    pass_point = np.zeros(n_pass, np.int64)
    pass_point[pass_id] = points
    pass_point = pass_point[used]  # ascending: passes were numbered point by point
    # Pairs of passes of the same point: the passes of each point padded into a row.
    first = np.flatnonzero(np.r_[True, pass_point[1:] != pass_point[:-1]])
    per_point = np.diff(np.r_[first, pass_point.size])
    widest = int(per_point.max())
    if widest < 2:
        return empty
    row = np.repeat(np.arange(first.size), per_point)
    rank = np.arange(pass_point.size) - np.repeat(first, per_point)
    padded = np.full((first.size, widest, 2), np.nan)
    padded[row, rank] = mean
    a, b = np.triu_indices(widest, 1)
    distance = np.linalg.norm(padded[:, a] - padded[:, b], axis=2)
    owner = np.broadcast_to(pass_point[first][:, None], distance.shape)
    ok = np.isfinite(distance)
    return distance[ok], owner[ok]


def summarise(distance: Array, pair_points: npt.NDArray[np.int64], seen: int) -> dict[str, Any]:
    """RMS, median, p90 and max (metres) of pass-pair disagreements; counts."""
    if distance.size == 0:
        nan = math.nan
        return {
            "rms_m": nan,
            "median_m": nan,
            "p90_m": nan,
            "max_m": nan,
            "pairs": 0,
            "points": seen,
            "points_with_pairs": 0,
        }
    return {
        "rms_m": float(math.sqrt(float(np.mean(distance**2)))),
        "median_m": float(np.median(distance)),
        "p90_m": float(np.percentile(distance, 90)),
        "max_m": float(distance.max()),
        "pairs": int(distance.size),
        "points": seen,
        "points_with_pairs": int(np.unique(pair_points).size),
    }


def lane_disagreement(
    times: Array,
    true: Array,
    estimate: Array,
    heads: Heads,
    fan: Fan,
    quadrat_centres: Array | None = None,
    gap_s: float = PASS_GAP_S,
    step_m: float = GRID_STEP_M,
) -> dict[str, Any]:
    """Lane disagreement over a ``step_m`` grid of the surveyed area and at the quadrat
    centres ((k, 2) UTM), together and each alone (``grid``, ``quadrats``).

    Per frame: ``times`` (s), ``true`` and ``estimate`` antenna poses (NaN rows: no truth /
    not mapped) and ``heads``, the true sonar head (rows without truth are ignored)."""
    grid_east, grid_north = survey_grid(heads, fan.range_m, step_m)
    centres = np.zeros((0, 2)) if quadrat_centres is None else np.asarray(quadrat_centres, float)
    east = np.concatenate([grid_east, centres[:, 0]])
    north = np.concatenate([grid_north, centres[:, 1]])
    has_truth = np.flatnonzero(np.all(np.isfinite(true), axis=1) & np.isfinite(heads.east))
    local_frames, points = fan_hits(fan, heads.take(has_truth), east, north)
    frames = has_truth[local_frames]
    distance, owner = pass_disagreements(frames, points, times, true, estimate, east, north, gap_s)
    mapped = np.all(np.isfinite(estimate[frames]), axis=1)
    seen_points = np.unique(points[mapped])
    is_grid = owner < grid_east.size
    seen_grid = int(np.count_nonzero(seen_points < grid_east.size))
    report = summarise(distance, owner, int(seen_points.size))
    report["grid_step_m"] = step_m
    report["pass_gap_s"] = gap_s
    report["grid"] = summarise(distance[is_grid], owner[is_grid], seen_grid)
    report["quadrats"] = summarise(
        distance[~is_grid], owner[~is_grid], int(seen_points.size) - seen_grid
    )
    return report
