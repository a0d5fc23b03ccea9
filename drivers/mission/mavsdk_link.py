"""The link to the autopilot through MAVSDK: its URL and a session with it.

``mavsdk_url`` checks a connection URL and translates older spellings; ``connected`` opens
a ground-station session with the first autopilot heard and yields a ``Link``, which holds
the plugins the survey commands use.

MAVSDK (the ``mavsdk`` 4.x binding around ``libcmavsdk``) is driven through its
callback entry points (``*_async``), bridged to asyncio in one place, ``hand_over`` (used by
``Link.call`` for every request): ``mavsdk.asyncio`` runs the blocking variants on executor
threads, and a thread still blocked in MAVSDK when a time-out gives up keeps the process
from exiting. Every exchange (``Link.exchange``) has a deadline and a bounded number of
retries; a refusal is a ``SeamapError`` that says, in one line, what the autopilot lacks or
refused.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager, suppress
from typing import Any

import mavsdk
from mavsdk import Autopilot, ComponentType, Configuration, ConnectionResult, Mavsdk
from mavsdk.plugins.action import Action
from mavsdk.plugins.mission_raw import MissionRaw
from mavsdk.plugins.telemetry import Telemetry

from drivers.errors import SeamapError
from drivers.formats.qgc_plan import Firmware

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT_S = 20.0
"""The longest one step may take: hearing the autopilot, its GPS fix and home, one
exchange (upload, read-back, arm, start) with its retries."""
ATTEMPTS = 3
"""Tries per exchange while the autopilot answers busy, times out or the link hiccups."""
SETTLE_S = 1.0
"""How long a link being closed waits for MAVSDK to answer the requests it gave up on."""

_HOST_PORT = re.compile(r"^(udpin|udpout|tcpin|tcpout)://(\[[^\]]*\]|[^:/\[\]]*):(\d+)$")
_PYMAVLINK = re.compile(r"^(udpin|udpout|udp|tcp):([^:/]*):(\d+)$")
_SERIAL = re.compile(r"^serial://(/[^:]+):(\d+)$")
URL_FORMS = "udpin://HOST:PORT, udpout://HOST:PORT, tcpout://HOST:PORT or serial:///dev/ttyX:BAUD"


def mavsdk_url(url: str) -> str:
    """The MAVSDK 4 connection URL for ``url``: ``udpin://HOST:PORT`` (listen; HOST 0.0.0.0
    for every interface), ``udpout://HOST:PORT`` (send to), ``tcpin://``/``tcpout://`` and
    ``serial:///dev/ttyACM0:57600`` pass as they are; pymavlink's ``udpin:HOST:PORT`` /
    ``udpout:HOST:PORT`` and MAVSDK 1's ``udp://:14540`` are translated. SeamapError else."""
    url = url.strip()
    legacy = re.match(r"^udp://([^:/]*):(\d+)$", url)
    if legacy:  # MAVSDK 1 spelling: udp:// listened
        url = f"udpin://{legacy.group(1) or '0.0.0.0'}:{legacy.group(2)}"
    pymavlink = _PYMAVLINK.match(url)
    if pymavlink:
        kind = {"udp": "udpin", "tcp": "tcpout"}.get(pymavlink.group(1), pymavlink.group(1))
        url = f"{kind}://{pymavlink.group(2)}:{pymavlink.group(3)}"
    host_port = _HOST_PORT.match(url)
    if host_port:
        kind, host, port = host_port.groups()
        if not host:
            if kind not in ("udpin", "tcpin"):
                raise SeamapError(f"{url!r}: {kind} needs the HOST to send to")
            host = "0.0.0.0"
        if not 0 < int(port) <= 65535:
            raise SeamapError(f"{url!r}: port {port} is not 1..65535")
        return f"{kind}://{host}:{int(port)}"
    serial = _SERIAL.match(url)
    if serial:
        if int(serial.group(2)) <= 0:
            raise SeamapError(f"{url!r}: baud rate {serial.group(2)} is not a rate")
        return url
    if url.startswith("serial://") or url.startswith("/dev/"):
        raise SeamapError(f"{url!r}: a serial link needs its baud rate, serial:///dev/ttyX:BAUD")
    raise SeamapError(f"{url!r}: not a MAVLink connection URL ({URL_FORMS})")


