"""Oculus wire messages: header, Status, SimpleFire and SimplePingResult parse/build."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.errors import SeamapError
from drivers.oculus import (
    HEADER_SIZE,
    OCULUS_ID,
    FireFlags,
    MasterMode,
    MessageHeader,
    MessageId,
    OculusFormatError,
    PingRate,
    RawMessage,
    SimpleFire,
    StatusMessage,
    build_simple_ping,
    parse_message,
    parse_simple_ping,
    read_ping_info,
)
from mapping.samples import Ping
from tests.fuzzing import fuzz

DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "oculus"
REAL_PING_SIZE = 182016


def make_ping(
    *,
    n_beams: int = 64,
    n_ranges: int = 50,
    dtype: type[np.unsignedinteger] = np.uint8,
    gains: bool = False,
    seed: int = 0,
    ping_id: int = 1000,
    time: float = 1_700_000_000.25,
    attitude: bool = False,
) -> Ping:
    """A small synthetic ping with uneven bearings like the real sonar's."""
    rng = np.random.default_rng(seed)
    # Denser in the centre, as the M1200d's beams are; quantised to 1/100 degree.
    x = np.linspace(-1.0, 1.0, n_beams)
    bearings_deg = np.round(30.0 * (0.85 * x + 0.15 * x**3), 2)
    image = rng.integers(0, np.iinfo(dtype).max, (n_ranges, n_beams), dtype=dtype, endpoint=True)
    return Ping(
        time=time,
        ping_id=ping_id,
        master_mode=MasterMode.HIGH_FREQUENCY,
        frequency_hz=2_100_000.0,
        range_resolution_m=0.0125,
        bearings_rad=np.radians(bearings_deg),
        image=image,
        gains=rng.integers(1, 2**32, n_ranges).astype(np.float64) if gains else None,
        speed_of_sound_mps=1490.5,
        gain_percent=40.0,
        gamma=127,
        heading_rad=math.radians(271.5) if attitude else None,
        pitch_rad=math.radians(-3.25) if attitude else None,
        roll_rad=math.radians(1.5) if attitude else None,
    )


def assert_same_ping(got: Ping, want: Ping) -> None:
    """Equal in every pixel, bearing (to 1/100 degree), gain and field."""
    assert got.image.dtype == want.image.dtype
    np.testing.assert_array_equal(got.image, want.image)
    np.testing.assert_array_equal(
        np.rint(np.degrees(got.bearings_rad) * 100), np.rint(np.degrees(want.bearings_rad) * 100)
    )
    np.testing.assert_allclose(got.bearings_rad, want.bearings_rad, rtol=0, atol=1e-12)
    if want.gains is None:
        assert got.gains is None
    else:
        assert got.gains is not None
        np.testing.assert_array_equal(got.gains, want.gains)
    for name in ("time", "ping_id", "master_mode", "frequency_hz", "range_resolution_m"):
        assert getattr(got, name) == getattr(want, name), name
    for name in ("speed_of_sound_mps", "gain_percent", "gamma"):
        assert getattr(got, name) == getattr(want, name), name
    for name in ("heading_rad", "pitch_rad", "roll_rad"):
        expected = getattr(want, name)
        if expected is None:
            assert getattr(got, name) is None, name
        else:
            assert getattr(got, name) == pytest.approx(expected, rel=1e-12), name


def real_pings() -> bytes:
    path = DATA_DIR / "three_pings_8bit.raw"
    if not path.exists():
        pytest.skip(f"real Oculus captures not found at {DATA_DIR}")
    return path.read_bytes()


# --- header, enums, Status, SimpleFire ---------------------------------------------------


def test_header_round_trips_and_rejects_short_or_foreign_bytes() -> None:
    header = MessageHeader(0x1ED4, 7, MessageId.SIMPLE_PING_RESULT, 2, 123456, 0)
    raw = header.pack()
    assert len(raw) == HEADER_SIZE and raw[:2] == b"SO"
    assert MessageHeader.unpack(raw) == header
    assert MessageHeader.unpack(raw).message_size == 123456 + HEADER_SIZE
    with pytest.raises(OculusFormatError, match="truncated"):
        MessageHeader.unpack(raw[:15])
    with pytest.raises(OculusFormatError, match="magic"):
        MessageHeader.unpack(b"XX" + raw[2:])
    assert issubclass(OculusFormatError, SeamapError)
    assert OCULUS_ID == 0x4F53


def test_enumerations_match_the_protocol() -> None:
    assert [PingRate(i).hz for i in range(6)] == [10.0, 15.0, 40.0, 5.0, 2.0, 0.0]
    assert FireFlags.BEAMS_512 == 0x40 and FireFlags.SEND_GAIN == 4
    assert MessageId(0x23).display_name == "SimplePingResult"


