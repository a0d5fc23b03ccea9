"""Read MAVLink navigation logs (.tlog, ArduPilot DataFlash .bin) into typed samples.

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
counted, a cut-off end is reported, and reading goes on. Memory is bounded by the samples
kept (the file is memory-mapped, not read).
"""

from __future__ import annotations

import itertools
import math
import mmap
import os
import re
import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

from pymavlink import DFReader
from pymavlink.dialects.v20 import all as mavlink

from drivers.mavlink import convert
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample
from seamap.config import HEADING_SOURCES, IMU_SOURCES
from seamap.errors import SeamapError

Buffer = bytes | mmap.mmap
T = TypeVar("T")


class NavLogError(SeamapError):
    """A navigation log that cannot be read at all: missing, unreadable, or not a log."""


@dataclass
class NavReadReport:
    """What reading a log met. Times are UNIX seconds (see ``time_reference``)."""

    path: str
    format: str
    """"tlog" or "dataflash"."""
    file_bytes: int = 0
    messages: int = 0
    """Messages decoded, from every system and of every type."""
    counts: dict[str, int] = field(default_factory=dict)
    bytes_skipped: int = 0
    """Bytes that belonged to no readable message (corruption, garbage between messages)."""
    bad_packets: int = 0
    """Complete-looking frames rejected: MAVLink CRC or length errors, invalid FMT."""
    bad_timestamps: int = 0
    """Messages dropped because their stamp alone jumped by more than an hour and back."""
    truncated: bool = False
    """The file ends inside a message (the writer stopped mid-write)."""
    time_backwards: int = 0
    """Samples stamped earlier than the previous sample of the same stream (file order);
    the sample lists are sorted by time (stable) all the same."""
    first_time: float | None = None
    last_time: float | None = None
    time_reference: str = "receive"
    """"receive": the tlog's receive stamps; "gps": DataFlash TimeUS on the GPS clock
    (UNIX); "boot": DataFlash without a GPS week, seconds since boot, NOT UNIX time;
    "none": no timestamps at all."""
    autopilot_id: tuple[int, int] | None = None
    """(system, component) whose messages were used."""
    other_system_messages: int = 0
    unusable_messages: int = 0
    """Navigation messages that gave no sample (unknown sentinel, NaN, out of range)."""
    notes: list[str] = field(default_factory=list)


@dataclass
class NavLog:
    """Navigation samples of one log, each list sorted by time (UNIX s, stable)."""

    imu: list[ImuSample]
    gnss: list[GnssFix]
    heading: list[HeadingSample]
    attitude: list[AttitudeSample]
    autopilot: str
    """"ardupilot", "px4" or "unknown" (from HEARTBEAT; DataFlash logs are ArduPilot's)."""
    heading_source: str | None
    """Config name of the heading used ("attitude", ..., "compass"), None if no heading."""
    imu_source: str | None
    """Config name of the IMU message used ("highres", ...; "IMU" for DataFlash)."""
    gnss_source: str | None
    report: NavReadReport


_GLITCH_S = 3600.0
"""A stamp this far from its neighbours on both sides is corruption, not a clock step."""


def _drop_time_glitches(
    records: Iterable[tuple[float, T]], report: NavReadReport
) -> Iterator[tuple[float, T]]:
    """Drop records whose stamp alone jumps away and back (a damaged stamp).

    One record is held back after a jump: if the next one returns near the time before the
    jump, the held one was a glitch; otherwise the clock stepped and both are kept.
    """
    last: float | None = None
    held: tuple[float, T] | None = None
    for record in records:
        stamp = record[0]
        if held is not None:
            if last is not None and abs(stamp - last) <= _GLITCH_S:
                report.bad_timestamps += 1
            else:
                yield held
                last = held[0]
            held = None
        if last is None or abs(stamp - last) <= _GLITCH_S:
            yield record
            last = stamp
        else:
            held = record
    if held is not None:
        yield held


@dataclass
class _Span:
    first: float | None = None
    last: float | None = None
    previous: float | None = None
    backwards: int = 0

    def add(self, stamp: float) -> None:
        self.first = stamp if self.first is None else min(self.first, stamp)
        self.last = stamp if self.last is None else max(self.last, stamp)
        if self.previous is not None and stamp < self.previous:
            self.backwards += 1
        self.previous = stamp


