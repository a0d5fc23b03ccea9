"""Quality metrics: the paper's image metrics (Sec. IV, Tables I and IV), trajectory
consistency (Table II), and, against a simulator's truth, absolute trajectory error, the
quadrat-spacing error (Table III) and the mosaic's geometric error.

Images are float intensities in [0, 1] with a validity mask; positions are metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


def entropy(image: Array, mask: Mask) -> float:
    """Shannon entropy of the 256-level histogram, divided by 8 bits (0..1)."""
    values = np.clip(np.rint(image[mask] * 255.0), 0, 255).astype(np.int64)
    if values.size == 0:
        return 0.0
    p = np.bincount(values, minlength=256) / values.size
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum() / 8.0)


def variance(image: Array, mask: Mask) -> float:
    return float(np.var(image[mask])) if mask.any() else 0.0


def rms_contrast(image: Array, mask: Mask) -> float:
    """Standard deviation of the intensities (Peli 1990)."""
    return float(np.std(image[mask])) if mask.any() else 0.0


def _interior(mask: Mask, border: int) -> Mask:
    kernel = np.ones((2 * border + 1, 2 * border + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), kernel).astype(bool)


def tenengrad(image: Array, mask: Mask) -> float:
    """Mean squared Sobel gradient magnitude inside the mask (Krotkov 1988)."""
    img = image.astype(np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    inside = _interior(mask, 1)
    return float(np.mean((gx * gx + gy * gy)[inside])) if inside.any() else 0.0


def variance_of_laplacian(image: Array, mask: Mask) -> float:
    """Variance of the Laplacian inside the mask (Pech-Pacheco et al. 2000)."""
    lap = cv2.Laplacian(image.astype(np.float32), cv2.CV_32F, ksize=3)
    inside = _interior(mask, 1)
    return float(np.var(lap[inside])) if inside.any() else 0.0


def image_metrics(image: Array, mask: Mask) -> dict[str, float]:
    """Ent., Var., RMS, Ten., VoL of an image in [0, 1] (the paper's Tables I and IV)."""
    return {
        "entropy": entropy(image, mask),
        "variance": variance(image, mask),
        "rms_contrast": rms_contrast(image, mask),
        "tenengrad": tenengrad(image, mask),
        "variance_of_laplacian": variance_of_laplacian(image, mask),
    }


def relative_pose_consistency(a: Array, b: Array) -> tuple[float, float]:
    """MAE and RMSE (metres) between the frame-to-frame displacements of two trajectories
    (n, >=2) over the frames both have (the paper's Table II)."""
    both = np.all(np.isfinite(a[:, :2]), axis=1) & np.all(np.isfinite(b[:, :2]), axis=1)
    idx = np.flatnonzero(both)
    if idx.size < 2:
        return math.nan, math.nan
    da = np.diff(a[idx, :2], axis=0)
    db = np.diff(b[idx, :2], axis=0)
    err = np.linalg.norm(da - db, axis=1)
    return float(err.mean()), float(math.sqrt(float(np.mean(err**2))))


def absolute_trajectory_error(estimate: Array, truth: Array) -> dict[str, float]:
    """Position error (metres) of georeferenced poses against the truth, as they are
    (``rmse``) and after the best rigid 2-D alignment (``aligned_rmse``: shape only)."""
    ok = np.all(np.isfinite(estimate[:, :2]), axis=1) & np.all(np.isfinite(truth[:, :2]), axis=1)
    if ok.sum() < 2:
        return {"rmse": math.nan, "mean": math.nan, "max": math.nan, "aligned_rmse": math.nan}
    e, t = estimate[ok, :2], truth[ok, :2]
    err = np.linalg.norm(e - t, axis=1)
    ec, tc = e.mean(axis=0), t.mean(axis=0)
    a, b = e - ec, t - tc
    theta = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b)))
    c, s = math.cos(theta), math.sin(theta)
    aligned = a @ np.array([[c, s], [-s, c]]) + tc
    aligned_err = np.linalg.norm(aligned - t, axis=1)
    return {
        "rmse": float(math.sqrt(float(np.mean(err**2)))),
        "mean": float(err.mean()),
        "max": float(err.max()),
        "aligned_rmse": float(math.sqrt(float(np.mean(aligned_err**2)))),
    }


@dataclass(frozen=True, slots=True)
class Quadrat:
    """A square frame on the seabed: centre (UTM metres), side (metres, between the bar
    centre lines), orientation of one side (radians clockwise from grid north)."""

    east: float
    north: float
    side_m: float
    row: int
    index: int
    orientation_rad: float = 0.0


