"""The boat's true motion: a lawnmower path and how a small boat follows it.

Frames: local grid east/north (metres, see ``site.py``), up = height above the still
water surface (metres); headings are grid headings in radians clockwise from grid north;
attitude is FRD (roll positive starboard down, pitch positive bow up). The reference
point is the GPS antenna.

The path is lanes joined by U-turns of a fixed radius (two quarter circles and a straight
when the lanes are wider apart than the turn diameter). The boat starts at rest at the
run-in, speeds up, holds the survey speed (with a small wobble), and stops at the end of
the run-out. It follows the path with a small random cross-track error; in a current it
crabs: the heading points along its velocity through the water (survey speed along the
course minus the current), and the heading oscillates a few degrees about that. Waves add
roll, pitch and heave: sums of sinusoids of 1.5-4 s periods around the chop's dominant
period with random phases (2-3 degrees RMS of roll and pitch, a few cm of heave on a
field day). The tide (``tide_rate_mps``) lifts the water, and the boat with it, at a
steady rate from the survey's start: ``up`` is above the still water surface AT THE
START (the datum every depth in the simulator is measured from). Everything is sampled
on a dense 200 Hz grid and smoothed, so velocities, accelerations and body rates are
finite differences of smooth signals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter1d

from tools.sim.scenarios import Scenario

FloatArray = npt.NDArray[np.float64]

DENSE_RATE_HZ = 200.0
_STOP_SPEED_MPS = 0.3  # below this the course comes from the path, not the velocity


@dataclass(frozen=True)
class Segment:
    """One piece of path: a straight (turn 0) or an arc turning right (+1) or left (-1).

    start_east/north: metres; bearing: grid bearing of the tangent at the start (radians).
    """

    start_east: float
    start_north: float
    bearing: float
    length: float
    turn: int = 0
    radius: float = 0.0

    def end(self) -> tuple[float, float, float]:
        """Position (east, north) and tangent bearing at the end of the segment."""
        e, n, b = _eval_segment(self, np.array([self.length]))
        return float(e[0]), float(n[0]), float(b[0])


def _eval_segment(seg: Segment, u: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    if seg.turn == 0:
        b = np.full_like(u, seg.bearing)
        return (
            seg.start_east + u * math.sin(seg.bearing),
            seg.start_north + u * math.cos(seg.bearing),
            b,
        )
    d = float(seg.turn)
    centre_b = seg.bearing + d * math.pi / 2
    ce = seg.start_east + seg.radius * math.sin(centre_b)
    cn = seg.start_north + seg.radius * math.cos(centre_b)
    b = seg.bearing + d * u / seg.radius
    return (
        ce + seg.radius * np.sin(b - d * math.pi / 2),
        cn + seg.radius * np.cos(b - d * math.pi / 2),
        b,
    )


@dataclass(frozen=True)
class SurveyPath:
    """The planned path: its segments, and the lanes (start and end, local east/north m,
    without the run-in and run-out)."""

    segments: tuple[Segment, ...]
    lanes: tuple[tuple[float, float, float, float], ...] = ()

    @property
    def length(self) -> float:
        return sum(s.length for s in self.segments)

    def evaluate(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Position (east, north, m) and unwrapped tangent bearing (rad) at arc lengths s."""
        starts = np.cumsum([0.0] + [seg.length for seg in self.segments[:-1]])
        s = np.clip(np.asarray(s, np.float64), 0.0, self.length)
        index = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(starts) - 1)
        east = np.empty_like(s)
        north = np.empty_like(s)
        bearing = np.empty_like(s)
        for i, seg in enumerate(self.segments):
            sel = index == i
            if np.any(sel):
                east[sel], north[sel], bearing[sel] = _eval_segment(seg, s[sel] - starts[i])
        return east, north, bearing


