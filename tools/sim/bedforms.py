"""The sand itself: texture, ripple trains, smooth mud and shell patches.

Frames and units: local grid east/north metres; rasters north-up with square cells
(``seabed`` module doc), cell centres given as ``east`` (1, w) and ``north`` (h, 1)
float32 columns.

Ripples. A train is ``amplitude * envelope * (sin phi - 0.2 cos 2 phi)`` (crests sharper
than troughs) with the phase ``phi = k (u . x + warp(x)) + defects(x)``: ``k = 2 pi /
wavelength``, u the unit vector of the train's bearing, and ``warp`` a sum of long plane
waves ``sum_j a_j sin(q_j . x + c_j)`` (metres) whose wave vectors lie mostly along the
crests. The train's local wave vector is ``k (u + grad warp)``: the crests turn by
``ripple_bend_deg`` RMS across the site, over ``ripple_bend_scale_m``, and the local
wavelength changes by about half that fraction (``RippleTrain.local_wave``); the
defects (a 2.5 m random field, 2 rad) bend and fork single crests and the envelope
(a 5 m random field) fades them in patches. Two trains are superposed: the main one and
a second, longer and lower, from another direction (a wave-formed and a current-formed
set, as on a tidal flat).

Mud patches: smooth mud with little texture and almost no relief (``mud_reflectivity``,
a tenth of the ripples, a fifth of the texture): where a registration finds nothing to
hold on to.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
F32Array = npt.NDArray[np.float32]

_WARP_WAVES = 8
_WARP_SPREAD_RAD = math.radians(30.0)  # warp wave vectors about the crest direction
MUD_RADIUS_M = (1.5, 4.0)


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
    # Bicubic interpolation of white noise has a standard deviation of about 0.72.
    grid *= np.float32(1 / 0.72)
    big = cv2.resize(grid, (cw, ch), interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(big[:h, :w])


@dataclass(frozen=True)
class RippleTrain:
    """One ripple train (see the module doc): mean wavelength (m), amplitude (m), grid
    bearing of the mean wave vector (radians), RMS crest turn (radians), and the warp's
    plane waves: wave vectors ``warp_k_east``/``warp_k_north`` (rad/m), amplitudes
    ``warp_amplitude_m``, phases ``warp_phase`` (rad)."""

    wavelength_m: float
    amplitude_m: float
    bearing_rad: float
    bend_rad: float
    warp_k_east: FloatArray
    warp_k_north: FloatArray
    warp_amplitude_m: FloatArray
    warp_phase: FloatArray

    def local_wave(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Local wavelength (m) and grid bearing of the wave vector (radians, crests
        perpendicular to it) at local points (the defects left out)."""
        e, n = np.asarray(east, np.float64)[..., None], np.asarray(north, np.float64)[..., None]
        c = self.warp_amplitude_m * np.cos(
            self.warp_k_east * e + self.warp_k_north * n + self.warp_phase
        )
        ge = math.sin(self.bearing_rad) + np.sum(c * self.warp_k_east, axis=-1)
        gn = math.cos(self.bearing_rad) + np.sum(c * self.warp_k_north, axis=-1)
        return self.wavelength_m / np.hypot(ge, gn), np.arctan2(ge, gn)


def ripple_train(
    rng: np.random.Generator,
    wavelength_m: float,
    amplitude_m: float,
    bearing_deg: float,
    bend_deg: float,
    bend_scale_m: float,
) -> RippleTrain:
    """A train whose crests turn ``bend_deg`` RMS over about ``bend_scale_m``: the warp's
    wave vectors within about 30 degrees of the crest direction, wavelengths 0.7-2.5
    times the scale, amplitudes scaled so that the RMS slope of the warp across the mean
    wave vector is tan(bend)."""
    beta = math.radians(bearing_deg)
    crest = beta + math.pi / 2
    direction = crest + rng.normal(0.0, _WARP_SPREAD_RAD, _WARP_WAVES)
    k = 2 * math.pi / (bend_scale_m * rng.uniform(0.7, 2.5, _WARP_WAVES))
    k_east, k_north = k * np.sin(direction), k * np.cos(direction)
    weight = rng.uniform(0.5, 1.0, _WARP_WAVES)
    phase = rng.uniform(0.0, 2 * math.pi, _WARP_WAVES)
    across = k_east * math.sin(crest) + k_north * math.cos(crest)
    rms = math.sqrt(float(np.sum((weight * across) ** 2)) / 2)
    amplitude = weight * math.tan(math.radians(bend_deg)) / max(rms, 1e-12)
    return RippleTrain(
        wavelength_m, amplitude_m, beta, math.radians(bend_deg), k_east, k_north, amplitude, phase
    )


