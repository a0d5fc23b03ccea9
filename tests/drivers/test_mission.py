"""Survey missions (``drivers.mission``, ``seamap survey``) against a real autopilot peer.

The peer is MAVSDK itself configured as an AUTOPILOT, with the server plugins of its
server component (MissionRawServer, ActionServer, TelemetryServer, MavlinkDirectServer),
on 127.0.0.1 over UDP, a free port per test. It sends to the port the client listens on
(``udpin://``), as SITL or a telemetry radio bridge does. Like real firmware it streams
MISSION_CURRENT, position, home and GPS while it runs. The daemon is a zenoh queryable
on 127.0.0.1 (free TCP port, no multicast scouting).

The peer runs on MAVSDK's own threads and a publishing thread of its own, through the
callback API: the client's asyncio loop (or the CLI's ``asyncio.run``) never waits for it.
"""

from __future__ import annotations

import asyncio
import json
import math
import sys
import threading
import time
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk
from mavsdk.plugins.action_server import ActionServer, AllowableFlightModes
from mavsdk.plugins.mavlink_direct_server import MavlinkDirectServer, MavlinkMessage
from mavsdk.plugins.mission_raw_server import MissionRawServer
from mavsdk.plugins.telemetry_server import (
    Battery,
    FixType,
    GpsInfo,
    Heading,
    Position,
    RawGps,
    TelemetryServer,
    VelocityNed,
)

from daemon import request
from daemon.config import SiteConfig, ZenohConfig, config_from_dict
from drivers import mission
from drivers.errors import SeamapError
from drivers.mission import Firmware, RawItem
from drivers.zenoh_io import control_key, json_bytes, open_session
from seamap.cli import build_parser, main
from tests.ports import free_tcp_port, free_udp_port

HOME = (47.3977419, 8.5455938, 488.25)  # lat, lon (degrees), AMSL (m)
WAYPOINTS = [(47.3978, 8.5456), (47.39795, 8.54575), (47.3981, 8.5456), (47.39825, 8.54575)]
SPEED_MPS = 1.5
VEHICLE = "testboat"
SLACK_S = 5.0  # what a refusal may take beyond its time-out on a slow machine


AREA = {
    "type": "Polygon",
    "coordinates": [[[8.5455, 47.3977], [8.5459, 47.3977], [8.5459, 47.3984], [8.5455, 47.3984],
                     [8.5455, 47.3977]]],
}  # fmt: skip
"""The area the small plan covers (GeoJSON, WGS84), as ``seamap survey plan`` writes it."""


def write_plan(folder: Path, firmware_type: int = 3, area: dict[str, Any] | None = None) -> Path:
    """A small QGroundControl plan: set the speed, then four waypoints (relative alt 0);
    with ``area``, the area it covers as ``seamap survey plan`` keeps it."""
    items: list[dict[str, Any]] = [
        {"type": "SimpleItem", "autoContinue": True, "command": 178, "doJumpId": 1,
         "frame": 2, "params": [1, SPEED_MPS, -1, 0, 0, 0, 0]},
    ]  # fmt: skip
    for n, (lat, lon) in enumerate(WAYPOINTS, start=2):
        items.append(
            {"type": "SimpleItem", "autoContinue": True, "command": 16, "doJumpId": n,
             "frame": 3, "params": [0, 0, 0, None, lat, lon, 0], "AltitudeMode": 1}
        )  # fmt: skip
    plan = {
        "fileType": "Plan",
        "groundStation": "QGroundControl",
        "version": 1,
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
        "mission": {
            "cruiseSpeed": SPEED_MPS,
            "firmwareType": firmware_type,
            "globalPlanAltitudeMode": 1,
            "hoverSpeed": 5,
            "items": items,
            "plannedHomePosition": list(HOME),
            "vehicleType": 10,
            "version": 2,
        },
    }
    if area is not None:
        plan["seamap"] = {"version": 1, "area": area}
    path = folder / ("ardupilot.plan" if firmware_type == 3 else "px4.plan")
    path.write_text(json.dumps(plan, indent=2))
    return path


