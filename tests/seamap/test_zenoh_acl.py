"""The boat <-> shore link secured as systemd/zenoh-boat.json5 and zenoh-shore.json5 say:
TLS, user/password authentication and access control (eclipse-zenoh 1.10).

Real sessions on 127.0.0.1 (multicast scouting off, free ports), opened the way the daemon
opens its own (``[zenoh] config_file`` through ``drivers.zenoh_io``) from copies of the
example files in which only the install paths are changed; the certificates are made with
the openssl commands README.md gives. The shore may subscribe, get tiles and send survey
requests; nothing it puts or deletes gets past the boat; a peer without the password, or
without TLS trust, never joins.

Negative checks first see a message of their own kind go through the same link (a
positive control), then wait ``QUIET_S`` more before asserting that nothing else came.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from daemon.config import ZenohConfig
from drivers.errors import SeamapError
from drivers.zenoh_io import (
    PLACEHOLDER,
    TileInfo,
    alive_key,
    control_key,
    decode_tile,
    encode_tile,
    json_bytes,
    open_session,
    parse_tile_key,
    pose_key,
    session_config,
    status_key,
    tile_key,
    tiles_selector,
)
from tests.ports import free_tcp_port

SYSTEMD_DIR = Path(__file__).resolve().parents[2] / "systemd"
BOAT_JSON5 = SYSTEMD_DIR / "zenoh-boat.json5"
SHORE_JSON5 = SYSTEMD_DIR / "zenoh-shore.json5"
USERS_EXAMPLE = SYSTEMD_DIR / "zenoh-users.example.txt"
TEST_PASSWORD = "test-only-7f3a9c"
INSTALL_DIR = "/etc/seamap/"  # where the example files expect themselves and the TLS files

OPENSSL = shutil.which("openssl")
pytestmark = pytest.mark.skipif(
    OPENSSL is None, reason="the openssl command is needed to make the test certificates"
)

VEHICLE = "boat1"
SURVEY = "s1"
QUIET_S = 1.5  # how long a negative check waits after its positive control came through
TIMEOUT_S = 10.0  # how long a positive check may take before it fails
TILE_VALUES = np.arange(1, 17, dtype=np.uint8).reshape(4, 4)
TILE_INFO = TileInfo(epsg=32631, res_m=0.02, west=15.36, north=-10.24, size_px=4, version=1)


# --- certificates (README.md, "Securing the link") and the installed example files ---------


def openssl(cwd: Path, *args: str) -> None:
    assert OPENSSL is not None
    subprocess.run([OPENSSL, *args], cwd=cwd, check=True, capture_output=True)


def make_ca(tls: Path, name: str) -> None:
    openssl(
        tls, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
        "-days", "3650", "-subj", "/CN=seamap CA", "-keyout", f"{name}.key", "-out", f"{name}.crt",
    )  # fmt: skip


def make_certificate(tls: Path, name: str, common_name: str, extensions: str, ca: str) -> None:
    openssl(
        tls, "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
        "-subj", f"/CN={common_name}", "-keyout", f"{name}.key", "-out", f"{name}.csr",
    )  # fmt: skip
    (tls / f"{name}.ext").write_text(extensions)
    openssl(
        tls, "x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.crt", "-CAkey", f"{ca}.key",
        "-CAcreateserial", "-days", "825", "-extfile", f"{name}.ext", "-out", f"{name}.crt",
    )  # fmt: skip


def with_password(text: str) -> str:
    """The example's placeholder password replaced, as an installer must (the daemon and
    the shore refuse to run with it)."""
    assert PLACEHOLDER in text
    return text.replace(f"{PLACEHOLDER}-shore-password", TEST_PASSWORD)


def installed_copy(source: Path, etc: Path) -> Path:
    """``source`` as installed under ``etc`` instead of /etc/seamap/, with a real password."""
    text = source.read_text(encoding="utf-8")
    assert INSTALL_DIR in text, f"{source.name} no longer refers to {INSTALL_DIR}"
    if PLACEHOLDER in text:
        text = with_password(text)
    target = etc / source.name
    target.write_text(text.replace(INSTALL_DIR, f"{etc}/"), encoding="utf-8")
    return target


@dataclass(frozen=True)
class Install:
    """The example files and the TLS files of boat and shore, as README.md installs them."""

    boat_json5: Path
    shore_json5: Path
    tls: Path


@pytest.fixture(scope="module")
def install(tmp_path_factory: pytest.TempPathFactory) -> Install:
    etc = tmp_path_factory.mktemp("etc-seamap")
    tls = etc / "tls"
    tls.mkdir()
    make_ca(tls, "ca")
    # The shore connects to 127.0.0.1 here: the boat's certificate must name it.
    make_certificate(
        tls, "boat", "boat1", "subjectAltName=DNS:localhost,IP:127.0.0.1\n"
        "extendedKeyUsage=serverAuth\n", ca="ca",
    )  # fmt: skip
    make_certificate(
        tls, "shore", "shore", "subjectAltName=DNS:shore\nextendedKeyUsage=clientAuth\n", ca="ca"
    )
    make_ca(tls, "other-ca")  # a CA the shore does not trust
    (etc / "zenoh-users.txt").write_text(with_password(USERS_EXAMPLE.read_text()))
    return Install(installed_copy(BOAT_JSON5, etc), installed_copy(SHORE_JSON5, etc), tls)


def boat_zenoh(install: Install, port: int) -> ZenohConfig:
    """The daemon's [zenoh] table on the boat: the example file, TLS on 127.0.0.1:port."""
    return ZenohConfig(
        mode="peer", listen=[f"tls/127.0.0.1:{port}"], connect=[],
        multicast_scouting=False, config_file=str(install.boat_json5),
    )  # fmt: skip


