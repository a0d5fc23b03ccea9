"""Oculus log files: v1 (``.oculus`` binary) write and read, v2 (SQLite) read, raw network
captures read, summary.

v1: a 48-byte RmLogHeader ``<2I16s2H4xqd`` (magic 0x11223344, header size, source
"Oculus", version 1, encryption, key, creation time), then items: a 40-byte RmLogItem
``<2I2H4xdH2x2I4x`` (magic 0xAABBCCDD, header size, type 10 = Oculus sonar, version, time
in UNIX s, compression 0 none / 1 Qt qCompress, originalSize, payloadSize) followed by one
raw network message. v2: SQLite, table ``data(entryId, timestamp ms, type, dataSourceId,
length, payload)``. Raw capture: Oculus network messages one after another as the sonar
sent them, no log framing and no receipt times (liboculus's and driver tools' recordings, a
TCP stream's bytes); framed as a live link is (``OculusFramer``), its pings stamped from a
``CaptureClock`` the user gives. The readers stream (one item in memory at a time), never raise on
damage after the first bytes, and account for what they could not read in a
``LogReadReport``.
"""

from __future__ import annotations

import math
import sqlite3
import struct
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from drivers.oculus.framer import OculusFramer, header_is_plausible
from drivers.oculus.ping import PingInfo, parse_simple_ping, read_ping_info
from drivers.oculus.protocol import (
    HEADER_SIZE,
    OCULUS_MAGIC,
    DataSize,
    MessageHeader,
    MessageId,
    OculusFormatError,
    message_name,
)
from mapping.samples import Ping

RAW_CAPTURE = 0
"""``LogReadReport.version`` of a raw network capture (no log framing)."""
V1_FILE_MAGIC = 0x11223344
V1_ITEM_MAGIC = 0xAABBCCDD
ITEM_TYPE_OCULUS = 10
COMPRESSION_NONE = 0
COMPRESSION_QT = 1
MAX_ITEM_PAYLOAD = 64 * 1024 * 1024
_FILE_HEADER = struct.Struct("<2I16s2H4xqd")
_ITEM_HEADER = struct.Struct("<2I2H4xdH2x2I4x")
_FILE_MAGIC_BYTES = struct.pack("<I", V1_FILE_MAGIC)
_ITEM_MAGIC_BYTES = struct.pack("<I", V1_ITEM_MAGIC)
_SQLITE_MAGIC = b"SQLite format 3\x00"
_SCAN_CHUNK = 1 << 20
_QT_SIZE = struct.Struct(">I")

assert _FILE_HEADER.size == 48
V1_FILE_HEADER_SIZE = _FILE_HEADER.size
"""Bytes of a v1 log's file header: a log no longer than this holds no item."""
assert _ITEM_HEADER.size == 40

PathLike = str | Path


def qt_compress(data: bytes) -> bytes:
    """Qt ``qCompress``: 4-byte big-endian original size, then a zlib stream."""
    return _QT_SIZE.pack(len(data)) + zlib.compress(data)


def qt_uncompress(data: bytes, max_size: int = MAX_ITEM_PAYLOAD) -> bytes | None:
    """Qt ``qUncompress``; None when the data is not a sound qCompress block."""
    if len(data) < _QT_SIZE.size:
        return None
    (size,) = _QT_SIZE.unpack_from(data)
    if size > max_size:
        return None
    try:
        # max_length bounds memory even if the zlib stream is hostile.
        out = zlib.decompressobj().decompress(data[_QT_SIZE.size :], size + 1)
    except zlib.error:
        return None
    return out if len(out) == size else None


@dataclass
class LogItem:
    """One logged record: receive time (UNIX s), the payload (a raw Oculus message for
    sonar items) and the item type (v1 RmLogItem type, 10 = Oculus; v2 ``data.type``)."""

    time: float
    message: bytes
    item_type: int