_logs_routed = False


def _route_mavsdk_logs() -> None:
    """MAVSDK writes its own log lines on stderr; send them to ``logging`` (debug) instead,
    so that a refusal stays one line."""
    global _logs_routed
    if not _logs_routed:

        def to_logging(level: Any, message: str, file: str | None, line: int) -> bool:
            log.debug("mavsdk %s: %s", getattr(level, "name", level), message)
            return True  # handled: no default output

        mavsdk.log_subscribe(to_logging)
        _logs_routed = True


def _settle(future: asyncio.Future[tuple[Any, ...]], value: tuple[Any, ...]) -> None:
    if not future.done():
        future.set_result(value)


def hand_over(
    loop: asyncio.AbstractEventLoop, future: asyncio.Future[tuple[Any, ...]], value: tuple[Any, ...]
) -> None:
    """From MAVSDK's callback thread to the waiting coroutine (the one crossing)."""
    with suppress(RuntimeError):  # the loop is closed: nobody waits any more
        loop.call_soon_threadsafe(_settle, future, value)


_REASONS = {
    "TIMEOUT": "the autopilot did not answer",
    "DENIED": "the autopilot refused it",
    "COMMAND_DENIED": "the autopilot refused it",
    "BUSY": "the autopilot is busy",
    "NO_SYSTEM": "the autopilot is gone",
    "CONNECTION_ERROR": "the link failed",
    "INT_MESSAGES_NOT_SUPPORTED": "the autopilot does not take MISSION_ITEM_INT",
    "TOO_MANY_MISSION_ITEMS": "the autopilot has no room for that many items",
    "UNSUPPORTED": "the autopilot does not support it",
    "NO_MISSION_AVAILABLE": "the autopilot holds no mission",
    "INVALID_ARGUMENT": "the autopilot found an item invalid",
    "INVALID_SEQUENCE": "the autopilot saw items out of sequence",
    "PROTOCOL_ERROR": "the mission protocol went wrong",
}
_TRANSIENT = frozenset({"TIMEOUT", "BUSY", "CONNECTION_ERROR", "UNKNOWN", "ERROR"})


def _reason(result: Any) -> str:
    name = getattr(result, "name", str(result))
    return f"{_REASONS.get(name, name.lower().replace('_', ' '))} ({name})"


