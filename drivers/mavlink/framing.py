"""Frame MAVLink logs: find and decode .tlog frames and DataFlash messages, past damage.

A .tlog is a sequence of records: an 8-byte big-endian UNIX receive time in microseconds,
then one MAVLink 1 or 2 frame. A DataFlash .bin is a sequence of ``A3 95 <type> <fields>``
messages whose layouts are declared in-band by FMT (type 128) messages. The kind is told
by the content, not the file name.

Framing is ours, decoding is pymavlink's: each tlog frame goes through the MAVLink 2
parser's ``decode`` (CRC checked, MAVLink 1 and 2), each DataFlash message becomes a
pymavlink ``DFMessage`` (format scaling applied) on the time base of pymavlink's
``DFReaderClock_usec``, so values and times are what pymavlink gives for a healthy log.
We frame ourselves because field logs end badly: pymavlink's tlog reader picks its dialect
module from the first frame and the ``MAVLINK20`` variable (process-wide; a log starting
with MAVLink 1 loses every MAVLink 2 extension field, GPS_RAW_INT.h_acc included) and
loses the frames after a bad one; DFReader raises on a corrupt FMT, recurses once per
unreadable message and prints to stdout/stderr. Here damaged bytes are skipped and
counted, a cut-off end is reported, and reading goes on. The file is memory-mapped, not
read. What the framing met goes into a ``FramingReport`` (``navlog.NavReadReport`` is one);
turning messages into samples is ``navlog``'s job.
"""

from __future__ import annotations

import mmap
import os
import re
import struct
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from pymavlink import DFReader
from pymavlink.dialects.v20 import all as mavlink

from drivers.errors import SeamapError

Buffer = bytes | mmap.mmap


class NavLogError(SeamapError):
    """A navigation log that cannot be read at all: missing, unreadable, or not a log."""


class FramingReport(Protocol):
    """Where framing counts what it met (``navlog.NavReadReport`` is one)."""

    messages: int
    counts: dict[str, int]
    bytes_skipped: int
    bad_packets: int
    truncated: bool
    time_reference: str
    notes: list[str]


@dataclass
class ScanTally:
    """A ``FramingReport`` for scans whose counts nobody reads (look-ahead scans, and
    callers that only want the frames)."""

    messages: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    bytes_skipped: int = 0
    bad_packets: int = 0
    truncated: bool = False
    time_reference: str = "none"
    notes: list[str] = field(default_factory=list)


# --- files ---------------------------------------------------------------------------------


@contextmanager
def open_log(path: str | os.PathLike[str]) -> Iterator[tuple[Path, Buffer]]:
    """The file's bytes, memory-mapped; NavLogError for a missing or unreadable file."""
    where = Path(path)
    try:
        handle = open(where, "rb")  # noqa: SIM115 - closed below, after the mapping
    except FileNotFoundError:
        raise NavLogError(f"{where}: no such file") from None
    except IsADirectoryError:
        raise NavLogError(f"{where}: is a directory, not a MAVLink log") from None
    except OSError as exc:
        raise NavLogError(f"{where}: cannot read ({exc.strerror or exc})") from None
    with handle:
        if os.fstat(handle.fileno()).st_size == 0:
            raise NavLogError(f"{where}: empty file, not a MAVLink log")
        try:
            mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # not mappable (a pipe, a special file): read it
            yield where, handle.read()
            return
        with mapped:
            yield where, mapped


def detect_format(buf: Buffer, where: Path) -> str:
    """ "tlog" or "dataflash" from the first bytes; NavLogError for anything else."""
    if buf[:3] == b"\xa3\x95\x80":
        return "dataflash"
    # A readable record (plausible stamp, magic, good CRC) near the start makes a tlog,
    # even if the very first bytes were damaged.
    head = buf[: 65536 + _MAX_RECORD]
    if next(scan_tlog(head, ScanTally()), None) is not None:
        return "tlog"
    # Or a first record cut off by the end of the file (stamp and magic seen).
    if 9 <= len(buf) < _MAX_RECORD and _tlog_tail_is_cut(bytes(buf)):
        return "tlog"
    raise NavLogError(
        f"{where}: not a MAVLink log (neither a .tlog nor an ArduPilot DataFlash .bin)"
    )


# --- tlog framing ------------------------------------------------------------------------

_STAMP = struct.Struct(">Q")
_MAGIC = re.compile(rb"[\xfd\xfe]")
_MAX_STAMP_US = 1 << 53
"""Year 2255: a larger 'receive time' is not one (and random bytes rarely pass)."""
_MIN_RECORD = 8 + 8
"""Stamp plus the smallest MAVLink 1 frame (6-byte header, no payload, CRC)."""
_MAX_RECORD = 8 + 10 + 255 + 2 + 13
"""Stamp plus the largest MAVLink 2 frame (header, payload, CRC, signature)."""