@dataclass
class LogReadReport:
    """What a reader got out of a log and what it had to leave.

    version: 1 or 2 (``.oculus`` v1 or v2), ``RAW_CAPTURE`` (0) for a network capture.
    skipped_items: items not delivered, by reason. bytes_skipped: bytes passed over to
    resynchronise on the next item. truncated / bytes_unread: the file ends inside an item
    (power cut mid-write; for v2, SQLite reported a damaged file). messages: Oculus
    messages seen, by type name. corrupt_pings: SimplePingResults that failed to decode.
    """

    version: int = RAW_CAPTURE
    items: int = 0
    pings: int = 0
    skipped_items: dict[str, int] = field(default_factory=dict)
    corrupt_pings: int = 0
    bytes_skipped: int = 0
    truncated: bool = False
    bytes_unread: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    first_error: str | None = None

    @property
    def format(self) -> str:
        """What was read: "oculus-v1", "oculus-v2" or "oculus-raw" (a network capture)."""
        return "oculus-raw" if self.version == RAW_CAPTURE else f"oculus-v{self.version}"

    def skip(self, reason: str) -> None:
        self.skipped_items[reason] = self.skipped_items.get(reason, 0) + 1

    def corrupt(self, error: str) -> None:
        self.corrupt_pings += 1
        if self.first_error is None:
            self.first_error = error


class OculusLogWriter:
    """Write a v1 ``.oculus`` log, append-only: a crash leaves a readable prefix.

    Refuses to replace an existing file unless ``overwrite``. ``start_time``: the file
    header's creation time (UNIX s, default now).
    """

    def __init__(
        self, path: PathLike, *, start_time: float | None = None, overwrite: bool = False
    ) -> None:
        self.path = Path(path)
        self.items_written = 0
        self._file: BinaryIO = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115
        created = time.time() if start_time is None else start_time
        self._file.write(
            _FILE_HEADER.pack(V1_FILE_MAGIC, _FILE_HEADER.size, b"Oculus", 1, 0, 0, created)
        )

    def write(self, message: bytes, time: float, *, compress: bool = False) -> None:
        """Append one Oculus message received at ``time`` (UNIX s) as an RmLogItem type 10.

        ``compress`` stores it Qt-qCompressed (compression 1). OculusFormatError if
        ``message`` is not one whole Oculus message.
        """
        message = bytes(message)
        header = MessageHeader.unpack(message)
        if header.message_size != len(message):
            raise OculusFormatError(
                f"log item: message is {len(message)} bytes, its header says {header.message_size}"
            )
        payload = qt_compress(message) if compress else message
        item = _ITEM_HEADER.pack(
            V1_ITEM_MAGIC,
            _ITEM_HEADER.size,
            ITEM_TYPE_OCULUS,
            1,
            time,
            COMPRESSION_QT if compress else COMPRESSION_NONE,
            len(message),
            len(payload),
        )
        # One write per item keeps the file a sequence of whole items as far as possible.
        self._file.write(item + payload)
        self.items_written += 1

    def flush(self) -> None:
        """Push buffered items to the operating system."""
        self._file.flush()

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> OculusLogWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _detect_version(path: Path) -> int:
    try:
        with open(path, "rb") as f:
            start = f.read(len(_SQLITE_MAGIC))
    except OSError as e:
        raise OculusFormatError(f"{path}: cannot read ({e.strerror})") from e
    if start.startswith(_SQLITE_MAGIC):
        return 2
    # A file cut inside the 4-byte magic (even an empty one) is a truncated v1 log.
    if start[:4] == _FILE_MAGIC_BYTES or (len(start) < 4 and _FILE_MAGIC_BYTES.startswith(start)):
        return 1
    if is_raw_capture_start(start) or _frames_a_message(path):
        return RAW_CAPTURE
    raise OculusFormatError(
        f"{path}: not an Oculus log or capture (starts with {start[:8].hex(' ')}, expected "
        "44 33 22 11 (.oculus v1), 'SQLite format 3' (.oculus v2) or an Oculus message "
        "header 53 4F (a raw capture))"
    )


CAPTURE_SCAN = 4 << 20
"""Bytes of a file searched for a whole Oculus message when it does not start with one (a
capture begun mid-message: a ping is up to a few hundred kB)."""


