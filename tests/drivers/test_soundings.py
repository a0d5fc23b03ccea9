"""A downward echosounder's soundings: DISTANCE_SENSOR / RANGEFINDER / RFND into RangeSample,
from one message, from .tlog and DataFlash logs, from the live link; one stream, no doubles,
no non-reading ever a distance."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import DFReader
from pymavlink.dialects.v20 import all as mavlink

from drivers.mavlink import convert, read_nav_log, summarize_nav_log
from drivers.mavlink.link import MavlinkLink
from mapping.samples import RangeSample
from seamap.cli import main
from tests.drivers import mavlink_fixtures as fx
from tests.ports import free_udp_port
from tools.emulators.autopilot import AutopilotEmulator

T = 1_718_000_000.25
TIMEOUT_S = 10.0


def on_the_wire(msg: Any, mavlink1: bool = False) -> Any:
    """The message as a receiver decodes its frame (MAVLink 1 loses the extensions)."""
    frame = fx.TlogWriter().frame(fx.Sent(0, msg, mavlink1=mavlink1))
    return mavlink.MAVLink(None).decode(bytearray(frame))


def distance_sensor(
    current: int,
    *,
    low: int = 30,
    high: int = 5000,
    orientation: int = fx.DOWNWARD,
    covariance: int = 4,
    quality: int = 87,
    sensor_id: int = 0,
) -> Any:
    return mavlink.MAVLink_distance_sensor_message(
        1234, low, high, current, 1, sensor_id, orientation, covariance, 0.5, 0.5,
        (0, 0, 0, 0), quality,
    )  # fmt: skip


def no_time(samples: list[Any]) -> list[Any]:
    return [dataclasses.replace(s, time=0.0) for s in samples]


def expected_soundings(messages: list[fx.Sent]) -> list[RangeSample]:
    """What the downward DISTANCE_SENSORs of the autopilot should give: converted one by
    one, the non-readings left out."""
    out = []
    for sent in messages:
        msg = on_the_wire(sent.msg, sent.mavlink1)
        if (sent.sysid, sent.compid) == (1, 1) and msg.get_type() == "DISTANCE_SENSOR":
            sample = convert.range_from_mavlink(msg, sent.time)
            if sample is not None:
                out.append(sample)
    return out


# --- one message ----------------------------------------------------------------------------


def test_distance_sensor_looking_down_is_a_sounding_in_metres() -> None:
    sample = convert.range_from_mavlink(on_the_wire(distance_sensor(347)), T)
    assert sample == RangeSample(
        T, 3.47, min_m=0.3, max_m=50.0, signal_quality=87, variance_m2=4e-4,
        source="DISTANCE_SENSOR",
    )  # fmt: skip


@pytest.mark.parametrize("orientation", [0, 24, 2, 4, 6, 100])
def test_a_sensor_not_looking_down_is_no_sounding(orientation: int) -> None:
    msg = on_the_wire(distance_sensor(347, orientation=orientation))
    assert convert.downward_range_sensor(msg) is None
    assert convert.range_from_mavlink(msg, T) is None


@pytest.mark.parametrize(
    "fields",
    [
        {"current": 0},  # no echo
        {"current": 65535},  # UINT16_MAX: no reading
        {"current": 5001},  # beyond max
        {"current": 29},  # below min
        {"current": 347, "quality": 1},  # MAVLink: 1 = invalid signal
    ],
    ids=["zero", "uint16-max", "beyond-max", "below-min", "invalid-signal"],
)
def test_a_non_reading_is_never_a_distance(fields: dict[str, int]) -> None:
    assert convert.range_from_mavlink(on_the_wire(distance_sensor(**fields)), T) is None


def test_span_ends_are_readings() -> None:
    for current in (30, 5000):
        sample = convert.range_from_mavlink(on_the_wire(distance_sensor(current)), T)
        assert sample is not None and sample.distance_m == current / 100


def test_unknown_covariance_and_quality_are_none() -> None:
    for covariance in (0, 255):
        sample = convert.range_from_mavlink(
            on_the_wire(distance_sensor(347, covariance=covariance, quality=0)), T
        )
        assert sample is not None
        assert (sample.variance_m2, sample.signal_quality) == (None, None)
    # Above 100 % is no percentage: the reading stays, its quality is unknown.
    sample = convert.range_from_mavlink(on_the_wire(distance_sensor(347, quality=180)), T)
    assert sample is not None and sample.signal_quality is None
    big = convert.range_from_mavlink(on_the_wire(distance_sensor(347, covariance=254)), T)
    assert big is not None and big.variance_m2 == pytest.approx(0.0254)


def test_a_span_that_is_none_leaves_the_distance_unchecked() -> None:
    for low, high in ((0, 0), (30, 65535), (500, 400)):
        sample = convert.range_from_mavlink(
            on_the_wire(distance_sensor(347, low=low, high=high)), T
        )
        assert sample is not None and sample.distance_m == 3.47
        assert (sample.min_m, sample.max_m) == (None, None)


def test_mavlink1_distance_sensor_has_no_quality() -> None:
    msg = on_the_wire(distance_sensor(347, quality=87), mavlink1=True)
    sample = convert.range_from_mavlink(msg, T)
    assert sample is not None and sample.distance_m == 3.47 and sample.signal_quality is None


def test_rangefinder_is_metres_and_zero_or_nan_is_no_reading() -> None:
    sample = convert.range_from_mavlink(
        on_the_wire(mavlink.MAVLink_rangefinder_message(3.5, 1.2)), T
    )
    assert sample == RangeSample(T, 3.5, source="RANGEFINDER")
    assert convert.downward_range_sensor(mavlink.MAVLink_rangefinder_message(3.5, 1.2)) == 0
    for distance in (0.0, -1.0, math.nan, math.inf):
        msg = on_the_wire(mavlink.MAVLink_rangefinder_message(distance, 1.2))
        assert convert.range_from_mavlink(msg, T) is None


@settings(max_examples=300, deadline=None)
@given(
    low=st.integers(0, 65535),
    high=st.integers(0, 65535),
    current=st.integers(0, 65535),
    orientation=st.integers(0, 255),
    covariance=st.integers(0, 255),
    quality=st.integers(0, 255),
)
def test_any_distance_sensor_on_the_wire_is_a_valid_sounding_or_none(
    low: int, high: int, current: int, orientation: int, covariance: int, quality: int
) -> None:
    msg = on_the_wire(
        distance_sensor(
            current, low=low, high=high, orientation=orientation, covariance=covariance,
            quality=quality,
        )
    )  # fmt: skip
    sample = convert.range_from_mavlink(msg, T)
    if sample is None:
        return
    assert orientation == fx.DOWNWARD
    assert 0.0 < sample.distance_m < 655.35
    if sample.min_m is not None and sample.max_m is not None:
        assert sample.min_m <= sample.distance_m <= sample.max_m
    assert sample.signal_quality is None or 2 <= sample.signal_quality <= 100
    assert sample.variance_m2 is None or 0.0 < sample.variance_m2 < 0.0255


@pytest.mark.parametrize(
    "field, value",
    [
        ("current_distance", math.nan),
        ("current_distance", math.inf),
        ("current_distance", 1e30),
        ("current_distance", -5),
        ("current_distance", None),
        ("current_distance", "347"),
        ("min_distance", math.nan),
        ("max_distance", 1e300),
        ("covariance", math.nan),
        ("signal_quality", math.inf),
        ("orientation", math.nan),
        ("id", math.nan),
    ],
)
def test_malformed_fields_never_crash(field: str, value: Any) -> None:
    """A message built in code (or by another dialect) with values no uint field holds:
    no exception, and never a distance out of the sensor's own numbers."""
    msg = distance_sensor(347)
    setattr(msg, field, value)
    sample = convert.range_from_mavlink(msg, T)
    if field in ("current_distance", "orientation"):
        assert sample is None or sample.distance_m == 3.47
    else:
        assert sample is not None and sample.distance_m == 3.47