def _frame_template(side_px: float, bar_px: float, angle_rad: float) -> npt.NDArray[np.float32]:
    """A bright square outline, rotated, zero-mean (for normalised matching)."""
    size = math.ceil((side_px + 4 * bar_px) * 1.45) | 1
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    # Offsets along the side's bearing, image vector (sin b, -cos b) as y points south,
    # and across it, (cos b, sin b).
    sb, cb = math.sin(angle_rad), math.cos(angle_rad)
    u = (xx - c) * sb - (yy - c) * cb
    v = (xx - c) * cb + (yy - c) * sb
    d = np.maximum(np.abs(u), np.abs(v))
    template = np.clip(bar_px / 2.0 + 0.5 - np.abs(d - side_px / 2.0), 0.0, 1.0).astype(np.float32)
    return template - template.mean()


def _filled(mosaic: Array, covered: Mask) -> npt.NDArray[np.float32]:
    """The mosaic with no-data pixels set to its mean (so they match nothing)."""
    values = mosaic[covered]
    fill = float(values.mean()) if values.size else 0.0
    return np.where(covered, mosaic, fill).astype(np.float32)


def _peak(response: npt.NDArray[np.float32]) -> tuple[float, float, float]:
    """Sub-pixel (x, y) of the maximum of a match response, and its value."""
    _, score, _, (px, py) = cv2.minMaxLoc(response)

    def refine(line: Array, k: int) -> float:
        if 0 < k < line.size - 1:
            den = line[k - 1] - 2 * line[k] + line[k + 1]
            if den < 0:
                return float(k + 0.5 * (line[k - 1] - line[k + 1]) / den)
        return float(k)

    return (
        refine(response[py, :].astype(float), px),
        refine(response[:, px].astype(float), py),
        float(score),
    )


def layout_offset(
    image: npt.NDArray[np.float32],
    west: float,
    north: float,
    res_m: float,
    quadrats: Sequence[Quadrat],
    search_m: float,
    bar_m: float,
) -> tuple[float, float] | None:
    """Where the whole quadrat layout lies in the mosaic relative to the truth (east,
    north metres): the rigid pattern of all frames matched at once, which cannot confuse
    one frame with its neighbour however far the georeferencing is off."""
    margin = 0.5
    e0 = min(q.east for q in quadrats) - margin - max(q.side_m for q in quadrats)
    n1 = max(q.north for q in quadrats) + margin + max(q.side_m for q in quadrats)
    e1 = max(q.east for q in quadrats) + margin + max(q.side_m for q in quadrats)
    n0 = min(q.north for q in quadrats) - margin - max(q.side_m for q in quadrats)
    width, height = round((e1 - e0) / res_m), round((n1 - n0) / res_m)
    pattern = np.zeros((height, width), np.float32)
    for q in quadrats:
        t = _frame_template(q.side_m / res_m, max(bar_m / res_m, 2.0), q.orientation_rad)
        t = t - t.min()
        x = round((q.east - e0) / res_m) - t.shape[1] // 2
        y = round((n1 - q.north) / res_m) - t.shape[0] // 2
        xs, ys = (
            slice(max(x, 0), min(x + t.shape[1], width)),
            slice(max(y, 0), min(y + t.shape[0], height)),
        )
        pattern[ys, xs] = np.maximum(
            pattern[ys, xs], t[ys.start - y : ys.stop - y, xs.start - x : xs.stop - x]
        )
    pattern -= pattern.mean()
    pad = round(search_m / res_m)
    x0 = round((e0 - west) / res_m) - pad
    y0 = round((north - n1) / res_m) - pad
    x1, y1 = x0 + width + 2 * pad, y0 + height + 2 * pad
    if x0 < 0 or y0 < 0 or x1 > image.shape[1] or y1 > image.shape[0]:
        return None
    response = cv2.matchTemplate(image[y0:y1, x0:x1], pattern, cv2.TM_CCOEFF_NORMED)
    px, py, _ = _peak(response)
    return ((px - pad) * res_m, -(py - pad) * res_m)


def locate_quadrats(
    mosaic: Array,
    covered: Mask,
    west: float,
    north: float,
    res_m: float,
    quadrats: Sequence[Quadrat],
    layout_search_m: float = 2.0,
    search_m: float = 0.3,
    bar_m: float = 0.04,
) -> list[tuple[float, float, float] | None]:
    """Find each quadrat in a north-up mosaic (top-left corner at UTM west/north): first
    the whole layout within ``layout_search_m`` of the truth (the georeferencing error),
    then each frame by normalised template matching of a square outline of its side and
    orientation within ``search_m`` of there (less than half the 1 m spacing, so a match
    cannot jump to a neighbour). A GPS bias of several sigma can put the layout beyond
    the search: the search is also made twice as wide, and the placement whose frames
    agree best on the layout's offset (a false placement scatters them) is kept.
    Returns (east, north, match score) or None per quadrat."""
    image = _filled(mosaic, covered)
    best: list[tuple[float, float, float] | None] = [None] * len(quadrats)
    best_spread = math.inf
    for search in (layout_search_m, 2 * layout_search_m):
        offset = layout_offset(image, west, north, res_m, quadrats, search, bar_m) or (0.0, 0.0)
        found = _locate_each(image, covered, west, north, res_m, quadrats, offset, search_m, bar_m)
        shifts = np.array(
            [(f[0] - q.east, f[1] - q.north) for q, f in zip(quadrats, found, strict=True) if f]
        )
        spread = float(np.linalg.norm(shifts.std(axis=0))) if len(shifts) >= 2 else math.inf
        if spread < best_spread:
            best, best_spread = found, spread
    return best