def _frames_a_message(path: Path) -> bool:
    """Whether the framer finds a whole, recognised Oculus message (a plausible header
    and, for a ping, a fixed part whose sizes agree) in the file's first CAPTURE_SCAN
    bytes: the capture of a stream joined mid-message."""
    framer = OculusFramer()
    try:
        with open(path, "rb") as f:
            remaining = CAPTURE_SCAN
            while remaining > 0:
                chunk = f.read(min(_SCAN_CHUNK, remaining))
                if chunk:
                    framer.feed(chunk)
                else:
                    framer.flush()
                if framer.messages_out > framer.messages_unrecognised:
                    return True
                if not chunk:
                    return False
                remaining -= len(chunk)
    except OSError:
        return False
    return False


def is_raw_capture(path: PathLike) -> bool:
    """Whether a file is a raw network capture (module doc): it starts with a plausible
    Oculus message header, or holds a whole recognised message within its first
    ``CAPTURE_SCAN`` bytes (a capture joined mid-message)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(HEADER_SIZE)
    except OSError:
        return False
    return is_raw_capture_start(head) or _frames_a_message(path)


def is_raw_capture_start(head: bytes) -> bool:
    """Whether a file's first 16 bytes are a plausible Oculus message header (the start of
    a raw network capture): the magic, a known msgId and a size that fits it."""
    if len(head) < HEADER_SIZE or head[:2] != OCULUS_MAGIC:
        return False
    return header_is_plausible(MessageHeader.unpack(head[:HEADER_SIZE]))


def iter_log_items(path: PathLike, report: LogReadReport | None = None) -> Iterator[LogItem]:
    """Stream the items of a v1 or v2 Oculus log, told apart by the first bytes.

    Raises OculusFormatError at once if the file is not an Oculus log; damage further on
    is counted in ``report`` instead.
    """
    path = Path(path)
    report = LogReadReport() if report is None else report
    report.version = _detect_version(path)
    if report.version == 2:
        return _iter_v2(path, _v2_query(path), report)
    if report.version == RAW_CAPTURE:
        return _iter_raw(path, report)
    return _iter_v1(path, report)


def _iter_raw(path: Path, report: LogReadReport) -> Iterator[LogItem]:
    """The messages of a raw capture, framed as a live link's bytes are (garbage and cut
    messages skipped and counted); each item's time is NaN (a capture has none)."""
    framer = OculusFramer()
    with open(path, "rb") as f:
        while True:
            chunk = f.read(_SCAN_CHUNK)
            messages = framer.feed(chunk) if chunk else framer.flush()
            for message in messages:
                report.items += 1
                report.bytes_skipped = framer.bytes_skipped
                yield LogItem(math.nan, message, ITEM_TYPE_OCULUS)
            if not chunk:
                break
    report.bytes_skipped = framer.bytes_skipped
    if framer.pending_bytes:
        # The capture ends inside a message: its head is all there is.
        report.truncated, report.bytes_unread = True, framer.pending_bytes


def _scan_for_item(f: BinaryIO, start: int) -> int | None:
    """File offset of the next item magic at or after ``start``, None if there is none."""
    pos = start
    while True:
        f.seek(pos)
        chunk = f.read(_SCAN_CHUNK)
        found = chunk.find(_ITEM_MAGIC_BYTES)
        if found >= 0:
            return pos + found
        if len(chunk) < _SCAN_CHUNK:
            return None
        pos += len(chunk) - (len(_ITEM_MAGIC_BYTES) - 1)


def _decode_v1_payload(payload: bytes, compression: int) -> tuple[bytes | None, str]:
    """The message in an item payload, or None and why not."""
    if compression == COMPRESSION_NONE:
        return payload, ""
    if compression == COMPRESSION_QT:
        message = qt_uncompress(payload)
        return message, "" if message is not None else "bad qCompress data"
    return None, f"compression {compression}"


def _is_whole_message(message: bytes) -> bool:
    return (
        message[:2] == OCULUS_MAGIC
        and len(message) >= HEADER_SIZE
        and MessageHeader.unpack(message).message_size == len(message)
    )


@dataclass
class _V1Read:
    """The outcome of reading the v1 item at one file offset."""

    status: str  # "item", "eof", "truncated" or "bad"
    reason: str = ""  # why the item is bad or was not delivered
    item: LogItem | None = None
    next_pos: int = 0
    unread: int = 0


