"""Reading whole navigation logs: every sample back, the right source, damage survived."""

from __future__ import annotations

import json
import math
import os
import random
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink import DFReader
from pymavlink.dialects.v20 import all as mavlink

from drivers.mavlink import NavLog, NavLogError, convert, read_nav_log, summarize_nav_log
from tests.drivers import mavlink_fixtures as fx
from tests.fuzzing import fuzz

REPO = Path(__file__).resolve().parents[2]


def decoded(sent: fx.Sent) -> Any:
    """The message as a receiver decodes its frame (MAVLink 1 loses the extensions)."""
    return mavlink.MAVLink(None).decode(bytearray(fx.TlogWriter().frame(sent)))


def autopilot_messages(messages: list[fx.Sent]) -> list[tuple[float, Any]]:
    return [(s.time, decoded(s)) for s in messages if (s.sysid, s.compid) == (1, 1)]


def expect(messages: list[fx.Sent], kind: str, convert_one: Any) -> list[Any]:
    samples = [convert_one(m, t) for t, m in autopilot_messages(messages) if m.get_type() == kind]
    return [s for s in samples if s is not None]


def heading_degrees_error(a: float, b_deg: float) -> float:
    return abs((math.degrees(a) - b_deg + 180.0) % 360.0 - 180.0)


# --- tlog read back ------------------------------------------------------------------------


@pytest.mark.parametrize("mavlink1_until_s", [0.0, 1.5, 99.0], ids=["v2", "v1-then-v2", "v1"])
def test_ardupilot_tlog_reads_back_every_sample(tmp_path: Path, mavlink1_until_s: float) -> None:
    messages = fx.ardupilot_messages(mavlink1_until_s=mavlink1_until_s)
    nav = read_nav_log(fx.write_tlog(tmp_path / "rover.tlog", messages))

    assert (nav.autopilot, nav.imu_source, nav.heading_source) == ("ardupilot", "raw", "attitude")
    assert nav.gnss_source == "GPS_RAW_INT"
    assert nav.imu == expect(messages, "RAW_IMU", convert.imu_from_mavlink)
    assert nav.gnss == expect(messages, "GPS_RAW_INT", convert.gnss_from_mavlink)
    assert nav.heading == expect(messages, "ATTITUDE", convert.heading_from_mavlink)
    assert nav.attitude == expect(messages, "ATTITUDE", convert.attitude_from_mavlink)
    assert len(nav.imu) == 30 and len(nav.gnss) == 15 and len(nav.attitude) == 30

    # Against the truth, not only against the conversion: receive times, position, heading.
    assert nav.imu[0].time == pytest.approx(fx.T0_US / 1e6 + 10e-6, abs=1e-6)
    for sample in nav.heading:
        truth = fx.Truth(sample.time - fx.T0_US / 1e6)
        assert heading_degrees_error(sample.heading_rad, truth.heading_deg) < 1e-4
    last = nav.gnss[-1]
    truth = fx.Truth(last.time - fx.T0_US / 1e6)
    assert (last.lat_deg, last.lon_deg) == pytest.approx((truth.lat_deg, truth.lon_deg), abs=1e-7)
    # h_acc is a MAVLink 2 extension: absent (None) exactly where the frame was MAVLink 1.
    for fix in nav.gnss:
        v1 = fix.time - fx.T0_US / 1e6 < mavlink1_until_s
        assert (fix.h_acc_m is None) == v1
    report = nav.report
    assert (report.bytes_skipped, report.bad_packets, report.truncated) == (0, 0, False)
    assert report.messages == len(messages)
    assert report.autopilot_id == (1, 1)
    assert report.other_system_messages == sum((s.sysid, s.compid) != (1, 1) for s in messages)


