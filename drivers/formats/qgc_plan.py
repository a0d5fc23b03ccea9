"""QGroundControl ``.plan`` files: ``load_plan`` reads one into a ``Plan``.

A plan is JSON: ``mission.items`` of SimpleItems with command, frame, params and
autoContinue (the waypoints QGroundControl stored for a survey or corridor scan are taken
too); ``mission.plannedHomePosition``; ``mission.firmwareType`` 3 = ArduPilot, 12 = PX4;
and, in plans ``seamap survey plan`` wrote, ``seamap.area``: the GeoJSON geometry the
mission is to cover (for the daemon's coverage; its polygons are checked by whoever uses
it). Anything else is a ``SeamapError`` naming the file and what is wrong with it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError

GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})
"""Frames whose x/y are latitude/longitude (degE7 in MISSION_ITEM_INT)."""
LOCAL_FRAMES = frozenset({1, 4, 7, 8, 9, 12, 20, 21})
"""Frames whose x/y are metres (times 1e4 in MISSION_ITEM_INT)."""


class Firmware(Enum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"


FIRMWARE_TYPES = {Firmware.ARDUPILOT.value: 3, Firmware.PX4.value: 12}
"""The ``.plan``'s ``mission.firmwareType`` (a MAV_AUTOPILOT value) of each firmware, for
the reader here and the writer (``drivers.formats.plan_export``)."""
_QGC_FIRMWARE = {code: Firmware(name) for name, code in FIRMWARE_TYPES.items()}


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
    area: dict[str, Any] | None = None
    """``seamap.area``: the GeoJSON geometry (WGS84) the mission is to cover, if given."""


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
    extra = data.get("seamap")
    area = extra.get("area") if isinstance(extra, dict) else None
    if area is not None and not (isinstance(area, dict) and isinstance(area.get("type"), str)):
        raise _BadPlan("seamap.area is not a GeoJSON geometry")
    return Plan(path, tuple(items), home, firmware, area)


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
