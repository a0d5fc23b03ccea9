"""Forward model of an Oculus M1200d ping over the seabed.

Frames. The sonar frame is FRD-like: x along the boresight, y to starboard, z completing
a right-handed frame (down when level). A beam at bearing theta (positive to starboard)
and elevation phi (positive below the sonar's x-y plane) looks along
``d = (cos phi cos theta, cos phi sin theta, sin phi)``. The sonar frame is the body
frame (FRD) yawed by ``mount_yaw`` and pitched down by ``tilt``:
``R_body_sonar = Rz(mount_yaw) Ry(-tilt)``. The world frame is local grid
north/east/down (metres; down from the still water surface).

Geometry (per ping, vectorised over range bins x beams). The echo at slant range r in
beam theta comes from where the beam's vertical arc meets the seabed's mean plane
``m . p = D`` (m = (-slope_north, -slope_east, 1)). With w = R_world_sonar^T m,
``a(theta) = w_x cos theta + w_y sin theta``, ``b = w_z``, ``c = D - m . S`` (S the sonar
position): ``a cos phi + b sin phi = c / r``, so
``phi = asin(c / (r rho)) - atan2(a, b)``, rho = hypot(a, b). Bins with
``c / (r rho) > 1`` are nearer than the seabed: water column. The grazing angle on the
plane is ``asin(h / r)`` with h the sonar's perpendicular altitude ``c / |m|``.

Echo intensity (linear, after the sonar's TVG), per bin:
``reflectivity x Lambert(local grazing) x vertical beam pattern(phi) x visibility``,
blurred across beams by the horizontal beamwidth, times speckle (gamma, mean 1,
correlated across neighbouring beams), times the TVG's residual range trend, plus an
exponential noise floor and a near-field ring-down. Local grazing = grazing + the slope
of the height map along the beam; visibility = 0 in acoustic shadows, found along each
beam with a running minimum of the depression tangent ``(h - z) / ground_range`` (a
point is hidden when a nearer point pokes above its line of sight). Then each row gets
its gain (TVG applied in steps, a fixed per-row error, the ping's gain-assist level: the
ring artefacts), gamma correction ``(I / full_scale) ** (gamma / 255)`` and 8 bits.

The per-row gain words sent with the ping are ``round(65536 * g)``, g the linear intensity
gain applied to the row relative to the sonar's nominal TVG law (so 65536 = nominal).
The residual trend (``tvg_residual_exponent``) is NOT in the gain words: the sonar does
not know its TVG is off.

Simplified: the vertical fan is the standard spherical (azimuth/elevation) model, not
the cone of a line array; echoes are placed at the mean plane's range (no layover from
object heights, a few millimetres here); multipath and surface echoes are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from tools.sim.scenarios import Scenario
from tools.sim.seabed import Seabed

FloatArray = npt.NDArray[np.float64]
F32Array = npt.NDArray[np.float32]

GAIN_WORD_UNITY = 65536
_NO_GROUND = np.float32(1e6)  # depression tangent of bins that do not reach the seabed
_SHADOW_SOFTNESS_M = 0.003  # height margin over which a shadow edge fades (anti-aliasing)
_RINGDOWN_INTENSITY = 0.6
_RINGDOWN_M = 0.03
_SIDELOBE = 0.002  # two-way vertical pattern floor outside the main lobe


def bearing_table(n_beams: int, fan_deg: float, edge_ratio: float) -> FloatArray:
    """Beam bearings (radians, ascending, positive to starboard), non-uniform like the
    real tables: ``theta = A (u + c u^3)``, u uniform in [-1, 1], with c chosen so the
    spacing at the edges is ``edge_ratio`` times the centre spacing, quantised to 1/100
    degree as the sonar sends them. (The real 256-beam +-30 degree table fits this form
    to 0.03 degree with an edge ratio of about 1.18.)"""
    c = (edge_ratio - 1.0) / 3.0
    half = fan_deg / 2.0
    u = np.linspace(-1.0, 1.0, n_beams)
    deg = half * (u + c * u**3) / (1.0 + c)
    return np.radians(np.rint(deg * 100.0) / 100.0)


def rot_y(angle: float) -> FloatArray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> FloatArray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def mount_rotation(mount_yaw_rad: float, tilt_rad: float) -> FloatArray:
    """Sonar -> body (FRD) rotation: yawed by mount_yaw, boresight pitched down by tilt."""
    return rot_z(mount_yaw_rad) @ rot_y(-tilt_rad)


@dataclass(frozen=True)
class SonarModel:
    """Fixed parameters of the simulated sonar and the per-beam/per-range precomputations.

    bearings_rad: (n_beams,); ranges_m: (n_ranges,) bin centres ``(i + 0.5) * res``;
    row_gain_db: (n_ranges,) the gain error the sonar applies on each row (the rings), dB.
    """

    bearings_rad: FloatArray
    range_resolution_m: float
    ranges_m: FloatArray
    mount_offset_m: FloatArray
    mount_rotation: FloatArray
    vertical_aperture_rad: float
    beam_blur_sigma: float
    """Across-beam blur (in beams) standing for the horizontal beamwidth."""
    full_scale: float
    noise_floor: float
    speckle_shape: float
    tvg_residual: F32Array
    row_gain_db: F32Array
    gamma: int

    @classmethod
    def from_scenario(cls, s: Scenario, rng: np.random.Generator) -> SonarModel:
        bearings = bearing_table(s.n_beams, s.fan_deg, s.beam_edge_ratio)
        n_ranges = round(s.range_m / s.range_resolution_m)
        ranges = (np.arange(n_ranges, dtype=np.float64) + 0.5) * s.range_resolution_m
        spacing = float(np.degrees(np.median(np.diff(bearings)))) if s.n_beams > 1 else 1.0
        # TVG applied in steps: the ideal law (30 log r for an extended seabed, plus
        # absorption) rounded to the step: a sawtooth error that grows denser with range.
        ideal_db = 30.0 * np.log10(np.maximum(ranges, 0.05)) + 0.6 * ranges
        step = s.tvg_step_db
        stepped = np.round(ideal_db / step) * step if step > 0 else ideal_db
        row_gain_db = (stepped - ideal_db) + rng.normal(0.0, s.row_gain_jitter_db, n_ranges)
        return cls(
            bearings_rad=bearings,
            range_resolution_m=s.range_resolution_m,
            ranges_m=ranges,
            mount_offset_m=np.array([s.mount_x_m, s.mount_y_m, s.mount_z_m]),
            mount_rotation=mount_rotation(math.radians(s.mount_yaw_deg), math.radians(s.tilt_deg)),
            vertical_aperture_rad=math.radians(s.vertical_aperture_deg),
            beam_blur_sigma=s.horizontal_beamwidth_deg / spacing / 2.355,
            full_scale=s.full_scale,
            noise_floor=s.noise_floor,
            speckle_shape=s.speckle_shape,
            tvg_residual=((ranges / 2.5) ** s.tvg_residual_exponent).astype(np.float32),
            row_gain_db=row_gain_db.astype(np.float32),
            gamma=s.gamma,
        )

    @property
    def n_beams(self) -> int:
        return len(self.bearings_rad)

    @property
    def n_ranges(self) -> int:
        return len(self.ranges_m)

    def gain_words(self, assist_db: float) -> FloatArray:
        """The per-row gain words of a ping with gain-assist level ``assist_db``."""
        g = 10.0 ** ((self.row_gain_db.astype(np.float64) + assist_db) / 10.0)
        return np.rint(GAIN_WORD_UNITY * g)


@dataclass(frozen=True)
class SonarPose:
    """Where the sonar head is and how it points, world = local grid north/east/down.

    position_ned: (3,) metres (down from the still water surface);
    rotation: (3, 3) sonar -> world.
    """

    position_ned: FloatArray
    rotation: FloatArray


def sonar_pose(antenna_ned: FloatArray, body_to_world: FloatArray, model: SonarModel) -> SonarPose:
    """The sonar head's pose from the antenna position and the body attitude."""
    position = antenna_ned + body_to_world @ model.mount_offset_m
    return SonarPose(position, body_to_world @ model.mount_rotation)


