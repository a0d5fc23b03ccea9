"""The live link to an Oculus sonar: discover it, keep it pinging, turn its stream into Pings.

Transport (PROTOCOLS.md): the sonar broadcasts an OculusStatusMsg by UDP (port 52102) about
once a second; commands and pings use TCP (port 52100); the sonar pings only for a short
while after each SimpleFire, so the link re-sends it every ``fire_interval_s``.

The link never raises on what the sonar sends: bytes that frame as nothing are counted in
``LinkStats.bytes_skipped``, pings that do not parse in ``parse_errors``. A lost connection,
or no ping for ``silence_timeout_s``, closes the socket and reconnects after an exponential,
capped backoff, cut short as soon as the sonar's status broadcast is heard again (the
link listens on the status port all along): a sonar back from a power cut is pinging
again within a second of its first status, not after the backoff's 4 or 8 s. Iterate
``pings()`` inside ``contextlib.aclosing`` (or cancel the task that iterates it) so that
the firing task and the sockets are closed when you stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import AsyncGenerator, Callable
from dataclasses import dataclass, field
from typing import Protocol

from drivers.oculus.framer import OculusFramer
from drivers.oculus.ping import parse_simple_ping
from drivers.oculus.protocol import (
    HEADER_SIZE,
    FireFlags,
    MasterMode,
    MessageHeader,
    MessageId,
    OculusFormatError,
    PingRate,
    SimpleFire,
    StatusMessage,
)
from mapping.samples import Ping

log = logging.getLogger(__name__)

MessageCallback = Callable[[bytes, float], None]
"""Called with every whole message (header + payload) and its receive time (UNIX s)."""

_READ_SIZE = 1 << 16


@dataclass(frozen=True)
class FireSettings:
    """What the link asks the sonar for (sent as SimpleFire v2, range in metres).

    range_m: metres. gain_percent: 0..100. gamma: 0..255 (127 ~ gamma 0.5).
    """

    master_mode: MasterMode = MasterMode.HIGH_FREQUENCY
    range_m: float = 10.0
    gain_percent: float = 50.0
    gamma: int = 127
    ping_rate: PingRate = PingRate.HZ10
    data_16bit: bool = False
    send_gain: bool = False

    def to_message(self) -> SimpleFire:
        """The SimpleFire v2 message for these settings."""
        flags = FireFlags.RANGE_IN_METRES | FireFlags.SIMPLE_RETURN | FireFlags.GAIN_ASSIST
        if self.data_16bit:
            flags |= FireFlags.DATA_16BIT
        if self.send_gain:
            flags |= FireFlags.SEND_GAIN
        return SimpleFire(
            version=2,
            master_mode=int(self.master_mode),
            ping_rate=int(self.ping_rate),
            gamma=self.gamma,
            flags=int(flags),
            range_m=self.range_m,
            gain_percent=self.gain_percent,
        )


@dataclass(frozen=True)
class LinkTiming:
    """Timing of the link, seconds.

    fire_interval_s: SimpleFire re-send period. silence_timeout_s: no ping for this long
    means the link is dead. idle_flush_s: after this long without bytes, a message the
    framer holds back (its tail could start a header) is released. backoff_*: reconnect
    delay, doubled after each failed attempt up to backoff_max_s.
    """

    fire_interval_s: float = 1.0
    silence_timeout_s: float = 5.0
    connect_timeout_s: float = 3.0
    idle_flush_s: float = 0.2
    backoff_initial_s: float = 0.5
    backoff_max_s: float = 10.0


@dataclass
class LinkStats:
    """Counters since the link was made.

    connects: TCP connections made; reconnects: connections after the first one;
    silences: connections given up because no ping came for ``silence_timeout_s``;
    bytes_received / bytes_skipped: from the TCP stream (skipped = framed as nothing);
    messages: whole messages framed; parse_errors: SimplePingResults that did not parse.
    """

    pings: int = 0
    messages: int = 0
    connects: int = 0
    reconnects: int = 0
    silences: int = 0
    bytes_received: int = 0
    bytes_skipped: int = 0
    parse_errors: int = 0
    statuses: int = 0
    """Status messages heard from the sonar (UDP)."""
    last_status_time: float | None = None
    """When the latest was heard (UNIX s)."""
    sonar_address: str | None = None
    last_status: StatusMessage | None = field(default=None, repr=False)


class _Silence(Exception):
    """No ping for ``silence_timeout_s``."""


class _StatusWatch(asyncio.DatagramProtocol):
    """Hands every valid OculusStatusMsg and its sender's address to ``on_status``."""

    def __init__(self, on_status: Callable[[StatusMessage, str], None]) -> None:
        self._on_status = on_status

    def datagram_received(self, data: bytes, addr: tuple[str | bytes, int]) -> None:
        try:
            status = StatusMessage.unpack(data)
        except OculusFormatError:
            return
        self._on_status(status, str(addr[0]))