def lawnmower(s: Scenario) -> SurveyPath:
    """The survey path: n_lanes lanes of lane_length_m, lane_spacing_m apart, centred on
    the survey centre, the first along lane_bearing_deg, with U-turns between them.

    Lanes in ``skip_lanes`` (numbered from 0 across) are planned but not driven: the boat
    turns from the lane before them straight into the lane after, a wider U-turn, and the
    lanes it drives keep alternating direction. ``lanes`` holds the driven lanes only."""
    beta = math.radians(s.lane_bearing_deg)
    across = (math.sin(beta + math.pi / 2), math.cos(beta + math.pi / 2))
    driven = [lane for lane in range(s.n_lanes) if lane not in s.skip_lanes]
    segments: list[Segment] = []
    lanes: list[tuple[float, float, float, float]] = []
    for k, lane in enumerate(driven):
        offset = (lane - (s.n_lanes - 1) / 2) * s.lane_spacing_m
        bearing = beta if k % 2 == 0 else beta + math.pi
        half = s.lane_length_m / 2
        length = s.lane_length_m
        before = s.run_in_m if k == 0 else 0.0
        after = s.run_in_m if k == len(driven) - 1 else 0.0
        start_e = s.survey_centre_east_m + offset * across[0] - (half + before) * math.sin(bearing)
        start_n = s.survey_centre_north_m + offset * across[1] - (half + before) * math.cos(bearing)
        segments.append(Segment(start_e, start_n, bearing, length + before + after))
        lane_e = start_e + before * math.sin(bearing)
        lane_n = start_n + before * math.cos(bearing)
        lanes.append(
            (
                lane_e,
                lane_n,
                lane_e + length * math.sin(bearing),
                lane_n + length * math.cos(bearing),
            )
        )
        if k == len(driven) - 1:
            break
        turn = 1 if k % 2 == 0 else -1  # the next lane is always to the right of lane 0
        width = (driven[k + 1] - lane) * s.lane_spacing_m
        radius = min(s.turn_radius_m, width / 2)
        e, n, b = segments[-1].end()
        straight = width - 2 * radius
        if straight < 1e-9:
            segments.append(Segment(e, n, b, math.pi * radius, turn, radius))
            continue
        quarter = Segment(e, n, b, math.pi / 2 * radius, turn, radius)
        segments.append(quarter)
        e, n, b = quarter.end()
        segments.append(Segment(e, n, b, straight))
        e, n, b = segments[-1].end()
        segments.append(Segment(e, n, b, math.pi / 2 * radius, turn, radius))
    return SurveyPath(tuple(segments), tuple(lanes))


@dataclass(frozen=True)
class Motion:
    """The true motion sampled densely (``DENSE_RATE_HZ``) from ``time[0]`` (UNIX s).

    east/north: antenna position, local grid frame (m); up: antenna height above the still
    water (m); vel_*/acc_*: their time derivatives (m/s, m/s^2); heading: grid heading
    (rad, unwrapped); roll/pitch (rad, FRD); *_rate: time derivatives of the Euler angles
    (rad/s); course: grid course over ground (rad, unwrapped); path_s: arc length along
    the planned path (m).
    """

    time: FloatArray
    east: FloatArray
    north: FloatArray
    up: FloatArray
    vel_east: FloatArray
    vel_north: FloatArray
    vel_up: FloatArray
    acc_east: FloatArray
    acc_north: FloatArray
    acc_up: FloatArray
    heading: FloatArray
    roll: FloatArray
    pitch: FloatArray
    heading_rate: FloatArray
    roll_rate: FloatArray
    pitch_rate: FloatArray
    course: FloatArray
    path_s: FloatArray

    @property
    def start(self) -> float:
        return float(self.time[0])

    @property
    def end(self) -> float:
        return float(self.time[-1])

    def at(self, times: FloatArray) -> dict[str, FloatArray]:
        """Every field linearly interpolated at ``times`` (UNIX s, within the motion)."""
        t = np.asarray(times, np.float64)
        return {
            name: np.interp(t, self.time, getattr(self, name))
            for name in self.__dataclass_fields__
            if name != "time"
        }