@dataclass(frozen=True)
class Footprint:
    """Where each (range, beam) bin meets the seabed's mean plane (float32 arrays)."""

    north: F32Array
    east: F32Array
    elevation: F32Array
    """Elevation phi of the echo in the sonar frame (radians, positive down)."""
    valid: npt.NDArray[np.bool_]
    """False where the bin is nearer than the seabed (water column)."""
    altitude: float
    """Perpendicular distance from the sonar to the mean plane (m)."""


def footprint(model: SonarModel, pose: SonarPose, seabed: Seabed) -> Footprint:
    """Intersect every bin's vertical arc with the mean plane (see the module doc)."""
    m = np.array([-seabed.slope_north, -seabed.slope_east, 1.0])
    m_norm = float(np.linalg.norm(m))
    s = pose.position_ned
    c = seabed.depth0 - float(m @ s)
    w = pose.rotation.T @ m
    cos_b = np.cos(model.bearings_rad)
    sin_b = np.sin(model.bearings_rad)
    a = w[0] * cos_b + w[1] * sin_b
    rho = np.hypot(a, w[2])
    alpha = np.arctan2(a, w[2])
    r = model.ranges_m.astype(np.float32)[:, None]
    q = np.float32(c) / (r * rho.astype(np.float32)[None, :])
    valid = q < 1.0
    phi = np.arcsin(np.minimum(q, np.float32(1.0))) - alpha.astype(np.float32)[None, :]
    rc = r * np.cos(phi)
    rs = r * np.sin(phi)
    rot = pose.rotation
    a_n = (rot[0, 0] * cos_b + rot[0, 1] * sin_b).astype(np.float32)
    a_e = (rot[1, 0] * cos_b + rot[1, 1] * sin_b).astype(np.float32)
    north = np.float32(s[0]) + rc * a_n[None, :] + rs * np.float32(rot[0, 2])
    east = np.float32(s[1]) + rc * a_e[None, :] + rs * np.float32(rot[1, 2])
    return Footprint(north, east, phi, valid, c / m_norm)


