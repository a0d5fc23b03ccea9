"""A simulated survey played through the emulated sonar and autopilot on one clock, received
by the real links over loopback: every ping arrives, and each reaches the client at the
same offset from the GPS messages as in the simulation."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from drivers.mavlink.link import MavlinkLink
from drivers.oculus.link import LinkTiming, OculusLink
from drivers.oculus.logfile import iter_pings
from mapping.samples import Ping
from tests.ports import free_udp_port
from tools.emulators.autopilot import read_autopilot_messages
from tools.emulators.clock import PlaybackClock
from tools.emulators.playback import SurveyPlayback, main
from tools.sim import simulate

DEADLINE_S = 40.0
IN_STEP_S = 0.030
"""Allowed error of a ping's receipt offset from its nearest GPS_RAW_INT."""
IN_STEP_OUTLIERS = 2
"""How many pings may miss IN_STEP_S: a hold-up of the kernel or of a thread the stall
watcher does not see (CI once measured one ping 99 ms off on a loaded 2-core machine)."""
OUT_OF_STEP_S = 0.25
"""No ping may be this far off: half the 0.5 s ping period, where a ping held back or sent
early would be stamped in its neighbour's slot."""
SPACING_S = 0.005
"""Allowed mean error of the receipt spacing of consecutive pings."""
STALL_S = 0.008
"""A hold-up of the test's process longer than this (descheduled on a loaded machine, or
busy) is a stall: what arrives right after one is late for want of CPU, not because of
the playback, and is left out of the timing checks."""
WATCH_PERIOD_S = 0.004
LINK_TIMING = LinkTiming(idle_flush_s=0.005)
"""OculusLink's framer holds back a ping whose last byte is 0x53 (it could start the next
header) until more bytes come or the link has been idle for ``idle_flush_s``, and stamps it
then: with the default 0.2 s, such a ping (about 2 in 60 here) is stamped one ping period
late. A short flush keeps that below the tolerance."""


@dataclass(frozen=True)
class Survey:
    sonar: Path
    nav: Path
    ping_time: dict[int, float]
    """Simulated ping time (UNIX s) by ping id, in log order."""
    gps_time: dict[int, float]
    """Simulated GPS_RAW_INT stamp (UNIX s) by its time_usec field."""


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Survey:
    summary = simulate("quadrats", 4, tmp_path_factory.mktemp("sim"), max_pings=60, n_beams=64)
    ping_time = {p.ping_id: p.time for p in iter_pings(summary.sonar_path)}
    gps_time = {
        msg.time_usec: stamp
        for stamp, msg in read_autopilot_messages(summary.nav_path)
        if msg.get_type() == "GPS_RAW_INT"
    }
    assert len(ping_time) == 60 and len(gps_time) >= 10
    return Survey(summary.sonar_path, summary.nav_path, ping_time, gps_time)


