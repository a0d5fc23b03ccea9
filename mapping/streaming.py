"""The streaming engine: the paper's pipeline run as samples arrive, in bounded memory.

Feed it typed samples in the order they arrive (``add``); it keeps them a moment
(``reorder_s``) to put them in time order and drop duplicates, runs the EKF forward, and
processes each sonar frame once the filter has passed the frame's time (or, with the
navigation silent, once the pings themselves have moved ``reorder_s`` past it: nothing
waits for a lost sensor). Each frame is preprocessed, registered against the last
accepted one and validated (``mapping.frames``), placed by chaining onto its
predecessor's pose, and blended into the tile store at once. Every ``solve_every``
accepted frames the pose graph of the last ``window_frames`` frames is re-solved, the
frame before the window held where it is; frames whose pose moves by more than
``move_threshold_m`` are taken out of their tiles and put back. A frame's pose is final
when it leaves the window; its image is kept (uint8, bounded) so that the live re-solve
(``mapping.live_resolve``: every ``resolve.every_s`` of survey time, the drawn frames
placed again by the survey-end pass's fusion) can draw it again where it now belongs.

Out come pose updates (per frame, and again when a pose moves or becomes final, or when
a re-solve draws a final frame again) and tile
updates (rendered at most every ``render_every_s`` of survey time, with a growing
version), through callbacks. ``finish`` is the survey-end pass: the whole survey
re-solved offline (smoothed EKF, loop closures, single- or two-stage) with the
registrations made live, and every tile re-rendered from the pings.
"""

from __future__ import annotations

import heapq
import itertools
import math
import time as clock
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from mapping.blend import make_scorer
from mapping.bottom import (
    BottomModel,
    SonarGeometry,
    pose_interpolator,
    slope_in_heading,
    sounding_points,
)
from mapping.closures import world_rotation
from mapping.ekf import PSI, ImuInput, NavFilter, level_imu
from mapping.fmt import SonarGrid
from mapping.frames import FrameOutcome, LocalRegistration, SonarMount
from mapping.geo import LocalFrame
from mapping.live_anchor import AnchorParams, LiveAnchor
from mapping.live_closures import LiveClosureParams, LiveClosures
from mapping.live_resolve import (
    Bridge,
    Drawn,
    DrawnFrame,
    LiveResolver,
    ResolveClosure,
    ResolveParams,
    align,
    pack,
)
from mapping.mosaic import SonarPose, TileGrid, TileKey
from mapping.navigation import AttitudeTrack, position_sigma
from mapping.pipeline import (
    Mode,
    NavSamples,
    PipelineParams,
    SurveyResult,
    map_survey,
    sonar_geometry,
)
from mapping.polar import Attitude
from mapping.posegraph import Edge
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping, RangeSample
from mapping.survey_graph import registration_sqrt_info
from mapping.tiles import TileImage, TileSpill, TileStore, frame_layers

Array = npt.NDArray[np.float64]
_MOST_REDRAWS = 3.0
"""Frames drawn again with one new frame, at most."""
Sample = ImuSample | GnssFix | HeadingSample | AttitudeSample | RangeSample | Ping


LIVE_BOTTOM_REFRESH_S = 2.0
"""The live bottom model takes in the soundings that came since it was last built this
often (s): the echosounder's footprint ahead of the boat is sounded a few seconds later,
and a rebuild of an hour's soundings (18,000 at 5 Hz) costs milliseconds."""


@dataclass(frozen=True, slots=True)
class StreamingParams:
    pipeline: PipelineParams = field(default_factory=PipelineParams)
    reorder_s: float = 0.25
    """Samples are held this long (survey time) to be put in time order."""
    window_frames: int = 30
    """Accepted frames re-optimised together (3 s at 10 Hz): a fixed-lag smoother over
    the last six GPS fixes. Longer windows move frames further between their first
    blend and their final pose, so more of them are blended twice."""
    solve_every: int = 10
    """Re-solve the window every this many accepted frames."""
    move_threshold_m: float = 0.02
    """A frame whose fan has moved more than this (a mosaic pixel) since it was blended
    is re-blended when its pose becomes final."""
    live_move_threshold_m: float = 0.25
    """While in the window, a frame is re-blended only when it moved more than this: the
    window's solution shifts with every GPS fix by a centimetre or two, and chasing each
    shift would re-blend every frame at every solve."""
    render_every_s: float = 0.5
    """New coverage is rendered at most this often (survey time): a ping shows within
    ``reorder_s`` plus this."""
    refine_every_s: float = 1.5
    """Pixels that already showed are re-rendered (refined by later frames) this often."""
    redraw_render_every_s: float = 6.0
    """Pixels a re-solve's redraws changed are rendered this often: a stretch's redraws
    go on over the same tiles for seconds, and rendered with every refine a pixel is
    blended again each time. Measured on quadrats seed 1 at 5 Hz (two runs each, against
    every 1.5 s): render 11.7 -> 10.4 ms a frame; nothing at 2 Hz, where most tiles a
    redraw touches leave memory, and are rendered then, before the next."""
    evict_after_s: float = 30.0
    """A tile no frame has touched for this long may leave memory."""
    tile_memory_mb: float | None = 256.0
    """Such idle tiles stay in memory, the least recently used leaving first, while the
    tiles take no more than this (None: idle tiles leave at once)."""
    live_registration_res_m: float | None = 0.03
    """Pixel size of the live registrations (None: the pipeline's). 3 cm halves the FFT
    work; the survey-end pass registers again at the pipeline's full resolution."""
    final_mode: Mode = Mode.SINGLE_STAGE
    """The survey-end pass: single-stage, or two-stage for long surveys."""
    closure_hold_frames: int = 100
    """While a pair of passes waits for agreeing closures, frames drawn since the last
    closure stay in the window, up to this many (10 s at 10 Hz; a live frame holds its
    image, score and mask, about 1 MB on a 5 m fan at 2 cm)."""
    anchor: AnchorParams = field(default_factory=AnchorParams)
    """How the live chain is tied to the GNSS and the heading filter."""
    closures: LiveClosureParams = field(default_factory=LiveClosureParams)
    """Live loop closures against keyframes of the final map."""
    resolve: ResolveParams = field(default_factory=ResolveParams)
    """The drawn map re-solved and redrawn every few seconds of survey."""
    resolve_tiles_in_memory: int = 16
    """While redrawing, tiles idle for ``evict_after_s`` leave memory once more than this
    many are loaded (5.2 MB each): a redraw over an old stretch loads its tiles."""
    bridge_velocity_age_s: float = 5.0
    """A frame the registration could not chain is bridged at the speed (vehicle frame)
    the registrations last measured when they measured it this recently, else by the
    filter's dead reckoning."""
    bridge_velocity_sigma_mps: float = 0.06
    """Error of such a bridge per second it spans: 9-16 cm over 2 s measured at a U-turn
    in a GNSS outage (quadrats seed 10, 2 Hz)."""
    bridge_filter_sigma_mps: float = 0.3
    """Error of a filter's dead-reckoned bridge per second: 50-80 cm over 2 s measured in
    a GNSS outage (the same survey), where the accelerometers alone carry the velocity."""
    heading_fresh_s: float = 1.0
    """The filter's heading is a measurement of the chain's for the anchor while the gyro
    has carried it without a break since the last compass heading, or this long after
    one: with the autopilot link silent the filter holds its heading whatever the boat
    does, and when the link returns the gyro comes back before the compass has spoken."""
    gnss_time_offset_s: float = 0.1
    """A fix shows the antenna this long before the frame stamps say (fix lag minus
    sonar latency)."""
    reuse_registrations: bool = False
    """The survey-end pass reuses the live registrations instead of registering every
    frame again against the smoothed EKF. Faster (no FMT at the end), but the live ones
    were guided by the live filter, so the result differs from an offline single-stage
    run by up to a centimetre; re-registering makes the two identical."""