# --- files ---------------------------------------------------------------------------------


@contextmanager
def _open_log(path: str | os.PathLike[str]) -> Iterator[tuple[Path, Buffer]]:
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


def _detect(buf: Buffer, where: Path) -> str:
    """ "tlog" or "dataflash" from the first bytes; NavLogError for anything else."""
    if buf[:3] == b"\xa3\x95\x80":
        return "dataflash"
    # A readable record (plausible stamp, magic, good CRC) near the start makes a tlog,
    # even if the very first bytes were damaged.
    head = buf[: 65536 + _MAX_RECORD]
    if next(_scan_tlog(head, NavReadReport(str(where), "tlog")), None) is not None:
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
    parser: Any, buf: Buffer, pos: int, report: NavReadReport
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


def _scan_tlog(buf: Buffer, report: NavReadReport) -> Iterator[tuple[float, Any]]:
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


class _DataFlash:
    """Walks a DataFlash log message by message, learning formats (FMT, UNIT, MULT, FMTU)."""

    def __init__(self, buf: Buffer, report: NavReadReport) -> None:
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


def _dataflash_time_base(buf: Buffer, report: NavReadReport) -> float | None:
    """The offset (s) from TimeUS to UNIX time, as pymavlink's DFReader finds it.

    The first GPS message with a week number (GWk > 0) fixes it, through
    ``DFReaderClock_usec.find_time_base`` (GPS week and ms of week, leap seconds as
    pymavlink counts them). Without one, DFReader counts from boot (offset 0), and so do
    we, reporting time_reference "boot". None for a log without TimeUS at all.
    """
    scan = _DataFlash(buf, NavReadReport(report.path, "dataflash"))
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


