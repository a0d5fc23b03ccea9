"""A test bed for FMT registration: a seabed and a forward-looking sonar of our own.

The seabed is a reflectivity raster (1 cm) with a random multi-scale texture, sand
ripples, shell patches and a few bright point targets; optionally rows of identical racks
a metre apart (quadrat rows, farm racks): a texture that repeats along east. The sonar
renders polar pings of it from a known pose (each bin's seabed point from the mapper's own
``polar_to_ground``: the bed tests registration, not the projection), with across-beam
blur, speckle, a vertical beam pattern and the artefacts that stay put in the sonar frame
(a near-field band, per-row gain rings, a beam-edge roll-off); the mapper's
``Preprocessor`` then turns them into Cartesian frames exactly as the pipeline does. Pairs
of frames at sonar poses with a known relative pose are what the other ``test_fmt_*``
files register.

Poses: (east, north) metres and heading in radians clockwise from north, of the sonar's
level frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from mapping.fmt import FmtRegistrar
from mapping.polar import FanGeometry, polar_to_ground
from mapping.preprocess import Preprocessor, PreprocessParams
from mapping.se2 import RelativePose

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Seabed:
    """Reflectivity in [0, 1] (rows from north to south), ``res_m`` a pixel, the south-west
    corner at east = north = 0."""

    reflectivity: F32
    res_m: float

    @property
    def size_m(self) -> float:
        return self.reflectivity.shape[0] * self.res_m


def _noise(rng: np.random.Generator, size: int, scale: int) -> F32:
    coarse = rng.standard_normal((size // scale + 3, size // scale + 3)).astype(np.float32)
    return cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC)


def make_seabed(
    rng: np.random.Generator,
    size_m: float = 14.0,
    res_m: float = 0.01,
    ripples: float = 0.35,
    ripple_period_m: float = 0.3,
    bars_period_m: float | None = None,
    bars: float = 0.0,
    texture: float = 1.0,
) -> Seabed:
    """A seabed ``size_m`` square. ripples/bars/texture: amplitudes of the sand ripples
    (crests bent a little, amplitude modulated), of the racks that repeat every
    ``bars_period_m`` east (rows running north-south) and of the random texture."""
    n = round(size_m / res_m)
    y, x = np.mgrid[0:n, 0:n].astype(np.float32) * np.float32(res_m)
    field = np.zeros((n, n), np.float32)
    for scale_m, amplitude in ((0.03, 0.6), (0.09, 0.7), (0.3, 0.5), (1.0, 0.4)):
        field += texture * amplitude * _noise(rng, n, max(round(scale_m / res_m), 1))
    if ripples:
        bend = 0.08 * _noise(rng, n, round(2.0 / res_m))
        envelope = 0.6 + 0.4 * np.tanh(_noise(rng, n, round(1.5 / res_m)))
        phase = 2 * np.pi * ((0.8 * x + 0.6 * y) + bend) / ripple_period_m
        field += ripples * 3.0 * envelope * np.sin(phase).astype(np.float32)
    if bars and bars_period_m:
        # Rows of identical racks: a textured strip that repeats every period east.
        period = round(bars_period_m / res_m)
        strip = rng.standard_normal((n, period)).astype(np.float32)
        strip = cv2.GaussianBlur(np.tile(strip, (1, 3)), (0, 0), 3.0)[:, period : 2 * period]
        strip /= strip.std()
        field += bars * np.tile(strip, (1, n // period + 1))[:, :n]
    field = (field - field.min()) / (field.max() - field.min())
    # Shell patches: clumps of bright grains.
    patches = _noise(rng, n, round(0.8 / res_m)) > 1.2
    grains = rng.random((n, n)) > 0.92
    field = np.where(patches & grains, np.minimum(field + 0.5, 1.0), field)
    # A few bright point targets (a bolt, a shell, a stone).
    targets = np.zeros((n, n), np.float32)
    for _ in range(round(0.3 * size_m * size_m)):
        r, c = rng.integers(0, n, 2)
        targets[r, c] = 1.0
    targets = cv2.GaussianBlur(targets, (0, 0), 1.5 / (res_m / 0.01))
    field = np.clip(field + 20.0 * targets, 0.0, 1.0)
    return Seabed(field.astype(np.float32), res_m)


def bearing_table(n_beams: int, fan_deg: float, edge_ratio: float = 1.3) -> F64:
    """Bearings (radians, ascending), denser in the centre like the real sonar's table."""
    c = (edge_ratio - 1.0) / 3.0
    u = np.linspace(-1.0, 1.0, n_beams)
    return np.radians(0.5 * fan_deg * (u + c * u**3) / (1.0 + c))


