"""systemd's watchdog (``daemon.watchdog.Watchdog``) over a real datagram socket: petted
while the recorder is flushed on time and the mapping thread runs, withheld (said in a
line) when either stalls; and the recorder's flush timer."""

from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import pytest

from daemon.health import LiveParts
from daemon.notify import Notifier
from daemon.watchdog import RECORDER_LATE_S, Watchdog


class FakeRecorder:
    def __init__(self) -> None:
        self.polls = 0

    def poll(self) -> None:
        self.polls += 1


class FakeMapper:
    def __init__(self, alive: bool) -> None:
        self.alive = alive


@pytest.fixture
def manager(tmp_path: Path) -> Iterator[socket.socket]:
    """systemd's end of $NOTIFY_SOCKET."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    sock.settimeout(10.0)
    yield sock
    sock.close()


def notifier(manager: socket.socket) -> Notifier:
    """A notifier whose watchdog wants a pet every 0.1 s (a 0.2 s timeout)."""
    return Notifier({"NOTIFY_SOCKET": manager.getsockname(), "WATCHDOG_USEC": "200000"})


def test_the_recorder_is_flushed_and_the_watchdog_petted(manager: socket.socket) -> None:
    parts = LiveParts()
    recorder = FakeRecorder()
    parts.recorder = cast(Any, recorder)
    parts.mapper = cast(Any, FakeMapper(alive=True))
    watchdog = Watchdog(parts, notifier(manager))

    async def main() -> list[bytes]:
        tasks = [
            asyncio.create_task(watchdog.recording_task()),
            asyncio.create_task(watchdog.task()),
        ]
        try:
            pets = [await asyncio.to_thread(manager.recv, 4096) for _ in range(2)]
            for _ in range(1000):
                if recorder.polls >= 2:
                    break
                await asyncio.sleep(0.01)
            return pets
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    assert asyncio.run(main()) == [b"WATCHDOG=1", b"WATCHDOG=1"]
    assert recorder.polls >= 2


def test_a_stalled_mapping_thread_withholds_the_watchdog(
    manager: socket.socket, caplog: pytest.LogCaptureFixture
) -> None:
    parts = LiveParts()
    parts.mapper = cast(Any, FakeMapper(alive=False))
    watchdog = Watchdog(parts, notifier(manager))
    assert not watchdog.alive()

    async def main() -> None:
        task = asyncio.create_task(watchdog.task())
        try:
            for _ in range(1000):
                if any(r.getMessage().startswith("watchdog withheld") for r in caplog.records):
                    break
                await asyncio.sleep(0.01)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    with caplog.at_level(logging.ERROR, logger="daemon.service"):
        asyncio.run(main())
    withheld = [r for r in caplog.records if r.name == "daemon.service"]
    assert withheld and withheld[0].getMessage() == (
        "watchdog withheld: recorder or mapping stalled"
    )
    manager.setblocking(False)
    with pytest.raises(BlockingIOError):  # not one pet
        manager.recv(4096)


def test_a_recorder_not_flushed_on_time_is_a_stall() -> None:
    parts = LiveParts()
    watchdog = Watchdog(parts, Notifier({}))
    assert watchdog.alive()  # no survey: nothing to stall
    watchdog._last_recorder_poll -= RECORDER_LATE_S + 1.0
    assert not watchdog.alive()


def test_without_systemd_the_watchdog_task_waits() -> None:
    watchdog = Watchdog(LiveParts(), Notifier({}))

    async def main() -> bool:
        task = asyncio.create_task(watchdog.task())
        await asyncio.sleep(0)
        waiting = not task.done()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return waiting

    assert asyncio.run(main())