def _dataflash_records(
    scan: _DataFlash, time_base: float | None
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


# --- choosing what to keep ---------------------------------------------------------------

_IMU_NAMES = {message: name for name, message in convert.IMU_MESSAGES.items()}
_HEADING_NAMES = {message: name for name, message in convert.HEADING_MESSAGES.items()}
_NAV_MESSAGES = {*_IMU_NAMES, *_HEADING_NAMES, *convert.GNSS_MESSAGES}


@dataclass
class _Vehicle:
    """Candidate sample streams from one sender, one list per source, until one is chosen.

    Every wanted source is collected over the whole log, and "auto" picks at the end, so
    a log never switches source midway.
    """

    wanted_imu: str
    wanted_heading: str
    declination_rad: float
    imu: dict[str, list[ImuSample]] = field(default_factory=dict)
    heading: dict[str, list[HeadingSample]] = field(default_factory=dict)
    compass: dict[str, list[HeadingSample]] = field(default_factory=dict)
    compass_level: dict[str, list[HeadingSample]] = field(default_factory=dict)
    gnss: dict[str, list[GnssFix]] = field(default_factory=dict)
    attitude: list[AttitudeSample] = field(default_factory=list)
    imu_ids: dict[str, int] = field(default_factory=dict)
    h_acc_by_time_us: dict[int, float] = field(default_factory=dict)
    gnss_time_us: list[int] = field(default_factory=list)
    samples: int = 0
    unusable: int = 0

    def fresh(self) -> _Vehicle:
        """An empty collector with the same choices."""
        return _Vehicle(self.wanted_imu, self.wanted_heading, self.declination_rad)

    def _add(self, streams: dict[str, list[T]], name: str, sample: T | None) -> None:
        if sample is None:
            self.unusable += 1
            return
        streams.setdefault(name, []).append(sample)
        self.samples += 1

    def _add_mag(self, key: str, time: float, mag: tuple[float, float, float] | None) -> None:
        """A compass heading from ``mag`` and the latest attitude (level if none yet)."""
        if mag is None or self.wanted_heading not in ("auto", "compass"):
            return
        if self.wanted_heading == "auto" and self.heading:
            return  # "auto" prefers any other heading to the compass: keep no compass
        latest = self.attitude[-1] if self.attitude else None
        roll, pitch = (latest.roll_rad, latest.pitch_rad) if latest else (0.0, 0.0)
        heading = convert.tilt_compensated_heading(mag, roll, pitch, self.declination_rad)
        if heading is not None:
            streams = self.compass if latest else self.compass_level
            streams.setdefault(key, []).append(HeadingSample(time, heading, "MAG", 0.0))

    def _add_attitude(self, sample: AttitudeSample | None) -> None:
        if sample is None:
            self.unusable += 1
        else:
            self.attitude.append(sample)
            self.samples += 1

    def take_mavlink(self, msg: Any, time: float) -> None:
        """Convert one MAVLink message from this sender into the streams it feeds."""
        kind = msg.get_type()
        if kind == "ATTITUDE":
            self._add_attitude(convert.attitude_from_mavlink(msg, time))
        name = _IMU_NAMES.get(kind)
        if name is not None and self.wanted_imu in ("auto", name):
            # One IMU per message type: the first id seen (the MAVLink 2 "id" extension).
            instance = convert.imu_instance(msg)
            if self.imu_ids.setdefault(kind, instance) == instance:
                sample = convert.imu_from_mavlink(msg, time)
                self._add(self.imu, name, sample)
                if sample is not None:
                    self._add_mag(name, time, sample.mag_gauss)
        if kind in convert.GNSS_MESSAGES:
            self._add(self.gnss, kind, convert.gnss_from_mavlink(msg, time))
        name = _HEADING_NAMES.get(kind)
        if name is not None and self.wanted_heading in ("auto", name):
            self._add(self.heading, name, convert.heading_from_mavlink(msg, time))

    def take_dataflash(self, msg: Any, time: float, time_us: int) -> None:
        """Convert one DataFlash message; only instance 0 (the primary sensor) is read.

        DataFlash has no checksum: a message that lacks the fields its type should have,
        or holds values of the wrong kind (a damaged FMT), is counted as unusable.
        """
        try:
            self._take_dataflash(msg, time, time_us)
        except (AttributeError, KeyError, IndexError, TypeError, ValueError, OverflowError):
            self.unusable += 1

    def _take_dataflash(self, msg: Any, time: float, time_us: int) -> None:
        known = convert.dataflash_kind(msg)
        if known is None or known[1] != 0:
            return
        kind = known[0]
        if kind == "IMU":
            self._add(self.imu, "IMU", convert.imu_from_dataflash(msg, time))
        elif kind == "GPS":
            fix = convert.gnss_from_dataflash(msg, time)
            self._add(self.gnss, "GPS", fix)
            if fix is not None:
                self.gnss_time_us.append(time_us)
        elif kind == "GPA":
            h_acc = convert.h_acc_from_dataflash(msg)
            if h_acc is not None:
                self.h_acc_by_time_us[time_us] = h_acc
        elif kind == "MAG":
            self._add_mag("MAG", time, convert.mag_from_dataflash(msg))
        elif kind == "ATT":
            self._add_attitude(convert.attitude_from_dataflash(msg, time))
            if self.wanted_heading in ("auto", "attitude"):
                self._add(self.heading, "attitude", convert.heading_from_dataflash(msg, time))

    def join_gpa(self) -> None:
        """Give each DataFlash GPS fix the HAcc of the GPA logged with it (same TimeUS)."""
        fixes = self.gnss.get("GPS")
        if fixes and self.h_acc_by_time_us:
            self.gnss["GPS"] = [
                replace(fix, h_acc_m=self.h_acc_by_time_us.get(time_us))
                for fix, time_us in zip(fixes, self.gnss_time_us, strict=True)
            ]


def _pick(streams: dict[str, list[T]], order: Iterable[str], wanted: str) -> str | None:
    """The wanted source, or for "auto" the first in ``order`` that gave samples."""
    candidates = [name for name in order if wanted in ("auto", name)]
    return next((name for name in candidates if streams.get(name)), None)


def _by_time(samples: list[Any], report: NavReadReport) -> list[Any]:
    """Sorted by time (stable: receive order among equal stamps); count the steps back."""
    report.time_backwards += sum(1 for a, b in itertools.pairwise(samples) if b.time < a.time)
    return sorted(samples, key=lambda sample: sample.time)


_PLAIN_HEADINGS = ("attitude", "global_position", "vfr_hud")


def _finish(
    vehicle: _Vehicle,
    report: NavReadReport,
    autopilot: str,
    *,
    imu_order: tuple[str, ...],
    gnss_order: tuple[str, ...],
    compass_key: str | None,
) -> NavLog:
    """Choose one source per stream over the whole log and sort the samples."""
    usable = [name for name in imu_order if convert.imu_source_usable(name, autopilot)]
    if vehicle.imu.get("raw") and "raw" not in usable:
        report.notes.append("RAW_IMU ignored: PX4 fills it with raw sensor counts")
    imu_name = _pick(vehicle.imu, usable, vehicle.wanted_imu)
    heading_name = _pick(vehicle.heading, _PLAIN_HEADINGS, vehicle.wanted_heading)
    heading = vehicle.heading.get(heading_name, []) if heading_name else []
    if heading_name is None and vehicle.wanted_heading in ("auto", "compass"):
        # Before the first attitude the compass cannot be tilt-compensated; a log without
        # any attitude is read as level.
        compass_streams = vehicle.compass if vehicle.attitude else vehicle.compass_level
        heading = compass_streams.get(compass_key or imu_name or "", [])
        if heading:
            heading_name = "compass"
            if not vehicle.attitude:
                report.notes.append("compass heading assumes a level vehicle: no attitude")
    gnss_name = _pick(vehicle.gnss, gnss_order, "auto")
    for wanted, chosen, what in (
        (vehicle.wanted_imu, imu_name, "imu_source"),
        (vehicle.wanted_heading, heading_name, "heading_source"),
    ):
        if wanted != "auto" and chosen is None:
            report.notes.append(f"{what} {wanted!r}: no usable samples from the autopilot")
    report.unusable_messages = vehicle.unusable
    return NavLog(
        imu=_by_time(vehicle.imu.get(imu_name, []) if imu_name else [], report),
        gnss=_by_time(vehicle.gnss.get(gnss_name, []) if gnss_name else [], report),
        heading=_by_time(heading, report),
        attitude=_by_time(vehicle.attitude, report),
        autopilot=autopilot,
        heading_source=heading_name,
        imu_source=imu_name,
        gnss_source=gnss_name,
        report=report,
    )


# --- public API --------------------------------------------------------------------------


def read_nav_log(
    path: str | os.PathLike[str],
    *,
    heading_source: str = "auto",
    imu_source: str = "auto",
    declination_deg: float = 0.0,
) -> NavLog:
    """Read a .tlog or DataFlash .bin into navigation samples (SI, FRD, UNIX seconds).

    heading_source / imu_source / declination_deg mean what ``MavlinkConfig`` documents;
    "auto" picks the first source in the documented order that the log carries, decided
    over the whole log. Only the autopilot's messages are used: the (system, component)
    of the first autopilot HEARTBEAT. Damage is skipped and reported (``NavLog.report``);
    NavLogError only for a file that cannot be read or is not a MAVLink log at all.
    """
    if heading_source not in HEADING_SOURCES:
        raise ValueError(f"heading_source {heading_source!r} is not one of {HEADING_SOURCES}")
    if imu_source not in IMU_SOURCES:
        raise ValueError(f"imu_source {imu_source!r} is not one of {IMU_SOURCES}")
    declination_rad = math.radians(declination_deg)
    with _open_log(path) as (where, buf):
        kind = _detect(buf, where)
        report = NavReadReport(str(where), kind, file_bytes=len(buf))
        if kind == "tlog":
            return _read_tlog(buf, report, _Vehicle(imu_source, heading_source, declination_rad))
        if imu_source != "auto":
            report.notes.append(f"imu_source {imu_source!r} is MAVLink's; DataFlash gives IMU")
        vehicle = _Vehicle("auto", heading_source, declination_rad)
        return _read_dataflash(buf, report, vehicle)


def _read_tlog(buf: Buffer, report: NavReadReport, template: _Vehicle) -> NavLog:
    vehicles: dict[tuple[int, int], _Vehicle] = {}
    counts: Counter[str] = Counter()
    sent: Counter[tuple[int, int]] = Counter()
    span = _Span()
    autopilot_id: tuple[int, int] | None = None
    autopilot = "unknown"
    not_vehicles: set[tuple[int, int]] = set()
    for time, msg in _drop_time_glitches(_scan_tlog(buf, report), report):
        kind = msg.get_type()
        counts[kind] += 1
        span.add(time)
        sender = (msg.get_srcSystem(), msg.get_srcComponent())
        sent[sender] += 1
        if kind == "HEARTBEAT":
            if not convert.is_autopilot_heartbeat(msg):
                not_vehicles.add(sender)
            elif autopilot_id is None:
                autopilot_id, autopilot = sender, convert.autopilot_name(msg.autopilot)
        if kind in _NAV_MESSAGES:
            if sender not in vehicles:
                vehicles[sender] = template.fresh()
            vehicles[sender].take_mavlink(msg, time)
    if autopilot_id is None:
        # No autopilot HEARTBEAT: the sender of the most navigation samples that is not a GCS.
        senders = [sender for sender in vehicles if sender not in not_vehicles]
        autopilot_id = max(senders, key=lambda s: vehicles[s].samples, default=None)
        if autopilot_id is not None:
            report.notes.append(f"no autopilot HEARTBEAT: using system {autopilot_id}")
    report.counts = dict(sorted(counts.items()))
    report.first_time, report.last_time = span.first, span.last
    report.autopilot_id = autopilot_id
    report.other_system_messages = sum(sent.values()) - sent[autopilot_id] if autopilot_id else 0
    vehicle = vehicles.get(autopilot_id, template) if autopilot_id else template
    return _finish(
        vehicle,
        report,
        autopilot,
        imu_order=convert.IMU_AUTO_ORDER,
        gnss_order=convert.GNSS_MESSAGES,
        compass_key=None,
    )


def _read_dataflash(buf: Buffer, report: NavReadReport, vehicle: _Vehicle) -> NavLog:
    time_base = _dataflash_time_base(buf, report)
    if time_base is None:
        report.notes.append("no TimeUS in the log (pre-2015 format): no samples read")
    scan = _DataFlash(buf, report)
    span = _Span()
    for time, (fmt, offset) in _drop_time_glitches(_dataflash_records(scan, time_base), report):
        span.add(time)
        if fmt.name in convert.DATAFLASH_MESSAGES:
            msg = scan.decode(fmt, offset)
            msg._timestamp = time
            vehicle.take_dataflash(msg, time, scan.time_us(fmt, offset) or 0)
    vehicle.join_gpa()
    report.first_time, report.last_time = span.first, span.last
    return _finish(
        vehicle,
        report,
        "ardupilot",
        imu_order=("IMU",),
        gnss_order=("GPS",),
        compass_key="MAG",
    )


def summarize_nav_log(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What a .tlog or .bin holds, for ``seamap info``; streams, keeps no samples.

    Keys: kind ("mavlink"), format ("tlog" | "dataflash"), count, first_time, last_time
    (UNIX s, or s since boot when time_reference is "boot"), messages {TYPE: count},
    autopilot, autopilot_id, time_reference, file_bytes, bytes_skipped, bad_packets,
    bad_timestamps, truncated, time_backwards (tlog receive stamps; None for DataFlash,
    whose message types are not written in strict time order).
    """
    with _open_log(path) as (where, buf):
        kind = _detect(buf, where)
        report = NavReadReport(str(where), kind, file_bytes=len(buf))
        span = _Span()
        autopilot = "unknown"
        if kind == "tlog":
            counts: Counter[str] = Counter()
            for time, msg in _drop_time_glitches(_scan_tlog(buf, report), report):
                counts[msg.get_type()] += 1
                span.add(time)
                if report.autopilot_id is None and convert.is_autopilot_heartbeat(msg):
                    report.autopilot_id = (msg.get_srcSystem(), msg.get_srcComponent())
                    autopilot = convert.autopilot_name(msg.autopilot)
            report.counts = dict(sorted(counts.items()))
        else:
            autopilot = "ardupilot"
            time_base = _dataflash_time_base(buf, report)
            scan = _DataFlash(buf, report)
            for time, _ in _drop_time_glitches(_dataflash_records(scan, time_base), report):
                span.add(time)
    return {
        "kind": "mavlink",
        "format": kind,
        "count": sum(report.counts.values()),
        "first_time": span.first,
        "last_time": span.last,
        "messages": report.counts,
        "autopilot": autopilot,
        "autopilot_id": list(report.autopilot_id) if report.autopilot_id else None,
        "time_reference": report.time_reference,
        "file_bytes": report.file_bytes,
        "bytes_skipped": report.bytes_skipped,
        "bad_packets": report.bad_packets,
        "bad_timestamps": report.bad_timestamps,
        "truncated": report.truncated,
        "time_backwards": span.backwards if kind == "tlog" else None,
    }
