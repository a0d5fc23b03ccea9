"""Oculus log files: v1 write/read (checked against oculus-python), v2 SQLite, damage."""

from __future__ import annotations

import sqlite3
import struct
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.oculus import (
    LogReadReport,
    OculusFormatError,
    OculusLogWriter,
    StatusMessage,
    build_simple_ping,
    iter_log_items,
    iter_pings,
    parse_simple_ping,
    qt_compress,
    summarize_oculus_log,
)
from mapping.samples import Ping
from tests.drivers.test_oculus_protocol import (
    REAL_PING_SIZE,
    assert_same_ping,
    make_ping,
    real_pings,
)
from tests.fuzzing import fuzz

FILE_HEADER_SIZE = 48
ITEM_HEADER_SIZE = 40
T0 = 1_700_000_000.0


def sample_pings(n: int = 3, *, gains: bool = False, version: int = 2) -> list[Ping]:
    return [
        make_ping(seed=k, ping_id=500 + k, time=T0 + 0.1 * k, gains=gains, attitude=version == 2)
        for k in range(n)
    ]


def write_log(path: Path, messages: list[tuple[bytes, float]], **kwargs: bool) -> list[int]:
    """Write a v1 log; return the file offset where each item ends."""
    ends = []
    with OculusLogWriter(path, start_time=T0) as writer:
        for message, time in messages:
            writer.write(message, time, **kwargs)
            writer.flush()
            ends.append(path.stat().st_size)
    return ends


def ping_log(path: Path, pings: list[Ping], version: int = 2) -> list[int]:
    return write_log(path, [(build_simple_ping(p, version=version), p.time) for p in pings])


def test_v1_log_round_trips_every_ping_exactly(tmp_path: Path) -> None:
    pings = sample_pings(2, version=1) + sample_pings(2, gains=True)
    versions = [1, 1, 2, 2]
    messages = [
        (build_simple_ping(p, version=v), p.time) for p, v in zip(pings, versions, strict=True)
    ]
    status = StatusMessage(device_id=3).pack()
    path = tmp_path / "a.oculus"
    write_log(path, [*messages[:2], (status, T0 + 5), *messages[2:]])
    report = LogReadReport()
    got = list(iter_pings(path, report))
    assert len(got) == len(pings)
    for read, written in zip(got, pings, strict=True):
        assert_same_ping(read, written)
    assert (report.version, report.items, report.pings) == (1, 5, 4)
    assert report.messages == {"SimplePingResult": 4, "Status": 1}
    assert not report.truncated and report.bytes_skipped == 0
    items = list(iter_log_items(path))
    assert items[2].message == status and items[2].time == T0 + 5 and items[2].item_type == 10


def test_log_layout_is_the_documented_v1_layout(tmp_path: Path) -> None:
    path = tmp_path / "a.oculus"
    message = build_simple_ping(make_ping())
    write_log(path, [(message, 12.5)])
    raw = path.read_bytes()
    magic, size, source, version, encryption, _key, created = struct.unpack_from(
        "<2I16s2H4xqd", raw
    )
    assert (magic, size, source.rstrip(b"\0"), version, encryption) == (
        0x11223344,
        48,
        b"Oculus",
        1,
        0,
    )
    assert created == T0
    item = struct.unpack_from("<2I2H4xdH2x2I4x", raw, FILE_HEADER_SIZE)
    assert item == (0xAABBCCDD, 40, 10, 1, 12.5, 0, len(message), len(message))
    assert raw[FILE_HEADER_SIZE + ITEM_HEADER_SIZE :] == message


