"""The streaming engine's navigation record: the filter run forward over the navigation
samples, what a ping's processing asks of it, and the raw record for the survey-end pass.

Each navigation sample, in time order (``mapping.stream_reorder``), goes into the
navigation filter (``mapping.ekf``: IMU levelled by the latest attitude, compass headings,
GNSS positions and Doppler velocities) and into the record the survey-end pass re-reads
(the IMU compactly, ``ImuRecord``). The local frame (``mapping.geo.LocalFrame``) is laid
around the first usable fix. What the later stages need of a sample comes out as a
``Measured``: the live re-solve's gyro, compass and GNSS measurements (local metres, grid
heading) and the fixes the live chain's anchor is tied to.

For a ping the record gives the filter's pose there (``PingNavigation``: the registration's
prior and odometry, the gyro epoch, when the compass last spoke) and the attitude the ping
is projected with: roll and pitch from the attitude reports around its stamp, and the
altitude and slope of the seabed under the sonar from the echosounder's soundings so far
(the live bottom model, rebuilt every ``LIVE_BOTTOM_REFRESH_S``), as the survey-end pass
has it from all of them.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mapping.bottom import (
    BottomModel,
    SonarGeometry,
    pose_interpolator,
    slope_in_heading,
    sounding_points,
)
from mapping.ekf import PSI, ImuInput, NavFilter, level_imu
from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from mapping.navigation import AttitudeTrack, position_sigma
from mapping.pipeline import NavSamples, PipelineParams, sonar_geometry
from mapping.polar import Attitude
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping, RangeSample
from mapping.se2 import turn

Array = npt.NDArray[np.float64]
NavSample = ImuSample | GnssFix | HeadingSample | AttitudeSample | RangeSample

LIVE_BOTTOM_REFRESH_S = 2.0
"""The live bottom model takes in the soundings that came since it was last built this
often (s): the echosounder's footprint ahead of the boat is sounded a few seconds later,
and a rebuild of an hour's soundings (18,000 at 5 Hz) costs milliseconds."""


@dataclass(frozen=True, slots=True)
class Measured:
    """What one navigation sample gives the stages after the filter (each None where the
    sample gives nothing of it)."""

    yaw_rate: tuple[float, float] | None = None
    """An IMU sample's (time, levelled yaw rate rad/s): the live re-solve's gyro."""
    heading: tuple[float, float] | None = None
    """A compass heading's (time, grid heading rad), once the local frame is laid."""
    gnss: tuple[float, float, float, float, float] | None = None
    """A usable fix's (time, x, y, vx, vy): local metres and its Doppler velocity (m/s
    east, north; NaN: none), for the live re-solve."""
    chain_fix: tuple[float, float, float] | None = None
    """The same fix's (time less ``gnss_time_offset_s``, x, y) for the live chain's
    anchor, once the filter runs."""


NOTHING = Measured()


@dataclass(frozen=True, slots=True)
class PingNavigation:
    """The filter at a ping's stamp: what the ping's registration and its place in the
    live chain are measured against."""

    prior: Array | None
    """Vehicle pose (local x, y, grid heading); None before the filter has started."""
    odometry: Array | None
    """The filter's dead-reckoned path there (``NavFilter.odometry``)."""
    gyro: int | None
    """The filter's gyro epoch there (``NavFilter.gyro_epoch_at``; None: no fresh IMU)."""
    compass_time: float
    """Stamp of the last compass heading (-inf: none yet)."""
    compass_epoch: int | None
    """The gyro epoch at that heading."""


