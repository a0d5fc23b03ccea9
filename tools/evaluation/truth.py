"""Score a mapping result against a reference: the simulator's truth (``truth.json`` and
``seabed.tif``) or a reference trajectory CSV (``tools.evaluation.reference``).

Reports the absolute trajectory error of the vehicle reference point, heading error,
relative-pose consistency and the relative pose error over 10 s against the reference; the
lane disagreement (``tools.lanes``: how far apart two passes over the same seabed draw
it, from the true fans and the estimated poses); with the simulator's truth also the
quadrat-spacing error of the paper's Table III (each quadrat array located in the mosaic
as a rigid layout, then each frame by template matching) within each array, and each
array's offset from the truth (the georeferencing error); and a displacement field between
the mosaic and the true seabed (phase correlation in patches). Both kinds of reference
feed ``evaluate`` through ``Reference.at`` (true poses, heads and fan per frame time), so
every metric is computed one way.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import rasterio

from drivers.errors import SeamapError
from mapping.coverage import SonarFan
from mapping.pipeline import SurveyResult
from tools.evaluation.metrics import (
    Found,
    Quadrat,
    absolute_trajectory_error,
    array_offsets,
    displacement_field,
    image_metrics,
    locate_quadrats,
    quadrat_spacing_error,
    relative_pose_consistency,
)
from tools.evaluation.reference import (
    MAX_GAP_S,
    Matched,
    Reference,
    SonarSetup,
    looks_like_csv,
    read_reference_csv,
)
from tools.footprint import Fan, Heads, fan_hits
from tools.lanes import lane_disagreement
from tools.se2 import relative_pose_error

Array = npt.NDArray[np.float64]
Index = npt.NDArray[np.int64]


def load_truth(path: Path) -> dict[str, Any]:
    try:
        truth: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such truth file") from None
    except (OSError, ValueError) as exc:
        raise SeamapError(
            f"{path}: not a readable truth.json ({exc}) nor a reference trajectory CSV "
            "(a header row with time,lat,lon,heading_deg)"
        ) from None
    if truth.get("format") != "seamap-sim-truth":
        raise SeamapError(f"{path}: not a seamap simulator truth file")
    return truth


def truth_index(truth: dict[str, Any], times: Array, tolerance_s: float = 1e-4) -> Index:
    """Per frame time, the index of the truth ping with that time (the .oculus item
    time), or -1 where there is none."""
    t = np.array([p["time"] for p in truth["pings"]], dtype=np.float64)
    out = np.full(times.size, -1, np.int64)
    if t.size == 0 or times.size == 0:
        return out
    order = np.argsort(t, kind="stable")
    t_sorted = t[order]
    right = np.clip(np.searchsorted(t_sorted, times), 0, t.size - 1)
    left = np.clip(right - 1, 0, t.size - 1)
    nearer = np.where(
        np.abs(t_sorted[left] - times) <= np.abs(t_sorted[right] - times), left, right
    )
    close = np.abs(t_sorted[nearer] - times) < tolerance_s
    out[close] = order[nearer[close]]
    return out


def truth_poses(truth: dict[str, Any], times: Array) -> Array:
    """True (east, north, grid heading rad) of the antenna at each frame time (UTM);
    NaN where no truth ping has that time."""
    index = truth_index(truth, times)
    pings = truth["pings"]
    out = np.full((times.size, 3), np.nan)
    known = np.flatnonzero(index >= 0)
    if known.size:
        rows = [pings[i] for i in index[known]]
        out[known] = [(p["east"], p["north"], math.radians(p["grid_heading_deg"])) for p in rows]
    return out


def truth_heads(truth: dict[str, Any], times: Array) -> Heads:
    """The true sonar head at each frame time (``tools.footprint.Heads``); NaN where no
    truth ping has that time."""
    index = truth_index(truth, times)
    if not truth["pings"]:
        return Heads.missing(times.size)
    aligned = Heads.from_pings(truth["pings"]).take(np.maximum(index, 0))
    missing = index < 0
    for column in (aligned.east, aligned.north):
        column[missing] = np.nan
    return aligned


def quadrats_of(truth: dict[str, Any]) -> list[Quadrat]:
    """The truth's quadrats (``features.quadrats``); ``array`` absent: one array."""
    out = []
    for q in truth.get("features", {}).get("quadrats", []):
        (e0, n0), (e1, n1) = q["corners"][0], q["corners"][1]
        side_bearing = math.atan2(e1 - e0, n1 - n0)
        out.append(
            Quadrat(
                q["centre_east"],
                q["centre_north"],
                q["side_m"],
                q["row"],
                q["index"],
                side_bearing,
                int(q.get("array", 0)),
            )
        )
    return out


