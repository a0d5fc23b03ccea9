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

The engine is a composition of stages, each with one job, that pass each other what they
need as arguments and results (so that each could run on its own, with queues between):

- ``mapping.stream_reorder.ReorderBuffer``: the samples in time order, each once;
- ``mapping.stream_navigation.NavigationRecord``: the filter, the local frame, the
  attitude and seabed a ping is projected with, and the record for the survey-end pass;
- ``mapping.stream_front``: each ping preprocessed and registered, here or in a worker
  process (``front``), up to ``front_depth`` pings ahead of the stages after it;
- ``mapping.stream_chain.LiveChain``: each frame chained, the chain's anchor and its
  loop closures, the frames' live poses;
- ``mapping.stream_window.LiveWindow``: which frames are live and which final, and the
  live re-solve;
- ``mapping.stream_drawing.LiveDrawing``: the tiles, frames blended and drawn again,
  renders and the tiles that leave memory.

The engine holds what is the live map's own (each frame's stamp and pose), routes each
stage's results to the next, and publishes the poses and tiles. The stages after the
front take the navigation's measurements and the front's frames in one queue, in the
order the samples were released, whenever the front's results arrive: they see the same
sequence wherever the front runs. The one thing the front is given from them, the bottom
model of the echosounder's soundings placed by the live poses (built after a frame, over
the soundings released with its ping), is the newest built ``front_depth`` frames back.
The map is the same, to the bit, for any placement of the front.
"""

from __future__ import annotations

import math
import time as clock
from array import array
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mapping.bottom import BottomModel
from mapping.ekf import NavFilter
from mapping.fmt import Registration
from mapping.frames import FrameOutcome, LocalRegistration, SonarMount
from mapping.geo import LocalFrame
from mapping.live_anchor import LiveAnchor
from mapping.live_closures import ClosureJob, LiveClosures
from mapping.live_resolve import DrawnFrame, LiveResolver
from mapping.mosaic import TileKey
from mapping.pipeline import (
    SurveyResult,
    map_survey,
)
from mapping.posegraph import Edge
from mapping.samples import Ping
from mapping.stream_chain import LiveChain
from mapping.stream_drawing import LiveDrawing, Redraw, RenderedTile
from mapping.stream_front import Front, FrontJob, FrontResult, FrontStage, InlineFront
from mapping.stream_navigation import Measured, NavigationRecord, NavSample, PingNavigation
from mapping.stream_params import StreamingParams
from mapping.stream_reorder import Admission, ReorderBuffer, Sample
from mapping.stream_window import LiveWindow
from mapping.tasks import TaskPool
from mapping.tiles import TileImage, TileSpill, TileStore

Array = npt.NDArray[np.float64]


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


@dataclass(frozen=True, slots=True)
class _Navigated:
    """A navigation sample's measurements, waiting for the stages after the front."""

    time: float
    measured: Measured


@dataclass(frozen=True, slots=True)
class _Sent:
    """A ping handed to the front, waiting for its result."""

    index: int
    time: float
    at: PingNavigation
    sent: float
    """``time.perf_counter`` when it was handed over."""
    held: tuple[int, int]
    """The soundings and attitude reports the navigation held then (``NavigationRecord.held``)."""


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
    front_wait_s: float = 0.0
    """Time the engine waited for the front's results (a front in a worker process)."""

    @property
    def redraw_wait_mean_s(self) -> float:
        return self.redraw_wait_s / max(self.frames_redrawn, 1)

    def time(self, stage: str, started: float) -> float:
        now = clock.perf_counter()
        self.stage_s[stage] = self.stage_s.get(stage, 0.0) + now - started
        return now