class ImuRecord:
    """IMU samples as rows of float64 arrays (9 numbers, NaN for a missing magnetometer)
    in chunks: a fifth of the memory of the sample objects, for 2 hours of 55 Hz."""

    CHUNK = 16384

    def __init__(self) -> None:
        self._chunks: list[Array] = []
        self._sources: list[str] = []
        self._fill = self.CHUNK

    def append(self, s: ImuSample) -> None:
        if self._fill == self.CHUNK:
            self._chunks.append(np.empty((self.CHUNK, 10)))
            self._fill = 0
        mag = s.mag_gauss if s.mag_gauss is not None else (math.nan, math.nan, math.nan)
        self._chunks[-1][self._fill] = (s.time, *s.accel_mps2, *s.gyro_rps, *mag)
        if not self._sources or self._sources[-1] != s.source:
            self._sources.append(s.source)
        self._fill += 1

    def samples(self) -> list[ImuSample]:
        if not self._chunks:
            return []
        rows = np.concatenate([*self._chunks[:-1], self._chunks[-1][: self._fill]])
        source = self._sources[-1] if self._sources else ""
        out = []
        for r in rows.tolist():
            mag = None if math.isnan(r[7]) else (r[7], r[8], r[9])
            out.append(ImuSample(r[0], (r[1], r[2], r[3]), (r[4], r[5], r[6]), mag, source))
        return out