async def until(condition: Callable[[], bool], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met in time")
        await asyncio.sleep(0.01)


@dataclass
class Received:
    """What the clients got, stamped on receipt (UNIX s), and the playback's counters."""

    pings: list[Ping] = field(default_factory=list)
    gps: dict[int, float] = field(default_factory=dict)
    """Receipt time by GPS_RAW_INT time_usec."""
    pings_sent: int = 0
    pings_missed: int = 0
    pings_total: int = 0
    sonar_reconnects: int = 0
    stalls: list[tuple[float, float]] = field(default_factory=list)
    """(start, end) UNIX s of the times the process was held up longer than STALL_S."""

    def after_stall(self, t: float) -> bool:
        """Whether receipt time ``t`` falls in a stall or just after it."""
        return any(start <= t <= end + STALL_S for start, end in self.stalls)


During = Callable[[SurveyPlayback, Received], Awaitable[None]]


def play(
    survey: Survey,
    *,
    mavlink: str = "udp",
    speed: float = 1.0,
    timing: LinkTiming = LINK_TIMING,
    during: During | None = None,
    hear_status: bool = True,
) -> Received:
    """Play ``survey`` to a real OculusLink and MavlinkLink until done; ``during`` runs
    alongside (fault injection). Fails if tasks are left running."""
    got = Received()
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True

    def on_packet(packet: bytes, t: float) -> None:
        for msg in parser.parse_buffer(packet) or []:
            if msg.get_type() == "GPS_RAW_INT":
                got.gps[msg.time_usec] = t

    async def watch_stalls() -> None:
        while True:
            before = time.time()
            await asyncio.sleep(WATCH_PERIOD_S)
            after = time.time()
            if after - before > WATCH_PERIOD_S + STALL_S:
                got.stalls.append((before, after))

    async def consume(link: OculusLink) -> None:
        async with contextlib.aclosing(link.pings()) as pings:
            async for ping in pings:
                got.pings.append(ping)

    async def main() -> None:
        status_port, mav_port = free_udp_port(), free_udp_port()
        playback = SurveyPlayback(
            survey.sonar,
            survey.nav,
            status_to=("127.0.0.1", status_port),
            mavlink="pty" if mavlink == "pty" else "udp",
            mavlink_target_port=mav_port,
            speed=speed,
        )
        async with contextlib.AsyncExitStack() as stack:
            # The client listens before the UDP playback starts; a pty exists once started.
            url = f"udpin:127.0.0.1:{mav_port}"
            if mavlink == "pty":
                await stack.enter_async_context(playback)
                url = str(playback.autopilot.device_path)
            link = MavlinkLink(url, on_packet=on_packet, heartbeat_period_s=0.2)
            nav = await stack.enter_async_context(link)
            if mavlink != "pty":
                await stack.enter_async_context(playback)
            sonar = OculusLink(
                "127.0.0.1",
                tcp_port=playback.sonar.tcp_port,
                # Deaf to the status: a reconnect then waits out its whole backoff.
                status_port=status_port if hear_status else free_udp_port(),
                timing=timing,
            )
            consumer = asyncio.create_task(consume(sonar))
            watcher = asyncio.create_task(watch_stalls())
            extra = asyncio.ensure_future(during(playback, got)) if during else None
            try:
                await playback.done.wait()
                await until(lambda: len(got.pings) >= playback.sonar.pings_sent, 2.0)
                if extra is not None:
                    await extra
            finally:
                for task in (consumer, watcher, extra):
                    if task is not None:
                        task.cancel()
                        with contextlib.suppress(asyncio.CancelledError):
                            await task
            got.pings_sent = playback.sonar.pings_sent
            got.pings_missed = playback.sonar.pings_missed
            got.pings_total = playback.pings_total
            got.sonar_reconnects = sonar.stats.reconnects
            assert nav.stats.bad_packets == 0

    async def bounded() -> None:
        await asyncio.wait_for(main(), DEADLINE_S)
        await asyncio.sleep(0)
        leftover = asyncio.all_tasks() - {asyncio.current_task()}
        assert not leftover, f"tasks left running: {leftover}"

    asyncio.run(bounded())
    return got


def assert_in_step(errors: np.ndarray) -> None:
    """Every ping within OUT_OF_STEP_S of its place, all but IN_STEP_OUTLIERS within
    IN_STEP_S."""
    off = np.abs(errors)
    assert off.max() < OUT_OF_STEP_S, errors
    assert np.count_nonzero(off >= IN_STEP_S) <= IN_STEP_OUTLIERS, errors


def in_step_errors(survey: Survey, got: Received, speed: float = 1.0) -> np.ndarray:
    """Per received ping: (its receipt - the receipt of the GPS_RAW_INT nearest in sim
    time) - (the same difference in the simulation, at the playback speed), s; for the
    pings that neither they nor that GPS_RAW_INT arrived after a stall. Checks that most
    pings are left to judge."""
    usec = np.array(sorted(got.gps), dtype=np.int64)
    gps_sim = np.array([survey.gps_time[u] for u in usec])
    gps_got = np.array([got.gps[u] for u in usec])
    errors = []
    for ping in got.pings:
        sim = survey.ping_time[ping.ping_id]
        k = int(np.argmin(np.abs(gps_sim - sim)))
        if not (got.after_stall(ping.time) or got.after_stall(gps_got[k])):
            errors.append((ping.time - gps_got[k]) - (sim - gps_sim[k]) / speed)
    assert len(errors) > 0.5 * len(got.pings), f"too many stalls to judge: {got.stalls}"
    return np.array(errors)


def spacing_error(survey: Survey, got: Received, speed: float = 1.0) -> float:
    """Mean |receipt spacing - simulated spacing / speed| of consecutive received pings
    (neither received after a stall), s."""
    errors = [
        abs((b.time - a.time) - (survey.ping_time[b.ping_id] - survey.ping_time[a.ping_id]) / speed)
        for a, b in itertools.pairwise(got.pings)
        if not (got.after_stall(a.time) or got.after_stall(b.time))
    ]
    assert len(errors) > 0.5 * (len(got.pings) - 1), f"too many stalls to judge: {got.stalls}"
    return float(np.mean(errors))


def test_clock_maps_survey_time_to_wall_time() -> None:
    clock = PlaybackClock(speed=2.0)
    assert not clock.started and clock.origin is None
    with pytest.raises(RuntimeError):
        clock.wall(0.0)
    clock.start(1000.0, wall_t0=50.0)
    assert clock.origin == (1000.0, 50.0)
    assert clock.wall(1004.0) == 52.0 and clock.sim(52.0) == 1004.0
    with pytest.raises(RuntimeError):
        clock.start(0.0)
    with pytest.raises(ValueError):
        PlaybackClock(speed=0.0)

    async def sleeps() -> float:
        live = PlaybackClock()
        waiter = asyncio.create_task(live.sleep_until(5.0))
        await asyncio.sleep(0.05)
        assert not waiter.done()  # not started: waits
        live.start(4.9)
        await waiter
        return time.monotonic() - live.wall(5.0)

    late = asyncio.run(sleeps())
    assert -1e-3 < late < 0.5  # not early; late only by what the machine's load makes it


def test_every_ping_arrives_in_step_with_the_navigation(survey: Survey) -> None:
    got = play(survey)
    assert [p.ping_id for p in got.pings] == list(survey.ping_time)
    assert got.pings_sent == got.pings_total == 60 and got.pings_missed == 0
    assert set(got.gps) == set(survey.gps_time), "every GPS_RAW_INT arrived"
    assert_in_step(in_step_errors(survey, got))
    assert spacing_error(survey, got) < SPACING_S


def test_pings_while_the_sonar_is_disconnected_are_missed_not_queued(survey: Survey) -> None:
    async def drop_once(playback: SurveyPlayback, got: Received) -> None:
        await until(lambda: len(got.pings) >= 20, DEADLINE_S)
        await asyncio.sleep(0.03)  # between two pings: none is half sent
        playback.sonar.drop_connection()

    # The link waits 1 s before reconnecting (deaf to the status, which would bring it
    # back at once): ~1 s without a client.
    timing = dataclasses.replace(LINK_TIMING, backoff_initial_s=1.0, backoff_max_s=1.0)
    got = play(survey, timing=timing, during=drop_once, hear_status=False)
    ids = [p.ping_id for p in got.pings]
    missing = [k for k in survey.ping_time if k not in set(ids)]
    assert got.sonar_reconnects == 1
    assert ids == sorted(ids) and ids[:20] == list(survey.ping_time)[:20]
    assert got.pings_missed == len(missing) >= 5
    assert got.pings_sent == len(ids) == got.pings_total - got.pings_missed
    order = list(survey.ping_time)
    first = order.index(missing[0])
    assert missing == order[first : first + len(missing)], "one gap, while disconnected"
    assert_in_step(in_step_errors(survey, got))


def test_pty_playback_at_double_speed(survey: Survey) -> None:
    got = play(survey, mavlink="pty", speed=2.0)
    assert [p.ping_id for p in got.pings] == list(survey.ping_time)
    assert set(got.gps) == set(survey.gps_time)
    assert_in_step(in_step_errors(survey, got, speed=2.0))
    assert spacing_error(survey, got, speed=2.0) < SPACING_S


def test_playback_cut_at_max_pings_keeps_the_navigation_until_just_after(survey: Survey) -> None:
    async def main() -> tuple[int, int, float]:
        playback = SurveyPlayback(
            survey.sonar, survey.nav, mavlink_target_port=free_udp_port(), max_pings=10
        )
        async with playback:
            stamps = [stamp for stamp, _ in playback.autopilot.messages]
            return playback.pings_total, playback.nav_total, max(stamps)

    total, nav_total, last_nav = asyncio.run(main())
    last_ping = list(survey.ping_time.values())[9]
    assert total == 10 and nav_total > 0
    assert last_ping < last_nav <= last_ping + 0.5


def test_command_line_refuses_a_bad_mavlink_target(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--sonar", "s.oculus", "--nav", "n.tlog", "--mavlink", "udp:port"])
    assert exit_.value.code == 2
    assert "expected udp:PORT or pty" in capsys.readouterr().err