def _sinusoids(
    rng: np.random.Generator, t: FloatArray, periods: FloatArray, std: float
) -> FloatArray:
    """A smooth random signal: sinusoids of the given periods, random phases and weights,
    scaled to standard deviation ``std``."""
    weights = rng.uniform(0.5, 1.0, len(periods))
    phases = rng.uniform(0.0, 2 * math.pi, len(periods))
    signal = np.zeros_like(t)
    for w, p, ph in zip(weights, periods, phases, strict=True):
        signal += w * np.sin(2 * math.pi * t / p + ph)
    # The std of a sum of unit-weight sinusoids is sqrt(sum(w^2) / 2).
    return signal * std / math.sqrt(float(np.sum(weights**2)) / 2)


WAVE_PERIOD_RANGE_S = (1.5, 4.0)
"""A small boat's roll and pitch in a light chop: periods of 1.5-4 s."""


def wave_components(s: Scenario) -> FloatArray:
    """Periods (s) of the sinusoids of roll, pitch and heave: 0.7-1.6 times the dominant
    period, kept within ``WAVE_PERIOD_RANGE_S``."""
    periods = np.array([0.7, 0.85, 1.0, 1.25, 1.6]) * s.wave_period_s
    return np.clip(periods, *WAVE_PERIOD_RANGE_S)


def simulate_motion(s: Scenario, rng: np.random.Generator) -> tuple[SurveyPath, Motion]:
    """Sample the boat's true motion along the scenario's lawnmower (see module doc)."""
    path = lawnmower(s)
    dt = 1.0 / DENSE_RATE_HZ
    ta = s.accel_time_s
    cruise_time = path.length / s.speed_mps
    t = np.arange(0.0, cruise_time + ta + dt / 2, dt)

    def smoothstep(x: FloatArray) -> FloatArray:
        x = np.clip(x, 0.0, 1.0)
        return x * x * (3 - 2 * x)

    # Accelerating over ta and decelerating over ta covers speed * ta: the survey takes
    # path_length / speed + ta, and ends at rest at the end of the path.
    wobble = 1.0 + _sinusoids(rng, t, np.array([7.0, 13.0, 29.0]), s.speed_wobble)
    speed = s.speed_mps * (smoothstep(t / ta) - smoothstep((t - cruise_time) / ta)) * wobble
    dist = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) * dt / 2)])
    # The wobble changes the distance run a little: rescale so the path ends exactly.
    scale = path.length / dist[-1]
    speed *= scale
    dist = np.minimum(dist * scale, path.length)

    east, north, tangent = path.evaluate(dist)
    tangent = np.unwrap(tangent)
    cross = _sinusoids(rng, t, np.array([17.0, 31.0, 53.0]), s.cross_track_m)
    # Fade the cross-track error in and out with the speed: at rest the boat is on its mark.
    cross *= np.clip(speed / s.speed_mps, 0.0, 1.0)
    east = east + cross * np.sin(tangent + math.pi / 2)
    north = north + cross * np.cos(tangent + math.pi / 2)
    sigma = 0.3 * DENSE_RATE_HZ  # smooths the curvature steps at arc joins (0.3 s)
    east = gaussian_filter1d(east, sigma, mode="nearest")
    north = gaussian_filter1d(north, sigma, mode="nearest")
    tangent = gaussian_filter1d(tangent, sigma, mode="nearest")

    vel_e = np.gradient(east, dt)
    vel_n = np.gradient(north, dt)
    ground_speed = np.hypot(vel_e, vel_n)
    # The course over ground: the velocity's bearing while moving, the path's when nearly
    # stopped (where the velocity direction is noise).
    vel_bearing = tangent + np.angle(np.exp(1j * (np.arctan2(vel_e, vel_n) - tangent)))
    blend = np.clip((ground_speed - _STOP_SPEED_MPS) / _STOP_SPEED_MPS, 0.0, 1.0)
    course = tangent + blend * (vel_bearing - tangent)

    # Crab: the boat points along its velocity through the water, which is the survey
    # velocity along the course minus the current (taken at the survey speed so the
    # heading is steady while speeding up).
    cur = math.radians(s.current_toward_deg)
    water_e = s.speed_mps * np.sin(course) - s.current_mps * math.sin(cur)
    water_n = s.speed_mps * np.cos(course) - s.current_mps * math.cos(cur)
    crab = np.angle(np.exp(1j * (np.arctan2(water_e, water_n) - course)))
    yaw_wobble = _sinusoids(rng, t, np.array([3.1, 5.3, 8.9, 14.0]), math.radians(s.yaw_wobble_deg))
    heading = course + crab + yaw_wobble

    wave_periods = wave_components(s)
    roll = _sinusoids(rng, t, wave_periods, math.radians(s.roll_deg))
    pitch = _sinusoids(rng, t, wave_periods, math.radians(s.pitch_deg))
    pitch += math.radians(s.trim_deg) * (ground_speed / s.speed_mps) ** 2
    heave = _sinusoids(rng, t, wave_periods, s.heave_m)
    up = s.antenna_height_m + heave
    if s.tide_rate_mps:
        up = up + s.tide_rate_mps * t  # the boat floats on the rising (falling) water

    vel_up = np.gradient(up, dt)
    motion = Motion(
        time=s.start_time + t,
        east=east,
        north=north,
        up=up,
        vel_east=vel_e,
        vel_north=vel_n,
        vel_up=vel_up,
        acc_east=np.gradient(vel_e, dt),
        acc_north=np.gradient(vel_n, dt),
        acc_up=np.gradient(vel_up, dt),
        heading=heading,
        roll=roll,
        pitch=pitch,
        heading_rate=np.gradient(heading, dt),
        roll_rate=np.gradient(roll, dt),
        pitch_rate=np.gradient(pitch, dt),
        course=course,
        path_s=dist,
    )
    return path, motion


