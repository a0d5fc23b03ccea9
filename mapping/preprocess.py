"""Sonar frame preprocessing (Zhang et al., Sec. III.C), every step switchable.

0. Optional flat-fielding on the polar frame: each range line and beam divided by what
   the sonar's insonification gives it, the running mean of the last seconds' pings
   (``flat_field_s``, off by default), at the ping's altitude.
1. Row-wise equalisation on the polar frame: each range row (scanline) loses its mean
   over the beams, which removes the ring artefacts of per-row gain and TVG residue.
2. Optional denoising: median (k = 5) or non-local means (h = 15, template 7, search 21).
3. Histogram matching to a reference, then CLAHE (clip 1.5, 16 x 16 tiles).
4. Optional Gaussian blur (k = 3, sigma from the kernel size).
5. Polar to Cartesian with the real bearing table and slant-to-ground range through the
   cone beam model, each ping at its own roll, pitch and altitude when given
   (``mapping.polar``), a fan mask that also drops the unlit near field, a
   Hamming-tapered edge weight (``mapping.fmt.hamming_taper``) and each pixel's weight
   by its place in the fan (``mapping.blend.hurtos_weight``, for Hurtós's blending).

Intensities come out as float32 in [0, 1] on a ``SonarGrid``; the mask marks valid pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from mapping.blend import hurtos_weight
from mapping.fmt import hamming_taper
from mapping.grid import SonarGrid
from mapping.polar import (
    Attitude,
    CartesianTables,
    FanGeometry,
    PingProjection,
    fan_grid,
    to_cartesian,
)


@dataclass(frozen=True, slots=True)
class PreprocessParams:
    """Switches and settings of each step (defaults: the paper's chosen scheme)."""

    equalize_rows: bool = True
    denoise: str = "none"  # "none" | "median" | "nlm"
    histogram_match: bool = True
    clahe: bool = True
    clahe_clip: float = 1.5
    clahe_tiles: int = 16
    blur: bool = False
    res_m: float = 0.02
    """Cartesian pixel size (metres) of the frames that are blended into the mosaic (and
    registered for loop closures) while the range lines are ``cell_reference_resolution_m``
    apart or less. The mosaic's own pixel is ``PipelineParams.mosaic_res_m``, whatever the
    range."""
    registration_res_m: float = 0.02
    """Pixel size of the frames that are registered, likewise. 3 cm halves the FFT work,
    but on the simulator at a 5 m range it adds a small yaw bias that drifts the FMT-only
    chain by 4 degrees a minute (against 1 at 2 cm): accuracy first."""
    cell_reference_resolution_m: float = 0.01
    """The sonar's range resolution (m, its range lines' spacing) up to which the frames
    keep ``res_m`` and ``registration_res_m``; coarser lines (a longer range) make both
    cells grow in proportion (``ground_cell_m``). 1 cm: the M1200d's lines up to a 6 m
    range, at which those cells and every pixel-sized setting (tapers, low-pass, peak
    radius, variance window) were chosen and measured (the quadrats, shore, mud and RTK
    surveys at 5 m). Measured on deep seed 1 (10 m range, 1.67 cm lines, single-stage;
    2 cm cells, then 3.3 cm): lanes RMS 13.7 -> 10.2 cm, quadrat spacing 8.5 -> 3.0 cm,
    10 s relative error 11.5 -> 14.4 cm and 0.27 -> 0.29 degrees, 0.77 -> 0.31 s a frame.
    Cells in proportion to the range instead (4 cm) were cheaper (0.20 s) but drifted
    more: 10 s relative error 20.6 cm, heading error 0.64 degrees against 0.34."""
    taper_px: int = 10
    vertical_aperture_deg: float = 20.0
    """Vertical beam width: with tilt and altitude it says where the seabed is lit."""
    near_margin_deg: float = 1.0
    """Extra degrees trimmed from the lit band's near edge, where the beam pattern falls."""
    flat_field_s: float = 0.0
    """Time constant (s) of the running mean that flat-fields each ping; 0: off (the
    default, below). The sonar lights its fan unevenly: the vertical beam's lobe and the
    grazing angle over range, each beam's own gain across it, and the lit band's near
    edge curved across the fan (the cone meets the bed later at the fan's sides). Row
    equalisation takes out the first only; the rest is fixed to the sonar, and every pair
    of frames correlates on it at no motion. Averaged over 100 preprocessed frames it held
    22 % of a single frame's variance on rippled sand (quadrats seed 2) and 38-68 % on mud
    3-5 m deep at a 10.7 m range (field day 6), where 636 of 1,140 registrations locked
    within decimetres of no motion (true motion 0.17-0.64 m) and the accepted ones
    measured 86 % of the way travelled. The mean is kept in range over altitude (a flat
    bed is lit the same way at r / h), so a boat over a slope does not leave its lit band
    behind. Measured, single-stage, 10 s against off: field day 6 (mud, 3-5 m) lanes 641
    -> 213 cm, the registrations' scale 0.86 -> 0.95; rippled sand (quadrats 2) 3.3 ->
    3.4 cm, field day 1 (a slope) 4.7 -> 5.0 cm; but field day 5 (debris on mud, 6 m deep,
    2 Hz, 16.5 m range) 20.7 -> 64 cm (38 cm without the altitude scaling, whose sonar
    altitudes are noisy at 6 m; 34 cm subtracting the mean instead of dividing by it; 89
    cm at 2 s). Off until it is a gain everywhere."""
    flat_field_clip: float = 3.0
    """A ping enters the running mean at most at this many times it: brighter is an
    object's echo (or the speckle's tail: 3 % of a gamma(1.5) speckle's values), which
    would otherwise darken the next frames where it was."""
    flat_field_rows: float = 8.0
    """The running mean is smoothed along range by a Gaussian of this many range lines
    (the lobe and the beams' gains are smooth in range): its speckle falls by about 5x,
    to about 5 % of the mean at 2 Hz."""
    flat_field_floor: float = 0.1
    """Below this fraction of the lit band's median level the mean is held at it: parts of
    the fan darker than -10 dB (the water column left inside the window, a shadow) stay
    dark rather than being raised to the seabed's level with their noise."""


@dataclass(frozen=True, slots=True)
class SonarFrame:
    """A preprocessed Cartesian frame: ``image`` float32 in [0, 1], ``mask`` valid pixels,
    ``weight`` the Hamming-tapered edge weight (0 outside the mask), all on the blending
    grid; ``coarse`` the same frame on the registration grid (0 outside its fan).

    The grids and the fixed fan mask (``Preprocessor.tables.mask``, the lit region on a
    level boat) are the same for every ping; a ping projected at its own attitude lands a
    few centimetres off that region, so ``mask`` varies per ping: it is the fixed mask
    less the pixels this ping's tilted fan does not reach (those are 0 in ``image``,
    ``weight`` and ``coarse``). What the ping covers beyond the fixed mask is not kept.
    ``weight`` is the fixed mask's taper cut to ``mask``; ``fan_weight`` likewise the
    level fan's Hurtós weight (``mapping.blend.hurtos_weight``: 1 at the fan's centre, 0
    at its edges)."""

    image: npt.NDArray[np.float32]
    mask: npt.NDArray[np.bool_]
    weight: npt.NDArray[np.float32]
    coarse: npt.NDArray[np.float32]
    fan_weight: npt.NDArray[np.float32]
    coarse_mask: npt.NDArray[np.bool_] | None = None
    """Where ``coarse`` has data, when the frame needs a window of its own (a ping at its
    own altitude: its lit band moves by decimetres from the fixed fan's); None: the
    registration grid's fixed fan window holds. Cut by the fixed window, such a frame's
    hard edge, fixed to the sonar, would show to the correlation as a peak at no motion
    (``FmtRegistrar.prepare``'s ``mask`` tapers it instead)."""
    own_mask: npt.NDArray[np.bool_] | None = None
    """Likewise ``mask`` on the blending grid (for the registrations made there)."""


def lit_min_range(
    altitude_m: float, tilt_deg: float, aperture_deg: float, margin_deg: float
) -> float:
    """Shortest slant range (m) at which the vertical beam reaches a flat seabed."""
    if altitude_m <= 0:
        return 0.0
    steepest = math.radians(min(tilt_deg + aperture_deg / 2.0 - margin_deg, 89.0))
    return altitude_m / math.sin(steepest) if steepest > 0 else 0.0


def ground_cell_m(res_m: float, range_resolution_m: float, reference_m: float) -> float:
    """The Cartesian cell (metres) of a fan whose range lines are ``range_resolution_m``
    apart: ``res_m`` for lines up to ``reference_m``, ``res_m`` times their ratio for
    coarser ones, to the millimetre (lines a hair coarser keep the reference's cell).

    The sonar's frame is nearly the same at every range: a fixed fan of beams (0.6 degrees
    wide at 1.2 MHz: a cross-range cell of r * 0.0105 rad at range r) and a few hundred
    range lines (the M1200d keeps about range / 600 beyond 6 m; below, its 1.2 MHz pulse
    keeps them at about 1 cm), so its resolution grows with the range on both axes
    once the lines do. A cell in proportion to the range lines keeps a frame's pixels per
    range line (a 2 cm cell is 2 lines of 1 cm at a 5 m range, 2 of 1.67 cm at 10 m) and
    its pixel count and FFT sizes within (600 / 500)^2 = 1.44 times the 5 m fan's, where
    a fixed cell makes them grow with the square of the range (a 10 m fan at 2 cm has 4.2
    times a 5 m fan's pixels, a 17.5 m fan 13 times). The cross-range cell at the far
    edge stays coarser than the pixel (10.5 cm at 10 m against 3.3 cm). Pixel-sized
    settings (the registration's taper, low-pass and peak radius, blending's variance
    window) keep their meaning relative to the sonar's resolution; the registration's
    yaw, a pixel's error over lever arms that grow with the range, errs less than at
    5 m, and its translation errs as the cell grows."""
    if range_resolution_m <= reference_m:
        return res_m
    return max(res_m, round(res_m * range_resolution_m / reference_m, 3))


def equalize_rows(polar: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Subtract each range row's mean over the beams, keep the frame's overall mean."""
    row_mean = polar.mean(axis=1, keepdims=True)
    return polar - row_mean + float(polar.mean())


def _scale_rows(image: npt.NDArray[np.float32], factor: float) -> npt.NDArray[np.float32]:
    """``image`` (polar) with range stretched by ``factor``: row i takes what lay at range
    (i + 0.5) / factor (the last row's value beyond the end)."""
    if abs(factor - 1.0) < 1e-3:
        return image.copy()
    rows, cols = image.shape
    warp = np.array([[1.0, 0.0, 0.0], [0.0, 1.0 / factor, 0.5 / factor - 0.5]])
    return cv2.warpAffine(
        image,
        warp,
        (cols, rows),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def _as_float(image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]) -> npt.NDArray[np.float32]:
    """A ping's polar image as float32 on the 8-bit scale (16-bit pings scaled down)."""
    frame = image.astype(np.float32)
    if image.dtype == np.uint16:
        frame *= 255.0 / 65535.0
    return frame


def _to_uint8(image: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def match_histogram(
    image: npt.NDArray[np.uint8], reference_cdf: npt.NDArray[np.float64]
) -> npt.NDArray[np.uint8]:
    """Map grey levels so the image's cumulative histogram follows ``reference_cdf``
    (256 values, non-decreasing, ending at 1)."""
    counts = np.bincount(image.ravel(), minlength=256).astype(np.float64)
    cdf = np.cumsum(counts) / max(counts.sum(), 1.0)
    lut = np.interp(cdf, reference_cdf, np.arange(256.0))
    return lut.astype(np.uint8)[image]


def histogram_cdf(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.float64]:
    counts = np.bincount(image.ravel(), minlength=256).astype(np.float64)
    return np.cumsum(counts) / max(counts.sum(), 1.0)


@dataclass
class Preprocessor:
    """Preprocesses the frames of one sonar setting; tables are built once per geometry.

    tilt_deg: boresight tilt below horizontal. The histogram reference is the first
    frame's equalised histogram unless ``reference_cdf`` is given. Each ping may come
    with its ``Attitude`` (roll, pitch, altitude); the projection then also needs the
    fan's lever arm and mount yaw (``FanGeometry.of(..., lever_arm_m=, mount_yaw_rad=)``).
    """

    fan: FanGeometry
    tilt_deg: float
    params: PreprocessParams = field(default_factory=PreprocessParams)
    grid: SonarGrid | None = None
    reference_cdf: npt.NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        p = self.params
        self.min_range_m = lit_min_range(
            self.fan.altitude_m, self.tilt_deg, p.vertical_aperture_deg, p.near_margin_deg
        )
        # The cells at this fan's range lines (metres): blending's and registration's.
        lines = self.fan.range_resolution_m
        self.res_m = ground_cell_m(p.res_m, lines, p.cell_reference_resolution_m)
        self.registration_res_m = ground_cell_m(
            p.registration_res_m, lines, p.cell_reference_resolution_m
        )
        if self.grid is None:
            self.grid = fan_grid(self.fan, self.res_m, self.min_range_m)
        self.projection = PingProjection(self.fan, self.grid, self.min_range_m)
        self.tables: CartesianTables = self.projection.level
        self.weight = hamming_taper(self.tables.mask, p.taper_px)
        self.fan_weight = self._fan_weight(self.tables)
        if self.registration_res_m == self.res_m:
            self.registration_grid, self.registration_projection = self.grid, self.projection
        else:
            self.registration_grid = fan_grid(self.fan, self.registration_res_m, self.min_range_m)
            self.registration_projection = PingProjection(
                self.fan, self.registration_grid, self.min_range_m
            )
        self.registration_tables: CartesianTables = self.registration_projection.level

        self._ping_weight: tuple[
            CartesianTables, npt.NDArray[np.float32], npt.NDArray[np.float32]
        ] = (self.tables, self.weight, self.fan_weight)
        first_lit = int(self.min_range_m / self.fan.range_resolution_m)
        self.first_lit_row = min(max(first_lit, 0), self.fan.n_ranges - 1)
        self._clahe = cv2.createCLAHE(
            clipLimit=p.clahe_clip, tileGridSize=(p.clahe_tiles, p.clahe_tiles)
        )
        self._flat: npt.NDArray[np.float32] | None = None  # running mean, at the fan's altitude
        self._flat_time = math.nan
        self._flat_count = 0

    def flatten(
        self,
        frame: npt.NDArray[np.float32],
        altitude_m: float | None,
        time: float | None,
        divide: bool = True,
    ) -> npt.NDArray[np.float32]:
        """Step 0: ``frame`` (polar, float) divided by the sonar's insonification, the
        running mean of the pings before it (``PreprocessParams.flat_field_s``), at the
        ping's brightness; then the mean takes this ping in. ``time``: the ping's stamp
        (s; None: the mean is of every ping so far). ``divide`` False: the mean only takes
        the ping in (a ping not looked at, for the pings after it), ``frame`` returned."""
        p = self.params
        lit = frame[self.first_lit_row :]
        gain = float(lit.mean()) if lit.size else 0.0
        if p.flat_field_s <= 0 or gain <= 0:
            return frame
        scale = 1.0
        h0 = self.fan.altitude_m
        if altitude_m is not None and h0 > 0 and altitude_m > 0:
            scale = altitude_m / h0
        here = frame * np.float32(1.0 / gain)
        at_reference = _scale_rows(here, 1.0 / scale)  # the ping seen from the fan's altitude
        if self._flat is None:
            self._flat = at_reference
        reference = self._smoothed(self._flat)
        out = frame
        if divide:
            mean = _scale_rows(reference, scale)
            lit_mean = mean[self.first_lit_row :]
            level = float(np.median(lit_mean)) if lit_mean.size else 1.0
            floor = np.float32(max(p.flat_field_floor * level, 1e-6))
            out = (here / np.maximum(mean, floor) * np.float32(gain * level)).astype(
                np.float32, copy=False
            )
        # Then the mean takes this ping in: a plain mean of the pings so far until they
        # span the time constant, a running one after.
        dt = 0.0
        if time is not None:
            if math.isfinite(self._flat_time):
                dt = max(time - self._flat_time, 0.0)
            self._flat_time = time
        self._flat_count += 1
        alpha = max(1.0 - math.exp(-dt / p.flat_field_s), 1.0 / self._flat_count)
        # What is far brighter than the mean (an object, a rock, the strong tail of the
        # speckle) is the seabed's, not the sonar's: it enters at most ``flat_field_clip``
        # times the mean, so it leaves no dark ghost in the frames after it.
        clipped = np.minimum(at_reference, reference * np.float32(p.flat_field_clip))
        cv2.addWeighted(self._flat, 1.0 - alpha, clipped, alpha, 0.0, dst=self._flat)
        return out

    def observe(
        self,
        image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
        attitude: Attitude | None = None,
        time: float | None = None,
    ) -> None:
        """A ping that is not preprocessed still enters the flat field's running mean, so
        the pings looked at after it are flattened as in the pass that saw them all."""
        if self.params.flat_field_s <= 0:
            return
        frame = _as_float(image)
        altitude = attitude.altitude_m if attitude is not None else None
        self.flatten(frame, altitude, time, divide=False)

    def _smoothed(self, mean: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        sigma = self.params.flat_field_rows
        if sigma <= 0:
            return mean
        return cv2.GaussianBlur(
            mean, (1, 0), sigmaX=0.0, sigmaY=sigma, borderType=cv2.BORDER_REPLICATE
        )

    def polar(
        self,
        image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
        altitude_m: float | None = None,
        time: float | None = None,
    ) -> npt.NDArray[np.uint8]:
        """Steps 0-4 on the polar frame (rows = ranges), as 8-bit; ``altitude_m`` and
        ``time`` the ping's, for the flat field."""
        p = self.params
        frame = _as_float(image)
        frame = self.flatten(frame, altitude_m, time)
        lit = frame[self.first_lit_row :]
        if p.equalize_rows:
            lit = equalize_rows(lit)
        out = np.zeros(frame.shape, np.uint8)
        lit8 = _to_uint8(lit)
        if p.denoise == "median":
            lit8 = cv2.medianBlur(lit8, 5)
        elif p.denoise == "nlm":
            lit8 = cv2.fastNlMeansDenoising(
                lit8, None, h=15, templateWindowSize=7, searchWindowSize=21
            )
        elif p.denoise != "none":
            raise ValueError(f"unknown denoise method {p.denoise!r} (none, median, nlm)")
        if p.histogram_match:
            if self.reference_cdf is None:
                self.reference_cdf = histogram_cdf(lit8)
            lit8 = match_histogram(lit8, self.reference_cdf)
        if p.clahe:
            lit8 = self._clahe.apply(lit8)
        if p.blur:
            lit8 = cv2.GaussianBlur(lit8, (3, 3), 0)
        out[self.first_lit_row :] = lit8
        return out

    def __call__(
        self,
        image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
        attitude: Attitude | None = None,
        time: float | None = None,
    ) -> SonarFrame:
        """All steps: a polar ping image (n_ranges, n_beams) to a Cartesian SonarFrame,
        projected at the ping's ``attitude`` (None: level at the fan's altitude); ``time``
        its stamp (s), for the flat field's running mean."""
        polar = self.polar(image, attitude.altitude_m if attitude is not None else None, time)
        tables = self.projection.tables(attitude)
        registration_tables = self.registration_projection.tables(attitude)
        scale = np.float32(1.0 / 255.0)
        cart = to_cartesian(polar, tables) * scale
        coarse = (
            cart
            if registration_tables is tables
            else to_cartesian(polar, registration_tables) * scale
        )
        weight, fan_weight = self._weights(tables)
        # A ping at its own altitude (the seabed model's) gets a window of its own: its lit
        # band moves by decimetres from ping to ping, and cut by the fixed fan's window its
        # far edge, fixed to the sonar, shows to the correlation as a peak at no motion.
        # Measured on a sloping shore (the sonar 0.8-2 m above the bed, the true altitude
        # and slope given per ping): with the fixed window wherever the mask stayed within
        # the taper, one registration in twenty between frames 1.6-1.8 m up measured no
        # motion, lanes 41 cm apart; with every such frame in its own window, 3.2 cm. A
        # ping that only rolls and pitches keeps the fixed window, as before (a frame
        # whose mask leaves part of the window's flat core out also needs its own: that
        # moves today's surveys' maps and waits for a run of the accuracy matrix).
        own = (
            attitude is not None
            and attitude.altitude_m is not None
            and attitude.altitude_m != self.fan.altitude_m
        )
        return SonarFrame(
            cart,
            tables.mask,
            weight,
            coarse,
            fan_weight,
            coarse_mask=registration_tables.mask if own else None,
            own_mask=tables.mask if own else None,
        )

    def _weights(
        self, tables: CartesianTables
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """The level fan's taper and Hurtós weight cut to a ping's mask."""
        if self._ping_weight[0] is not tables:
            zero = np.float32(0.0)
            self._ping_weight = (
                tables,
                np.where(tables.mask, self.weight, zero),
                np.where(tables.mask, self.fan_weight, zero),
            )
        return self._ping_weight[1], self._ping_weight[2]

    def _fan_weight(self, tables: CartesianTables) -> npt.NDArray[np.float32]:
        """Each pixel's Hurtós weight by its beam bearing and slant range in the level
        fan, whose range band runs from the first lit range to the last bin's far edge."""
        fan = self.fan
        bearings = np.asarray(fan.bearings_rad)
        bearing = np.interp(tables.map_beam, np.arange(bearings.size), bearings)
        slant = (tables.map_range.astype(np.float64) + 0.5) * fan.range_resolution_m
        near = max(self.min_range_m, 0.5 * fan.range_resolution_m)
        far = (fan.n_ranges - 0.5) * fan.range_resolution_m
        return hurtos_weight(
            bearing, slant, tables.mask, (float(bearings[0]), float(bearings[-1])), (near, far)
        )