class Sonar:
    """A forward-looking sonar over a flat seabed, and the mapper's view of its pings.

    range_m, range_resolution_m: slant range and bin size; altitude_m above the seabed;
    tilt_deg below horizontal; registration_res_m: pixel size of the registered frames.
    """

    def __init__(
        self,
        range_m: float = 5.0,
        n_beams: int = 512,
        fan_deg: float = 130.0,
        range_resolution_m: float = 0.01,
        altitude_m: float = 1.0,
        tilt_deg: float = 15.0,
        registration_res_m: float = 0.02,
        speckle_shape: float | None = 2.0,
        artefacts: float = 1.0,
        seed: int = 0,
    ) -> None:
        self.bearings = bearing_table(n_beams, fan_deg)
        self.n_ranges = round(range_m / range_resolution_m)
        self.range_resolution_m = range_resolution_m
        self.altitude_m = altitude_m
        self.tilt = math.radians(tilt_deg)
        self.speckle_shape = speckle_shape
        slant = (np.arange(self.n_ranges) + 0.5) * range_resolution_m
        # Where each bin meets the seabed: the mapper's own model (the bed tests
        # registration, not the projection, which tests/mapping/test_polar.py covers).
        forward, starboard = polar_to_ground(
            np.broadcast_to(slant[:, None], (slant.size, n_beams)),
            np.broadcast_to(self.bearings[None, :], (slant.size, n_beams)),
            altitude_m,
            self.tilt,
        )
        self.forward, self.starboard = forward, starboard
        # Bins that miss the seabed look far outside it (remap's border is 0).
        self._forward = np.nan_to_num(forward, nan=-1e5).astype(np.float32)
        self._starboard = np.nan_to_num(starboard, nan=-1e5).astype(np.float32)
        depression = np.arcsin(np.clip(altitude_m / slant, 0.0, 1.0))[:, None]
        # Static in the sonar frame: the vertical beam pattern, the beam-edge roll-off, a
        # bright near-field band and per-row gain rings (a stepped TVG, a jittered gain).
        rng = np.random.default_rng(seed)
        aperture = math.radians(20.0) / 2.355
        pattern = np.exp(-0.5 * ((depression - self.tilt) / aperture) ** 2)
        edge = np.cos(0.8 * self.bearings[None, :]) ** 2
        lit = altitude_m / math.sin(self.tilt + math.radians(9.0))
        near = 0.5 * np.exp(-np.clip(slant - lit, 0.0, None) / 0.25)[:, None]
        ideal_db = 30.0 * np.log10(np.maximum(slant, 0.05))
        ring_db = (np.round(ideal_db / 0.75) * 0.75 - ideal_db) + rng.normal(0, 0.2, slant.size)
        rings = (10.0 ** (ring_db / 10.0))[:, None]
        gain = np.where(np.isfinite(forward), pattern * (1.0 + artefacts * (edge - 1.0)), 0.0) * (
            1.0 + artefacts * (rings - 1.0)
        )
        self.gain = gain.astype(np.float32)
        self.near = (artefacts * near * np.isfinite(forward)).astype(np.float32)
        self.fan = FanGeometry.of(
            self.bearings, self.n_ranges, range_resolution_m, altitude_m, self.tilt
        )
        self.preprocessor = Preprocessor(
            self.fan, tilt_deg, PreprocessParams(registration_res_m=registration_res_m)
        )
        self.grid = self.preprocessor.registration_grid
        self.mask = self.preprocessor.registration_tables.mask

    def ping(
        self,
        seabed: Seabed,
        east: float,
        north: float,
        heading: float,
        rng: np.random.Generator,
    ) -> npt.NDArray[np.uint8]:
        """The polar ping (n_ranges, n_beams), 8-bit, of the sonar at that pose."""
        s, c = np.float32(math.sin(heading)), np.float32(math.cos(heading))
        scale = np.float32(1.0 / seabed.res_m)
        rows = seabed.reflectivity.shape[0]
        map_x = (east * scale - 0.5) + (self._forward * s + self._starboard * c) * scale
        map_y = (rows - north * scale - 0.5) - (self._forward * c - self._starboard * s) * scale
        echo = cv2.remap(seabed.reflectivity, map_x, map_y, cv2.INTER_LINEAR)
        echo += np.float32(0.15)
        if self.speckle_shape is not None:
            speckle = rng.standard_gamma(self.speckle_shape, echo.shape, dtype=np.float32)
            speckle *= np.float32(1.0 / self.speckle_shape)
            echo *= cv2.GaussianBlur(speckle, (0, 0), sigmaX=0.7, sigmaY=0.01)
        echo = cv2.GaussianBlur(echo, (0, 0), sigmaX=1.0, sigmaY=0.01)  # beamwidth
        intensity = echo * self.gain + self.near
        intensity += np.float32(0.02) * rng.random(echo.shape, dtype=np.float32)
        return np.clip(255.0 * np.sqrt(intensity * np.float32(0.5)), 0, 255).astype(np.uint8)

    def frame(
        self, seabed: Seabed, pose: tuple[float, float, float], rng: np.random.Generator
    ) -> F32:
        """The registration frame the mapper makes of a ping at ``pose``."""
        return self.preprocessor(self.ping(seabed, *pose, rng)).coarse

    def registrar(self) -> FmtRegistrar:
        return FmtRegistrar(self.grid, self.mask)