def shore_zenoh(install: Install, port: int, mode: str = "peer") -> ZenohConfig:
    """A shore program's [zenoh] table: the example file, connecting to the boat's port."""
    return ZenohConfig(
        mode=mode, listen=[], connect=[f"tls/127.0.0.1:{port}"],
        multicast_scouting=False, config_file=str(install.shore_json5),
    )  # fmt: skip


def open_changed(cfg: ZenohConfig, changes: dict[str, Any]) -> zenoh.Session:
    """A session from ``cfg`` with some zenoh keys changed (the variants the files describe)."""
    config = session_config(cfg)
    for key, value in changes.items():
        config.insert_json5(key, json.dumps(value))
    return zenoh.open(config)


# --- sessions ------------------------------------------------------------------------------


class Inbox:
    """What a subscriber (or a queryable) received, in order, from zenoh's threads."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._items: list[tuple[str, str, bytes]] = []

    def add(self, kind: str, key: str, payload: bytes) -> None:
        with self._changed:
            self._items.append((kind, key, payload))
            self._changed.notify_all()

    def on_sample(self, sample: zenoh.Sample) -> None:
        kind = "DELETE" if sample.kind == zenoh.SampleKind.DELETE else "PUT"
        self.add(kind, str(sample.key_expr), sample.payload.to_bytes())

    def items(self) -> list[tuple[str, str, bytes]]:
        with self._changed:
            return list(self._items)

    def wait_for(self, payload: bytes, timeout: float = TIMEOUT_S) -> bool:
        with self._changed:
            return self._changed.wait_for(
                lambda: any(item[2] == payload for item in self._items), timeout
            )

    def from_shore(self) -> list[tuple[str, str, bytes]]:
        """Anything the shore sent: its payloads start with b"shore", and it is the only
        one that deletes."""
        return [i for i in self.items() if i[2].startswith(b"shore") or i[0] == "DELETE"]


def marker(who: str) -> bytes:
    return f"{who}:{uuid.uuid4().hex}".encode()


def publish_until(session: zenoh.Session, key: str, inbox: Inbox) -> bytes:
    """Put one marker on ``key`` again and again until ``inbox`` has it (a subscription
    takes a moment to reach the publisher); fail after TIMEOUT_S."""
    payload = marker("boat")
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        session.put(key, payload)
        if inbox.wait_for(payload, timeout=0.2):
            return payload
    raise AssertionError(f"{key}: the publication never arrived")


@dataclass
class Boat:
    session: zenoh.Session
    port: int
    inbox: Inbox  # the boat's own subscriber on seamap/**
    requests: Inbox  # survey requests its control queryable answered
    keep: list[Any]  # declared entities, kept alive


def open_boat(cfg: ZenohConfig, changes: dict[str, Any] | None = None) -> Boat:
    """A boat as the daemon runs it: it subscribes to seamap/** (to catch what it must not
    receive), serves its tiles and survey control, and holds its liveliness token."""
    session = open_changed(cfg, changes or {})
    inbox, requests = Inbox(), Inbox()

    def serve_tiles(query: zenoh.Query) -> None:
        query.reply(
            tile_key(VEHICLE, SURVEY, *TILE_INFO.key()), encode_tile(TILE_VALUES),
            encoding=zenoh.Encoding.IMAGE_PNG, attachment=TILE_INFO.to_json(),
        )  # fmt: skip

    def serve_control(query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b"{}"
        requests.add("QUERY", str(query.key_expr), payload)
        action = json.loads(payload).get("action")
        query.reply(query.key_expr, json_bytes({"ok": True, "survey": SURVEY, "action": action}))

    keep = [
        session.declare_subscriber("seamap/**", inbox.on_sample),
        session.declare_queryable(tiles_selector(VEHICLE), serve_tiles, complete=True),
        session.declare_queryable(control_key(VEHICLE), serve_control, complete=True),
        session.liveliness().declare_token(alive_key(VEHICLE)),
    ]
    return Boat(session, int(cfg.listen[0].rsplit(":", 1)[1]), inbox, requests, keep)


def control_roundtrip(shore: zenoh.Session, boat: Boat) -> None:
    """Positive control for the shore -> boat direction: a survey status request goes
    through and is answered (same link, same priority as the shore's puts)."""
    request = marker("control")
    replies = list(
        shore.get(
            control_key(VEHICLE), payload=json_bytes({"action": "status", "id": request.decode()}),
            timeout=TIMEOUT_S,
        )
    )  # fmt: skip
    assert [r.ok is not None for r in replies] == [True], "the survey request went unanswered"
    assert any(request in item[2] for item in boat.requests.items())


def wait_connected(session: zenoh.Session) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not (session.info.peers_zid() or session.info.routers_zid()):
        assert time.monotonic() < deadline, "the session never connected"
        time.sleep(0.05)


@dataclass
class Link:
    boat: Boat
    shore: zenoh.Session
    shore_inbox: Inbox
    viewer: zenoh.Session  # a second, client-mode shore station: the boat routes its data
    viewer_inbox: Inbox


@pytest.fixture(scope="module")
def link(install: Install) -> Iterator[Link]:
    port = free_tcp_port()
    boat = open_boat(boat_zenoh(install, port))
    sessions = [boat.session]
    try:
        shore = open_session(shore_zenoh(install, port))
        sessions.append(shore)
        viewer = open_session(shore_zenoh(install, port, mode="client"))
        sessions.append(viewer)
        shore_inbox, viewer_inbox = Inbox(), Inbox()
        keep = [
            shore.declare_subscriber("seamap/**", shore_inbox.on_sample),
            viewer.declare_subscriber("seamap/**", viewer_inbox.on_sample),
        ]
        wait_connected(shore)
        yield Link(boat, shore, shore_inbox, viewer, viewer_inbox)
        del keep
    finally:
        for session in reversed(sessions):
            session.close()


# --- what the shore may do -----------------------------------------------------------------


def test_boat_publications_reach_the_shore_over_tls(link: Link) -> None:
    pose = publish_until(link.boat.session, pose_key(VEHICLE), link.shore_inbox)
    assert ("PUT", pose_key(VEHICLE), pose) in link.shore_inbox.items()
    tile = tile_key(VEHICLE, SURVEY, 0, 0)
    assert ("PUT", tile, publish_until(link.boat.session, tile, link.shore_inbox)) in (
        link.shore_inbox.items()
    )
    # ...and to the client-mode viewer, which the boat routes for.
    publish_until(link.boat.session, status_key(VEHICLE), link.viewer_inbox)


def test_shore_gets_the_tiles_from_the_boat_queryable(link: Link) -> None:
    replies = list(link.shore.get(tiles_selector(VEHICLE, "*"), timeout=TIMEOUT_S))
    samples = [r.ok for r in replies if r.ok is not None]
    assert len(samples) == len(replies) == 1
    sample = samples[0]
    assert parse_tile_key(str(sample.key_expr)) is not None
    assert str(sample.encoding) == str(zenoh.Encoding.IMAGE_PNG)
    assert sample.attachment is not None
    assert TileInfo.from_json(sample.attachment.to_bytes()) == TILE_INFO
    np.testing.assert_array_equal(decode_tile(sample.payload.to_bytes()), TILE_VALUES)


def test_shore_may_start_and_stop_a_survey(link: Link) -> None:
    """Documented choice: a survey request is a query the boat answers, so it is allowed."""
    for action in ("start", "stop"):
        replies = list(
            link.shore.get(
                control_key(VEHICLE), payload=json_bytes({"action": action}), timeout=TIMEOUT_S
            )
        )
        assert len(replies) == 1 and replies[0].ok is not None
        assert json.loads(replies[0].ok.payload.to_bytes())["action"] == action


def test_shore_sees_the_boat_alive(link: Link) -> None:
    replies = list(link.shore.liveliness().get("seamap/*/alive", timeout=TIMEOUT_S))
    assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [alive_key(VEHICLE)]
    # As `seamap shore` follows it: a liveliness subscriber with history.
    tokens = Inbox()
    sub = link.shore.liveliness().declare_subscriber(
        "seamap/*/alive", tokens.on_sample, history=True
    )
    assert tokens.wait_for(b"") and tokens.items()[0][:2] == ("PUT", alive_key(VEHICLE))
    sub.undeclare()


