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


def _best_turn(a: Array, b: Array) -> float:
    """The angle (radians, x towards y) of the rotation that best maps the centred points
    ``a`` (n, 2) onto the centred points ``b`` in the least-squares sense."""
    return math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b)))


def _turn_matrix(angle: float) -> Array:
    """Right-multiplying (n, 2) row vectors by this turns them by ``angle``."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, s], [-s, c]])


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
    aligned = a @ _turn_matrix(_best_turn(a, b)) + tc
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
    centre lines), orientation of one side (radians clockwise from grid north), and the
    array (rigid layout) it belongs to."""

    east: float
    north: float
    side_m: float
    row: int
    index: int
    orientation_rad: float = 0.0
    array: int = 0


Found = tuple[float, float, float] | None
"""A located quadrat: (east, north UTM metres, match score), or None."""


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
    x, y = _refine(response, px, py)
    return x, y, float(score)


def _refine(response: npt.NDArray[np.float32], px: int, py: int) -> tuple[float, float]:
    """Sub-pixel position of the response's local maximum at integer (px, py)."""

    def refine(line: Array, k: int) -> float:
        if 0 < k < line.size - 1:
            den = line[k - 1] - 2 * line[k] + line[k + 1]
            if den < 0:
                return float(k + 0.5 * (line[k - 1] - line[k + 1]) / den)
        return float(k)

    return refine(response[py, :].astype(float), px), refine(response[:, px].astype(float), py)


def _window(
    image: npt.NDArray[np.float32], x0: int, y0: int, x1: int, y1: int, fill: float
) -> npt.NDArray[np.float32]:
    """image[y0:y1, x0:x1], ``fill`` where it reaches outside the image."""
    out = np.full((y1 - y0, x1 - x0), fill, np.float32)
    sx0, sy0 = max(x0, 0), max(y0, 0)
    sx1, sy1 = min(x1, image.shape[1]), min(y1, image.shape[0])
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = image[sy0:sy1, sx0:sx1]
    return out