@dataclass(frozen=True, slots=True)
class PoseUpdate:
    """The vehicle reference point's pose for a frame: UTM metres, heading from true
    north (degrees), WGS84; ``final`` once it can no longer change live."""

    frame: int
    time: float
    east: float
    north: float
    heading_deg: float
    lat: float
    lon: float
    epsg: int
    final: bool


@dataclass(frozen=True, slots=True)
class TileUpdate:
    """A rendered tile (values 1..255, 0 = no data) on the contract's grid."""

    key: TileKey
    values: npt.NDArray[np.uint8]
    version: int
    epsg: int
    res_m: float
    size_px: int
    west: float
    north: float
    frames: tuple[int, ...] = ()
    """Frames whose pixels reached this tile since its previous update (for latency)."""


@dataclass
class StreamStats:
    frames_received: int = 0
    frames_mapped: int = 0
    frames_rejected: int = 0
    frames_skipped: int = 0
    samples_late: int = 0
    samples_duplicate: int = 0
    windows_solved: int = 0
    frames_reblended: int = 0
    resolves: int = 0
    frames_redrawn: int = 0
    """Final frames drawn again after a re-solve moved them."""
    redraw_wait_s: float = 0.0
    """Survey time moved frames waited to be drawn again, summed: the drawn map's lag
    behind the re-solve (``redraw_wait_mean_s`` a frame)."""
    redraw_wait_max_s: float = 0.0
    tile_spill_failures: int = 0
    """Idle tiles that could not go to disk (kept in memory) and why the latest could not:
    a full disk, say."""
    tile_spill_error: str | None = None
    rejected: dict[str, int] = field(default_factory=dict)
    stage_s: dict[str, float] = field(default_factory=dict)

    @property
    def redraw_wait_mean_s(self) -> float:
        return self.redraw_wait_s / max(self.frames_redrawn, 1)

    def time(self, stage: str, started: float) -> float:
        now = clock.perf_counter()
        self.stage_s[stage] = self.stage_s.get(stage, 0.0) + now - started
        return now


class _PosesIn:
    """Drawn poses looked up one at a time and taken into another frame."""

    def __init__(self, frame: DrawnFrame, poses: list[Array]) -> None:
        self.frame = frame
        self.drawn = poses

    def __getitem__(self, k: int) -> Array:
        return self.frame.poses(np.asarray(self.drawn[k], float)[None, :])[0]


@dataclass
class _Live:
    """A frame still in the window: what re-blending it needs."""

    index: int
    time: float
    layers: npt.NDArray[np.float32]  # (rows, cols, 3): image, score, mask
    mask: npt.NDArray[np.bool_]
    grid: SonarGrid
    tiles: list[TileKey]
    blended_pose: Array  # sonar (x, y, yaw) it was blended at