def test_gcs_and_companion_messages_are_not_the_boat(tmp_path: Path) -> None:
    nav = read_nav_log(
        fx.write_tlog(tmp_path / "x.tlog", fx.ardupilot_messages(with_gps_raw=False)),
        heading_source="global_position",
    )
    # The GCS's follow-me GLOBAL_POSITION_INT (hdg 90 deg, -35.3 / 149.1) and the companion's
    # ATTITUDE (roll 0.5 rad) come from other (system, component)s.
    assert all(fix.lon_deg > 149.16 for fix in nav.gnss)
    assert all(abs(a.roll_rad) < math.radians(10.01) for a in nav.attitude)
    assert all(abs(math.degrees(h.heading_rad) - 90.0) > 1 for h in nav.heading)


def test_same_as_pymavlinks_own_reader(tmp_path: Path) -> None:
    """mavutil.mavlink_connection (in its own process: it switches dialects globally)
    gives the same messages and stamps."""
    path = fx.write_tlog(tmp_path / "rover.tlog", fx.ardupilot_messages())
    script = (
        "import json, sys\n"
        "from pymavlink import mavutil\n"
        "from drivers.mavlink import convert\n"
        "take = {'RAW_IMU': convert.imu_from_mavlink, 'GPS_RAW_INT': convert.gnss_from_mavlink,\n"
        "        'ATTITUDE': convert.attitude_from_mavlink}\n"
        "log = mavutil.mavlink_connection(sys.argv[1])\n"
        "out = []\n"
        "while (m := log.recv_match()) is not None:\n"
        "    if (m.get_srcSystem(), m.get_srcComponent()) == (1, 1) and m.get_type() in take:\n"
        "        out.append(repr(take[m.get_type()](m, m._timestamp)))\n"
        "print(json.dumps(out))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, str(path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "MAVLINK20": "1"},
    )
    theirs = json.loads(done.stdout)
    nav = read_nav_log(path)
    ours: list[Any] = [*nav.imu, *nav.gnss, *nav.attitude]
    assert len(theirs) == len(ours) == 75
    assert sorted(theirs) == sorted(repr(s) for s in ours)


def test_px4_tlog(tmp_path: Path) -> None:
    messages = fx.px4_messages()
    path = fx.write_tlog(tmp_path / "px4.tlog", messages)
    nav = read_nav_log(path)
    assert (nav.autopilot, nav.imu_source, nav.heading_source) == ("px4", "highres", "attitude")
    assert nav.imu == expect(messages, "HIGHRES_IMU", convert.imu_from_mavlink)
    assert nav.imu[0].accel_mps2 == pytest.approx((0.31, -0.21, -9.79), rel=1e-6)
    assert nav.imu[0].mag_gauss is not None
    assert nav.gnss[0].h_acc_m == pytest.approx(0.014)
    assert nav.gnss[0].fix_type == 6

    # PX4's RAW_IMU holds raw counts: never used, even when asked for.
    raw = read_nav_log(path, imu_source="raw")
    assert raw.imu == [] and raw.imu_source is None
    assert any("PX4" in note for note in raw.report.notes)
    # PX4 sends GLOBAL_POSITION_INT.hdg = 65535 (unknown): no heading from it.
    unknown = read_nav_log(path, heading_source="global_position")
    assert unknown.heading == [] and unknown.heading_source is None
    hud = read_nav_log(path, heading_source="vfr_hud")
    assert len(hud.heading) == 20
    assert all(h.resolution_rad == pytest.approx(math.radians(1)) for h in hud.heading)