class FakeAutopilot:
    """MAVSDK as the autopilot, on ``udpout://127.0.0.1:PORT``; ``auto``: whether it takes
    the mission mode.

    ``missions``: "accept" (MissionRawServer), "silent" (declares MISSION_INT, never
    answers an upload) or "reject" (answers MISSION_COUNT with MISSION_ACK DENIED)."""

    def __init__(
        self, port: int, *, fix: FixType = FixType.FIX_3D, armable: bool = True,
        missions: str = "accept", auto: bool = True,
    ) -> None:  # fmt: skip
        self.fix = fix
        self.uploads: list[list[RawItem]] = []
        self.arm_requests: list[tuple[str, bool]] = []
        self.mode_requests: list[tuple[str, str]] = []
        self.current = -1
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.AUTOPILOT))
        result = self.mavsdk.add_any_connection(f"udpout://127.0.0.1:{port}")
        assert result == ConnectionResult.SUCCESS
        # Every plugin is kept: one that is collected stops answering.
        self.component = self.mavsdk.server_component()
        self.missions = MissionRawServer(self.component)
        self.actions = ActionServer(self.component)
        self.telemetry = TelemetryServer(self.component)
        self.direct = MavlinkDirectServer(self.component)
        self.missions.subscribe_incoming_mission(self._on_mission)
        self.missions.subscribe_current_item_changed(self._on_current)
        self.actions.subscribe_arm_disarm(self._on_arm)
        self.actions.subscribe_flight_mode_change(self._on_mode)
        self.actions.set_armable(armable, armable)
        self.actions.set_disarmable(True, True)
        self.actions.set_allowable_flight_modes(AllowableFlightModes(*[auto] * 7))
        if missions in ("silent", "reject"):
            # Creating the server plugin declared MISSION_INT; without it nothing answers.
            self.missions.destroy()
        if missions == "reject":
            self.direct.subscribe_message("MISSION_COUNT", self._deny)
        self._stop = threading.Event()
        self._publisher = threading.Thread(target=self._publish, daemon=True)
        self._publisher.start()

    def _on_mission(self, result: Any, plan: Any, _user_data: Any) -> None:
        self.uploads.append([RawItem.from_mavsdk(item) for item in plan.mission_items])

    def _on_current(self, item: Any, _user_data: Any) -> None:
        self.current = int(item.seq)

    def _on_arm(self, result: Any, arm: Any, _user_data: Any) -> None:
        self.arm_requests.append((result.name, bool(arm.arm)))

    def _on_mode(self, result: Any, mode: Any, _user_data: Any) -> None:
        self.mode_requests.append((result.name, mode.name))

    def _deny(self, message: Any, _user_data: Any) -> None:
        ack = {"target_system": message.system_id, "target_component": message.component_id,
               "type": 14, "mission_type": 0}  # fmt: skip
        self.direct.send_message(
            MavlinkMessage("MISSION_ACK", 0, 0, message.system_id, message.component_id,
                           json.dumps(ack))
        )  # fmt: skip

    def _publish(self) -> None:
        lat, lon, alt = HOME
        while not self._stop.wait(0.2):
            satellites = 12 if self.fix >= FixType.FIX_3D else 0
            gps = RawGps(int(time.time() * 1e6), lat, lon, alt, 0.8, 1.2, 0.0, 0.0, alt,
                         0.5, 0.8, 0.1, 1.0, 0.0)  # fmt: skip
            self.telemetry.publish_raw_gps(gps, GpsInfo(satellites, self.fix))
            self.telemetry.publish_sys_status(Battery(12.4, 0.9), True, True, True, True, True)
            if self.fix >= FixType.FIX_3D:
                here = Position(lat, lon, alt, 0.0)
                self.telemetry.publish_position(here, VelocityNed(0.0, 0.0, 0.0), Heading(90.0))
                self.telemetry.publish_home(here)
            if self.uploads and self.current >= 0:  # MISSION_CURRENT, as firmware streams it
                fields = {"seq": self.current, "total": len(self.uploads[-1]),
                          "mission_state": 3, "mission_mode": 1}  # fmt: skip
                self.direct.send_message(
                    MavlinkMessage("MISSION_CURRENT", 0, 0, 0, 0, json.dumps(fields))
                )

    def close(self) -> None:
        self._stop.set()
        self._publisher.join(timeout=5)
        self.mavsdk.destroy()


