"""A downward echosounder (a Ping2-class altimeter on the autopilot's serial port).

Frames and units: local grid north/east/down (metres, down from the still water surface
at the survey's start, as everywhere in the simulator); the transducer sits at
``echosounder_x_m/_y_m/_z_m`` (body FRD from the GPS antenna) and looks along the body's
z axis, so roll and pitch tilt its beam. Times are UNIX seconds.

The physics of a sounding. The transducer's ping spreads in a cone of
``echosounder_beam_deg`` (full -3 dB width; a Ping2's 115 kHz beam is about 30 degrees)
and the device reports the FIRST strong return: the nearest point of the bottom inside
the cone. On a bed sloping by angle a with the cone's axis vertical, that is the foot of
the perpendicular (while a is within the half-cone), ``h cos a`` for a vertical distance
h: shorter than the depth below the transducer. It is found by casting rays over the
cone (the axis and rings at 1/3, 2/3 and 3/3 of the half-angle, 8, 12 and 16 rays) and
intersecting each with the bed's surface (the mean plane, the undulation and the height
map's relief: a fixed-point march along the ray), the nearest hit winning.

What it reports (``simulate_echosounder``):

- range noise ``echosounder_noise_m + echosounder_noise_fraction * range`` (1 sigma);
- a signal quality (MAVLink 1-100) from the echo's strength: ``SNR = 30 dB + 10 log10(
  reflectivity / 0.34) - 20 log10(range / 1 m)`` (an extended bottom's echo falls as
  20 log r; 30 dB of margin for sand at 1 m), quality ``40 + 2 SNR`` within 10-100, +-2;
- dropouts: a two-state chain spends ``echosounder_dropout`` of the time with the bottom
  lost, in runs of about a second (bubbles under the hull, a sharp turn); in a run half
  the soundings send no message and half are sent flagged with a signal quality of 1-10
  and the last distance the tracker held;
- false short returns (weed, a fish) in ``echosounder_false_rate`` of the soundings: 15-80
  % of the range, quality 20-60;
- nothing below the transducer's 0.3 m blanking distance (no message).

The message's time_boot_ms is the sounding's ping plus ``echosounder_lag_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from tools.sim.scenarios import Scenario
from tools.sim.seabed import Seabed
from tools.sim.trajectory import Motion, euler_to_matrix

FloatArray = npt.NDArray[np.float64]

MIN_DISTANCE_M = 0.3
"""The transducer's blanking distance: no sounding closer (m)."""
MAX_DISTANCE_M = 30.0
"""The range the autopilot is told the device reaches (m; a Ping2 is rated to 30 m)."""
KIND_OK, KIND_LOW, KIND_MISSING, KIND_FALSE = "ok", "low_signal", "missing", "false_return"
_RINGS = ((0.0, 1), (1.0 / 3.0, 8), (2.0 / 3.0, 12), (1.0, 16))  # (fraction of half-cone, rays)
_MARCH_STEPS = 6
_DROPOUT_RUN_S = 1.0
_SAND_REFLECTIVITY = 0.34


@dataclass(frozen=True)
class Soundings:
    """Per sounding: ``time`` (the message's time_boot, UNIX s), ``ping_time`` (when it
    pinged), the transducer's ``east``/``north`` (local m) and ``depth`` (m below the
    datum), ``vertical_m`` (true distance straight down to the bed, relief included),
    ``nearest_m`` (true nearest bottom in the cone: what a perfect device reports),
    ``reported_m`` (what the message says; NaN where no message), ``sent`` (a message went
    out), ``quality`` (signal_quality 1-100; 0 where none), ``kind`` (``KIND_*``)."""

    time: FloatArray
    ping_time: FloatArray
    east: FloatArray
    north: FloatArray
    depth: FloatArray
    vertical_m: FloatArray
    nearest_m: FloatArray
    reported_m: FloatArray
    sent: npt.NDArray[np.bool_]
    quality: npt.NDArray[np.int64]
    noise_sigma_m: FloatArray
    kind: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.time)


def cone_directions(beam_deg: float) -> FloatArray:
    """Unit ray directions (n, 3) over the cone about the body's +z (FRD)."""
    half = math.radians(beam_deg / 2.0)
    rays = []
    for fraction, count in _RINGS:
        off = fraction * half
        for j in range(count):
            az = 2 * math.pi * j / count
            rays.append([math.sin(off) * math.cos(az), math.sin(off) * math.sin(az), math.cos(off)])
    return np.array(rays)


def bed_depth(seabed: Seabed, east: FloatArray, north: FloatArray) -> FloatArray:
    """Depth of the bed's surface, relief included (m below the datum)."""
    return np.asarray(seabed.depth_at(east, north) - seabed.relief_at(east, north), np.float64)


def cast(seabed: Seabed, origin: FloatArray, direction: FloatArray) -> FloatArray:
    """Distance along rays (``origin`` (..., 3) north/east/down, unit ``direction``
    (..., 3) pointing down) to the bed's surface: the fixed point of ``t = (D(P + t u) -
    z) / u_z`` (converges while the bed's slope along the ray is below the ray's own,
    true of survey beds within a 15-degree half-cone)."""
    uz = np.maximum(direction[..., 2], 1e-3)
    t = (bed_depth(seabed, origin[..., 1], origin[..., 0]) - origin[..., 2]) / uz
    for _ in range(_MARCH_STEPS):
        at = origin + t[..., None] * direction
        t = (bed_depth(seabed, at[..., 1], at[..., 0]) - origin[..., 2]) / uz
    return np.asarray(t, np.float64)