def layout_votes(
    image: npt.NDArray[np.float32],
    covered: Mask,
    west: float,
    north: float,
    res_m: float,
    quadrats: Sequence[Quadrat],
    search_m: float,
    bar_m: float,
    slack_m: float = 0.12,
) -> Array:
    """How well the rigid layout of ``quadrats`` fits the mosaic at every offset from the
    truth within ``search_m`` (a (2p+1, 2p+1) map, p = search_m / res_m; centre = no
    offset, x east, y south), as votes of its frames.

    Each frame's outline is matched on its own (normalised correlation, local, so the
    texture between the frames weighs nothing: ripples whose crests line up with the
    sides of a whole periodic layout would otherwise outvote the frames), loosened by
    ``slack_m`` (a mosaic is not rigid), and votes ``score - threshold`` where its window
    is covered (at least half of it) and nothing where the mosaic has no data. The
    threshold lies midway between the frame's typical score over the search (bare
    seabed) and its best (a frame): bare seabed votes against a placement, a frame for
    it, no data neither. So the layout one frame (1 m) off, which still fits six of
    eight frames, loses on the two it puts on bare seabed, and a placement that puts
    frames only where the mosaic stops does not."""
    pad = round(search_m / res_m)
    votes = np.zeros((2 * pad + 1, 2 * pad + 1))
    radius = max(round(slack_m / res_m), 0)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    coverage = covered.astype(np.float32)
    for q in quadrats:
        template = _frame_template(q.side_m / res_m, max(bar_m / res_m, 2.0), q.orientation_rad)
        th, tw = template.shape
        x0 = round((q.east - west) / res_m - 0.5) - tw // 2 - pad
        y0 = round((north - q.north) / res_m - 0.5) - th // 2 - pad
        x1, y1 = x0 + tw + 2 * pad, y0 + th + 2 * pad
        window = _window(image, x0, y0, x1, y1, float(image.mean()) if image.size else 0.0)
        score = np.nan_to_num(cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED))
        seen = cv2.boxFilter(_window(coverage, x0, y0, x1, y1, 0.0), -1, (tw, th))
        seen = seen[th // 2 : th // 2 + 2 * pad + 1, tw // 2 : tw // 2 + 2 * pad + 1] >= 0.5
        if not seen.any():
            continue
        score = cv2.dilate(score, kernel)
        typical, best = float(np.median(score[seen])), float(score[seen].max())
        votes += np.where(seen, score - (typical + best) / 2.0, 0.0)
    return votes


def layout_offset(
    image: npt.NDArray[np.float32],
    covered: Mask,
    west: float,
    north: float,
    res_m: float,
    quadrats: Sequence[Quadrat],
    search_m: float,
    bar_m: float,
) -> tuple[float, float] | None:
    """Where the whole layout lies in the mosaic relative to the truth (east, north
    metres; the best of ``layout_votes``), or None if the mosaic shows it nowhere."""
    votes = layout_votes(image, covered, west, north, res_m, quadrats, search_m, bar_m)
    if not np.any(votes > 0):
        return None
    pad = (votes.shape[0] - 1) // 2
    # The slack makes the top flat: take the middle of the best votes' plateau.
    top = votes >= votes.max() - 1e-9
    _, labels = cv2.connectedComponents(top.astype(np.uint8))
    py, px = np.unravel_index(int(np.argmax(votes)), votes.shape)
    ys, xs = np.nonzero(labels == labels[py, px])
    return ((float(np.mean(xs)) - pad) * res_m, -(float(np.mean(ys)) - pad) * res_m)


def locate_quadrats(
    mosaic: Array,
    covered: Mask,
    west: float,
    north: float,
    res_m: float,
    quadrats: Sequence[Quadrat],
    layout_search_m: float = 4.0,
    search_m: float = 0.3,
    bar_m: float = 0.04,
) -> list[Found]:
    """Find each quadrat in a north-up mosaic (top-left corner at UTM west/north), one
    array (``Quadrat.array``) at a time: first where the array lies as a rigid layout
    within ``layout_search_m`` of the truth (``layout_offset``, by the votes of its frames
    so that a placement one period off loses; the georeferencing error: a GNSS can be
    2-3 m off, and each array is placed on its own, as the error wanders between them),
    then each frame by normalised template matching of a square outline
    of its side and orientation within ``search_m`` of there (less than half the 1 m
    spacing, so a match cannot jump to a neighbour). Returns (east, north, match score)
    or None per quadrat, in the order given."""
    image = _filled(mosaic, covered)
    found: list[Found] = [None] * len(quadrats)
    for array in sorted({q.array for q in quadrats}):
        members = [k for k, q in enumerate(quadrats) if q.array == array]
        group = [quadrats[k] for k in members]
        offset = layout_offset(image, covered, west, north, res_m, group, layout_search_m, bar_m)
        placed = _locate_each(
            image, covered, west, north, res_m, group, offset or (0.0, 0.0), search_m, bar_m
        )
        for k, f in zip(members, placed, strict=True):
            found[k] = f
    return found


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
) -> list[Found]:
    """Each frame matched within ``search_m`` of its true place moved by ``offset``
    (east, north metres); None where the mosaic covers less than half the search."""
    found: list[Found] = []
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


def _spacing_stats(errors: Array, prefix: str = "") -> dict[str, float]:
    if errors.size == 0:
        return {f"{prefix}mae": math.nan, f"{prefix}rmse": math.nan, f"{prefix}pairs": 0.0}
    err = np.abs(errors)
    return {
        f"{prefix}mae": float(err.mean()),
        f"{prefix}rmse": float(math.sqrt(float(np.mean(err**2)))),
        f"{prefix}pairs": float(err.size),
    }


def _pair_errors(
    quadrats: Sequence[Quadrat], found: Sequence[Found]
) -> tuple[Array, npt.NDArray[np.bool_], npt.NDArray[np.int64]]:
    """For every pair of located quadrats: the error of their distance (metres, located
    minus true), whether both are in the same array, and the first one's array."""
    located = np.array([f is not None for f in found], bool)
    true = np.array([(q.east, q.north) for q in quadrats], float).reshape(-1, 2)
    got = np.array([(f[0], f[1]) if f is not None else (np.nan, np.nan) for f in found])
    array = np.array([q.array for q in quadrats], np.int64)
    a, b = np.triu_indices(len(quadrats), 1)
    both = located[a] & located[b]
    a, b = a[both], b[both]
    error = np.linalg.norm(got[a] - got[b], axis=1) - np.linalg.norm(true[a] - true[b], axis=1)
    return error, array[a] == array[b], array[a]