def _read_v1_item(f: BinaryIO, pos: int) -> _V1Read:
    f.seek(pos)
    raw = f.read(_ITEM_HEADER.size)
    if not raw:
        return _V1Read("eof")
    if len(raw) < _ITEM_HEADER.size and _ITEM_MAGIC_BYTES.startswith(raw[:4]):
        return _V1Read("truncated", unread=len(raw))
    if len(raw) < _ITEM_HEADER.size or raw[:4] != _ITEM_MAGIC_BYTES:
        return _V1Read("bad", "bad item magic")
    _, size, item_type, _, stamp, compression, _, payload_size = _ITEM_HEADER.unpack(raw)
    if size != _ITEM_HEADER.size or payload_size > MAX_ITEM_PAYLOAD:
        return _V1Read("bad", "bad item header")
    payload = f.read(payload_size)
    if len(payload) < payload_size:
        # A short payload is a cut file, unless payloadSize is corrupt and items follow.
        if _ITEM_MAGIC_BYTES in payload:
            return _V1Read("bad", "bad item size")
        return _V1Read("truncated", unread=_ITEM_HEADER.size + len(payload))
    after = f.read(len(_ITEM_MAGIC_BYTES))
    message, reason = _decode_v1_payload(payload, compression)
    # Trust payloadSize when the next item starts right after the payload (or the file
    # ends there), or when the payload is itself one whole Oculus message.
    framed = _ITEM_MAGIC_BYTES.startswith(after)
    sound = message is not None and (item_type != ITEM_TYPE_OCULUS or _is_whole_message(message))
    if not (framed or sound):
        return _V1Read("bad", "bad item size")
    item = None if message is None else LogItem(stamp, message, item_type)
    return _V1Read("item", reason, item, pos + _ITEM_HEADER.size + payload_size)


def _iter_v1(path: Path, report: LogReadReport) -> Iterator[LogItem]:
    with open(path, "rb") as f:
        head = f.read(_FILE_HEADER.size)
        if len(head) < _FILE_HEADER.size:
            report.truncated, report.bytes_unread = True, len(head)
            return
        header_size = _FILE_HEADER.unpack(head)[1]
        # A longer header is skipped whole; a nonsensical size is ignored.
        pos = header_size if _FILE_HEADER.size < header_size <= 4096 else _FILE_HEADER.size
        resyncing = False
        while True:
            result = _read_v1_item(f, pos)
            if result.status == "eof":
                return
            if result.status == "truncated":
                report.truncated, report.bytes_unread = True, result.unread
                return
            if result.status == "bad":
                if not resyncing:  # one lost item per run of skipped bytes
                    report.skip(result.reason)
                resyncing = True
                found = _scan_for_item(f, pos + 1)
                end = f.seek(0, 2) if found is None else found
                report.bytes_skipped += end - pos
                if found is None:
                    return
                pos = found
                continue
            resyncing = False
            pos = result.next_pos
            if result.item is None:
                report.skip(result.reason)
                continue
            report.items += 1
            yield result.item


def _v2_query(path: Path) -> str:
    """The SELECT that streams the data table; OculusFormatError if there is none."""
    try:
        conn = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True)
    except sqlite3.Error as e:
        raise OculusFormatError(f"{path}: cannot open the SQLite log ({e})") from e
    # A damaged file can hold invalid UTF-8 (in text and even in SQLite's error messages).
    conn.text_factory = bytes
    try:
        rows = conn.execute("PRAGMA table_info(data)").fetchall()
        columns = {bytes(row[1]).decode("utf-8", "replace") for row in rows}
    except (sqlite3.Error, UnicodeDecodeError):
        columns = {"timestamp", "type", "payload", "entryId"}  # damaged: _iter_v2 reports it
    finally:
        conn.close()
    if not {"timestamp", "payload"} <= columns:
        raise OculusFormatError(f"{path}: SQLite file without an Oculus data table (not a v2 log)")
    item_type = "type" if "type" in columns else "0"
    order = "entryId" if "entryId" in columns else "rowid"
    return f"SELECT timestamp, {item_type}, payload FROM data ORDER BY {order}"


def _decode_v2_payload(payload: bytes) -> bytes | None:
    if payload[:2] == OCULUS_MAGIC:
        return payload
    message = qt_uncompress(payload)
    if message is None:
        try:
            message = zlib.decompressobj().decompress(payload, MAX_ITEM_PAYLOAD)
        except zlib.error:
            return None
    return message if message[:2] == OCULUS_MAGIC else None


