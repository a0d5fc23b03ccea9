"""The seabed: a reflectivity map, a height map, a mean plane, and the features on it.

Frames and units: local grid east/north metres (see ``site.py``). The maps are north-up
rasters with square cells of ``resolution`` metres: row 0 is the northern edge
(``north``), column 0 the western edge (``west``); cell (row, col) has its centre at
``(west + (col + 0.5) * res, north - (row + 0.5) * res)``.

- ``reflectivity``: uint8, 255 * the seabed's backscatter reflectivity (1..255; the
  truth GeoTIFF is this array). Sand is about 0.34 with multi-scale texture, shell hash
  brighter, oysters 0.5-0.85, PVC frames 0.85, aluminium frames 1.0.
- ``height``: float32 metres above the mean plane: sand ripples (oriented sinusoids with
  wandering phase and amplitude, sharp crests), millimetre roughness, shell patches,
  oysters (ellipsoid caps, piled in clumps) and the quadrat frames (raised bars).
- the mean plane: depth below the still water surface ``depth0 + slope_east * east +
  slope_north * north`` (metres, positive down).

The quadrat array is the paper's (Sec. IV-A-2): two parallel rows of four square frames,
aluminium 0.43 m and PVC 0.62 m on a side (measured between bar centre lines), the rows
1.52 m apart between their nearest sides, frames 1 m apart centre to centre in a row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from tools.sim.scenarios import Scenario

FloatArray = npt.NDArray[np.float64]
F32Array = npt.NDArray[np.float32]

# The paper's layout (metres): 17 in and 24.5 in frames, rows 60 in apart, 1 m spacing.
ALUMINIUM_SIDE_M = 0.43
PVC_SIDE_M = 0.62
ROW_GAP_M = 1.52
FRAME_SPACING_M = 1.0
FRAMES_PER_ROW = 4
ROW_CENTRE_DISTANCE_M = ROW_GAP_M + ALUMINIUM_SIDE_M / 2 + PVC_SIDE_M / 2

# The bars: aluminium flat bar 25 mm wide standing 25 mm proud, bright; PVC pipe of 1 in
# schedule 40 (33.4 mm outside diameter), a little less bright.
_MATERIALS = {
    "aluminium": {"side": ALUMINIUM_SIDE_M, "width": 0.025, "height": 0.025, "refl": 1.0},
    "pvc": {"side": PVC_SIDE_M, "width": 0.0334, "height": 0.0334, "refl": 0.85},
}


@dataclass(frozen=True)
class Quadrat:
    """One square frame (local frame). side_m is measured between bar centre lines;
    bearing_rad is the grid bearing of the row axis (two sides are parallel to it)."""

    row: int
    index: int
    material: str
    side_m: float
    bar_width_m: float
    bar_height_m: float
    centre_east: float
    centre_north: float
    bearing_rad: float

    def corners(self) -> FloatArray:
        """The four corners of the bar centre lines, (4, 2) local east/north, in order
        back-left, front-left, front-right, back-right (looking along the row)."""
        u = np.array([math.sin(self.bearing_rad), math.cos(self.bearing_rad)])
        v = np.array([u[1], -u[0]])  # to the right of the row axis
        h = self.side_m / 2
        c = np.array([self.centre_east, self.centre_north])
        return np.array(
            [c - h * u - h * v, c + h * u - h * v, c + h * u + h * v, c - h * u + h * v]
        )


@dataclass(frozen=True)
class Oysters:
    """Individual oysters (local frame, metres; bearing of the long axis in radians)."""

    east: FloatArray
    north: FloatArray
    length: FloatArray
    width: FloatArray
    height: FloatArray
    bearing: FloatArray
    reflectivity: FloatArray
    clump: npt.NDArray[np.int64]
    """Clump number (-1 for oysters placed inside a quadrat)."""
    quadrat: npt.NDArray[np.int64]
    """Index into Seabed.quadrats of the frame the oyster lies in, or -1."""

    @classmethod
    def empty(cls) -> Oysters:
        z = np.zeros(0)
        i = np.zeros(0, np.int64)
        return cls(z, z, z, z, z, z, z, i, i)

    def __len__(self) -> int:
        return len(self.east)


@dataclass(frozen=True)
class ShellPatch:
    centre_east: float
    centre_north: float
    radius_m: float


@dataclass(frozen=True)
class Seabed:
    """Maps and features of the seabed (see the module doc for frames and units)."""

    reflectivity: npt.NDArray[np.uint8]
    height: F32Array
    west: float
    north: float
    resolution: float
    depth0: float
    slope_east: float
    slope_north: float
    quadrats: tuple[Quadrat, ...] = ()
    oysters: Oysters = field(default_factory=Oysters.empty)
    shell_patches: tuple[ShellPatch, ...] = ()

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.reflectivity.shape[0]), int(self.reflectivity.shape[1]))

    @property
    def east_edge(self) -> float:
        return self.west + self.shape[1] * self.resolution

    @property
    def south(self) -> float:
        return self.north - self.shape[0] * self.resolution

    def depth_at(self, east: FloatArray, north: FloatArray) -> FloatArray:
        """Depth of the mean plane below the still water surface (m) at local east/north."""
        return (
            self.depth0 + self.slope_east * np.asarray(east) + self.slope_north * np.asarray(north)
        )

    def pixel(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Fractional (col, row) raster coordinates of local east/north points."""
        col = (np.asarray(east) - self.west) / self.resolution - 0.5
        row = (self.north - np.asarray(north)) / self.resolution - 0.5
        return col, row