def rfnd(layout: str, values: dict[str, float], units: tuple[str, str] | None = None) -> Any:
    """A DFMessage of an RFND layout from raw field values (as the bytes hold them)."""
    chars, columns = fx.RFND_LAYOUTS[layout][:2]
    fmt = DFReader.DFFormat(fx.RFND_TYPE, "RFND", 0, chars, columns)
    if units is not None:
        fmt.set_unit_ids(units[0], {"s": "s", "#": "instance", "m": "m", "%": "%", "-": ""})
        fmt.set_mult_ids(units[1], {"F": 1e-6, "B": 1e-2, "0": 1.0, "-": 0.0})
    elements = [values.get(name, 0) for name in fmt.columns]
    return DFReader.DFMessage(fmt, elements, True, None)


def test_rfnd_distance_is_read_as_the_log_declares_it() -> None:
    def distance(msg: Any) -> float | None:
        found = convert.ranges_from_dataflash(msg, T)
        assert len(found) == 1 and found[0][0] == 1
        return found[0][1].distance_m if found[0][1] is not None else None

    down = {"Instance": 1, "Stat": 4, "Orient": fx.DOWNWARD}
    # Format C: uint16 cm, which pymavlink scales by 0.01.
    assert distance(rfnd("instance", {**down, "Dist": 347}, ("s#m--", "F-B--"))) == 3.47
    # A float, metres (FMTU multiplier 1).
    floats = {**down, "Dist": 3.47, "Quality": -1}
    assert distance(rfnd("float", floats, ("s#m--%", "F-0--0"))) == 3.47
    # A plain integer: cm when the FMTU says m x 1e-2, or says nothing; m when it says m.
    cm = rfnd("integer_cm", {**down, "Dist": 347}, ("s#m--", "F-B--"))
    assert distance(cm) == pytest.approx(3.47)
    assert distance(rfnd("integer_cm", {**down, "Dist": 347})) == pytest.approx(3.47)
    assert distance(rfnd("integer_cm", {**down, "Dist": 3}, ("s#m--", "F-0--"))) == 3.0


