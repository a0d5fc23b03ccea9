"""Bottoms other than rippled sand: soft mud, shell hash, gravel and cobble, debris.

Each is written from what the bottom is: its backscatter reflectivity (0..1, the sand's
0.34 as the reference; see ``seabed``) and its relief (metres above the mean plane), at
the scales a 1.2 MHz sonar with 1 cm cells sees. Frames and rasters as in ``seabed``
(north-up, ``east`` (1, w) and ``north`` (h, 1) cell-centre columns, local metres).

- Soft mud / silt (``soft_mud``): fine, porous, water-rich sediment scatters weakly
  (``soft_mud_reflectivity``, 0.12: ~4.5 dB below sand) and almost uniformly: a
  speckle-scale variation of 3 % (flocs, worm tubes, the odd shell grain, 3 cm), 2 %
  bioturbation mottling (0.5 m) and 4 % slow change of water content (6 m): about 5 %
  in all. Its relief is a millimetre or two: burrow mounds and pits (4 cm, 1.2 mm RMS)
  and faint hummocks (0.25 m, 0.8 mm). Currents too weak to move sand leave no ripples.
- Shell hash (``shell_hash``): broken shell, 1-3 cm fragments, lying on muddy sand at a
  cover of 25 % on average (5-50 %, patchy over ~2 m): each fragment a strong scatterer
  at any grazing angle (0.65 +-20 %), 2-6 mm proud. The armour of shell damps the
  ripples (the sand's trains at 0.3 of their amplitude: ``SHELL_RIPPLE``).
- Gravel and cobble (``gravel_patches``): patches 1-4 m across over about a third of the
  bed, among the sand (whose ripples fade to a fifth inside them: gravel armours the bed);
  gravel clasts (3-7 cm) give a lumpy relief of about 7 mm RMS and a bright, rough
  reflectivity (0.55 +-25 %); cobbles (6-25 cm, two per square metre of patch) stand
  3-12 cm proud as ellipsoid caps of reflectivity 0.6-0.8.
- Debris on smooth mud (``place_debris``, ``paint_debris``): tyres lying flat (0.56-0.76 m
  across, a 0.16-0.2 m tube, rubber 0.45), concrete blocks (0.39 x 0.19 x 0.19 m or 0.5 x
  0.5 x 0.25 m, 0.7), pipes and timbers (0.5-2 m long, 5-15 cm thick, 0.5): one per 15 m^2
  on average, at least 2 m apart, resting rigidly on the mud.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.special import ndtri

from tools.sim.bedforms import patch_mask, smooth_noise
from tools.sim.structures import Canvas

FloatArray = npt.NDArray[np.float64]
F32Array = npt.NDArray[np.float32]

SHELL_RIPPLE = 0.3
"""The sand's ripple amplitude left under shell hash (a fraction)."""
GRAVEL_COVER = 0.35
DEBRIS_PER_M2 = 1.0 / 15.0
DEBRIS_SPACING_M = 2.0
_SHELL_REFLECTIVITY = 0.65
_GRAVEL_REFLECTIVITY = 0.55
_COBBLES_PER_M2 = 2.0
_GRAVEL_SAND_RIPPLE = 0.2


@dataclass(frozen=True)
class GravelPatch:
    """A gravel and cobble patch (local centre, metres; radius metres)."""

    centre_east: float
    centre_north: float
    radius_m: float


@dataclass(frozen=True)
class Debris:
    """One object on the bed: ``kind`` "tyre", "block" or "pipe"; local centre (m); grid
    bearing of its long axis (degrees); ``length_m`` (outer diameter of a tyre), ``width_m``
    (a tyre's tube, a pipe's diameter), ``height_m`` above the bed; reflectivity."""

    kind: str
    centre_east: float
    centre_north: float
    bearing_deg: float
    length_m: float
    width_m: float
    height_m: float
    reflectivity: float


def soft_mud(
    reflectivity: float, shape: tuple[int, int], res: float, rng: np.random.Generator
) -> tuple[F32Array, F32Array]:
    """Reflectivity and height (m) of a soft mud bottom (module doc)."""
    texture = smooth_noise(rng, shape, res, 0.03) * np.float32(0.03)
    texture += smooth_noise(rng, shape, res, 0.5) * np.float32(0.02)
    texture += smooth_noise(rng, shape, res, 6.0) * np.float32(0.04)
    refl = np.float32(reflectivity) * (np.float32(1.0) + texture)
    del texture
    height = smooth_noise(rng, shape, res, 0.04) * np.float32(0.0012)
    height += smooth_noise(rng, shape, res, 0.25) * np.float32(0.0008)
    return refl, height