def relative(a: tuple[float, float, float], b: tuple[float, float, float]) -> RelativePose:
    """Pose b in the sonar frame of pose a (forward, starboard metres; yaw clockwise)."""
    de, dn = b[0] - a[0], b[1] - a[1]
    s, c = math.sin(a[2]), math.cos(a[2])
    yaw = (b[2] - a[2] + math.pi) % (2 * math.pi) - math.pi
    return RelativePose(s * de + c * dn, c * de - s * dn, yaw)


def moved(a: tuple[float, float, float], rel: RelativePose) -> tuple[float, float, float]:
    """The pose at ``rel`` from pose ``a``."""
    s, c = math.sin(a[2]), math.cos(a[2])
    return (
        a[0] + rel.forward_m * s + rel.starboard_m * c,
        a[1] + rel.forward_m * c - rel.starboard_m * s,
        a[2] + rel.yaw_rad,
    )


def test_a_point_target_lands_where_the_mapper_puts_it() -> None:
    sonar = Sonar()
    seabed = Seabed(np.zeros((800, 800), np.float32), 0.01)
    pose = (4.0, 1.0, 0.3)
    target = moved(pose, RelativePose(3.5, -1.0, 0.0))
    row = round(seabed.reflectivity.shape[0] - target[1] / 0.01 - 0.5)
    col = round(target[0] / 0.01 - 0.5)
    seabed.reflectivity[row - 1 : row + 2, col - 1 : col + 2] = 1.0
    ping = sonar.ping(seabed, *pose, np.random.default_rng(0)).astype(np.float64)
    ping = ping - np.median(ping, axis=1, keepdims=True)
    ping[~(sonar.forward > 2.5)] = 0.0  # the lit seabed, not the near-field band
    bin_, beam = np.unravel_index(int(np.argmax(ping)), ping.shape)
    near = np.zeros(ping.shape, bool)
    near[bin_ - 6 : bin_ + 7, beam - 6 : beam + 7] = True
    bright = near & (ping > 0.5 * ping.max())
    assert abs(float(np.mean(sonar.forward[bright])) - 3.5) < 0.01
    assert abs(float(np.mean(sonar.starboard[bright])) + 1.0) < 0.01