def quadrat_layout(s: Scenario) -> tuple[Quadrat, ...]:
    """The 2 x 4 array centred on the scenario's quadrat centre: row 0 aluminium, row 1
    PVC, each row's axis ROW_CENTRE_DISTANCE_M / 2 either side of the centre."""
    rho = math.radians(s.quadrat_row_bearing_deg)
    u = np.array([math.sin(rho), math.cos(rho)])
    v = np.array([u[1], -u[0]])  # right of the row axis
    pvc_sign = 1.0 if s.quadrat_pvc_side == "right" else -1.0
    centre = np.array([s.quadrat_centre_east_m, s.quadrat_centre_north_m])
    quadrats = []
    for row, material in enumerate(("aluminium", "pvc")):
        sign = pvc_sign if material == "pvc" else -pvc_sign
        axis = centre + sign * ROW_CENTRE_DISTANCE_M / 2 * v
        m = _MATERIALS[material]
        for index in range(FRAMES_PER_ROW):
            along = (index - (FRAMES_PER_ROW - 1) / 2) * FRAME_SPACING_M
            c = axis + along * u
            quadrats.append(
                Quadrat(
                    row,
                    index,
                    material,
                    m["side"],
                    m["width"],
                    m["height"],
                    float(c[0]),
                    float(c[1]),
                    rho,
                )
            )
    return tuple(quadrats)


def smooth_noise(
    rng: np.random.Generator, shape: tuple[int, int], resolution: float, scale_m: float
) -> F32Array:
    """Zero-mean, unit-variance random field with features about ``scale_m`` across:
    white noise on a grid of that spacing, bicubically upsampled."""
    h, w = shape
    gh = max(2, math.ceil(h * resolution / scale_m)) + 3
    gw = max(2, math.ceil(w * resolution / scale_m)) + 3
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    # Resize a larger field and crop, so that the grid spacing is scale_m exactly and the
    # map edges are not special.
    ch = round((gh - 1) * scale_m / resolution)
    cw = round((gw - 1) * scale_m / resolution)
    big = cv2.resize(grid, (cw, ch), interpolation=cv2.INTER_CUBIC)
    field_ = big[:h, :w]
    # Bicubic interpolation of white noise has a standard deviation of about 0.72.
    return np.ascontiguousarray(field_ * np.float32(1 / 0.72))