def test_rfnd_status_quality_and_orientation() -> None:
    down = {"Instance": 1, "Dist": 347, "Orient": fx.DOWNWARD}
    for stat in (0, 1, 2, 3):  # NotConnected, NoData, OutOfRangeLow, OutOfRangeHigh
        assert convert.ranges_from_dataflash(rfnd("quality", {**down, "Stat": stat}), T) == [
            (1, None)
        ]
    for quality, expected in ((-1, None), (55, 55), (100, 100)):
        [(_, sample)] = convert.ranges_from_dataflash(
            rfnd("quality", {**down, "Stat": 4, "Quality": quality}), T
        )
        assert sample is not None and sample.signal_quality == expected
    for quality in (0, 1):  # no signal (ArduPilot sends both as MAVLink's "invalid")
        [(_, sample)] = convert.ranges_from_dataflash(
            rfnd("quality", {**down, "Stat": 4, "Quality": quality}), T
        )
        assert sample is None
    forward = rfnd("quality", {**down, "Stat": 4, "Orient": fx.FORWARD})
    assert convert.ranges_from_dataflash(forward, T) == []
    # Two distances a message: the downward one by its orientation, or both without any.
    two = rfnd("orient", {"Dist1": 750, "Orient1": 0, "Dist2": 347, "Orient2": fx.DOWNWARD})
    assert no_time([s for _, s in convert.ranges_from_dataflash(two, T)]) == [
        RangeSample(0.0, 3.47, source="RFND")
    ]
    plain = convert.ranges_from_dataflash(rfnd("plain", {"Dist1": 347, "Dist2": 0}), T)
    assert [(i, s.distance_m if s else None) for i, s in plain] == [(0, 3.47), (1, None)]