@pytest.mark.parametrize("gains", [False, True])
def test_oculus_python_reads_our_v1_log_identically(tmp_path: Path, gains: bool) -> None:
    """The independent reader agrees on every pixel, bearing, gain, time and ping id.

    oculus-python decodes only SimplePingResult v2 (its v1 fire struct cannot be built) and
    only logs holding nothing else, so the log holds v2 8-bit pings.
    """
    # oculus-python still uses the NumPy 1 name.
    np.NAN = np.nan  # type: ignore[attr-defined]  # noqa: NPY201
    import bps_oculus.io as bps_io  # installed by the Makefile, without its GUI OpenCV

    pings = sample_pings(3, gains=gains)
    path = tmp_path / "a.oculus"
    ping_log(path, pings)
    theirs = list(bps_io.process_v1(path))
    ours = list(iter_pings(path))
    assert len(theirs) == len(ours) == len(pings)
    for (info, result, polar, _), mine, written in zip(theirs, ours, pings, strict=True):
        assert info.entryId == result.pingId == mine.ping_id == written.ping_id
        assert info.timestamp == mine.time == written.time
        np.testing.assert_array_equal(polar.polar_image, mine.image)
        np.testing.assert_allclose(polar.bearing_table, mine.bearings_rad, rtol=0, atol=1e-12)
        if gains:
            assert mine.gains is not None
            np.testing.assert_array_equal(polar.gain_table, mine.gains)
        else:
            assert mine.gains is None and np.all(np.isnan(polar.gain_table))


def test_qcompressed_items_are_read(tmp_path: Path) -> None:
    pings = sample_pings(2)
    path = tmp_path / "a.oculus"
    messages = [(build_simple_ping(p), p.time) for p in pings]
    write_log(path, messages, compress=True)
    raw = path.read_bytes()
    item = struct.unpack_from("<2I2H4xdH2x2I4x", raw, FILE_HEADER_SIZE)
    assert item[5] == 1 and item[6] == len(messages[0][0]) and item[7] < item[6]
    payload = raw[FILE_HEADER_SIZE + ITEM_HEADER_SIZE :][: item[7]]
    # Qt's qCompress: big-endian original size, then zlib.
    assert struct.unpack(">I", payload[:4])[0] == item[6]
    assert zlib.decompress(payload[4:]) == messages[0][0]
    for read, written in zip(iter_pings(path), pings, strict=True):
        assert_same_ping(read, written)


def test_bad_qcompress_data_is_skipped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "a.oculus"
    pings = sample_pings(3)
    ends = write_log(path, [(build_simple_ping(p), p.time) for p in pings], compress=True)
    raw = bytearray(path.read_bytes())
    raw[ends[0] + ITEM_HEADER_SIZE + 10] ^= 0xFF  # inside the second item's zlib stream
    path.write_bytes(raw)
    report = LogReadReport()
    assert [p.ping_id for p in iter_pings(path, report)] == [500, 502]
    assert report.skipped_items == {"bad qCompress data": 1}


def make_v2_log(path: Path, rows: list[tuple[float, bytes]]) -> None:
    """An Oculus v2 (SQLite) log with the documented tables."""
    conn = sqlite3.connect(path)
    conn.executescript(
        """
        CREATE TABLE metadata (key TEXT NOT NULL, value ANY NOT NULL);
        CREATE TABLE dataSources (dataSourceId INT PRIMARY KEY, dataSourceType INT NOT NULL,
                                  dataSourceName TEXT NOT NULL);
        CREATE TABLE dataSourceProperties (dataSourceId INT, key TEXT NOT NULL,
                                           value ANY NOT NULL);
        CREATE TABLE data (entryId INTEGER PRIMARY KEY, timestamp INT NOT NULL,
                           type INT NOT NULL, dataSourceId INT, length INT NOT NULL,
                           payload BLOB NOT NULL);
        CREATE TABLE resources (name TEXT NOT NULL, payload BLOB NOT NULL);
        CREATE TABLE bookmarks (bookmarkId INT, title TEXT NOT NULL, comments TEXT);
        INSERT INTO metadata VALUES ('logVersion', 2);
        INSERT INTO dataSources VALUES (0, 0, 'Oculus');
        """
    )
    conn.executemany(
        "INSERT INTO data VALUES (?, ?, 1, 0, ?, ?)",
        [(k, round(t * 1000), len(p), p) for k, (t, p) in enumerate(rows)],
    )
    conn.commit()
    conn.close()