def _locate_each(
    image: npt.NDArray[np.float32],
    covered: Mask,
    west: float,
    north: float,
    res_m: float,
    quadrats: Sequence[Quadrat],
    offset: tuple[float, float],
    search_m: float,
    bar_m: float,
) -> list[tuple[float, float, float] | None]:
    found: list[tuple[float, float, float] | None] = []
    for q in quadrats:
        template = _frame_template(q.side_m / res_m, max(bar_m / res_m, 2.0), q.orientation_rad)
        half = template.shape[0] // 2 + round(search_m / res_m)
        cx = (q.east + offset[0] - west) / res_m - 0.5
        cy = (north - q.north - offset[1]) / res_m - 0.5
        x0, y0 = round(cx) - half, round(cy) - half
        x1, y1 = x0 + 2 * half + 1, y0 + 2 * half + 1
        if x0 < 0 or y0 < 0 or x1 > image.shape[1] or y1 > image.shape[0]:
            found.append(None)
            continue
        if covered[y0:y1, x0:x1].mean() < 0.5:
            found.append(None)
            continue
        response = cv2.matchTemplate(image[y0:y1, x0:x1], template, cv2.TM_CCOEFF_NORMED)
        px, py, score = _peak(response)
        fx = px + template.shape[1] // 2 + x0
        fy = py + template.shape[0] // 2 + y0
        found.append((west + (fx + 0.5) * res_m, north - (fy + 0.5) * res_m, score))
    return found


def quadrat_spacing_error(
    quadrats: Sequence[Quadrat], found: Sequence[tuple[float, float, float] | None]
) -> dict[str, float]:
    """MAE / RMSE (metres) of the distances between every pair of located quadrats
    against the true distances (the paper's Table III), and how many were located."""
    errors = []
    for a in range(len(quadrats)):
        for b in range(a + 1, len(quadrats)):
            fa, fb = found[a], found[b]
            if fa is None or fb is None:
                continue
            true = math.hypot(
                quadrats[a].east - quadrats[b].east, quadrats[a].north - quadrats[b].north
            )
            got = math.hypot(fa[0] - fb[0], fa[1] - fb[1])
            errors.append(got - true)
    located = sum(f is not None for f in found)
    if not errors:
        return {"mae": math.nan, "rmse": math.nan, "located": float(located), "pairs": 0.0}
    err = np.abs(np.array(errors))
    return {
        "mae": float(err.mean()),
        "rmse": float(math.sqrt(float(np.mean(err**2)))),
        "located": float(located),
        "pairs": float(err.size),
    }


def displacement_field(
    mosaic: Array,
    covered: Mask,
    truth: Array,
    patch_px: int = 128,
    min_coverage: float = 0.9,
    min_peak: float = 0.08,
) -> dict[str, float]:
    """How far the mosaic is from the true seabed (both on one grid, pixels): in patches
    where both have texture, the shift phase correlation finds between them.

    ``offset_px``: length of the mean shift (the georeferencing error, GPS-limited);
    ``distortion_rms_px``: RMS of the shifts about their mean (the mosaic's internal
    geometry: lanes that disagree, drift, warping); ``rms_px``/``max_px`` of the raw
    shifts; ``patches`` measured.
    """
    shifts = []
    window = cv2.createHanningWindow((patch_px, patch_px), cv2.CV_32F)
    rows, cols = mosaic.shape
    for y in range(0, rows - patch_px + 1, patch_px // 2):
        for x in range(0, cols - patch_px + 1, patch_px // 2):
            if covered[y : y + patch_px, x : x + patch_px].mean() < min_coverage:
                continue
            a = mosaic[y : y + patch_px, x : x + patch_px].astype(np.float32)
            b = truth[y : y + patch_px, x : x + patch_px].astype(np.float32)
            if a.std() < 1e-3 or b.std() < 1e-3:
                continue
            (dx, dy), peak = cv2.phaseCorrelate(b - b.mean(), a - a.mean(), window)
            if peak >= min_peak:
                shifts.append((dx, dy))
    if not shifts:
        nan = math.nan
        return {
            "offset_px": nan,
            "distortion_rms_px": nan,
            "rms_px": nan,
            "max_px": nan,
            "patches": 0.0,
        }
    v = np.array(shifts)
    mean = v.mean(axis=0)
    length = np.linalg.norm(v, axis=1)
    return {
        "offset_px": float(np.linalg.norm(mean)),
        "distortion_rms_px": float(math.sqrt(float(np.mean(np.sum((v - mean) ** 2, axis=1))))),
        "rms_px": float(math.sqrt(float(np.mean(length**2)))),
        "max_px": float(length.max()),
        "patches": float(len(shifts)),
    }
