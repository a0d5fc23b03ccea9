"""The live MAVLink link to the autopilot: pymavlink bytes in, typed samples out, on asyncio.

``MavlinkLink`` opens a pymavlink connection (``udpin:HOST:PORT``, ``udpout:HOST:PORT`` or a
serial device + baud through pyserial), speaks MAVLink 2 and bridges to asyncio in one
place: ``loop.add_reader`` on the connection's file descriptor. Each read is stamped on
receipt (``time.time()``, UNIX s); each packet goes raw to ``on_packet(bytes, time)`` (the
.tlog recorder) and is then converted by ``drivers.mavlink.convert`` into ``ImuSample``,
``GnssFix``, ``HeadingSample``, ``AttitudeSample`` and a downward echosounder's
``RangeSample`` for ``on_sample`` (or ``samples()``).
Only the autopilot counts: the (system, component) of the first autopilot HEARTBEAT.

It announces itself once a second (HEARTBEAT, MAV_TYPE_ONBOARD_CONTROLLER /
MAV_AUTOPILOT_INVALID), asks for the streams the EKF needs with MAV_CMD_SET_MESSAGE_INTERVAL
(one at a time, each checked by COMMAND_ACK) and falls back to REQUEST_DATA_STREAM for what
was refused or unanswered. No autopilot HEARTBEAT for ``heartbeat_timeout_s`` = link down;
a serial port is reopened with backoff, UDP keeps listening; when the heartbeat returns the
streams are asked for again. Bad bytes are counted, never raised.

Live source choice (``heading_source`` / ``imu_source`` "auto"): unlike ``navlog`` the link
cannot look at the whole log, so a stream follows the best source (in the config's order)
seen so far, never going back down; GLOBAL_POSITION_INT as a GNSS fix and the compass as a
heading are fallbacks taken only when nothing better came within ``fallback_s`` of link up;
so is RANGEFINDER for the soundings (ArduPilot sends it beside the DISTANCE_SENSOR of the
same downward sensor, which has its valid span and quality).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("MAVLINK20", "1")  # before mavutil: MAVLink 2 from the first packet

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from drivers.mavlink import convert
from mapping.samples import NavSample

__all__ = ["DEFAULT_RATES_HZ", "LinkStats", "MavlinkLink", "StreamRequest"]

PacketCallback = Callable[[bytes, float], None]
SampleCallback = Callable[[NavSample], None]

DEFAULT_RATES_HZ: dict[str, float] = {
    "IMU": 50.0,
    "GPS_RAW_INT": 5.0,
    "ATTITUDE": 10.0,
    "GLOBAL_POSITION_INT": 10.0,
    "VFR_HUD": 4.0,
    "DISTANCE_SENSOR": 10.0,
}
"""Requested rates (Hz); "IMU" stands for the IMU message chosen per autopilot.
DISTANCE_SENSOR: a downward echosounder's soundings (an autopilot without a rangefinder
sends none, whatever is asked)."""

_DATA_STREAMS: dict[str, int] = {
    "RAW_IMU": mavlink2.MAV_DATA_STREAM_RAW_SENSORS,
    "SCALED_IMU": mavlink2.MAV_DATA_STREAM_RAW_SENSORS,
    "SCALED_IMU2": mavlink2.MAV_DATA_STREAM_RAW_SENSORS,
    "SCALED_IMU3": mavlink2.MAV_DATA_STREAM_RAW_SENSORS,
    "HIGHRES_IMU": mavlink2.MAV_DATA_STREAM_RAW_SENSORS,
    "GPS_RAW_INT": mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS,
    "ATTITUDE": mavlink2.MAV_DATA_STREAM_EXTRA1,
    "GLOBAL_POSITION_INT": mavlink2.MAV_DATA_STREAM_POSITION,
    "VFR_HUD": mavlink2.MAV_DATA_STREAM_EXTRA2,
    "DISTANCE_SENSOR": mavlink2.MAV_DATA_STREAM_EXTRA3,
}
"""ArduPilot's legacy stream groups (REQUEST_DATA_STREAM) that carry each message."""

_SERIAL_BACKOFF_S = (0.2, 0.5, 1.0, 2.0, 5.0)
_UNIX_PREFIXES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:", "mcast:")