@dataclass
class _Canvas:
    """Mutable maps while the seabed is being painted (objects go on top of the sand)."""

    west: float
    north: float
    resolution: float
    objects: F32Array  # object height above the sand (m)
    alpha: F32Array  # object coverage 0..1
    refl: F32Array  # object reflectivity

    def window(
        self, east: float, north: float, radius: float
    ) -> tuple[slice, slice, FloatArray, FloatArray]:
        """A square window of cells around a point, clipped to the map, with the cell
        centre coordinates (local east/north, broadcastable)."""
        res = self.resolution
        h, w = self.objects.shape
        c0 = max(0, int((east - radius - self.west) / res))
        c1 = min(w, int((east + radius - self.west) / res) + 2)
        r0 = max(0, int((self.north - north - radius) / res))
        r1 = min(h, int((self.north - north + radius) / res) + 2)
        e = self.west + (np.arange(c0, c1) + 0.5) * res
        n = self.north - (np.arange(r0, r1) + 0.5) * res
        return slice(r0, r1), slice(c0, c1), e[None, :], n[:, None]

    def stamp(
        self, rows: slice, cols: slice, height: FloatArray, alpha: FloatArray, refl: FloatArray
    ) -> None:
        """Put an object in a window where it is taller than what is there."""
        top = height > self.objects[rows, cols]
        top &= alpha > 0
        self.objects[rows, cols] = np.where(top, height, self.objects[rows, cols])
        self.alpha[rows, cols] = np.where(
            top, np.maximum(alpha, self.alpha[rows, cols]), self.alpha[rows, cols]
        )
        self.refl[rows, cols] = np.where(top, refl, self.refl[rows, cols])


def _paint_quadrats(
    quadrats: tuple[Quadrat, ...],
    bed: _Canvas,
) -> None:
    """Raise and brighten the frame bars (anti-aliased over one cell)."""
    res = bed.resolution
    for q in quadrats:
        half = q.side_m / 2 + q.bar_width_m
        rows, cols, e, n = bed.window(q.centre_east, q.centre_north, half * math.sqrt(2))
        ue, un = math.sin(q.bearing_rad), math.cos(q.bearing_rad)
        a = (e - q.centre_east) * ue + (n - q.centre_north) * un
        b = (e - q.centre_east) * un - (n - q.centre_north) * ue
        h = q.side_m / 2
        m = np.maximum(np.abs(a), np.abs(b))
        inside = m <= h
        dist = np.where(
            inside, h - m, np.hypot(np.maximum(np.abs(a) - h, 0), np.maximum(np.abs(b) - h, 0))
        )
        r = q.bar_width_m / 2
        alpha = np.clip((r - dist) / res + 0.5, 0.0, 1.0)
        if q.material == "pvc":
            profile = q.bar_height_m / 2 + np.sqrt(np.maximum(r * r - dist * dist, 0.0))
        else:
            profile = np.full_like(dist, q.bar_height_m)
        bed.stamp(
            rows, cols, profile * alpha, alpha, np.full_like(dist, _MATERIALS[q.material]["refl"])
        )