def _iter_v2(path: Path, query: str, report: LogReadReport) -> Iterator[LogItem]:
    try:
        conn = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True)
    except sqlite3.Error as e:
        report.truncated, report.first_error = True, f"SQLite: {e}"
        return
    conn.text_factory = bytes  # see _v2_query
    try:
        # A cursor streams rows: memory holds one payload at a time.
        cursor = conn.execute(query)
        while (row := cursor.fetchone()) is not None:
            stamp, item_type, payload = row
            if not isinstance(payload, bytes) or not isinstance(stamp, int | float):
                report.skip("bad data row")
                continue
            message = _decode_v2_payload(payload)
            if message is None:
                report.skip("undecodable payload")
                continue
            report.items += 1
            yield LogItem(stamp / 1000.0, message, item_type if isinstance(item_type, int) else 0)
    except (sqlite3.Error, UnicodeDecodeError) as e:
        report.truncated, report.first_error = True, f"SQLite: {e}"
    finally:
        conn.close()


def _ping_info(item: LogItem, report: LogReadReport) -> PingInfo | None:
    """Count the item's message in ``report``; the checked PingInfo if it is a usable ping."""
    if report.version == 1 and item.item_type != ITEM_TYPE_OCULUS:
        report.skip(f"item type {item.item_type}")
        return None
    try:
        header = MessageHeader.unpack(item.message)
    except OculusFormatError:
        report.skip("not an Oculus message")
        return None
    name = message_name(header.msg_id)
    report.messages[name] = report.messages.get(name, 0) + 1
    if header.msg_id != MessageId.SIMPLE_PING_RESULT:
        return None
    try:
        info = read_ping_info(item.message)
    except OculusFormatError as e:
        report.corrupt(str(e))
        return None
    if len(item.message) < info.message_size:
        report.corrupt(f"SimplePingResult ping {info.ping_id}: truncated message")
        return None
    if info.data_size > DataSize.BITS16:
        report.corrupt(f"SimplePingResult ping {info.ping_id}: {8 * info.sample_size}-bit data")
        return None
    return info


_PING_NAME = message_name(MessageId.SIMPLE_PING_RESULT)


@dataclass(frozen=True)
class CaptureClock:
    """How a raw capture's pings are stamped (it has no receipt times): its first ping at
    ``start`` (UNIX s, the boat computer's clock, as a log's item times are), the others
    ``1 / rate_hz`` apart, or, without a rate, apart as the sonar's own clock says
    (SimplePingResult v2's pingStartTime, seconds since power-up; v1's has no documented
    unit, so a v1 capture needs the rate)."""

    start: float
    rate_hz: float | None = None

    def __post_init__(self) -> None:
        if not math.isfinite(self.start):
            raise OculusFormatError(f"capture start time must be finite, got {self.start}")
        if self.rate_hz is not None and not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise OculusFormatError(f"capture ping rate must be > 0 Hz, got {self.rate_hz}")


class _CaptureStamps:
    """A CaptureClock applied to one capture, ping by ping."""

    def __init__(self, path: Path, clock: CaptureClock) -> None:
        self.path, self.clock = path, clock
        self.first: float | None = None
        self.last = -math.inf

    def stamp(self, info: PingInfo, index: int) -> float:
        """The time of the capture's ping ``index`` (counting every SimplePingResult, the
        corrupt ones too: they hold their place in the rate's sequence); OculusFormatError
        when its clock cannot give one (a v1 ping without a rate, a clock stepping back)."""
        clock = self.clock
        if clock.rate_hz is not None:
            return clock.start + index / clock.rate_hz
        own = info.ping_start_time
        if info.version != 2 or not math.isfinite(own):
            raise OculusFormatError(
                f"{self.path}: SimplePingResult v1 pings carry no clock with a documented "
                "unit: give the capture's ping rate (--sonar-rate)"
            )
        if own < self.last:
            raise OculusFormatError(
                f"{self.path}: the sonar's clock steps back at ping {info.ping_id} "
                f"({self.last:.3f} -> {own:.3f} s since power-up: a restart); give the "
                "capture's ping rate (--sonar-rate) or split the capture there"
            )
        self.last = own
        self.first = own if self.first is None else self.first
        return clock.start + (own - self.first)


