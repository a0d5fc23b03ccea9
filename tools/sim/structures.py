"""What lies on the sand: quadrat arrays, farm racks and oysters, painted into the maps.

Frames and units: local grid east/north metres (see ``site.py``); bearings are grid
bearings, radians in code. Painting works on a ``Canvas``: the sand's height map (read:
rigid things rest on its crests) and the objects' height above the sand, coverage and
reflectivity (written; ``seabed.generate_seabed`` puts them on top of the sand).

The quadrat array is the paper's (Sec. IV-A-2): two parallel rows of four square frames,
aluminium 0.43 m and PVC 0.62 m on a side (measured between bar centre lines), the rows
1.52 m apart between their nearest sides, frames 1 m apart centre to centre in a row. A
scenario may lay several arrays. A farm rack (trestle) is a ladder of steel bars: rows 1 m
apart tied by cross bars. Frames and racks are rigid: they rest on the sand's crests
(their base is the 98th percentile of the sand height under their bars), so ripples pass
beneath them. Oysters are ellipsoid caps, piled in clumps, scattered, in beds, or
planted in rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from tools.sim.scenarios import OysterBed, Rack, Scenario

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
RACK_REFLECTIVITY = 0.95  # galvanised steel
_REST_PERCENTILE = 98.0


@dataclass(frozen=True)
class Quadrat:
    """One square frame (local frame). side_m is measured between bar centre lines;
    bearing_rad is the grid bearing of the row axis (two sides are parallel to it);
    ``array`` numbers the scenario's arrays (0 the scenario's own, then
    ``quadrat_arrays``)."""

    row: int
    index: int
    material: str
    side_m: float
    bar_width_m: float
    bar_height_m: float
    centre_east: float
    centre_north: float
    bearing_rad: float
    array: int = 0

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


def quadrat_layout(s: Scenario) -> tuple[Quadrat, ...]:
    """Every array's 2 x 4 frames: array 0 centred on the scenario's quadrat centre, then
    ``s.quadrat_arrays``; in each, row 0 aluminium, row 1 PVC, each row's axis
    ROW_CENTRE_DISTANCE_M / 2 either side of the array's centre."""
    arrays = [
        (s.quadrat_centre_east_m, s.quadrat_centre_north_m, s.quadrat_row_bearing_deg,
         s.quadrat_pvc_side),
        *((a.centre_east_m, a.centre_north_m, a.row_bearing_deg, a.pvc_side)
          for a in s.quadrat_arrays),
    ]  # fmt: skip
    quadrats = []
    for number, (east, north, bearing_deg, pvc_side) in enumerate(arrays):
        rho = math.radians(bearing_deg)
        u = np.array([math.sin(rho), math.cos(rho)])
        v = np.array([u[1], -u[0]])  # right of the row axis
        pvc_sign = 1.0 if pvc_side == "right" else -1.0
        centre = np.array([east, north])
        for row, material in enumerate(("aluminium", "pvc")):
            sign = pvc_sign if material == "pvc" else -pvc_sign
            axis = centre + sign * ROW_CENTRE_DISTANCE_M / 2 * v
            m = _MATERIALS[material]
            for index in range(FRAMES_PER_ROW):
                c = axis + (index - (FRAMES_PER_ROW - 1) / 2) * FRAME_SPACING_M * u
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
                        number,
                    )
                )
    return tuple(quadrats)


def rack_bars(rack: Rack) -> FloatArray:
    """The centre lines of a rack's bars, (n, 4) local [east0, north0, east1, north1]:
    the rows along the rack's bearing (first the one on the left looking along it), then
    the ties across them."""
    beta = math.radians(rack.bearing_deg)
    u = np.array([math.sin(beta), math.cos(beta)])
    v = np.array([u[1], -u[0]])  # right of the rack's axis
    c = np.array([rack.centre_east_m, rack.centre_north_m])
    width = (rack.n_rows - 1) * rack.row_spacing_m
    bars = []
    for i in range(rack.n_rows):
        offset = c + (i * rack.row_spacing_m - width / 2) * v
        bars.append([*(offset - rack.length_m / 2 * u), *(offset + rack.length_m / 2 * u)])
    if rack.tie_spacing_m > 0 and rack.n_rows > 1:
        for j in range(int(rack.length_m / rack.tie_spacing_m + 1e-9) + 1):
            along = c + (j * rack.tie_spacing_m - rack.length_m / 2) * u
            bars.append([*(along - width / 2 * v), *(along + width / 2 * v)])
    return np.array(bars, np.float64).reshape(-1, 4)


