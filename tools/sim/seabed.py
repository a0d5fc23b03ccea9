"""The seabed: a reflectivity map, a height map, a mean plane, and the features on it.

Frames and units: local grid east/north metres (see ``site.py``). The maps are north-up
rasters with square cells of ``resolution`` metres: row 0 is the northern edge
(``north``), column 0 the western edge (``west``); cell (row, col) has its centre at
``(west + (col + 0.5) * res, north - (row + 0.5) * res)``.

- ``reflectivity``: uint8, 255 * the seabed's backscatter reflectivity (1..255; the
  truth GeoTIFF is this array). Sand is about 0.34 with multi-scale texture, smooth mud
  darker and nearly featureless, shell hash brighter, oysters 0.5-0.85, PVC frames 0.85,
  aluminium frames 1.0, steel racks 0.95.
- ``height``: float32 metres above the mean plane: two superposed ripple trains with
  bending crests (``bedforms``), millimetre roughness, shell patches, oysters (ellipsoid
  caps, piled in clumps, in beds and rows), the quadrat frames and the racks' bars
  (rigid, resting on the crests: ``structures``).
- the mean plane: depth below the still water surface ``depth0 + slope_east * east +
  slope_north * north`` (metres, positive down).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from tools.sim.bathymetry import Undulation, draw_undulation
from tools.sim.bedforms import (
    MudPatch,
    RippleTrain,
    ShellPatch,
    paint_ripples,
    patch_mask,
    place_mud,
    ripple_train,
    smooth_noise,
)
from tools.sim.bottoms import (
    SHELL_RIPPLE,
    Debris,
    GravelPatch,
    gravel_patches,
    paint_debris,
    place_debris,
    shell_hash,
    soft_mud,
)
from tools.sim.scenarios import Scenario
from tools.sim.structures import (
    ALUMINIUM_SIDE_M,
    FRAME_SPACING_M,
    FRAMES_PER_ROW,
    PVC_SIDE_M,
    ROW_CENTRE_DISTANCE_M,
    ROW_GAP_M,
    Canvas,
    Oysters,
    Quadrat,
    paint_oysters,
    paint_quadrats,
    paint_racks,
    place_oysters,
    quadrat_layout,
)

FloatArray = npt.NDArray[np.float64]
F32Array = npt.NDArray[np.float32]

__all__ = [
    "ALUMINIUM_SIDE_M",
    "FRAMES_PER_ROW",
    "FRAME_SPACING_M",
    "PVC_SIDE_M",
    "ROW_CENTRE_DISTANCE_M",
    "ROW_GAP_M",
    "MudPatch",
    "Oysters",
    "Quadrat",
    "RippleTrain",
    "Seabed",
    "ShellPatch",
    "generate_seabed",
    "quadrat_layout",
    "smooth_noise",
]

_MUD_RIPPLE = 0.1  # ripples left on mud, as a fraction
_MUD_TEXTURE = 0.2  # texture left on mud, as a fraction
_MUD_CLUMPS = 0.1  # scattered clumps left on a soft mud bottom, as a fraction


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
    mud_patches: tuple[MudPatch, ...] = ()
    ripples: tuple[RippleTrain, ...] = ()
    seabed_type: str = "sand"
    gravel_patches: tuple[GravelPatch, ...] = ()
    debris: tuple[Debris, ...] = ()
    undulation: Undulation | None = None
    """The bed's long-wavelength shape above the mean plane (``bathymetry``), or None."""

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
        """Depth of the bed's smooth surface (the mean plane, raised by the undulation if
        any; not the cm-scale relief of ``height``) below the still water surface at the
        start of the survey (m, positive down) at local east/north."""
        plane = (
            self.depth0 + self.slope_east * np.asarray(east) + self.slope_north * np.asarray(north)
        )
        if self.undulation is None:
            return plane
        return plane - self.undulation.height(east, north)

    def depth_gradient(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(d depth / d east, d depth / d north) of that smooth surface (m/m)."""
        shape = np.broadcast(np.asarray(east), np.asarray(north)).shape
        ge = np.full(shape, self.slope_east, np.float64)
        gn = np.full(shape, self.slope_north, np.float64)
        if self.undulation is not None:
            ue, un = self.undulation.gradient(east, north)
            ge -= ue
            gn -= un
        return ge, gn

    def relief_at(self, east: FloatArray, north: FloatArray) -> FloatArray:
        """The height map (m above the smooth surface) bilinearly at local points."""
        col, row = self.pixel(east, north)
        h, w = self.shape
        col = np.clip(np.asarray(col, np.float64), 0.0, w - 1.0)
        row = np.clip(np.asarray(row, np.float64), 0.0, h - 1.0)
        c0 = np.minimum(np.floor(col).astype(np.int64), w - 2 if w > 1 else 0)
        r0 = np.minimum(np.floor(row).astype(np.int64), h - 2 if h > 1 else 0)
        fc, fr = col - c0, row - r0
        c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
        z = self.height
        top = z[r0, c0] * (1 - fc) + z[r0, c1] * fc
        bottom = z[r1, c0] * (1 - fc) + z[r1, c1] * fc
        return np.asarray(top * (1 - fr) + bottom * fr, np.float64)

    def pixel(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Fractional (col, row) raster coordinates of local east/north points."""
        col = (np.asarray(east) - self.west) / self.resolution - 0.5
        row = (self.north - np.asarray(north)) / self.resolution - 0.5
        return col, row


def _survey_area(
    s: Scenario, bounds: tuple[float, float, float, float]
) -> tuple[float, float, float, float]:
    """The part of the map the boat runs over: the bounds less the sonar's reach."""
    west, south, east, north = bounds
    inset = min(s.range_m, (east - west) / 4, (north - south) / 4)
    return west + inset, south + inset, east - inset, north - inset


def _firm_ground(s: Scenario, quadrats: tuple[Quadrat, ...]) -> FloatArray:
    """Circles (n, 3: local east, north, radius m) around the quadrats, racks and oyster
    beds, which mud keeps clear of."""
    circles = [(q.centre_east, q.centre_north, q.side_m) for q in quadrats]
    circles += [
        (
            r.centre_east_m,
            r.centre_north_m,
            math.hypot(r.length_m, (r.n_rows - 1) * r.row_spacing_m) / 2,
        )
        for r in s.racks
    ]
    circles += [
        (b.centre_east_m, b.centre_north_m, math.hypot(b.length_m, b.width_m) / 2)
        for b in s.oyster_beds
    ]
    return np.array(circles, np.float64).reshape(-1, 3)


def _sand(
    s: Scenario,
    bounds: tuple[float, float, float, float],
    quadrats: tuple[Quadrat, ...],
    rng: np.random.Generator,
) -> tuple[
    F32Array, F32Array, tuple[ShellPatch, ...], tuple[MudPatch, ...], tuple[RippleTrain, ...]
]:
    """Rippled sand with mud and shell patches: reflectivity and height (m) over
    ``bounds``, the patches and the ripple trains."""
    west, south, east, north = bounds
    res = s.seabed_resolution_m
    shape = (round((north - south) / res), round((east - west) / res))
    e = (west + (np.arange(shape[1], dtype=np.float32) + 0.5) * res)[None, :]
    n = (north - (np.arange(shape[0], dtype=np.float32) + 0.5) * res)[:, None]

    # Sand: texture at four scales; the finest stands for grain-size and shell-hash speckle.
    fine = smooth_noise(rng, shape, res, 0.03)
    texture = smooth_noise(rng, shape, res, 4.0) * np.float32(0.10)
    texture += smooth_noise(rng, shape, res, 1.0) * np.float32(0.10)
    texture += smooth_noise(rng, shape, res, 0.25) * np.float32(0.08)
    texture += fine * np.float32(0.10)

    # Smooth mud: where it lies, the ripples, roughness and texture all but vanish.
    mud = place_mud(rng, s.n_mud_patches, _survey_area(s, bounds), _firm_ground(s, quadrats))
    mud_mask = patch_mask(mud, e, n, rng, 0.8)
    sandy = np.float32(1.0) - mud_mask

    # Two ripple trains with bending crests; shell debris collects in the main train's
    # troughs (brighter there).
    trains = (
        ripple_train(rng, s.ripple_wavelength_m, s.ripple_amplitude_m, s.ripple_bearing_deg,
                     s.ripple_bend_deg, s.ripple_bend_scale_m),
        ripple_train(rng, s.ripple2_wavelength_m, s.ripple2_amplitude_m, s.ripple2_bearing_deg,
                     s.ripple_bend_deg, s.ripple_bend_scale_m),
    )  # fmt: skip
    flat = np.float32(_MUD_RIPPLE) + np.float32(1.0 - _MUD_RIPPLE) * sandy
    height = np.zeros(shape, np.float32)
    for number, train in enumerate(trains):
        defects = smooth_noise(rng, shape, res, 2.5) * np.float32(2.0)
        envelope = np.clip(0.7 + 0.35 * smooth_noise(rng, shape, res, 5.0), 0.15, 1.0)
        envelope *= flat
        relief, sin_phase = paint_ripples(train, e, n, defects, envelope)
        height += relief
        if number == 0:
            texture -= sin_phase * envelope * np.float32(0.06)
        del defects, envelope, relief, sin_phase
    height += fine * (np.float32(0.001) * flat)

    # Shell patches: irregular bright, rough areas.
    patches = []
    for _ in range(s.n_shell_patches):
        pe, pn = rng.uniform(west, east), rng.uniform(south, north)
        radius = float(rng.uniform(0.4, 1.5))
        patches.append(ShellPatch(float(pe), float(pn), radius))
    shells = tuple(patches)
    shell_mask = patch_mask(shells, e, n, rng, 0.4)
    texture += shell_mask * (0.18 + 0.12 * fine)
    height += shell_mask * 0.004 * np.abs(fine)
    del shell_mask, fine

    texture *= np.float32(_MUD_TEXTURE) + np.float32(1.0 - _MUD_TEXTURE) * sandy
    base = np.float32(s.sand_reflectivity) * sandy + np.float32(s.mud_reflectivity) * mud_mask
    refl = base * (1.0 + texture)
    return refl, height, shells, mud, trains


def generate_seabed(
    s: Scenario,
    bounds: tuple[float, float, float, float],
    rng: np.random.Generator,
    shape_rng: np.random.Generator | None = None,
) -> Seabed:
    """Paint the scenario's seabed over ``bounds`` = (west, south, east, north), local
    metres (whole metres keep the cells on a whole-metre UTM grid). ``rng`` draws the
    bottom (``s.seabed_type``: sand, or one of ``bottoms``), ``shape_rng`` the
    undulation (``bathymetry``; needed when ``s.undulation_amplitude_m`` > 0)."""
    west, south, east, north = bounds
    res = s.seabed_resolution_m
    shape = (round((north - south) / res), round((east - west) / res))
    quadrats = quadrat_layout(s)
    kind = s.seabed_type
    shells: tuple[ShellPatch, ...] = ()
    mud: tuple[MudPatch, ...] = ()
    trains: tuple[RippleTrain, ...] = ()
    gravel: tuple[GravelPatch, ...] = ()
    clumps = s  # the scenario the scattered clumps are placed from
    if kind in ("sand", "shell", "gravel"):
        bed = s
        if kind == "shell":
            bed = dataclasses.replace(
                s,
                ripple_amplitude_m=s.ripple_amplitude_m * SHELL_RIPPLE,
                ripple2_amplitude_m=s.ripple2_amplitude_m * SHELL_RIPPLE,
                n_shell_patches=0,
            )
        refl, height, shells, mud, trains = _sand(bed, bounds, quadrats, rng)
        if kind == "shell":
            shell_hash(refl, height, res, rng)
        elif kind == "gravel":
            e = (west + (np.arange(shape[1], dtype=np.float32) + 0.5) * res)[None, :]
            n = (north - (np.arange(shape[0], dtype=np.float32) + 0.5) * res)[:, None]
            gravel = gravel_patches(_survey_area(s, bounds), e, n, res, refl, height, rng)
    else:  # soft mud, bare or with debris: very few clumps on it
        refl, height = soft_mud(s.soft_mud_reflectivity, shape, res, rng)
        clumps = dataclasses.replace(
            s, scattered_clumps_per_m2=s.scattered_clumps_per_m2 * _MUD_CLUMPS, oyster_beds=()
        )

    oysters = place_oysters(clumps, quadrats, bounds, rng)
    canvas = Canvas(
        west,
        north,
        res,
        height,
        np.zeros(shape, np.float32),
        np.zeros(shape, np.float32),
        np.zeros(shape, np.float32),
    )
    paint_oysters(oysters, canvas, rng)
    paint_racks(s.racks, canvas)
    paint_quadrats(quadrats, canvas)
    debris: tuple[Debris, ...] = ()
    if kind == "objects":
        debris = place_debris(_survey_area(s, bounds), _firm_ground(s, quadrats), rng)
        paint_debris(debris, canvas)
    height += canvas.objects
    refl += canvas.alpha * (canvas.refl - refl)
    reflectivity = np.clip(np.rint(refl * 255.0), 1, 255).astype(np.uint8)
    undulation = None
    if s.undulation_amplitude_m > 0:
        if shape_rng is None:
            raise ValueError("an undulating bed needs its generator (shape_rng)")
        undulation = draw_undulation(
            s.undulation_amplitude_m, s.undulation_wavelength_m, s.undulation_bearing_deg, shape_rng
        )
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
        shell_patches=shells,
        mud_patches=mud,
        ripples=trains,
        seabed_type=kind,
        gravel_patches=gravel,
        debris=debris,
        undulation=undulation,
    )
