"""Navigation priors for sonar frames: typed samples in, EKF-smoothed poses out.

Turns the drivers' samples (``mapping.samples``) into filter inputs in the survey's local
frame, runs ``mapping.ekf.NavFilter`` through them in time order, and reads the estimate
at every sonar frame time. Offline (replay) a Rauch-Tung-Striebel pass smooths the
estimate with the measurements that came after each frame; the streaming engine uses the
same ``NavInputs`` and filter incrementally.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mapping.ekf import PSI, STATE_SIZE, EkfParams, ImuInput, NavFilter, level_imu
from mapping.geo import LocalFrame
from mapping.polar import Attitude
from mapping.samples import AttitudeSample, GnssFix, GnssFixType, HeadingSample, ImuSample
from mapping.se2 import wrap_pi

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class PositionFix:
    """A GNSS fix in the local frame: metres east/north, sigma (m, the filter's: floored,
    or from HDOP or a default when the receiver reports no accuracy); velocity m/s
    east/north (NaN when unknown); h_acc_m: the receiver's own reported horizontal
    accuracy (1 sigma per axis, metres, not floored; NaN when it reported none) and
    fix_type its fix type (``GnssFixType``), by which the survey-end fusion weighs the
    fix."""

    time: float
    x: float
    y: float
    sigma_m: float
    vx: float = math.nan
    vy: float = math.nan
    h_acc_m: float = math.nan
    fix_type: int = GnssFixType.FIX_3D


@dataclass(frozen=True, slots=True)
class HeadingFix:
    """A heading in the local frame: radians clockwise from grid north."""

    time: float
    heading: float
    sigma_rad: float


@dataclass(frozen=True, slots=True)
class NavInputs:
    """Filter inputs in the local frame, each list sorted by time."""

    imu: list[ImuInput]
    positions: list[PositionFix]
    headings: list[HeadingFix]


def _attitude_lookup(
    attitude: Sequence[AttitudeSample],
) -> tuple[Array, Array, Array] | None:
    if not attitude:
        return None
    times = np.array([a.time for a in attitude])
    order = np.argsort(times, kind="stable")
    return (
        times[order],
        np.unwrap(np.array([a.roll_rad for a in attitude])[order]),
        np.unwrap(np.array([a.pitch_rad for a in attitude])[order]),
    )


def position_sigma(fix: GnssFix, params: EkfParams) -> float:
    """Horizontal sigma of a fix: the receiver's h_acc, else HDOP-scaled, else a default."""
    if fix.h_acc_m is not None and fix.h_acc_m > 0:
        sigma = fix.h_acc_m
    elif fix.hdop is not None and fix.hdop > 0:
        sigma = fix.hdop * params.hdop_to_sigma_m
    else:
        sigma = params.position_sigma_m
    return max(sigma, params.min_position_sigma_m)


def prepare_inputs(
    frame: LocalFrame,
    imu: Sequence[ImuSample],
    gnss: Sequence[GnssFix],
    heading: Sequence[HeadingSample],
    attitude: Sequence[AttitudeSample] = (),
    params: EkfParams | None = None,
) -> NavInputs:
    """Convert samples to the local frame: fixes to east/north metres, true headings and
    courses to grid headings, IMU samples levelled with the interpolated roll/pitch."""
    params = params or EkfParams()
    lookup = _attitude_lookup(attitude)
    imu_sorted = sorted(imu, key=lambda s: s.time)
    imu_inputs: list[ImuInput] = []
    if imu_sorted:
        times = np.array([s.time for s in imu_sorted])
        if lookup is not None:
            a_times, rolls, pitches = lookup
            inside = (times >= a_times[0] - 1.0) & (times <= a_times[-1] + 1.0)
            roll_at = np.interp(times, a_times, rolls)
            pitch_at = np.interp(times, a_times, pitches)
        for i, sample in enumerate(imu_sorted):
            if lookup is not None and inside[i]:
                roll: float | None = float(roll_at[i])
                pitch: float | None = float(pitch_at[i])
            else:
                roll = pitch = None
            fwd, stbd, rate = level_imu(sample.accel_mps2, sample.gyro_rps, roll, pitch)
            imu_inputs.append(ImuInput(sample.time, fwd, stbd, rate))

    usable = sorted((f for f in gnss if f.usable), key=lambda f: f.time)
    positions: list[PositionFix] = []
    if usable:
        xs, ys = frame.to_local([f.lat_deg for f in usable], [f.lon_deg for f in usable])
        for fix, x, y in zip(usable, xs, ys, strict=True):
            vx = vy = math.nan
            if (
                fix.speed_mps is not None
                and fix.course_rad is not None
                and fix.speed_mps >= params.min_course_speed_mps
            ):
                course = frame.true_to_grid(fix.course_rad, fix.lat_deg, fix.lon_deg)
                vx, vy = fix.speed_mps * math.sin(course), fix.speed_mps * math.cos(course)
            h_acc = fix.h_acc_m if fix.h_acc_m is not None and fix.h_acc_m > 0 else math.nan
            positions.append(
                PositionFix(
                    fix.time,
                    float(x),
                    float(y),
                    position_sigma(fix, params),
                    vx,
                    vy,
                    h_acc,
                    int(fix.fix_type),
                )
            )

    headings: list[HeadingFix] = []
    if heading:
        # The convergence varies by micro-radians across a survey: one value will do.
        lat, lon = (usable[0].lat_deg, usable[0].lon_deg) if usable else frame.to_latlon(0, 0)
        convergence = frame.convergence_rad(float(lat), float(lon))
        for h in sorted(heading, key=lambda s: s.time):
            sigma = math.hypot(params.heading_sigma_rad, h.resolution_rad / math.sqrt(12.0))
            headings.append(
                HeadingFix(h.time, (h.heading_rad + convergence) % (2 * math.pi), sigma)
            )
    return NavInputs(imu_inputs, positions, headings)