# --- .tlog ------------------------------------------------------------------------------------


def test_tlog_soundings_downward_only_no_doubles_no_non_readings(tmp_path: Path) -> None:
    sounder = fx.echosounder_messages()
    nav = read_nav_log(
        fx.write_tlog(tmp_path / "x.tlog", fx.by_time(fx.ardupilot_messages(), sounder))
    )
    assert nav.range_source == "DISTANCE_SENSOR"
    assert nav.ranges == expected_soundings(sounder)
    # 30 pings of the echosounder, 11 of them no reading; RANGEFINDER (the same sensor)
    # and the forward sensor (7.5 m) give none.
    assert len(nav.ranges) == 30 - sum(fx.no_reading(k) is not None for k in range(30)) == 19
    assert {s.source for s in nav.ranges} == {"DISTANCE_SENSOR"}
    for sample in nav.ranges:
        truth = fx.Truth(sample.time - fx.T0_US / 1e6 - 100e-6)
        assert sample.distance_m == pytest.approx(truth.depth_m, abs=0.005)
        assert sample.min_m == 0.3 and sample.max_m == 50.0
    assert [s.variance_m2 for s in nav.ranges[:2]] == [pytest.approx(4e-4), None]
    assert [s.signal_quality for s in nav.ranges[:2]] == [87, None]
    assert any("RANGEFINDER ignored" in note for note in nav.report.notes)
    # The other streams are as they were.
    assert len(nav.imu) == 30 and nav.gnss_source == "GPS_RAW_INT"


def test_tlog_rangefinder_alone(tmp_path: Path) -> None:
    sounder = fx.echosounder_messages(distance_sensor=False)
    nav = read_nav_log(
        fx.write_tlog(tmp_path / "x.tlog", fx.by_time(fx.ardupilot_messages(), sounder))
    )
    assert nav.range_source == "RANGEFINDER"
    # RANGEFINDER has no span or quality: only its zero distances are known non-readings.
    zeros = sum(fx.no_reading(k) == "zero" for k in range(30))
    assert len(nav.ranges) == 30 - zeros
    assert all(s.source == "RANGEFINDER" and s.min_m is None for s in nav.ranges)
    assert nav.report.notes == []


def test_tlog_distance_sensor_alone_and_mavlink1(tmp_path: Path) -> None:
    sounder = fx.echosounder_messages(rangefinder=False, mavlink1=True)
    nav = read_nav_log(
        fx.write_tlog(tmp_path / "x.tlog", fx.by_time(fx.ardupilot_messages(), sounder))
    )
    assert nav.range_source == "DISTANCE_SENSOR"
    assert nav.ranges == expected_soundings(sounder)
    # MAVLink 1 has no signal_quality: the "invalid signal" pings cannot be told.
    assert len(nav.ranges) == 30 - sum(
        fx.no_reading(k) not in (None, "invalid signal") for k in range(30)
    )
    assert {s.signal_quality for s in nav.ranges} == {None}


def test_distance_sensor_without_a_reading_still_outranks_rangefinder(tmp_path: Path) -> None:
    """A downward DISTANCE_SENSOR whose every reading is out of its span: RANGEFINDER
    repeats those same readings without the span, so it is not taken instead."""
    sounder = [
        dataclasses.replace(s, msg=distance_sensor(9000))
        if s.msg.get_type() == "DISTANCE_SENSOR" and s.msg.orientation == fx.DOWNWARD
        else s
        for s in fx.echosounder_messages()
    ]
    nav = read_nav_log(
        fx.write_tlog(tmp_path / "x.tlog", fx.by_time(fx.ardupilot_messages(), sounder))
    )
    assert nav.range_source == "DISTANCE_SENSOR" and nav.ranges == []


def test_soundings_from_another_system_are_not_the_boats(tmp_path: Path) -> None:
    sounder = fx.echosounder_messages(sysid=2)
    nav = read_nav_log(
        fx.write_tlog(tmp_path / "x.tlog", fx.by_time(fx.ardupilot_messages(), sounder))
    )
    assert nav.ranges == [] and nav.range_source is None


