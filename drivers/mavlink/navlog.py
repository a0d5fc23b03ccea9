"""Read MAVLink navigation logs (.tlog, ArduPilot DataFlash .bin) into typed samples.

``framing`` finds and decodes the messages (past damage) and the times; here they become
IMU, GNSS, heading and attitude samples and a downward echosounder's soundings from the
autopilot alone, one source is chosen per stream over the whole log, and what the
reading met is reported (``NavReadReport``).
Consecutive .tlog segments of one survey (the recorder starts one per daemon start) are
read as one log. ``summarize_nav_log`` gives ``seamap info`` the same counts without
keeping samples. Memory is bounded by the samples kept (files are memory-mapped, not read).
"""

from __future__ import annotations

import itertools
import math
import os
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

from drivers.mavlink import convert
from drivers.mavlink.framing import (
    Buffer,
    DataFlashScan,
    NavLogError,
    ScanTally,
    dataflash_records,
    dataflash_time_base,
    detect_format,
    open_log,
    scan_tlog,
)
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, RangeSample

__all__ = ["NavLog", "NavLogError", "NavReadReport", "read_nav_log", "summarize_nav_log"]

T = TypeVar("T")


HEADING_SOURCES = ("auto", "attitude", "global_position", "vfr_hud", "compass")
IMU_SOURCES = ("auto", "highres", "scaled", "scaled2", "scaled3", "raw")


@dataclass
class NavReadReport:
    """What reading a log met. Times are UNIX seconds (see ``time_reference``).

    For .tlog segments read as one log, ``path`` names them joined by " + " and every
    count and byte total is over all of them.
    """

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
    """The file (for segments: any of them) ends inside a message (the writer stopped
    mid-write; a note names each such segment)."""
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
    ranges: list[RangeSample] = field(default_factory=list)
    """Soundings of a downward echosounder (readings only: no reading is no sample)."""
    range_source: str | None = None
    """The message they came from: "DISTANCE_SENSOR", "RANGEFINDER" or "RFND"; None
    when the log has no downward rangefinder."""


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


# --- choosing what to keep ---------------------------------------------------------------

_IMU_NAMES = {message: name for name, message in convert.IMU_MESSAGES.items()}
_HEADING_NAMES = {message: name for name, message in convert.HEADING_MESSAGES.items()}
_NAV_MESSAGES = {*_IMU_NAMES, *_HEADING_NAMES, *convert.GNSS_MESSAGES, *convert.RANGE_MESSAGES}
_DATAFLASH_READ = {*convert.DATAFLASH_MESSAGES, *convert.DATAFLASH_RANGE_MESSAGES}


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
    ranges: dict[str, list[RangeSample]] = field(default_factory=dict)
    range_seen: set[str] = field(default_factory=set)
    """Range messages seen looking down, readings or not: their presence decides the
    source (a DISTANCE_SENSOR whose readings are all out of range still outranks
    RANGEFINDER, which would give those same non-readings as distances)."""
    range_ids: dict[str, int] = field(default_factory=dict)
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
        if kind in convert.RANGE_MESSAGES:
            self.take_range(msg, time)

    def take_range(self, msg: Any, time: float) -> None:
        """A DISTANCE_SENSOR or RANGEFINDER: a sounding of the first downward sensor seen
        (one id per message type; forward-looking sensors are not soundings)."""
        kind = msg.get_type()
        sensor = convert.downward_range_sensor(msg)
        if sensor is None or self.range_ids.setdefault(kind, sensor) != sensor:
            return
        self.range_seen.add(kind)
        self._add(self.ranges, kind, convert.range_from_mavlink(msg, time))

    def take_rfnd(self, msg: Any, time: float) -> None:
        """A DataFlash RFND: the soundings of the first downward rangefinder seen."""
        for instance, sample in convert.ranges_from_dataflash(msg, time):
            if self.range_ids.setdefault("RFND", instance) == instance:
                self.range_seen.add("RFND")
                self._add(self.ranges, "RFND", sample)

    def take_dataflash(self, msg: Any, time: float, time_us: int) -> None:
        """Convert one DataFlash message; only instance 0 (the primary sensor) is read,
        and of the rangefinders (RFND) the first one looking down.

        DataFlash has no checksum: a message that lacks the fields its type should have,
        or holds values of the wrong kind (a damaged FMT), is counted as unusable.
        """
        try:
            self._take_dataflash(msg, time, time_us)
        except (AttributeError, KeyError, IndexError, TypeError, ValueError, OverflowError):
            self.unusable += 1

    def _take_dataflash(self, msg: Any, time: float, time_us: int) -> None:
        if msg.get_type() in convert.DATAFLASH_RANGE_MESSAGES:
            self.take_rfnd(msg, time)
            return
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