@dataclass(frozen=True)
class NavEstimate:
    """The EKF estimate at requested times: states (n, 8), covariances (n, 8, 8); rows
    before the filter could start (no fix or heading yet) are NaN and ``valid`` False."""

    times: Array
    states: Array
    covariances: Array
    valid: npt.NDArray[np.bool_]

    @property
    def poses(self) -> Array:
        """(n, 3): x east (m), y north (m), heading (rad clockwise from grid north)."""
        return self.states[:, [0, 1, PSI]]

    def prior_weights(self) -> Array:
        """(n, 2) weights of each pose's position and heading prior in the optimisation:
        1 where the filter is as sure as it usually is in this survey (the paper's unit
        weight), less where it is less sure (a GPS outage dead-reckoned), as
        (typical sigma / sigma)^2, capped at 1; 0 where there is no estimate."""
        weights = np.zeros((self.times.size, 2))
        if not self.valid.any():
            return weights
        cov = self.covariances[self.valid]
        sigma_pos = np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))
        sigma_ang = np.sqrt(cov[:, PSI, PSI])
        for column, sigma in enumerate((sigma_pos, sigma_ang)):
            typical = float(np.median(sigma))
            weights[self.valid, column] = np.minimum(1.0, (typical / np.maximum(sigma, 1e-9)) ** 2)
        return weights


_IMU, _POSITION, _HEADING, _QUERY = 0, 1, 2, 3


def estimate_at(
    inputs: NavInputs,
    query_times: Sequence[float] | Array,
    params: EkfParams | None = None,
    smooth: bool = True,
) -> NavEstimate:
    """Run the filter through all inputs and read the estimate at ``query_times``.

    smooth: add the Rauch-Tung-Striebel backward pass (offline use); otherwise each
    query sees only the measurements before it (what a live filter knows).
    """
    params = params or EkfParams()
    queries = np.asarray(query_times, float)
    events: list[tuple[float, int, int]] = []
    events += [(s.time, _IMU, i) for i, s in enumerate(inputs.imu)]
    events += [(s.time, _POSITION, i) for i, s in enumerate(inputs.positions)]
    events += [(s.time, _HEADING, i) for i, s in enumerate(inputs.headings)]
    events += [(float(t), _QUERY, i) for i, t in enumerate(queries)]
    events.sort()

    nav = NavFilter(params)
    # Epoch k: filtered state after its measurement, prior before it, transition into it.
    filt_x: list[Array] = []
    filt_p: list[Array] = []
    prior_x: list[Array] = []
    prior_p: list[Array] = []
    trans: list[Array] = []
    query_epoch = np.full(len(queries), -1, int)
    pending_heading: HeadingFix | None = None

    for time, kind, index in events:
        if kind == _IMU:
            nav.add_imu(inputs.imu[index])
            continue
        if kind == _HEADING:
            pending_heading = inputs.headings[index]
            if not nav.initialised:
                continue
        if kind == _POSITION and not nav.initialised:
            fix = inputs.positions[index]
            if pending_heading is None:
                continue
            velocity = (0.0, 0.0) if math.isnan(fix.vx) else (fix.vx, fix.vy)
            nav.initialise(fix.time, fix.x, fix.y, pending_heading.heading, velocity)
            nav.mark()
            x, p = nav.state()
            filt_x.append(x)
            filt_p.append(p)
            prior_x.append(x)
            prior_p.append(p)
            trans.append(np.eye(STATE_SIZE))
            continue
        if not nav.initialised:
            continue
        nav.predict_to(time)
        x_prior, p_prior = nav.state()
        if kind == _POSITION:
            fix = inputs.positions[index]
            nav.update_position(time, fix.x, fix.y, fix.sigma_m)
            if not math.isnan(fix.vx):
                nav.update_velocity(time, fix.vx, fix.vy, params.velocity_sigma_mps)
        elif kind == _HEADING:
            assert pending_heading is not None
            nav.update_heading(time, pending_heading.heading, pending_heading.sigma_rad)
        else:
            query_epoch[index] = len(filt_x)
        x, p = nav.state()
        prior_x.append(x_prior)
        prior_p.append(p_prior)
        filt_x.append(x)
        filt_p.append(p)
        trans.append(nav.mark())

    states = np.full((len(queries), STATE_SIZE), np.nan)
    covariances = np.full((len(queries), STATE_SIZE, STATE_SIZE), np.nan)
    if filt_x:
        xs, ps = (
            _rts(filt_x, filt_p, prior_x, prior_p, trans)
            if smooth
            else (np.array(filt_x), np.array(filt_p))
        )
        valid = query_epoch >= 0
        states[valid] = xs[query_epoch[valid]]
        covariances[valid] = ps[query_epoch[valid]]
    valid = query_epoch >= 0
    return NavEstimate(queries, states, covariances, valid)


