"""Survey missions on the autopilot through MAVSDK (issue 7).

A survey plan is a QGroundControl ``.plan`` file (JSON: ``mission.items`` of SimpleItems
with command, frame, params and autoContinue; ``mission.plannedHomePosition``;
``mission.firmwareType`` 3 = ArduPilot, 12 = PX4). ``load_plan`` reads it; ``start_survey``
connects to the autopilot, checks that it is ready (a 3D GPS fix and a home position),
uploads the plan as raw MISSION_ITEM_INTs (ArduPilot: a home placeholder at seq 0, which
the autopilot overwrites with its home; PX4: none), reads the mission back and compares it
with what was sent, arms and starts the mission (MAVSDK sends DO_SET_MODE AUTO, then
MISSION_START). ``mission_status``, ``pause_survey`` (HOLD), ``resume_survey`` (AUTO again)
and ``abort_survey`` (RTL) follow and steer it. ``request_survey_start`` then asks the
boat daemon, over zenoh, to open a survey.

MAVSDK (the ``mavsdk`` 4.x binding around ``libcmavsdk``) is driven through its
callback entry points (``*_async``), bridged to asyncio in one place, ``_Link.call``:
``mavsdk.asyncio`` runs the blocking variants on executor threads, and a thread still
blocked in MAVSDK when a time-out gives up keeps the process from exiting. Every exchange
here has a deadline and a bounded number of retries; a refusal is a ``SeamapError`` that
says, in one line, what the autopilot lacks or refused.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import re
import time
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager, suppress
from dataclasses import dataclass, replace
from enum import Enum
from pathlib import Path
from typing import Any

import mavsdk
from mavsdk import Autopilot, ComponentType, Configuration, ConnectionResult, Mavsdk
from mavsdk.plugins.action import Action
from mavsdk.plugins.mavlink_direct import MavlinkDirect
from mavsdk.plugins.mission_raw import MissionItem, MissionRaw
from mavsdk.plugins.telemetry import Telemetry

from seamap.config import SiteConfig, ZenohConfig
from seamap.errors import SeamapError

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT_S = 20.0
"""The longest one step may take: hearing the autopilot, its GPS fix and home, one
exchange (upload, read-back, arm, start) with its retries."""
ATTEMPTS = 3
"""Tries per exchange while the autopilot answers busy, times out or the link hiccups."""

MAV_CMD_NAV_WAYPOINT = 16
MAV_FRAME_GLOBAL = 0
MAV_FRAME_MISSION = 2
GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})
"""Frames whose x/y are latitude/longitude (degE7 in MISSION_ITEM_INT)."""
LOCAL_FRAMES = frozenset({1, 4, 7, 8, 9, 12, 20, 21})
"""Frames whose x/y are metres (times 1e4 in MISSION_ITEM_INT)."""
_FRAME_TWIN = {5: 0, 6: 3, 11: 10}
"""Deprecated *_INT frames and the frame they mean (autopilots answer with the latter)."""


class Firmware(Enum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"


_QGC_FIRMWARE = {3: Firmware.ARDUPILOT, 12: Firmware.PX4}  # MAV_AUTOPILOT values


# --- the plan ------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlanItem:
    """One SimpleItem of a ``.plan``: a MAVLink mission command; params 5..7 are latitude,
    longitude (degrees) and altitude (metres) in global frames; NaN where the file says null."""

    command: int
    frame: int
    params: tuple[float, float, float, float, float, float, float]
    autocontinue: bool = True


@dataclass(frozen=True)
class Plan:
    path: Path
    items: tuple[PlanItem, ...]
    home: tuple[float, float, float] | None
    """plannedHomePosition: latitude, longitude (degrees), altitude AMSL (metres)."""
    firmware: Firmware | None
    """From mission.firmwareType; None when the plan is for any autopilot."""


def load_plan(path: str | Path) -> Plan:
    """Read a QGroundControl ``.plan``; SeamapError naming the file and what is wrong."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such plan file") from None
    except IsADirectoryError:
        raise SeamapError(f"{path}: is a directory, not a plan file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SeamapError(f"{path}: cannot read the plan ({exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SeamapError(f"{path}: not a QGroundControl plan (not JSON: {exc})") from None
    try:
        return _plan_from(path, data)
    except _BadPlan as exc:
        raise SeamapError(f"{path}: not a usable plan ({exc})") from None


class _BadPlan(ValueError):
    pass


def _plan_from(path: Path, data: Any) -> Plan:
    if not isinstance(data, dict) or not isinstance(data.get("mission"), dict):
        raise _BadPlan("no 'mission' object")
    if data.get("fileType", "Plan") != "Plan":
        raise _BadPlan(f"fileType is {data.get('fileType')!r}, not 'Plan'")
    mission = data["mission"]
    raw_items = mission.get("items")
    if not isinstance(raw_items, list):
        raise _BadPlan("mission.items is not a list")
    items: list[PlanItem] = []
    for index, raw in enumerate(raw_items):
        items.extend(_items_of(f"mission.items[{index}]", raw))
    if not items:
        raise _BadPlan("mission.items holds no mission item")
    if len(items) >= 65535:
        raise _BadPlan(f"{len(items)} mission items, more than MAVLink can carry")
    home = mission.get("plannedHomePosition")
    if home is not None:
        if not (isinstance(home, list) and len(home) == 3 and all(_is_number(v) for v in home)):
            raise _BadPlan("mission.plannedHomePosition is not [lat, lon, alt]")
        if not (abs(home[0]) <= 90 and abs(home[1]) <= 180):
            raise _BadPlan(f"mission.plannedHomePosition {home} is not on Earth")
        home = (float(home[0]), float(home[1]), float(home[2]))
    firmware_type = mission.get("firmwareType")
    firmware = _QGC_FIRMWARE.get(firmware_type) if isinstance(firmware_type, int) else None
    return Plan(path, tuple(items), home, firmware)


def _items_of(where: str, raw: Any) -> list[PlanItem]:
    if not isinstance(raw, dict):
        raise _BadPlan(f"{where} is not an object")
    kind = raw.get("type")
    if kind == "SimpleItem":
        return [_simple_item(where, raw)]
    transect = raw.get("TransectStyleComplexItem")
    if kind == "ComplexItem" and isinstance(transect, dict):
        # QGroundControl keeps the waypoints it generated for a survey / corridor scan.
        inner = transect.get("Items")
        if isinstance(inner, list) and inner:
            return [_simple_item(f"{where}.Items[{i}]", item) for i, item in enumerate(inner)]
    what = raw.get("complexItemType", kind)
    raise _BadPlan(f"{where} is a {what!r} item; only SimpleItems (waypoints) are supported")


def _simple_item(where: str, raw: Any) -> PlanItem:
    if not isinstance(raw, dict) or raw.get("type", "SimpleItem") != "SimpleItem":
        raise _BadPlan(f"{where} is not a SimpleItem")
    command, frame, params = raw.get("command"), raw.get("frame"), raw.get("params")
    if not (isinstance(command, int) and 0 <= command <= 65535):
        raise _BadPlan(f"{where}: command {command!r} is not a MAV_CMD number")
    if not (isinstance(frame, int) and 0 <= frame <= 255):
        raise _BadPlan(f"{where}: frame {frame!r} is not a MAV_FRAME number")
    if not (isinstance(params, list) and len(params) == 7):
        raise _BadPlan(f"{where}: params is not a list of 7 values")
    if not all(v is None or _is_number(v) for v in params):
        raise _BadPlan(f"{where}: params {params} holds something other than numbers and null")
    values = tuple(math.nan if v is None else float(v) for v in params)
    autocontinue = raw.get("autoContinue", True)
    if not isinstance(autocontinue, bool):
        raise _BadPlan(f"{where}: autoContinue is not true or false")
    if frame in GLOBAL_FRAMES:
        lat, lon, alt = values[4:7]
        if not (abs(lat) <= 90 and abs(lon) <= 180 and math.isfinite(alt)):
            raise _BadPlan(f"{where}: position {lat}, {lon}, {alt} m is not a place")
    elif frame not in LOCAL_FRAMES and any(v != round(v) for v in values[4:6] if math.isfinite(v)):
        raise _BadPlan(f"{where}: params 5 and 6 of a frame {frame} item travel as integers")
    return PlanItem(command, frame, values, autocontinue)  # type: ignore[arg-type]


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


# --- raw mission items ----------------------------------------------------------------------


@dataclass(frozen=True)
class RawItem:
    """A MISSION_ITEM_INT as it travels: x/y are degE7 in global frames, metres * 1e4 in
    local ones, the value itself otherwise; z is altitude (metres)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float

    def to_mavsdk(self) -> Any:
        return MissionItem(
            self.seq, self.frame, self.command, self.current, self.autocontinue,
            self.param1, self.param2, self.param3, self.param4, self.x, self.y, self.z, 0,
        )  # fmt: skip

    @classmethod
    def from_mavsdk(cls, item: Any) -> RawItem:
        return cls(
            int(item.seq), int(item.frame), int(item.command), int(item.current),
            int(item.autocontinue), float(item.param1), float(item.param2),
            float(item.param3), float(item.param4), int(item.x), int(item.y), float(item.z),
        )  # fmt: skip


def mission_items(plan: Plan, firmware: Firmware) -> list[RawItem]:
    """The items to upload: the plan's, numbered from 0, behind a home placeholder at seq 0
    for ArduPilot (which keeps its home there and overwrites what is sent)."""
    items = [_raw(item) for item in plan.items]
    if firmware is Firmware.ARDUPILOT:
        lat, lon, alt = plan.home or _first_position(plan)
        placeholder = RawItem(
            0, MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.0, 0.0, 0.0,
            round(lat * 1e7), round(lon * 1e7), alt,
        )  # fmt: skip
        items.insert(0, placeholder)
    return [replace(item, seq=seq, current=int(seq == 0)) for seq, item in enumerate(items)]


def _first_position(plan: Plan) -> tuple[float, float, float]:
    for item in plan.items:
        if item.frame in GLOBAL_FRAMES:
            return item.params[4], item.params[5], 0.0
    return 0.0, 0.0, 0.0


def _raw(item: PlanItem) -> RawItem:
    p = item.params
    if item.frame in GLOBAL_FRAMES:
        x, y = round(p[4] * 1e7), round(p[5] * 1e7)
    elif item.frame in LOCAL_FRAMES:
        x, y = (0 if math.isnan(v) else round(v * 1e4) for v in p[4:6])
    else:
        x, y = (0 if math.isnan(v) else round(v) for v in p[4:6])
    return RawItem(0, item.frame, item.command, 0, int(item.autocontinue),
                   p[0], p[1], p[2], p[3], x, y, p[6])  # fmt: skip


def mismatch(
    sent: Sequence[RawItem], read_back: Sequence[RawItem], firmware: Firmware
) -> str | None:
    """None when the autopilot holds what was sent, else the first difference in words.

    Same commands, frames, x/y integers, altitude within 1 cm, params within float32
    rounding, autocontinue. Allowed for, as autopilots answer: an *_INT frame comes back as
    its plain twin, a MAV_FRAME_MISSION item (no position) as frame 0, a null (NaN) param
    as 0; ArduPilot answers 0 for the params it does not keep for a command and puts its
    home at seq 0 (not compared)."""
    if len(sent) != len(read_back):
        return f"the autopilot holds {len(read_back)} items, {len(sent)} were sent"
    ardupilot = firmware is Firmware.ARDUPILOT
    for ours, theirs in zip(sent[ardupilot:], read_back[ardupilot:], strict=True):
        where = f"item {ours.seq}"
        if theirs.command != ours.command:
            return f"{where}: command {theirs.command} read back, {ours.command} sent"
        if not _frames_agree(ours.frame, theirs.frame):
            return f"{where}: frame {theirs.frame} read back, {ours.frame} sent"
        if (theirs.x, theirs.y) != (ours.x, ours.y):
            return f"{where}: x/y {theirs.x}, {theirs.y} read back, {ours.x}, {ours.y} sent"
        if not _same(ours.z, theirs.z, 0.01):
            return f"{where}: altitude {theirs.z:g} m read back, {ours.z:g} m sent"
        for n in range(1, 5):
            a, b = getattr(ours, f"param{n}"), getattr(theirs, f"param{n}")
            tolerance = 1e-5 * max(1.0, abs(a) if math.isfinite(a) else 0.0)
            if not (_same(a, b, tolerance) or (ardupilot and b == 0.0)):
                return f"{where}: param{n} {b:g} read back, {a:g} sent"
        if bool(theirs.autocontinue) != bool(ours.autocontinue):
            return (
                f"{where}: autocontinue {theirs.autocontinue} read back, {ours.autocontinue} sent"
            )
    return None


def _frames_agree(sent: int, read_back: int) -> bool:
    sent, read_back = _FRAME_TWIN.get(sent, sent), _FRAME_TWIN.get(read_back, read_back)
    return sent == read_back or (sent == MAV_FRAME_MISSION and read_back == MAV_FRAME_GLOBAL)


def _same(a: float, b: float, tolerance: float) -> bool:
    a = 0.0 if math.isnan(a) else a
    b = 0.0 if math.isnan(b) else b
    return abs(a - b) <= tolerance


# --- connection URLs ------------------------------------------------------------------------

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


# --- the MAVSDK link ------------------------------------------------------------------------

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


def _hand_over(
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
_FIX_NAMES = ("no GPS", "no fix", "2D fix", "3D fix", "DGPS fix", "RTK float", "RTK fixed")


def _reason(result: Any) -> str:
    name = getattr(result, "name", str(result))
    return f"{_REASONS.get(name, name.lower().replace('_', ' '))} ({name})"


class _Link:
    """A MAVSDK ground station with one autopilot: the plugins used here and the one bridge
    from MAVSDK's callback thread to asyncio."""

    def __init__(self, url: str, system: Any) -> None:
        self.url = url
        self.system = system
        self.telemetry = Telemetry(system)
        self.mission = MissionRaw(system)
        self.action = Action(system)
        self._armed: bool | None = None  # from the HEARTBEATs after the plugin came
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
            _hand_over(loop, answered, args[:-1])

        start(on_result)
        return await asyncio.wait_for(answered, max(timeout_s, 0.0))

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
async def _connected(url: str, timeout_s: float) -> AsyncIterator[_Link]:
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
            _hand_over(loop, heard, (system,))

        handle = instance.first_autopilot_async(timeout_s, on_autopilot)
        try:
            (system,) = await asyncio.wait_for(heard, timeout_s + 5.0)
        except TimeoutError:
            system = None
        finally:
            instance.cancel_first_autopilot(handle)
        if system is None:
            raise SeamapError(f"no autopilot heard on {url} within {timeout_s:g} s")
        yield _Link(url, system)
    finally:
        instance.destroy()


# --- starting a survey ----------------------------------------------------------------------


@dataclass(frozen=True)
class Readiness:
    fix: str
    satellites: int
    home: tuple[float, float]
    armable: bool
    """The autopilot's pre-arm checks pass (SYS_STATUS); informative only: MAVSDK's own
    server never reports it, and some firmware does not either. The arm command decides."""


@dataclass(frozen=True)
class MissionStart:
    firmware: Firmware
    plan_items: int
    items_sent: int
    """Items uploaded, with ArduPilot's home placeholder."""
    readiness: Readiness
    was_armed: bool


async def start_survey(
    plan: Plan, url: str, timeout_s: float = DEFAULT_TIMEOUT_S, firmware: Firmware | None = None
) -> MissionStart:
    """Upload ``plan`` to the autopilot on ``url``, check it, arm and start it (AUTO).

    ``firmware`` overrides the plan's. SeamapError, with the mission not started, when no
    autopilot answers, it has no 3D fix or no home within ``timeout_s``, the upload fails
    or reads back different, or it refuses to arm or to start (then it is disarmed again
    if it was armed here)."""
    async with _connected(url, timeout_s) as link:
        firmware = _firmware(plan, link, firmware)
        readiness = await _wait_ready(link, timeout_s)
        items = mission_items(plan, firmware)
        await link.exchange(
            f"uploading the mission ({len(items)} items)",
            lambda done: link.mission.upload_mission_async([i.to_mavsdk() for i in items], done),
            timeout_s,
            on_timeout=link.mission.cancel_mission_upload,
        )
        _, downloaded = await link.exchange(
            "reading the mission back",
            link.mission.download_mission_async,
            timeout_s,
            on_timeout=link.mission.cancel_mission_download,
        )
        problem = mismatch(items, [RawItem.from_mavsdk(i) for i in downloaded], firmware)
        if problem is not None:
            raise SeamapError(f"the mission read back differs from the plan: {problem}")
        was_armed = await link.armed(timeout_s)
        if not was_armed:
            try:
                await link.exchange("arming", link.action.arm_async, timeout_s)
            except SeamapError as exc:
                checks = "" if readiness.armable else "; its pre-arm checks do not pass"
                raise SeamapError(
                    f"not armable: {exc}{checks}; the mission is uploaded, not started"
                ) from None
        try:
            await link.exchange(
                "starting the mission (AUTO)", link.mission.start_mission_async, timeout_s
            )
        except SeamapError as exc:
            if was_armed:
                raise
            # Armed by us and not going anywhere: leave it as it was found.
            try:
                await link.exchange("disarming", link.action.disarm_async, min(timeout_s, 5.0))
            except SeamapError as disarm:
                raise SeamapError(f"{exc}; it stays ARMED ({disarm})") from None
            raise SeamapError(f"{exc}; disarmed again") from None
        return MissionStart(firmware, len(plan.items), len(items), readiness, was_armed)


def _firmware(plan: Plan, link: _Link, override: Firmware | None) -> Firmware:
    reported = link.autopilot()
    chosen = override or plan.firmware or reported
    if chosen is None:
        raise SeamapError(
            f"{plan.path}: the plan names no firmware (mission.firmwareType) and the "
            "autopilot says neither ArduPilot nor PX4"
        )
    if reported is not None and reported is not chosen:
        raise SeamapError(
            f"{plan.path}: a {chosen.value} plan, but the autopilot runs {reported.value}"
        )
    return chosen


async def _wait_ready(link: _Link, timeout_s: float) -> Readiness:
    """Wait for a 3D fix and a home position; SeamapError naming what is missing."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while True:
        gps = link.telemetry.gps_info()
        home = link.telemetry.home()
        health = link.telemetry.health()
        fix_type = int(gps.fix_type)
        has_home = bool(health.is_home_position_ok) or math.isfinite(home.latitude_deg)
        if fix_type >= 3 and has_home:
            return Readiness(
                _FIX_NAMES[min(fix_type, 6)], int(gps.num_satellites),
                (float(home.latitude_deg), float(home.longitude_deg)), bool(health.is_armable),
            )  # fmt: skip
        if loop.time() >= deadline:
            if fix_type < 3:
                raise SeamapError(
                    f"no GPS fix: the autopilot reports {_FIX_NAMES[max(0, fix_type)]} with "
                    f"{gps.num_satellites} satellites after {timeout_s:g} s; a survey needs "
                    "a 3D fix"
                )
            raise SeamapError(
                f"no home position from the autopilot after {timeout_s:g} s (it sets one "
                "once its position estimate is good)"
            )
        await asyncio.sleep(0.2)


# --- following and steering -----------------------------------------------------------------

MISSION_STATES = {1: "no mission", 2: "not started", 3: "active", 4: "paused", 5: "complete"}
"""MISSION_CURRENT.mission_state (MAVLink MISSION_STATE)."""


def mission_progress_from(current_seq: int, total: int) -> dict[str, Any]:
    """Mission progress from MISSION_CURRENT: ``{"current": seq, "total": n, "fraction"}``.

    ``total`` as MISSION_CURRENT gives it (the mission's item count; 0 = not told, 65535 =
    no mission: both make total and fraction None). Fraction of the items passed, 0..1."""
    known = 0 < total < 65535
    fraction = min(max(current_seq / total, 0.0), 1.0) if known else None
    return {"current": current_seq, "total": total if known else None, "fraction": fraction}


@dataclass(frozen=True)
class MissionStatus:
    current: int
    """MISSION_CURRENT.seq: the item being worked on."""
    total: int | None
    state: str | None
    flight_mode: str
    armed: bool

    def as_dict(self) -> dict[str, Any]:
        progress = mission_progress_from(self.current, self.total or 0)
        return {
            **progress,
            "state": self.state,
            "flight_mode": self.flight_mode,
            "armed": self.armed,
        }


async def mission_status(url: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> MissionStatus:
    """The mission's progress from the autopilot's MISSION_CURRENT (the item count from a
    download when the autopilot does not say), its flight mode and arming state."""
    async with _connected(url, timeout_s) as link:
        direct = MavlinkDirect(link.system)
        loop = asyncio.get_running_loop()
        heard: asyncio.Future[tuple[Any, ...]] = loop.create_future()

        def on_message(message: Any, _user_data: Any) -> None:
            _hand_over(loop, heard, (message.fields_json,))

        direct.subscribe_message("MISSION_CURRENT", on_message)
        try:
            (fields_json,) = await asyncio.wait_for(heard, timeout_s)
        except TimeoutError:
            raise SeamapError(
                f"the autopilot sent no MISSION_CURRENT within {timeout_s:g} s"
            ) from None
        fields = json.loads(fields_json)
        total: int | None = int(fields.get("total", 0))
        if not total or total >= 65535:
            total = await _item_count(link, timeout_s)
        state = MISSION_STATES.get(int(fields.get("mission_state", 0)))
        mode = link.telemetry.flight_mode()
        return MissionStatus(
            int(fields["seq"]), total, state, getattr(mode, "name", str(mode)),
            await link.armed(timeout_s),
        )  # fmt: skip


async def _item_count(link: _Link, timeout_s: float) -> int | None:
    """MISSION_CURRENT's idea of the total: the items, without ArduPilot's home."""
    try:
        _, items = await link.exchange(
            "reading the mission", link.mission.download_mission_async, timeout_s,
            on_timeout=link.mission.cancel_mission_download,
        )  # fmt: skip
    except SeamapError as exc:
        log.info("mission item count unknown: %s", exc)
        return None
    return len(items) - (1 if link.autopilot() is Firmware.ARDUPILOT else 0)


async def pause_survey(url: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Hold where the boat is (HOLD mode); ``resume_survey`` continues."""
    async with _connected(url, timeout_s) as link:
        await link.exchange(
            "holding (pausing the mission)", link.mission.pause_mission_async, timeout_s
        )


async def resume_survey(url: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Continue the mission from its current item (AUTO again)."""
    async with _connected(url, timeout_s) as link:
        await link.exchange(
            "continuing the mission (AUTO)", link.mission.start_mission_async, timeout_s
        )


async def abort_survey(url: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Give up the survey and return to launch (RTL)."""
    async with _connected(url, timeout_s) as link:
        await link.exchange(
            "returning to launch (RTL)", link.action.return_to_launch_async, timeout_s
        )


# --- telling the daemon ---------------------------------------------------------------------


@dataclass(frozen=True)
class DaemonTarget:
    """Where the boat daemon's survey control answers: a zenoh client session and the
    vehicle id (key ``seamap/{vehicle}/control/survey``)."""

    vehicle: str
    zenoh: ZenohConfig


@dataclass(frozen=True)
class DaemonAnswer:
    survey: str | None
    """The survey the daemon opened, or None with ``problem`` saying why not."""
    problem: str | None = None


def daemon_target(
    config: SiteConfig | None, endpoint: str | None = None, vehicle: str | None = None
) -> DaemonTarget | None:
    """The daemon to tell, from a site config (its [daemon] vehicle; its [zenoh] connect
    endpoints and its listen endpoints reached on loopback: the daemon's own config on the
    boat works as is) and/or an explicit zenoh ``endpoint`` and ``vehicle``. None when
    neither config nor endpoint is given. SeamapError for a malformed endpoint or id."""
    from seamap.shore_state import id_problem
    from seamap.zenoh_io import endpoint_problem

    if config is None and endpoint is None:
        if vehicle is not None:
            raise SeamapError("--vehicle needs --daemon ENDPOINT or --config SITE.toml")
        return None
    if vehicle is None and config is None:
        raise SeamapError("--daemon needs --vehicle ID (or --config with a [daemon] vehicle)")
    vehicle = vehicle if vehicle is not None else config.daemon.vehicle  # type: ignore[union-attr]
    if id_problem(vehicle):
        raise SeamapError(f"vehicle {vehicle!r}: {id_problem(vehicle)}")
    if endpoint is not None:
        problem = endpoint_problem(endpoint)
        if problem is not None:
            raise SeamapError(f"--daemon {endpoint!r}: not a zenoh endpoint ({problem})")
        connect = [endpoint]
    else:
        assert config is not None
        connect = [*config.zenoh.connect, *(_on_loopback(e) for e in config.zenoh.listen)]
        if not connect:
            raise SeamapError("config: [zenoh] has no endpoint to reach the daemon on")
    config_file = config.zenoh.config_file if config is not None else ""
    session = ZenohConfig(
        mode="client", listen=[], connect=connect, multicast_scouting=False,
        config_file=config_file,
    )  # fmt: skip
    return DaemonTarget(vehicle, session)


def _on_loopback(endpoint: str) -> str:
    """A listen endpoint on every interface, as this machine reaches it."""
    return endpoint.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:")


def request_survey_start(target: DaemonTarget, timeout_s: float = 10.0) -> DaemonAnswer:
    """Ask the daemon to open a survey: a zenoh ``get`` on its control key with payload
    ``{"action": "start"}``; its reply ``{"ok": true, "survey": ID}`` (the survey already
    open, if one is: asking again is harmless). Tried up to ATTEMPTS times while the daemon
    cannot be reached or nothing answers; blocks up to about ``timeout_s``; never raises."""
    from seamap import zenoh_io

    deadline = time.monotonic() + timeout_s
    answer = DaemonAnswer(None, "not asked")
    for _ in range(ATTEMPTS):
        answer, retry = _ask_daemon(target, deadline)
        if answer.survey is not None or not retry or deadline - time.monotonic() < 1.0:
            break
        log.info("daemon: %s; asking again", answer.problem)
        time.sleep(0.5)
    if answer.survey is None and answer.problem is None:
        key = zenoh_io.control_key(target.vehicle)
        answer = DaemonAnswer(None, f"nothing answered on {key} (is the daemon running?)")
    return answer


def _ask_daemon(target: DaemonTarget, deadline: float) -> tuple[DaemonAnswer, bool]:
    """One request; the answer (``problem`` None: nobody answered) and whether to retry."""
    from seamap import zenoh_io

    try:
        session = zenoh_io.open_session(target.zenoh)
    except SeamapError as exc:
        where = ", ".join(target.zenoh.connect)
        return DaemonAnswer(None, f"cannot reach the daemon at {where} ({_short(str(exc))})"), True
    try:
        payload = zenoh_io.json_bytes({"action": "start"})
        key = zenoh_io.control_key(target.vehicle)
        timeout_s = max(deadline - time.monotonic(), 0.1)
        problem = None
        for reply in session.get(key, payload=payload, timeout=timeout_s):
            if reply.ok is None:
                problem = f"the daemon answered with an error: {_text(reply.err)}"
                continue
            try:
                answer = json.loads(reply.ok.payload.to_bytes())
            except ValueError:
                problem = "the daemon's answer is not JSON"
                continue
            if isinstance(answer, dict) and answer.get("ok") and answer.get("survey"):
                return DaemonAnswer(str(answer["survey"])), False
            error = answer.get("error") if isinstance(answer, dict) else answer
            problem = f"the daemon did not open a survey ({error})"
        return DaemonAnswer(None, problem), problem is None  # a refusal is not retried
    except Exception as exc:  # zenoh raises its own ZError for a session gone bad
        return DaemonAnswer(None, f"the request to the daemon failed ({_short(str(exc))})"), True
    finally:
        session.close()


def _text(error: Any) -> str:
    try:
        return str(error.payload.to_bytes().decode("utf-8", "replace"))
    except Exception:  # no payload to show
        return "?"


def _short(message: str) -> str:
    """zenoh's messages end with the Rust source position: drop it."""
    return re.sub(r"\s+at /\S+\.rs:\d+\.?", "", message).strip()


__all__ = [
    "DEFAULT_TIMEOUT_S",
    "DaemonAnswer",
    "DaemonTarget",
    "Firmware",
    "MissionStart",
    "MissionStatus",
    "Plan",
    "PlanItem",
    "RawItem",
    "Readiness",
    "abort_survey",
    "daemon_target",
    "load_plan",
    "mavsdk_url",
    "mismatch",
    "mission_items",
    "mission_progress_from",
    "mission_status",
    "pause_survey",
    "request_survey_start",
    "resume_survey",
    "start_survey",
]
