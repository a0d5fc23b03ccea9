"""The survey recorder (daemon/recording.py): segments, read-back, power cut, full disk."""

from __future__ import annotations

import asyncio
import errno
import math
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import all as mavlink

from daemon.recording import SurveyRecorder, TlogWriter, segments
from drivers.mavlink import read_nav_log, summarize_nav_log
from drivers.mavlink.framing import ScanTally, open_log, scan_tlog
from drivers.mavlink.link import MavlinkLink
from drivers.oculus.logfile import LogReadReport, OculusLogWriter, iter_log_items, iter_pings
from drivers.oculus.ping import build_simple_ping
from mapping.samples import Ping, RangeSample
from tests.drivers import mavlink_fixtures as fx
from tests.ports import free_udp_port
from tools.emulators.autopilot import AutopilotEmulator

T0 = 1_718_000_000.0
MB = 1024 * 1024


class FakeClock:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def ping_message(k: int) -> tuple[bytes, float]:
    """A small SimplePingResult v2 (8 ranges x 4 beams) and its receive time."""
    rng = np.random.default_rng(k)
    ping = Ping(
        time=T0 + 0.1 * k,
        ping_id=1000 + k,
        master_mode=2,
        frequency_hz=1.2e6,
        range_resolution_m=0.01,
        bearings_rad=np.radians(np.array([-30.0, -10.0, 10.0, 30.0])),
        image=rng.integers(1, 255, size=(8, 4), dtype=np.uint8),
        speed_of_sound_mps=1500.0,
    )
    return build_simple_ping(ping), ping.time


_SENDER = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def mavlink_packet(k: int) -> tuple[bytes, float]:
    """A HEARTBEAT (even k) or GPS_RAW_INT (odd k) as bytes on the wire, and its time."""
    if k % 2 == 0:
        msg: Any = mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_SURFACE_BOAT, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0, 3
        )
    else:
        msg = mavlink.MAVLink_gps_raw_int_message(
            int((T0 + k) * 1e6), 3, 434_000_000 + k, -17_000_000 - k, 1000, 80, 90, 150, 0, 12
        )
    return bytes(msg.pack(_SENDER)), T0 + 0.05 * k


def read_tlog(path: Path) -> list[tuple[float, bytes]]:
    """(time, packet bytes) of every record of a .tlog as it is on disk."""
    with open_log(path) as (_, buf):
        return [(t, bytes(msg.get_msgbuf())) for t, msg in scan_tlog(buf, ScanTally())]


def read_sonar(path: Path) -> list[tuple[float, bytes]]:
    return [(item.time, item.message) for item in iter_log_items(path)]


def assert_tlog(got: list[tuple[float, bytes]], want: list[tuple[bytes, float]]) -> None:
    assert [p for _, p in got] == [p for p, _ in want]
    for (t_got, _), (_, t_want) in zip(got, want, strict=True):
        assert math.isclose(t_got, t_want, abs_tol=1e-6)


def test_segment_reads_back_every_item_and_time(tmp_path: Path) -> None:
    survey = tmp_path / "surveys" / "s1"
    pings = [ping_message(k) for k in range(5)]
    packets = [mavlink_packet(k) for k in range(10)]
    with SurveyRecorder(survey, min_free_bytes=0) as rec:
        for message, t in pings:
            assert rec.record_sonar(message, t)
        for packet, t in packets:
            assert rec.record_mavlink(packet, t)
    assert rec.stats.segment == 1 and rec.stats.segments == 1
    assert rec.stats.sonar.items == 5 and rec.stats.nav.items == 10
    assert rec.stats.nav.bytes == sum(len(p) + 8 for p, _ in packets)
    assert rec.stats.errors == 0 and not rec.stats.full and rec.stats.fsyncs >= 1

    sonar, nav = segments(survey)
    assert [p.name for p in sonar] == ["sonar-001.oculus"]
    assert [p.name for p in nav] == ["nav-001.tlog"]
    assert read_sonar(sonar[0]) == [(t, m) for m, t in pings]
    decoded = list(iter_pings(sonar[0]))
    assert [(p.ping_id, p.time) for p in decoded] == [
        (1000 + k, t) for k, (_, t) in enumerate(pings)
    ]
    assert_tlog(read_tlog(nav[0]), packets)
    navlog = read_nav_log(nav[0])
    assert navlog.autopilot == "ardupilot"
    assert len(navlog.gnss) == 5
    assert navlog.report.messages == 10 and not navlog.report.truncated


def test_malformed_sonar_message_is_rejected_not_raised(tmp_path: Path) -> None:
    with SurveyRecorder(tmp_path, min_free_bytes=0) as rec:
        assert not rec.record_sonar(b"not an oculus message", T0)
        assert rec.record_sonar(*ping_message(0))
    assert rec.stats.sonar.rejected == 1 and rec.stats.sonar.items == 1
    assert rec.recording is False