def test_heading_sources_on_request(tmp_path: Path) -> None:
    path = fx.write_tlog(tmp_path / "x.tlog", fx.ardupilot_messages())
    for source, message in convert.HEADING_MESSAGES.items():
        nav = read_nav_log(path, heading_source=source)
        assert nav.heading_source == source
        assert {h.source for h in nav.heading} == {message}
        assert len(nav.heading) == 30
        for sample in nav.heading:
            truth = fx.Truth(sample.time - fx.T0_US / 1e6)
            assert heading_degrees_error(sample.heading_rad, truth.heading_deg) <= 1.0
    compass = read_nav_log(path, heading_source="compass", declination_deg=fx.SITE_DECLINATION_DEG)
    assert compass.heading_source == "compass" and len(compass.heading) == 30
    for sample in compass.heading:
        assert sample.source == "MAG"
        truth = fx.Truth(sample.time - fx.T0_US / 1e6)
        # RAW_IMU's milligauss integers and the 10 Hz attitude limit it to a few tenths.
        assert heading_degrees_error(sample.heading_rad, truth.heading_deg) < 0.5
    # Declination is what turns magnetic into true north.
    magnetic = read_nav_log(path, heading_source="compass")
    offsets = [
        heading_degrees_error(m.heading_rad, math.degrees(t.heading_rad) - fx.SITE_DECLINATION_DEG)
        for m, t in zip(magnetic.heading, compass.heading, strict=True)
    ]
    assert max(offsets) < 1e-9


def test_auto_heading_falls_back_in_order_and_never_flips(tmp_path: Path) -> None:
    no_attitude = fx.ardupilot_messages(with_attitude=False)
    nav = read_nav_log(fx.write_tlog(tmp_path / "a.tlog", no_attitude))
    assert nav.heading_source == "global_position"
    assert {h.source for h in nav.heading} == {"GLOBAL_POSITION_INT"}
    assert nav.attitude == []

    # ATTITUDE only from t = 1 s: still the chosen source, for the whole log.
    late = [
        s
        for s in fx.ardupilot_messages()
        if not (s.msg.get_type() == "ATTITUDE" and s.sysid == 1 and s.time_us < fx.T0_US + 1e6)
    ]
    nav = read_nav_log(fx.write_tlog(tmp_path / "b.tlog", late))
    assert nav.heading_source == "attitude" and len(nav.heading) == 20
    assert {h.source for h in nav.heading} == {"ATTITUDE"}

    # Only a magnetometer and no attitude: the compass, read as level.
    bare = [s for s in no_attitude if s.msg.get_type() not in ("GLOBAL_POSITION_INT", "VFR_HUD")]
    nav = read_nav_log(fx.write_tlog(tmp_path / "c.tlog", bare))
    assert nav.heading_source == "compass" and len(nav.heading) == 30
    assert any("level" in note for note in nav.report.notes)


def test_imu_sources(tmp_path: Path) -> None:
    messages = fx.ardupilot_messages()
    path = fx.write_tlog(tmp_path / "x.tlog", messages)
    nav = read_nav_log(path, imu_source="scaled2")
    assert nav.imu_source == "scaled2"
    assert nav.imu == expect(messages, "SCALED_IMU2", convert.imu_from_mavlink)
    missing = read_nav_log(path, imu_source="highres")
    assert missing.imu == [] and missing.imu_source is None
    assert any("imu_source 'highres'" in note for note in missing.report.notes)
    no_raw = [s for s in messages if s.msg.get_type() != "RAW_IMU"]
    assert read_nav_log(fx.write_tlog(tmp_path / "y.tlog", no_raw)).imu_source == "scaled2"


def test_global_position_is_only_a_fallback(tmp_path: Path) -> None:
    messages = fx.ardupilot_messages(with_gps_raw=False)
    nav = read_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    assert nav.gnss_source == "GLOBAL_POSITION_INT"
    assert nav.gnss == expect(messages, "GLOBAL_POSITION_INT", convert.gnss_from_mavlink)
    assert {fix.source for fix in nav.gnss} == {"GLOBAL_POSITION_INT"}


def test_log_without_heartbeat_uses_the_navigation_sender(tmp_path: Path) -> None:
    messages = [s for s in fx.ardupilot_messages() if s.msg.get_type() != "HEARTBEAT"]
    nav = read_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    assert nav.autopilot == "unknown" and nav.report.autopilot_id == (1, 1)
    assert len(nav.imu) == 30