def test_status_message_round_trips_in_142_bytes() -> None:
    status = StatusMessage(
        device_id=1234,
        part_number=1042,
        status=0x4003,
        firmware_version0=0x01020003,
        firmware_date0=20200101,
        ip_addr="192.168.2.4",
        ip_mask="255.255.255.0",
        connected_ip="192.168.2.1",
        mac=bytes([0x00, 0x1B, 0x2C, 0x3D, 0x4E, 0x5F]),
        temperatures=(21.5, 22.0, 23.25, 24.0, 25.0, 26.0, 27.0, 28.0),
        pressure=1.013,
        src_device_id=1234,
    )
    raw = status.pack()
    assert len(raw) == 142
    # The address travels in network order: its first octet is the first byte.
    assert raw[16 + 36 : 16 + 40] == bytes([192, 168, 2, 4])
    assert StatusMessage.unpack(raw) == status
    assert parse_message(raw) == status
    with pytest.raises(OculusFormatError, match="truncated"):
        StatusMessage.unpack(raw[:100])


@pytest.mark.parametrize(("version", "size"), [(1, 53), (2, 89)])
def test_simple_fire_round_trips_in_53_or_89_bytes(version: int, size: int) -> None:
    fire = SimpleFire(
        version=version,
        master_mode=MasterMode.LOW_FREQUENCY,
        ping_rate=PingRate.HZ15,
        gamma=150,
        flags=int(FireFlags.RANGE_IN_METRES | FireFlags.DATA_16BIT),
        range_m=25.0,
        gain_percent=60.0,
        salinity=35.0,
        ext_flags=0b1000 if version == 2 else 0,
        src_device_id=0,
        dst_device_id=0x1ED4,
    )
    raw = fire.pack()
    assert len(raw) == size == fire.size
    header = MessageHeader.unpack(raw)
    assert (header.msg_id, header.msg_version, header.message_size) == (0x15, version, size)
    assert SimpleFire.unpack(raw) == fire
    assert parse_message(raw) == fire


def test_other_messages_stay_raw() -> None:
    dummy = MessageHeader(0x1ED4, 0, MessageId.DUMMY, 0, 0).pack()
    assert parse_message(dummy) == RawMessage(MessageHeader.unpack(dummy), b"")
    config = MessageHeader(0, 0x1ED4, MessageId.USER_CONFIG, 0, 12).pack() + bytes(range(12))
    parsed = parse_message(config)
    assert isinstance(parsed, RawMessage) and parsed.payload == bytes(range(12))


# --- real M1200d pings --------------------------------------------------------------------


def test_real_pings_parse_with_their_quirks() -> None:
    data = real_pings()
    assert len(data) == 3 * REAL_PING_SIZE
    for k in range(3):
        message = data[k * REAL_PING_SIZE : (k + 1) * REAL_PING_SIZE]
        ping = parse_simple_ping(message, 100.0 + k)
        assert ping.ping_id == 415323 + k
        assert (ping.n_beams, ping.n_ranges) == (256, 703)
        assert ping.extra["msg_version"] == 0 and ping.extra["layout_version"] == 1
        assert ping.extra["ping_rate"] == 195  # the garbage echo: tolerated, kept raw
        assert ping.master_mode == MasterMode.HIGH_FREQUENCY
        assert ping.frequency_hz == pytest.approx(2.1e6, rel=0.01)
        assert ping.max_range_m == pytest.approx(2.0, rel=0.01)
        assert ping.gains is None and ping.heading_rad is None
        assert ping.image.dtype == np.uint8
        # The image is the bytes at imageOffset, range-major.
        offset = struct.unpack_from("<I", message, 53 + 57)[0]
        assert offset == 2048
        raw_image = np.frombuffer(message, np.uint8, 703 * 256, offset).reshape(703, 256)
        np.testing.assert_array_equal(ping.image, raw_image)
        degrees = np.degrees(ping.bearings_rad)
        assert np.all(np.diff(degrees) > 0)
        assert degrees[0] == pytest.approx(-30.0, abs=0.05)
        assert degrees[-1] == pytest.approx(30.0, abs=0.05)
        step = np.diff(degrees)
        assert step[0] == pytest.approx(0.26, abs=0.006)
        assert step[-1] == pytest.approx(0.26, abs=0.006)
        assert step[120:136].mean() == pytest.approx(0.22, abs=0.006)


def test_one_ping_capture_matches_the_first_of_three() -> None:
    path = DATA_DIR / "one_ping_8bit.raw"
    if not path.exists():
        pytest.skip(f"real Oculus captures not found at {DATA_DIR}")
    ping = parse_simple_ping(path.read_bytes(), 0.0)
    assert (ping.ping_id, ping.n_beams, ping.n_ranges) == (415323, 256, 703)


def test_rebuilding_a_real_ping_reproduces_its_bytes() -> None:
    """The builder writes what the sonar wrote, except the undefined padding before the image."""
    message = real_pings()[:REAL_PING_SIZE]
    ping = parse_simple_ping(message, 0.0)
    rebuilt = build_simple_ping(ping, version=1, msg_version=0, ping_rate=195)
    assert len(rebuilt) == len(message)
    bearing_end = 122 + 2 * 256
    assert rebuilt[:bearing_end] == message[:bearing_end]
    assert rebuilt[2048:] == message[2048:]