def _paint_oysters(oysters: Oysters, bed: _Canvas, rng: np.random.Generator) -> None:
    """Ellipsoid caps, all at once: each oyster gets a k x k window of cells around it."""
    if len(oysters) == 0:
        return
    res = bed.resolution
    h, w = bed.objects.shape
    k = math.ceil(float(np.max(oysters.length)) / res) + 3
    offs = np.arange(k) - k // 2
    col0 = np.floor((oysters.east - bed.west) / res).astype(np.int64)
    row0 = np.floor((bed.north - oysters.north) / res).astype(np.int64)
    cols = col0[:, None, None] + offs[None, None, :]
    rows = row0[:, None, None] + offs[None, :, None]
    e = bed.west + (cols + 0.5) * res - oysters.east[:, None, None]
    n = bed.north - (rows + 0.5) * res - oysters.north[:, None, None]
    sb, cb = np.sin(oysters.bearing)[:, None, None], np.cos(oysters.bearing)[:, None, None]
    a = (e * sb + n * cb) / (oysters.length[:, None, None] / 2)
    b = (e * cb - n * sb) / (oysters.width[:, None, None] / 2)
    q = 1.0 - a * a - b * b
    # Oysters in a clump pile on each other: each sits up to 12 mm above the sand.
    base = np.where(oysters.clump >= 0, rng.uniform(0.0, 0.012, len(oysters)), 0.0)
    cap = oysters.height[:, None, None] * np.sqrt(np.maximum(q, 0.0)) + base[:, None, None]
    alpha = np.clip(q * 6.0, 0.0, 1.0)
    texture = rng.uniform(0.75, 1.2, q.shape)  # the rough shell
    refl = oysters.reflectivity[:, None, None] * texture
    ok = (q > 0) & (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    flat = (rows * w + cols)[ok]
    cap, alpha, refl = cap[ok], alpha[ok], refl[ok]
    obj = bed.objects.reshape(-1)
    np.maximum.at(obj, flat, cap.astype(np.float32))
    # The topmost oyster at a cell gives that cell its reflectivity.
    top = cap >= obj[flat] - 1e-7
    bed.refl.reshape(-1)[flat[top]] = refl[top]
    al = bed.alpha.reshape(-1)
    np.maximum.at(al, flat[top], alpha[top].astype(np.float32))


def _place_oysters(
    s: Scenario,
    quadrats: tuple[Quadrat, ...],
    bounds: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> Oysters:
    """Oysters inside each frame, in clumps scattered over the map, and in the beds."""
    west, south, east, north = bounds
    parts: list[dict[str, FloatArray]] = []

    def oysters_at(ce: FloatArray, cn: FloatArray, clump: FloatArray, quad: FloatArray) -> None:
        m = len(ce)
        length = rng.uniform(0.06, 0.11, m)
        parts.append(
            {
                "east": ce,
                "north": cn,
                "length": length,
                "width": length * rng.uniform(0.5, 0.65, m),
                "height": rng.uniform(0.02, 0.04, m),
                "bearing": rng.uniform(0, 2 * math.pi, m),
                "reflectivity": rng.uniform(0.5, 0.85, m),
                "clump": clump,
                "quadrat": quad,
            }
        )

    for qi, q in enumerate(quadrats):
        m = max(1, s.oysters_per_quadrat + int(rng.integers(-2, 3)))
        inner = q.side_m / 2 - q.bar_width_m - 0.04
        a, b = rng.uniform(-inner, inner, (2, m))
        ue, un = math.sin(q.bearing_rad), math.cos(q.bearing_rad)
        oysters_at(
            q.centre_east + a * ue + b * un,
            q.centre_north + a * un - b * ue,
            np.full(m, -1.0),
            np.full(m, float(qi)),
        )

    clump_e: list[FloatArray] = []
    clump_n: list[FloatArray] = []
    clump_size: list[npt.NDArray[np.int64]] = []
    area = (east - west) * (north - south)
    m = int(rng.poisson(s.scattered_clumps_per_m2 * area))
    clump_e.append(rng.uniform(west, east, m))
    clump_n.append(rng.uniform(south, north, m))
    clump_size.append(1 + rng.poisson(2.0, m))
    for bed in s.oyster_beds:
        m = int(rng.poisson(bed.clumps_per_m2 * bed.length_m * bed.width_m))
        a = rng.uniform(-bed.length_m / 2, bed.length_m / 2, m)
        b = rng.uniform(-bed.width_m / 2, bed.width_m / 2, m)
        beta = math.radians(bed.bearing_deg)
        clump_e.append(bed.centre_east_m + a * math.sin(beta) + b * math.cos(beta))
        clump_n.append(bed.centre_north_m + a * math.cos(beta) - b * math.sin(beta))
        clump_size.append(2 + rng.poisson(6.0, m))
    ce, cn, size = np.concatenate(clump_e), np.concatenate(clump_n), np.concatenate(clump_size)
    # Keep clumps off the frames: the quadrats were laid on clean sand.
    for q in quadrats:
        far = np.hypot(ce - q.centre_east, cn - q.centre_north) > q.side_m * 0.75 + 0.15
        ce, cn, size = ce[far], cn[far], size[far]
    ids = np.repeat(np.arange(len(ce)), size.astype(np.int64))
    spread = 0.03 + 0.01 * np.sqrt(size[ids])
    oysters_at(
        ce[ids] + rng.normal(0, 1, len(ids)) * spread,
        cn[ids] + rng.normal(0, 1, len(ids)) * spread,
        ids.astype(np.float64),
        np.full(len(ids), -1.0),
    )

    cat = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    return Oysters(
        cat["east"],
        cat["north"],
        cat["length"],
        cat["width"],
        cat["height"],
        cat["bearing"],
        cat["reflectivity"],
        cat["clump"].astype(np.int64),
        cat["quadrat"].astype(np.int64),
    )


def generate_seabed(
    s: Scenario, bounds: tuple[float, float, float, float], rng: np.random.Generator
) -> Seabed:
    """Paint the scenario's seabed over ``bounds`` = (west, south, east, north), local
    metres (whole metres keep the cells on a whole-metre UTM grid)."""
    west, south, east, north = bounds
    res = s.seabed_resolution_m
    shape = (round((north - south) / res), round((east - west) / res))
    e = (west + (np.arange(shape[1], dtype=np.float32) + 0.5) * res)[None, :]
    n = (north - (np.arange(shape[0], dtype=np.float32) + 0.5) * res)[:, None]

    # Sand: texture at four scales; the finest stands for grain-size and shell-hash speckle.
    fine = smooth_noise(rng, shape, res, 0.03)
    refl = smooth_noise(rng, shape, res, 4.0) * np.float32(0.10)
    refl += smooth_noise(rng, shape, res, 1.0) * np.float32(0.10)
    refl += smooth_noise(rng, shape, res, 0.25) * np.float32(0.08)
    refl += fine * np.float32(0.10)

    # Ripples: the phase wanders (crests bend and fork) and the amplitude fades in patches.
    k = np.float32(2 * math.pi / s.ripple_wavelength_m)
    rb = math.radians(s.ripple_bearing_deg)
    phase = e * (k * np.float32(math.sin(rb))) + n * (k * np.float32(math.cos(rb)))
    phase += smooth_noise(rng, shape, res, 2.5) * np.float32(2.0)
    envelope = np.clip(0.7 + 0.35 * smooth_noise(rng, shape, res, 5.0), 0.15, 1.0)
    sin_phase = np.sin(phase)
    # Sharper crests than troughs; shell debris collects in the troughs (brighter there).
    height = (sin_phase - np.float32(0.2) * np.cos(2 * phase)) * envelope
    height *= np.float32(s.ripple_amplitude_m)
    refl -= sin_phase * envelope * np.float32(0.06)
    del phase, envelope, sin_phase
    height += fine * np.float32(0.001)

    # Shell patches: irregular bright, rough areas.
    patches = []
    edge_noise = smooth_noise(rng, shape, res, 0.4)
    for _ in range(s.n_shell_patches):
        pe, pn = rng.uniform(west, east), rng.uniform(south, north)
        radius = float(rng.uniform(0.4, 1.5))
        patches.append(ShellPatch(float(pe), float(pn), radius))
        c0 = max(0, int((pe - 1.5 * radius - west) / res))
        c1 = min(shape[1], int((pe + 1.5 * radius - west) / res) + 1)
        r0 = max(0, int((north - pn - 1.5 * radius) / res))
        r1 = min(shape[0], int((north - pn + 1.5 * radius) / res) + 1)
        if c0 >= c1 or r0 >= r1:
            continue
        d = np.hypot(e[:, c0:c1] - pe, n[r0:r1, :] - pn) / radius
        mask = np.clip((1.0 - d + 0.3 * edge_noise[r0:r1, c0:c1]) * 4.0, 0.0, 1.0)
        refl[r0:r1, c0:c1] += mask * (0.18 + 0.12 * fine[r0:r1, c0:c1])
        height[r0:r1, c0:c1] += mask * 0.004 * np.abs(fine[r0:r1, c0:c1])
    del edge_noise, fine

    refl = np.float32(s.sand_reflectivity) * (1.0 + refl)

    quadrats = quadrat_layout(s)
    oysters = _place_oysters(s, quadrats, bounds, rng)
    canvas = _Canvas(
        west,
        north,
        res,
        np.zeros(shape, np.float32),
        np.zeros(shape, np.float32),
        np.zeros(shape, np.float32),
    )
    _paint_oysters(oysters, canvas, rng)
    _paint_quadrats(quadrats, canvas)
    height += canvas.objects
    refl += canvas.alpha * (canvas.refl - refl)
    reflectivity = np.clip(np.rint(refl * 255.0), 1, 255).astype(np.uint8)
    return Seabed(
        reflectivity=reflectivity,
        height=height.astype(np.float32),
        west=west,
        north=north,
        resolution=res,
        depth0=s.water_depth_m,
        slope_east=s.seabed_slope_east,
        slope_north=s.seabed_slope_north,
        quadrats=quadrats,
        oysters=oysters,
        shell_patches=tuple(patches),
    )