@pytest.fixture
def port() -> int:
    return free_udp_port()


@pytest.fixture
def autopilot(port: int) -> Iterator[FakeAutopilot]:
    peer = FakeAutopilot(port)
    yield peer
    peer.close()


def url_of(port: int) -> str:
    return f"udpin://127.0.0.1:{port}"


def wait_for(condition: Any, timeout_s: float = 10.0) -> None:
    """Until ``condition()`` holds (bounded). The fake autopilot's MAVSDK hands its
    callbacks (arm, mode) over on its own thread: a command answered to the client may be
    recorded a moment later, later still on a loaded machine."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the condition never came true"
        time.sleep(0.05)


def nan_free(item: RawItem) -> tuple[Any, ...]:
    return tuple(
        "nan" if isinstance(v, float) and math.isnan(v) else v for v in vars(item).values()
    )


# --- the plan and its items -----------------------------------------------------------------


def test_a_plan_reads_as_its_simple_items(tmp_path: Path) -> None:
    plan = mission.load_plan(write_plan(tmp_path))
    assert plan.firmware is Firmware.ARDUPILOT
    assert plan.home == HOME
    assert [item.command for item in plan.items] == [178, 16, 16, 16, 16]
    assert math.isnan(plan.items[1].params[3])
    assert [item.params[4:6] for item in plan.items[1:]] == WAYPOINTS
    assert mission.load_plan(write_plan(tmp_path, 12)).firmware is Firmware.PX4


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("{not json", "not JSON"),
        ('{"fileType": "Plan"}', "no 'mission' object"),
        ('{"mission": {"items": []}}', "no mission item"),
        ('{"mission": {"items": [{"type": "ComplexItem", "complexItemType": "structureScan"}]}}',
         "structureScan"),
        ('{"mission": {"items": [{"type": "SimpleItem", "command": 16, "frame": 3, '
         '"params": [0, 0, 0, 0, 95.0, 8.5, 0]}]}}', "not a place"),
        ('{"mission": {"items": [{"type": "SimpleItem", "command": 16, "frame": 3, '
         '"params": [0, 0, 0]}]}}', "7 values"),
    ],
)  # fmt: skip
def test_a_bad_plan_is_named_with_the_reason(tmp_path: Path, text: str, reason: str) -> None:
    path = tmp_path / "bad.plan"
    path.write_text(text)
    with pytest.raises(SeamapError, match=reason) as caught:
        mission.load_plan(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


def test_ardupilot_gets_a_home_placeholder_px4_does_not(tmp_path: Path) -> None:
    plan = mission.load_plan(write_plan(tmp_path))
    ardupilot = mission.mission_items(plan, Firmware.ARDUPILOT)
    px4 = mission.mission_items(plan, Firmware.PX4)
    assert [i.seq for i in ardupilot] == list(range(6)) and [i.seq for i in px4] == list(range(5))
    home = ardupilot[0]
    assert (home.command, home.frame) == (16, 0)
    assert (home.x, home.y, home.z) == (round(HOME[0] * 1e7), round(HOME[1] * 1e7), HOME[2])
    assert [nan_free(i)[1:] for i in ardupilot[2:]] == [nan_free(i)[1:] for i in px4[1:]]
    speed = px4[0]
    assert (speed.command, speed.frame, speed.param2, speed.x, speed.y) == (178, 2, SPEED_MPS, 0, 0)
    assert [(i.x, i.y) for i in px4[1:]] == [(round(a * 1e7), round(b * 1e7)) for a, b in WAYPOINTS]


def test_a_read_back_that_differs_is_found(tmp_path: Path) -> None:
    sent = mission.mission_items(mission.load_plan(write_plan(tmp_path)), Firmware.ARDUPILOT)
    same = list(sent)
    # ArduPilot puts its own home at seq 0, answers frame 0 for an item without a position,
    # the plain frame for an *_INT one, and 0 for a param it does not keep or a NaN sent.
    same[0] = RawItem(**{**vars(sent[0]), "x": 1, "y": 2, "z": 3.0})
    same[1] = RawItem(**{**vars(sent[1]), "frame": 0, "param3": 0.0})
    same[2] = RawItem(**{**vars(sent[2]), "frame": 6, "param4": 0.0})
    assert mission.mismatch(sent, same, Firmware.ARDUPILOT) is None
    # PX4 keeps every param: a lost one is a difference there.
    px4 = mission.mismatch(sent, [sent[0], *same[1:]], Firmware.PX4)
    assert px4 == "item 1: param3 0 read back, -1 sent"
    moved = list(sent)
    moved[3] = RawItem(**{**vars(sent[3]), "x": sent[3].x + 1})
    assert "item 3: x/y" in (mission.mismatch(sent, moved, Firmware.ARDUPILOT) or "")
    lower = list(sent)
    lower[4] = RawItem(**{**vars(sent[4]), "z": sent[4].z - 0.05})
    assert "item 4: altitude" in (mission.mismatch(sent, lower, Firmware.ARDUPILOT) or "")
    assert "holds 5 items" in (mission.mismatch(sent, sent[:5], Firmware.ARDUPILOT) or "")


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("udpin://0.0.0.0:14550", "udpin://0.0.0.0:14550"),
        ("udpout://192.168.1.20:14555", "udpout://192.168.1.20:14555"),
        ("serial:///dev/ttyACM0:57600", "serial:///dev/ttyACM0:57600"),
        ("udpin:0.0.0.0:14550", "udpin://0.0.0.0:14550"),  # pymavlink's spelling
        ("udp://:14540", "udpin://0.0.0.0:14540"),  # MAVSDK 1's
        ("tcpout://127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
    ],
)
def test_connection_urls_as_mavsdk_4_takes_them(given: str, expected: str) -> None:
    assert mission.mavsdk_url(given) == expected


@pytest.mark.parametrize(
    ("given", "reason"),
    [
        ("serial:///dev/ttyACM0", "baud"),
        ("/dev/ttyACM0", "baud"),
        ("udpout://:14550", "HOST"),
        ("udpin://0.0.0.0:70000", "port"),
        ("http://example.com", "not a MAVLink connection URL"),
    ],
)
def test_bad_connection_urls_are_refused(given: str, reason: str) -> None:
    with pytest.raises(SeamapError, match=reason):
        mission.mavsdk_url(given)


def test_mission_progress_for_the_daemon() -> None:
    assert mission.mission_progress_from(3, 12) == {"current": 3, "total": 12, "fraction": 0.25}
    assert mission.mission_progress_from(12, 12)["fraction"] == 1.0
    for unknown in (0, 65535):
        assert mission.mission_progress_from(2, unknown) == {
            "current": 2, "total": None, "fraction": None
        }  # fmt: skip


# --- against the autopilot peer -------------------------------------------------------------


@pytest.mark.parametrize("firmware_type", [3, 12])
def test_start_uploads_checks_arms_and_starts(
    tmp_path: Path, autopilot: FakeAutopilot, port: int, firmware_type: int
) -> None:
    plan = mission.load_plan(write_plan(tmp_path, firmware_type))
    started = asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=20))

    firmware = Firmware.ARDUPILOT if firmware_type == 3 else Firmware.PX4
    assert started.firmware is firmware and started.plan_items == 5
    assert started.readiness.fix == "3D fix" and started.readiness.satellites == 12
    # What the autopilot received: the plan's items, behind a home for ArduPilot only.
    (received,) = autopilot.uploads
    commands = [178, 16, 16, 16, 16]
    if firmware is Firmware.ARDUPILOT:
        home = received[0]
        assert (home.seq, home.command, home.frame) == (0, 16, 0)
        assert (home.x, home.y) == (round(HOME[0] * 1e7), round(HOME[1] * 1e7))
        assert home.z == pytest.approx(HOME[2])
        received = received[1:]
    assert [item.command for item in received] == commands
    assert [item.frame for item in received] == [2, 3, 3, 3, 3]
    assert received[0].param2 == pytest.approx(SPEED_MPS)
    assert [(i.x, i.y) for i in received[1:]] == [
        (round(lat * 1e7), round(lon * 1e7)) for lat, lon in WAYPOINTS
    ]
    assert all(item.z == 0.0 and item.autocontinue for item in received)
    assert started.items_sent == len(autopilot.uploads[0])
    # Armed, then AUTO (MAVSDK's PX4-style mode for this generic autopilot), then started.
    wait_for(lambda: autopilot.arm_requests and autopilot.mode_requests)
    assert autopilot.arm_requests == [("SUCCESS", True)]
    assert ("SUCCESS", "MISSION") in autopilot.mode_requests
    wait_for(lambda: autopilot.current == 0)


def test_status_reports_the_current_item_of_the_total(
    tmp_path: Path, autopilot: FakeAutopilot, port: int, capfd: pytest.CaptureFixture[str]
) -> None:
    plan = mission.load_plan(write_plan(tmp_path))
    asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=20))
    wait_for(lambda: autopilot.current == 0)
    autopilot.missions.set_current_item_complete()  # the boat reached items 0 and 1
    autopilot.missions.set_current_item_complete()
    wait_for(lambda: autopilot.current == 2)

    status = asyncio.run(mission.mission_status(url_of(port), timeout_s=20))
    assert (status.current, status.total, status.state) == (2, 6, "active")
    assert status.armed
    # Through the command line, one line or one JSON object.
    capfd.readouterr()
    assert main(["survey", "status", "--connect", url_of(port), "--json"]) == 0
    assert json.loads(capfd.readouterr().out) == {
        "current": 2, "total": 6, "fraction": pytest.approx(2 / 6), "state": "active",
        "flight_mode": status.flight_mode, "armed": True,
    }  # fmt: skip


def test_pause_resume_abort_send_hold_auto_and_rtl(
    tmp_path: Path, autopilot: FakeAutopilot, port: int, capfd: pytest.CaptureFixture[str]
) -> None:
    plan = mission.load_plan(write_plan(tmp_path, 12))
    asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=20))
    autopilot.mode_requests.clear()
    # MAVSDK 4.1.0's ActionServer turns HOLD down whatever it is allowed: a refusal, then,
    # that must come back as one clear line.
    with pytest.raises(SeamapError, match=r"holding .* refused it \(DENIED\)"):
        asyncio.run(mission.pause_survey(url_of(port), timeout_s=20))
    wait_for(lambda: len(autopilot.mode_requests) >= 1)
    assert autopilot.mode_requests[-1][1] == "HOLD"
    asyncio.run(mission.resume_survey(url_of(port), timeout_s=20))
    wait_for(lambda: len(autopilot.mode_requests) >= 2)
    assert autopilot.mode_requests[-1] == ("SUCCESS", "MISSION")
    capfd.readouterr()
    assert main(["survey", "abort", "--connect", url_of(port)]) == 0
    wait_for(lambda: len(autopilot.mode_requests) >= 3)
    assert autopilot.mode_requests[-1] == ("SUCCESS", "RETURN_TO_LAUNCH")
    assert capfd.readouterr().out == "returning to launch (RTL)\n"


# --- refusals -------------------------------------------------------------------------------


def test_no_gps_fix_is_refused_before_anything_is_sent(tmp_path: Path, port: int) -> None:
    peer = FakeAutopilot(port, fix=FixType.NO_FIX)
    try:
        plan = mission.load_plan(write_plan(tmp_path))
        began = time.monotonic()
        with pytest.raises(SeamapError, match=r"no GPS fix: .*no fix with 0 satellites"):
            asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=3))
        assert time.monotonic() - began < 2 * 3 + SLACK_S  # hearing the autopilot, the fix
        assert peer.uploads == [] and peer.arm_requests == [] and peer.mode_requests == []
    finally:
        peer.close()


@pytest.mark.parametrize(
    ("behaviour", "reason"),
    [("silent", "did not answer within 5 s"), ("reject", r"refused it \(DENIED\)")],
)
def test_a_failed_upload_is_refused_within_the_timeout(
    tmp_path: Path, port: int, behaviour: str, reason: str
) -> None:
    peer = FakeAutopilot(port, missions=behaviour)
    try:
        plan = mission.load_plan(write_plan(tmp_path))
        began = time.monotonic()
        with pytest.raises(SeamapError, match=f"uploading the mission .*{reason}"):
            asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=5))
        assert time.monotonic() - began < 3 * 5 + SLACK_S
        assert peer.arm_requests == [] and peer.mode_requests == []
    finally:
        peer.close()


def test_a_vehicle_that_will_not_arm_is_not_started(tmp_path: Path, port: int) -> None:
    peer = FakeAutopilot(port, armable=False)
    try:
        plan = mission.load_plan(write_plan(tmp_path))
        with pytest.raises(SeamapError, match="not armable: arming failed"):
            asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=10))
        # The refusal is recorded on MAVSDK's own thread: wait for it (bounded).
        wait_for(lambda: peer.uploads and peer.arm_requests, timeout_s=5.0)
        assert len(peer.uploads) == 1
        assert all(r == ("COMMAND_DENIED", True) for r in peer.arm_requests)
        assert peer.mode_requests == []
    finally:
        peer.close()


def test_a_mission_that_will_not_start_is_disarmed_again(tmp_path: Path, port: int) -> None:
    peer = FakeAutopilot(port, auto=False)
    try:
        plan = mission.load_plan(write_plan(tmp_path))
        with pytest.raises(SeamapError, match=r"starting .* refused it .*; disarmed again$"):
            asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=10))
        wait_for(lambda: len(peer.arm_requests) >= 2 and peer.mode_requests, timeout_s=5.0)
        assert peer.arm_requests == [("SUCCESS", True), ("SUCCESS", False)]
        assert [mode for _, mode in peer.mode_requests] == ["MISSION"]
    finally:
        peer.close()


def test_no_autopilot_is_a_clear_timeout(tmp_path: Path, port: int) -> None:
    plan = mission.load_plan(write_plan(tmp_path))
    with pytest.raises(
        SeamapError, match=r"no autopilot heard on udpin://127\.0\.0\.1:\d+ within 2 s"
    ):
        asyncio.run(mission.start_survey(plan, url_of(port), timeout_s=2))


# --- the daemon -----------------------------------------------------------------------------


class FakeDaemon:
    """The daemon's survey control queryable, on tcp/127.0.0.1:PORT."""

    def __init__(self, port: int) -> None:
        self.requests: list[Any] = []
        self.session = open_session(
            ZenohConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], connect=[],
                        multicast_scouting=False)
        )  # fmt: skip
        self.queryable = self.session.declare_queryable(
            control_key(VEHICLE), self._answer, complete=True
        )

    def _answer(self, query: Any) -> None:
        self.requests.append(json.loads(query.payload.to_bytes()))
        query.reply(control_key(VEHICLE), json_bytes({"ok": True, "survey": "X"}))

    def close(self) -> None:
        self.queryable.undeclare()
        self.session.close()