def test_samples_before_the_first_heartbeat_are_kept(tmp_path: Path) -> None:
    messages = fx.ardupilot_messages()
    first_heartbeat = next(i for i, s in enumerate(messages) if s.msg.get_type() == "HEARTBEAT")
    del messages[first_heartbeat]
    nav = read_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    assert nav.autopilot == "ardupilot" and len(nav.imu) == 30
    assert nav.imu[0].time == pytest.approx(fx.T0_US / 1e6 + 10e-6, abs=1e-6)


def test_time_going_backwards_is_reported_and_samples_sorted(tmp_path: Path) -> None:
    messages = fx.ardupilot_messages()
    index = next(i for i, s in enumerate(messages) if s.msg.get_type() == "RAW_IMU" and i > 40)
    stepped = messages[index]
    messages[index] = fx.Sent(stepped.time_us - 500_000, stepped.msg, 1, 1)
    nav = read_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    assert nav.report.time_backwards == 1
    assert [s.time for s in nav.imu] == sorted(s.time for s in nav.imu)
    assert len(nav.imu) == 30


def test_a_damaged_stamp_does_not_make_a_sample(tmp_path: Path) -> None:
    messages = fx.ardupilot_messages()
    index = next(i for i, s in enumerate(messages) if s.msg.get_type() == "RAW_IMU" and i > 40)
    glitch = messages[index]
    messages[index] = fx.Sent(glitch.time_us + 10 * 365 * 86400 * 10**6, glitch.msg, 1, 1)
    nav = read_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    assert nav.report.bad_timestamps == 1 and len(nav.imu) == 29
    assert nav.report.last_time is not None and nav.report.last_time < fx.T0_US / 1e6 + 10


def test_a_clock_step_is_not_damage(tmp_path: Path) -> None:
    """A boat computer without a real-time clock counts from 1970 until NTP or GPS sets it."""
    offset = fx.T0_US - 3_600_000_000
    messages = [
        replace(s, time_us=s.time_us - offset) if i < 100 else s
        for i, s in enumerate(fx.ardupilot_messages())
    ]
    nav = read_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    assert len(nav.imu) == 30 and nav.report.bad_timestamps == 0
    assert nav.report.first_time == 3600.0


# --- DataFlash -----------------------------------------------------------------------------


def dfreader_samples(path: Path) -> dict[str, list[Any]]:
    """The samples that pymavlink's own DataFlash reader and our converters give."""
    log = DFReader.DFReader_binary(str(path))
    out: dict[str, list[Any]] = {"imu": [], "gnss": [], "attitude": [], "heading": []}
    while (msg := log.recv_msg()) is not None:
        name, time = msg.get_type(), msg._timestamp
        if name == "IMU" and msg.I == 0:
            out["imu"].append(convert.imu_from_dataflash(msg, time))
        elif name == "GPS" and msg.I == 0:
            out["gnss"].append(convert.gnss_from_dataflash(msg, time))
        elif name == "ATT":
            out["attitude"].append(convert.attitude_from_dataflash(msg, time))
            out["heading"].append(convert.heading_from_dataflash(msg, time))
    return out


@pytest.mark.parametrize("att", [fx.ATT_CENTIDEGREES, fx.ATT_DEGREES], ids=["c", "f"])
def test_dataflash_reads_back_as_pymavlink_does(tmp_path: Path, att: tuple[str, str]) -> None:
    path = fx.ardupilot_dataflash(att=att).save(tmp_path / "00000001.BIN")
    nav = read_nav_log(path)
    theirs = dfreader_samples(path)
    assert (nav.autopilot, nav.imu_source, nav.heading_source) == ("ardupilot", "IMU", "attitude")
    assert nav.imu == theirs["imu"] and len(nav.imu) == 30
    assert nav.attitude == theirs["attitude"]
    assert nav.heading == theirs["heading"]
    assert [replace_h_acc(f) for f in nav.gnss] == theirs["gnss"]
    assert nav.report.time_reference == "gps"
    assert (nav.report.bytes_skipped, nav.report.truncated) == (0, False)


