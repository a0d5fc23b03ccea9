"""The live MAVLink link against the autopilot emulator, over real loopback UDP and a pty:
the samples are the ones the log reader gets from the same simulated tlog, streams are
requested and acknowledged, the link survives the device going away, line noise and a
GPS outage."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from drivers.mavlink.link import MavlinkLink
from drivers.mavlink.navlog import NavLog, read_nav_log
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample
from tests.ports import free_udp_port
from tools.emulators.autopilot import AutopilotEmulator
from tools.emulators.relay import UdpRelay
from tools.sim import simulate

TIMEOUT_S = 10.0


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, NavLog]:
    summary = simulate("quadrats", 3, tmp_path_factory.mktemp("sim"), duration_s=4.0, n_beams=64)
    return summary.nav_path, read_nav_log(summary.nav_path)


async def until(condition: Callable[[], bool], timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met in time")
        await asyncio.sleep(0.02)


Body = Callable[[MavlinkLink, AutopilotEmulator, list[Any]], Awaitable[None]]


def run_udp(tlog: Path, body: Body, link_options: Any = None, **emulator: Any) -> None:
    """Link on udpin:127.0.0.1:<free>, emulator sending to it; ``body`` drives the test."""

    async def main() -> None:
        received: list[Any] = []
        port = free_udp_port()
        link = MavlinkLink(
            f"udpin:127.0.0.1:{port}", on_sample=received.append, **(link_options or {})
        )
        emu = AutopilotEmulator.from_tlog(tlog, **emulator)
        async with link, emu:
            await emu.start_udp(port)
            await body(link, emu, received)

    asyncio.run(asyncio.wait_for(main(), 2 * TIMEOUT_S))


def values(samples: list[Any]) -> list[Any]:
    return [dataclasses.replace(sample, time=0.0) for sample in samples]


def of(kind: type, samples: list[Any]) -> list[Any]:
    return [s for s in samples if isinstance(s, kind)]


def test_samples_equal_what_the_log_reader_gives(survey: tuple[Path, NavLog]):
    tlog, nav = survey

    got: list[Any] = []

    async def body(link: MavlinkLink, emu: AutopilotEmulator, received: list[Any]) -> None:
        await asyncio.wait_for(emu.done.wait(), TIMEOUT_S)
        await until(lambda: len(of(ImuSample, received)) >= len(nav.imu), 2.0)
        got.extend(received)

    run_udp(tlog, body, time_scale=4.0)
    # The link cannot see the whole log: "auto" takes the best heading seen so far, so a
    # GLOBAL_POSITION_INT heading may precede the first ATTITUDE; compare the log's choice.
    headings = [h for h in of(HeadingSample, got) if h.source == nav.heading[0].source]
    assert values(of(ImuSample, got)) == values(nav.imu)
    assert values(of(GnssFix, got)) == values(nav.gnss)
    assert values(headings) == values(nav.heading)
    assert values(of(AttitudeSample, got)) == values(nav.attitude)
    times = [s.time for s in got]
    assert times == sorted(times)


def test_heartbeat_and_message_intervals_reach_the_autopilot_and_are_acked(survey):
    tlog, _ = survey

    async def body(link: MavlinkLink, emu: AutopilotEmulator, got: list[Any]) -> None:
        await until(lambda: len(link.stats.requests) == 6 and emu.client.acks_sent == 6)
        await until(lambda: all(r.result == "accepted" for r in link.stats.requests.values()))
        assert (18, 8) in emu.client.heartbeats  # ONBOARD_CONTROLLER, AUTOPILOT_INVALID
        assert emu.client.intervals_us == {
            "RAW_IMU": 20_000,
            "GPS_RAW_INT": 200_000,
            "ATTITUDE": 100_000,
            "GLOBAL_POSITION_INT": 100_000,
            "VFR_HUD": 250_000,
            "DISTANCE_SENSOR": 100_000,  # a downward echosounder's soundings
        }
        assert emu.client.data_streams == []
        assert link.stats.autopilot == "ardupilot" and link.stats.autopilot_id == (1, 1)
        assert link.stats.link_up

    run_udp(tlog, body, time_scale=4.0)


def test_refused_intervals_fall_back_to_request_data_stream(survey):
    tlog, _ = survey

    async def body(link: MavlinkLink, emu: AutopilotEmulator, got: list[Any]) -> None:
        await until(lambda: len(emu.client.data_streams) == 6)
        assert all(r.result == "refused" and r.fallback for r in link.stats.requests.values())
        # (stream, Hz, start): RAW_SENSORS 50, EXTENDED_STATUS 5, POSITION 10, EXTRA1 10,
        # EXTRA2 4, EXTRA3 10 (ArduPilot's groups for RAW_IMU, GPS_RAW_INT,
        # GLOBAL_POSITION_INT, ..., DISTANCE_SENSOR).
        assert sorted(emu.client.data_streams) == [
            (1, 50, 1),
            (2, 5, 1),
            (6, 10, 1),
            (10, 10, 1),
            (11, 4, 1),
            (12, 10, 1),
        ]
        await until(lambda: len(got) >= 20)

    run_udp(tlog, body, accept_intervals=False, time_scale=4.0)


def test_serial_pty_recovers_when_the_device_goes_away_and_returns(survey):
    tlog, _ = survey

    async def main() -> None:
        got: list[Any] = []
        emu = AutopilotEmulator.from_tlog(tlog, time_scale=0.5, heartbeat_period_s=0.2)
        device = await emu.start_pty()
        link = MavlinkLink(
            str(device), on_sample=got.append, heartbeat_period_s=0.2, heartbeat_timeout_s=1.0
        )
        async with emu, link:
            await until(lambda: len(of(ImuSample, got)) >= 10)
            emu.stop()
            assert not device.exists()
            await until(lambda: not link.stats.link_up)
            before = len(got)
            emu.restart()
            await until(lambda: link.stats.reconnects == 1 and link.stats.link_up)
            await until(lambda: len(of(ImuSample, got[before:])) >= 10)
        assert link.stats.link_downs == 1
        assert link.stats.reopens >= 1
        assert link.stats.bad_packets == 0

    asyncio.run(asyncio.wait_for(main(), 2 * TIMEOUT_S))


def test_after_a_silence_samples_flow_before_the_next_heartbeat(survey):
    """The link cut (a UDP relay gone silent) long enough to be declared down: when it
    returns, the autopilot's streams are samples at once, not only from its next heartbeat
    (up to a heartbeat period later) on; the recording has those packets too."""
    tlog, _ = survey

    async def main() -> None:
        got: list[Any] = []
        port = free_udp_port()
        # Heartbeats every 2 s, the link down after 2.5 s without one: a 3 s cut starting
        # just after a heartbeat ends a second before the next one.
        link = MavlinkLink(f"udpin:127.0.0.1:{port}", on_sample=got.append, heartbeat_timeout_s=2.5)
        emu = AutopilotEmulator.from_tlog(tlog, time_scale=0.4, heartbeat_period_s=2.0)
        async with link, UdpRelay(port) as relay, emu:
            await emu.start_udp(relay.port)
            await until(lambda: link.stats.link_up)
            seen = link.stats.last_heartbeat
            await until(lambda: link.stats.last_heartbeat != seen)
            relay.cut(3.0)
            await until(lambda: not link.stats.link_up, 5.0)
            await until(lambda: not relay.is_cut, 5.0)
            returned = time.time()
            await until(lambda: link.stats.link_up, 5.0)
            back_up = link.stats.last_heartbeat
            assert back_up is not None
        assert link.stats.link_downs == 1
        assert back_up - returned > 0.5, "the cut ended well before the next heartbeat"
        before_heartbeat = [s for s in of(ImuSample, got) if returned <= s.time < back_up]
        # 55 Hz in the log, played at 0.4x: 22 a second; the old link gave none.
        assert len(before_heartbeat) >= 0.5 * 22 * (back_up - returned)

    asyncio.run(asyncio.wait_for(main(), 2 * TIMEOUT_S))


def test_garbage_is_counted_and_samples_after_it_arrive(survey):
    tlog, _ = survey

    async def body(link: MavlinkLink, emu: AutopilotEmulator, got: list[Any]) -> None:
        await until(lambda: len(got) >= 20)
        for _ in range(5):
            emu.inject_garbage(300)
        after = time.time()
        await until(lambda: link.stats.bad_bytes > 0)
        await until(lambda: len([s for s in of(ImuSample, got) if s.time > after]) >= 20)
        assert link.stats.link_up

    run_udp(tlog, body, time_scale=2.0)


def test_gps_pause_stops_gnss_but_not_imu(survey):
    tlog, _ = survey

    async def body(link: MavlinkLink, emu: AutopilotEmulator, got: list[Any]) -> None:
        await until(lambda: len(of(GnssFix, got)) >= 1)
        start, end = emu.pause_gps(1.0)
        await asyncio.wait_for(emu.done.wait(), TIMEOUT_S)
        gnss = [s.time for s in of(GnssFix, got)]
        imu_in_pause = [s for s in of(ImuSample, got) if start < s.time < end]
        assert not [t for t in gnss if start + 0.05 < t < end]
        assert any(t >= end for t in gnss)
        assert len(imu_in_pause) >= 50  # 55 Hz log time, replayed 2x faster, for 1 s

    run_udp(tlog, body, time_scale=2.0)


def test_mission_progress_is_kept_from_mission_current(survey):
    tlog, _ = survey

    async def body(link: MavlinkLink, emu: AutopilotEmulator, got: list[Any]) -> None:
        await until(lambda: link.stats.link_up)
        assert link.stats.mission is None
        emu._send(mavlink2.MAVLink_mission_current_message(3, 12, 3, 0))  # item 3 of 12, active
        await until(lambda: link.stats.mission is not None)
        assert link.stats.mission is not None
        assert link.stats.mission.to_dict() == {"current": 3, "total": 12, "state": "active"}

    run_udp(tlog, body, time_scale=2.0)