def paint_ripples(
    train: RippleTrain,
    east: F32Array,
    north: F32Array,
    defects: F32Array,
    envelope: F32Array,
) -> tuple[F32Array, F32Array]:
    """The train's height (m) over the grid and its ``sin phi`` (for the brighter shell
    debris in the troughs). The warp is evaluated exactly as a low-rank product: each
    plane wave ``sin(qe e + qn n + c) = sin(qe e + c) cos(qn n) + cos(qe e + c) sin(qn n)``."""
    e64, n64 = east.astype(np.float64).ravel(), north.astype(np.float64).ravel()
    arg_e = np.outer(train.warp_k_east, e64) + train.warp_phase[:, None]
    arg_n = np.outer(train.warp_k_north, n64)
    a = train.warp_amplitude_m[:, None]
    by_east = np.concatenate([a * np.sin(arg_e), a * np.cos(arg_e)]).astype(np.float32)
    by_north = np.concatenate([np.cos(arg_n), np.sin(arg_n)]).T.astype(np.float32)
    k = np.float32(2 * math.pi / train.wavelength_m)
    phase = by_north @ by_east  # the warp (m), (h, w)
    phase += east * np.float32(math.sin(train.bearing_rad))
    phase += north * np.float32(math.cos(train.bearing_rad))
    phase *= k
    phase += defects
    sin_phase = np.sin(phase)
    del phase
    # sin phi - 0.2 cos 2 phi = sin phi + 0.4 sin^2 phi - 0.2
    height = np.square(sin_phase)
    height *= np.float32(0.4)
    height += sin_phase
    height -= np.float32(0.2)
    height *= envelope
    height *= np.float32(train.amplitude_m)
    return height, sin_phase


@dataclass(frozen=True)
class MudPatch:
    """A patch of smooth mud (local centre, metres; radius metres)."""

    centre_east: float
    centre_north: float
    radius_m: float


@dataclass(frozen=True)
class ShellPatch:
    centre_east: float
    centre_north: float
    radius_m: float


def place_mud(
    rng: np.random.Generator,
    count: int,
    area: tuple[float, float, float, float],
    keep_clear: FloatArray,
) -> tuple[MudPatch, ...]:
    """``count`` patches with centres in ``area`` (west, south, east, north, local m) and
    radii in ``MUD_RADIUS_M``, each kept half a metre clear of the circles ``keep_clear``
    ((n, 3) east, north, radius: the quadrats, racks and oyster beds lie on firm sand)
    when 30 tries allow it."""
    west, south, east, north = area
    patches = []
    for _ in range(count):
        for _attempt in range(30):
            radius = float(rng.uniform(*MUD_RADIUS_M))
            ce, cn = float(rng.uniform(west, east)), float(rng.uniform(south, north))
            gap = np.hypot(keep_clear[:, 0] - ce, keep_clear[:, 1] - cn) - keep_clear[:, 2]
            if np.all(gap > radius + 0.5):
                break
        patches.append(MudPatch(ce, cn, radius))
    return tuple(patches)


class RoundPatch(Protocol):
    """Anything with a local centre and a radius (metres)."""

    @property
    def centre_east(self) -> float: ...
    @property
    def centre_north(self) -> float: ...
    @property
    def radius_m(self) -> float: ...


def patch_mask(
    patches: Sequence[RoundPatch],
    east: F32Array,
    north: F32Array,
    rng: np.random.Generator,
    edge_scale_m: float,
    grow: float = 1.5,
) -> F32Array:
    """Coverage 0..1 of round patches with ragged edges (a random field of features
    ``edge_scale_m`` across moves the edge by up to a third of the radius), each painted
    in its own window of the grid (``east`` (1, w), ``north`` (h, 1) cell centres)."""
    w, h = east.shape[1], north.shape[0]
    resolution = float(east[0, 1] - east[0, 0]) if w > 1 else 1.0
    west, north0 = float(east[0, 0]) - resolution / 2, float(north[0, 0]) + resolution / 2
    mask = np.zeros((h, w), np.float32)
    for p in patches:
        reach = grow * p.radius_m
        c0 = max(0, int((p.centre_east - reach - west) / resolution))
        c1 = min(w, int((p.centre_east + reach - west) / resolution) + 1)
        r0 = max(0, int((north0 - p.centre_north - reach) / resolution))
        r1 = min(h, int((north0 - p.centre_north + reach) / resolution) + 1)
        if c0 >= c1 or r0 >= r1:
            continue
        edge = smooth_noise(rng, (r1 - r0, c1 - c0), resolution, edge_scale_m)
        d = np.hypot(east[:, c0:c1] - p.centre_east, north[r0:r1, :] - p.centre_north)
        d /= np.float32(p.radius_m)
        m = np.clip((1.0 - d + 0.3 * edge) * 4.0, 0.0, 1.0)
        mask[r0:r1, c0:c1] = np.maximum(mask[r0:r1, c0:c1], m)
    return mask