class NavigationRecord:
    """See the module docstring. Feed samples in time order (``take``, ``at_ping``)."""

    def __init__(
        self, mount: SonarMount, pipeline: PipelineParams, gnss_time_offset_s: float
    ) -> None:
        self.mount = mount
        self.pipeline = pipeline
        self.gnss_time_offset_s = gnss_time_offset_s
        """A fix shows the antenna this long before the frame stamps say
        (``StreamingParams.gnss_time_offset_s``)."""
        self.nav = NavFilter(pipeline.ekf)
        self.frame: LocalFrame | None = None
        """The local frame, laid around the first usable fix."""
        self._convergence = 0.0  # grid minus true north there (set with the frame)
        self._recent_attitude: deque[AttitudeSample] = deque(maxlen=256)
        self._attitude: AttitudeSample | None = None
        self._pending_heading: HeadingSample | None = None
        self._last_compass = -math.inf  # stamp of the last compass heading
        self._compass_epoch: int | None = None  # the gyro epoch at that heading
        # The seabed under each ping from the echosounder's soundings so far (rebuilt
        # every ``LIVE_BOTTOM_REFRESH_S``), as the survey-end pass has it from all of them.
        self._geometry: SonarGeometry | None = None
        self._bottom: BottomModel | None = None
        self._bottom_built = (-math.inf, 0)  # (when, how many soundings it had)
        # The raw navigation for the survey-end pass: IMU rows compactly in arrays.
        self._imu = ImuRecord()
        self._fixes: list[GnssFix] = []
        self._headings: list[HeadingSample] = []
        self._attitudes: list[AttitudeSample] = []
        self._ranges: list[RangeSample] = []  # a downward echosounder's soundings

    # -- samples ---------------------------------------------------------------------------
    def take(self, sample: NavSample) -> Measured:
        """One navigation sample, in time order: into the filter and the record."""
        if isinstance(sample, ImuSample):
            self._imu.append(sample)
            att = self._attitude
            roll = att.roll_rad if att is not None and sample.time - att.time < 1.0 else None
            pitch = att.pitch_rad if roll is not None and att is not None else None
            fwd, stbd, rate = level_imu(sample.accel_mps2, sample.gyro_rps, roll, pitch)
            self.nav.add_imu(ImuInput(sample.time, fwd, stbd, rate))
            return Measured(yaw_rate=(sample.time, rate))
        if isinstance(sample, AttitudeSample):
            self._attitudes.append(sample)
            self._recent_attitude.append(sample)
            self._attitude = sample
            return NOTHING
        if isinstance(sample, HeadingSample):
            return self._heading(sample)
        if isinstance(sample, GnssFix):
            self._fixes.append(sample)
            return self._gnss(sample) if sample.usable else NOTHING
        if isinstance(sample, RangeSample):
            self._ranges.append(sample)
        return NOTHING

    def _heading(self, sample: HeadingSample) -> Measured:
        self._headings.append(sample)
        self._pending_heading = sample
        self._last_compass = sample.time
        self._compass_epoch = self.nav.gyro_epoch_at(sample.time)
        if self.frame is None:
            return NOTHING
        heading = self._grid_heading(sample)
        if self.nav.initialised:
            sigma = math.hypot(
                self.pipeline.ekf.heading_sigma_rad, sample.resolution_rad / math.sqrt(12)
            )
            self.nav.update_heading(sample.time, heading, sigma)
        return Measured(heading=(sample.time, heading))

    def _grid_heading(self, sample: HeadingSample) -> float:
        assert self.frame is not None
        return (sample.heading_rad + self._convergence) % (2 * math.pi)

    def _gnss(self, fix: GnssFix) -> Measured:
        p = self.pipeline.ekf
        if self.frame is None:
            self.frame = LocalFrame.around(fix.lat_deg, fix.lon_deg)
            self._convergence = self.frame.convergence_rad(fix.lat_deg, fix.lon_deg)
        xs, ys = self.frame.to_local([fix.lat_deg], [fix.lon_deg])
        x, y = float(xs[0]), float(ys[0])
        vx = vy = math.nan
        if (
            fix.speed_mps is not None
            and fix.course_rad is not None
            and fix.speed_mps >= p.min_course_speed_mps
        ):
            course = (fix.course_rad + self._convergence) % (2 * math.pi)
            vx, vy = fix.speed_mps * math.sin(course), fix.speed_mps * math.cos(course)
        measured = (fix.time, x, y, vx, vy)
        if not self.nav.initialised:
            if self._pending_heading is not None:
                velocity = (0.0, 0.0) if math.isnan(vx) else (vx, vy)
                heading = self._grid_heading(self._pending_heading)
                self.nav.initialise(fix.time, x, y, heading, velocity)
            return Measured(gnss=measured)
        self.nav.update_position(fix.time, x, y, position_sigma(fix, p))
        if not math.isnan(vx):
            self.nav.update_velocity(fix.time, vx, vy, p.velocity_sigma_mps)
        return Measured(gnss=measured, chain_fix=(fix.time - self.gnss_time_offset_s, x, y))

    # -- pings -----------------------------------------------------------------------------
    def at_ping(self, ping: Ping) -> PingNavigation:
        """The filter run on to the ping's stamp, and its pose there. The first ping also
        gives the sonar's geometry the bottom model needs."""
        prior: Array | None = None
        odometry: Array | None = None
        gyro: int | None = None
        if self.nav.initialised:
            self.nav.predict_to(ping.time)
            odometry = self.nav.odometry.copy()
            gyro = self.nav.gyro_epoch_at(ping.time)
            state, _ = self.nav.state()
            prior = state[[0, 1, PSI]]
        if self._geometry is None and self.mount.altitude_m > 0:
            self._geometry = sonar_geometry(ping, self.mount, self.pipeline)
        return PingNavigation(prior, odometry, gyro, self._last_compass, self._compass_epoch)

    def ping_attitude(
        self, stamp: float, times: Sequence[float], poses: Sequence[Array]
    ) -> Attitude | None:
        """The attitude a ping stamped ``stamp`` is projected with: its roll and pitch
        (``tilt_at``; level when the pipeline does not project the attitude) with the
        seabed's altitude and slope under it (``bottom_at``). ``times``, ``poses``: the
        live map's frames so far (NaN where rejected), which place the soundings
        (``live_bottom``)."""
        return self.attitude_over(stamp, self.live_bottom(stamp, times, poses))

    def attitude_over(self, stamp: float, model: BottomModel | None) -> Attitude | None:
        """``ping_attitude`` over a bottom model built already (``build_bottom``; None:
        none yet)."""
        tilt = self.tilt_at(stamp) if self.pipeline.project_attitude else None
        return self.bottom_at(stamp, tilt, model)

    def bottom_at(
        self, stamp: float, tilt: Attitude | None, model: BottomModel | None
    ) -> Attitude | None:
        """``tilt`` with the altitude and slope of the seabed plane of ``model`` under the
        sonar at ``stamp`` (the ping being processed: the filter's pose now); ``tilt`` as
        it is without one."""
        if model is None or not self.nav.initialised:
            return tilt
        state, _ = self.nav.state()
        vehicle = state[[0, 1, PSI]]
        plane = model.at(stamp, self.mount.sonar_pose(vehicle))
        if plane is None:
            return tilt
        forward, starboard = slope_in_heading(plane, float(vehicle[2]))
        roll, pitch = (tilt.roll_rad, tilt.pitch_rad) if tilt is not None else (0.0, 0.0)
        return Attitude(roll, pitch, plane.altitude_m, forward, starboard)

    def live_bottom(
        self, now: float, times: Sequence[float], poses: Sequence[Array]
    ) -> BottomModel | None:
        """The bottom model of the soundings so far, placed by the live map's ``poses``
        at ``times``, rebuilt when ``LIVE_BOTTOM_REFRESH_S`` has passed and new soundings
        came (None: no echosounder, or too few)."""
        model = self.build_bottom(now, times, poses, self.held)
        if model is not None:
            self._bottom = model
        return self._bottom

    @property
    def held(self) -> tuple[int, int]:
        """How many soundings and attitude reports the record holds: what a stage behind
        the filter builds the bottom model over, as it stood when a ping was released
        (``build_bottom``)."""
        return len(self._ranges), len(self._attitudes)

    def build_bottom(
        self,
        now: float,
        times: Sequence[float],
        poses: Sequence[Array],
        held: tuple[int, int],
    ) -> BottomModel | None:
        """A new bottom model of the first ``held`` soundings (and attitude reports, which
        tilt them), placed by the live map's ``poses`` at ``times``, when
        ``LIVE_BOTTOM_REFRESH_S`` has passed since the last one and soundings came since;
        None otherwise (or no echosounder, or too few)."""
        b = self.pipeline.bottom
        soundings, attitudes = held
        if not b.use_echosounder or soundings == 0 or self._geometry is None:
            return None
        when, count = self._bottom_built
        if now - when < LIVE_BOTTOM_REFRESH_S or soundings == count:
            return None
        self._bottom_built = (now, soundings)
        track_times = np.array(times, float)
        track = np.array(poses, float).reshape(-1, 3)
        if int(np.all(np.isfinite(track), axis=1).sum()) < 2:
            return None
        latency = self.pipeline.single_stage.graph.sonar_latency_s
        attitude = AttitudeTrack(self._attitudes[:attitudes], latency)
        points, stamps = sounding_points(
            self._ranges[:soundings],
            pose_interpolator(track_times, track),
            attitude.at,
            b.echosounder,
        )
        if len(points) < b.min_soundings:
            return None
        geometry = self._geometry
        return BottomModel(points, stamps, geometry.down_m, geometry.footprint(), b)

    def tilt_at(self, stamp: float) -> Attitude | None:
        """Roll and pitch when a ping stamped ``stamp`` was taken, from the recent
        attitude reports (None without one within half a second)."""
        recent = self._recent_attitude
        if not recent:
            return None
        t = stamp - self.pipeline.single_stage.graph.sonar_latency_s
        before = after = None
        for a in reversed(recent):
            if a.time <= t:
                before = a
                break
            after = a
        if before is None or after is None:
            near = before or after
            if near is None or abs(near.time - t) > 0.5:
                return None
            return Attitude(near.roll_rad, near.pitch_rad)
        span = after.time - before.time
        w = (t - before.time) / span if span > 0 else 0.0
        roll = before.roll_rad + w * turn(after.roll_rad - before.roll_rad)
        pitch = before.pitch_rad + w * (after.pitch_rad - before.pitch_rad)
        return Attitude(roll, pitch)

    # -- survey end ------------------------------------------------------------------------
    def survey(self) -> NavSamples:
        """Every navigation sample taken, for the survey-end pass."""
        return NavSamples(
            self._imu.samples(), self._fixes, self._headings, self._attitudes, ranges=self._ranges
        )
