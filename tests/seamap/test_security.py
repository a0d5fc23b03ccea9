"""``seamap security init`` (issue 13, 4): the set it writes works as written, with real
zenoh sessions on 127.0.0.1: a shore of the set follows the boat and may start or stop a
survey; a foreign client (plain TCP, or TLS without the set's certificate and password)
never joins, cannot stop a survey and cannot publish as the boat; a shore of the set
cannot publish as the boat either. And the daemon refuses plain TCP on the network."""

from __future__ import annotations

import json
import stat
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from daemon.config import ZenohConfig, config_from_dict, dump_config
from drivers.zenoh_io import control_key, json_bytes, open_session, pose_key, session_config
from tests.daemon.harness import free_udp_port
from tests.ports import free_tcp_port
from tests.seamap.test_cli import assert_one_line_error, seamap
from tests.seamap.test_zenoh_acl import (
    QUIET_S,
    TIMEOUT_S,
    VEHICLE,
    Boat,
    Inbox,
    control_roundtrip,
    marker,
    open_boat,
    publish_until,
    wait_connected,
)


@dataclass(frozen=True)
class Made:
    out: Path
    port: int


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> Made:
    out = tmp_path_factory.mktemp("security") / "set"
    port = free_tcp_port()
    result = seamap(
        "security", "init", "--out", out, "--vehicle", VEHICLE, "--shores", "2",
        "--port", str(port),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    return Made(out, port)


def zenoh_table(folder: Path, **changes: Any) -> ZenohConfig:
    """A side's [zenoh] lines from the set, as its site file would hold them."""
    table = tomllib.loads((folder / "zenoh.toml").read_text())["zenoh"]
    table.update(changes)
    return config_from_dict({"zenoh": table}).zenoh


def test_the_set_holds_both_sides_files_with_private_keys_private(made: Made) -> None:
    out = made.out
    for name in ("ca.crt", "ca.key", "boat/boat.crt", "boat/boat.key", "boat/boat.json5",
                 "boat/zenoh-users.txt", "boat/zenoh.toml", "shore-1/shore-1.json5",
                 "shore-2/shore-2.key", "shore-2/zenoh.toml"):  # fmt: skip
        assert (out / name).is_file(), name
    for secret in ("ca.key", "boat/boat.key", "boat/zenoh-users.txt", "shore-1/shore-1.key",
                   "shore-1/shore-1.json5"):  # fmt: skip
        assert stat.S_IMODE((out / secret).stat().st_mode) == 0o600, secret
    users = (out / "boat/zenoh-users.txt").read_text().splitlines()
    assert [line.split(":")[0] for line in users] == ["shore-1", "shore-2"]
    assert len({line.split(":", 1)[1] for line in users}) == 2  # a password each
    assert "ca.key" not in " ".join(p.name for p in (out / "boat").iterdir())
    boat = zenoh_table(out / "boat")
    assert boat.listen == [f"tls/0.0.0.0:{made.port}"] and Path(boat.config_file).is_file()
    session_config(boat)  # zenoh reads it
    shore = zenoh_table(out / "shore-1")
    assert shore.connect == [f"tls/localhost:{made.port}"] and shore.listen == []


def test_a_second_set_is_not_written_over_the_first(made: Made) -> None:
    again = seamap("security", "init", "--out", made.out, "--vehicle", VEHICLE)
    assert_one_line_error(again, "already holds a security set")
    bad = seamap("security", "init", "--out", made.out / "x", "--vehicle", "a/b")
    assert_one_line_error(bad, "--vehicle 'a/b'")


@dataclass
class Running:
    boat: Boat
    shore: zenoh.Session
    shore_inbox: Inbox


@pytest.fixture(scope="module")
def running(made: Made) -> Iterator[Running]:
    # The boat on loopback only (the set's file listens on 0.0.0.0): the shores connect to
    # 127.0.0.1, which the boat's certificate names by default.
    boat = open_boat(zenoh_table(made.out / "boat", listen=[f"tls/127.0.0.1:{made.port}"]))
    sessions = [boat.session]
    try:
        shore = open_session(
            zenoh_table(made.out / "shore-1", connect=[f"tls/127.0.0.1:{made.port}"])
        )
        sessions.append(shore)
        inbox = Inbox()
        keep = [shore.declare_subscriber("seamap/**", inbox.on_sample)]
        wait_connected(shore)
        yield Running(boat, shore, inbox)
        del keep
    finally:
        for session in reversed(sessions):
            session.close()


def test_a_shore_of_the_set_follows_the_boat_and_asks_for_surveys(running: Running) -> None:
    publish_until(running.boat.session, pose_key(VEHICLE), running.shore_inbox)
    control_roundtrip(running.shore, running.boat)


def test_a_shore_of_the_set_cannot_publish_as_the_boat(running: Running) -> None:
    control_roundtrip(running.shore, running.boat)  # the link is up (positive control)
    bogus = marker("shore")
    running.shore.put(pose_key(VEHICLE), bogus)
    time.sleep(QUIET_S)
    assert all(item[2] != bogus for item in running.boat.inbox.items())


def _foreign(config: zenoh.Config, running: Running) -> None:
    """A client that is not of the set: it never joins, its stop request goes unanswered
    and its bogus pose reaches nobody."""
    session = zenoh.open(config)
    try:
        deadline = time.monotonic() + QUIET_S
        while time.monotonic() < deadline:
            assert not session.info.peers_zid() and not session.info.routers_zid()
            time.sleep(0.1)
        replies = list(
            session.get(
                control_key(VEHICLE), payload=json_bytes({"action": "stop"}), timeout=QUIET_S
            )
        )
        assert [r for r in replies if r.ok is not None] == []
        bogus = marker("shore")
        session.put(pose_key(VEHICLE), bogus)
        control_roundtrip(running.shore, running.boat)  # the boat still answers its shore
        time.sleep(QUIET_S)
        assert all(b"stop" not in item[2] for item in running.boat.requests.items())
        assert all(item[2] != bogus for item in running.boat.inbox.items())
        assert all(item[2] != bogus for item in running.shore_inbox.items())
    finally:
        session.close()


def test_a_client_in_plain_tcp_is_refused(made: Made, running: Running) -> None:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')  # a client would fail to open: a peer keeps trying
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{made.port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    _foreign(config, running)


def test_a_client_in_tls_without_the_sets_certificate_and_password_is_refused(
    made: Made, running: Running
) -> None:
    # It trusts the boat (it has ca.crt) but holds no certificate and no password.
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{made.port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5(
        "transport/link/tls/root_ca_certificate", json.dumps(str(made.out / "ca.crt"))
    )
    _foreign(config, running)


def test_the_daemon_refuses_plain_tcp_open_to_the_network(tmp_path: Path) -> None:
    data = {
        "daemon": {"state_dir": str(tmp_path / "state")},
        "sonar": {"address": "127.0.0.1", "tcp_port": free_tcp_port()},
        "mavlink": {"url": f"udpin:127.0.0.1:{free_udp_port()}"},
        "zenoh": {"listen": [f"tcp/0.0.0.0:{free_tcp_port()}"], "multicast_scouting": False},
    }
    config = tmp_path / "site.toml"
    config.write_text(dump_config(config_from_dict(data)))
    started = time.monotonic()
    result = seamap("run", "--config", config)
    assert_one_line_error(result, "[zenoh] listen 'tcp/0.0.0.0:", "seamap security init",
                          "allow_insecure = true")  # fmt: skip
    assert time.monotonic() - started < TIMEOUT_S * 6
    assert not (tmp_path / "state" / "surveys").exists() or not any(
        (tmp_path / "state" / "surveys").iterdir()
    )