def _frame_length(buf: Buffer, start: int) -> int | None:
    """Length of the MAVLink frame at ``start`` (its magic byte), from its header."""
    payload = buf[start + 1]
    if buf[start] == 0xFE:
        return 6 + payload + 2
    incompat = buf[start + 2]
    if incompat & ~0x01:  # only the signing flag is defined
        return None
    return 10 + payload + 2 + (13 if incompat & 0x01 else 0)


def _tlog_record(
    parser: Any, buf: Buffer, pos: int, report: FramingReport
) -> tuple[int, Any, int] | None:
    """(stamp µs, message, end offset) of a good record at ``pos``, else None."""
    stamp_us = _STAMP.unpack_from(buf, pos)[0]
    start = pos + 8
    if stamp_us >= _MAX_STAMP_US or buf[start] not in (0xFD, 0xFE):
        return None
    length = _frame_length(buf, start)
    if length is None or start + length > len(buf):
        return None
    end = start + length
    try:
        msg = parser.decode(bytearray(buf[start:end]))
    except Exception:  # pymavlink raises MAVError, and anything from a bad payload
        report.bad_packets += 1
        return None
    # No CRC check is possible for a message the dialect lacks: accept it only where the
    # next record starts right after it, close in time.
    if isinstance(msg, mavlink.MAVLink_unknown) and not _record_follows(buf, end, stamp_us):
        return None
    return stamp_us, msg, end


def _record_follows(buf: Buffer, pos: int, stamp_us: int) -> bool:
    """The file ends at ``pos`` or a record stamped within a day of ``stamp_us`` starts there."""
    if pos == len(buf):
        return True
    return (
        pos + 9 <= len(buf)
        and buf[pos + 8] in (0xFD, 0xFE)
        and abs(_STAMP.unpack_from(buf, pos)[0] - stamp_us) < 86_400_000_000
    )


def scan_tlog(buf: Buffer, report: FramingReport) -> Iterator[tuple[float, Any]]:
    """(receive time s, message) for every readable tlog record; resyncs past damage.

    Updates report.messages, bytes_skipped, bad_packets and truncated.
    """
    parser = mavlink.MAVLink(None)
    size = len(buf)
    pos = end_of_last = record_bytes = 0
    while size - pos >= _MIN_RECORD:
        record = _tlog_record(parser, buf, pos, report)
        if record is None:
            found = _MAGIC.search(buf, pos + 9)
            pos = size if found is None else found.start() - 8
            continue
        stamp_us, msg, end = record
        report.messages += 1
        record_bytes += end - pos
        pos = end_of_last = end
        msg._timestamp = stamp_us * 1.0e-6  # as pymavlink's mavlogfile stamps it
        yield msg._timestamp, msg
    tail = buf[end_of_last:]
    report.truncated = _tlog_tail_is_cut(tail)
    report.bytes_skipped = size - record_bytes - (len(tail) if report.truncated else 0)


def _tlog_tail_is_cut(tail: bytes) -> bool:
    """Whether the bytes after the last record are the start of a record cut off by EOF."""
    if not tail or len(tail) >= _MAX_RECORD:
        return False
    stamp_head = (tail[:8] + b"\0" * 8)[:8]  # a partial stamp: its known high bytes
    if _STAMP.unpack(stamp_head)[0] >= _MAX_STAMP_US:
        return False
    if len(tail) > 8 and tail[8] not in (0xFD, 0xFE):
        return False
    if len(tail) >= 11:
        length = _frame_length(tail, 8)
        return length is not None and 8 + length > len(tail)
    return True


# --- DataFlash framing -------------------------------------------------------------------

_HEAD = b"\xa3\x95"
_FMT_TYPE = 0x80
_TIME_US = struct.Struct("<Q")