def replace_h_acc(fix: Any) -> Any:
    return replace(fix, h_acc_m=None)


def replace_gnss(nav: NavLog, fixes: list[Any]) -> NavLog:
    return replace(nav, gnss=fixes)


def test_dataflash_against_the_truth(tmp_path: Path) -> None:
    nav = read_nav_log(fx.ardupilot_dataflash().save(tmp_path / "x.bin"))
    # The GPS clock of the first fix with a week number sets UNIX time (TimeUS 5.4 s).
    gps_us = 5_000_000 + 400_000 + 30
    time_base = fx.gps_unix_time(fx.GPS_WEEK, fx.GPS_MS_AT_BOOT + gps_us // 1000) - gps_us * 1e-6
    assert nav.imu[0].time == pytest.approx(time_base + 5.0, abs=1e-6)
    for sample in nav.attitude:
        truth = fx.Truth(sample.time - time_base - 5.00001)
        assert heading_degrees_error(sample.yaw_rad, truth.heading_deg) < 0.006
        assert math.degrees(sample.roll_rad) == pytest.approx(truth.roll_deg, abs=0.006)
    assert nav.imu[0].accel_mps2 == pytest.approx((0.3, -0.2, -9.80665), abs=1e-6)
    assert {s.source for s in nav.imu} == {"IMU[0]"}
    # GPA's HAcc joins its GPS fix; 0 (not reported) before the fix.
    assert [f.h_acc_m for f in nav.gnss] == [None, None] + [pytest.approx(1.35)] * 13
    assert [f.usable for f in nav.gnss] == [False, False] + [True] * 13


def test_dataflash_compass_uses_mag_and_attitude(tmp_path: Path) -> None:
    path = fx.ardupilot_dataflash().save(tmp_path / "x.bin")
    nav = read_nav_log(path, heading_source="compass", declination_deg=fx.SITE_DECLINATION_DEG)
    assert nav.heading_source == "compass" and len(nav.heading) == 30
    for heading, attitude in zip(nav.heading, nav.attitude, strict=True):
        assert heading_degrees_error(heading.heading_rad, math.degrees(attitude.yaw_rad)) < 0.5


def test_dataflash_without_gps_time_counts_from_boot(tmp_path: Path) -> None:
    nav = read_nav_log(fx.ardupilot_dataflash(gps_week=False).save(tmp_path / "x.bin"))
    assert nav.report.time_reference == "boot"
    assert nav.imu[0].time == pytest.approx(5.0)
    assert any("since boot" in note for note in nav.report.notes)


def test_kind_comes_from_the_content(tmp_path: Path) -> None:
    tlog = fx.write_tlog(tmp_path / "looks_like.bin", fx.ardupilot_messages(seconds=1))
    assert read_nav_log(tlog).report.format == "tlog"
    dataflash = fx.ardupilot_dataflash(seconds=1).save(tmp_path / "looks_like.tlog")
    assert read_nav_log(dataflash).report.format == "dataflash"


# --- summary -------------------------------------------------------------------------------


def test_summary_of_a_tlog(tmp_path: Path) -> None:
    messages = fx.ardupilot_messages()
    summary = summarize_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    json.dumps(summary)
    types = [s.msg.get_type() for s in messages]
    assert summary["messages"] == {t: types.count(t) for t in sorted(set(types))}
    assert summary["count"] == len(messages)
    assert (summary["kind"], summary["format"], summary["autopilot"]) == (
        "mavlink",
        "tlog",
        "ardupilot",
    )
    assert summary["first_time"] == messages[0].time
    assert summary["last_time"] == messages[-1].time
    assert (summary["bytes_skipped"], summary["truncated"]) == (0, False)


def test_summary_of_a_dataflash_log(tmp_path: Path) -> None:
    log = fx.ardupilot_dataflash()
    summary = summarize_nav_log(log.save(tmp_path / "x.bin"))
    json.dumps(summary)
    assert summary["format"] == "dataflash" and summary["autopilot"] == "ardupilot"
    assert summary["messages"]["IMU"] == 60 and summary["messages"]["FMT"] == 10
    assert summary["time_reference"] == "gps"
    # From the first message (UNIT, TimeUS 1 ms) to the last (MAG, TimeUS 7.90002 s).
    assert summary["last_time"] - summary["first_time"] == pytest.approx(7.89902, abs=1e-6)


# --- damage --------------------------------------------------------------------------------


def is_prefix(part: NavLog, whole: NavLog) -> bool:
    streams = ("imu", "gnss", "heading", "attitude")
    return all(getattr(whole, s)[: len(getattr(part, s))] == getattr(part, s) for s in streams)


def test_tlog_cut_anywhere_reads_up_to_the_cut(tmp_path: Path) -> None:
    writer = fx.TlogWriter().extend(fx.ardupilot_messages())
    whole = read_nav_log(writer.save(tmp_path / "whole.tlog"))
    boundaries = {*writer.offsets, len(writer.data)}
    rng = random.Random(7)
    cuts = sorted({*rng.sample(range(20, len(writer.data)), 120), *range(20, 60)})
    path = tmp_path / "cut.tlog"
    for cut in cuts:
        path.write_bytes(bytes(writer.data[:cut]))
        nav = read_nav_log(path)
        assert is_prefix(nav, whole), cut
        assert nav.report.truncated == (cut not in boundaries), cut
        assert nav.report.bytes_skipped == 0, cut
        assert summarize_nav_log(path)["truncated"] == nav.report.truncated


def test_dataflash_cut_anywhere_reads_up_to_the_cut(tmp_path: Path) -> None:
    data = fx.ardupilot_dataflash().data
    whole = read_nav_log(fx.ardupilot_dataflash().save(tmp_path / "whole.bin"))
    rng = random.Random(8)
    path = tmp_path / "cut.bin"
    for cut in sorted(rng.sample(range(3, len(data)), 120)):
        path.write_bytes(bytes(data[:cut]))
        nav = read_nav_log(path)
        assert nav.report.bytes_skipped == 0, cut
        if nav.report.time_reference == "gps":  # cut after the first GPS week
            # (A fix cut off from its GPA, logged right after it, has no h_acc.)
            nav.gnss = [replace_h_acc(f) for f in nav.gnss]
            whole_fixes = [replace_h_acc(f) for f in whole.gnss]
            assert is_prefix(nav, replace_gnss(whole, whole_fixes)), cut
        assert len(nav.imu) <= len(whole.imu)


def corrupt(data: bytes, seed: int, blocks: int = 6) -> bytes:
    """Random bytes written over a few blocks in the middle, as a bad SD card does."""
    rng = random.Random(seed)
    damaged = bytearray(data)
    for _ in range(blocks):
        start = rng.randrange(len(data) // 5, len(data) * 4 // 5)
        length = rng.randrange(1, 40)
        damaged[start : start + length] = rng.randbytes(length)
    return bytes(damaged[: len(data)])


@pytest.mark.parametrize("seed", range(8))
def test_corrupted_tlog_keeps_every_good_sample_and_no_bad_one(tmp_path: Path, seed: int) -> None:
    writer = fx.TlogWriter().extend(fx.ardupilot_messages(seconds=6))
    whole = read_nav_log(writer.save(tmp_path / "whole.tlog"))
    path = tmp_path / "bad.tlog"
    path.write_bytes(corrupt(bytes(writer.data), seed))
    nav = read_nav_log(path)
    assert nav.report.bytes_skipped > 0 or nav.report.bad_packets > 0
    assert len(nav.imu) >= 0.8 * len(whole.imu)
    # The CRC rejects every damaged frame: whatever comes out was sent (stamps are not
    # CRC-protected, so values are compared).
    good_imu = {(s.accel_mps2, s.gyro_rps, s.mag_gauss) for s in whole.imu}
    good_fixes = {(f.lat_deg, f.lon_deg, f.fix_type) for f in whole.gnss}
    good_yaw = {h.heading_rad for h in whole.heading}
    assert all((s.accel_mps2, s.gyro_rps, s.mag_gauss) in good_imu for s in nav.imu)
    assert all((f.lat_deg, f.lon_deg, f.fix_type) in good_fixes for f in nav.gnss)
    assert all(h.heading_rad in good_yaw for h in nav.heading)
    summarize_nav_log(path)


@pytest.mark.parametrize("seed", range(8))
def test_corrupted_dataflash_reads_on(tmp_path: Path, seed: int) -> None:
    data = bytes(fx.ardupilot_dataflash(seconds=6).data)
    path = tmp_path / "bad.bin"
    path.write_bytes(corrupt(data, seed))
    nav = read_nav_log(path)
    assert len(nav.imu) >= 40  # of 60: damage costs a few messages, not the rest of the log
    summarize_nav_log(path)


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("notes.txt", b"This is a survey note, not a log.\n" * 20),
        ("image.png", b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4),
        ("random.tlog", random.Random(3).randbytes(5000)),
        ("short.tlog", b"\x00\x06\x1a"),
        ("empty.tlog", b""),
    ],
)
def test_not_a_log_is_a_one_line_error_naming_the_file(
    tmp_path: Path, name: str, content: bytes
) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    for read in (read_nav_log, summarize_nav_log):
        with pytest.raises(NavLogError) as error:
            read(path)
        assert str(path) in str(error.value) and "\n" not in str(error.value)


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(NavLogError, match="no such file"):
        read_nav_log(tmp_path / "nope.tlog")
    with pytest.raises(NavLogError, match="directory"):
        summarize_nav_log(tmp_path)


