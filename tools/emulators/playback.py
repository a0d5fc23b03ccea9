"""Play a recorded or simulated survey through the emulated sonar and autopilot, in step.

A client (the boat daemon) stamps every message on receipt, so for its map to be right each
ping must reach it at the same offset from the navigation messages as in the survey. Both
emulators therefore take one ``PlaybackClock``, which maps the survey's clock (UNIX s, the
log stamps) onto ``time.monotonic()``: the sonar sends ping ``p`` at ``clock.wall(p.time)``
and the autopilot a message stamped ``t`` at ``clock.wall(t)``.

``SurveyPlayback`` plays a ``sonar.oculus`` and a ``nav.tlog`` (e.g. from ``seamap
simulate``) on 127.0.0.1 this way; its clock starts at the survey's first stamp once the
client has fired the sonar and spoken to the autopilot, so nothing is lost at the start.

Command line (runs until the survey is played; one progress line a second)::

    python -m tools.emulators.playback --sonar S --nav N --sonar-port P --status-port Q \\
        --mavlink udp:PORT|pty [--start-after S] [--max-pings N] [--speed X]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from drivers.oculus.logfile import iter_pings
from tools.emulators.autopilot import AutopilotEmulator, read_autopilot_messages
from tools.emulators.clock import PlaybackClock
from tools.emulators.sonar import SonarEmulator

__all__ = ["NAV_TAIL_S", "PlaybackClock", "SurveyPlayback", "main"]

NAV_TAIL_S = 0.5
"""With ``max_pings`` cutting a survey short, navigation is played up to this long (s of
survey time) after the last ping played, as ``seamap simulate --max-pings`` cuts its logs."""


def _ping_times(path: Path, max_pings: int | None) -> list[float]:
    """Times (UNIX s) of the pings ``iter_pings`` gives, in file order: the first
    ``max_pings`` + 1 at most (the one after the cut says that there was a cut)."""
    pings = iter_pings(path)
    if max_pings is not None:
        pings = itertools.islice(pings, max_pings + 1)
    return [ping.time for ping in pings]


class SurveyPlayback:
    """A survey's sonar log and tlog played on 127.0.0.1 by a ``SonarEmulator`` and an
    ``AutopilotEmulator`` on one ``PlaybackClock`` (use ``async with`` or
    ``start()``/``close()``).

    sonar_log: a v1/v2 Oculus log, read lazily (one ping ahead). nav_log: a .tlog; the
    autopilot's messages are replayed (``AutopilotEmulator``). sonar_tcp_port: 0 picks a
    free port (read ``sonar.tcp_port``). status_to: where the sonar's status messages go,
    None for none. mavlink: "udp" (sends to 127.0.0.1:``mavlink_target_port``, where the
    client listens) or "pty" (the client opens ``autopilot.device_path``). start_after_s:
    seconds between the client being there (sonar fired and autopilot spoken to) and the
    clock's start. max_pings: play only the first pings, and the navigation up to
    ``NAV_TAIL_S`` after the last of them. speed: survey seconds per wall second.

    After ``start()``: ``sonar`` and ``autopilot`` (for fault injection), ``clock``,
    ``pings_total`` (pings to play), ``nav_total`` (autopilot messages to play). ``started``
    is set when the clock starts, ``done`` when both sources are exhausted.
    """

    def __init__(
        self,
        sonar_log: str | os.PathLike[str],
        nav_log: str | os.PathLike[str],
        *,
        sonar_tcp_port: int = 0,
        status_to: tuple[str, int] | None = None,
        mavlink: Literal["udp", "pty"] = "udp",
        mavlink_target_port: int | None = None,
        start_after_s: float = 0.0,
        max_pings: int | None = None,
        speed: float = 1.0,
    ) -> None:
        if mavlink not in ("udp", "pty"):
            raise ValueError(f"SurveyPlayback: mavlink {mavlink!r} is not 'udp' or 'pty'")
        if mavlink == "udp" and mavlink_target_port is None:
            raise ValueError("SurveyPlayback: mavlink 'udp' needs mavlink_target_port")
        if max_pings is not None and max_pings < 0:
            raise ValueError(f"SurveyPlayback: max_pings {max_pings} is negative")
        self.sonar_log = Path(sonar_log)
        self.nav_log = Path(nav_log)
        self.sonar_tcp_port = sonar_tcp_port
        self.status_to = status_to
        self.mavlink = mavlink
        self.mavlink_target_port = mavlink_target_port
        self.start_after_s = start_after_s
        self.max_pings = max_pings
        self.clock = PlaybackClock(speed)
        self.started = asyncio.Event()
        self.done = asyncio.Event()
        self.pings_total = 0
        self.nav_total = 0
        self._sonar: SonarEmulator | None = None
        self._autopilot: AutopilotEmulator | None = None
        self._task: asyncio.Task[None] | None = None

    @property
    def sonar(self) -> SonarEmulator:
        if self._sonar is None:
            raise RuntimeError("SurveyPlayback not started")
        return self._sonar

    @property
    def autopilot(self) -> AutopilotEmulator:
        if self._autopilot is None:
            raise RuntimeError("SurveyPlayback not started")
        return self._autopilot

    async def start(self) -> None:
        """Read what to play (in a worker thread: a sonar log can be large), start both
        emulators and the task that starts the clock and watches for the end."""
        times, messages = await asyncio.gather(
            asyncio.to_thread(_ping_times, self.sonar_log, self.max_pings),
            asyncio.to_thread(read_autopilot_messages, self.nav_log),
        )
        if self.max_pings is not None and len(times) > self.max_pings:
            del times[self.max_pings :]
            end = times[-1] + NAV_TAIL_S if times else -float("inf")
            messages = [(stamp, msg) for stamp, msg in messages if stamp <= end]
        if not times and not messages:
            raise ValueError(f"SurveyPlayback: nothing to play in {self.sonar_log}, {self.nav_log}")
        self.pings_total, self.nav_total = len(times), len(messages)
        first = min([*times[:1], *(stamp for stamp, _ in messages[:1])])
        pings = itertools.islice(iter_pings(self.sonar_log), self.pings_total)
        self._sonar = SonarEmulator(
            pings, tcp_port=self.sonar_tcp_port, status_to=self.status_to, clock=self.clock
        )
        self._autopilot = AutopilotEmulator(messages, wait_for_client=False, clock=self.clock)
        try:
            await self._sonar.start()
            if self.mavlink == "udp":
                assert self.mavlink_target_port is not None
                await self._autopilot.start_udp(self.mavlink_target_port)
            else:
                await self._autopilot.start_pty()
        except BaseException:
            await self.close()  # e.g. the sonar's port is taken: release what did start
            raise
        self._task = asyncio.create_task(self._run(first))

    async def _run(self, first: float) -> None:
        sonar, autopilot = self.sonar, self.autopilot
        await asyncio.gather(sonar.wait_fired(), autopilot.client_seen.wait())
        await asyncio.sleep(self.start_after_s)
        self.clock.start(first)
        self.started.set()
        await asyncio.gather(sonar.done.wait(), autopilot.done.wait())
        self.done.set()

    async def close(self) -> None:
        """Stop the playback and both emulators; safe to call twice."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._sonar is not None:
            await self._sonar.close()
        if self._autopilot is not None:
            await self._autopilot.close()

    async def __aenter__(self) -> SurveyPlayback:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m tools.emulators.playback",
        description="Play a survey's sonar.oculus and nav.tlog through an emulated Oculus "
        "sonar and Pixhawk on 127.0.0.1, in step.",
    )
    parser.add_argument("--sonar", type=Path, required=True, help="sonar log (.oculus)")
    parser.add_argument("--nav", type=Path, required=True, help="autopilot log (.tlog)")
    parser.add_argument("--sonar-port", type=int, default=52100, help="sonar TCP port")
    parser.add_argument(
        "--status-port", type=int, default=52102, help="UDP port the sonar status goes to"
    )
    parser.add_argument(
        "--mavlink",
        default="udp:14550",
        help="udp:PORT (send to 127.0.0.1:PORT, where the client listens) or pty",
    )
    parser.add_argument(
        "--start-after", type=float, default=0.0, help="s between the client and the start"
    )
    parser.add_argument("--max-pings", type=int, default=None, help="play only these pings")
    parser.add_argument("--speed", type=float, default=1.0, help="survey s per wall s")
    args = parser.parse_args(argv)
    kind, _, port = args.mavlink.partition(":")
    if not (args.mavlink == "pty" or (kind == "udp" and port.isdigit())):
        parser.error(f"--mavlink {args.mavlink!r}: expected udp:PORT or pty")
    args.mavlink_kind = kind
    args.mavlink_port = int(port) if port else None
    return args