class DataFlashScan:
    """Walks a DataFlash log message by message, learning formats (FMT, UNIT, MULT, FMTU)."""

    def __init__(self, buf: Buffer, report: FramingReport) -> None:
        self.buf = buf
        self.report = report
        fmt = DFReader.DFFormat(_FMT_TYPE, "FMT", 89, "BBnNZ", "Type,Length,Name,Format,Columns")
        self.formats: dict[int, Any] = {_FMT_TYPE: fmt}
        self.structs: dict[int, struct.Struct] = {_FMT_TYPE: struct.Struct(fmt.msg_struct)}
        self.units: dict[str, str] = {}
        self.mults: dict[str, float] = {}

    def messages(self) -> Iterator[tuple[Any, int]]:
        """(DFFormat, offset of the message body) for every message, in file order."""
        buf, size = self.buf, len(self.buf)
        pos = end_of_last = message_bytes = 0
        while size - pos >= 3:
            if buf[pos : pos + 2] != _HEAD:
                found = buf.find(_HEAD, pos + 1)
                pos = size if found < 0 else found
                continue
            fmt = self.formats.get(buf[pos + 2])
            if fmt is None or pos + fmt.len > size or not self._learn(fmt, pos + 3):
                pos += 1
                continue
            self.report.messages += 1
            message_bytes += fmt.len
            yield fmt, pos + 3
            pos = end_of_last = pos + fmt.len
        tail = buf[end_of_last:]
        self.report.truncated = self._tail_is_cut(tail)
        cut = len(tail) if self.report.truncated else 0
        self.report.bytes_skipped = size - message_bytes - cut

    def decode(self, fmt: Any, offset: int) -> Any:
        """The message as pymavlink's DFMessage (format multipliers applied)."""
        elements = list(self.structs[fmt.type].unpack_from(self.buf, offset))
        return DFReader.DFMessage(fmt, elements, True, None)

    def time_us(self, fmt: Any, offset: int) -> int | None:
        """The TimeUS (µs since boot) that starts nearly every message, if this one has it."""
        if fmt.columns[:1] == ["TimeUS"] and fmt.format[:1] == "Q":
            return int(_TIME_US.unpack_from(self.buf, offset)[0])
        return None

    def _learn(self, fmt: Any, offset: int) -> bool:
        """Take in a format-defining message; False if it is corrupt (then it is skipped)."""
        if fmt.name not in ("FMT", "UNIT", "MULT", "FMTU"):
            return True
        msg = self.decode(fmt, offset)
        try:
            if fmt.name == "FMT":
                return self._learn_format(msg)
            if fmt.name == "UNIT":
                self.units[chr(msg.Id)] = msg.Label
            elif fmt.name == "MULT":
                self.mults[chr(msg.Id)] = float(f"{msg.Mult:.7g}")  # as DFReader rounds it
            elif msg.FmtType in self.formats:
                described = self.formats[msg.FmtType]
                described.set_unit_ids(msg.UnitIds, self.units)
                described.set_mult_ids(msg.MultIds, self.mults)
        except Exception:  # damaged unit metadata only loses unit names
            pass
        return True

    def _learn_format(self, msg: Any) -> bool:
        if msg.Type == _FMT_TYPE:
            return True  # FMT describing itself: the layout is fixed, a change is damage
        name, chars, columns = msg.Name, msg.Format, msg.Columns
        if not name or any(c not in DFReader.FORMAT_TO_STRUCT for c in chars):
            self.report.bad_packets += 1  # DFFormat would print and raise on these
            return False
        try:
            described = DFReader.DFFormat(
                msg.Type, name, msg.Length, chars, columns, oldfmt=self.formats.get(msg.Type)
            )
        except Exception:
            described = None
        if (
            described is None
            or msg.Length != 3 + struct.calcsize(described.msg_struct)
            or len(described.columns) != len(chars)
        ):
            self.report.bad_packets += 1
            return False
        self.formats[msg.Type] = described
        self.structs[msg.Type] = struct.Struct(described.msg_struct)
        return True

    def _tail_is_cut(self, tail: bytes) -> bool:
        if not tail or not _HEAD.startswith(tail[:2]):
            return False
        if len(tail) < 3:
            return True
        fmt = self.formats.get(tail[2])
        return fmt is not None and len(tail) < fmt.len


def dataflash_time_base(buf: Buffer, report: FramingReport) -> float | None:
    """The offset (s) from TimeUS to UNIX time, as pymavlink's DFReader finds it.

    The first GPS message with a week number (GWk > 0) fixes it, through
    ``DFReaderClock_usec.find_time_base`` (GPS week and ms of week, leap seconds as
    pymavlink counts them). Without one, DFReader counts from boot (offset 0), and so do
    we, reporting time_reference "boot". None for a log without TimeUS at all.
    """
    scan = DataFlashScan(buf, ScanTally())
    first_us: int | None = None
    gps = None
    for fmt, offset in scan.messages():
        if first_us is None:
            first_us = scan.time_us(fmt, offset)
        if fmt.name == "GPS":
            msg = scan.decode(fmt, offset)
            try:
                if msg.GWk > 0 and float(msg.GMS) >= 0 and float(msg.TimeUS) >= 0:
                    gps = msg
                    break
            except (AttributeError, TypeError, ValueError):
                break  # not the TimeUS-era GPS format: no GPS clock (as DFReader)
    if first_us is None:
        report.time_reference = "none"
        return None
    if gps is None:
        report.time_reference = "boot"
        report.notes.append("no GPS week in the log: times are seconds since boot, not UNIX")
        return 0.0
    clock = DFReader.DFReaderClock_usec()
    clock.find_time_base(gps, first_us)
    report.time_reference = "gps"
    return float(clock.timebase)


def dataflash_records(
    scan: DataFlashScan, time_base: float | None
) -> Iterator[tuple[float, tuple[Any, int]]]:
    """(time s, (format, body offset)) of every timed message; counts every message."""
    counts: Counter[str] = Counter()
    for fmt, offset in scan.messages():
        counts[fmt.name] += 1
        time_us = scan.time_us(fmt, offset)
        if time_us is not None and time_base is not None:
            # The arithmetic of DFReaderClock_usec.set_message_timestamp.
            yield time_base + time_us * 0.000001, (fmt, offset)
    scan.report.counts = dict(sorted(counts.items()))