# --- build/parse round trips ---------------------------------------------------------------


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("gains", [False, True])
def test_build_parse_round_trip(version: int, dtype: type[np.unsignedinteger], gains: bool) -> None:
    ping = make_ping(n_beams=256, dtype=dtype, gains=gains, attitude=version == 2, seed=version)
    message = build_simple_ping(ping, version=version)
    info = read_ping_info(message)
    assert info.version == version and info.header.msg_version == version
    assert len(message) == info.message_size == info.image_offset + info.image_size
    assert info.has_gain_rows == gains
    flags = FireFlags(info.fire.flags)
    assert (FireFlags.SEND_GAIN in flags) == gains
    assert (FireFlags.DATA_16BIT in flags) == (dtype == np.uint16)
    assert FireFlags.BEAMS_512 not in flags
    assert_same_ping(parse_simple_ping(message, ping.time), ping)


@pytest.mark.parametrize("version", [1, 2])
def test_512_beam_round_trip(version: int) -> None:
    ping = make_ping(n_beams=512, n_ranges=40, gains=True, dtype=np.uint16)
    message = build_simple_ping(ping, version=version)
    assert FireFlags.BEAMS_512 in FireFlags(read_ping_info(message).fire.flags)
    assert_same_ping(parse_simple_ping(message, ping.time), ping)


def test_round_trip_keeps_extra_fields() -> None:
    ping = parse_simple_ping(build_simple_ping(make_ping(attitude=True), version=2), 5.0)
    again = parse_simple_ping(build_simple_ping(ping, version=2), 5.0)
    assert again.extra == ping.extra
    assert_same_ping(again, ping)


def test_gain_rows_can_be_forced_or_dropped() -> None:
    ping = make_ping(gains=True)
    without = parse_simple_ping(build_simple_ping(ping, send_gain=False), 0.0)
    assert without.gains is None
    np.testing.assert_array_equal(without.image, ping.image)
    unity = parse_simple_ping(build_simple_ping(make_ping(), send_gain=True), 0.0)
    assert unity.gains is not None and np.all(unity.gains == 1.0)


@pytest.mark.parametrize(("built", "claimed"), [(1, 0), (1, 2), (2, 1), (2, 0)])
def test_layout_is_decided_by_sizes_not_msg_version(built: int, claimed: int) -> None:
    ping = make_ping(attitude=built == 2)
    message = build_simple_ping(ping, version=built, msg_version=claimed)
    parsed = parse_simple_ping(message, ping.time)
    assert parsed.extra["layout_version"] == built and parsed.extra["msg_version"] == claimed
    assert_same_ping(parsed, ping)


def _patched(message: bytes, offset: int, fmt: str, value: int) -> bytes:
    out = bytearray(message)
    struct.pack_into(fmt, out, offset, value)
    return bytes(out)


def test_inconsistent_pings_raise_a_one_line_error_naming_the_field() -> None:
    message = build_simple_ping(make_ping(), version=1)
    tail = 53  # the v1 ping fields start after the fire message
    cases = {
        "imageSize": _patched(message, tail + 61, "<I", 1234),
        "messageSize": _patched(message, tail + 65, "<I", 99),
        "dataSize": _patched(message, tail + 44, "<B", 7),
        "not 0x23": _patched(message, 6, "<H", 0x22),
    }
    for needle, bad in cases.items():
        with pytest.raises(OculusFormatError, match=needle) as err:
            parse_simple_ping(bad, 0.0)
        assert "\n" not in str(err.value)
    with pytest.raises(OculusFormatError, match="truncated"):
        parse_simple_ping(message[:-1], 0.0)


def test_24_bit_pings_are_reported_unsupported() -> None:
    ping = make_ping(n_beams=4, n_ranges=3)
    message = bytearray(build_simple_ping(ping, version=1))
    info = read_ping_info(message)
    image = bytes(3 * 4 * 3)  # 24-bit: 3 bytes per sample
    struct.pack_into("<B", message, 53 + 44, 2)
    struct.pack_into("<II", message, 53 + 61, len(image), info.image_offset + len(image))
    struct.pack_into("<I", message, 10, info.image_offset + len(image) - HEADER_SIZE)
    message = message[: info.image_offset] + image
    with pytest.raises(OculusFormatError, match="24-bit samples unsupported"):
        parse_simple_ping(bytes(message), 0.0)


_VALID_PING = build_simple_ping(make_ping(n_beams=16, n_ranges=8, gains=True), version=2)


@pytest.mark.fuzz
@fuzz(150)
@given(
    edits=st.lists(
        st.tuples(st.integers(0, len(_VALID_PING) - 1), st.integers(0, 255)), max_size=8
    ),
    cut=st.integers(0, len(_VALID_PING)),
)
def test_mutated_pings_raise_only_oculus_format_error(
    edits: list[tuple[int, int]], cut: int
) -> None:
    message = bytearray(_VALID_PING)
    # Bias edits to the fixed struct, where they matter most.
    for position, value in edits:
        message[position % 220] = value
    try:
        ping = parse_simple_ping(bytes(message[: max(cut, 16)]), 0.0)
    except OculusFormatError:
        return
    assert ping.image.shape == (ping.n_ranges, ping.n_beams)