@pytest.fixture
def daemon() -> Iterator[tuple[FakeDaemon, int]]:
    zenoh_port = free_tcp_port()
    fake = FakeDaemon(zenoh_port)
    yield fake, zenoh_port
    fake.close()


def test_the_daemon_is_asked_to_open_a_survey(daemon: tuple[FakeDaemon, int]) -> None:
    fake, zenoh_port = daemon
    # As the daemon's own site config names it: its vehicle, listening on every interface.
    config = config_from_dict(
        {"daemon": {"vehicle": VEHICLE},
         "zenoh": {"listen": [f"tcp/0.0.0.0:{zenoh_port}"], "multicast_scouting": False}}
    )  # fmt: skip
    target = request.daemon_target(config)
    assert target is not None and target.zenoh.connect == [f"tcp/127.0.0.1:{zenoh_port}"]
    assert request.request_survey_start(target, timeout_s=10) == request.DaemonAnswer("X")
    assert fake.requests == [{"action": "start"}]
    # Or named on the command line.
    explicit = request.daemon_target(None, f"tcp/127.0.0.1:{zenoh_port}", VEHICLE)
    assert explicit is not None
    assert request.request_survey_start(explicit, timeout_s=10).survey == "X"


def test_daemon_targets_are_checked_before_anything_moves() -> None:
    assert request.daemon_target(None) is None
    with pytest.raises(SeamapError, match="--daemon needs --vehicle"):
        request.daemon_target(None, "tcp/127.0.0.1:7447")
    with pytest.raises(SeamapError, match="not a zenoh endpoint"):
        request.daemon_target(None, "127.0.0.1:7447", VEHICLE)
    with pytest.raises(SeamapError, match="vehicle 'a/b'"):
        request.daemon_target(SiteConfig(), vehicle="a/b")


