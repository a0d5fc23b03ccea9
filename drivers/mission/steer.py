"""Following and steering a running mission on the autopilot.

``mission_status`` reads its progress (MISSION_CURRENT), flight mode and arming state;
``pause_survey`` holds (HOLD), ``resume_survey`` continues (AUTO again), ``abort_survey``
returns to launch (RTL). ``mission_progress_from`` gives the daemon the same progress from
the MISSION_CURRENT on its own link.
"""

from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import dataclass
from typing import Any

from mavsdk.plugins.mavlink_direct import MavlinkDirect

from drivers.errors import SeamapError
from drivers.formats.qgc_plan import Firmware
from drivers.mission.mavsdk_link import DEFAULT_TIMEOUT_S, Link, connected, hand_over

log = logging.getLogger(__name__)

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
    async with connected(url, timeout_s) as link:
        direct = MavlinkDirect(link.system)
        loop = asyncio.get_running_loop()
        heard: asyncio.Future[tuple[Any, ...]] = loop.create_future()

        def on_message(message: Any, _user_data: Any) -> None:
            hand_over(loop, heard, (message.fields_json,))

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


async def _item_count(link: Link, timeout_s: float) -> int | None:
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
    async with connected(url, timeout_s) as link:
        await link.exchange(
            "holding (pausing the mission)", link.mission.pause_mission_async, timeout_s
        )


async def resume_survey(url: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Continue the mission from its current item (AUTO again)."""
    async with connected(url, timeout_s) as link:
        await link.exchange(
            "continuing the mission (AUTO)", link.mission.start_mission_async, timeout_s
        )


async def abort_survey(url: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Give up the survey and return to launch (RTL)."""
    async with connected(url, timeout_s) as link:
        await link.exchange(
            "returning to launch (RTL)", link.action.return_to_launch_async, timeout_s
        )