class StreamingEngine:
    """See the module docstring. Not thread-safe: one feeder."""

    def __init__(
        self,
        mount: SonarMount,
        params: StreamingParams | None = None,
        on_pose: Callable[[PoseUpdate], None] | None = None,
        on_tile: Callable[[TileUpdate], None] | None = None,
        spill: TileSpill | None = None,
        front: FrontStage | None = None,
    ) -> None:
        """``front``: where the front stage runs (``mapping.stream_front``; None: in this
        process, each ping as it is released)."""
        self.mount = mount
        self.params = params or StreamingParams()
        self.on_pose = on_pose
        self.on_tile = on_tile
        self.stats = StreamStats()
        p = self.params
        self.reorder = ReorderBuffer(p.reorder_s)
        self.navigation = NavigationRecord(mount, p.pipeline, p.gnss_time_offset_s)
        self.front: FrontStage = front if front is not None else InlineFront(Front(mount, p))
        self._queue: deque[_Navigated | _Sent] = deque()
        """What the stages after the front have still to take, in release order."""
        self._sent = 0
        """Pings handed to the front."""
        self._now = -math.inf
        """The stamp of the sample the stages after the front take (or took last)."""
        self.chain = LiveChain(mount, p)
        self.window = LiveWindow(mount, p)
        self.drawing = LiveDrawing(mount, p, spill)
        # Per frame, survey-long but small (a few numbers a frame).
        self.times: list[float] = []
        self.poses: list[Array] = []
        self.outcomes: list[FrameOutcome] = []
        """Every frame's registration, kept for the survey-end pass only when it reuses them
        (``reuse_registrations``): 300 bytes a frame otherwise held for nothing."""
        self.edges: list[Edge] = []
        self.sent_at = array("d")
        """Per frame: ``time.perf_counter`` when its ping went to the front (latency)."""
        self._bottoms: deque[tuple[int, BottomModel]] = deque()
        """Bottom models of the echosounder's soundings, each with the frame after which
        it was built (``NavigationRecord.build_bottom``, over the live poses then): a ping
        is projected over the newest built ``front_depth`` frames before it, the same
        whenever the front asks."""
        self._closure_jobs: dict[int, list[ClosureJob]] = {}
        """Loop closures' registrations to hand to the front with the ping of this index."""
        self._registered: list[tuple[int, Registration]] = []
        """Closures' registrations come back from the front, for the next accepted frame."""

    # -- the stages' parts others read -----------------------------------------------------
    @property
    def frame(self) -> LocalFrame | None:
        """The local frame (laid around the first usable fix)."""
        return self.navigation.frame

    @property
    def nav(self) -> NavFilter:
        """The navigation filter, run forward."""
        return self.navigation.nav

    @property
    def local(self) -> LocalRegistration:
        """The live preprocessing and registration (a front in this process only)."""
        assert isinstance(self.front, InlineFront), "the front runs in another process"
        return self.front.front.local

    @property
    def anchor(self) -> LiveAnchor:
        """What ties the live chain to the GNSS, the compass and the closures."""
        return self.chain.anchor

    @property
    def closures(self) -> LiveClosures | None:
        """The live loop closures (None until the first frame is chained, or when off)."""
        return self.chain.closures

    @property
    def resolver(self) -> LiveResolver:
        """What the live re-solve keeps (the drawn frames' images among it)."""
        return self.window.resolver

    @property
    def drawn_frame(self) -> DrawnFrame:
        """The live map's frame against the GNSS's (``mapping.live_resolve.align``)."""
        return self.window.drawn_frame

    @property
    def tiles(self) -> TileStore:
        """The live mosaic's tiles."""
        return self.drawing.tiles

    # -- input -------------------------------------------------------------------------
    def add(self, sample: Sample) -> None:
        """Take one sample (any type) as it arrives."""
        admission = self.reorder.offer(sample)
        if admission is Admission.LATE:
            self.stats.samples_late += 1
            if isinstance(sample, Ping):
                self.stats.frames_received += 1
                self.stats.frames_skipped += 1
            return
        if admission is Admission.DUPLICATE:
            self.stats.samples_duplicate += 1
            return
        self._process(self.reorder.due())

    @property
    def processed_upto(self) -> float:
        """Every sample stamped at or before this time (s) has been processed (by every
        stage: what the front still holds has not)."""
        return self._released if self._queue else self.reorder.released

    @property
    def _released(self) -> float:
        """The stamp of the sample the stages after the front take now, or took last
        (``tools.bench`` reads it when a tile is published)."""
        return self._now

    def flush(self) -> None:
        """Process everything held (the end of the stream), render what changed, and
        make every remaining pose final."""
        self._process(self.reorder.release(math.inf))
        self._take(everything=True)
        self._solve_window(final=True)
        self._redraw(self._released, 0.0, everything=True)
        self._render(force=True)

    def take_ready(self) -> None:
        """Let the stages after the front take what the front has finished, without a new
        sample (a daemon between samples)."""
        self._take()

    def close(self) -> None:
        """Let go of the front (its worker process, if it has one)."""
        self.front.close()

    def _process(self, samples: Iterable[Sample]) -> None:
        for sample in samples:
            if isinstance(sample, Ping):
                self._send(sample)
            else:
                self._navigate(sample)
            self._take()

    # -- navigation --------------------------------------------------------------------
    def _navigate(self, sample: NavSample) -> None:
        started = clock.perf_counter()
        self._queue.append(_Navigated(sample.time, self.navigation.take(sample)))
        self.stats.time("ekf", started)

    def _navigated(self, event: _Navigated) -> None:
        """The stages after the front take a navigation sample's measurements."""
        started = clock.perf_counter()
        measured = event.measured
        self.window.take_navigation(measured)
        if measured.chain_fix is not None:
            self.chain.take_fix(measured.chain_fix)
        self.stats.time("ekf", started)

    # -- frames --------------------------------------------------------------------------
    def _send(self, ping: Ping) -> None:
        """Hand a ping to the front with the filter's pose at its stamp and the attitude
        and seabed to project it with, over the live map's frames up to ``front_depth``
        before it as they were chained (waiting for the stages after the front to have
        them): what the front is given does not depend on how far behind it they are."""
        self.stats.frames_received += 1
        index = self._sent
        self._sent += 1
        upto = max(index - self.params.front_depth, 0)
        self._take(upto=upto)
        started = clock.perf_counter()
        at = self.navigation.at_ping(ping)
        attitude = self.navigation.attitude_over(ping.time, self._bottom_before(upto))
        self.stats.time("ekf", started)
        closures = tuple(self._closure_jobs.pop(index, ()))
        self.front.submit(FrontJob(index, ping, at, attitude, closures))
        sent = clock.perf_counter()
        self.sent_at.append(sent)
        self._queue.append(_Sent(index, ping.time, at, sent, self.navigation.held))

    def _bottom_before(self, upto: int) -> BottomModel | None:
        """The newest bottom model built after a frame before ``upto`` (``_bottoms``)."""
        bottoms = self._bottoms
        while len(bottoms) > 1 and bottoms[1][0] < upto:
            bottoms.popleft()
        return bottoms[0][1] if bottoms and bottoms[0][0] < upto else None

    def _take(self, upto: int | None = None, everything: bool = False) -> None:
        """The stages after the front take what waits for them, in order: navigation at
        once, frames as the front's results come; they wait for a result while more than
        ``front_depth`` frames are with the front, or until frame ``upto`` is chained
        (``everything``: until nothing waits)."""
        queue = self._queue
        while queue:
            head = queue[0]
            if isinstance(head, _Navigated):
                queue.popleft()
                self._now = head.time
                self._navigated(head)
                continue
            must = (
                everything
                or (upto is not None and len(self.times) < upto)
                or self._sent - len(self.times) > self.params.front_depth
            )
            if not must and not self.front.ready():
                return
            started = clock.perf_counter()
            result = self.front.result()
            self.stats.front_wait_s += clock.perf_counter() - started
            queue.popleft()
            self._now = head.time
            self._frame(head, result)

    def _frame(self, sent: _Sent, result: FrontResult) -> None:
        stats = self.stats
        index = sent.index
        if result.index != index:
            raise RuntimeError(f"the front returned frame {result.index} for frame {index}")
        self.chain.take_front(result)
        self._registered.extend(result.closures)
        for stage, seconds in result.seconds.items():
            stats.stage_s[stage] = stats.stage_s.get(stage, 0.0) + seconds
        started = clock.perf_counter()
        at = sent.at
        outcome = result.outcome
        self.times.append(sent.time)
        if self.params.reuse_registrations:
            self.outcomes.append(outcome)
        if not outcome.accepted:
            stats.frames_rejected += 1
            stats.rejected[outcome.reason] = stats.rejected.get(outcome.reason, 0) + 1
            self.poses.append(np.full(3, np.nan))
            self._build_bottom(sent)
            return
        assert at.prior is not None
        stats.frames_mapped += 1
        bridge = self.chain.link(index, sent.time, at, outcome.edge)
        self.window.add_frame(index, sent.time, at.prior, outcome, bridge, self.times)
        outcome.registration = None  # the edges are what is kept of it
        if outcome.edge is not None:
            self.edges.append(outcome.edge)
        started = stats.time("blending", started)
        taken, job = self.chain.close_loop(index, sent.time, result.image, self._registered)
        self._registered.clear()
        if job is not None:
            # Registered with the ping ``front_depth + 1`` on: the next one not yet
            # handed to the front, wherever it runs and however far behind it the stages
            # after it are; applied when that ping's result comes back.
            self._closure_jobs.setdefault(index + self.params.front_depth + 1, []).append(job)
        self.window.take_closures(taken)
        started = stats.time("closures", started)
        pose = self.chain.live_pose(index)
        self.poses.append(pose)
        # Blend at once at the chained pose.
        sonar = self.mount.sonar_pose(pose)
        self.drawing.draw(
            index, sent.time, result.layers, result.mask, self.chain.grid, sonar, self.frame
        )
        stats.time("blending", started)
        self._emit_pose(index, final=False)
        if self.window.solve_due:
            self._solve_window(final=False)
        if self.window.resolve_due(sent.time):
            self._resolve(sent.time)
        if self.params.resolve.enabled:
            self._redraw(sent.time, self.params.resolve.redraws_per_frame)
        self._render(force=False)
        self._build_bottom(sent)

    def _build_bottom(self, sent: _Sent) -> None:
        """After a frame: a new bottom model when one is due, over the live poses now and
        the soundings the navigation held when the frame's ping was released."""
        model = self.navigation.build_bottom(sent.time, self.times, self.poses, sent.held)
        if model is not None:
            self._bottoms.append((sent.index, model))

    # -- the live window -------------------------------------------------------------
    def _solve_window(self, final: bool) -> None:
        """Place the frames still in the window where the anchor now puts them (frames
        move with its correction, never against each other); re-blend frames that moved;
        finalise frames leaving the window."""
        started = clock.perf_counter()
        window = self.window.start_solve()
        if window:
            self.stats.windows_solved += 1
            for k in window:
                self.poses[k] = self.chain.live_pose(k)
        self.stats.time("optimisation", started)
        started = clock.perf_counter()
        # Frames leaving the window become final.
        newest = self.window.newest
        held = self.chain.holding(self.times[newest]) if newest is not None and not final else None
        leaving = self.window.leaving(final, held, self.times)
        reblended = self.drawing.reblend(self.poses, set(leaving), self.frame)
        for k in reblended:
            self.stats.frames_reblended += 1
            self._emit_pose(k, final=False)
        for k in leaving:
            live = self.drawing.take_live(k)
            if live is not None:
                if self.params.resolve.enabled:
                    # Its image is kept to draw it again after a re-solve (the oldest kept
                    # go to make room: drawn at their pose now if they wait, settled).
                    for old in self.window.keep_drawn(live, self.chain.chained(k)):
                        self._count_redraw(self.drawing.let_go(old, live.time, self.frame))
                else:
                    self.drawing.settle(k, live.tiles)  # re-solves off: its tiles forget it
                self.chain.offer_keyframe(k, live.time, self.poses[k], live.image, live.grid)
            self._emit_pose(k, final=True)
            self.chain.finalise(k)
        self.stats.time("blending", started)

    # -- the live re-solve ---------------------------------------------------------------
    def _resolve(self, now: float) -> None:
        """Re-solve the drawn frames (``mapping.live_resolve``), queue those that moved to
        be drawn again (their poses and keyframes move now), and carry the chain on from
        the new map."""
        started = clock.perf_counter()
        resolution = self.window.resolve(now, self.poses)
        if resolution is None:
            return
        self.stats.resolves += 1
        for move in resolution.moves:
            k = move.index
            self.poses[k] = np.array(move.pose, float)
            self.drawing.queue_redraw(k, self.poses[k], now)
            self._emit_pose(k, final=True)
            self.chain.move_keyframe(k, move.pose, move.chain)
        self.chain.follow(resolution)
        self.stats.time("resolve", started)

    def _redraw(self, now: float, credit: float, everything: bool = False) -> None:
        """Draw again ``credit`` more of the frames re-solves moved, or all of them with
        ``everything`` (``LiveDrawing.redraw``)."""
        started = clock.perf_counter()
        done = self.drawing.redraw(now, credit, self.window.drawn, self.frame, everything)
        if done is None:
            return
        for redrawn in done.redrawn:
            self._count_redraw(redrawn)
        self._publish_all(done.rendered)
        self.stats.time("resolve", started)

    def _count_redraw(self, redrawn: Redraw | None) -> None:
        if redrawn is None:
            return
        stats = self.stats
        stats.redraw_wait_s += redrawn.wait_s
        stats.redraw_wait_max_s = max(stats.redraw_wait_max_s, redrawn.wait_s)
        stats.frames_redrawn += 1

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
        released = self._released
        now = released if released != math.inf else max(self.times, default=0.0)
        started = clock.perf_counter()
        rendered = self.drawing.render(now, force)
        if rendered is None:
            return
        self._publish_all(rendered)
        self.stats.time("render", started)

    def _publish_all(self, rendered: Iterable[RenderedTile]) -> None:
        for tile in rendered:
            self._publish(tile)
        self.stats.tile_spill_failures = self.tiles.spill_failures
        self.stats.tile_spill_error = self.tiles.spill_error

    def _publish(self, rendered: RenderedTile) -> None:
        if self.on_tile is None or self.frame is None:
            return
        image = rendered.image
        grid = self.tiles.grid
        west, north = grid.tile_west_north(image.key)
        self.on_tile(
            TileUpdate(
                image.key, image.values, image.version, self.frame.epsg, grid.res_m,
                grid.tile_px, west, north, rendered.frames,
            )
        )  # fmt: skip

    # -- survey end ------------------------------------------------------------------------
    def live_result(self) -> SurveyResult:
        """The live map as it stands (call ``flush`` first for the whole survey): each
        frame's live pose, the live tiles, the live registrations; what a survey without
        its survey-end pass (``[daemon] final_pass = false``) leaves. The filter's priors
        are not kept live (NaN)."""
        if self.frame is None:
            raise ValueError("no navigation fix: the live map has no frame to be placed in")
        poses = np.array(self.poses) if self.poses else np.zeros((0, 3))
        times = np.array(self.times, float)
        stages = {stage: float(seconds) for stage, seconds in self.stats.stage_s.items()}
        return SurveyResult(
            frame=self.frame,
            mode=self.params.final_mode,
            times=times,
            priors=np.full((times.size, 3), np.nan),
            poses=poses,
            mapped=np.all(np.isfinite(poses), axis=1),
            outcomes=list(self.outcomes),
            rejected=Counter(self.stats.rejected),
            timings=stages,
            mosaic=self.tiles,
            edges=list(self.edges),
            mount=self.mount,
        )

    def finish(
        self,
        pings: Callable[[], Iterable[Ping]],
        progress: Callable[[str, int, int], None] | None = None,
        spill: TileSpill | None = None,
        pool: TaskPool | None = None,
    ) -> SurveyResult:
        """The survey-end pass over every frame (``pings()`` yields them again, in
        order): the smoothed EKF, the registrations (again, or the live ones), loop
        closures, the final mode's optimisation, and every tile re-rendered; tile versions
        carry on growing."""
        self.flush()
        result = map_survey(
            pings,
            self.navigation.survey(),
            self.mount,
            self.params.pipeline,
            self.params.final_mode,
            progress,
            registrations=self.outcomes if self.params.reuse_registrations else None,
            spill=spill,
            pool=pool,
        )
        # Continue the live versions so a subscriber sees every final tile as newer.
        for key in result.mosaic.all_keys():
            result.mosaic.versions[key] = self.tiles.versions.get(key, 0)
        if self.on_tile is not None:
            for image in result.mosaic.rendered_tiles():
                bumped = TileImage(image.key, image.values, image.version + 1)
                result.mosaic.versions[image.key] = bumped.version
                self._publish(self.drawing.rendered(bumped))
        return result
