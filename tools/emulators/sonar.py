"""An Oculus M1200d on the wire: UDP status broadcasts, TCP fire in, SimplePingResult v2 out.

The emulator sends an OculusStatusMsg to ``status_to`` about once a second, accepts one TCP
client at a time (a new client replaces the old one), and after each SimpleFire sends pings
from its source for ``fire_timeout_s`` seconds at the fired ping rate (or ``rate_hz``). It
honours the fire's 8/16-bit data size, send-gain flag and gain/gamma (echoed back); the
range demand is informational (the source's images are sent as they are). The ping source
is shared across connections, so pings resume where they stopped after a reconnect.

Given a ``tools.emulators.clock.PlaybackClock`` the emulator plays its source in the
source's own time instead: each ping is sent at ``clock.wall(ping.time)`` (waiting for the
clock to start), if a client is connected and a fire is live then; a ping whose time
passes while the sonar is not fired (no client, or the fire lapsed) is skipped and counted
in ``pings_missed``, never queued, as a real sonar does not ping unfired.

Faults for tests: ``drop_connection()`` aborts the client's socket; ``inject_garbage(n)``
writes ``n`` random bytes between two messages.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
from collections.abc import Iterable, Iterator
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from drivers.oculus.framer import OculusFramer
from drivers.oculus.ping import build_simple_ping
from drivers.oculus.protocol import (
    FireFlags,
    MessageHeader,
    MessageId,
    OculusFormatError,
    PingRate,
    SimpleFire,
    StatusMessage,
)
from mapping.samples import Ping

if TYPE_CHECKING:
    from tools.emulators.clock import PlaybackClock

log = logging.getLogger(__name__)

M1200D_PART_NUMBER = 1042
_SRC_DEVICE_ID = 0x1ED4
_HANDLER_EXIT_S = 0.5  # how long close() lets client handlers end by themselves


def _with_data_size(image: np.ndarray, want_16bit: bool) -> np.ndarray:
    """The image as 16-bit (8-bit scaled by 257) or 8-bit (top byte) as the fire asks."""
    if want_16bit and image.dtype == np.uint8:
        return image.astype(np.uint16) * np.uint16(257)
    if not want_16bit and image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return image


def encode_ping(ping: Ping, fire: SimpleFire) -> bytes:
    """The SimplePingResult v2 an M1200d would send for ``ping`` under ``fire``."""
    image = _with_data_size(ping.image, bool(fire.flags & FireFlags.DATA_16BIT))
    echoed = dataclasses.replace(ping, image=image, gain_percent=fire.gain_percent)
    return build_simple_ping(
        echoed,
        version=2,
        send_gain=bool(fire.flags & FireFlags.SEND_GAIN),
        ping_rate=fire.ping_rate,
        gamma=fire.gamma,
        flags=fire.flags,
        src_device_id=_SRC_DEVICE_ID,
    )


class SonarEmulator:
    """An asyncio Oculus sonar on ``host`` (use ``async with`` or ``start()``/``close()``).

    pings: the ping source, consumed as pings are sent. tcp_port: 0 picks a free port
    (read ``tcp_port`` after ``start()``). status_to: (host, port) for the status messages,
    None for none. status_interval_s, fire_timeout_s: seconds. rate_hz: overrides the fired
    ping rate (Hz), e.g. to run tests fast. clock: send each ping at ``clock.wall(ping.time)``
    rather than at a rate (see the module docstring; ``rate_hz`` is then unused).

    Counters: ``pings_sent``; ``pings_missed`` (clock only: pings skipped while not fired).
    ``done`` is set when the source is exhausted.
    """

    def __init__(
        self,
        pings: Iterable[Ping],
        *,
        host: str = "127.0.0.1",
        tcp_port: int = 0,
        status_to: tuple[str, int] | None = ("127.0.0.1", 52102),
        status_interval_s: float = 1.0,
        fire_timeout_s: float = 2.0,
        rate_hz: float | None = None,
        device_id: int = 1,
        seed: int = 0,
        clock: PlaybackClock | None = None,
    ) -> None:
        self.host = host
        self.status_to = status_to
        self.status_interval_s = status_interval_s
        self.fire_timeout_s = fire_timeout_s
        self.rate_hz = rate_hz
        self.device_id = device_id
        self.fires_received = 0
        self.clock = clock
        self.pings_sent = 0
        self.pings_missed = 0
        self.connections = 0
        self.done = asyncio.Event()
        self.last_fire: SimpleFire | None = None
        self._requested_port = tcp_port
        self._pings = iter(pings)
        self._rng = np.random.default_rng(seed)
        self._fire_time = -float("inf")  # loop time of the last fire
        self._fired = asyncio.Event()
        self._server: asyncio.Server | None = None
        self._status_task: asyncio.Task[None] | None = None
        self._player_task: asyncio.Task[None] | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._handlers: set[asyncio.Task[object]] = set()

    @property
    def tcp_port(self) -> int:
        """The TCP port the emulator listens on (after ``start()``)."""
        if self._server is None:
            raise RuntimeError("SonarEmulator not started")
        return int(self._server.sockets[0].getsockname()[1])

    @property
    def pinging(self) -> bool:
        """Whether a fire arrived within ``fire_timeout_s`` asking for pings."""
        return self._live_fire() is not None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self._requested_port)
        if self.status_to is not None:
            self._status_task = asyncio.create_task(self._broadcast_status(self.status_to))
        if self.clock is not None:
            self._player_task = asyncio.create_task(self._play(self.clock))

    async def close(self) -> None:
        for own in (self._status_task, self._player_task):
            if own is not None:
                own.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await own
        self._status_task = self._player_task = None
        if self._server is not None:
            self._server.close()
        self.drop_connection()
        if self._handlers:
            # An aborted connection ends its handler; cancel only what is still running
            # after a moment (Python 3.11's start_server logs a cancelled handler as an error).
            await asyncio.wait(set(self._handlers), timeout=_HANDLER_EXIT_S)
        for task in list(self._handlers):
            task.cancel()
        await asyncio.gather(*self._handlers, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()

    async def __aenter__(self) -> SonarEmulator:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def drop_connection(self) -> None:
        """Abort the client's TCP connection (as a sonar reboot or a cut cable would)."""
        if self._writer is not None:
            self._writer.transport.abort()
            self._writer = None

    async def wait_fired(self) -> None:
        """Return once a fire asking for pings is live (see ``pinging``)."""
        while not self.pinging:
            self._fired.clear()
            await self._fired.wait()

    def inject_garbage(self, n_bytes: int) -> None:
        """Write ``n_bytes`` random bytes to the client between two messages.

        The bytes hold no 0x53 (the first byte of the Oculus magic), so that a framer can
        drop exactly these bytes; a real corruption may also fake a header.
        """
        if self._writer is None:
            return
        garbage = self._rng.integers(0, 255, n_bytes, dtype=np.uint8)
        garbage[garbage == 0x53] = 0x00
        self._writer.write(garbage.tobytes())

    def _status_message(self) -> bytes:
        return StatusMessage(
            device_id=self.device_id,
            part_number=M1200D_PART_NUMBER,
            ip_addr=self.host,
            ip_mask="255.255.255.0",
            src_device_id=_SRC_DEVICE_ID,
        ).pack()

    async def _broadcast_status(self, target: tuple[str, int]) -> None:
        loop = asyncio.get_running_loop()
        # Unconnected socket: an unreachable port raises nothing (as broadcast on a LAN).
        transport, _ = await loop.create_datagram_endpoint(
            asyncio.DatagramProtocol, local_addr=(self.host, 0), allow_broadcast=True
        )
        try:
            message = self._status_message()
            while True:
                transport.sendto(message, target)
                await asyncio.sleep(self.status_interval_s)
        finally:
            transport.close()

    def _live_fire(self) -> SimpleFire | None:
        fire = self.last_fire
        if fire is None or fire.ping_rate == PingRate.STANDBY:
            return None
        age = asyncio.get_running_loop().time() - self._fire_time
        return fire if age <= self.fire_timeout_s else None

    def _period_s(self, fire: SimpleFire) -> float:
        rate = self.rate_hz
        if rate is None:
            try:
                rate = PingRate(fire.ping_rate).hz
            except ValueError:
                rate = PingRate.HZ10.hz
        return 1.0 / rate

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        self.drop_connection()  # one client at a time
        self._writer = writer
        self.connections += 1
        # With a clock, one player task sends to whichever client is connected.
        pinger = asyncio.create_task(self._send_pings(writer)) if self.clock is None else None
        framer = OculusFramer()
        try:
            while data := await reader.read(1 << 16):
                for message in framer.feed(data):
                    self._command(message)
        except OSError:
            pass
        finally:
            if pinger is not None:
                pinger.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await pinger
            if self._writer is writer:
                self._writer = None
            writer.transport.abort()
            self._handlers.discard(task)

    def _command(self, message: bytes) -> None:
        header = MessageHeader.unpack(message)
        if header.msg_id != MessageId.SIMPLE_FIRE:
            return
        try:
            fire = SimpleFire.unpack(message)
        except OculusFormatError:
            return
        self.last_fire = fire
        self.fires_received += 1
        self._fire_time = asyncio.get_running_loop().time()
        self._fired.set()

    async def _send_pings(self, writer: asyncio.StreamWriter) -> None:
        """Ping while fired; wait for the next fire when not."""
        try:
            while True:
                fire = self._live_fire()
                if fire is None:
                    self._fired.clear()
                    await self._fired.wait()
                    continue
                ping = next(self._pings, None)
                if ping is None:
                    log.info("sonar emulator: ping source exhausted")
                    self.done.set()
                    return
                writer.write(encode_ping(ping, fire))
                await writer.drain()
                self.pings_sent += 1
                await asyncio.sleep(self._period_s(fire))
        except OSError:
            return

    async def _play(self, clock: PlaybackClock) -> None:
        """Send each ping of the source at ``clock.wall(ping.time)`` if fired then, else skip
        it. The next ping is read (and encoded for the last fire) in a worker thread while
        waiting, so that a large ping does not hold up the event loop at its send time."""
        ahead: tuple[Ping, SimpleFire | None, bytes | None] | None = await asyncio.to_thread(
            _read_ahead, self._pings, self.last_fire
        )
        while ahead is not None:
            ping, encoded_for, message = ahead
            await clock.sleep_until(ping.time)
            fire, writer = self._live_fire(), self._writer
            if fire is None or writer is None:
                self.pings_missed += 1
            else:
                if message is None or fire != encoded_for:
                    message = encode_ping(ping, fire)
                try:
                    writer.write(message)
                    await writer.drain()
                except OSError:  # the connection died under the write: lost with it
                    self.pings_missed += 1
                else:
                    self.pings_sent += 1
            ahead = await asyncio.to_thread(_read_ahead, self._pings, self.last_fire)
        log.info("sonar emulator: ping source exhausted")
        self.done.set()


def _read_ahead(
    pings: Iterator[Ping], fire: SimpleFire | None
) -> tuple[Ping, SimpleFire | None, bytes | None] | None:
    """The next ping, the fire it was encoded for and its encoding (None without a fire);
    None once ``pings`` is exhausted. Runs in a worker thread."""
    ping = next(pings, None)
    if ping is None:
        return None
    if fire is None or fire.ping_rate == PingRate.STANDBY:
        return ping, None, None
    return ping, fire, encode_ping(ping, fire)