def test_a_query_outside_the_rules_is_answered_by_nobody(link: Link) -> None:
    """A get on seamap/** is not included in any allowed key: the boat drops it (and zenoh
    ends the query at once rather than at its timeout)."""
    assert list(link.shore.get("seamap/**", timeout=TIMEOUT_S)) == []


# --- what the shore may not do -------------------------------------------------------------


def test_shore_puts_and_deletes_reach_nobody_through_the_boat(link: Link) -> None:
    link.shore.put(pose_key(VEHICLE), marker("shore"))
    link.shore.put(tile_key(VEHICLE, "x", 0, 0), marker("shore"))
    link.shore.put(status_key(VEHICLE), marker("shore"))
    link.shore.delete(tile_key(VEHICLE, SURVEY, 0, 0))
    # Positive controls: the shore's request after its puts reached the boat; a boat
    # publication after that reached the viewer the boat routes for.
    control_roundtrip(link.shore, link.boat)
    publish_until(link.boat.session, status_key(VEHICLE), link.viewer_inbox)
    time.sleep(QUIET_S)

    assert link.boat.inbox.from_shore() == []
    assert link.viewer_inbox.from_shore() == []


def test_the_boat_drops_shore_puts_on_arrival(install: Install) -> None:
    """Even a shore that is told of the boat's subscriber (an extra rule, for this test only:
    the example hides the boat's subscriptions, so a well-behaved shore never sends) gets
    nothing in: the boat drops its puts at ingress, silently."""
    cfg = boat_zenoh(install, free_tcp_port())
    rules = json.loads(session_config(cfg).get_json("access_control/rules"))
    policies = json.loads(session_config(cfg).get_json("access_control/policies"))
    rules.append(
        {"id": "tell-subscriptions", "messages": ["declare_subscriber"], "flows": ["egress"],
         "permission": "allow", "key_exprs": ["seamap/**"]}
    )  # fmt: skip
    policies[0]["rules"].append("tell-subscriptions")
    boat = open_boat(cfg, {"access_control/rules": rules, "access_control/policies": policies})
    try:
        with open_session(shore_zenoh(install, boat.port)) as shore:
            publisher = shore.declare_publisher(pose_key(VEHICLE))
            deadline = time.monotonic() + TIMEOUT_S
            # The stub says bool; zenoh 1.10 returns a MatchingStatus.
            while not publisher.matching_status.matching:  # type: ignore[attr-defined]
                assert time.monotonic() < deadline, "the shore never learned of the subscriber"
                time.sleep(0.05)
            publisher.put(marker("shore"))
            shore.put(tile_key(VEHICLE, "x", 0, 0), marker("shore"))
            control_roundtrip(shore, boat)
            time.sleep(QUIET_S)
            assert boat.inbox.from_shore() == []
    finally:
        boat.session.close()