def test_survey_start_on_the_command_line(
    tmp_path: Path,
    autopilot: FakeAutopilot,
    port: int,
    daemon: tuple[FakeDaemon, int],
    capfd: pytest.CaptureFixture[str],
) -> None:
    fake, zenoh_port = daemon
    capfd.readouterr()
    status = main(
        ["survey", "start", str(write_plan(tmp_path)), "--connect", url_of(port),
         "--daemon", f"tcp/127.0.0.1:{zenoh_port}", "--vehicle", VEHICLE]
    )  # fmt: skip
    assert status == 0
    out = capfd.readouterr().out.splitlines()
    assert out[0].startswith("mission started: 5 items") and "armed, AUTO" in out[0]
    assert out[1:] == [f"survey X recording on {VEHICLE}"]
    assert fake.requests == [{"action": "start"}]
    wait_for(lambda: autopilot.uploads and autopilot.mode_requests)
    assert len(autopilot.uploads) == 1 and ("SUCCESS", "MISSION") in autopilot.mode_requests


def test_survey_start_hands_the_plans_area_to_the_daemon(
    tmp_path: Path,
    autopilot: FakeAutopilot,
    port: int,
    daemon: tuple[FakeDaemon, int],
    capfd: pytest.CaptureFixture[str],
) -> None:
    fake, zenoh_port = daemon
    capfd.readouterr()
    status = main(
        ["survey", "start", str(write_plan(tmp_path, area=AREA)), "--connect", url_of(port),
         "--daemon", f"tcp/127.0.0.1:{zenoh_port}", "--vehicle", VEHICLE]
    )  # fmt: skip
    assert status == 0
    out = capfd.readouterr().out.splitlines()
    assert out[1:] == [f"survey X recording on {VEHICLE} (covering the plan's area)"]
    assert fake.requests == [{"action": "start", "area": AREA}]