def test_only_the_first_downward_sensor_is_read(tmp_path: Path) -> None:
    sounder = fx.echosounder_messages(rangefinder=False, forward=False)
    second = [
        dataclasses.replace(s, time_us=s.time_us + 5, msg=distance_sensor(1234, sensor_id=3))
        for s in sounder
    ]
    nav = read_nav_log(
        fx.write_tlog(tmp_path / "x.tlog", fx.by_time(fx.ardupilot_messages(), sounder, second))
    )
    assert nav.ranges == expected_soundings(sounder)


def test_sounding_stamps_glitches_dropped_and_steps_back_sorted(tmp_path: Path) -> None:
    sounder = fx.echosounder_messages(rangefinder=False, forward=False)
    messages = fx.by_time(fx.ardupilot_messages(), sounder)
    good = [sounder[k] for k in range(30) if fx.no_reading(k) is None]
    # In file order: one stamp damaged (ten years on), one stepped back 0.35 s.
    for sent, shift_us in ((good[4], 10 * 365 * 86400 * 10**6), (good[8], -350_000)):
        index = messages.index(sent)
        messages[index] = dataclasses.replace(sent, time_us=sent.time_us + shift_us)
    nav = read_nav_log(fx.write_tlog(tmp_path / "x.tlog", messages))
    assert nav.report.bad_timestamps == 1 and nav.report.time_backwards >= 1
    assert len(nav.ranges) == len(good) - 1
    times = [s.time for s in nav.ranges]
    assert times == sorted(times)
    assert max(times) < fx.T0_US / 1e6 + 10


# --- DataFlash ------------------------------------------------------------------------------


def dfreader_soundings(path: Path) -> list[RangeSample]:
    """The soundings pymavlink's own DataFlash reader gives, converted by ours."""
    log = DFReader.DFReader_binary(str(path))
    out: list[RangeSample] = []
    first: int | None = None
    while (msg := log.recv_msg()) is not None:
        if msg.get_type() == "RFND":
            for instance, sample in convert.ranges_from_dataflash(msg, msg._timestamp):
                first = instance if first is None else first
                if instance == first and sample is not None:
                    out.append(sample)
    return out