def shell_hash(refl: F32Array, height: F32Array, res: float, rng: np.random.Generator) -> None:
    """Strew shell fragments over the bed, in place (module doc): a 2.5 cm random field
    above its local cover quantile is a fragment."""
    shape = refl.shape
    cover = np.clip(0.25 + 0.15 * smooth_noise(rng, shape, res, 2.0), 0.05, 0.5)
    threshold = ndtri(1.0 - cover).astype(np.float32)
    del cover
    field = smooth_noise(rng, shape, res, 0.025)
    field -= threshold
    del threshold
    mask = np.clip(field * np.float32(4.0), 0.0, 1.0)
    del field
    bright = np.float32(_SHELL_REFLECTIVITY) * (
        np.float32(1.0) + np.float32(0.2) * smooth_noise(rng, shape, res, 0.02)
    )
    refl += mask * (bright - refl)
    del bright
    proud = np.float32(0.004) + np.float32(0.001) * smooth_noise(rng, shape, res, 0.02)
    height += mask * np.clip(proud, 0.002, 0.006)


def gravel_patches(
    area: tuple[float, float, float, float],
    east: F32Array,
    north: F32Array,
    res: float,
    refl: F32Array,
    height: F32Array,
    rng: np.random.Generator,
) -> tuple[GravelPatch, ...]:
    """Lay gravel and cobble patches over ``GRAVEL_COVER`` of ``area`` (west, south, east,
    north), in place (module doc); returns the patches."""
    west, south, east_edge, north_edge = area
    size = (east_edge - west) * (north_edge - south)
    radii: list[float] = []
    while math.pi * sum(r * r for r in radii) < GRAVEL_COVER * size:
        radii.append(float(rng.uniform(0.5, 2.0)))
    patches = tuple(
        GravelPatch(float(rng.uniform(west, east_edge)), float(rng.uniform(south, north_edge)), r)
        for r in radii
    )
    mask = patch_mask(patches, east, north, rng, 0.5)
    shape = refl.shape
    height *= np.float32(1.0) - np.float32(1.0 - _GRAVEL_SAND_RIPPLE) * mask
    lumps = np.maximum(smooth_noise(rng, shape, res, 0.03), 0.0) * np.float32(0.010)
    lumps += np.maximum(smooth_noise(rng, shape, res, 0.07), 0.0) * np.float32(0.012)
    height += mask * lumps
    del lumps
    gravel = np.float32(_GRAVEL_REFLECTIVITY) * (
        np.float32(1.0) + np.float32(0.25) * smooth_noise(rng, shape, res, 0.03)
    )
    refl += mask * (gravel - refl)
    del gravel

    # Cobbles where the patch is whole: ellipsoid caps.
    count = int(rng.poisson(_COBBLES_PER_M2 * float(np.sum(mask > 0.5)) * res * res))
    rows, cols = np.nonzero(mask > 0.5)
    del mask
    if count and len(rows):
        pick = rng.integers(0, len(rows), count)
        ce = east[0, cols[pick]].astype(np.float64) + rng.uniform(-res / 2, res / 2, count)
        cn = north[rows[pick], 0].astype(np.float64) + rng.uniform(-res / 2, res / 2, count)
        length = rng.uniform(0.06, 0.25, count)
        paint_caps(
            height,
            refl,
            float(east[0, 0]) - res / 2,
            float(north[0, 0]) + res / 2,
            res,
            ce,
            cn,
            length,
            length * rng.uniform(0.6, 0.9, count),
            length * rng.uniform(0.25, 0.5, count),
            rng.uniform(0.0, math.pi, count),
            rng.uniform(0.6, 0.8, count),
        )
    return patches