def simulate_echosounder(
    s: Scenario, seabed: Seabed, motion: Motion, times: FloatArray, rng: np.random.Generator
) -> Soundings:
    """The soundings whose messages are stamped ``times`` (UNIX s; module doc)."""
    n = len(times)
    ping_time = np.asarray(times, np.float64) - s.echosounder_lag_s
    at = motion.at(ping_time)
    body = euler_to_matrix(at["heading"], at["pitch"], at["roll"])  # body -> grid NED
    antenna = np.stack([at["north"], at["east"], -at["up"]], axis=1)
    offset = np.array([s.echosounder_x_m, s.echosounder_y_m, s.echosounder_z_m])
    face = antenna + body @ offset
    rays = np.einsum("nij,rj->nri", body, cone_directions(s.echosounder_beam_deg))
    hits = cast(seabed, np.broadcast_to(face[:, None, :], rays.shape), rays)
    nearest = np.min(np.where(hits > 0, hits, np.inf), axis=1)
    best = np.argmin(np.where(hits > 0, hits, np.inf), axis=1)
    down = np.zeros((n, 3))
    down[:, 2] = 1.0
    vertical = cast(seabed, face, down)
    spot = face + nearest[:, None] * rays[np.arange(n), best]
    refl = _reflectivity_at(seabed, spot[:, 1], spot[:, 0])

    sigma = s.echosounder_noise_m + s.echosounder_noise_fraction * nearest
    reported = nearest + rng.normal(0.0, 1.0, n) * sigma
    snr_db = 30.0 + 10.0 * np.log10(np.maximum(refl, 1e-3) / _SAND_REFLECTIVITY)
    snr_db -= 20.0 * np.log10(np.maximum(nearest, 0.1))
    quality = np.clip(np.rint(40.0 + 2.0 * snr_db + rng.normal(0.0, 2.0, n)), 10, 100)
    quality = quality.astype(np.int64)

    # Dropouts: a two-state chain, mean run _DROPOUT_RUN_S lost, ``dropout`` of the time.
    dt = 1.0 / s.echosounder_rate_hz
    p = s.echosounder_dropout
    leave_lost = min(1.0, dt / _DROPOUT_RUN_S)
    enter_lost = min(1.0, leave_lost * p / max(1.0 - p, 1e-9)) if p > 0 else 0.0
    chain = rng.random(n)
    split = rng.random(n)
    false_draw = rng.random(n)
    false_scale = rng.uniform(0.15, 0.8, n)
    false_quality = rng.integers(20, 61, n)
    low_quality = rng.integers(1, 11, n)
    lost = np.zeros(n, bool)
    state = bool(rng.random() < p)
    for k in range(n):
        lost[k] = state
        state = (chain[k] >= leave_lost) if state else (chain[k] < enter_lost)
    kind = np.full(n, KIND_OK, dtype=object)
    fooled = ~lost & (false_draw < s.echosounder_false_rate)
    reported = np.where(fooled, nearest * false_scale, reported)
    quality = np.where(fooled, false_quality, quality)
    kind[fooled] = KIND_FALSE
    kind[lost & (split < 0.5)] = KIND_MISSING
    flagged = lost & (split >= 0.5)
    kind[flagged] = KIND_LOW
    quality = np.where(flagged, low_quality, quality)
    # A flagged sounding repeats the last distance the tracker held.
    held = np.where(lost, np.nan, reported)
    index = np.where(np.isfinite(held), np.arange(n), 0)
    index = np.maximum.accumulate(index)
    reported = np.where(
        flagged, np.where(np.isfinite(held[index]), held[index], reported), reported
    )
    blank = reported < MIN_DISTANCE_M
    kind[blank & (kind != KIND_MISSING)] = KIND_MISSING
    sent = kind != KIND_MISSING
    reported = np.where(sent, reported, np.nan)
    quality = np.where(sent, quality, 0).astype(np.int64)
    return Soundings(
        time=np.asarray(times, np.float64),
        ping_time=ping_time,
        east=face[:, 1],
        north=face[:, 0],
        depth=face[:, 2],
        vertical_m=vertical,
        nearest_m=nearest,
        reported_m=reported,
        sent=np.asarray(sent, bool),
        quality=quality,
        noise_sigma_m=sigma,
        kind=tuple(str(k) for k in kind),
    )


def _reflectivity_at(seabed: Seabed, east: FloatArray, north: FloatArray) -> FloatArray:
    """The bed's reflectivity (0..1) at the nearest cell of local points."""
    col, row = seabed.pixel(east, north)
    h, w = seabed.shape
    c = np.clip(np.rint(col).astype(np.int64), 0, w - 1)
    r = np.clip(np.rint(row).astype(np.int64), 0, h - 1)
    return np.asarray(seabed.reflectivity[r, c], np.float64) / 255.0
