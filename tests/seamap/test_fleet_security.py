"""A fleet secured with ``seamap security init --router`` on 127.0.0.1: ``seamap router
--config`` with the set's router files (a child process), two boats (the daemon's zenoh
publisher, each a TLS client with its own user) and two shores (a ``ShoreStation`` and a
plain session), as the set writes them. The shore follows both boats and stops one's
survey; a boat cannot publish, answer or be alive as the other; a shore's puts reach
nobody; a client without the set (plain TCP, no certificate, no or a wrong password) is
refused at the door, and one with another user's password is let in but allowed nothing.

Negative checks first see a message of their own kind go through the same link (a
positive control), then wait ``QUIET_S`` more before asserting that nothing else came.

What the tests wait for, so that a loaded machine cannot fail them:

- a put reaches a subscriber only if the router already holds the subscription when the
  put arrives (it comes on another session's link). A session's messages reach the router
  in order, so once a round trip the subscriber's session made *after* subscribing has
  come back (the station: the boats' tokens its liveliness subscriber was given; shore-2:
  a liveliness ``get``), the router holds the subscription;
- the tests' own puts use congestion control BLOCK: a put with DROP (zenoh's default) may
  be dropped at the router when the link to the subscriber is busy, and a positive
  control or a forged message must not be lost that way. The boats' publisher puts live
  tiles, poses and status with DROP (its design: a slow shore loses them), so the boats'
  tiles are checked through the station's catch-up (a ``get``; its replies are BLOCK)
  and poses and status are published while no tile is on the way.
"""

from __future__ import annotations

import asyncio
import json
import stat
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh
from cryptography import x509

from daemon.config import ZenohConfig, config_from_dict, load_config
from daemon.publisher import ZenohPublisher
from drivers.zenoh_io import (
    alive_key,
    control_key,
    json_bytes,
    open_session,
    parse_tile_key,
    pose_key,
    session_config,
    tiles_selector,
)
from mapping.streaming import TileUpdate
from seamap.router import router_settings
from seamap.security import FleetSecuritySet, init_fleet_security
from seamap.shore import ShoreSettings, ShoreStation
from tests.ports import free_tcp_port
from tests.seamap.test_fleet import BOATS, SURVEY, _holds, _pose, _tile

SEAMAP = str(Path(sys.executable).parent / "seamap")
WAIT_S = 20.0
QUIET_S = 1.5
BLOCK = zenoh.CongestionControl.BLOCK


# --- the set, the router and the clients, as the set's files say -----------------------------


def zenoh_table(folder: Path, endpoint: str) -> ZenohConfig:
    """A client's [zenoh] lines from the set (its connect made ``endpoint``)."""
    table = tomllib.loads((folder / "zenoh.toml").read_text())["zenoh"]
    table["connect"] = [endpoint]
    return config_from_dict({"zenoh": table}).zenoh


def users_file(made: FleetSecuritySet) -> dict[str, str]:
    lines = (made.router / "zenoh-users.txt").read_text().splitlines()
    return dict(line.split(":", 1) for line in lines)


