"""A simulated Pixhawk (ArduPilot Rover-like) speaking MAVLink 2 over UDP or a pty.

``AutopilotEmulator`` replays the autopilot's messages of a simulated ``nav.tlog`` (what
``tools.sim.simulate`` writes) at their recorded timing divided by ``time_scale``, re-packed
with its own sequence numbers as system 1 / component 1, and sends its own HEARTBEAT
(MAV_TYPE_SURFACE_BOAT, MAV_AUTOPILOT_ARDUPILOTMEGA) every ``heartbeat_period_s`` of wall
time (the log's own heartbeats and the ground station's messages are not replayed). Given
a ``tools.emulators.clock.PlaybackClock``, it sends each message at the clock's wall time
of its log stamp instead, in step with the other devices on that clock.

It answers MAV_CMD_SET_MESSAGE_INTERVAL with COMMAND_ACK (accepted, or unsupported when
``accept_intervals`` is False) and thins a stream to the requested interval where it can:
every k-th message, k = round(interval / the stream's period in the log), never faster than
the log (intervals are in log time: ``time_scale`` speeds up the clock, not the rates). A
message type sent for several sensors (DISTANCE_SENSOR, RAW_IMU with their ``id``) is one
stream per sensor, each thinned on its own, as an autopilot sends each instance at the
requested interval. Every message the log's autopilot sent is replayed, whatever its type
(DISTANCE_SENSOR and RANGEFINDER soundings included).
REQUEST_DATA_STREAM is recorded. Transports: UDP on 127.0.0.1 (sends to
``target``, and to whoever last wrote to it) or a pseudo-terminal whose slave is reached
through a stable symlink, ``device_path``, as a USB serial device would be.

Fault injection: ``pause_gps(s)``, ``inject_garbage(n)``, ``stop()`` / ``restart()`` (the
device disappears: the pty is closed and its symlink removed; UDP goes silent).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import socket
import tempfile
import time
import tty
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from drivers.mavlink.framing import open_log, scan_tlog
from drivers.mavlink.navlog import NavReadReport

if TYPE_CHECKING:
    from tools.emulators.clock import PlaybackClock

__all__ = ["AutopilotEmulator", "ClientLog", "read_autopilot_messages"]

SYSID = 1
COMPID = 1


@dataclass
class ClientLog:
    """What the emulator received from its client (the companion computer)."""

    heartbeats: list[tuple[int, int]] = field(default_factory=list)
    """(MAV_TYPE, MAV_AUTOPILOT) of each HEARTBEAT."""
    intervals_us: dict[str, int] = field(default_factory=dict)
    """SET_MESSAGE_INTERVAL requests: message name -> interval (µs)."""
    acks_sent: int = 0
    data_streams: list[tuple[int, int, int]] = field(default_factory=list)
    """REQUEST_DATA_STREAM: (stream id, rate Hz, start/stop)."""
    counts: Counter[str] = field(default_factory=Counter)


def read_autopilot_messages(path: str | os.PathLike[str]) -> list[tuple[float, Any]]:
    """(receive time, UNIX s; message) of a .tlog's autopilot (system 1) messages in file
    order, HEARTBEAT aside: what ``AutopilotEmulator`` replays."""
    with open_log(path) as (where, buf):
        report = NavReadReport(str(where), "tlog")
        return [
            (stamp, msg)
            for stamp, msg in scan_tlog(buf, report)
            if msg.get_srcSystem() == SYSID and msg.get_type() != "HEARTBEAT"
        ]


def _stream(msg: Any) -> tuple[str, int]:
    """(message type, sensor id): the stream a message belongs to. Messages with an ``id``
    field (DISTANCE_SENSOR, RAW_IMU, HIGHRES_IMU) are one stream per sensor."""
    # Not getattr(msg, "id"): on messages without that field it is the class's message id.
    has_id = "id" in msg.get_fieldnames()
    return msg.get_type(), int(msg.id) if has_id else 0


class AutopilotEmulator:
    """A MAVLink 2 autopilot fed by recorded messages (see the module docstring).

    messages: (time s, pymavlink message) in time order; time_scale > 1 replays faster;
    wait_for_client: start the replay when the client's first packet arrives (so nothing
    is lost before it listens); heartbeats go out from the start regardless.
    clock: send each message at ``clock.wall(time)`` (waiting for the clock to start)
    instead; the clock's owner then decides when the replay starts, so ``wait_for_client``
    is not consulted and ``time_scale`` must stay 1 (the clock's ``speed`` sets the pace).
    ``client_seen`` is set at the client's first packet; ``replayed`` counts the log's
    messages sent (not thinned out, paused or lost while stopped).
    """

    def __init__(
        self,
        messages: Sequence[tuple[float, Any]],
        *,
        time_scale: float = 1.0,
        heartbeat_period_s: float = 1.0,
        accept_intervals: bool = True,
        wait_for_client: bool = True,
        seed: int = 0,
        clock: PlaybackClock | None = None,
    ) -> None:
        if clock is not None and time_scale != 1.0:
            raise ValueError("AutopilotEmulator: with a clock, the clock's speed sets the pace")
        self.messages = list(messages)
        self.time_scale = time_scale
        self.heartbeat_period_s = heartbeat_period_s
        self.accept_intervals = accept_intervals
        self.wait_for_client = wait_for_client
        self.clock = clock
        self.client = ClientLog()
        self.sent: Counter[str] = Counter()
        self.replayed = 0
        self.dropped_writes = 0
        self.done = asyncio.Event()
        self.device_path: Path | None = None
        self.udp_port: int | None = None
        self._mav = mavlink.MAVLink(None, SYSID, COMPID)
        self._parser = mavlink.MAVLink(None, 255, 0)
        self._parser.robust_parsing = True
        self._period_s = self._periods()
        self._every: dict[tuple[str, int], int] = {}
        self._gps_paused_until = 0.0
        self._rng = random.Random(seed)
        self.client_seen = asyncio.Event()
        self._running = False
        self._fd: int | None = None
        self._slave_fd: int | None = None
        self._sock: socket.socket | None = None
        self._target: tuple[str, int] | None = None
        self._kind = ""
        self._tmpdir: tempfile.TemporaryDirectory[str] | None = None
        self._tasks: list[asyncio.Task[None]] = []

    @classmethod
    def from_tlog(cls, path: str | os.PathLike[str], **options: Any) -> AutopilotEmulator:
        """An emulator replaying the autopilot's messages of a .tlog."""
        return cls(read_autopilot_messages(path), **options)

    def _periods(self) -> dict[tuple[str, int], float]:
        """Median interval (s, log time) between messages of each stream."""
        times: dict[tuple[str, int], list[float]] = {}
        for stamp, msg in self.messages:
            times.setdefault(_stream(msg), []).append(stamp)
        return {
            key: float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1.0
            for key, stamps in times.items()
        }

    # --- transports ------------------------------------------------------------------------

    async def start_udp(self, target_port: int, host: str = "127.0.0.1", port: int = 0) -> int:
        """Bind host:port (0: any free port), send to host:target_port; returns our port."""
        self._kind = "udp"
        self._target = (host, target_port)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, port))
        self._sock.setblocking(False)
        self.udp_port = self._sock.getsockname()[1]
        self._fd = self._sock.fileno()
        await self._start()
        return self.udp_port

    async def start_pty(self) -> Path:
        """Open a pseudo-terminal; returns the device path the client opens (a symlink)."""
        self._kind = "pty"
        self._tmpdir = tempfile.TemporaryDirectory(prefix="seamap-autopilot-")
        self.device_path = Path(self._tmpdir.name) / "ttyPixhawk"
        self._open_pty()
        await self._start()
        return self.device_path

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: bytes pass as they are
        os.set_blocking(master, False)
        self._fd, self._slave_fd = master, slave
        assert self.device_path is not None
        link = self.device_path.with_suffix(".new")
        link.unlink(missing_ok=True)
        link.symlink_to(os.ttyname(slave))
        os.replace(link, self.device_path)

    async def _start(self) -> None:
        self._running = True
        self._watch()
        self._tasks = [
            asyncio.create_task(self._heartbeats()),
            asyncio.create_task(self._replay()),
        ]

    def _watch(self) -> None:
        assert self._fd is not None
        asyncio.get_running_loop().add_reader(self._fd, self._on_readable)

    def stop(self) -> None:
        """The autopilot goes away: the pty closes and its device path disappears; over UDP
        nothing is sent or read. The replay clock keeps running (messages are lost)."""
        self._running = False
        if self._fd is not None:
            asyncio.get_running_loop().remove_reader(self._fd)
        if self._kind == "pty":
            for fd in (self._fd, self._slave_fd):
                if fd is not None:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self._fd = self._slave_fd = None
            if self.device_path is not None:
                self.device_path.unlink(missing_ok=True)

    def restart(self) -> None:
        """The autopilot comes back (a new pty behind the same ``device_path``)."""
        if self._kind == "pty":
            self._open_pty()
        self._running = True
        self._watch()

    async def close(self) -> None:
        """Stop everything and release the transport."""
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []
        if self._running:
            self.stop()
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._tmpdir is not None:
            self._tmpdir.cleanup()
            self._tmpdir = None

    async def __aenter__(self) -> AutopilotEmulator:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # --- fault injection -------------------------------------------------------------------

    def pause_gps(self, seconds: float) -> tuple[float, float]:
        """No GPS_RAW_INT for ``seconds`` of wall time from now; returns (start, end), UNIX s."""
        now = time.time()
        self._gps_paused_until = now + seconds
        return now, self._gps_paused_until

    def inject_garbage(self, n: int) -> None:
        """Send ``n`` random bytes (line noise; may contain MAVLink start markers)."""
        self._write(bytes(self._rng.getrandbits(8) for _ in range(n)))

    # --- I/O -------------------------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        if not self._running or self._fd is None:
            return
        try:
            if self._sock is not None:
                assert self._target is not None
                self._sock.sendto(data, self._target)
            elif os.write(self._fd, data) < len(data):
                self.dropped_writes += 1  # the rest is lost, as on a full UART buffer
        except OSError:
            self.dropped_writes += 1

    def _send(self, msg: Any) -> None:
        self._write(bytes(msg.pack(self._mav)))
        self._mav.seq = (self._mav.seq + 1) % 256
        self.sent[msg.get_type()] += 1

    def _on_readable(self) -> None:
        try:
            if self._sock is not None:
                data, sender = self._sock.recvfrom(65535)
                self._target = sender  # reply to whoever last wrote, as udpin does
            else:
                assert self._fd is not None
                data = os.read(self._fd, 4096)
        except OSError:
            return
        for msg in self._parser.parse_buffer(data) or []:
            self._on_message(msg)

    def _on_message(self, msg: Any) -> None:
        kind = msg.get_type()
        self.client.counts[kind] += 1
        self.client_seen.set()
        if kind == "HEARTBEAT":
            self.client.heartbeats.append((msg.type, msg.autopilot))
        elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            name = mavlink.mavlink_map[int(msg.param1)].msgname
            self.client.intervals_us[name] = int(msg.param2)
            result = mavlink.MAV_RESULT_ACCEPTED
            if not self.accept_intervals:
                result = mavlink.MAV_RESULT_UNSUPPORTED
            else:
                self._set_interval(name, msg.param2)
            self._send(mavlink.MAVLink_command_ack_message(msg.command, result))
            self.client.acks_sent += 1
        elif kind == "REQUEST_DATA_STREAM":
            self.client.data_streams.append(
                (msg.req_stream_id, msg.req_message_rate, msg.start_stop)
            )

    def _set_interval(self, name: str, interval_us: float) -> None:
        """-1 stops the streams of message ``name``, 0 restores their default, else every
        k-th message of each."""
        for key, period in self._period_s.items():
            if key[0] != name:
                continue
            if interval_us < 0:
                self._every[key] = 0
            elif interval_us == 0:
                self._every.pop(key, None)
            else:
                # In log time: replaying faster speeds the clock up, not the requested rates.
                self._every[key] = max(1, round(interval_us * 1e-6 / period))

    # --- tasks -----------------------------------------------------------------------------

    async def _heartbeats(self) -> None:
        heartbeat = mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_SURFACE_BOAT,
            mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            10,  # Rover AUTO
            mavlink.MAV_STATE_ACTIVE,
            3,
        )
        while True:
            self._send(heartbeat)
            await asyncio.sleep(self.heartbeat_period_s)

    async def _replay(self) -> None:
        seen: Counter[tuple[str, int]] = Counter()
        if self.clock is not None:
            for stamp, msg in self.messages:
                await self.clock.sleep_until(stamp)
                self._replay_one(msg, seen)
            self.done.set()
            return
        if self.wait_for_client:
            await self.client_seen.wait()
        if not self.messages:
            self.done.set()
            return
        start_wall = time.monotonic()
        first = self.messages[0][0]
        for stamp, msg in self.messages:
            delay = start_wall + (stamp - first) / self.time_scale - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            self._replay_one(msg, seen)
        self.done.set()

    def _replay_one(self, msg: Any, seen: Counter[tuple[str, int]]) -> None:
        """Send one logged message unless its stream is thinned out or the GPS is paused;
        ``seen`` counts the log's messages by stream so far."""
        kind = msg.get_type()
        key = _stream(msg)
        every = self._every.get(key, 1)
        seen[key] += 1
        if every == 0 or (seen[key] - 1) % every:
            return
        if kind == "GPS_RAW_INT" and time.time() < self._gps_paused_until:
            return
        if self._running:
            self.replayed += 1
        self._send(msg)