def test_v2_sqlite_log_is_read_exactly(tmp_path: Path) -> None:
    real = real_pings()
    real_messages = [real[k * REAL_PING_SIZE : (k + 1) * REAL_PING_SIZE] for k in range(3)]
    pings = sample_pings(3)
    built = [build_simple_ping(p) for p in pings]
    rows = [
        (pings[0].time, built[0]),
        (T0 + 1, real_messages[0]),
        (pings[1].time, qt_compress(built[1])),  # the payload may be compressed
        (T0 + 2, StatusMessage().pack()),
        (T0 + 3, real_messages[1]),
        (pings[2].time, zlib.compress(built[2])),
        (T0 + 4, b"not an oculus message"),
        (T0 + 5, real_messages[2]),
    ]
    path = tmp_path / "v2.oculus"
    make_v2_log(path, rows)
    report = LogReadReport()
    got = list(iter_pings(path, report))
    assert [p.ping_id for p in got] == [500, 415323, 501, 415324, 502, 415325]
    for read, written in zip(got[0::2], pings, strict=True):
        # v2 stores milliseconds: the time survives to the millisecond.
        assert read.time == round(written.time * 1000) / 1000
        assert_same_ping(read, replace(written, time=read.time))
    for k, read in enumerate(got[1::2]):
        assert read.time == T0 + 1 + 2 * k
        assert_same_ping(read, parse_simple_ping(real_messages[k], read.time))
    assert report.version == 2 and report.items == 7 and report.pings == 6
    assert report.skipped_items == {"undecodable payload": 1}
    summary = summarize_oculus_log(path)
    assert summary["format"] == "oculus-v2" and summary["count"] == 6
    assert summary["beams"] == [64, 256] and summary["ranges"] == [50, 703]