def _range_source(vehicle: _Vehicle, order: Iterable[str], report: NavReadReport) -> str | None:
    """The first range message in ``order`` seen looking down; a note when a later one
    is left out (ArduPilot's RANGEFINDER repeats its downward DISTANCE_SENSOR)."""
    seen = [name for name in order if name in vehicle.range_seen]
    for other in seen[1:]:
        report.notes.append(f"{other} ignored: {seen[0]} reports the same soundings")
    return seen[0] if seen else None


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
    range_order: tuple[str, ...],
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
    range_name = _range_source(vehicle, range_order, report)
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
        ranges=_by_time(vehicle.ranges.get(range_name, []) if range_name else [], report),
        range_source=range_name,
    )


# --- public API --------------------------------------------------------------------------


NavPaths = str | os.PathLike[str] | Sequence[str | os.PathLike[str]]
"""One log, or the .tlog segments of one log in time order."""


def read_nav_log(
    path: NavPaths,
    *,
    heading_source: str = "auto",
    imu_source: str = "auto",
    declination_deg: float = 0.0,
) -> NavLog:
    """Read a .tlog or DataFlash .bin into navigation samples (SI, FRD, UNIX seconds).

    ``path`` may also be a sequence of .tlog segments (consecutive recordings of one
    survey, in time order): they are read as one log, in the order given, with one
    report over all of them. Only tlog segments can be joined: several DataFlash .bin
    files, or a .bin among .tlogs, raise NavLogError.

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
    paths = [path] if isinstance(path, str | os.PathLike) else list(path)
    if not paths:
        raise ValueError("read_nav_log: no log given")
    declination_rad = math.radians(declination_deg)
    with ExitStack() as stack:
        logs = [stack.enter_context(open_log(one)) for one in paths]
        kinds = [detect_format(buf, where) for where, buf in logs]
        if len(logs) > 1 and "dataflash" in kinds:
            where = logs[kinds.index("dataflash")][0]
            raise NavLogError(
                f"{where}: a DataFlash .bin cannot be joined with other logs "
                "(only .tlog segments can be read as one log)"
            )
        report = NavReadReport(
            " + ".join(str(where) for where, _ in logs),
            kinds[0],
            file_bytes=sum(len(buf) for _, buf in logs),
        )
        if kinds[0] == "tlog":
            vehicle = _Vehicle(imu_source, heading_source, declination_rad)
            return _read_tlog(_tlog_records(logs, report), report, vehicle)
        if imu_source != "auto":
            report.notes.append(f"imu_source {imu_source!r} is MAVLink's; DataFlash gives IMU")
        vehicle = _Vehicle("auto", heading_source, declination_rad)
        return _read_dataflash(logs[0][1], report, vehicle)


def _tlog_records(
    logs: Sequence[tuple[Path, Buffer]], report: NavReadReport
) -> Iterator[tuple[float, Any]]:
    """(receive time s, message) of each tlog in turn; their framing counts summed into
    ``report``. Stamp glitches are judged within each file: the gap between two segments
    is a real one."""
    for where, buf in logs:
        tally = ScanTally()
        yield from _drop_time_glitches(scan_tlog(buf, tally), report)
        report.messages += tally.messages
        report.bytes_skipped += tally.bytes_skipped
        report.bad_packets += tally.bad_packets
        if tally.truncated:
            report.truncated = True
            if len(logs) > 1:
                report.notes.append(f"{where}: ends inside a message")


def _read_tlog(
    records: Iterable[tuple[float, Any]], report: NavReadReport, template: _Vehicle
) -> NavLog:
    vehicles: dict[tuple[int, int], _Vehicle] = {}
    counts: Counter[str] = Counter()
    sent: Counter[tuple[int, int]] = Counter()
    span = _Span()
    autopilot_id: tuple[int, int] | None = None
    autopilot = "unknown"
    not_vehicles: set[tuple[int, int]] = set()
    for time, msg in records:
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
        range_order=convert.RANGE_MESSAGES,
        compass_key=None,
    )


def _read_dataflash(buf: Buffer, report: NavReadReport, vehicle: _Vehicle) -> NavLog:
    time_base = dataflash_time_base(buf, report)
    if time_base is None:
        report.notes.append("no TimeUS in the log (pre-2015 format): no samples read")
    scan = DataFlashScan(buf, report)
    span = _Span()
    for time, (fmt, offset) in _drop_time_glitches(dataflash_records(scan, time_base), report):
        span.add(time)
        if fmt.name in _DATAFLASH_READ:
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
        range_order=convert.DATAFLASH_RANGE_MESSAGES,
        compass_key="MAG",
    )


def summarize_nav_log(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What a .tlog or .bin holds, for ``seamap info``; streams, keeps no samples.

    Keys: kind ("mavlink"), format ("tlog" | "dataflash"), count, first_time, last_time
    (UNIX s, or s since boot when time_reference is "boot"), messages {TYPE: count},
    autopilot, autopilot_id, time_reference, file_bytes, bytes_skipped, bad_packets,
    bad_timestamps, truncated, time_backwards (tlog receive stamps; None for DataFlash,
    whose message types are not written in strict time order), soundings (the downward
    echosounder's readings that ``read_nav_log`` keeps) and soundings_source (the message
    they come from, None without one).
    """
    with open_log(path) as (where, buf):
        kind = detect_format(buf, where)
        report = NavReadReport(str(where), kind, file_bytes=len(buf))
        span = _Span()
        autopilot = "unknown"
        # Soundings per sender: they are the autopilot's only, as read_nav_log keeps them.
        sounders: dict[tuple[int, int], _Vehicle] = {}
        if kind == "tlog":
            counts: Counter[str] = Counter()
            for time, msg in _drop_time_glitches(scan_tlog(buf, report), report):
                counts[msg.get_type()] += 1
                span.add(time)
                if report.autopilot_id is None and convert.is_autopilot_heartbeat(msg):
                    report.autopilot_id = (msg.get_srcSystem(), msg.get_srcComponent())
                    autopilot = convert.autopilot_name(msg.autopilot)
                if msg.get_type() in convert.RANGE_MESSAGES:
                    source = (msg.get_srcSystem(), msg.get_srcComponent())
                    sounders.setdefault(source, _Vehicle("auto", "auto", 0.0)).take_range(msg, time)
            report.counts = dict(sorted(counts.items()))
            range_order: tuple[str, ...] = convert.RANGE_MESSAGES
            sender = report.autopilot_id or max(
                sounders, key=lambda s: sounders[s].samples, default=(0, 0)
            )
        else:
            autopilot = "ardupilot"
            time_base = dataflash_time_base(buf, report)
            scan = DataFlashScan(buf, report)
            sender = (0, 0)
            rfnd = sounders.setdefault(sender, _Vehicle("auto", "auto", 0.0))
            for time, (fmt, offset) in _drop_time_glitches(
                dataflash_records(scan, time_base), report
            ):
                span.add(time)
                if fmt.name in convert.DATAFLASH_RANGE_MESSAGES:
                    rfnd.take_dataflash(scan.decode(fmt, offset), time, 0)
            range_order = convert.DATAFLASH_RANGE_MESSAGES
        sounder = sounders.get(sender)
        range_name = _range_source(sounder, range_order, report) if sounder else None
        soundings = len(sounder.ranges.get(range_name, [])) if sounder and range_name else 0
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
        "soundings": soundings,
        "soundings_source": range_name,
    }