def test_restart_opens_a_new_segment_and_leaves_the_old_one(tmp_path: Path) -> None:
    with SurveyRecorder(tmp_path, min_free_bytes=0) as first:
        first.record_sonar(*ping_message(0))
        first.record_mavlink(*mavlink_packet(0))
    old = {p: p.read_bytes() for p in tmp_path.iterdir()}
    with SurveyRecorder(tmp_path, min_free_bytes=0) as second:
        second.record_sonar(*ping_message(1))
        second.record_mavlink(*mavlink_packet(1))
    assert second.stats.segment == 2 and second.stats.segments == 2
    assert {p: p.read_bytes() for p in old} == old
    sonar, nav = segments(tmp_path)
    assert [p.name for p in sonar] == ["sonar-001.oculus", "sonar-002.oculus"]
    assert [p.name for p in nav] == ["nav-001.tlog", "nav-002.tlog"]
    assert read_sonar(sonar[1]) == [(ping_message(1)[1], ping_message(1)[0])]
    assert_tlog(read_tlog(nav[1]), [mavlink_packet(1)])


def test_numbering_skips_past_any_leftover_file(tmp_path: Path) -> None:
    # A crash between creating the two files of segment 3 left only its .tlog.
    TlogWriter(tmp_path / "nav-003.tlog").close()
    with SurveyRecorder(tmp_path, min_free_bytes=0) as rec:
        pass
    assert rec.stats.segment == 4
    assert (tmp_path / "sonar-004.oculus").exists() and (tmp_path / "nav-004.tlog").exists()


def test_power_cut_keeps_everything_older_than_the_flush_interval(tmp_path: Path) -> None:
    clock = FakeClock()
    rec = SurveyRecorder(tmp_path, flush_interval_s=1.0, min_free_bytes=0, clock=clock)
    pings = [ping_message(k) for k in range(6)]
    packets = [mavlink_packet(k) for k in range(12)]
    for k in range(6):
        clock.now += 0.3  # items arrive every 0.3 s
        rec.record_sonar(*pings[k])
        rec.record_mavlink(*packets[2 * k])
        rec.record_mavlink(*packets[2 * k + 1])
    # Cut at clock 101.8: items from before 100.8 (k <= 2) must be on disk; the flush at
    # the first item of 101.2 put pings[:4] and packets[:6] there.
    assert rec.stats.flushes >= 2
    assert rec.sonar_path is not None and rec.nav_path is not None
    # Power cut: read the files as they are, without close (the object stays alive, so no
    # finaliser flushes behind our back). The readers see a prefix of what was recorded.
    report = LogReadReport()
    on_disk = [(i.time, i.message) for i in iter_log_items(rec.sonar_path, report)]
    assert len(on_disk) >= 3 and on_disk == [(t, m) for m, t in pings[: len(on_disk)]]
    nav_on_disk = read_tlog(rec.nav_path)
    assert len(nav_on_disk) >= 6
    assert_tlog(nav_on_disk, packets[: len(nav_on_disk)])
    # Idle: a timer calling poll() gets the rest out once the interval has passed.
    rec.poll()
    clock.now += 1.0
    rec.poll()
    assert read_sonar(rec.sonar_path) == [(t, m) for m, t in pings]
    assert_tlog(read_tlog(rec.nav_path), packets)
    rec.close()


def test_fsync_at_most_once_a_second(tmp_path: Path) -> None:
    clock = FakeClock()
    rec = SurveyRecorder(tmp_path, flush_interval_s=0.0, min_free_bytes=0, clock=clock)
    synced_at = rec.stats.fsyncs
    for k in range(20):
        clock.now += 0.125  # exact in binary: 20 items over 2.5 s
        rec.record_mavlink(*mavlink_packet(k))
    assert rec.stats.flushes >= 20  # every item, with flush_interval_s = 0
    assert rec.stats.fsyncs - synced_at == 2  # at 1.0 s and 2.0 s
    rec.close()


def test_background_fsync_runs_off_the_caller_and_never_piles_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import daemon.recording as recording

    caller = threading.get_ident()
    release = threading.Event()
    synced: list[tuple[int, str]] = []

    def slow_fsync(path: Path) -> None:  # an SD card that takes its time
        release.wait(5.0)
        synced.append((threading.get_ident(), path.name))

    clock = FakeClock()
    rec = SurveyRecorder(
        tmp_path, flush_interval_s=0.0, min_free_bytes=0, clock=clock, fsync_in_background=True
    )
    monkeypatch.setattr(recording, "_fsync_path", slow_fsync)
    opened = rec.stats.fsyncs
    for k in range(40):
        clock.now += 0.125  # 5 s of items while the first fsync hangs
        assert rec.record_mavlink(*mavlink_packet(k))
    assert rec.stats.fsyncs - opened == 1 and synced == []  # in flight; the caller went on
    release.set()
    rec.close()  # waits for it, then syncs what came since
    assert rec.stats.fsyncs - opened == 2
    assert {thread for thread, _ in synced[:2]} != {caller}
    assert synced[-1][0] == caller and len(synced) == 4
    assert len(read_tlog(rec.nav_path or tmp_path)) == 40