# --- who may not connect -------------------------------------------------------------------


def test_a_wrong_password_never_joins(link: Link, install: Install) -> None:
    """A peer-mode session opens anyway (zenoh keeps retrying in the background), but the
    boat refuses every handshake: no peer, no data."""
    cfg = shore_zenoh(install, link.boat.port)
    with open_changed(cfg, {"transport/auth/usrpwd/password": "wrong"}) as intruder:
        inbox = Inbox()
        sub = intruder.declare_subscriber("seamap/**", inbox.on_sample)
        # Positive control: the same boat publications reach the real shore.
        publish_until(link.boat.session, pose_key(VEHICLE), link.shore_inbox)
        time.sleep(QUIET_S)
        assert inbox.items() == []
        assert intruder.info.peers_zid() == []
        assert str(intruder.zid()) not in {str(z) for z in link.boat.session.info.peers_zid()}
        del sub


def test_a_client_with_an_unknown_user_fails_to_open(link: Link, install: Install) -> None:
    """In client mode zenoh gives up at once: the session does not open."""
    cfg = shore_zenoh(install, link.boat.port, mode="client")
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        open_changed(cfg, {"transport/auth/usrpwd/user": "intruder"}).close()


def test_the_shore_refuses_a_boat_it_cannot_verify(link: Link, install: Install) -> None:
    """TLS works both ways: with another CA as its root, the shore never joins the boat."""
    cfg = shore_zenoh(install, link.boat.port)
    other_ca = str(install.tls / "other-ca.crt")
    with open_changed(cfg, {"transport/link/tls/root_ca_certificate": other_ca}) as shore:
        inbox = Inbox()
        sub = shore.declare_subscriber("seamap/**", inbox.on_sample)
        publish_until(link.boat.session, pose_key(VEHICLE), link.shore_inbox)
        time.sleep(QUIET_S)
        assert inbox.items() == []
        assert shore.info.peers_zid() == []
        del sub


