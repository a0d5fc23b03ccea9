"""Forward model of an Oculus M1200d ping over the seabed.

Frames. The sonar frame is FRD-like: x along the boresight, y to starboard, z completing
a right-handed frame (down when level). The sonar frame is the body frame (FRD) yawed by
``mount_yaw`` and pitched down by ``tilt``: ``R_body_sonar = Rz(mount_yaw) Ry(-tilt)``.
The world frame is local grid north/east/down (metres; down from the still water
surface).

Beams. The Oculus is a line array along the sonar's y axis: beamforming resolves only the
angle to that axis, so a beam at bearing theta (positive to starboard) is a CONE about
it, the points p with ``sin theta = p_y / |p|``. A point of the beam at slant range r is
``p = r (cos theta cos psi, sin theta, cos theta sin psi)``, psi the angle about the
array axis (0 on the boresight plane x-y, positive down); the vertical beam pattern is a
function of psi. (Not the spherical azimuth/elevation model, ``atan2(p_y, p_x) = theta``:
the two agree on the boresight plane, but a wide beam's cone bends down towards the
sonar: at 60 degrees and 2.5 m slant range, on a bed 1 m below a sonar tilted 15
degrees, they put the echo 20-30 cm apart, and the lit swath starts twice as far out at
60 degrees as ahead.)

Geometry (per ping, vectorised over range bins x beams). The echo at slant range r in
beam theta comes from where the beam's cone meets the seabed: the mean plane ``m . P =
D`` (m = (-slope_north, -slope_east, 1)) raised by the relief z there, ``m . P = D -
z |m|``. With w = R_world_sonar^T m and c = D - z |m| - m . S (S the sonar position),
``r (cos theta (w_x cos psi + w_z sin psi) + w_y sin theta) = c``, so
``psi = asin((c / r - w_y sin theta) / rho) - atan2(w_x, w_z)``,
``rho = cos theta hypot(w_x, w_z)``: the near (front) solution. Bins where the argument
leaves [-1, 1] do not reach the seabed (water column). The relief enters by one
fixed-point step (the height under the mean-plane footprint lifts the plane, and the
echo is placed where the cone meets the lifted plane), so raised objects lean towards
the sonar (layover) as they do in real images. The grazing angle on the plane is
``asin(h / r)`` with h the sonar's perpendicular altitude ``(D - m . S) / |m|``. An undulating bed
(``bathymetry``) lifts the plane by its swell U where each bin's cone meets it: ``L =
U(P(L)) / |m|`` is solved per bin by Newton's method (decimetres of swell move a
low-grazing footprint by metres, too far for a single step); the relief then lifts it
further by the fixed-point step above, and the grazing angle and the slope along the
beam are taken on the undulating surface (``h - L``, the swell added to the relief).

Echo intensity (linear, after the sonar's TVG), per bin:
``reflectivity x Lambert(local grazing) x vertical beam pattern(psi) x visibility``,
blurred across beams by the horizontal beamwidth, times speckle (gamma, mean 1,
correlated across neighbouring beams), times the TVG's residual range trend, plus an
exponential noise floor and a near-field ring-down. Local grazing = grazing + the slope
of the height map along the beam; visibility = 0 in acoustic shadows, found along each
beam with a running minimum of psi (a point is hidden when a nearer point of its beam
is seen at a smaller depression angle about the array axis: it pokes above the line of
sight). Then each row gets its gain (TVG applied in steps, a fixed per-row error, the
ping's gain-assist level: the ring artefacts), gamma correction
``(I / full_scale) ** (gamma / 255)`` and 8 bits.

The per-row gain words sent with the ping are ``round(65536 * g)``, g the linear intensity
gain applied to the row relative to the sonar's nominal TVG law (so 65536 = nominal).
The residual trend (``tvg_residual_exponent``) is NOT in the gain words: the sonar does
not know its TVG is off.

Simplified: one fixed-point step of layover (a multi-valued range, where a tall object's
top and the bed behind it share a bin, keeps the bed behind); multipath and surface
echoes are left out.
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
    """Where each (range, beam) bin's cone meets the seabed (float32 arrays, local grid
    north/east metres)."""

    north: F32Array
    east: F32Array
    elevation: F32Array
    """psi, the angle of the echo about the array axis (radians, 0 on the sonar's x-y
    plane, positive down)."""
    valid: npt.NDArray[np.bool_]
    """False where the bin does not reach the seabed (water column)."""
    altitude: float
    """Perpendicular distance from the sonar to the mean plane (m)."""


def footprint(
    model: SonarModel,
    pose: SonarPose,
    seabed: Seabed,
    lift_m: F32Array | None = None,
    angles: bool = True,
) -> Footprint:
    """Intersect every bin's beam cone with the mean plane, or with the plane raised by
    ``lift_m`` (metres above it, per bin; broadcastable to (ranges, beams)): see the
    module doc. ``angles`` False leaves ``elevation`` empty (positions only)."""
    m = np.array([-seabed.slope_north, -seabed.slope_east, 1.0])
    m_norm = float(np.linalg.norm(m))
    s = pose.position_ned
    c0 = seabed.depth0 - float(m @ s)
    w = pose.rotation.T @ m
    alpha = math.atan2(w[0], w[2])
    cos_b = np.cos(model.bearings_rad)
    sin_b = np.sin(model.bearings_rad)
    rho = (cos_b * math.hypot(w[0], w[2])).astype(np.float32)
    r = model.ranges_m.astype(np.float32)[:, None]
    c = np.float32(c0) if lift_m is None else np.float32(c0) - lift_m * np.float32(m_norm)
    q = c / r - (w[1] * sin_b).astype(np.float32)
    q /= rho
    valid = np.abs(q) < np.float32(1.0)
    np.clip(q, np.float32(-1.0), np.float32(1.0), out=q)
    # psi = asin(q) - alpha, so cos psi = k cos alpha + q sin alpha and sin psi =
    # q cos alpha - k sin alpha with k = sqrt(1 - q^2): p / r = (cos theta cos psi,
    # sin theta, cos theta sin psi) turned into the world is k a + q b + d per beam.
    k = np.sqrt(np.float32(1.0) - q * q)
    rot = pose.rotation
    ca, sa = math.cos(alpha), math.sin(alpha)
    out = []
    for axis, origin in ((0, s[0]), (1, s[1])):
        a = ((rot[axis, 0] * ca - rot[axis, 2] * sa) * cos_b).astype(np.float32)
        b = ((rot[axis, 0] * sa + rot[axis, 2] * ca) * cos_b).astype(np.float32)
        d = (rot[axis, 1] * sin_b).astype(np.float32)
        coord = k * a
        coord += q * b
        coord += d
        coord *= r
        coord += np.float32(origin)
        out.append(coord)
    psi = np.arcsin(q) - np.float32(alpha) if angles else np.zeros((0, 0), np.float32)
    return Footprint(out[0], out[1], psi, valid, c0 / m_norm)


def _f32(x: object) -> F32Array:
    return np.asarray(x, np.float32)


def _running_min(values: F32Array) -> F32Array:
    """``np.minimum.accumulate(values, axis=0)`` (the same numbers: a minimum is exact),
    a row at a time, which is several times faster on a C-ordered (ranges, beams) array."""
    out = values.copy()
    for i in range(1, out.shape[0]):
        np.minimum(out[i - 1], out[i], out=out[i])
    return out


def _pixels(seabed: Seabed, fp: Footprint) -> tuple[F32Array, F32Array]:
    """Fractional (col, row) raster coordinates of the footprint (float32)."""
    inv = np.float32(1.0 / seabed.resolution)
    col = (fp.east - np.float32(seabed.west)) * inv - np.float32(0.5)
    row = (np.float32(seabed.north) - fp.north) * inv - np.float32(0.5)
    return col, row


_SWELL_STEPS = 4
_SWELL_PROBE_M = 0.01


def _undulation_lift(model: SonarModel, pose: SonarPose, seabed: Seabed) -> F32Array | None:
    """Per bin, the lift L (m, along the plane's normal) at which the bin's cone meets the
    plane raised by the undulation there: the root of ``f(L) = U(P(L)) / |m| - L``, P(L)
    the footprint on the plane raised by L, by Newton's method with the derivative taken
    over a 1 cm probe (``_SWELL_STEPS`` steps; the step's slope bounded so that grazing
    bins, where the surface faces away, stay put rather than jump). None without one."""
    und = seabed.undulation
    if und is None:
        return None
    m_norm = math.sqrt(1.0 + seabed.slope_east**2 + seabed.slope_north**2)
    probe = np.float32(_SWELL_PROBE_M)

    def residual(lift: F32Array | None) -> F32Array:
        fp = footprint(model, pose, seabed, lift, angles=False)
        return _f32(und.height(fp.east, fp.north) / m_norm)

    lift = residual(None)
    for _ in range(_SWELL_STEPS):
        here = residual(lift)
        ahead = residual(lift + probe)
        slope = np.minimum((ahead - here) / probe - np.float32(1.0), np.float32(-0.2))
        lift = lift - (here - lift) / slope
    return lift


def _mean_echo(model: SonarModel, pose: SonarPose, seabed: Seabed) -> tuple[F32Array, F32Array]:
    """The noiseless echo intensity (linear, after an ideal TVG) per (range, beam), and
    the range column (n_ranges, 1), both float32."""
    border = cv2.BORDER_REPLICATE
    # The undulation (if any) lifts the plane the cone is cut with, solved exactly per
    # bin; then layover, one fixed-point step: the relief under that footprint lifts it.
    swell = _undulation_lift(model, pose, seabed)
    col, row = _pixels(seabed, footprint(model, pose, seabed, swell, angles=False))
    lift = _f32(cv2.remap(seabed.height, col, row, cv2.INTER_LINEAR, borderMode=border))
    if swell is not None:
        lift += swell
    fp = footprint(model, pose, seabed, lift)
    col, row = _pixels(seabed, fp)
    refl = _f32(cv2.remap(seabed.reflectivity, col, row, cv2.INTER_LINEAR, borderMode=border))
    z = _f32(cv2.remap(seabed.height, col, row, cv2.INTER_LINEAR, borderMode=border))
    del col, row, lift

    r = _f32(model.ranges_m)[:, None]
    h: F32Array | np.float32 = np.float32(fp.altitude)
    if seabed.undulation is not None:
        # The grazing angle and the slope along the beam are taken on the undulating
        # surface: the plane's altitude less the swell there, the swell in the relief.
        m_norm = math.sqrt(1.0 + seabed.slope_east**2 + seabed.slope_north**2)
        swell_here = _f32(seabed.undulation.height(fp.east, fp.north) / m_norm)
        z += swell_here
        h = np.maximum(np.float32(fp.altitude) - swell_here, np.float32(0.01))
    ground = np.sqrt(np.maximum(r * r - h * h, np.float32(1e-6)))

    # Acoustic shadows: a bin is hidden when a nearer bin of its beam is seen at a smaller
    # angle psi (its top pokes above this bin's line of sight).
    psi = np.where(fp.valid, fp.elevation, _NO_GROUND)
    below = psi - _running_min(psi)
    below *= r
    visibility = np.clip(1.0 - below * np.float32(1.0 / _SHADOW_SOFTNESS_M), 0.0, 1.0)

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


def _speckle(rng: np.random.Generator, shape_param: float, size: tuple[int, int]) -> F32Array:
    """Gamma(shape_param) / shape_param speckle (mean 1). A half-integer shape is drawn as
    a sum of exponentials, plus for the half ``E sin^2(pi U / 2)`` (Gamma(1/2) = Gamma(1) x
    Beta(1/2, 1/2), and Beta(1/2, 1/2) is the arcsine law): the same distribution as
    numpy's gamma sampler, faster."""
    twice = round(2 * shape_param)
    if abs(2 * shape_param - twice) > 1e-9 or not 1 <= twice <= 6:
        out = rng.standard_gamma(shape_param, size, dtype=np.float32)
    else:
        out = np.zeros(size, np.float32)
        for _ in range(twice // 2):
            out += rng.standard_exponential(size, dtype=np.float32)
        if twice % 2:
            arc = np.sin(rng.random(size, dtype=np.float32) * np.float32(math.pi / 2))
            arc *= arc
            arc *= rng.standard_exponential(size, dtype=np.float32)
            out += arc
    out *= np.float32(1.0 / shape_param)
    return out


def render_ping(
    model: SonarModel,
    pose: SonarPose,
    seabed: Seabed,
    rng: np.random.Generator | None,
    assist_db: float = 0.0,
    bits: int = 8,
) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
    """One ping's image (n_ranges, n_beams), row 0 nearest, 8-bit or (``bits`` 16) the
    same through the same gamma quantised 257 times finer. ``rng`` None renders the
    noiseless mean image (no speckle, no noise floor) for geometry checks."""
    echo, r = _mean_echo(model, pose, seabed)
    if rng is not None:
        speckle = _speckle(rng, model.speckle_shape, echo.shape)
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
    if bits == 16:
        return (pixels * np.float32(257.0) + np.float32(0.5)).astype(np.uint16)
    return (pixels + np.float32(0.5)).astype(np.uint8)
