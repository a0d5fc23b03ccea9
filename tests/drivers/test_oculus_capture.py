"""Real Oculus recordings as they come: raw network captures (the shared real M1200d
pings), ViewPoint .oculus v1 and v2 logs with 8- and 16-bit pings with and without the
gain prefix, and SimplePingResult v1 and v2 whatever msgVersion says."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.oculus import (
    LogReadReport,
    OculusFormatError,
    StatusMessage,
    build_simple_ping,
    iter_log_items,
    iter_pings,
    parse_simple_ping,
    summarize_oculus_log,
)
from drivers.oculus.logfile import RAW_CAPTURE, CaptureClock
from tests.drivers.test_oculus_logfile import CUT, EDITS, T0, _mutated, make_v2_log, write_log
from tests.drivers.test_oculus_protocol import (
    DATA_DIR,
    REAL_PING_SIZE,
    assert_same_ping,
    make_ping,
    real_pings,
)
from tests.fuzzing import fuzz

REPO = Path(__file__).resolve().parents[2]


def seamap(*args: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "seamap", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
        check=False,
    )


def test_the_real_capture_is_three_pings_with_their_bearings_range_and_8_bit_data() -> None:
    path = DATA_DIR / "three_pings_8bit.raw"
    report = LogReadReport()
    pings = list(iter_pings(path, report))
    assert report.version == RAW_CAPTURE and report.format == "oculus-raw"
    assert [p.ping_id for p in pings] == [415323, 415324, 415325]
    assert report.items == 3 and report.bytes_skipped == 0 and not report.truncated
    real = real_pings()
    for k, ping in enumerate(pings):
        # No receipt time in a capture; otherwise the ping as the message parser reads it.
        assert math.isnan(ping.time)
        message = real[k * REAL_PING_SIZE : (k + 1) * REAL_PING_SIZE]
        assert_same_ping(replace(ping, time=0.0), parse_simple_ping(message, 0.0))
        assert ping.image.dtype == np.uint8 and ping.image.shape == (703, 256)
        # Uneven bearings, about +-30 degrees (high-frequency mode's 60 degree fan).
        degrees = np.degrees(ping.bearings_rad)
        assert degrees[0] == pytest.approx(-30.0, abs=0.01)
        assert degrees[-1] == pytest.approx(30.0, abs=0.01)
        steps = np.diff(degrees)
        assert steps.min() > 0 and steps[0] > steps[128] * 1.1
        assert ping.max_range_m == pytest.approx(2.0, abs=0.01)
        assert ping.extra["msg_version"] == 0 and ping.extra["layout_version"] == 1
    summary = summarize_oculus_log(path)
    assert summary["format"] == "oculus-raw" and summary["count"] == 3
    assert summary["first_time"] is None and summary["last_time"] is None
    assert summary["beams"] == [256] and summary["ranges"] == [703]
    assert summary["sample_bits"] == [8] and summary["gain_rows"] == [False]
    assert summary["msg_versions"] == [0] and summary["ping_versions"] == [1]
    assert summary["range_m"] == pytest.approx([1.998, 1.998], abs=1e-3)
    assert summary["bearings_deg"] == pytest.approx([-30.0, 30.0], abs=0.01)


def test_seamap_info_reads_the_real_captures() -> None:
    done = seamap("info", DATA_DIR / "three_pings_8bit.raw")
    assert done.returncode == 0, done.stderr
    text = done.stdout
    assert "oculus-raw" in text and "no receipt stamps" in text
    lines = {
        line.split(":")[0].strip(): line.split(":", 1)[1].strip()
        for line in text.splitlines()[1:]
        if ":" in line
    }
    assert lines["pings"] == "3" and lines["beams"] == "[256]" and lines["ranges"] == "[703]"
    assert lines["range (m)"] == "1.998" and lines["sample bits"] == "[8]"
    assert lines["bearings (deg)"] == "-30.000 .. +30.000"
    done = seamap("info", DATA_DIR / "one_ping_8bit.raw", "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["kind"] == "oculus" and summary["count"] == 1
    assert summary["first_time"] is None and summary["sample_bits"] == [8]


def test_what_is_not_a_log_or_capture_is_one_line(tmp_path: Path) -> None:
    # An Oculus magic with an implausible header (msgId 0x99) is not a capture either.
    implausible = b"SO" + bytes([0, 0, 0, 0, 0x99, 0]) + bytes(200)
    for name, data in (("text.raw", b"not sonar data\n"), ("magic.raw", implausible)):
        path = tmp_path / name
        path.write_bytes(data)
        done = seamap("info", path)
        assert done.returncode == 2 and "Traceback" not in done.stderr
        assert len(done.stderr.strip().splitlines()) == 1
        assert "not an Oculus log or capture" in done.stderr and str(path) in done.stderr
        with pytest.raises(OculusFormatError, match="raw capture"):
            list(iter_pings(path))


def test_a_damaged_capture_loses_only_the_damage(tmp_path: Path) -> None:
    real = real_pings()
    messages = [real[k * REAL_PING_SIZE : (k + 1) * REAL_PING_SIZE] for k in range(3)]
    built = build_simple_ping(make_ping(seed=1, dtype=np.uint16, gains=True), version=2)
    data = (
        messages[0]
        + StatusMessage().pack()
        + b"\x00garbage between messages\x53"
        + built
        + messages[1][: REAL_PING_SIZE // 2]  # cut: the next message follows at once
        + messages[2]
        + built[:1000]  # the capture ends inside a message
    )
    path = tmp_path / "damaged.raw"
    path.write_bytes(data)
    report = LogReadReport()
    pings = list(iter_pings(path, report))
    assert [p.ping_id for p in pings] == [415323, 1000, 415325]
    assert pings[1].image.dtype == np.uint16 and pings[1].gains is not None
    assert report.messages == {"SimplePingResult": 3, "Status": 1}
    assert report.bytes_skipped == len(b"\x00garbage between messages\x53") + REAL_PING_SIZE // 2
    assert report.truncated and report.bytes_unread == 1000


def _capture(path: Path, pings: list[bytes]) -> Path:
    path.write_bytes(b"".join(pings))
    return path


def test_a_capture_is_stamped_by_the_clock_it_is_given(tmp_path: Path) -> None:
    own = [100.0, 100.1, 100.25, 100.3]  # v2 pingStartTime: seconds since power-up
    v2 = [
        build_simple_ping(replace(make_ping(seed=k, ping_id=k), extra={"ping_start_time": t}))
        for k, t in enumerate(own)
    ]
    path = _capture(tmp_path / "v2.raw", v2)
    start = 1_765_000_000.5
    got = [p.time for p in iter_pings(path, clock=CaptureClock(start))]
    assert got == pytest.approx([start + t - own[0] for t in own], abs=1e-9)
    got = [p.time for p in iter_pings(path, clock=CaptureClock(start, rate_hz=4.0))]
    assert got == pytest.approx([start, start + 0.25, start + 0.5, start + 0.75], abs=1e-9)
    # A corrupt ping keeps its place in the rate's sequence.
    bad = bytearray(v2[1])
    bad[161] = 7  # the v2 struct's dataSize: not 0..3
    path = _capture(tmp_path / "corrupt.raw", [v2[0], bytes(bad), v2[2], v2[3]])
    report = LogReadReport()
    got = [p.time for p in iter_pings(path, report, clock=CaptureClock(start, rate_hz=4.0))]
    assert report.corrupt_pings == 1
    assert got == pytest.approx([start, start + 0.5, start + 0.75], abs=1e-9)
    # v1 pings have no clock with a documented unit; a clock that steps back is a restart.
    v1 = [
        build_simple_ping(make_ping(seed=k, ping_id=k), version=1, msg_version=0) for k in range(2)
    ]
    with pytest.raises(OculusFormatError, match="--sonar-rate"):
        list(iter_pings(_capture(tmp_path / "v1.raw", v1), clock=CaptureClock(start)))
    back = [v2[2], v2[0]]
    with pytest.raises(OculusFormatError, match="steps back"):
        list(iter_pings(_capture(tmp_path / "back.raw", back), clock=CaptureClock(start)))
    with pytest.raises(OculusFormatError, match="rate"):
        CaptureClock(start, rate_hz=0.0)


# What real units write: ViewPoint's v1 and v2 logs, 8- and 16-bit pings, with and without
# the per-row gain prefix, v1 pings sent with msgVersion 0 (and 1), v2 with 2 (or 0/1).
VARIANTS = [
    (version, msg_version, dtype, gains)
    for version, msg_versions in ((1, (0, 1)), (2, (2, 0, 1)))
    for msg_version in msg_versions
    for dtype in (np.uint8, np.uint16)
    for gains in (False, True)
]


@pytest.mark.parametrize("log_version", [1, 2, RAW_CAPTURE])
def test_every_ping_variant_reads_exactly_from_every_container(
    tmp_path: Path, log_version: int
) -> None:
    pings = [
        make_ping(
            seed=k,
            ping_id=k,
            time=T0 + 0.1 * k,
            dtype=dtype,
            gains=gains,
            attitude=version == 2,
            n_beams=256 if k % 2 else 64,
        )
        for k, (version, _, dtype, gains) in enumerate(VARIANTS)
    ]
    messages = [
        build_simple_ping(p, version=v, msg_version=m)
        for p, (v, m, _, _) in zip(pings, VARIANTS, strict=True)
    ]
    path = tmp_path / f"log{log_version}.oculus"
    if log_version == 1:
        write_log(path, [(m, p.time) for m, p in zip(messages, pings, strict=True)])
    elif log_version == 2:
        make_v2_log(path, [(p.time, m) for m, p in zip(messages, pings, strict=True)])
    else:
        _capture(path, messages)
    report = LogReadReport()
    got = list(iter_pings(path, report))
    assert report.version == log_version and report.corrupt_pings == 0
    assert len(got) == len(VARIANTS)
    for read, written, (version, msg_version, dtype, gains) in zip(
        got, pings, VARIANTS, strict=True
    ):
        assert read.extra["layout_version"] == version and read.extra["msg_version"] == msg_version
        assert read.image.dtype == dtype and (read.gains is not None) == gains
        assert_same_ping(replace(read, time=written.time), written)
        if log_version == 1:
            assert read.time == written.time
        elif log_version == 2:
            assert read.time == round(written.time * 1000) / 1000  # milliseconds
    summary = summarize_oculus_log(path)
    assert summary["sample_bits"] == [8, 16] and summary["gain_rows"] == [False, True]
    assert summary["msg_versions"] == [0, 1, 2] and summary["ping_versions"] == [1, 2]
    assert [item.item_type for item in iter_log_items(path)] == [
        10 if log_version != 2 else 1
    ] * len(VARIANTS)


_CAPTURE_PINGS = [
    build_simple_ping(
        make_ping(n_beams=16, n_ranges=8, seed=k, ping_id=k, gains=k == 1), version=1 + k % 2
    )
    for k in range(3)
]


@pytest.mark.fuzz
@fuzz(150)
@given(edits=EDITS, span=CUT, clocked=st.booleans())
def test_mutated_captures_never_crash_the_reader(
    tmp_path: Path, edits: list[tuple[int, int]], span: tuple[int, int], clocked: bool
) -> None:
    """A raw capture with bytes changed and a span cut anywhere: the reader gives what it
    can frame, or one OculusFormatError (not a capture; a clock it cannot stamp by),
    never another exception; every ping it gives is a whole one."""
    path = tmp_path / "mutated.raw"
    path.write_bytes(_mutated(b"".join(_CAPTURE_PINGS), edits, span))
    report = LogReadReport()
    clock = CaptureClock(T0, None if clocked else 5.0)
    try:
        pings = list(iter_pings(path, report, clock))
        summarize_oculus_log(path)
    except OculusFormatError as exc:
        assert "\n" not in str(exc)
        return
    assert report.pings == len(pings) <= report.items
    for ping in pings:
        assert math.isfinite(ping.time) and ping.image.shape == (8, 16)


def test_a_capture_joined_mid_message_is_still_a_capture(tmp_path: Path) -> None:
    """A stream recorded from the middle of a ping: the tail of that ping, then whole
    messages. The file is told a capture by the first whole message in it."""
    real = real_pings()
    path = tmp_path / "joined.raw"
    path.write_bytes(real[1000:])
    report = LogReadReport()
    assert [p.ping_id for p in iter_pings(path, report)] == [415324, 415325]
    assert report.version == RAW_CAPTURE and report.bytes_skipped == REAL_PING_SIZE - 1000
    done = seamap("info", path, "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["format"] == "oculus-raw" and summary["count"] == 2
    assert summary["bytes_skipped"] == REAL_PING_SIZE - 1000