def paint_caps(
    height: F32Array,
    refl: F32Array,
    west: float,
    north: float,
    res: float,
    east_c: FloatArray,
    north_c: FloatArray,
    length: FloatArray,
    width: FloatArray,
    cap: FloatArray,
    bearing: FloatArray,
    reflectivity: FloatArray,
) -> None:
    """Ellipsoid caps (``cap`` metres tall) on the height map, each on the bed under its
    centre, all at once (a k x k window per cap); the topmost gives a cell its
    reflectivity."""
    h, w = height.shape
    k = math.ceil(float(np.max(length)) / res) + 3
    offs = np.arange(k) - k // 2
    col0 = np.floor((east_c - west) / res).astype(np.int64)
    row0 = np.floor((north - north_c) / res).astype(np.int64)
    cols = col0[:, None, None] + offs[None, None, :]
    rows = row0[:, None, None] + offs[None, :, None]
    e = west + (cols + 0.5) * res - east_c[:, None, None]
    n = north - (rows + 0.5) * res - north_c[:, None, None]
    sb, cb = np.sin(bearing)[:, None, None], np.cos(bearing)[:, None, None]
    a = (e * sb + n * cb) / (length[:, None, None] / 2)
    b = (e * cb - n * sb) / (width[:, None, None] / 2)
    q = 1.0 - a * a - b * b
    base = height[np.clip(row0, 0, h - 1), np.clip(col0, 0, w - 1)].astype(np.float64)
    top = base[:, None, None] + cap[:, None, None] * np.sqrt(np.maximum(q, 0.0))
    ok = (q > 0) & (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    flat = (rows * w + cols)[ok]
    top = top[ok].astype(np.float32)
    colour = np.broadcast_to(reflectivity[:, None, None], q.shape)[ok].astype(np.float32)
    hv = height.reshape(-1)
    before = hv[flat].copy()
    np.maximum.at(hv, flat, top)
    won = (top >= hv[flat]) & (top > before)
    refl.reshape(-1)[flat[won]] = colour[won]


def place_debris(
    area: tuple[float, float, float, float], keep_clear: FloatArray, rng: np.random.Generator
) -> tuple[Debris, ...]:
    """Objects at ``DEBRIS_PER_M2`` over ``area`` (west, south, east, north), at least
    ``DEBRIS_SPACING_M`` apart and a metre clear of the circles ``keep_clear`` ((n, 3)
    east, north, radius: the quadrats), by dart throwing (module doc)."""
    west, south, east, north = area
    wanted = int(rng.poisson(DEBRIS_PER_M2 * (east - west) * (north - south)))
    placed: list[Debris] = []
    centres = np.zeros((0, 2))
    for _ in range(wanted * 20):
        if len(placed) == wanted:
            break
        ce, cn = float(rng.uniform(west, east)), float(rng.uniform(south, north))
        kind = ("tyre", "block", "pipe")[int(rng.integers(3))]
        bearing = float(rng.uniform(0.0, 180.0))
        if kind == "tyre":
            outer = float(rng.uniform(0.56, 0.76))
            tube = float(rng.uniform(0.16, 0.2))
            item = Debris(kind, ce, cn, bearing, outer, tube, tube, 0.45)
        elif kind == "block":
            big = rng.random() < 0.3
            dims = (0.5, 0.5, 0.25) if big else (0.39, 0.19, 0.19)
            item = Debris(kind, ce, cn, bearing, *dims, 0.7)
        else:
            diameter = float(rng.uniform(0.05, 0.15))
            item = Debris(
                kind, ce, cn, bearing, float(rng.uniform(0.5, 2.0)), diameter, diameter, 0.5
            )
        gap = np.hypot(keep_clear[:, 0] - ce, keep_clear[:, 1] - cn) - keep_clear[:, 2]
        if np.any(gap < 1.0 + item.length_m / 2):
            continue
        if len(centres) and np.min(np.hypot(*(centres - [ce, cn]).T)) < DEBRIS_SPACING_M:
            continue
        placed.append(item)
        centres = np.vstack([centres, [ce, cn]])
    return tuple(placed)


def paint_debris(debris: tuple[Debris, ...], bed: Canvas) -> None:
    """Each object's profile (height above its base, m) resting rigidly on the bed."""
    res = bed.resolution
    for d in debris:
        rows, cols, e, n = bed.window(d.centre_east, d.centre_north, d.length_m / 2 + 2 * res)
        beta = math.radians(d.bearing_deg)
        a = (e - d.centre_east) * math.sin(beta) + (n - d.centre_north) * math.cos(beta)
        b = (e - d.centre_east) * math.cos(beta) - (n - d.centre_north) * math.sin(beta)
        if d.kind == "tyre":
            tube = d.width_m / 2
            off = np.abs(np.hypot(a, b) - (d.length_m / 2 - tube))
            profile = tube + np.sqrt(np.maximum(tube * tube - off * off, 0.0))
            alpha = np.clip((tube - off) / res + 0.5, 0.0, 1.0)
        elif d.kind == "block":
            out = np.hypot(
                np.maximum(np.abs(a) - d.length_m / 2, 0.0),
                np.maximum(np.abs(b) - d.width_m / 2, 0.0),
            )
            inside = (np.abs(a) <= d.length_m / 2) & (np.abs(b) <= d.width_m / 2)
            alpha = np.where(inside, 1.0, np.clip(0.5 - out / res, 0.0, 1.0))
            profile = np.full_like(alpha, d.height_m)
        else:
            radius = d.width_m / 2
            off = np.hypot(b, np.maximum(np.abs(a) - d.length_m / 2, 0.0))
            profile = radius + np.sqrt(np.maximum(radius * radius - off * off, 0.0))
            alpha = np.clip((radius - off) / res + 0.5, 0.0, 1.0)
        bed.stamp_rigid(rows, cols, profile, alpha, d.reflectivity)