@dataclass
class Inbox:
    """Samples a plain session received: (key, payload)."""

    items: list[tuple[str, bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def payloads(self) -> list[bytes]:
        with self.lock:
            return [payload for _key, payload in self.items]


@dataclass
class Boat:
    """A boat's publisher with its event loop running (survey control is answered there)."""

    vehicle: str
    publisher: ZenohPublisher
    session: zenoh.Session
    loop: asyncio.AbstractEventLoop
    thread: threading.Thread
    requests: list[dict[str, Any]]

    def close(self) -> None:
        self.publisher.detach()
        self.publisher.close()
        self.session.close()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(WAIT_S)
        self.loop.close()


def open_boat(vehicle: str, folder: Path, endpoint: str, state: Path) -> Boat:
    requests: list[dict[str, Any]] = []

    async def control(request: dict[str, Any]) -> dict[str, Any]:
        requests.append(request)
        return {"ok": True, "vehicle": vehicle, "action": request.get("action")}

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    publisher = ZenohPublisher(vehicle, state / vehicle / "surveys", loop, control=control)
    session = open_session(zenoh_table(folder, endpoint))
    publisher.attach(session)
    return Boat(vehicle, publisher, session, loop, thread, requests)


@dataclass
class Fleet:
    made: FleetSecuritySet
    endpoint: str
    router: subprocess.Popen[bytes]
    boats: dict[str, Boat]
    station: ShoreStation
    observer: zenoh.Session
    """shore-2: a plain session subscribed to seamap/**."""
    observed: Inbox


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> FleetSecuritySet:
    out = tmp_path_factory.mktemp("fleet-security") / "set"
    return init_fleet_security(out, list(BOATS), [], shores=2, port=free_tcp_port())


@pytest.fixture(scope="module")
def fleet(made: FleetSecuritySet, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    state = tmp_path_factory.mktemp("fleet-state")
    # The router's site file as the set writes it, on loopback only (it listens on 0.0.0.0).
    endpoint = f"tls/127.0.0.1:{made.port}"
    log = state / "router.log"
    with open(log, "wb") as out:
        router = subprocess.Popen(
            [SEAMAP, "router", "--config", str(made.router / "zenoh.toml"), "--listen", endpoint],
            stdout=out,
            stderr=out,
        )
    boats: dict[str, Boat] = {}
    sessions: list[zenoh.Session] = []
    stations: list[ShoreStation] = []
    try:
        deadline = time.monotonic() + WAIT_S
        while b"listening on" not in log.read_bytes():
            assert router.poll() is None, log.read_text()
            assert time.monotonic() < deadline, "the router did not start"
            time.sleep(0.05)
        for vehicle in BOATS:
            boats[vehicle] = open_boat(vehicle, made.boats[vehicle], endpoint, state)
        station = ShoreStation(
            ShoreSettings(
                out_dir=state / "shore-1",
                zenoh=zenoh_table(made.shores[0], endpoint),
                write_interval_s=1,
            )
        )
        station.open()
        stations.append(station)
        observer = open_session(zenoh_table(made.shores[1], endpoint))
        sessions.append(observer)
        observed = Inbox()
        keep = observer.declare_subscriber("seamap/**", observed.on_sample)
        # The router holds each subscription once a round trip the subscriber's session
        # made after subscribing is back: the station's tokens, shore-2's liveliness get.
        assert station.run(WAIT_S, until=lambda s: all(s.alive(v) for v in BOATS)), (
            "the station never saw both boats' tokens"
        )
        tokens = observer.liveliness().get(alive_key("*"), timeout=WAIT_S)
        alive = sorted(str(t.ok.key_expr) for t in tokens if t.ok is not None)
        assert alive == [alive_key(v) for v in BOATS], f"shore-2 sees tokens {alive}"
        yield Fleet(made, endpoint, router, boats, station, observer, observed)
        del keep
    finally:
        for station in stations:
            station.close()
        for session in sessions:
            session.close()
        for boat in boats.values():
            boat.close()
        router.terminate()
        router.wait(WAIT_S)


def until(fleet: Fleet, condition: Callable[[ShoreStation], bool], what: str) -> None:
    assert fleet.station.run(WAIT_S, until=condition), f"timed out waiting for {what}"


def observed(fleet: Fleet, payload: bytes) -> None:
    """Wait until shore-2 received ``payload`` (a positive control)."""
    deadline = time.monotonic() + WAIT_S
    while payload not in fleet.observed.payloads():
        assert time.monotonic() < deadline, f"shore-2 never received {payload!r}"
        time.sleep(0.05)


def pose_bytes(t: float, north: float) -> bytes:
    """A pose as a boat's publisher puts it."""
    return json_bytes(
        {"time": t, "lat": 39.0, "lon": -76.0, "east": 500_000.0, "north": north,
         "heading_deg": 90.0, "epsg": 32618, "frame": int(t), "final": False}
    )  # fmt: skip


# --- the file set ------------------------------------------------------------------------------


def test_the_fleet_set_holds_every_sides_files_with_secrets_private(
    made: FleetSecuritySet,
) -> None:
    out = made.out
    assert sorted(p.name for p in out.iterdir()) == [
        "boat-boat1", "boat-boat2", "ca.crt", "ca.key", "router", "shore-1", "shore-2",
    ]  # fmt: skip
    secrets = ["ca.key", "router/router.key", "router/zenoh-users.txt"]
    for user in made.users:
        secrets += [f"{user}/{user}.key", f"{user}/{user}.json5"]
    for secret in secrets:
        assert stat.S_IMODE((out / secret).stat().st_mode) == 0o600, secret
    assert not any(p.name == "ca.key" for p in out.rglob("*") if p.parent != out)
    users = users_file(made)
    assert list(users) == ["boat-boat1", "boat-boat2", "shore-1", "shore-2"]
    assert len(set(users.values())) == 4  # a password each
    certificate = x509.load_pem_x509_certificate((made.router / "router.crt").read_bytes())
    names = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert names.get_values_for_type(x509.DNSName) == ["localhost"]
    assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    # The router's site file is accepted as written (its listen endpoint is tls/).
    settings = router_settings(load_config(made.router / "zenoh.toml"))
    assert settings.zenoh.listen == [f"tls/0.0.0.0:{made.port}"]
    session_config(settings.zenoh)  # zenoh reads router.json5
    for user in made.users:
        client = tomllib.loads((out / user / "zenoh.toml").read_text())["zenoh"]
        assert client["mode"] == "client" and client["listen"] == []
        assert client["connect"] == [f"tls/localhost:{made.port}"]
        config = json.loads((out / user / f"{user}.json5").read_text().split("\n", 2)[2])
        assert config["transport"]["auth"]["usrpwd"] == {"user": user, "password": users[user]}


# --- the fleet through the router -----------------------------------------------------------


def test_the_shore_follows_both_boats_and_stops_a_survey(fleet: Fleet) -> None:
    until(fleet, lambda s: all(s.alive(v) is True for v in BOATS), "both boats' tokens")
    # Poses and status first, while no tile is on the way: they are put with congestion
    # control DROP, and two boats' tiles (~70 kB each) fill the router's queue to the
    # shore (two batches of 64 kB), so a message arriving then may be dropped.
    for b, (vehicle, boat) in enumerate(fleet.boats.items()):
        boat.publisher.pose(_pose(b, 100.0))
        boat.publisher.status({"vehicle": vehicle, "frames": {"mapped": 3 + b}})

    def poses_and_status(station: ShoreStation) -> bool:
        return all(
            any(p.time == 100.0 for p in station.track(v))
            and (station.status(v) or {}).get("frames", {}).get("mapped") == 3 + b
            for b, v in enumerate(BOATS)
        )

    until(fleet, poses_and_status, "both boats' poses and status")
    # A live tile (DROP) can be dropped that way too; the shore's catch-up cannot (a get,
    # its replies are BLOCK). Asked after the tiles were handed to the publishers, it is
    # answered after they hold them (one thread takes both, tiles first).
    sent: dict[str, list[TileUpdate]] = {}
    for b, (vehicle, boat) in enumerate(fleet.boats.items()):
        update = _tile(b, 0, seed=20 + b)
        boat.publisher.tile(SURVEY, update)
        sent[vehicle] = [update]
    fleet.station.catch_up()
    until(fleet, _holds(sent), "both boats' tiles")
    # Each boat's tile store answers a catch-up asked of every vehicle (seamap/*/...).
    tiles = fleet.observer.get(tiles_selector("*", SURVEY), target=zenoh.QueryTarget.ALL)
    keys = [parse_tile_key(str(r.ok.key_expr)) for r in tiles if r.ok is not None]
    assert sorted(k.vehicle for k in keys if k is not None) == list(BOATS)
    replies = list(fleet.observer.get(control_key("boat2"), payload=json_bytes({"action": "stop"})))
    answers = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
    assert answers == [{"ok": True, "vehicle": "boat2", "action": "stop"}]
    assert fleet.boats["boat2"].requests == [{"action": "stop"}]
    assert fleet.boats["boat1"].requests == []


def test_a_boat_cannot_publish_answer_or_be_alive_as_another(fleet: Fleet) -> None:
    boat1 = fleet.boats["boat1"].session
    forged_pose = pose_bytes(777.0, 1.0)
    boat1.put(pose_key("boat2"), forged_pose, congestion_control=BLOCK)
    forged_token = boat1.liveliness().declare_token("seamap/boat2/forged/alive")
    forged_queryable = boat1.declare_queryable(
        control_key("boat2") + "/forged", lambda q: q.reply(q.key_expr, b"forged")
    )
    own = pose_bytes(778.0, 2.0)
    boat1.put(pose_key("boat1"), own, congestion_control=BLOCK)
    observed(fleet, own)  # boat1's own pose passes the same link
    time.sleep(QUIET_S)
    assert forged_pose not in fleet.observed.payloads()
    assert all(p.time != 777.0 for p in fleet.station.track("boat2"))
    # Both gets end when the router has answered (the timeout only bounds a lost answer).
    tokens = list(fleet.observer.liveliness().get("seamap/boat2/**", timeout=WAIT_S))
    assert [str(t.ok.key_expr) for t in tokens if t.ok is not None] == ["seamap/boat2/alive"]
    replies = list(fleet.observer.get(control_key("boat2") + "/forged", timeout=WAIT_S))
    assert [r for r in replies if r.ok is not None] == []
    forged_token.undeclare()
    forged_queryable.undeclare()


def test_a_shores_puts_reach_nobody(fleet: Fleet) -> None:
    until(fleet, lambda s: all(s.alive(v) is True for v in BOATS), "both boats' tokens")
    fleet.observer.put(pose_key("boat1"), pose_bytes(888.0, 3.0), congestion_control=BLOCK)
    fleet.observer.put("seamap/boat1/survey/s1/forged", b"forged", congestion_control=BLOCK)
    own = pose_bytes(889.0, 4.0)
    fleet.boats["boat1"].session.put(pose_key("boat1"), own, congestion_control=BLOCK)
    until(fleet, lambda s: any(p.time == 889.0 for p in s.track("boat1")), "boat1's pose")
    time.sleep(QUIET_S)
    fleet.station.run(0.2)
    assert all(p.time != 888.0 for p in fleet.station.track("boat1"))


def _refused(fleet: Fleet, change: Callable[[zenoh.Config], None]) -> None:
    """A client made from shore-2's files by ``change`` cannot open its session."""
    config = session_config(zenoh_table(fleet.made.shores[1], fleet.endpoint))
    change(config)
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(config).close()


def test_a_foreign_client_is_refused(fleet: Fleet) -> None:
    port = fleet.made.port

    def plain_tcp(config: zenoh.Config) -> None:
        config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        config.insert_json5("transport/link/protocols", '["tcp"]')

    def no_certificate(config: zenoh.Config) -> None:
        config.insert_json5("transport/link/tls/enable_mtls", "false")

    def no_password(config: zenoh.Config) -> None:
        config.insert_json5("transport/auth/usrpwd", "{}")

    def wrong_password(config: zenoh.Config) -> None:
        config.insert_json5("transport/auth/usrpwd/password", '"not-the-password"')

    for change in (plain_tcp, no_certificate, no_password, wrong_password):
        _refused(fleet, change)


def test_another_users_password_without_its_certificate_is_allowed_nothing(
    fleet: Fleet,
) -> None:
    # boat2's user and password, shore-2's certificate: the router lets the session in
    # (the password is right) but no subject matches both, so every message is denied.
    config = session_config(zenoh_table(fleet.made.shores[1], fleet.endpoint))
    config.insert_json5("transport/auth/usrpwd/user", '"boat-boat2"')
    password = users_file(fleet.made)["boat-boat2"]
    config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    session = zenoh.open(config)
    try:
        session.put(pose_key("boat2"), pose_bytes(999.0, 5.0), congestion_control=BLOCK)
        replies = list(session.get(control_key("boat1"), payload=b'{"action": "stop"}'))
        assert [r for r in replies if r.ok is not None] == []
        own = pose_bytes(998.0, 6.0)
        fleet.boats["boat2"].session.put(pose_key("boat2"), own, congestion_control=BLOCK)
        observed(fleet, own)
        time.sleep(QUIET_S)
        assert pose_bytes(999.0, 5.0) not in fleet.observed.payloads()
        assert fleet.boats["boat1"].requests == []
    finally:
        session.close()


def test_cli_writes_a_fleet_set(tmp_path: Path) -> None:
    result = subprocess.run(
        [SEAMAP, "security", "init", "--router", "--out", str(tmp_path / "set"),
         "--vehicle", "a", "--vehicle", "b", "--host", "router.example"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    for folder in ("router", "boat-a", "boat-b", "shore-1"):
        assert (tmp_path / "set" / folder / "zenoh.toml").is_file(), folder
    toml = tomllib.loads((tmp_path / "set" / "boat-a" / "zenoh.toml").read_text())
    assert toml["zenoh"]["connect"] == ["tls/router.example:7447"]
    again = subprocess.run(
        [SEAMAP, "security", "init", "--out", str(tmp_path / "one"), "--vehicle", "a",
         "--vehicle", "b"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert again.returncode == 2 and "--router" in again.stderr