def water_level(s: Scenario, times: FloatArray) -> FloatArray:
    """Height of the water surface above its level at the survey's start (m) at
    ``times`` (UNIX s): the tide, ``tide_rate_mps`` per second (the boat's ``up`` rides
    on it)."""
    return s.tide_rate_mps * (np.asarray(times, np.float64) - s.start_time)


def euler_to_matrix(heading: FloatArray, pitch: FloatArray, roll: FloatArray) -> FloatArray:
    """Body (FRD) -> navigation (north, east, down) rotation matrices, shape (..., 3, 3),
    for ZYX Euler angles (radians): R = Rz(heading) Ry(pitch) Rx(roll)."""
    ch, sh = np.cos(heading), np.sin(heading)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    r = np.empty((*np.shape(heading), 3, 3))
    r[..., 0, 0] = ch * cp
    r[..., 0, 1] = ch * sp * sr - sh * cr
    r[..., 0, 2] = ch * sp * cr + sh * sr
    r[..., 1, 0] = sh * cp
    r[..., 1, 1] = sh * sp * sr + ch * cr
    r[..., 1, 2] = sh * sp * cr - ch * sr
    r[..., 2, 0] = -sp
    r[..., 2, 1] = cp * sr
    r[..., 2, 2] = cp * cr
    return r


def body_rates(
    roll: FloatArray,
    pitch: FloatArray,
    roll_rate: FloatArray,
    pitch_rate: FloatArray,
    heading_rate: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Euler angle rates -> body angular rates p, q, r (rad/s, FRD), ZYX convention."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    p = roll_rate - heading_rate * sp
    q = pitch_rate * cr + heading_rate * sr * cp
    r = -pitch_rate * sr + heading_rate * cr * cp
    return p, q, r
