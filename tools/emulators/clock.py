"""The emulators' shared clock: survey time played against wall time."""

from __future__ import annotations

import asyncio
import time


class PlaybackClock:
    """Survey time (UNIX s, the logs' clock) to wall time (``time.monotonic()`` s).

    Until ``start()`` sets the origin (survey time ``t0`` at wall time ``w0``) the clock is
    stopped; afterwards ``wall(t) = w0 + (t - t0) / speed``. speed: survey seconds played
    per wall second (1 = real time).
    """

    def __init__(self, speed: float = 1.0) -> None:
        if not speed > 0.0:
            raise ValueError(f"PlaybackClock: speed {speed} is not > 0")
        self.speed = speed
        self._origin: tuple[float, float] | None = None
        self._started = asyncio.Event()

    @property
    def origin(self) -> tuple[float, float] | None:
        """(survey time t0, wall time w0), None before ``start()``."""
        return self._origin

    @property
    def started(self) -> bool:
        return self._origin is not None

    def start(self, sim_t0: float, wall_t0: float | None = None) -> None:
        """Set the origin: survey time ``sim_t0`` plays at monotonic ``wall_t0`` (default
        now). A clock starts once; RuntimeError if it already has."""
        if self._origin is not None:
            raise RuntimeError("PlaybackClock already started")
        self._origin = (sim_t0, time.monotonic() if wall_t0 is None else wall_t0)
        self._started.set()

    def wall(self, sim_t: float) -> float:
        """The monotonic time (s) at which survey time ``sim_t`` plays."""
        if self._origin is None:
            raise RuntimeError("PlaybackClock not started")
        t0, w0 = self._origin
        return w0 + (sim_t - t0) / self.speed

    def sim(self, wall_t: float | None = None) -> float:
        """The survey time playing at monotonic time ``wall_t`` (default now)."""
        if self._origin is None:
            raise RuntimeError("PlaybackClock not started")
        t0, w0 = self._origin
        return t0 + ((time.monotonic() if wall_t is None else wall_t) - w0) * self.speed

    async def wait_started(self) -> None:
        """Return once ``start()`` has been called."""
        await self._started.wait()

    async def sleep_until(self, sim_t: float) -> None:
        """Wait for the clock to start, then until survey time ``sim_t`` plays (at once if
        it has passed)."""
        await self._started.wait()
        delay = self.wall(sim_t) - time.monotonic()
        if delay > 0.0:
            await asyncio.sleep(delay)
