"""Survey missions on the autopilot through MAVSDK (issue 7).

A survey plan is a QGroundControl ``.plan`` file. ``load_plan`` reads it; ``start_survey``
connects to the autopilot, checks that it is ready, uploads the plan as raw
MISSION_ITEM_INTs, reads them back and compares them with what was sent, arms and starts
the mission. ``mission_status``, ``pause_survey`` (HOLD), ``resume_survey`` (AUTO again)
and ``abort_survey`` (RTL) follow and steer it. (The client that asks the boat daemon over
zenoh to open a survey is the daemon's own: ``daemon.request``.)

``drivers.formats.qgc_plan`` reads ``.plan`` files; ``items`` turns a plan into the raw
items to upload and checks what the autopilot reads back; ``mavsdk_link`` holds the
connection URLs and the MAVSDK session with its one bridge to asyncio; ``start`` starts a
survey; ``steer`` follows and steers it.
"""

from drivers.formats.qgc_plan import (
    GLOBAL_FRAMES,
    LOCAL_FRAMES,
    Firmware,
    Plan,
    PlanItem,
    load_plan,
)
from drivers.mission.items import (
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    MAV_FRAME_MISSION,
    RawItem,
    mismatch,
    mission_items,
)
from drivers.mission.mavsdk_link import ATTEMPTS, DEFAULT_TIMEOUT_S, URL_FORMS, mavsdk_url
from drivers.mission.start import MissionStart, Readiness, start_survey
from drivers.mission.steer import (
    MISSION_STATES,
    MissionStatus,
    abort_survey,
    mission_progress_from,
    mission_status,
    pause_survey,
    resume_survey,
)

__all__ = [
    "ATTEMPTS",
    "DEFAULT_TIMEOUT_S",
    "GLOBAL_FRAMES",
    "LOCAL_FRAMES",
    "MAV_CMD_NAV_WAYPOINT",
    "MAV_FRAME_GLOBAL",
    "MAV_FRAME_MISSION",
    "MISSION_STATES",
    "URL_FORMS",
    "Firmware",
    "MissionStart",
    "MissionStatus",
    "Plan",
    "PlanItem",
    "RawItem",
    "Readiness",
    "abort_survey",
    "load_plan",
    "mavsdk_url",
    "mismatch",
    "mission_items",
    "mission_progress_from",
    "mission_status",
    "pause_survey",
    "resume_survey",
    "start_survey",
]
