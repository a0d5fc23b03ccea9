"""Supervised asyncio tasks: a task that fails is logged in one line and started again.

Each concern of the daemon (sonar, MAVLink, recording, health, control...) is a coroutine
function run by ``Supervisor.spawn``. If it raises, or returns while it should run
forever, the failure is logged with its reason, counted, and the coroutine started again
after a backoff (1 s doubling to 30 s, back to 1 s once it has run a minute); the other
tasks never notice. Cancellation (shutdown) is the only way out.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable

log = logging.getLogger(__name__)

BACKOFF_INITIAL_S = 1.0
BACKOFF_MAX_S = 30.0
STABLE_S = 60.0


class Supervisor:
    def __init__(self) -> None:
        self.restarts: dict[str, int] = {}
        self._tasks: dict[str, asyncio.Task[None]] = {}

    def spawn(self, name: str, run: Callable[[], Awaitable[None]]) -> None:
        """Run ``run()`` under supervision as task ``name``."""
        self.restarts.setdefault(name, 0)
        self._tasks[name] = asyncio.create_task(self._supervise(name, run), name=name)

    async def _supervise(self, name: str, run: Callable[[], Awaitable[None]]) -> None:
        backoff = BACKOFF_INITIAL_S
        while True:
            started = time.monotonic()
            try:
                await run()
                reason = "returned"
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                reason = f"{type(exc).__name__}: {exc}"
                log.debug("task %s failed", name, exc_info=True)
            if time.monotonic() - started >= STABLE_S:
                backoff = BACKOFF_INITIAL_S
            self.restarts[name] += 1
            log.error(
                "task failed, restarting",
                extra={"fields": {"task": name, "reason": reason, "in_s": backoff}},
            )
            await asyncio.sleep(backoff)
            backoff = min(2 * backoff, BACKOFF_MAX_S)

    async def cancel(self, *names: str) -> None:
        """Stop the named tasks for good (they are not restarted)."""
        tasks = [self._tasks.pop(name) for name in names if name in self._tasks]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

    async def stop(self) -> None:
        """Cancel every task and wait for them to end."""
        for task in self._tasks.values():
            task.cancel()
        for task in self._tasks.values():
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._tasks.clear()