def _rts(
    filt_x: list[Array],
    filt_p: list[Array],
    prior_x: list[Array],
    prior_p: list[Array],
    trans: list[Array],
) -> tuple[Array, Array]:
    """Rauch-Tung-Striebel smoother over epochs (Rauch, Tung & Striebel 1965), with the
    multi-step transition Jacobian between epochs and wrapped heading differences."""
    n = len(filt_x)
    xs = np.array(filt_x)
    ps = np.array(filt_p)
    for k in range(n - 2, -1, -1):
        f = trans[k + 1]
        p_pred = prior_p[k + 1]
        gain = filt_p[k] @ f.T @ np.linalg.pinv(p_pred)
        delta = xs[k + 1] - prior_x[k + 1]
        delta[PSI] = wrap_pi(float(delta[PSI]))
        xs[k] = filt_x[k] + gain @ delta
        xs[k, PSI] %= 2 * math.pi
        ps[k] = filt_p[k] + gain @ (ps[k + 1] - p_pred) @ gain.T
    return xs, ps


def gyro_epochs(inputs: NavInputs, times: Array, max_gap_s: float) -> npt.NDArray[np.int64]:
    """Per frame time, the gyro epoch as ``NavFilter.gyro_epoch_at`` gives it live: the
    number of IMU gaps longer than ``max_gap_s`` closed by then, -1 where the last IMU
    sample is older than ``max_gap_s`` (or there is none)."""
    times = np.asarray(times, float)
    imu_t = np.array([s.time for s in inputs.imu], float)
    out = np.full(times.size, -1, np.int64)
    if imu_t.size == 0 or times.size == 0:
        return out
    closes = imu_t[1:][np.diff(imu_t) > max_gap_s]  # where each gap ended
    last = np.searchsorted(imu_t, times, side="right") - 1
    fresh = (last >= 0) & (times - imu_t[np.maximum(last, 0)] <= max_gap_s)
    epoch = np.searchsorted(closes, times, side="right")
    out[fresh] = epoch[fresh]
    return out


class AttitudeTrack:
    """Roll and pitch at any time, interpolated from the autopilot's attitude reports.

    ``at(stamp)`` gives the attitude ``latency_s`` before a ping's stamp (when the ping
    was taken), or None where no report lies within ``max_gap_s`` (the ping is then
    projected level).
    """

    def __init__(
        self, attitude: Sequence[AttitudeSample], latency_s: float = 0.0, max_gap_s: float = 0.5
    ) -> None:
        lookup = _attitude_lookup(attitude)
        self.latency_s = latency_s
        self.max_gap_s = max_gap_s
        self._lookup = lookup

    def at(self, stamp: float) -> Attitude | None:
        if self._lookup is None:
            return None
        times, rolls, pitches = self._lookup
        t = stamp - self.latency_s
        k = int(np.searchsorted(times, t))
        near = min(abs(times[min(k, times.size - 1)] - t), abs(times[max(k - 1, 0)] - t))
        if near > self.max_gap_s:
            return None
        return Attitude(float(np.interp(t, times, rolls)), float(np.interp(t, times, pitches)))