@dataclass
class Canvas:
    """Mutable maps while the seabed is being painted: ``sand`` (the sand's height above
    the mean plane, m; read only), and what goes on top: ``objects`` (height above the
    sand, m), ``alpha`` (coverage 0..1), ``refl`` (reflectivity)."""

    west: float
    north: float
    resolution: float
    sand: F32Array
    objects: F32Array
    alpha: F32Array
    refl: F32Array

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

    def stamp_rigid(
        self, rows: slice, cols: slice, profile: FloatArray, alpha: FloatArray, refl: float
    ) -> None:
        """Put a rigid object resting on the sand's crests: ``profile`` is its height above
        its base (m), the base the 98th percentile of the sand under it."""
        sand = self.sand[rows, cols]
        covered = alpha > 0.5
        if not np.any(covered):
            return
        base = float(np.percentile(sand[covered], _REST_PERCENTILE))
        above = np.maximum(base + profile - sand, 0.0) * alpha
        self.stamp(rows, cols, above, alpha, np.full_like(above, refl))


def paint_quadrats(quadrats: tuple[Quadrat, ...], bed: Canvas) -> None:
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
        bed.stamp_rigid(rows, cols, profile, alpha, _MATERIALS[q.material]["refl"])


def paint_racks(racks: tuple[Rack, ...], bed: Canvas) -> None:
    """The racks' bars: flat-topped, ``bar_height_m`` above their base, anti-aliased."""
    res = bed.resolution
    for rack in racks:
        width = (rack.n_rows - 1) * rack.row_spacing_m
        reach = math.hypot(rack.length_m, width) / 2 + rack.bar_width_m
        rows, cols, e, n = bed.window(rack.centre_east_m, rack.centre_north_m, reach)
        beta = math.radians(rack.bearing_deg)
        ue, un = math.sin(beta), math.cos(beta)
        # along the rack from its start, across from its left row
        a = (e - rack.centre_east_m) * ue + (n - rack.centre_north_m) * un + rack.length_m / 2
        b = (e - rack.centre_east_m) * un - (n - rack.centre_north_m) * ue + width / 2
        outside_a = np.maximum(np.maximum(-a, a - rack.length_m), 0.0)
        outside_b = np.maximum(np.maximum(-b, b - width), 0.0)
        nearest_row = np.clip(np.rint(b / rack.row_spacing_m), 0, rack.n_rows - 1)
        dist = np.hypot(b - nearest_row * rack.row_spacing_m, outside_a)
        if rack.tie_spacing_m > 0 and rack.n_rows > 1:
            last = int(rack.length_m / rack.tie_spacing_m + 1e-9)
            nearest_tie = np.clip(np.rint(a / rack.tie_spacing_m), 0, last)
            dist = np.minimum(dist, np.hypot(a - nearest_tie * rack.tie_spacing_m, outside_b))
        alpha = np.clip((rack.bar_width_m / 2 - dist) / res + 0.5, 0.0, 1.0)
        profile = np.full_like(dist, rack.bar_height_m)
        bed.stamp_rigid(rows, cols, profile, alpha, RACK_REFLECTIVITY)


def paint_oysters(oysters: Oysters, bed: Canvas, rng: np.random.Generator) -> None:
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


def _bed_clumps(
    bed: OysterBed, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int64]]:
    """Clump centres (local east/north) and sizes of a bed: scattered at its density, or
    planted in rows (``row_spacing_m``) every ``clump_spacing_m`` with 3 cm of slop."""
    beta = math.radians(bed.bearing_deg)
    if bed.row_spacing_m > 0:
        n_rows = int(bed.width_m / bed.row_spacing_m + 1e-9) + 1
        step = bed.clump_spacing_m if bed.clump_spacing_m > 0 else 0.5
        n_along = int(bed.length_m / step + 1e-9) + 1
        a_grid, b_grid = np.meshgrid(
            (np.arange(n_along) - (n_along - 1) / 2) * step,
            (np.arange(n_rows) - (n_rows - 1) / 2) * bed.row_spacing_m,
        )
        a = a_grid.ravel() + rng.normal(0.0, 0.03, a_grid.size)
        b = b_grid.ravel() + rng.normal(0.0, 0.03, b_grid.size)
        size = 2 + rng.poisson(4.0, a.size)
    else:
        m = int(rng.poisson(bed.clumps_per_m2 * bed.length_m * bed.width_m))
        a = rng.uniform(-bed.length_m / 2, bed.length_m / 2, m)
        b = rng.uniform(-bed.width_m / 2, bed.width_m / 2, m)
        size = 2 + rng.poisson(6.0, m)
    east = bed.centre_east_m + a * math.sin(beta) + b * math.cos(beta)
    north = bed.centre_north_m + a * math.cos(beta) - b * math.sin(beta)
    return east, north, size.astype(np.int64)


def place_oysters(
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

    area = (east - west) * (north - south)
    m = int(rng.poisson(s.scattered_clumps_per_m2 * area))
    clump_e = [rng.uniform(west, east, m)]
    clump_n = [rng.uniform(south, north, m)]
    clump_size = [1 + rng.poisson(2.0, m)]
    for bed in s.oyster_beds:
        be, bn, bs = _bed_clumps(bed, rng)
        clump_e.append(be)
        clump_n.append(bn)
        clump_size.append(bs)
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