def seabed_on_grid(
    truth_path: Path,
    truth: dict[str, Any],
    shape: tuple[int, int],
    west: float,
    north: float,
    res: float,
) -> Array | None:
    """The true seabed reflectivity resampled onto the mosaic's grid, in [0, 1]."""
    seabed = truth.get("seabed", {})
    path = truth_path.parent / seabed.get("file", "seabed.tif")
    if not path.exists():
        return None
    with rasterio.open(path) as dataset:
        image = dataset.read(1).astype(np.float32) / 255.0
        t = dataset.transform
    # Mosaic pixel centre (x, y) -> UTM -> seabed pixel (cv2's centre-at-integer indices).
    matrix = np.array(
        [
            [res / t.a, 0.0, (west - t.c) / t.a + 0.5 * res / t.a - 0.5],
            [0.0, -res / t.e, (north - t.f) / t.e - 0.5 * res / t.e - 0.5],
        ]
    )
    factor = max(round(res / abs(t.a)), 1)
    if factor > 1:
        image = cv2.blur(image, (factor, factor))
    warped = cv2.warpAffine(
        image, matrix, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    )
    return warped.astype(np.float64)


def estimated_poses(result: SurveyResult) -> Array:
    """The result's vehicle poses in UTM (east, north, grid heading rad); NaN where the
    frame was not mapped."""
    est = np.full_like(result.poses, np.nan)
    ok = np.all(np.isfinite(result.poses), axis=1)
    est[ok, 0], est[ok, 1] = result.frame.to_utm(result.poses[ok, 0], result.poses[ok, 1])
    est[ok, 2] = result.poses[ok, 2]
    return est


def trajectory_section(times: Array, est: Array, true: Array) -> dict[str, Any]:
    """ATE, heading error, frame-to-frame consistency and the relative pose error over
    10 s of the estimated trajectory against the true one."""
    ate = absolute_trajectory_error(est, true)
    heading_err = np.degrees(np.angle(np.exp(1j * (est[:, 2] - true[:, 2]))))
    finite = np.isfinite(heading_err)
    mae, rmse = relative_pose_consistency(est, true)
    rpe = relative_pose_error(times, est, true, window_s=10.0)
    return {
        **ate,
        "heading_rmse_deg": float(np.sqrt(np.mean(heading_err[finite] ** 2)))
        if finite.any()
        else math.nan,
        "relative_mae": mae,
        "relative_rmse": rmse,
        "rpe_10s_m": rpe["translation_rms_m"],
        "rpe_10s_deg": rpe["yaw_rms_deg"],
        "rpe_10s_pairs": rpe["pairs"],
        "frames_scored": int(finite.sum()),
    }


MIN_VIEWS = 3
"""Mapped frames whose true fan must see a quadrat's centre for it to be looked for."""


def quadrat_views(
    quadrats: list[Quadrat], heads: Heads, fan: Fan, est: Array
) -> npt.NDArray[np.int64]:
    """How many mapped frames' true fans saw each quadrat's centre."""
    mapped = np.flatnonzero(np.all(np.isfinite(est), axis=1) & np.isfinite(heads.east))
    centres = np.array([(q.east, q.north) for q in quadrats], float).reshape(-1, 2)
    _, points = fan_hits(fan, heads.take(mapped), centres[:, 0], centres[:, 1])
    return np.bincount(points, minlength=len(quadrats)).astype(np.int64)


