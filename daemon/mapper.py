"""The streaming engine on its own thread: the one bridge between mapping and asyncio.

``submit`` (called on the event loop) hands a sample over and never blocks: navigation
samples always queue (they are small and the EKF needs every one); a sonar frame queues
only while fewer than ``max_backlog_frames`` wait, otherwise it is skipped and counted —
it stays recorded, and the survey-end pass maps it. The worker thread feeds the engine in
arrival order; the engine's pose and tile updates come back to the event loop through
``loop.call_soon_threadsafe``. An exception inside the engine is logged, the live map is
started afresh with a new engine (the recording is untouched) and the restart counted.

``on_final`` (optional) is called on the worker thread, once a frame, when the frame's
live pose first becomes final: its engine's local frame, its time and the vehicle's pose
there (the daemon's live coverage counts it). It must be quick and never raise into the
engine (it is guarded: an exception is logged once and the hook dropped).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from mapping.geo import LocalFrame
from mapping.samples import Ping
from mapping.streaming import PoseUpdate, Sample, StreamingEngine, StreamStats, TileUpdate

log = logging.getLogger(__name__)

U = TypeVar("U")
FinalHook = Callable[[LocalFrame, float, npt.NDArray[np.float64]], None]

IDLE_POLL_S = 0.05
"""With no sample coming, the thread lets the engine take its front's finished frames this
often (a front in a worker process finishes them while the thread waits)."""
MAX_QUEUED_SAMPLES = 200_000
"""A hard bound on everything queued (about a minute of navigation at full rates while the
engine is stuck); beyond it samples are dropped and counted."""


@dataclass
class MapperStats:
    """The worker's counters, read by the health task (plain ints: no lock needed)."""

    frames_submitted: int = 0
    frames_skipped: int = 0
    """Frames not given to the live engine because the backlog was full."""
    samples_dropped: int = 0
    restarts: int = 0
    """Times the engine failed and the live map started again."""
    last_error: str | None = None


class MappingWorker:
    """Feeds a ``StreamingEngine`` from a queue on a daemon thread (see the module doc)."""

    def __init__(
        self,
        engine_factory: Callable[[], StreamingEngine],
        *,
        loop: asyncio.AbstractEventLoop,
        max_backlog_frames: int,
        on_pose: Callable[[PoseUpdate], None] | None = None,
        on_tile: Callable[[TileUpdate], None] | None = None,
        segment: int = 0,
        name: str = "mapping",
        on_final: FinalHook | None = None,
    ) -> None:
        self._factory = engine_factory
        self._loop = loop
        self.max_backlog_frames = max_backlog_frames
        self.segment = segment
        """The recording segment this live map belongs to."""
        self.on_pose = on_pose
        self.on_tile = on_tile
        self.on_final = on_final
        self._finals_upto = -1
        """The newest frame index given to ``on_final`` (of the current engine)."""
        self.stats = MapperStats()
        self._queue: collections.deque[Sample | None] = collections.deque()
        self._wake = threading.Condition()
        self._pending_frames: collections.deque[float] = collections.deque()
        self._lock = threading.Lock()
        self._engine = self._new_engine()
        self._engine_stats: StreamStats = self._engine.stats
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    # --- event loop side -------------------------------------------------------------------

    def submit(self, sample: Sample) -> bool:
        """Queue one sample (event loop thread); False when it was skipped or dropped."""
        if self._stopped:
            return False
        if len(self._queue) >= MAX_QUEUED_SAMPLES:
            self.stats.samples_dropped += 1
            return False
        if isinstance(sample, Ping):
            self.stats.frames_submitted += 1
            with self._lock:
                if len(self._pending_frames) >= self.max_backlog_frames:
                    self.stats.frames_skipped += 1
                    return False
                self._pending_frames.append(sample.time)
        with self._wake:
            self._queue.append(sample)
            self._wake.notify()
        return True

    @property
    def backlog_frames(self) -> int:
        """Frames waiting to be mapped (queued or held by the engine to be put in order)."""
        return len(self._pending_frames)

    def lag_s(self, now: float | None = None) -> float:
        """Age (s) of the oldest frame received but not yet mapped; 0 when none waits."""
        with self._lock:
            oldest = self._pending_frames[0] if self._pending_frames else None
        if oldest is None:
            return 0.0
        return max(0.0, (time.time() if now is None else now) - oldest)

    @property
    def engine_stats(self) -> StreamStats:
        return self._engine_stats

    @property
    def engine(self) -> StreamingEngine:
        """The live engine (read it only after ``finish``: it belongs to the thread)."""
        return self._engine

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    async def finish(self) -> StreamStats:
        """Process what is queued, flush the engine (every pose final, every tile rendered)
        and stop the thread; the engine's statistics."""
        with self._wake:
            self._queue.append(None)
            self._stopped = True
            self._wake.notify()
        await asyncio.to_thread(self._thread.join)
        return self._engine_stats

    # --- worker thread ---------------------------------------------------------------------

    def _new_engine(self) -> StreamingEngine:
        engine = self._factory()
        engine.on_pose = self._pose
        engine.on_tile = self._tile
        return engine

    def _pose(self, update: PoseUpdate) -> None:
        if update.final and update.frame > self._finals_upto and self.on_final is not None:
            self._finals_upto = update.frame  # first final: frames turn final in order
            engine = self._engine
            if engine.frame is not None:
                try:
                    self.on_final(
                        engine.frame, engine.times[update.frame], engine.poses[update.frame]
                    )
                except Exception:
                    log.exception("live coverage failed; it stops for this survey")
                    self.on_final = None
        if self.on_pose is not None:
            self._call_soon(self.on_pose, update)

    def _tile(self, update: TileUpdate) -> None:
        if self.on_tile is not None:
            self._call_soon(self.on_tile, update)

    def _call_soon(self, callback: Callable[[U], None], update: U) -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed while the thread finished
            self._loop.call_soon_threadsafe(callback, update)

    def _run(self) -> None:
        while True:
            idle = False
            sample: Sample | None = None
            with self._wake:
                if not self._queue:
                    self._wake.wait(IDLE_POLL_S)
                if self._queue:
                    sample = self._queue.popleft()
                else:
                    idle = True
            try:
                if idle:
                    # Nothing came: the stages after the front take what it has finished
                    # (a worker's results), so the map does not wait for the next sample.
                    self._engine.take_ready()
                elif sample is None:
                    self._engine.flush()
                else:
                    self._engine.add(sample)
            except Exception as exc:
                self._failed(exc)
            if not idle and sample is None:
                self._engine.close()
                self._processed(math.inf)
                return
            self._processed(self._engine.processed_upto)

    def _processed(self, upto: float) -> None:
        with self._lock:
            while self._pending_frames and self._pending_frames[0] <= upto:
                self._pending_frames.popleft()

    def _failed(self, exc: Exception) -> None:
        self.stats.restarts += 1
        self.stats.last_error = f"{type(exc).__name__}: {exc}"
        log.error(
            "mapping engine failed; the live map starts again, the recording is intact",
            extra={"fields": {"reason": self.stats.last_error}},
        )
        log.debug("engine failure", exc_info=True)
        with contextlib.suppress(Exception):
            self._engine.close()
        self._engine = self._new_engine()
        self._engine_stats = self._engine.stats
        self._finals_upto = -1  # the new engine numbers its frames from 0