@dataclass
class StreamRequest:
    """One message asked for: interval (µs) and how the autopilot answered.

    result: "accepted" (COMMAND_ACK MAV_RESULT_ACCEPTED), "refused" (any other result),
    "unanswered" (no ACK after the retries) or "pending"; fallback: REQUEST_DATA_STREAM sent.
    """

    message: str
    interval_us: int
    result: str = "pending"
    fallback: bool = False


@dataclass(frozen=True)
class MissionProgress:
    """MISSION_CURRENT: the item being flown, of ``total`` (MAVLink 2 extension, 0 when the
    autopilot does not send it); ``state`` is MISSION_STATE (0 unknown, 1 no mission,
    2 not started, 3 active, 4 paused, 5 complete); ``time`` the receive stamp (UNIX s)."""

    current: int
    total: int
    state: int
    time: float

    STATES = ("unknown", "no mission", "not started", "active", "paused", "complete")

    def to_dict(self) -> dict[str, object]:
        state = self.STATES[self.state] if 0 <= self.state < len(self.STATES) else "unknown"
        return {"current": self.current, "total": self.total, "state": state}


@dataclass
class LinkStats:
    """What the link met. Rates are messages per second over the last ~1 s window."""

    packets: int = 0
    """Valid MAVLink packets received, from every system."""
    bad_packets: int = 0
    bad_bytes: int = 0
    """Bytes that made no valid packet (CRC errors, line noise)."""
    counts: Counter[str] = field(default_factory=Counter)
    """Autopilot messages by type."""
    rates_hz: dict[str, float] = field(default_factory=dict)
    samples: int = 0
    samples_dropped: int = 0
    """Samples lost because nobody drained ``samples()`` (queue full)."""
    link_up: bool = False
    link_downs: int = 0
    reconnects: int = 0
    """Times the autopilot's heartbeat came back after the link was down."""
    reopens: int = 0
    """Serial port re-opened after an error or a loss."""
    transport_errors: int = 0
    autopilot_id: tuple[int, int] | None = None
    autopilot: str = "unknown"
    requests: dict[str, StreamRequest] = field(default_factory=dict)
    last_heartbeat: float | None = None
    mission: MissionProgress | None = None
    """The autopilot's mission progress, from its latest MISSION_CURRENT."""


class _Chooser:
    """One sample stream's live source: the best (lowest index in ``order``) seen so far.

    ``late`` sources are only taken when nothing else came by the fallback deadline.
    """

    def __init__(self, order: tuple[str, ...], wanted: str, late: frozenset[str]) -> None:
        self.order = order if wanted == "auto" else (wanted,)
        self.late = late if wanted == "auto" else frozenset()
        self.current: str | None = None

    def accept(self, name: str, fallback_due: bool) -> bool:
        if name == self.current:
            return True  # chosen: no wait for better sources again after a reconnect
        if name not in self.order or (name in self.late and not fallback_due):
            return False
        if self.current is None or self.order.index(name) < self.order.index(self.current):
            self.current = name
        return name == self.current