@pytest.mark.parametrize("layout", list(fx.RFND_LAYOUTS))
def test_dataflash_rfnd_soundings(tmp_path: Path, layout: str) -> None:
    path = fx.ardupilot_dataflash(rfnd=layout).save(tmp_path / "00000001.BIN")
    nav = read_nav_log(path)
    assert nav.range_source == "RFND"
    assert len(nav.ranges) == 30 - sum(fx.rfnd_bad(k) for k in range(30))
    assert nav.ranges == dfreader_soundings(path)
    # Against the truth: the time base and the depth under the boat (the forward sensor's
    # 7.5 m never).
    gps_us = 5_000_000 + 400_000 + 30
    time_base = fx.gps_unix_time(fx.GPS_WEEK, fx.GPS_MS_AT_BOOT + gps_us // 1000) - gps_us * 1e-6
    for sample in nav.ranges:
        truth = fx.Truth(sample.time - time_base - 5.00004)
        assert sample.distance_m == pytest.approx(truth.depth_m, abs=0.006)
    quality = "Quality" in fx.RFND_LAYOUTS[layout][1]
    assert {s.signal_quality for s in nav.ranges} == ({80} if quality else {None})
    # The other streams are as they were.
    assert len(nav.imu) == 30 and nav.report.time_reference == "gps"


# --- summary, seamap info -------------------------------------------------------------------


def test_summary_counts_the_soundings_and_keeps_its_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sounder = fx.echosounder_messages()
    messages = fx.by_time(fx.ardupilot_messages(), sounder)
    tlog = fx.write_tlog(tmp_path / "x.tlog", messages)
    summary = summarize_nav_log(tlog)
    assert (summary["soundings"], summary["soundings_source"]) == (19, "DISTANCE_SENSOR")
    assert summary["messages"]["DISTANCE_SENSOR"] == 60 and summary["count"] == len(messages)
    bare = summarize_nav_log(fx.write_tlog(tmp_path / "bare.tlog", fx.ardupilot_messages()))
    assert (bare["soundings"], bare["soundings_source"]) == (0, None)
    assert set(bare) == set(summary)
    dataflash = summarize_nav_log(fx.ardupilot_dataflash(rfnd="quality").save(tmp_path / "x.bin"))
    assert (dataflash["soundings"], dataflash["soundings_source"]) == (26, "RFND")

    assert main(["info", str(tlog), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    for key in ("kind", "count", "first_time", "last_time", "messages"):
        assert key in printed
    assert printed["soundings"] == 19
    assert main(["info", str(tlog)]) == 0
    assert "soundings:      19 (DISTANCE_SENSOR, downward)" in capsys.readouterr().out


# --- the live link ----------------------------------------------------------------------------


async def until(condition: Any, timeout_s: float = TIMEOUT_S) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not condition():
        if loop.time() > deadline:
            raise TimeoutError("condition not met in time")
        await asyncio.sleep(0.02)


def run_link(tlog: Path, **link_options: Any) -> tuple[list[Any], MavlinkLink, AutopilotEmulator]:
    """The tlog played by the autopilot emulator to a link on a loopback UDP port, to the
    end; what the link gave."""
    received: list[Any] = []

    async def run() -> tuple[MavlinkLink, AutopilotEmulator]:
        port = free_udp_port()
        link = MavlinkLink(f"udpin:127.0.0.1:{port}", on_sample=received.append, **link_options)
        emu = AutopilotEmulator.from_tlog(tlog, time_scale=2.0)
        async with link, emu:
            await emu.start_udp(port)
            await asyncio.wait_for(emu.done.wait(), TIMEOUT_S)
            await asyncio.sleep(0.2)
        return link, emu

    link, emu = asyncio.run(asyncio.wait_for(run(), 2 * TIMEOUT_S))
    return received, link, emu


def test_live_link_gives_the_soundings_the_log_reader_gives(tmp_path: Path) -> None:
    messages = fx.by_time(fx.ardupilot_messages(), fx.echosounder_messages())
    tlog = fx.write_tlog(tmp_path / "x.tlog", messages)
    received, link, emu = run_link(tlog)
    soundings = [s for s in received if isinstance(s, RangeSample)]
    assert no_time(soundings) == no_time(read_nav_log(tlog).ranges)
    assert len(soundings) == 19
    # Asked for at 10 Hz; the emulator thins each sensor on its own, so both sensors'
    # DISTANCE_SENSOR and the RANGEFINDER all went out (passed through the emulator).
    assert emu.client.intervals_us["DISTANCE_SENSOR"] == 100_000
    assert link.stats.requests["DISTANCE_SENSOR"].result == "accepted"
    assert (emu.sent["DISTANCE_SENSOR"], emu.sent["RANGEFINDER"]) == (60, 30)
    assert link.stats.counts["DISTANCE_SENSOR"] == 60


def test_live_link_takes_rangefinder_when_there_is_no_distance_sensor(tmp_path: Path) -> None:
    messages = fx.by_time(fx.ardupilot_messages(), fx.echosounder_messages(distance_sensor=False))
    tlog = fx.write_tlog(tmp_path / "x.tlog", messages)
    received, _, _ = run_link(tlog, fallback_s=0.3)
    soundings = [s for s in received if isinstance(s, RangeSample)]
    # A fallback: taken once nothing better came for fallback_s after link up.
    assert len(soundings) >= 15
    assert {s.source for s in soundings} == {"RANGEFINDER"}
    logged = no_time(read_nav_log(tlog).ranges)
    assert no_time(soundings) == logged[len(logged) - len(soundings) :]