async def _play(args: argparse.Namespace) -> None:
    playback = SurveyPlayback(
        args.sonar,
        args.nav,
        sonar_tcp_port=args.sonar_port,
        status_to=("127.0.0.1", args.status_port),
        mavlink=args.mavlink_kind,
        mavlink_target_port=args.mavlink_port,
        start_after_s=args.start_after,
        max_pings=args.max_pings,
        speed=args.speed,
    )
    async with playback:
        sonar, autopilot = playback.sonar, playback.autopilot
        target: Any = autopilot.device_path or f"udp 127.0.0.1:{args.mavlink_port}"
        print(
            f"sonar tcp 127.0.0.1:{sonar.tcp_port}, status to udp 127.0.0.1:{args.status_port}; "
            f"autopilot on {target}; {playback.pings_total} pings, {playback.nav_total} nav "
            "messages; waiting for the client (sonar fired, autopilot spoken to)",
            flush=True,
        )
        began = time.monotonic()
        while not playback.done.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(playback.done.wait(), 1.0)
            state = "waiting"
            if playback.done.is_set():
                state = "done"
            elif playback.started.is_set():
                state = "playing"
            print(
                f"{time.monotonic() - began:7.1f} s {state}: pings {sonar.pings_sent}"
                f"/{playback.pings_total} (missed {sonar.pings_missed}), "
                f"nav {autopilot.replayed}/{playback.nav_total}",
                flush=True,
            )


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry (see the module docstring); returns the exit status."""
    args = _parse_args(argv)
    try:
        asyncio.run(_play(args))
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