class MavlinkLink:
    """An asyncio MAVLink link to one autopilot (see the module docstring).

    url: pymavlink connection string or a serial device path; baud for serial.
    on_packet(bytes, t): every valid packet as received, t = UNIX s receive stamp.
    on_sample(sample): typed samples; without it they queue for ``samples()``.
    rates_hz: requested rates by message ("IMU" = the chosen IMU message).
    heartbeat_timeout_s: no autopilot HEARTBEAT this long (s) = link down.
    fallback_s: how long (s) after link up the "auto" choices wait for preferred sources.
    """

    def __init__(
        self,
        url: str,
        *,
        baud: int = 115200,
        heading_source: str = "auto",
        imu_source: str = "auto",
        declination_deg: float = 0.0,
        on_packet: PacketCallback | None = None,
        on_sample: SampleCallback | None = None,
        rates_hz: dict[str, float] | None = None,
        heartbeat_period_s: float = 1.0,
        heartbeat_timeout_s: float = 3.0,
        ack_timeout_s: float = 0.5,
        fallback_s: float = 3.0,
        source_system: int = 1,
        source_component: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER,
        queue_size: int = 10000,
    ) -> None:
        self.url = url
        self.baud = baud
        self.serial = not url.startswith(_UNIX_PREFIXES)
        self.on_packet = on_packet
        self.on_sample = on_sample
        self.rates_hz = {**DEFAULT_RATES_HZ, **(rates_hz or {})}
        self.heartbeat_period_s = heartbeat_period_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.ack_timeout_s = ack_timeout_s
        self.fallback_s = fallback_s
        self.source_system = source_system
        self.source_component = source_component
        self.imu_source = imu_source
        self.declination_rad = math.radians(declination_deg)
        self.stats = LinkStats()
        self._imu = _Chooser(convert.IMU_AUTO_ORDER, imu_source, frozenset())
        self._heading = _Chooser(convert.HEADING_AUTO_ORDER, heading_source, frozenset({"compass"}))
        self._gnss = _Chooser(convert.GNSS_MESSAGES, "auto", frozenset({"GLOBAL_POSITION_INT"}))
        self._range = _Chooser(convert.RANGE_MESSAGES, "auto", frozenset({"RANGEFINDER"}))
        self._range_ids: dict[str, int] = {}
        self._imu_names = {message: name for name, message in convert.IMU_MESSAGES.items()}
        self._heading_names = {m: name for name, m in convert.HEADING_MESSAGES.items()}
        self._imu_ids: dict[str, int] = {}
        self._attitude: tuple[float, float] | None = None
        self._up_since: float | None = None
        self._conn: Any = None
        self._mav: Any = None
        self._fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._request_task: asyncio.Task[None] | None = None
        self._reopen_task: asyncio.Task[None] | None = None
        self._ack: asyncio.Future[int] | None = None
        self._queue: asyncio.Queue[NavSample] = asyncio.Queue(queue_size)
        self._rate_mark: tuple[float, Counter[str]] = (time.time(), Counter())

    # --- lifecycle -----------------------------------------------------------------------

    async def start(self) -> None:
        """Open the connection and start the heartbeat and the watchdog. A serial device
        that cannot be opened yet is retried with backoff (no error)."""
        self._loop = asyncio.get_running_loop()
        try:
            self._open()
        except Exception:
            if not self.serial:
                raise
            self.stats.transport_errors += 1
            self._schedule_reopen()
        self._tasks = [
            asyncio.create_task(self._heartbeat_loop()),
            asyncio.create_task(self._watchdog()),
        ]

    async def close(self) -> None:
        """Stop every task and close the connection; safe to call twice."""
        tasks = [*self._tasks, self._request_task, self._reopen_task]
        for task in tasks:
            if task is not None:
                task.cancel()
        for task in tasks:
            if task is not None:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        self._tasks, self._request_task, self._reopen_task = [], None, None
        self._close_transport()

    async def __aenter__(self) -> MavlinkLink:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def samples(self) -> AsyncIterator[NavSample]:
        """Samples in arrival order (only when no ``on_sample`` callback was given)."""
        while True:
            yield await self._queue.get()

    # --- transport -----------------------------------------------------------------------

    def _open(self) -> None:
        if self.serial:
            conn = mavutil.mavserial(
                self.url,
                baud=self.baud,
                source_system=self.source_system,
                source_component=self.source_component,
            )
        else:
            conn = mavutil.mavlink_connection(
                self.url, source_system=self.source_system, source_component=self.source_component
            )
        # Our own MAVLink 2 parser/encoder, whatever dialect mavutil was first imported with.
        mav = mavlink2.MAVLink(conn, self.source_system, self.source_component)
        mav.robust_parsing = True
        conn.mav = mav
        self._conn, self._mav, self._fd = conn, mav, conn.fd
        assert self._loop is not None
        self._loop.add_reader(conn.fd, self._on_readable)

    def _close_transport(self) -> None:
        if self._fd is not None and self._loop is not None:
            self._loop.remove_reader(self._fd)
        if self._conn is not None:
            with contextlib.suppress(Exception):
                self._conn.close()
        self._conn = self._mav = self._fd = None

    def _transport_failed(self) -> None:
        """A read or write error: the serial device went away. Close it and reopen."""
        self.stats.transport_errors += 1
        self._close_transport()
        if self.serial:
            self._schedule_reopen()

    def _schedule_reopen(self) -> None:
        if self._reopen_task is None or self._reopen_task.done():
            self._reopen_task = asyncio.create_task(self._reopen())

    async def _reopen(self) -> None:
        for attempt in range(1_000_000):
            await asyncio.sleep(_SERIAL_BACKOFF_S[min(attempt, len(_SERIAL_BACKOFF_S) - 1)])
            try:
                self._open()
            except Exception:
                self._close_transport()
                continue
            self.stats.reopens += 1
            return

    def _send(self, msg: Any) -> None:
        """Send one message (sequence numbered by our MAVLink 2 encoder), if connected."""
        if self._mav is None:
            return
        try:
            self._mav.send(msg)
        except Exception:
            self._transport_failed()

    # --- receiving -----------------------------------------------------------------------

    def _on_readable(self) -> None:
        """The add_reader callback: read what is there, stamp it, parse it."""
        now = time.time()
        try:
            data = self._conn.recv(4096) if self.serial else self._conn.recv()
        except Exception:
            self._transport_failed()
            return
        if not data:
            return
        try:
            messages = self._mav.parse_buffer(bytes(data)) or []
        except Exception:  # robust parsing should not raise; never let bytes kill the link
            self.stats.bad_packets += 1
            self.stats.bad_bytes += len(data)
            return
        for msg in messages:
            self._on_message(msg, now)

    def _on_message(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.stats.bad_packets += 1
            self.stats.bad_bytes += len(msg.data)
            return
        self.stats.packets += 1
        if self.on_packet is not None:
            self.on_packet(bytes(msg.get_msgbuf()), now)
        sender = (msg.get_srcSystem(), msg.get_srcComponent())
        if self.stats.autopilot_id is None:
            if not convert.is_autopilot_heartbeat(msg):
                return
            self.stats.autopilot_id = sender
            self.stats.autopilot = convert.autopilot_name(msg.autopilot)
        if sender != self.stats.autopilot_id:
            return
        self.stats.counts[kind] += 1
        if kind == "HEARTBEAT":
            self._on_heartbeat(now)
        elif kind == "COMMAND_ACK":
            ack = self._ack
            if msg.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL and ack and not ack.done():
                ack.set_result(int(msg.result))
        elif kind == "MISSION_CURRENT":
            self.stats.mission = MissionProgress(
                int(msg.seq), int(getattr(msg, "total", 0) or 0),
                int(getattr(msg, "mission_state", 0) or 0), now,
            )  # fmt: skip
        else:
            # Link down or not: a message from the autopilot is its data. After a silence
            # the streams come back before the next heartbeat (up to a period later): the
            # recording has those packets, and so must the live map (a daemon that waited
            # for the heartbeat left 0.6 s more of silence than its recording holds, and
            # its live map went elsewhere than a replay of that recording).
            self._convert(msg, kind, now)

    def _on_heartbeat(self, now: float) -> None:
        self.stats.last_heartbeat = now
        if self.stats.link_up:
            return
        self.stats.link_up = True
        self._up_since = now
        if self.stats.link_downs:
            self.stats.reconnects += 1
        # Announce ourselves at once: over udpin our earlier heartbeats had no address to go to.
        self._send_heartbeat()
        if self._request_task is not None:
            self._request_task.cancel()
        self._request_task = asyncio.create_task(self._request_streams())

    def _emit(self, sample: NavSample | None) -> None:
        if sample is None:
            return
        self.stats.samples += 1
        if self.on_sample is not None:
            self.on_sample(sample)
            return
        try:
            self._queue.put_nowait(sample)
        except asyncio.QueueFull:
            self.stats.samples_dropped += 1

    def _convert(self, msg: Any, kind: str, now: float) -> None:
        """One autopilot message into the samples of the chosen sources."""
        fallback_due = self._up_since is not None and now - self._up_since >= self.fallback_s
        if kind == "ATTITUDE":
            attitude = convert.attitude_from_mavlink(msg, now)
            if attitude is not None:
                self._attitude = (attitude.roll_rad, attitude.pitch_rad)
            self._emit(attitude)
        imu_name = self._imu_names.get(kind)
        if (
            imu_name is not None
            and convert.imu_source_usable(imu_name, self.stats.autopilot)
            and self._imu_ids.setdefault(kind, convert.imu_instance(msg))
            == convert.imu_instance(msg)
            and self._imu.accept(imu_name, fallback_due)
        ):
            imu = convert.imu_from_mavlink(msg, now)
            self._emit(imu)
            if imu is not None and self._heading.accept("compass", fallback_due):
                roll, pitch = self._attitude or (0.0, 0.0)
                self._emit(convert.compass_heading(imu, roll, pitch, self.declination_rad))
        if kind in convert.GNSS_MESSAGES and self._gnss.accept(kind, fallback_due):
            self._emit(convert.gnss_from_mavlink(msg, now))
        heading_name = self._heading_names.get(kind)
        if heading_name is not None and self._heading.accept(heading_name, fallback_due):
            self._emit(convert.heading_from_mavlink(msg, now))
        if kind in convert.RANGE_MESSAGES:
            # The first downward sensor seen, by id; forward-looking ones are no soundings.
            sensor = convert.downward_range_sensor(msg)
            if (
                sensor is not None
                and self._range_ids.setdefault(kind, sensor) == sensor
                and self._range.accept(kind, fallback_due)
            ):
                self._emit(convert.range_from_mavlink(msg, now))

    # --- sending ---------------------------------------------------------------------------

    async def _heartbeat_loop(self) -> None:
        while True:
            self._send_heartbeat()
            await asyncio.sleep(self.heartbeat_period_s)

    def _send_heartbeat(self) -> None:
        self._send(
            mavlink2.MAVLink_heartbeat_message(
                mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink2.MAV_AUTOPILOT_INVALID,
                0,
                0,
                mavlink2.MAV_STATE_ACTIVE,
                3,
            )
        )

    def _imu_message(self) -> str:
        if self.imu_source != "auto":
            return convert.IMU_MESSAGES[self.imu_source]
        return "HIGHRES_IMU" if self.stats.autopilot == "px4" else "RAW_IMU"

    def _wanted(self) -> dict[str, float]:
        rates = {k: v for k, v in self.rates_hz.items() if k != "IMU"}
        return {self._imu_message(): self.rates_hz["IMU"], **rates}

    async def _request_streams(self) -> None:
        """SET_MESSAGE_INTERVAL one message at a time (a COMMAND_ACK does not say which
        message it answers), two tries each; REQUEST_DATA_STREAM for the rest."""
        assert self.stats.autopilot_id is not None
        target_system, target_component = self.stats.autopilot_id
        refused: dict[int, float] = {}
        for message, rate_hz in self._wanted().items():
            request = StreamRequest(message, round(1e6 / rate_hz))
            self.stats.requests[message] = request
            msg_id = getattr(mavlink2, f"MAVLINK_MSG_ID_{message}")
            for confirmation in range(2):
                self._ack = asyncio.get_running_loop().create_future()
                self._send(
                    mavlink2.MAVLink_command_long_message(
                        target_system,
                        target_component,
                        mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
                        confirmation,
                        msg_id,
                        request.interval_us,
                        0,
                        0,
                        0,
                        0,
                        0,
                    )
                )
                try:
                    result = await asyncio.wait_for(self._ack, self.ack_timeout_s)
                except TimeoutError:
                    request.result = "unanswered"
                    continue
                accepted = result == mavlink2.MAV_RESULT_ACCEPTED
                request.result = "accepted" if accepted else "refused"
                break
            self._ack = None
            if request.result != "accepted":
                stream = _DATA_STREAMS[message]
                refused[stream] = max(refused.get(stream, 0.0), rate_hz)
                request.fallback = True
        for stream, rate_hz in refused.items():
            self._send(
                mavlink2.MAVLink_request_data_stream_message(
                    target_system, target_component, stream, max(1, round(rate_hz)), 1
                )
            )

    # --- watchdog --------------------------------------------------------------------------

    async def _watchdog(self) -> None:
        """Link loss (no autopilot heartbeat) and the per-type rates, four times a second."""
        while True:
            await asyncio.sleep(0.25)
            now = time.time()
            last = self.stats.last_heartbeat
            if self.stats.link_up and last is not None and now - last > self.heartbeat_timeout_s:
                self.stats.link_up = False
                self.stats.link_downs += 1
                self._up_since = None
                if self._request_task is not None:
                    self._request_task.cancel()
                if self.serial and self._conn is not None:
                    # A port that stays open but silent may be a stale device: reopen it.
                    self._close_transport()
                    self._schedule_reopen()
            mark_time, mark_counts = self._rate_mark
            if now - mark_time >= 1.0:
                self.stats.rates_hz = {
                    kind: (count - mark_counts[kind]) / (now - mark_time)
                    for kind, count in self.stats.counts.items()
                }
                self._rate_mark = (now, Counter(self.stats.counts))