def quadrat_section(
    quadrats: list[Quadrat], views: npt.NDArray[np.int64], image: Array,
    covered: npt.NDArray[np.bool_], west: float, north: float, res_m: float,
) -> dict[str, Any]:  # fmt: skip
    """The quadrats located in the mosaic: spacing error within each array and over all
    pairs, how far they lie from the truth, and each array's offset (the absolute
    georeferencing error there). Only quadrats the sonar saw (``views`` >= MIN_VIEWS
    mapped frames) are looked for: a frame never imaged can only be found in the
    speckle."""
    seen = [k for k in range(len(quadrats)) if views[k] >= MIN_VIEWS]
    found: list[Found] = [None] * len(quadrats)
    if seen:
        placed = locate_quadrats(image, covered, west, north, res_m, [quadrats[k] for k in seen])
        for k, f in zip(seen, placed, strict=True):
            found[k] = f
    spacing: dict[str, Any] = dict(quadrat_spacing_error(quadrats, found))
    spacing["seen"] = float(len(seen))
    offsets = [
        math.hypot(f[0] - q.east, f[1] - q.north)
        for q, f in zip(quadrats, found, strict=True)
        if f is not None
    ]
    spacing["position_mean_m"] = float(np.mean(offsets)) if offsets else math.nan
    spacing["position_max_m"] = float(np.max(offsets)) if offsets else math.nan
    arrays = array_offsets(quadrats, found)
    spacing["arrays"] = arrays
    norms = [a["offset_m"] for a in arrays if math.isfinite(a["offset_m"])]
    spacing["array_offset_max_m"] = float(max(norms)) if norms else math.nan
    return spacing


def evaluate(
    reference: Reference | Path,
    result: SurveyResult,
    mosaic: npt.NDArray[np.uint8],
    west: float,
    north: float,
    res_m: float,
    sonar: SonarSetup | None = None,
) -> dict[str, Any]:
    """The accuracy of one mapping result against a reference (report.json's
    ``accuracy``): ``reference`` (how the frames met it), ``trajectory``, ``lanes``,
    ``mosaic_quality``, ``quadrat_spacing`` (when the reference has quadrats),
    ``mosaic_vs_seabed`` (when it has the seabed), ``unavailable`` (why not, for a
    reference trajectory), and the seconds each took (``timings_s``). A path is read with
    ``load_reference``; ``sonar``: what the replay knows of the sonar (a reference
    trajectory's heads and fan are built from it)."""
    clock = time.perf_counter()
    timings: dict[str, float] = {}

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 4)
        clock = now

    if isinstance(reference, Path):
        reference = load_reference(reference)
    est = estimated_poses(result)
    matched = reference.at(result.times, result.frame.epsg, sonar)
    true = matched.poses
    mapped = np.all(np.isfinite(est), axis=1)
    known = np.all(np.isfinite(true), axis=1)
    report: dict[str, Any] = {
        "reference": {
            **matched.summary,
            "frames_mapped": int(mapped.sum()),
            "mapped_without_reference": int((mapped & ~known).sum()),
        },
        "trajectory": trajectory_section(result.times, est, true),
    }
    lap("trajectory")
    quadrats = reference.quadrats()
    centres = np.array([(q.east, q.north) for q in quadrats], float).reshape(-1, 2)
    heads, fan = matched.heads, matched.fan
    report["lanes"] = lane_disagreement(result.times, true, est, heads, fan, centres)
    lap("lanes")
    covered = mosaic > 0
    image = mosaic.astype(np.float64) / 255.0
    report["mosaic_quality"] = image_metrics(image, covered)
    lap("mosaic_quality")
    if quadrats:
        views = quadrat_views(quadrats, heads, fan, est)
        report["quadrat_spacing"] = quadrat_section(
            quadrats, views, image, covered, west, north, res_m
        )
        lap("quadrat_spacing")
    seabed = reference.seabed_on_grid(mosaic.shape, west, north, res_m)
    if seabed is not None:
        field = displacement_field(image, covered, seabed)
        report["mosaic_vs_seabed"] = {
            "offset_m": field["offset_px"] * res_m,
            "rotation_deg": field["rotation_deg"],
            "distortion_rms_m": field["distortion_rms_px"] * res_m,
            "rms_m": field["rms_px"] * res_m,
            "max_m": field["max_px"] * res_m,
            "patches": field["patches"],
        }
        lap("mosaic_vs_seabed")
    if reference.unavailable:
        report["unavailable"] = reference.unavailable
    report["timings_s"] = timings
    return report