def iter_pings(
    path: PathLike, report: LogReadReport | None = None, clock: CaptureClock | None = None
) -> Iterator[Ping]:
    """The SimplePingResults of a v1 or v2 log as Pings stamped with their item time, or
    of a raw capture stamped by ``clock`` (NaN times without one).

    Corrupt pings are skipped and counted (``report.corrupt_pings``), never raised; a
    capture whose clock cannot stamp a ping raises OculusFormatError.
    """
    path = Path(path)
    report = LogReadReport() if report is None else report
    stamps: _CaptureStamps | None = None
    for item in iter_log_items(path, report):
        info = _ping_info(item, report)
        if info is None:
            continue
        when = item.time
        if report.version == RAW_CAPTURE and clock is not None:
            stamps = _CaptureStamps(path, clock) if stamps is None else stamps
            when = stamps.stamp(info, report.messages[_PING_NAME] - 1)
        try:
            ping = parse_simple_ping(item.message, when)
        except OculusFormatError as e:
            report.corrupt(str(e))
            continue
        report.pings += 1
        yield ping


def summarize_oculus_log(path: PathLike) -> dict[str, object]:
    """What a log or raw capture holds, for ``seamap info`` (JSON-ready; streams, keeps no
    image).

    count: decodable pings; first/last_time: earliest/latest ping time (UNIX s; None for a
    raw capture, which has no receipt times); range_m: [min, max] of nRanges *
    rangeResolution (metres); bearings_deg: [min, max] of the bearing tables (degrees,
    positive to starboard); frequencies_hz rounded to 1 Hz; gain_rows: whether pings carry
    the per-row gain prefix; msg_versions: the headers' msgVersion as sent (v1 pings
    often say 0), ping_versions the layouts they were read as.
    """
    report = LogReadReport()
    first_time: float | None = None
    last_time: float | None = None
    beams: set[int] = set()
    ranges: set[int] = set()
    range_m: set[float] = set()
    modes: set[int] = set()
    freqs: set[int] = set()
    bits: set[int] = set()
    layouts: set[int] = set()
    msg_versions: set[int] = set()
    gain_rows: set[bool] = set()
    bearings = [math.inf, -math.inf]
    for item in iter_log_items(path, report):
        info = _ping_info(item, report)
        if info is None:
            continue
        report.pings += 1
        if math.isfinite(item.time):
            first_time = item.time if first_time is None else min(first_time, item.time)
            last_time = item.time if last_time is None else max(last_time, item.time)
        beams.add(info.n_beams)
        ranges.add(info.n_ranges)
        range_m.add(info.n_ranges * info.range_resolution_m)
        modes.add(info.fire.master_mode)
        freqs.add(round(info.frequency_hz))
        bits.add(8 * info.sample_size)
        layouts.add(info.version)
        msg_versions.add(info.header.msg_version)
        gain_rows.add(info.has_gain_rows)
        table = struct.unpack_from(f"<{info.n_beams}h", item.message, info.struct_size)
        bearings = [min(bearings[0], min(table) / 100.0), max(bearings[1], max(table) / 100.0)]
    skipped = dict(report.skipped_items)
    if report.corrupt_pings:
        skipped["corrupt ping"] = report.corrupt_pings
    return {
        "kind": "oculus",
        "format": report.format,
        "count": report.pings,
        "first_time": first_time,
        "last_time": last_time,
        "beams": sorted(beams),
        "ranges": sorted(ranges),
        "range_m": [min(range_m), max(range_m)] if range_m else None,
        "bearings_deg": bearings if report.pings else None,
        "modes": sorted(modes),
        "frequencies_hz": sorted(freqs),
        "sample_bits": sorted(bits),
        "gain_rows": sorted(gain_rows),
        "ping_versions": sorted(layouts),
        "msg_versions": sorted(msg_versions),
        "items": report.items,
        "messages": dict(sorted(report.messages.items())),
        "skipped": skipped,
        "bytes_skipped": report.bytes_skipped,
        "truncated": report.truncated,
        "bytes_unread": report.bytes_unread,
    }