def test_survey_start_refuses_a_plan_with_a_bad_area_before_anything_moves(
    tmp_path: Path, autopilot: FakeAutopilot, port: int, capfd: pytest.CaptureFixture[str]
) -> None:
    bow_tie = [[8.5455, 47.3977], [8.5459, 47.3984], [8.5459, 47.3977], [8.5455, 47.3984]]
    crossed = {"type": "Polygon", "coordinates": [bow_tie]}
    plan = write_plan(tmp_path, area=crossed)
    capfd.readouterr()
    assert main(["survey", "start", str(plan), "--connect", url_of(port)]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"seamap survey: {plan}: the plan's seamap.area"), (
        err
    )
    assert "crosses itself" in err[0]
    assert "Traceback" not in err[0]
    time.sleep(0.5)
    assert not autopilot.uploads


def test_a_silent_daemon_is_reported_and_the_mission_runs_on(
    tmp_path: Path, autopilot: FakeAutopilot, port: int, capfd: pytest.CaptureFixture[str]
) -> None:
    nobody = free_tcp_port()
    capfd.readouterr()
    status = main(
        ["survey", "start", str(write_plan(tmp_path)), "--connect", url_of(port),
         "--daemon", f"tcp/127.0.0.1:{nobody}", "--vehicle", VEHICLE]
    )  # fmt: skip
    assert status == 1
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the mission runs, but no survey was opened" in err[0]
    assert f"tcp/127.0.0.1:{nobody}" in err[0]
    # Not undone: no hold, no return.
    wait_for(lambda: autopilot.mode_requests)
    assert [mode for _, mode in autopilot.mode_requests] == ["MISSION"]