def test_full_disk_probe_stops_cleanly(tmp_path: Path) -> None:
    clock = FakeClock()
    free = {"bytes": 500 * MB}
    rec = SurveyRecorder(
        tmp_path, min_free_bytes=200 * MB, clock=clock, free_space=lambda _: free["bytes"]
    )
    rec.record_sonar(*ping_message(0))
    rec.record_mavlink(*mavlink_packet(0))
    free["bytes"] = 150 * MB
    rec.record_sonar(*ping_message(1))  # probe cached: still recorded
    clock.now += 1.5
    assert not rec.record_sonar(*ping_message(2))
    assert not rec.record_mavlink(*mavlink_packet(1))
    assert rec.stats.full and rec.stats.stopped and not rec.recording
    assert rec.stats.stop_reason is not None and "disk full" in rec.stats.stop_reason
    assert rec.stats.sonar.items == 2 and rec.stats.sonar.dropped == 1
    assert rec.stats.nav.dropped == 1
    rec.close()  # harmless after a stop
    sonar, nav = segments(tmp_path)
    assert read_sonar(sonar[0]) == [(t, m) for m, t in (ping_message(0), ping_message(1))]
    assert_tlog(read_tlog(nav[0]), [mavlink_packet(0)])


def test_already_full_disk_opens_no_segment(tmp_path: Path) -> None:
    rec = SurveyRecorder(tmp_path, free_space=lambda _: 10 * MB)
    assert rec.stats.full and rec.stats.segment == 0
    assert not rec.record_mavlink(*mavlink_packet(0))
    assert segments(tmp_path) == ([], [])


def test_enospc_from_write_stops_cleanly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rec = SurveyRecorder(tmp_path, min_free_bytes=0)
    for k in range(3):
        assert rec.record_sonar(*ping_message(k))
        assert rec.record_mavlink(*mavlink_packet(k))

    def no_space(self: object, *args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(OculusLogWriter, "write", no_space)
    assert not rec.record_sonar(*ping_message(3))  # never raises
    assert rec.stats.full and rec.stats.errors == 1
    assert rec.stats.stop_reason is not None and "No space" in rec.stats.stop_reason
    assert not rec.record_mavlink(*mavlink_packet(3))
    sonar, nav = segments(tmp_path)
    assert read_sonar(sonar[0]) == [(t, m) for m, t in map(ping_message, range(3))]
    assert_tlog(read_tlog(nav[0]), [mavlink_packet(k) for k in range(3)])


def test_other_write_error_stops_without_full(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = SurveyRecorder(tmp_path, min_free_bytes=0)
    rec.record_mavlink(*mavlink_packet(0))

    def io_error(self: object, *args: object) -> int:
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(TlogWriter, "write", io_error)
    assert not rec.record_mavlink(*mavlink_packet(1))
    assert rec.stats.stopped and not rec.stats.full and rec.stats.errors == 1
    assert_tlog(read_tlog(tmp_path / "nav-001.tlog"), [mavlink_packet(0)])


def test_the_live_links_recording_keeps_the_echosounders_packets(tmp_path: Path) -> None:
    """The daemon's wiring: every packet the link receives goes raw to the recorder, so
    DISTANCE_SENSOR (both sensors) and RANGEFINDER are in the survey's .tlog, and a replay
    of it has the soundings the live map had, at the same stamps."""
    played = fx.write_tlog(
        tmp_path / "played.tlog", fx.by_time(fx.ardupilot_messages(), fx.echosounder_messages())
    )
    survey = tmp_path / "surveys" / "s1"
    live: list[Any] = []

    async def run() -> None:
        port = free_udp_port()
        with SurveyRecorder(survey, min_free_bytes=0) as rec:

            def on_packet(packet: bytes, received: float) -> None:
                rec.record_mavlink(packet, received)

            link = MavlinkLink(
                f"udpin:127.0.0.1:{port}", on_packet=on_packet, on_sample=live.append
            )
            emu = AutopilotEmulator.from_tlog(played, time_scale=2.0)
            async with link, emu:
                await emu.start_udp(port)
                await asyncio.wait_for(emu.done.wait(), 10.0)
                await asyncio.sleep(0.2)

    asyncio.run(asyncio.wait_for(run(), 20.0))
    _, nav = segments(survey)
    messages = summarize_nav_log(nav[0])["messages"]
    assert (messages["DISTANCE_SENSOR"], messages["RANGEFINDER"]) == (60, 30)
    recorded = read_nav_log(nav[0])
    assert recorded.range_source == "DISTANCE_SENSOR" and len(recorded.ranges) == 19
    soundings = [s for s in live if isinstance(s, RangeSample)]
    assert len(soundings) == len(recorded.ranges)
    for got, kept in zip(soundings, recorded.ranges, strict=True):
        assert got.time == pytest.approx(kept.time, abs=1e-6)  # µs stamps in the .tlog
        assert got.distance_m == kept.distance_m and got.source == kept.source