class StreamingEngine:
    """See the module docstring. Not thread-safe: one feeder."""

    def __init__(
        self,
        mount: SonarMount,
        params: StreamingParams | None = None,
        on_pose: Callable[[PoseUpdate], None] | None = None,
        on_tile: Callable[[TileUpdate], None] | None = None,
        spill: TileSpill | None = None,
    ) -> None:
        self.mount = mount
        self.params = params or StreamingParams()
        p = self.params.pipeline
        self.on_pose = on_pose
        self.on_tile = on_tile
        self.stats = StreamStats()
        self.frame: LocalFrame | None = None
        self.nav = NavFilter(p.ekf)
        live_preprocess = p.preprocess
        if self.params.live_registration_res_m is not None:
            live_preprocess = replace(
                p.preprocess, registration_res_m=self.params.live_registration_res_m
            )
        self._recent_attitude: deque[AttitudeSample] = deque(maxlen=256)
        self.local = LocalRegistration(
            mount,
            live_preprocess,
            p.fmt,
            p.registration,
            self._attitude_at if p.project_attitude else self._bottom_at,
        )
        # The seabed under each ping from the echosounder's soundings so far (rebuilt
        # every ``LIVE_BOTTOM_REFRESH_S``), as the survey-end pass has it from all of them.
        self._geometry: SonarGeometry | None = None
        self._bottom: BottomModel | None = None
        self._bottom_built = (-math.inf, 0)  # (when, how many soundings it had)
        self.scorer = make_scorer(p.blend)
        self.tiles = TileStore(
            TileGrid(p.mosaic_res_m, p.tile_px),
            p.blend,
            spill,
            self.params.evict_after_s,
            None if self.params.tile_memory_mb is None else int(self.params.tile_memory_mb * 2**20),
        )
        self._heap: list[tuple[float, int, int, Sample]] = []
        self._seq = itertools.count()
        self._latest = -math.inf  # newest time seen on any stream
        self._released = -math.inf  # everything at or before this has been processed
        self._recent: deque[tuple[int, float]] = deque(maxlen=4096)  # (kind, time) seen
        self._recent_set: set[tuple[int, float]] = set()
        self._attitude: AttitudeSample | None = None
        self._pending_heading: HeadingSample | None = None
        # Per frame, survey-long but small (a few numbers a frame).
        self.times: list[float] = []
        self.poses: list[Array] = []
        self.outcomes: list[FrameOutcome] = []
        """Every frame's registration, kept for the survey-end pass only when it reuses them
        (``reuse_registrations``): 300 bytes a frame otherwise held for nothing."""
        self.edges: list[Edge] = []
        self._accepted: list[int] = []  # indices of accepted frames, in order
        self._final_upto = 0  # accepted[: this] are final
        self._live: dict[int, _Live] = {}
        self._since_solve = 0
        self._last_render = -math.inf
        self._last_refine = -math.inf
        self._last_redrawn_render = -math.inf
        self._pending_frames: dict[TileKey, list[int]] = {}
        # The live chain: per accepted frame, its chained position (local east/north),
        # raw chained heading, and the filter's odometry there (to bridge rejections).
        self.anchor = LiveAnchor(self.params.anchor)
        self._chain: dict[int, Array] = {}
        self._chain_heading: dict[int, float] = {}
        self._bends_at: dict[int, Array] = {}  # the anchor's bends when each was chained
        self._odometry: dict[int, Array] = {}
        self._gyro: dict[int, int | None] = {}  # the filter's gyro epoch at each frame
        self._last_compass = -math.inf  # stamp of the last compass heading
        self._compass_epoch: int | None = None  # the gyro epoch at that heading
        self._last_chained: int | None = None
        self._bridged: Bridge | None = None  # how the last frame chained was bridged
        self._registered_velocity: tuple[float, float, float] | None = None  # fwd, stbd, time
        self._pending_fixes: deque[tuple[float, float, float]] = deque(maxlen=256)
        self.closures: LiveClosures | None = None  # once the sonar's geometry is known
        single = p.single_stage
        self.resolver = LiveResolver(self.params.resolve, single.fusion, single.graph)
        self.drawn_frame = DrawnFrame()
        """The live map's frame against the GNSS's (``mapping.live_resolve.align``)."""
        self._to_redraw: dict[int, Array] = {}
        """Frames re-solves moved that are still to be drawn again, and their poses."""
        self._queued_at: dict[int, float] = {}
        self._redraw_credit = 0.0
        self._redraw_cursor = -1
        """The frame last drawn again: the queue is swept from the oldest frame on, from
        just after this one."""
        self._redraw_recent: deque[list[TileKey]] = deque(maxlen=10)
        """The tiles of the last redraws: kept in memory while redraws go on."""
        # The raw navigation for the survey-end pass: IMU rows compactly in arrays.
        self._imu = _ImuRecord()
        self._fixes: list[GnssFix] = []
        self._headings: list[HeadingSample] = []
        self._attitudes: list[AttitudeSample] = []
        self._ranges: list[RangeSample] = []  # a downward echosounder's soundings

    # -- input -------------------------------------------------------------------------
    def add(self, sample: Sample) -> None:
        """Take one sample (any type) as it arrives."""
        kind = _KINDS[type(sample)]
        t = float(sample.time)
        if t <= self._released:
            self.stats.samples_late += 1
            if isinstance(sample, Ping):
                self.stats.frames_received += 1
                self.stats.frames_skipped += 1
            return
        key = (kind, t)
        if key in self._recent_set:
            self.stats.samples_duplicate += 1
            return
        if len(self._recent) == self._recent.maxlen:
            self._recent_set.discard(self._recent[0])
        self._recent.append(key)
        self._recent_set.add(key)
        heapq.heappush(self._heap, (t, kind, next(self._seq), sample))
        if t > self._latest:
            self._latest = t
        self._release(self._latest - self.params.reorder_s)

    @property
    def processed_upto(self) -> float:
        """Every sample stamped at or before this time (s) has been processed."""
        return self._released

    def flush(self) -> None:
        """Process everything held (the end of the stream), render what changed, and
        make every remaining pose final."""
        self._release(math.inf)
        self._solve_window(final=True)
        self._redraw(self._released, 0.0, everything=True)
        self._render(force=True)

    def _release(self, upto: float) -> None:
        while self._heap and self._heap[0][0] <= upto:
            t, _, _, sample = heapq.heappop(self._heap)
            self._released = t
            if isinstance(sample, Ping):
                self._frame(sample)
            else:
                self._navigate(sample)
        if upto > self._released and upto != math.inf:
            self._released = upto

    # -- navigation --------------------------------------------------------------------
    def _navigate(self, sample: Sample) -> None:
        started = clock.perf_counter()
        if isinstance(sample, ImuSample):
            self._imu.append(sample)
            att = self._attitude
            roll = att.roll_rad if att is not None and sample.time - att.time < 1.0 else None
            pitch = att.pitch_rad if roll is not None and att is not None else None
            fwd, stbd, rate = level_imu(sample.accel_mps2, sample.gyro_rps, roll, pitch)
            self.nav.add_imu(ImuInput(sample.time, fwd, stbd, rate))
            self.resolver.add_yaw_rate(sample.time, rate)
        elif isinstance(sample, AttitudeSample):
            self._attitudes.append(sample)
            self._recent_attitude.append(sample)
            self._attitude = sample
        elif isinstance(sample, HeadingSample):
            self._headings.append(sample)
            self._pending_heading = sample
            self._last_compass = sample.time
            self._compass_epoch = self.nav.gyro_epoch_at(sample.time)
            if self.frame is not None:
                self.resolver.add_heading(sample.time, self._grid_heading(sample))
            if self.nav.initialised and self.frame is not None:
                heading = self._grid_heading(sample)
                sigma = math.hypot(
                    self.params.pipeline.ekf.heading_sigma_rad,
                    sample.resolution_rad / math.sqrt(12),
                )
                self.nav.update_heading(sample.time, heading, sigma)
        elif isinstance(sample, GnssFix):
            self._fixes.append(sample)
            if sample.usable:
                self._gnss(sample)
        elif isinstance(sample, RangeSample):
            self._ranges.append(sample)
        self.stats.time("ekf", started)

    def _attitude_at(self, stamp: float) -> Attitude | None:
        """Roll and pitch when a ping stamped ``stamp`` was taken, with the seabed's
        altitude and slope under it (``_bottom_at``)."""
        return self._bottom_at(stamp, self._tilt_at(stamp))

    def _bottom_at(self, stamp: float, tilt: Attitude | None = None) -> Attitude | None:
        """``tilt`` with the altitude and slope of the seabed plane under the sonar at
        ``stamp`` (the ping being processed: the filter's pose now) from the echosounder's
        soundings so far; ``tilt`` as it is without them."""
        model = self._live_bottom(stamp)
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

    def _live_bottom(self, now: float) -> BottomModel | None:
        """The bottom model of the soundings so far, rebuilt when ``LIVE_BOTTOM_REFRESH_S``
        has passed and new soundings came (None: no echosounder, or too few)."""
        b = self.params.pipeline.bottom
        if not b.use_echosounder or not self._ranges or self._geometry is None:
            return None
        when, count = self._bottom_built
        if now - when < LIVE_BOTTOM_REFRESH_S or len(self._ranges) == count:
            return self._bottom
        self._bottom_built = (now, len(self._ranges))
        times = np.array(self.times, float)
        poses = np.array(self.poses, float).reshape(-1, 3)
        if int(np.all(np.isfinite(poses), axis=1).sum()) < 2:
            return self._bottom
        latency = self.params.pipeline.single_stage.graph.sonar_latency_s
        track = AttitudeTrack(self._attitudes, latency)
        points, stamps = sounding_points(
            self._ranges, pose_interpolator(times, poses), track.at, b.echosounder
        )
        if len(points) >= b.min_soundings:
            geometry = self._geometry
            self._bottom = BottomModel(points, stamps, geometry.down_m, geometry.footprint(), b)
        return self._bottom

    def _tilt_at(self, stamp: float) -> Attitude | None:
        """Roll and pitch when a ping stamped ``stamp`` was taken, from the recent
        attitude reports (None without one within half a second)."""
        recent = self._recent_attitude
        if not recent:
            return None
        t = stamp - self.params.pipeline.single_stage.graph.sonar_latency_s
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
        roll = before.roll_rad + w * math.remainder(after.roll_rad - before.roll_rad, 2 * math.pi)
        pitch = before.pitch_rad + w * (after.pitch_rad - before.pitch_rad)
        return Attitude(roll, pitch)

    def _grid_heading(self, sample: HeadingSample) -> float:
        assert self.frame is not None
        return (sample.heading_rad + self._convergence) % (2 * math.pi)

    def _gnss(self, fix: GnssFix) -> None:
        p = self.params.pipeline.ekf
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
        self.resolver.add_gnss(fix.time, x, y, vx, vy)
        if not self.nav.initialised:
            if self._pending_heading is None:
                return
            velocity = (0.0, 0.0) if math.isnan(vx) else (vx, vy)
            self.nav.initialise(fix.time, x, y, self._grid_heading(self._pending_heading), velocity)
            return
        self._pending_fixes.append((fix.time - self.params.gnss_time_offset_s, x, y))
        self.nav.update_position(fix.time, x, y, position_sigma(fix, p))
        if not math.isnan(vx):
            self.nav.update_velocity(fix.time, vx, vy, p.velocity_sigma_mps)

    # -- frames --------------------------------------------------------------------------
    def _frame(self, ping: Ping) -> None:
        stats = self.stats
        stats.frames_received += 1
        index = len(self.times)
        started = clock.perf_counter()
        prior: Array | None = None
        odometry: Array | None = None
        gyro: int | None = None
        if self.nav.initialised:
            self.nav.predict_to(ping.time)
            odometry = self.nav.odometry.copy()
            gyro = self.nav.gyro_epoch_at(ping.time)
            state, _ = self.nav.state()
            prior = state[[0, 1, PSI]]
        started = stats.time("ekf", started)
        if self._geometry is None and self.mount.altitude_m > 0:
            self._geometry = sonar_geometry(ping, self.mount, self.params.pipeline)
        sonar_frame = self.local.frame(ping)
        started = stats.time("preprocess", started)
        outcome = self.local.register(index, ping.time, sonar_frame, prior, odometry, gyro)
        started = stats.time("registration", started)
        self.times.append(ping.time)
        if self.params.reuse_registrations:
            self.outcomes.append(outcome)
        if not outcome.accepted:
            stats.frames_rejected += 1
            stats.rejected[outcome.reason] = stats.rejected.get(outcome.reason, 0) + 1
            self.poses.append(np.full(3, np.nan))
            return
        assert prior is not None
        stats.frames_mapped += 1
        sqrt_info = measured_info = None
        graph = self.params.pipeline.single_stage.graph
        if outcome.edge is not None:
            sqrt_info = registration_sqrt_info(
                outcome, self.mount, graph, ping.time - self.times[outcome.edge.i]
            )
        if outcome.measured is not None and self.params.resolve.keyframe_edges:
            measured_info = registration_sqrt_info(
                outcome, self.mount, graph, ping.time - self.times[outcome.measured.i]
            )
        outcome.registration = None  # the edges are what is kept of it
        if outcome.edge is not None:
            self.edges.append(outcome.edge)
        self._chain_frame(index, ping.time, prior, odometry, outcome.edge, gyro)
        self.resolver.add_frame(
            index, ping.time, prior, outcome.edge, sqrt_info, self._bridged,
            outcome.measured, measured_info,
        )  # fmt: skip
        started = stats.time("blending", started)
        self._close_loop(index, ping.time, sonar_frame.image)
        self._take_closures()
        self._bends_at[index] = self.anchor.bends.copy()
        started = stats.time("closures", started)
        pose = self._live_pose(index)
        self.poses.append(pose)
        self._accepted.append(index)
        # Blend at once at the chained pose.
        grid = self.local.preprocessor.grid if self.local.preprocessor else None
        assert grid is not None
        score = self.scorer(
            sonar_frame.image, sonar_frame.mask, sonar_frame.weight, sonar_frame.fan_weight
        )
        sonar = self.mount.sonar_pose(pose)
        layers = frame_layers(sonar_frame.image, score, sonar_frame.mask)
        touched = self._insert(index, layers, sonar_frame.mask, grid, sonar, ping.time)
        self._live[index] = _Live(index, ping.time, layers, sonar_frame.mask, grid, touched, sonar)
        stats.time("blending", started)
        self._emit_pose(index, final=False)
        self._since_solve += 1
        if self._since_solve >= self.params.solve_every:
            self._solve_window(final=False)
        if self.resolver.due(ping.time):
            self._resolve(ping.time)
        if self.params.resolve.enabled:
            self._redraw(ping.time, self.params.resolve.redraws_per_frame)
        self._render(force=False)

    def _insert(
        self,
        index: int,
        layers: npt.NDArray[np.float32],
        mask: npt.NDArray[np.bool_],
        grid: SonarGrid,
        sonar: Array,
        time: float,
        deferred: bool = False,
    ) -> list[TileKey]:
        """Offer a frame (its stack of image, score and mask) to the tiles at sonar pose
        ``sonar`` (local); ``deferred``: a redraw (rendered at ``redraw_render_every_s``)."""
        assert self.frame is not None
        east, north = self.frame.to_utm(sonar[0], sonar[1])
        pose = SonarPose(float(east), float(north), float(sonar[2]))
        touched = self.tiles.insert_layers(index, layers, mask, grid, pose, time, deferred=deferred)
        for key in touched:
            self._pending_frames.setdefault(key, []).append(index)
        return touched

    # -- the live chain ---------------------------------------------------------------
    def _chain_frame(
        self,
        index: int,
        time: float,
        prior: Array,
        odometry: Array | None,
        edge: Edge | None,
        gyro: int | None = None,
    ) -> None:
        """Chain an accepted frame onto the previous one: by its registration, else by the
        filter's dead-reckoned motion (a rejection or a restart never jumps to the
        prior); then give the anchor the fixes and the heading residual up to here.

        gyro: the filter's gyro epoch here. Where it is not the previous frame's, the
        filter held its heading (the autopilot link silent): the turn is the chain's, and
        the filter's heading is no measurement for the anchor until the compass speaks."""
        last = self._last_chained
        self._bridged = None
        if last is None:
            self._chain[index] = prior[:2].copy()
            self._chain_heading[index] = float(prior[2])
            self.anchor.update_heading(time, 0.0)
        else:
            heading = self._chain_heading[last] + self.anchor.heading
            reckoned = self._dead_reckoned(last, odometry)
            span = time - self.times[last]
            covered = gyro is not None and self._gyro.get(last) == gyro
            if not covered:
                # The chain's turn since the last frame is the registrations', not the
                # gyro's: the anchor's heading rate error does not act over it.
                self.anchor.predict(time, gyro=False)
            bridge_sigma = 0.0
            scaled = True
            if edge is not None and edge.i == last:
                forward, starboard, dyaw = edge.forward_m, edge.starboard_m, edge.yaw_rad
                if span > 0:
                    self._registered_velocity = (forward / span, starboard / span, time)
            else:
                forward, starboard, dyaw = reckoned or (0.0, 0.0, 0.0)
                bridge_sigma = self.params.bridge_filter_sigma_mps * span
                scaled = False
            velocity = self._registered_velocity
            age = time - velocity[2] if velocity is not None else math.inf
            recent = age <= self.params.bridge_velocity_age_s
            bridged = edge is None or edge.i != last
            rate = (
                self.local.chain_rate(time, self.params.bridge_velocity_age_s) if bridged else None
            )
            if reckoned is not None and covered:
                # The heading follows the gyro (through the filter): over a ping it is good
                # to a hundredth of a degree, where a registration's yaw is good to a few
                # hundredths and its errors add up along the chain.
                dyaw = reckoned[2]
            elif bridged:
                # No gyro and no registration: the chain's turn rate, held.
                dyaw = rate[2] * span if rate is not None else 0.0
            if not covered and rate is not None:
                # The filter held its heading and velocity (no IMU): the chain's own, held.
                velocity, recent = (rate[0], rate[1], time), True
            if bridged and velocity is not None and recent:
                # Bridge at the speed the registrations last measured, turned by half the
                # gyro's turn (the chord of the arc): the boat's speed through a rejection
                # changes by centimetres a second, the filter's velocity (a GNSS outage:
                # the accelerometers alone) by decimetres.
                turn_s, turn_c = math.sin(0.5 * dyaw), math.cos(0.5 * dyaw)
                forward_v, starboard_v = velocity[0] * span, velocity[1] * span
                forward = forward_v * turn_c - starboard_v * turn_s
                starboard = forward_v * turn_s + starboard_v * turn_c
                bridge_sigma = self.params.bridge_velocity_sigma_mps * span
                scaled = True
            if scaled:
                forward *= 1.0 + self.anchor.scale
                starboard *= 1.0 + self.anchor.scale
            s, c = math.sin(heading), math.cos(heading)
            step = np.array([forward * s + starboard * c, forward * c - starboard * s])
            self._chain[index] = self._chain[last] + step
            self._chain_heading[index] = self._chain_heading[last] + dyaw
            if bridged:
                # The re-solve bridges it as the chain did, as uncertain as the chain
                # takes it (a live filter in a GNSS outage drifts by decimetres a
                # second: its poses are no odometry to bridge with).
                graph = self.params.pipeline.single_stage.graph
                rate_sigma = (
                    graph.odometry_rate_sigma_rps if covered else graph.coast_rate_sigma_rps
                )
                self._bridged = Bridge(
                    last, forward, starboard, dyaw,
                    graph.odometry_sigma_m + bridge_sigma,
                    graph.odometry_sigma_rad + rate_sigma * span,
                )  # fmt: skip
            self.anchor.chain_step((float(step[0]), float(step[1])), bridge_sigma, scaled)
            # Fixes whose (lagged) time lies up to this frame: residual against the chain.
            t0 = self.times[last]
            while self._pending_fixes and self._pending_fixes[0][0] <= time:
                t_fix, x, y = self._pending_fixes.popleft()
                if t_fix < t0 - 1.0:
                    continue
                x, y = self.drawn_frame.point(x, y)
                w = min(max((t_fix - t0) / max(time - t0, 1e-6), 0.0), 1.0)
                at = (1 - w) * self._chain[last] + w * self._chain[index]
                self.anchor.update_position(t_fix, (x - float(at[0]), y - float(at[1])))
            # The filter's heading carries the compass's error; the last re-solve
            # estimated it (misalignment and deviation).
            if time - self._last_compass <= self.params.heading_fresh_s or (
                gyro is not None and gyro == self._compass_epoch
            ):
                heading = float(prior[2]) - self.resolver.compass_error(float(prior[2]))
                heading += self.drawn_frame.turn
                self.anchor.update_heading(
                    time, math.remainder(heading - self._chain_heading[index], 2 * math.pi)
                )
        if odometry is not None:
            self._odometry[index] = odometry
        self._gyro[index] = gyro
        self._last_chained = index

    def _close_loop(self, index: int, time: float, image: npt.NDArray[np.float32]) -> None:
        """Register the frame against a keyframe of an earlier pass when one overlaps
        (``mapping.live_closures``); a confirmed closure updates the anchor."""
        if not self.params.closures.enabled:
            return
        preprocessor = self.local.preprocessor
        assert preprocessor is not None
        if self.closures is None:
            bearings = preprocessor.fan.bearings_rad
            self.closures = LiveClosures(
                self.params.closures,
                self.mount,
                (preprocessor.min_range_m, preprocessor.fan.max_range_m),
                max(abs(float(bearings[0])), abs(float(bearings[-1]))),
            )
        self.closures.consider(
            index,
            time,
            self._live_pose(index),
            self._chain[index],
            self._chain_heading[index],
            image,
            self.local.fine_registrar,
            self.anchor,
        )

    def _dead_reckoned(
        self, last: int, odometry: Array | None
    ) -> tuple[float, float, float] | None:
        """The filter's motion since frame ``last`` in that frame (forward, starboard, yaw),
        None when the filter has no odometry there."""
        before = self._odometry.get(last)
        if odometry is None or before is None:
            return None
        dx, dy, dyaw = odometry - before
        heading = self._chain_heading[last] + self.anchor.heading
        s, c = math.sin(heading), math.cos(heading)
        return float(s * dx + c * dy), float(c * dx - s * dy), float(dyaw)

    def _live_pose(self, k: int) -> Array:
        """The chained frame where the anchor puts it now (local metres, grid heading):
        the anchor's correction, less the map's bends it followed since the frame was
        chained (those belong to other places of the map)."""
        ce, cn = self.anchor.correction
        bends = self.anchor.bends - self._bends_at.get(k, self.anchor.bends)
        xy = self._chain[k]
        heading = (self._chain_heading[k] + self.anchor.heading - bends[2]) % (2 * math.pi)
        return np.array([xy[0] + ce - bends[0], xy[1] + cn - bends[1], heading])

    # -- the live window -------------------------------------------------------------
    def _solve_window(self, final: bool) -> None:
        """Place the frames still in the window where the anchor now puts them (frames
        move with its correction, never against each other); re-blend frames that moved;
        finalise frames leaving the window."""
        self._since_solve = 0
        started = clock.perf_counter()
        accepted = self._accepted
        window = accepted[self._final_upto :]
        if window:
            self.stats.windows_solved += 1
            for k in window:
                self.poses[k] = self._live_pose(k)
        self.stats.time("optimisation", started)
        started = clock.perf_counter()
        # Frames leaving the window become final.
        keep = 0 if final else self.params.window_frames
        upto = max(len(accepted) - keep, self._final_upto)
        held = (
            self.closures.holding(self.times[accepted[-1]])
            if self.closures is not None and accepted and not final
            else None
        )
        if held is not None:
            # A pair of passes waits for its closures to agree: the frames drawn since
            # just before its first one stay live, so that they move with it when it is
            # applied instead of staying where the GNSS put them (bounded).
            oldest = max(len(accepted) - self.params.closure_hold_frames, self._final_upto)
            while upto > oldest and self.times[accepted[upto - 1]] >= held:
                upto -= 1
        leaving = set(accepted[self._final_upto : upto])
        for k in list(self._live):
            threshold = (
                self.params.move_threshold_m if k in leaving else self.params.live_move_threshold_m
            )
            self._reblend_if_moved(k, threshold)
        for k in accepted[self._final_upto : upto]:
            live = self._live.pop(k, None)
            if live is not None:
                self._keep_drawn(k, live)
                if self.closures is not None:
                    # The correction it is drawn with: its pose less its chained one.
                    pose = self.poses[k]
                    drawn_with = np.array(
                        [
                            pose[0] - self._chain[k][0],
                            pose[1] - self._chain[k][1],
                            math.remainder(float(pose[2]) - self._chain_heading[k], 2 * math.pi),
                        ]
                    )
                    self.closures.offer_keyframe(
                        k,
                        live.time,
                        pose,
                        drawn_with,
                        float(self.anchor.correction_covariance()[2, 2]),
                        np.ascontiguousarray(live.layers[..., 0]),
                        live.grid,
                    )
            self._emit_pose(k, final=True)
            # A final frame is never chained onto again but the last one.
            if k != self._last_chained:
                self._chain.pop(k, None)
                self._chain_heading.pop(k, None)
                self._odometry.pop(k, None)
                self._gyro.pop(k, None)
                self._bends_at.pop(k, None)
        self._final_upto = upto
        self.stats.time("blending", started)

    # -- the live re-solve ---------------------------------------------------------------
    def _keep_drawn(self, k: int, live: _Live) -> None:
        """A frame became final: its image is kept to draw it again after a re-solve (or,
        with re-solves off, its tiles forget it)."""
        if not self.params.resolve.enabled:
            self.tiles.settle(k, live.tiles)
            return
        chain = np.array([*self._chain[k], self._chain_heading[k]])
        drawn = pack(
            k, live.time, live.layers[..., 0], live.layers[..., 1], live.mask, live.grid,
            live.tiles, live.blended_pose, chain,
        )  # fmt: skip
        for old in self.resolver.keep(drawn):
            pose = self._to_redraw.pop(old.index, None)
            if pose is not None:
                # Its image goes: drawn at its pose now, on the redraw budget's account
                # (at 10 Hz, 487 of 835 frames let go were still waiting: 2.3 ms a frame
                # beyond the budget).
                self._redraw_one(old, pose, live.time)
                self._redraw_credit -= 1.0
            self.tiles.settle(old.index, old.tiles)

    def _take_closures(self) -> None:
        """Closures the live anchor took are kept for the re-solve (covariance in the
        keyframe's vehicle frame)."""
        if self.closures is None or not self.closures.taken:
            return
        for c in self.closures.taken:
            rot = world_rotation(c.heading_i)
            cov = rot.T @ c.covariance @ rot
            r = c.relative
            self.resolver.add_closure(
                ResolveClosure(c.i, c.j, r.forward_m, r.starboard_m, r.yaw_rad, cov)
            )
        self.closures.taken.clear()

    def _resolve(self, now: float) -> None:
        """Re-solve the drawn frames (``mapping.live_resolve``), draw again those that
        moved, and carry the chain on from the new map."""
        started = clock.perf_counter()
        resolver = self.resolver
        if resolver.gnss_silent(now):
            resolver.solved(now)
            return
        old = self.drawn_frame
        back = old.inverse()
        # The solution is in the GNSS's frame: what holds it (the frame before the
        # stretch, keyframes outside it) is taken there from where it is drawn.
        out = resolver.solve(_PosesIn(back, self.poses))
        resolver.solved(now)
        if out is None:
            return
        nodes, in_gnss = out
        self.stats.resolves += 1
        rp = self.params.resolve
        if nodes[0] in resolver.drawn:
            # Nothing holds the stretch (no frame before it is fixed): keep the drawn
            # map's place and (within a bound) its orientation; change its shape.
            drawn_poses = np.array([self.poses[k] for k in nodes])
            new = align(in_gnss, drawn_poses, math.radians(rp.max_turn_deg))
        else:
            new = old
        solved = new.poses(in_gnss)
        # Where the chain joins the solution: the first frame of the live window (solved
        # with the rest: ``ResolveParams.live_tail``), else the last drawn frame.
        m_join = nodes.index(next(reversed(resolver.drawn)))
        if m_join + 1 < len(nodes) and nodes[m_join + 1] in self._chain:
            m_join += 1
            was_join = self._live_pose(nodes[m_join])
        else:
            was_join = self.poses[nodes[m_join]].copy()
        moved_nodes: list[int] = []
        for m, k in enumerate(nodes):
            drawn = resolver.drawn.get(k)
            if drawn is None:
                continue
            # Against its pose (where it is drawn, or is to be drawn once its turn in the
            # queue comes): the live poses do not depend on how soon frames are drawn.
            sonar = self.mount.sonar_pose(solved[m])
            was = self.mount.sonar_pose(self.poses[k])
            moved = math.hypot(sonar[0] - was[0], sonar[1] - was[1])
            moved += 5.0 * abs(math.remainder(sonar[2] - was[2], 2 * math.pi))
            if moved > rp.redraw_m:
                moved_nodes.append(m)
        # Every frame that moved is drawn again: redrawing only those that moved most
        # left neighbours drawn apart (quadrats seed 6 at 2 Hz: live lanes 8.0 -> 11.9 /
        # 10.4 cm, quadrat spacing 2.1 -> 4.4 / 6.5 cm). Its pose and its keyframe move
        # now; it is drawn again as the next frames come (``_redraw``), so that no frame
        # waits for a stretch's worth of redraws (seconds: the daemon would skip frames)
        # and the redraws take a bounded share of the engine's time.
        for m in moved_nodes:
            k, pose = nodes[m], solved[m]
            drawn = resolver.drawn[k]
            self.poses[k] = np.array(pose, float)
            self._to_redraw[k] = self.poses[k]
            self._queued_at.setdefault(k, now)
            self._emit_pose(k, final=True)
            if self.closures is not None:
                correction = np.array(
                    [
                        pose[0] - drawn.chain[0],
                        pose[1] - drawn.chain[1],
                        math.remainder(float(pose[2]) - drawn.chain[2], 2 * math.pi),
                    ]
                )
                self.closures.store.move(k, pose, self.mount.sonar_pose(pose), correction)
        if self.closures is not None:
            self.closures.rebase()
        # The chain carries on from the re-solved map: the live window moves so that its
        # first frame is where the solution puts it, next to the last drawn frame (moved
        # with the last drawn frame instead, the live window kept what the anchor's
        # corrections between two finalised blocks had put between them: 0.2-0.7 m
        # steps in the live map after the autopilot link came back). They keep their own
        # heading: the solution's end is its least certain part, and turned with it the
        # chain on quadrats seed 6 at 2 Hz took a 2.6 degree turn at the last re-solve and
        # drew the last lane 0.5 m off (live lanes 25 cm; 14 without).
        n = self._last_chained
        if n is not None and n in self._chain:
            move_e = float(solved[m_join][0] - was_join[0])
            move_n = float(solved[m_join][1] - was_join[1])
            self.anchor.x[0] += move_e
            self.anchor.x[1] += move_n
            # What the GNSS sees of the chain stays: the fixes since the joining frame were
            # taken against it, and the solution's bias is not known beyond that frame
            # (there it decays towards zero). Taking the solution's bias and its
            # covariance instead made quadrats seed 6 at 2 Hz 19 -> 42 cm live. The
            # fixes are taken into the new drawn frame: where the boat is, they move by
            # what the frame moved there.
            q = in_gnss[m_join]
            e0, n0 = old.point(float(q[0]), float(q[1]))
            e1, n1 = new.point(float(q[0]), float(q[1]))
            self.anchor.x[2] += (e1 - e0) - move_e
            self.anchor.x[3] += (n1 - n0) - move_n
        self.drawn_frame = new
        self.stats.time("resolve", started)

    def _redraw(self, now: float, credit: float, everything: bool = False) -> None:
        """Draw again frames re-solves moved: ``credit`` more of them (a new frame's
        ``resolve.redraws_per_frame``; what is left over carries to the next frame, up
        to three), or all of them with ``everything``.

        The queue is swept along the track, from the oldest frame to the newest and round
        again: consecutive redraws use the same tiles (drawn in order of how far they
        moved, a redraw loaded tiles from all over the stretch: 21 tiles in memory at
        once where 16 sufficed), no frame waits more than a sweep while new re-solves
        queue others, and the oldest, whose images go first (``resolve.memory_mb``), are
        drawn before they must be at once (newest first, those let go while waiting
        were 3 ms a frame at 10 Hz beyond the budget)."""
        if not self._to_redraw:
            self._redraw_credit = 0.0
            return
        started = clock.perf_counter()
        self._redraw_credit = min(self._redraw_credit + credit, _MOST_REDRAWS)
        recent = self._redraw_recent
        queue = self._to_redraw
        while queue and (everything or self._redraw_credit >= 1.0):
            cursor = self._redraw_cursor
            k = min((j for j in queue if j > cursor), default=-1)
            if k < 0:
                k = min(queue)
            self._redraw_cursor = k
            pose = queue.pop(k)
            self._redraw_credit -= 1.0
            drawn = self.resolver.drawn.get(k)
            if drawn is None:
                self._queued_at.pop(k, None)
                continue
            self._redraw_one(drawn, pose, now)
            recent.append(drawn.tiles)
            if len(self.tiles.active) > self.params.resolve_tiles_in_memory:
                # Tiles of a stretch the boat has left were loaded to be redrawn: they
                # leave memory again as the redraw moves on (memory follows the area),
                # but not those the last few redraws used (``_evict``: the next ones
                # use them too).
                self._evict(now)
        if not queue:
            self._redraw_credit = 0.0
            recent.clear()
        self.stats.time("resolve", started)

    def _redraw_one(self, drawn: Drawn, pose: Array, now: float) -> None:
        k = drawn.index
        wait = max(now - self._queued_at.pop(k, now), 0.0)
        self.stats.redraw_wait_s += wait
        self.stats.redraw_wait_max_s = max(self.stats.redraw_wait_max_s, wait)
        sonar = self.mount.sonar_pose(pose)
        self.tiles.remove(k, drawn.tiles, deferred=True)
        layers, mask = drawn.layers()
        drawn.tiles = self._insert(k, layers, mask, drawn.grid, sonar, drawn.time, deferred=True)
        drawn.blended_sonar = sonar
        self.stats.frames_redrawn += 1

    def _reblend_if_moved(self, k: int, threshold: float) -> None:
        live = self._live[k]
        sonar = self.mount.sonar_pose(self.poses[k])
        moved = math.hypot(sonar[0] - live.blended_pose[0], sonar[1] - live.blended_pose[1])
        # A yaw error turns the far edge of the fan (5 m away) the most.
        moved += 5.0 * abs(math.remainder(sonar[2] - live.blended_pose[2], 2 * math.pi))
        if moved <= threshold:
            return
        self.tiles.remove(k, live.tiles)
        live.tiles = self._insert(k, live.layers, live.mask, live.grid, sonar, live.time)
        live.blended_pose = sonar
        self.stats.frames_reblended += 1
        self._emit_pose(k, final=False)

    # -- output ---------------------------------------------------------------------------
    def _emit_pose(self, k: int, final: bool) -> None:
        if self.on_pose is None or self.frame is None:
            return
        pose = self.poses[k]
        east, north = self.frame.to_utm(pose[0], pose[1])
        lat, lon = self.frame.to_latlon(pose[0], pose[1])
        heading = math.degrees(self.frame.grid_to_true(float(pose[2]), float(lat), float(lon)))
        self.on_pose(
            PoseUpdate(
                k, self.times[k], float(east), float(north), heading % 360.0, float(lat),
                float(lon), self.frame.epsg, final,
            )
        )  # fmt: skip

    def _render(self, force: bool) -> None:
        now = self._released if self._released != math.inf else max(self.times, default=0.0)
        if not force and now - self._last_render < self.params.render_every_s:
            return
        self._last_render = now
        started = clock.perf_counter()
        full = force or now - self._last_refine >= self.params.refine_every_s
        if full:
            self._last_refine = now
        redrawn = force or now - self._last_redrawn_render >= self.params.redraw_render_every_s
        if redrawn and full:
            self._last_redrawn_render = now
        for image in self.tiles.render_dirty(new_only=not full, deferred=redrawn):
            self._publish(image)
        self._evict(now)
        self.stats.time("render", started)

    def _evict(self, now: float) -> None:
        keep = {key for live in self._live.values() for key in live.tiles}
        # Tiles the last redraws loaded stay while redraws go on (the next ones use them).
        keep.update(key for tiles in self._redraw_recent for key in tiles)
        for image in self.tiles.evict_idle(now, keep):
            self._publish(image)
        self.stats.tile_spill_failures = self.tiles.spill_failures
        self.stats.tile_spill_error = self.tiles.spill_error

    def _publish(self, image: TileImage) -> None:
        frames = tuple(self._pending_frames.pop(image.key, ()))
        if self.on_tile is None or self.frame is None:
            return
        grid = self.tiles.grid
        west, north = grid.tile_west_north(image.key)
        self.on_tile(
            TileUpdate(
                image.key, image.values, image.version, self.frame.epsg, grid.res_m,
                grid.tile_px, west, north, frames,
            )
        )  # fmt: skip

    # -- survey end ------------------------------------------------------------------------
    def finish(
        self,
        pings: Callable[[], Iterable[Ping]],
        progress: Callable[[str, int, int], None] | None = None,
        spill: TileSpill | None = None,
    ) -> SurveyResult:
        """The survey-end pass over every frame (``pings()`` yields them again, in
        order): the smoothed EKF, the registrations (again, or the live ones), loop
        closures, the final mode's optimisation, and every tile re-rendered; tile versions
        carry on growing."""
        self.flush()
        nav = NavSamples(
            self._imu.samples(), self._fixes, self._headings, self._attitudes, ranges=self._ranges
        )
        result = map_survey(
            pings,
            nav,
            self.mount,
            self.params.pipeline,
            self.params.final_mode,
            progress,
            registrations=self.outcomes if self.params.reuse_registrations else None,
            spill=spill,
        )
        # Continue the live versions so a subscriber sees every final tile as newer.
        for key in result.mosaic.all_keys():
            result.mosaic.versions[key] = self.tiles.versions.get(key, 0)
        if self.on_tile is not None:
            for image in result.mosaic.rendered_tiles():
                bumped = TileImage(image.key, image.values, image.version + 1)
                result.mosaic.versions[image.key] = bumped.version
                self._publish(bumped)
        return result


class _ImuRecord:
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


_KINDS: dict[type, int] = {
    ImuSample: 0,
    AttitudeSample: 1,
    HeadingSample: 2,
    GnssFix: 3,
    Ping: 4,
    RangeSample: 5,
}