# --- the command line -----------------------------------------------------------------------


@pytest.mark.parametrize("content", [None, "", "{not json", '{"mission": {"items": []}}'])
def test_survey_start_with_a_missing_or_bad_plan_is_one_line_and_status_2(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], content: str | None
) -> None:
    path = tmp_path / "survey.plan"
    if content is not None:
        path.write_text(content)
    status = main(["survey", "start", str(path), "--connect", "udpin://127.0.0.1:9"])
    assert status == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("seamap survey: ") and str(path) in err[0]
    assert "Traceback" not in err[0]


def test_survey_start_refuses_a_bad_url_or_daemon_first(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    plan = str(write_plan(tmp_path))
    assert main(["survey", "start", plan, "--connect", "/dev/ttyACM0"]) == 2
    assert main(["survey", "start", plan, "--connect", "udpin://0.0.0.0:9", "--daemon", "x"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "baud" in err[0] and "--daemon" in err[1]


def test_survey_plan_arguments(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    args = build_parser().parse_args(
        ["survey", "plan", "--area", "site.geojson", "--spacing", "2.5", "--angle", "30",
         "--speed", "1.2", "--lead-in", "8", "--entry", "sw", "--firmware", "px4",
         "--out", "site.plan"]
    )  # fmt: skip
    assert (args.survey_command, args.area, args.out) == (
        "plan",
        Path("site.geojson"),
        Path("site.plan"),
    )
    assert (args.spacing, args.angle, args.speed, args.lead_in) == (2.5, 30.0, 1.2, 8.0)
    assert (args.entry, args.firmware, args.overlap, args.config) == ("sw", "px4", None, None)
    # The planner is called with the options, overlap only when given.
    calls: list[dict[str, Any]] = []

    def plan_survey(area: Path, out: Path, config: SiteConfig, **options: Any) -> dict[str, Any]:
        calls.append(options)
        return {"waypoints": 26, "lanes": 12, "spacing_m": 2.5, "angle_deg": 30.0,
                "distance_m": 1234.0, "duration_s": 1028.0, "area_m2": 900.0,
                "covered_m2": 880.0, "coverage": 0.978, "files": [str(out)]}  # fmt: skip

    planner = types.ModuleType("daemon.plan_files")
    planner.plan_survey = plan_survey  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "daemon.plan_files", planner)
    assert args.handler(args) == 0
    assert "overlap" not in calls[0] and calls[0]["spacing_m"] == 2.5
    assert calls[0]["firmware"] == "px4" and calls[0]["entry"] == "sw"
    assert capfd.readouterr().out.startswith("site.plan: 12 lanes, 26 waypoints, spacing 2.50 m")
    args = build_parser().parse_args(
        ["survey", "plan", "--area", "a.geojson", "--overlap", "0.3", "--out", "a.plan"]
    )
    args.handler(args)
    assert calls[1]["overlap"] == 0.3 and calls[1]["speed_mps"] == 1.0