def test_the_boat_will_not_listen_on_plain_tcp(install: Install) -> None:
    cfg = boat_zenoh(install, free_tcp_port())
    tcp = ZenohConfig(
        listen=[cfg.listen[0].replace("tls/", "tcp/")], multicast_scouting=False,
        config_file=cfg.config_file,
    )  # fmt: skip
    with pytest.raises(SeamapError, match="Unsupported protocol: tcp"):
        open_session(tcp).close()


# --- mutual TLS (the files' enable_mtls switch) --------------------------------------------


def test_mutual_tls_admits_the_shore_certificate_only(install: Install) -> None:
    """enable_mtls on both sides, and the subject narrowed to the certificate's common name
    as the boat file suggests: the shore with its certificate gets the data; a shore
    without one (enable_mtls left false) never joins."""
    mtls = {"transport/link/tls/enable_mtls": True}
    subjects = [{"id": "shore", "usernames": ["shore"], "cert_common_names": ["shore"]}]
    boat = open_boat(
        boat_zenoh(install, free_tcp_port()), {**mtls, "access_control/subjects": subjects}
    )
    try:
        with (
            open_changed(shore_zenoh(install, boat.port), mtls) as shore,
            open_session(shore_zenoh(install, boat.port)) as no_certificate,
        ):
            inbox, refused = Inbox(), Inbox()
            subs = [
                shore.declare_subscriber("seamap/**", inbox.on_sample),
                no_certificate.declare_subscriber("seamap/**", refused.on_sample),
            ]
            wait_connected(shore)
            publish_until(boat.session, pose_key(VEHICLE), inbox)
            time.sleep(QUIET_S)
            assert refused.items() == []
            assert no_certificate.info.peers_zid() == []
            del subs
    finally:
        boat.session.close()


def test_the_example_placeholder_password_is_refused(tmp_path: Path) -> None:
    """Installed as shipped, without replacing REPLACE-ME, the boat will not start."""
    etc = tmp_path / "etc"
    etc.mkdir()
    text = (SYSTEMD_DIR / "zenoh-boat.json5").read_text().replace(INSTALL_DIR, f"{etc}/")
    (etc / "zenoh-boat.json5").write_text(text)
    shutil.copyfile(USERS_EXAMPLE, etc / "zenoh-users.txt")
    cfg = ZenohConfig(listen=["tls/127.0.0.1:7447"], config_file=str(etc / "zenoh-boat.json5"))
    with pytest.raises(SeamapError, match="still the example's REPLACE-ME"):
        session_config(cfg)