class SonarSettings(Protocol):
    """What the link reads of the site's ``[sonar]`` table (``daemon.config.SonarConfig``
    has these): the sonar's address and ports, and how to fire it."""

    @property
    def address(self) -> str: ...
    @property
    def tcp_port(self) -> int: ...
    @property
    def status_port(self) -> int: ...
    @property
    def frequency(self) -> str: ...
    @property
    def range_m(self) -> float: ...
    @property
    def gain_percent(self) -> float: ...
    @property
    def gamma(self) -> int: ...
    @property
    def ping_rate_hz(self) -> float: ...
    @property
    def data_bits(self) -> int: ...
    @property
    def send_gain(self) -> bool: ...


class OculusLink:
    """Asyncio client of one Oculus sonar.

    address: "auto" (take the sender of the first status message heard on
    ``status_host:status_port``) or an IPv4 address. ``on_message`` sees every whole message
    with its receive time (UNIX s) before anything parses it, e.g. to record a log.
    """

    def __init__(
        self,
        address: str = "auto",
        *,
        tcp_port: int = 52100,
        status_port: int = 52102,
        status_host: str = "0.0.0.0",
        fire: FireSettings | None = None,
        timing: LinkTiming | None = None,
        on_message: MessageCallback | None = None,
    ) -> None:
        self.address = address
        self.tcp_port = tcp_port
        self.status_port = status_port
        self.status_host = status_host
        self.fire = fire if fire is not None else FireSettings()
        self.timing = timing if timing is not None else LinkTiming()
        self.on_message = on_message
        self.stats = LinkStats()
        self._framer = OculusFramer()
        self._host: str | None = None if address == "auto" else address
        self._heard: asyncio.Event | None = None
        self._found: asyncio.Future[str] | None = None
        self._standby = False
        self._fire_changed: asyncio.Event | None = None

    @staticmethod
    def fire_from_config(config: SonarSettings) -> FireSettings:
        """The SimpleFire settings the ``[sonar]`` table asks for."""
        rates = {rate.hz: rate for rate in PingRate if rate != PingRate.STANDBY}
        return FireSettings(
            master_mode=(
                MasterMode.LOW_FREQUENCY if config.frequency == "low" else MasterMode.HIGH_FREQUENCY
            ),
            range_m=config.range_m,
            gain_percent=config.gain_percent,
            gamma=config.gamma,
            ping_rate=rates[float(config.ping_rate_hz)],
            data_16bit=config.data_bits == 16,
            send_gain=config.send_gain,
        )

    @classmethod
    def from_config(
        cls,
        config: SonarSettings,
        *,
        fire: FireSettings | None = None,
        timing: LinkTiming | None = None,
        on_message: MessageCallback | None = None,
    ) -> OculusLink:
        """A link to the sonar that ``config`` names, listening for status on all interfaces."""
        return cls(
            config.address,
            tcp_port=config.tcp_port,
            status_port=config.status_port,
            fire=fire if fire is not None else cls.fire_from_config(config),
            timing=timing,
            on_message=on_message,
        )

    def _on_status(self, status: StatusMessage, host: str) -> None:
        if self._host is not None and host != self._host:
            return  # another sonar on the network
        self.stats.statuses += 1
        self.stats.last_status = status
        self.stats.last_status_time = time.time()
        if self._heard is not None:
            self._heard.set()
        if self._found is not None and not self._found.done():
            self._found.set_result(host)

    async def _watch_status(self) -> asyncio.BaseTransport | None:
        """Listen on the status port for as long as the link lives (None if the port
        cannot be had: the reconnects then wait out their backoff)."""
        loop = asyncio.get_running_loop()
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _StatusWatch(self._on_status),
                local_addr=(self.status_host, self.status_port),
                reuse_port=False,
            )
        except OSError as e:
            if self.address == "auto":
                raise  # nothing else can find the sonar
            log.warning(
                "Oculus: cannot listen for status on port %d (%s): reconnects wait out "
                "their backoff", self.status_port, e,
            )  # fmt: skip
            return None
        return transport

    async def discover(self) -> str:
        """Wait for a status message on the status port; return the sender's IPv4 address."""
        transport = await self._watch_status()
        try:
            return await self._discover()
        finally:
            if transport is not None:
                transport.close()

    async def _discover(self) -> str:
        self._found = asyncio.get_running_loop().create_future()
        try:
            host = await self._found
        finally:
            self._found = None
        status = self.stats.last_status
        assert status is not None
        log.info("Oculus sonar %d (part %d) at %s", status.device_id, status.part_number, host)
        return host

    async def _pause(self, backoff: float) -> bool:
        """Wait ``backoff`` seconds before reconnecting, or less if the sonar's status is
        heard meanwhile; whether it was."""
        if self._heard is None:
            await asyncio.sleep(backoff)
            return False
        self._heard.clear()
        try:
            await asyncio.wait_for(self._heard.wait(), backoff)
        except TimeoutError:
            return False
        log.info("Oculus: status heard from the sonar, reconnecting now")
        return True

    async def pings(self) -> AsyncGenerator[Ping, None]:
        """Pings as they arrive (stamped on receipt, UNIX s), across reconnects, forever."""
        self._heard = asyncio.Event()
        watch = await self._watch_status()
        try:
            async with contextlib.aclosing(self._connected_pings()) as pings:
                async for ping in pings:
                    yield ping
        finally:
            if watch is not None:
                watch.close()
            self._heard = None

    async def _connected_pings(self) -> AsyncGenerator[Ping, None]:
        backoff = self.timing.backoff_initial_s
        while True:
            if self._host is None:
                self._host = await self._discover()
            try:
                reader, writer = await asyncio.wait_for(
                    asyncio.open_connection(self._host, self.tcp_port),
                    self.timing.connect_timeout_s,
                )
            except (OSError, TimeoutError) as e:
                log.warning("Oculus %s:%d: connect failed (%s)", self._host, self.tcp_port, e)
                if self.address == "auto":
                    self._host = None  # the sonar may have moved: listen again
                heard = await self._pause(backoff)
                backoff = (
                    self.timing.backoff_initial_s
                    if heard
                    else min(2.0 * backoff, self.timing.backoff_max_s)
                )
                continue
            self.stats.connects += 1
            self.stats.reconnects = self.stats.connects - 1
            self.stats.sonar_address = self._host
            self._framer.reset()
            self.stats.bytes_skipped = self._framer.bytes_skipped
            firing = asyncio.create_task(self._keep_firing(writer))
            try:
                async with contextlib.aclosing(self._receive(reader)) as received:
                    async for ping in received:
                        backoff = self.timing.backoff_initial_s
                        yield ping
            except _Silence:
                self.stats.silences += 1
                log.warning(
                    "Oculus: no ping for %.1f s, reconnecting", self.timing.silence_timeout_s
                )
            except OSError as e:
                log.warning("Oculus: connection lost (%s), reconnecting", e)
            finally:
                firing.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await firing
                writer.transport.abort()
            heard = await self._pause(backoff)
            backoff = (
                self.timing.backoff_initial_s
                if heard
                else min(2.0 * backoff, self.timing.backoff_max_s)
            )

    @property
    def standby(self) -> bool:
        """Whether the sonar is asked to stand by (no pings; its status is still heard)."""
        return self._standby

    def set_standby(self, standby: bool) -> None:
        """Ask the sonar to stand by (SimpleFire at ping rate standby: it stops pinging and
        its transducer rests; an M1200d pinging in air overheats) or to ping again. Takes
        effect at once on a live connection, else when it connects. While standing by, a
        quiet sonar is not a dead link."""
        if standby == self._standby:
            return
        self._standby = standby
        log.info("Oculus: %s", "standing by" if standby else "pinging")
        if self._fire_changed is not None:
            self._fire_changed.set()

    def _fire_message(self) -> bytes:
        fire = self.fire
        if self._standby:
            fire = dataclasses.replace(fire, ping_rate=PingRate.STANDBY)
        return fire.to_message().pack()

    async def _keep_firing(self, writer: asyncio.StreamWriter) -> None:
        """Send SimpleFire (or standby) now, every ``fire_interval_s`` and at once when
        ``set_standby`` changes it; stop quietly on a dead socket."""
        changed = self._fire_changed = asyncio.Event()
        try:
            while True:
                changed.clear()
                writer.write(self._fire_message())
                await writer.drain()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(changed.wait(), self.timing.fire_interval_s)
        except OSError:
            return  # the receive side sees the loss and reconnects
        finally:
            self._fire_changed = None

    async def _receive(self, reader: asyncio.StreamReader) -> AsyncGenerator[Ping, None]:
        """Pings from one connection; returns on EOF, raises _Silence on a quiet sonar.

        A message is stamped with the time of the read that completed it, also when the
        framer released it later (held back because its last byte could start a header).
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timing.silence_timeout_s
        last_data = time.time()
        while True:
            if self._standby:
                deadline = loop.time() + self.timing.silence_timeout_s  # quiet by request
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise _Silence
            try:
                data = await asyncio.wait_for(
                    reader.read(_READ_SIZE), min(remaining, self.timing.idle_flush_s)
                )
            except TimeoutError:
                messages = self._framer.flush()
                stamps = [last_data] * len(messages)
            else:
                received = time.time()
                if not data:
                    log.warning("Oculus: connection closed by the sonar, reconnecting")
                    return
                self.stats.bytes_received += len(data)
                held = self._framer.holds_complete_message()
                messages = self._framer.feed(data)
                stamps = [received] * len(messages)
                if held and stamps:
                    stamps[0] = last_data
                last_data = received
            self.stats.bytes_skipped = self._framer.bytes_skipped
            for message, stamp in zip(messages, stamps, strict=True):
                ping = self._handle(message, stamp)
                if ping is not None:
                    deadline = loop.time() + self.timing.silence_timeout_s
                    yield ping

    def _handle(self, message: bytes, received: float) -> Ping | None:
        """Record, count and (for a SimplePingResult) parse one whole message."""
        self.stats.messages += 1
        if self.on_message is not None:
            self.on_message(message, received)
        header = MessageHeader.unpack(message[:HEADER_SIZE])  # the framer checked it
        if header.msg_id != MessageId.SIMPLE_PING_RESULT:
            return None  # Status, Dummy (standby), UserConfig...: nothing to map
        try:
            ping = parse_simple_ping(message, received)
        except Exception as e:  # a corrupt ping is counted and skipped, never raised
            self.stats.parse_errors += 1
            log.debug("Oculus: corrupt ping skipped: %s", e)
            return None
        self.stats.pings += 1
        return ping
