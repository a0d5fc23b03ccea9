"""sd_notify over a real AF_UNIX datagram socket, as systemd's manager receives it."""

from __future__ import annotations

import logging
import os
import socket
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from daemon.notify import Notifier


class Manager:
    """The receiving end: a datagram socket bound where $NOTIFY_SOCKET points."""

    def __init__(self, sock: socket.socket, notify_socket: str) -> None:
        self.sock = sock
        self.notify_socket = notify_socket

    def receive(self) -> bytes:
        return self.sock.recv(4096)

    def nothing_pending(self) -> bool:
        self.sock.setblocking(False)
        try:
            self.sock.recv(4096)
        except BlockingIOError:
            return True
        finally:
            self.sock.settimeout(2.0)
        return False


@pytest.fixture
def manager(tmp_path: Path) -> Iterator[Manager]:
    path = tmp_path / "notify"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield Manager(sock, str(path))
    sock.close()


@pytest.fixture
def abstract_manager() -> Iterator[Manager]:
    name = f"seamap-test-{os.getpid()}-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    yield Manager(sock, "@" + name)
    sock.close()


def test_ready_with_status_is_one_datagram(manager: Manager) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": manager.notify_socket})
    assert notifier.enabled
    notifier.ready("recording survey 2024-05-01")
    assert manager.receive() == b"READY=1\nSTATUS=recording survey 2024-05-01"
    notifier.ready()
    assert manager.receive() == b"READY=1"
    notifier.close()


def test_each_message_is_exact(manager: Manager) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": manager.notify_socket})
    notifier.watchdog()
    assert manager.receive() == b"WATCHDOG=1"
    notifier.status("final pass: 120 of 580 frames")
    assert manager.receive() == b"STATUS=final pass: 120 of 580 frames"
    notifier.stopping("ending survey")
    assert manager.receive() == b"STOPPING=1\nSTATUS=ending survey"
    notifier.stopping()
    assert manager.receive() == b"STOPPING=1"
    notifier.extend_timeout(90)
    assert manager.receive() == b"EXTEND_TIMEOUT_USEC=90000000"
    notifier.extend_timeout(0.25)
    assert manager.receive() == b"EXTEND_TIMEOUT_USEC=250000"
    assert manager.nothing_pending()
    notifier.close()


def test_reloading_carries_the_monotonic_clock(manager: Manager) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": manager.notify_socket})
    before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    notifier.reloading()
    after = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    first, second = manager.receive().split(b"\n")
    assert first == b"RELOADING=1"
    key, value = second.split(b"=")
    assert key == b"MONOTONIC_USEC"
    assert before <= int(value) <= after
    notifier.close()


def test_status_stays_on_one_line(manager: Manager) -> None:
    """A newline in a status would smuggle in another assignment (READY=1 here)."""
    notifier = Notifier({"NOTIFY_SOCKET": manager.notify_socket})
    notifier.status("sonar lost\nREADY=1")
    assert manager.receive() == b"STATUS=sonar lost READY=1"
    notifier.close()


def test_abstract_socket(abstract_manager: Manager) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": abstract_manager.notify_socket})
    assert notifier.enabled
    notifier.ready("up")
    assert abstract_manager.receive() == b"READY=1\nSTATUS=up"
    notifier.watchdog()
    assert abstract_manager.receive() == b"WATCHDOG=1"
    notifier.close()


def test_reads_os_environ_by_default(manager: Manager, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NOTIFY_SOCKET", manager.notify_socket)
    monkeypatch.setenv("WATCHDOG_USEC", "30000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    notifier = Notifier()
    assert notifier.watchdog_interval_s == 30.0
    notifier.watchdog()
    assert manager.receive() == b"WATCHDOG=1"
    notifier.close()


def test_sends_again_after_close(manager: Manager) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": manager.notify_socket})
    notifier.close()
    notifier.close()
    notifier.status("still here")
    assert manager.receive() == b"STATUS=still here"
    notifier.close()


@pytest.mark.parametrize(
    ("environ", "interval_s"),
    [
        ({}, None),
        ({"WATCHDOG_USEC": "30000000"}, 30.0),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())}, 30.0),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid() + 1)}, None),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "main"}, None),
        ({"WATCHDOG_USEC": "1500000"}, 1.5),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "-5"}, None),
        ({"WATCHDOG_USEC": "30s"}, None),
        ({"WATCHDOG_USEC": ""}, None),
    ],
)
def test_watchdog_interval(environ: dict[str, str], interval_s: float | None) -> None:
    assert Notifier(environ).watchdog_interval_s == interval_s


def test_without_notify_socket_nothing_happens() -> None:
    notifier = Notifier({"WATCHDOG_USEC": "30000000"})
    assert not notifier.enabled
    assert notifier.watchdog_interval_s == 30.0  # told, even if nobody listens
    notifier.ready("x")
    notifier.status("x")
    notifier.watchdog()
    notifier.stopping()
    notifier.extend_timeout(10)
    notifier.reloading()
    notifier.close()


@pytest.mark.parametrize("value", ["", "relative/notify", "vsock:2:1234", "@"])
def test_unusable_notify_socket_disables(value: str) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": value})
    assert not notifier.enabled
    notifier.ready()
    notifier.close()


def test_missing_socket_does_not_raise_and_warns_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone")})
    assert notifier.enabled
    with caplog.at_level(logging.DEBUG, logger="daemon.notify"):
        notifier.ready("up")
        notifier.watchdog()
        notifier.watchdog()
        notifier.stopping()
    records = [r for r in caplog.records if r.name == "daemon.notify"]
    assert [r.levelno for r in records] == [
        logging.WARNING,
        logging.DEBUG,
        logging.DEBUG,
        logging.DEBUG,
    ]
    assert str(tmp_path / "gone") in records[0].getMessage()
    notifier.close()


def test_socket_that_goes_away_does_not_raise(manager: Manager) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": manager.notify_socket})
    notifier.watchdog()
    assert manager.receive() == b"WATCHDOG=1"
    manager.sock.close()
    os.unlink(manager.notify_socket)
    notifier.watchdog()  # the manager restarted away under us: ECONNREFUSED/ENOENT, logged
    notifier.close()


def test_bad_extension_is_not_sent(manager: Manager) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": manager.notify_socket})
    notifier.extend_timeout(float("nan"))
    notifier.extend_timeout(-1.0)
    assert manager.nothing_pending()
    notifier.close()