@dataclass(frozen=True)
class SimTruth:
    """The simulator's truth.json as a ``Reference``: the true poses and heads of the
    pings whose stamp is the frame's (``truth_poses``, ``truth_heads``), the true fan
    (``Fan.from_truth``), its quadrats and seabed."""

    path: Path
    truth: dict[str, Any]
    unavailable: str | None = None

    def at(self, times: Array, epsg: int, sonar: SonarSetup | None) -> Matched:
        poses = truth_poses(self.truth, times)
        matched = int(np.all(np.isfinite(poses), axis=1).sum())
        summary = {
            "kind": "simulator truth",
            "path": str(self.path),
            "frames": int(times.size),
            "frames_matched": matched,
            "frames_unmatched": int(times.size) - matched,
        }
        return Matched(poses, truth_heads(self.truth, times), Fan.from_truth(self.truth), summary)

    def quadrats(self) -> list[Quadrat]:
        return quadrats_of(self.truth)

    def seabed_on_grid(
        self, shape: tuple[int, int], west: float, north: float, res: float
    ) -> Array | None:
        return seabed_on_grid(self.path, self.truth, shape, west, north, res)


def load_reference(
    path: Path, tolerance_s: float | None = None, max_gap_s: float = MAX_GAP_S
) -> Reference:
    """The reference in ``path``, told by its content: a simulator's truth.json (a JSON
    object, ``format`` "seamap-sim-truth") or a reference trajectory CSV (a header row
    naming its columns; ``tolerance_s`` and ``max_gap_s`` match its times to the frames',
    ``tools.evaluation.reference``). SeamapError (one line) if it is neither."""
    if not path.is_file():
        raise SeamapError(f"{path}: no such truth file")
    if looks_like_csv(path):
        return read_reference_csv(path, tolerance_s, max_gap_s)
    return SimTruth(path, load_truth(path))


def truth_scorer(
    truth_path: Path, tolerance_s: float | None = None, max_gap_s: float = MAX_GAP_S
) -> Callable[[SurveyResult, npt.NDArray[np.uint8], float, float, float, SonarFan], dict[str, Any]]:
    """The scorer ``daemon.replay.replay`` takes (``Scorer``): ``evaluate`` against the
    reference in this file (``load_reference``, read now: a bad file fails before any
    mapping); the ``seamap.scorers`` entry point ``truth`` (``seamap replay --truth``).
    A reference trajectory's sonar is the result's mount with the replay's fan, at the
    altitude the replay used (``replay_altitude``)."""
    reference = load_reference(truth_path, tolerance_s, max_gap_s)

    def score(
        result: SurveyResult, mosaic: npt.NDArray[np.uint8], west: float, north: float,
        res_m: float, fan: SonarFan,
    ) -> dict[str, Any]:  # fmt: skip
        altitude = replay_altitude(result.bottom, result.mount.altitude_m)
        sonar = SonarSetup(result.mount, fan, altitude)
        return evaluate(reference, result, mosaic, west, north, res_m, sonar)

    return score


def replay_altitude(bottom: dict[str, Any], configured_m: float) -> float:
    """The sonar's altitude above the seabed a replay used (m): the median of its seabed
    planes' (from echosounder or sonar soundings: ``SurveyResult.bottom``, report.json's
    ``bottom``), else the configured one."""
    found = bottom.get("altitude_m")
    if isinstance(found, dict) and found.get("median") is not None:
        return float(found["median"])
    return float(configured_m)
