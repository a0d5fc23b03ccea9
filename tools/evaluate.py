"""Score a mapping result against a simulator's truth (``truth.json`` and ``seabed.tif``).

Reports the absolute trajectory error of the vehicle reference point, heading error,
relative-pose consistency against the truth, the quadrat-spacing error of the paper's
Table III (quadrats located in the mosaic by template matching), how far the located
quadrats are from where the truth puts them, and a displacement field between the mosaic
and the true seabed (phase correlation in patches).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import rasterio

from mapping.metrics import (
    Quadrat,
    absolute_trajectory_error,
    displacement_field,
    image_metrics,
    locate_quadrats,
    quadrat_spacing_error,
    relative_pose_consistency,
)
from mapping.pipeline import SurveyResult
from seamap.errors import SeamapError

Array = npt.NDArray[np.float64]


def load_truth(path: Path) -> dict[str, Any]:
    try:
        truth: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such truth file") from None
    except (OSError, ValueError) as exc:
        raise SeamapError(f"{path}: not a readable truth.json ({exc})") from None
    if truth.get("format") != "seamap-sim-truth":
        raise SeamapError(f"{path}: not a seamap simulator truth file")
    return truth


def truth_poses(truth: dict[str, Any], times: Array) -> Array:
    """True (east, north, grid heading rad) of the antenna at each frame time (UTM);
    NaN where no truth ping has that time."""
    pings = truth["pings"]
    t = np.array([p["time"] for p in pings])
    out = np.full((times.size, 3), np.nan)
    order = np.argsort(t)
    t_sorted = t[order]
    idx = np.clip(np.searchsorted(t_sorted, times), 0, max(t.size - 1, 0))
    for k, (i, time) in enumerate(zip(idx, times, strict=True)):
        for j in (i - 1, i):
            if 0 <= j < t.size and abs(t_sorted[j] - time) < 1e-4:
                p = pings[order[j]]
                out[k] = (p["east"], p["north"], math.radians(p["grid_heading_deg"]))
    return out


def quadrats_of(truth: dict[str, Any]) -> list[Quadrat]:
    out = []
    for q in truth.get("features", {}).get("quadrats", []):
        (e0, n0), (e1, n1) = q["corners"][0], q["corners"][1]
        side_bearing = math.atan2(e1 - e0, n1 - n0)
        out.append(
            Quadrat(
                q["centre_east"], q["centre_north"], q["side_m"], q["row"], q["index"], side_bearing
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


def evaluate(
    truth_path: Path,
    result: SurveyResult,
    mosaic: npt.NDArray[np.uint8],
    west: float,
    north: float,
    res_m: float,
) -> dict[str, Any]:
    truth = load_truth(truth_path)
    frame = result.frame
    est = np.full_like(result.poses, np.nan)
    ok = np.all(np.isfinite(result.poses), axis=1)
    est[ok, 0], est[ok, 1] = frame.to_utm(result.poses[ok, 0], result.poses[ok, 1])
    est[ok, 2] = result.poses[ok, 2]
    true = truth_poses(truth, result.times)
    ate = absolute_trajectory_error(est, true)
    heading_err = np.degrees(np.angle(np.exp(1j * (est[:, 2] - true[:, 2]))))
    finite = np.isfinite(heading_err)
    mae, rmse = relative_pose_consistency(est, true)
    report: dict[str, Any] = {
        "trajectory": {
            **ate,
            "heading_rmse_deg": float(np.sqrt(np.mean(heading_err[finite] ** 2)))
            if finite.any()
            else math.nan,
            "relative_mae": mae,
            "relative_rmse": rmse,
            "frames_scored": int(finite.sum()),
        }
    }
    covered = mosaic > 0
    image = mosaic.astype(np.float64) / 255.0
    report["mosaic_quality"] = image_metrics(image, covered)
    quadrats = quadrats_of(truth)
    if quadrats:
        found = locate_quadrats(image, covered, west, north, res_m, quadrats)
        spacing = quadrat_spacing_error(quadrats, found)
        offsets = [
            math.hypot(f[0] - q.east, f[1] - q.north)
            for q, f in zip(quadrats, found, strict=True)
            if f is not None
        ]
        spacing["position_mean_m"] = float(np.mean(offsets)) if offsets else math.nan
        spacing["position_max_m"] = float(np.max(offsets)) if offsets else math.nan
        report["quadrat_spacing"] = spacing
    seabed = seabed_on_grid(truth_path, truth, mosaic.shape, west, north, res_m)
    if seabed is not None:
        field = displacement_field(image, covered, seabed)
        report["mosaic_vs_seabed"] = {
            "offset_m": field["offset_px"] * res_m,
            "distortion_rms_m": field["distortion_rms_px"] * res_m,
            "rms_m": field["rms_px"] * res_m,
            "max_m": field["max_px"] * res_m,
            "patches": field["patches"],
        }
    return report