def quadrat_spacing_error(quadrats: Sequence[Quadrat], found: Sequence[Found]) -> dict[str, float]:
    """MAE / RMSE (metres) of the distances between located quadrats against the true
    distances (the paper's Table III), over the pairs within one array (``mae``,
    ``rmse``, ``pairs``: blind to where each array sits) and over all pairs (``all_*``:
    the same with one array); and how many were located."""
    located = float(sum(f is not None for f in found))
    if len(quadrats) < 2:
        within = all_pairs = np.zeros(0)
    else:
        error, same, _ = _pair_errors(quadrats, found)
        within, all_pairs = error[same], error
    return {
        **_spacing_stats(within),
        **_spacing_stats(all_pairs, "all_"),
        "located": located,
    }


def array_offsets(quadrats: Sequence[Quadrat], found: Sequence[Found]) -> list[dict[str, float]]:
    """Per array: where its located frames lie relative to the truth on average (east,
    north, norm: metres; the absolute georeferencing error there), how many were located,
    and the spacing error of its pairs."""
    out = []
    for array in sorted({q.array for q in quadrats}):
        members = [k for k, q in enumerate(quadrats) if q.array == array]
        group = [quadrats[k] for k in members]
        placed = [found[k] for k in members]
        shifts = np.array(
            [(f[0] - q.east, f[1] - q.north) for q, f in zip(group, placed, strict=True) if f]
        ).reshape(-1, 2)
        mean = shifts.mean(axis=0) if len(shifts) else np.full(2, np.nan)
        spacing = _spacing_stats(_pair_errors(group, placed)[0] if len(group) > 1 else np.zeros(0))
        out.append(
            {
                "array": float(array),
                "located": float(len(shifts)),
                "quadrats": float(len(group)),
                "offset_east_m": float(mean[0]),
                "offset_north_m": float(mean[1]),
                "offset_m": float(np.hypot(mean[0], mean[1])),
                "offset_spread_m": float(np.linalg.norm(shifts.std(axis=0)))
                if len(shifts) >= 2
                else math.nan,
                **spacing,
            }
        )
    return out


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
    ``rotation_deg``: the turn of the best rigid fit of the shifts, clockwise (the map's
    heading error as a whole, compass-limited); ``distortion_rms_px``: RMS of the shifts about
    that rigid fit (the mosaic's internal geometry: lanes that disagree, drift, warping;
    neither where the map sits nor how it is turned); ``rms_px``/``max_px`` of the raw
    shifts; ``patches`` measured.
    """
    shifts = []
    centres = []
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
                centres.append((x + patch_px / 2, y + patch_px / 2))
    if not shifts:
        nan = math.nan
        return {
            "offset_px": nan,
            "rotation_deg": nan,
            "distortion_rms_px": nan,
            "rms_px": nan,
            "max_px": nan,
            "patches": 0.0,
        }
    v = np.array(shifts)
    mean = v.mean(axis=0)
    length = np.linalg.norm(v, axis=1)
    # Rigid fit: where each patch centre went, a turn about the centroid plus a shift.
    p = np.array(centres)
    a = p - p.mean(axis=0)
    b = a + (v - mean)
    angle = _best_turn(a, b)
    residual = b - a @ _turn_matrix(angle)
    return {
        "offset_px": float(np.linalg.norm(mean)),
        # Image rows grow southwards, so a positive angle here turns x (east) towards
        # south: clockwise, as headings turn.
        "rotation_deg": math.degrees(angle),
        "distortion_rms_px": float(math.sqrt(float(np.mean(np.sum(residual**2, axis=1))))),
        "rms_px": float(math.sqrt(float(np.mean(length**2)))),
        "max_px": float(length.max()),
        "patches": float(len(shifts)),
    }