class Link:
    """A MAVSDK ground station with one autopilot: the plugins used here and the one bridge
    from MAVSDK's callback thread to asyncio."""

    def __init__(self, url: str, system: Any) -> None:
        self.url = url
        self.system = system
        self.telemetry = Telemetry(system)
        self.mission = MissionRaw(system)
        self.action = Action(system)
        self._armed: bool | None = None  # from the HEARTBEATs after the plugin came
        self._unanswered: list[asyncio.Future[tuple[Any, ...]]] = []
        """Requests given up on (timed out): MAVSDK still answers them, from its thread,
        at the latest while it is torn down (``settle``)."""
        self.telemetry.subscribe_armed(self._on_armed)

    def _on_armed(self, armed: Any, _user_data: Any) -> None:  # MAVSDK's callback thread
        self._armed = bool(armed)

    async def armed(self, timeout_s: float) -> bool:
        """Armed or not, as the next HEARTBEAT says: before one, the telemetry plugin
        answers "disarmed" whatever the vehicle is."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + min(timeout_s, 3.0)  # HEARTBEATs come at 1 Hz
        while self._armed is None and loop.time() < deadline:
            await asyncio.sleep(0.05)
        return self._armed if self._armed is not None else bool(self.telemetry.armed())

    def autopilot(self) -> Firmware | None:
        kind = self.system.autopilot_type()
        return {Autopilot.ARDUPILOT: Firmware.ARDUPILOT, Autopilot.PX4: Firmware.PX4}.get(kind)

    async def call(self, start: Callable[[Callable[..., None]], None], timeout_s: float) -> Any:
        """Start one MAVSDK ``*_async`` request and wait for its callback; returns what the
        callback got (result first). TimeoutError after ``timeout_s``."""
        loop = asyncio.get_running_loop()
        answered: asyncio.Future[tuple[Any, ...]] = loop.create_future()

        def on_result(*args: Any) -> None:  # the last argument is MAVSDK's user data
            hand_over(loop, answered, args[:-1])

        start(on_result)
        try:
            return await asyncio.wait_for(asyncio.shield(answered), max(timeout_s, 0.0))
        except TimeoutError:
            self._unanswered.append(answered)
            raise

    async def settle(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for the answers to requests given up on (a cancelled
        upload's comes promptly): destroying MAVSDK while one is on its way into Python
        from its thread crashed the process once (a segmentation fault in mavsdk-python's
        callback)."""
        pending = [f for f in self._unanswered if not f.done()]
        if pending:
            await asyncio.wait(pending, timeout=timeout_s)
        self._unanswered.clear()

    async def exchange(
        self,
        what: str,
        start: Callable[[Callable[..., None]], None],
        timeout_s: float,
        on_timeout: Callable[[], Any] | None = None,
    ) -> tuple[Any, ...]:
        """``call`` until it succeeds, retrying what may pass (busy, timed out) up to
        ATTEMPTS times within ``timeout_s``; SeamapError naming ``what`` and why else."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        for attempt in range(1, ATTEMPTS + 1):
            try:
                answer = await self.call(start, deadline - loop.time())
            except TimeoutError:
                if on_timeout is not None:
                    _quietly(on_timeout)
                raise SeamapError(
                    f"{what} failed: the autopilot did not answer within {timeout_s:g} s"
                ) from None
            result = answer[0]
            if result.name == "SUCCESS":
                return tuple(answer)
            left = deadline - loop.time()
            if result.name not in _TRANSIENT or attempt == ATTEMPTS or left < 1.0:
                tries = f" after {attempt} attempts" if attempt > 1 else ""
                raise SeamapError(f"{what} failed{tries}: {_reason(result)}")
            log.info("%s: %s, trying again", what, _reason(result))
            await asyncio.sleep(min(0.5 * attempt, left / 4))
        raise AssertionError("unreachable")


def _quietly(step: Callable[[], Any]) -> None:
    try:
        step()
    except Exception as exc:  # nothing to cancel any more
        log.debug("ignored: %s", exc)


@asynccontextmanager
async def connected(url: str, timeout_s: float) -> AsyncIterator[Link]:
    """A link to the first autopilot heard on ``url`` within ``timeout_s``."""
    url = mavsdk_url(url)
    _route_mavsdk_logs()
    instance = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        result = instance.add_any_connection(url)
        if result != ConnectionResult.SUCCESS:
            raise SeamapError(f"{url}: cannot open the link ({result.name})")
        loop = asyncio.get_running_loop()
        heard: asyncio.Future[tuple[Any, ...]] = loop.create_future()

        def on_autopilot(system: Any) -> None:
            hand_over(loop, heard, (system,))

        handle = instance.first_autopilot_async(timeout_s, on_autopilot)
        try:
            (system,) = await asyncio.wait_for(heard, timeout_s + 5.0)
        except TimeoutError:
            system = None
        finally:
            instance.cancel_first_autopilot(handle)
        if system is None:
            raise SeamapError(f"no autopilot heard on {url} within {timeout_s:g} s")
        link = Link(url, system)
        try:
            yield link
        finally:
            await link.settle(SETTLE_S)
    finally:
        instance.destroy()