def test_a_cut_v2_log_reads_what_it_can_and_never_raises(tmp_path: Path) -> None:
    path = tmp_path / "v2.oculus"
    pings = [make_ping(n_beams=16, n_ranges=8, seed=k, ping_id=k) for k in range(40)]
    make_v2_log(path, [(float(k), build_simple_ping(p)) for k, p in enumerate(pings)])
    data = path.read_bytes()
    cut_file = tmp_path / "cut.oculus"
    for cut in range(16, len(data), len(data) // 9):
        cut_file.write_bytes(data[:cut])
        report = LogReadReport()
        got = list(iter_pings(cut_file, report))
        assert report.truncated or len(got) == len(pings), cut
        assert [p.ping_id for p in got] == list(range(len(got)))


def test_sqlite_file_without_data_table_is_not_a_log(tmp_path: Path) -> None:
    path = tmp_path / "other.db"
    conn = sqlite3.connect(path)
    conn.execute("CREATE TABLE t (x INT)")
    conn.commit()
    conn.close()
    with pytest.raises(OculusFormatError, match="not a v2 log"):
        list(iter_pings(path))


def test_non_log_files_raise_a_one_line_error(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_bytes(b"hello, this is not sonar data\n")
    with pytest.raises(OculusFormatError, match="not an Oculus log") as err:
        iter_log_items(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)
    with pytest.raises(OculusFormatError, match="not an Oculus log"):
        summarize_oculus_log(path)
    with pytest.raises(OculusFormatError, match="cannot read"):
        iter_log_items(tmp_path / "missing.oculus")


def _cut_points(ends: list[int]) -> list[int]:
    """Cuts in the file header, in each item header and through each payload."""
    cuts = [0, 1, 3, 4, 20, 47]
    start = FILE_HEADER_SIZE
    for end in ends:
        cuts += [start, start + 1, start + 4, start + 39]
        cuts += [*range(start + ITEM_HEADER_SIZE, end, 523), end - 1]
        start = end
    return [*cuts, ends[-1]]


def test_truncated_logs_read_the_intact_prefix(tmp_path: Path) -> None:
    pings = sample_pings(3)
    full = tmp_path / "full.oculus"
    ends = ping_log(full, pings)
    data = full.read_bytes()
    cut_file = tmp_path / "cut.oculus"
    for cut in _cut_points(ends):
        cut_file.write_bytes(data[:cut])
        report = LogReadReport()
        got = list(iter_pings(cut_file, report))
        intact = sum(end <= cut for end in ends)
        assert [p.ping_id for p in got] == [p.ping_id for p in pings[:intact]], cut
        boundary = max([end for end in ends if end <= cut], default=FILE_HEADER_SIZE)
        at_boundary = cut in ends or cut == FILE_HEADER_SIZE
        assert report.truncated == (not at_boundary), cut
        assert report.bytes_unread == (cut - boundary if cut >= FILE_HEADER_SIZE else cut), cut
        assert report.bytes_skipped == 0 and report.corrupt_pings == 0
        summary = summarize_oculus_log(cut_file)
        assert summary["count"] == intact and summary["truncated"] == report.truncated


def test_a_bad_item_magic_is_resynchronised_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "a.oculus"
    ends = ping_log(path, sample_pings(4))
    raw = bytearray(path.read_bytes())
    raw[ends[0] : ends[0] + 4] = b"\x00\xcc\xbb\xaa"  # the second item's magic
    path.write_bytes(raw)
    report = LogReadReport()
    assert [p.ping_id for p in iter_pings(path, report)] == [500, 502, 503]
    assert report.skipped_items == {"bad item magic": 1}
    assert report.bytes_skipped == ends[1] - ends[0]
    assert not report.truncated


@pytest.mark.parametrize("delta", [-100, -1, 1, 7, 3000])
def test_a_wrong_item_size_loses_only_that_item(tmp_path: Path, delta: int) -> None:
    path = tmp_path / "a.oculus"
    ends = ping_log(path, sample_pings(4))
    raw = bytearray(path.read_bytes())
    size_at = ends[0] + 32  # payloadSize of the second item
    struct.pack_into("<I", raw, size_at, struct.unpack_from("<I", raw, size_at)[0] + delta)
    path.write_bytes(raw)
    report = LogReadReport()
    assert [p.ping_id for p in iter_pings(path, report)] == [500, 502, 503]
    assert report.skipped_items == {"bad item size": 1}
    assert report.bytes_skipped == ends[1] - ends[0]


def test_a_corrupt_ping_is_skipped_and_counted(tmp_path: Path) -> None:
    messages = [build_simple_ping(p) for p in sample_pings(3)]
    bad = bytearray(messages[1])
    struct.pack_into("<I", bad, 89 + 105, 17)  # v2 imageSize
    path = tmp_path / "a.oculus"
    write_log(path, [(messages[0], 1.0), (bytes(bad), 2.0), (messages[2], 3.0)])
    report = LogReadReport()
    assert [p.ping_id for p in iter_pings(path, report)] == [500, 502]
    assert report.corrupt_pings == 1 and report.first_error is not None
    assert "imageSize" in report.first_error
    assert summarize_oculus_log(path)["skipped"] == {"corrupt ping": 1}


def test_writer_is_append_only_and_never_clobbers(tmp_path: Path) -> None:
    path = tmp_path / "a.oculus"
    pings = sample_pings(3)
    with OculusLogWriter(path, start_time=T0) as writer:
        writer.flush()
        before = path.read_bytes()
        for ping in pings:
            writer.write(build_simple_ping(ping), ping.time)
            writer.flush()
            now = path.read_bytes()
            assert now.startswith(before)
            before = now
            # A reader sees every flushed ping while the writer is still open.
            assert [p.ping_id for p in iter_pings(path)][-1] == ping.ping_id
        with pytest.raises(OculusFormatError):
            writer.write(build_simple_ping(pings[0])[:-1], 0.0)
    with pytest.raises(FileExistsError):
        OculusLogWriter(path)


def test_summary_describes_the_log(tmp_path: Path) -> None:
    path = tmp_path / "a.oculus"
    low = make_ping(ping_id=1, time=T0 + 3, dtype=np.uint16)
    low = replace(low, master_mode=1, frequency_hz=1.2e6)
    pings = [*sample_pings(2), low]
    messages = [(build_simple_ping(p), p.time) for p in pings]
    write_log(path, [*messages, (StatusMessage().pack(), T0 + 9)])
    summary = summarize_oculus_log(path)
    assert summary == {
        "kind": "oculus",
        "format": "oculus-v1",
        "count": 3,
        "first_time": T0,
        "last_time": T0 + 3,
        "beams": [64],
        "ranges": [50],
        "range_m": [50 * 0.0125, 50 * 0.0125],
        "modes": [1, 2],
        "frequencies_hz": [1_200_000, 2_100_000],
        "bearings_deg": [-30.0, 30.0],
        "sample_bits": [8, 16],
        "gain_rows": [False],
        "ping_versions": [2],
        "msg_versions": [2],
        "items": 4,
        "messages": {"SimplePingResult": 3, "Status": 1},
        "skipped": {},
        "bytes_skipped": 0,
        "truncated": False,
        "bytes_unread": 0,
    }


_LOG_PINGS = [make_ping(n_beams=16, n_ranges=8, seed=k, ping_id=k) for k in range(3)]


def _small_log(tmp_dir: Path) -> bytes:
    path = tmp_dir / "small.oculus"
    if not path.exists():
        write_log(path, [(build_simple_ping(p), float(k)) for k, p in enumerate(_LOG_PINGS)])
    return path.read_bytes()


def _read_all(path: Path) -> LogReadReport:
    """Read with every reader; only a non-log start may raise."""
    report = LogReadReport()
    try:
        pings = list(iter_pings(path, report))
        summary = summarize_oculus_log(path)
    except OculusFormatError as err:
        assert "not an Oculus log" in str(err)
        return report
    assert len(pings) == report.pings == summary["count"]
    assert report.pings <= report.items
    return report


@pytest.mark.fuzz
@fuzz(150)
@given(data=st.binary(max_size=2000))
def test_random_bytes_after_a_log_header_never_crash_the_reader(
    tmp_path: Path, data: bytes
) -> None:
    path = tmp_path / "random.oculus"
    path.write_bytes(_small_log(tmp_path)[:FILE_HEADER_SIZE] + data)
    report = _read_all(path)
    assert report.pings == 0


EDITS = st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6)
"""Bytes set anywhere in a log: (position, wrapping; value)."""
CUT = st.tuples(st.integers(0, 10**6), st.integers(0, 300))
"""A span cut out of it: (start, wrapping; length)."""


@pytest.mark.fuzz
@fuzz(150)
@given(edits=EDITS, span=CUT)
def test_mutated_logs_never_crash_the_reader(
    tmp_path: Path, edits: list[tuple[int, int]], span: tuple[int, int]
) -> None:
    path = tmp_path / "mutated.oculus"
    path.write_bytes(_mutated(_small_log(tmp_path), edits, span))
    _read_all(path)


def _mutated(log: bytes, edits: list[tuple[int, int]], span: tuple[int, int]) -> bytes:
    """``log`` with bytes set at ``edits`` (position, value; positions wrap) and then
    ``span`` (start, length) cut out."""
    raw = bytearray(log)
    for position, value in edits:
        raw[position % len(raw)] = value
    start = span[0] % len(raw)
    del raw[start : start + span[1]]
    return bytes(raw)


def _small_v2_log(tmp_dir: Path) -> bytes:
    path = tmp_dir / "small-v2.oculus"
    if not path.exists():
        make_v2_log(path, [(float(k), build_simple_ping(p)) for k, p in enumerate(_LOG_PINGS)])
    return path.read_bytes()


@pytest.mark.fuzz
@fuzz(150)
@given(edits=EDITS, span=CUT)
def test_mutated_v2_logs_never_crash_the_reader(
    tmp_path: Path, edits: list[tuple[int, int]], span: tuple[int, int]
) -> None:
    """A v2 (SQLite) log with bytes changed and a span cut anywhere, its header and pages
    included: the reader gives what it can read, or one OculusFormatError, never another
    exception (SQLite's own errors included)."""
    path = tmp_path / "mutated-v2.oculus"
    path.write_bytes(_mutated(_small_v2_log(tmp_path), edits, span))
    report = LogReadReport()
    try:
        pings = list(iter_pings(path, report))
        summarize_oculus_log(path)
    except OculusFormatError:
        return
    assert len(pings) == report.pings <= len(_LOG_PINGS)
