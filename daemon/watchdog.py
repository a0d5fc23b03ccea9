"""systemd's watchdog (``Watchdog``): petted while the daemon does its work on time.

What the watchdog vouches for is that the recorder is flushed on time and the mapping
thread runs (the event loop itself runs, or the watchdog task would not). The recorder's
flush timer lives here for that reason: it is the first thing the watchdog checks, and a
recorder not flushed for five seconds withholds the watchdog, so that systemd restarts a
daemon that stopped recording.
"""

from __future__ import annotations

import asyncio
import logging
import time

from daemon.health import LiveParts
from daemon.notify import Notifier

# The daemon's lines keep the logger they always had ("service:" in the journal).
log = logging.getLogger("daemon.service")

RECORDER_POLL_S = 0.25
"""Seconds between recorder flushes: a pause in the data is still on disk within a second."""
RECORDER_LATE_S = 5.0
"""A recorder not flushed for this long counts as stalled."""


class Watchdog:
    """The recorder's flush timer and systemd's watchdog (see the module docstring);
    ``recording_task`` and ``task`` run under the daemon's supervisor."""

    def __init__(self, parts: LiveParts, notifier: Notifier) -> None:
        self.parts = parts
        self.notifier = notifier
        self._last_recorder_poll = time.monotonic()

    async def recording_task(self) -> None:
        """Flush the open survey's recorder every ``RECORDER_POLL_S``."""
        while True:
            self._last_recorder_poll = time.monotonic()
            recorder = self.parts.recorder
            if recorder is not None:
                recorder.poll()
            await asyncio.sleep(RECORDER_POLL_S)

    def alive(self) -> bool:
        """What the systemd watchdog vouches for: the recorder is flushed on time and the
        mapping thread runs (the loop itself runs, or this is not called)."""
        if time.monotonic() - self._last_recorder_poll > RECORDER_LATE_S:
            return False
        mapper = self.parts.mapper
        return mapper is None or mapper.alive

    async def task(self) -> None:
        """Pet the watchdog at half its interval while ``alive``; without a watchdog
        (not under systemd, or none asked for), wait for good."""
        interval = self.notifier.watchdog_interval_s
        if interval is None:
            await asyncio.Event().wait()
            return
        while True:
            if self.alive():
                self.notifier.watchdog()
            else:
                log.error("watchdog withheld: recorder or mapping stalled")
            await asyncio.sleep(interval / 2)