_TLOG = bytes(fx.TlogWriter().extend(fx.ardupilot_messages(seconds=1)).data)
_BIN = bytes(fx.ardupilot_dataflash(seconds=1).data)


def read_or_not_a_log(path: Path) -> None:
    """Reading never fails except with NavLogError, and then only for 'not a log'."""
    for read in (read_nav_log, summarize_nav_log):
        try:
            read(path)
        except NavLogError as error:
            assert "not a MAVLink log" in str(error)


_SETTINGS = fuzz(150)


@pytest.mark.fuzz
@_SETTINGS
@given(data=st.binary(min_size=1, max_size=3000))
def test_random_bytes_never_crash(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "random.tlog"
    path.write_bytes(data)
    read_or_not_a_log(path)


mutation = st.tuples(
    st.sampled_from(["overwrite", "delete", "insert"]),
    st.integers(0, 10_000),
    st.binary(min_size=1, max_size=30),
)


def mutate(data: bytes, mutations: list[tuple[str, int, bytes]]) -> bytes:
    out = bytearray(data)
    for kind, where, chunk in mutations:
        at = where % max(len(out), 1)
        if kind == "overwrite":
            out[at : at + len(chunk)] = chunk
        elif kind == "delete":
            del out[at : at + len(chunk)]
        else:
            out[at:at] = chunk
    return bytes(out)


@pytest.mark.fuzz
@_SETTINGS
@given(mutations=st.lists(mutation, min_size=1, max_size=8), cut=st.integers(1, 20_000))
def test_mutated_tlogs_never_crash(
    tmp_path: Path, mutations: list[tuple[str, int, bytes]], cut: int
) -> None:
    path = tmp_path / "mutated.tlog"
    path.write_bytes(mutate(_TLOG, mutations)[:cut])
    read_or_not_a_log(path)


@pytest.mark.fuzz
@_SETTINGS
@given(mutations=st.lists(mutation, min_size=1, max_size=8), cut=st.integers(1, 20_000))
def test_mutated_dataflash_never_crashes(
    tmp_path: Path, mutations: list[tuple[str, int, bytes]], cut: int
) -> None:
    path = tmp_path / "mutated.bin"
    path.write_bytes(mutate(_BIN, mutations)[:cut])
    read_or_not_a_log(path)
