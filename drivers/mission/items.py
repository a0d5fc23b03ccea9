"""The mission as it travels: raw MISSION_ITEM_INTs and their read-back check.

``mission_items`` turns a ``Plan`` into the items to upload (ArduPilot: a home placeholder
at seq 0, which the autopilot overwrites with its home; PX4: none); ``mismatch`` compares
what the autopilot reads back with what was sent.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

from mavsdk.plugins.mission_raw import MissionItem

from drivers.formats.qgc_plan import GLOBAL_FRAMES, LOCAL_FRAMES, Firmware, Plan, PlanItem

MAV_CMD_NAV_WAYPOINT = 16
MAV_FRAME_GLOBAL = 0
MAV_FRAME_MISSION = 2
_FRAME_TWIN = {5: 0, 6: 3, 11: 10}
"""Deprecated *_INT frames and the frame they mean (autopilots answer with the latter)."""


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