def _f32(x: object) -> F32Array:
    return np.asarray(x, np.float32)


def _running_min(values: F32Array) -> F32Array:
    """``np.minimum.accumulate(values, axis=0)`` (the same numbers: a minimum is exact),
    a row at a time, which is several times faster on a C-ordered (ranges, beams) array."""
    out = values.copy()
    for i in range(1, out.shape[0]):
        np.minimum(out[i - 1], out[i], out=out[i])
    return out


def _mean_echo(model: SonarModel, pose: SonarPose, seabed: Seabed) -> tuple[F32Array, F32Array]:
    """The noiseless echo intensity (linear, after an ideal TVG) per (range, beam), and
    the range column (n_ranges, 1), both float32."""
    fp = footprint(model, pose, seabed)
    col, row = seabed.pixel(fp.east.astype(np.float64), fp.north.astype(np.float64))
    col32, row32 = _f32(col), _f32(row)
    border = cv2.BORDER_REPLICATE
    refl = _f32(cv2.remap(seabed.reflectivity, col32, row32, cv2.INTER_LINEAR, borderMode=border))
    z = _f32(cv2.remap(seabed.height, col32, row32, cv2.INTER_LINEAR, borderMode=border))

    r = _f32(model.ranges_m)[:, None]
    h = np.float32(fp.altitude)
    ground = _f32(np.broadcast_to(np.sqrt(np.maximum(r * r - h * h, np.float32(1e-6))), z.shape))

    # Acoustic shadows: a bin is hidden when a nearer bin of its beam subtends a smaller
    # depression angle (its top pokes above this bin's line of sight).
    tan_dep = _f32(np.where(fp.valid, (h - z) / ground, _NO_GROUND))
    nearest = _running_min(tan_dep)
    visibility = np.clip(1.0 - (tan_dep - nearest) * ground / _SHADOW_SOFTNESS_M, 0.0, 1.0)

    # Local grazing angle: the plane's grazing angle plus the slope of the relief along
    # the beam (faces towards the sonar light up, faces away go dark).
    slope = np.zeros_like(z)
    slope[1:] = (z[1:] - z[:-1]) / np.maximum(ground[1:] - ground[:-1], np.float32(1e-4))
    slope = np.clip(slope, np.float32(-5.0), np.float32(5.0))
    sin_g = np.minimum(h / r, np.float32(1.0))
    cos_g = np.sqrt(np.float32(1.0) - sin_g * sin_g)
    sin_local = (sin_g + cos_g * slope) / np.sqrt(np.float32(1.0) + slope * slope)
    lambert = np.square(np.maximum(sin_local, np.float32(0.0)))

    ap = np.float32(model.vertical_aperture_rad)
    pattern = np.exp(np.float32(-4.0 * math.log(2.0)) * np.square(fp.elevation / ap))
    pattern += np.float32(_SIDELOBE)

    echo = refl * np.float32(1 / 255) * lambert * pattern * visibility
    echo = _f32(np.where(fp.valid, echo, np.float32(0.0)))
    blur = max(model.beam_blur_sigma, 0.3)
    return _f32(cv2.GaussianBlur(echo, (0, 0), sigmaX=blur, sigmaY=0.5)), r


def render_ping(
    model: SonarModel,
    pose: SonarPose,
    seabed: Seabed,
    rng: np.random.Generator | None,
    assist_db: float = 0.0,
) -> npt.NDArray[np.uint8]:
    """One ping's 8-bit image (n_ranges, n_beams), row 0 nearest. ``rng`` None renders the
    noiseless mean image (no speckle, no noise floor) for geometry checks."""
    echo, r = _mean_echo(model, pose, seabed)
    if rng is not None:
        speckle = rng.standard_gamma(model.speckle_shape, echo.shape, dtype=np.float32)
        speckle *= np.float32(1.0 / model.speckle_shape)
        # Beams overlap (0.6 degree beams ~0.25 degree apart): neighbours share speckle.
        echo *= _f32(cv2.GaussianBlur(speckle, (0, 0), sigmaX=0.7, sigmaY=0.01))
        noise = rng.standard_exponential(echo.shape, dtype=np.float32)
        noise *= np.float32(model.noise_floor)
    else:
        noise = np.full(echo.shape, model.noise_floor, np.float32)
    echo *= model.tvg_residual[:, None]
    echo += np.float32(_RINGDOWN_INTENSITY) * np.exp(-r / np.float32(_RINGDOWN_M))
    echo += noise

    gain = _f32(10.0 ** ((model.row_gain_db + np.float32(assist_db)) / np.float32(10.0)))
    echo *= gain[:, None]
    exponent = np.float32(model.gamma / 255.0)
    pixels = np.float32(255.0) * np.power(
        np.minimum(echo * np.float32(1.0 / model.full_scale), np.float32(1.0)), exponent
    )
    return (pixels + np.float32(0.5)).astype(np.uint8)
