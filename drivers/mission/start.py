"""Starting a survey on the autopilot: ``start_survey``.

It connects to the autopilot, checks that it is ready (a 3D GPS fix and a home position),
uploads the plan as raw MISSION_ITEM_INTs, reads the mission back and compares it with what
was sent, arms and starts the mission (MAVSDK sends DO_SET_MODE AUTO, then MISSION_START).
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

from drivers.errors import SeamapError
from drivers.formats.qgc_plan import Firmware, Plan
from drivers.mission.items import RawItem, mismatch, mission_items
from drivers.mission.mavsdk_link import DEFAULT_TIMEOUT_S, Link, connected

_FIX_NAMES = ("no GPS", "no fix", "2D fix", "3D fix", "DGPS fix", "RTK float", "RTK fixed")


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
    async with connected(url, timeout_s) as link:
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


def _firmware(plan: Plan, link: Link, override: Firmware | None) -> Firmware:
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


async def _wait_ready(link: Link, timeout_s: float) -> Readiness:
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
