"""systemd's notify protocol (``sd_notify``) without a dependency.

Under ``Type=notify`` systemd passes ``$NOTIFY_SOCKET``, an ``AF_UNIX`` datagram socket
(a filesystem path, or an abstract name written with a leading ``@``), and reads
newline-separated ``KEY=VALUE`` assignments from each datagram: ``READY=1`` when start-up
is done, ``WATCHDOG=1`` to pet the watchdog, ``STOPPING=1``, ``EXTEND_TIMEOUT_USEC=`` to
keep a long start or stop from timing out, ``STATUS=`` for ``systemctl status``.
``WATCHDOG_USEC`` (with ``WATCHDOG_PID``, when set, naming the process it is meant for)
tells how often the watchdog must be petted. See sd_notify(3) and sd_watchdog_enabled(3).

Without ``$NOTIFY_SOCKET`` (a terminal, a test, another init) every method does nothing.
A failed send never raises: the first is logged at WARNING, later ones at DEBUG.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections.abc import Mapping

log = logging.getLogger(__name__)

SEND_TIMEOUT_S = 1.0
"""Longest a send may block (the manager's queue full); the daemon's event loop calls us."""


def _socket_address(value: str) -> bytes | None:
    """The ``sendto`` address for ``$NOTIFY_SOCKET``, or None when it is unset or unusable."""
    if value.startswith("/"):
        return os.fsencode(value)
    if value.startswith("@") and len(value) > 1:
        return b"\0" + os.fsencode(value[1:])
    if value:
        # e.g. systemd 254's "vsock:CID:PORT" (a VM's manager), or a relative path
        log.warning("NOTIFY_SOCKET=%r is not a unix socket path; not notifying systemd", value)
    return None


def _watchdog_interval_s(environ: Mapping[str, str]) -> float | None:
    """The watchdog timeout (seconds) meant for this process, as sd_watchdog_enabled(3)."""
    usec_text = environ.get("WATCHDOG_USEC", "")
    if not usec_text:
        return None
    try:
        usec = int(usec_text)
    except ValueError:
        log.warning("ignoring WATCHDOG_USEC=%r: not an integer", usec_text)
        return None
    if usec <= 0:
        return None
    pid_text = environ.get("WATCHDOG_PID", "")
    if pid_text:
        try:
            pid = int(pid_text)
        except ValueError:
            log.warning("ignoring the watchdog: WATCHDOG_PID=%r is not a pid", pid_text)
            return None
        if pid != os.getpid():
            return None  # meant for another process (we were started by the main one)
    return usec / 1e6


def _one_line(text: str) -> str:
    """A value on one line: a newline would start a new assignment in the datagram."""
    return " ".join(text.splitlines())


class Notifier:
    """systemd's notify protocol ($NOTIFY_SOCKET); every method is a no-op without it."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env: Mapping[str, str] = os.environ if environ is None else environ
        self._address = _socket_address(env.get("NOTIFY_SOCKET", ""))
        self.enabled: bool = self._address is not None
        """NOTIFY_SOCKET names a unix socket: systemd (Type=notify) is listening."""
        self.watchdog_interval_s: float | None = _watchdog_interval_s(env)
        """The watchdog timeout (seconds) when systemd watches this process, else None;
        pet it (``watchdog()``) at half this."""
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._failed_before = False

    def ready(self, status: str | None = None) -> None:
        """Start-up is finished (``READY=1``), with an optional status line."""
        self._send("READY=1", status)

    def status(self, text: str) -> None:
        """The one-line status ``systemctl status`` shows."""
        self._send(None, text)

    def watchdog(self) -> None:
        """Pet the watchdog (``WATCHDOG=1``)."""
        self._send("WATCHDOG=1", None)

    def stopping(self, status: str | None = None) -> None:
        """Shutdown has begun (``STOPPING=1``), with an optional status line."""
        self._send("STOPPING=1", status)

    def extend_timeout(self, seconds: float) -> None:
        """Ask for ``seconds`` more before the current start/stop timeout fires.

        Not cumulative: each call sets a new deadline ``seconds`` from now, so send it again
        before that runs out while a long stop (the survey-end pass) still progresses.
        """
        if not math.isfinite(seconds) or seconds < 0:
            log.warning("not extending the systemd timeout by %r s", seconds)
            return
        self._send(f"EXTEND_TIMEOUT_USEC={round(seconds * 1e6)}", None)

    def reloading(self) -> None:
        """A configuration reload has begun (``RELOADING=1`` and ``MONOTONIC_USEC``);
        send ``ready()`` when it is done."""
        now_usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        self._send(f"RELOADING=1\nMONOTONIC_USEC={now_usec}", None)

    def close(self) -> None:
        """Close the socket (a later call opens it again)."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def _send(self, fields: str | None, status: str | None) -> None:
        if self._address is None:
            return
        lines = [] if fields is None else [fields]
        if status is not None:
            lines.append(f"STATUS={_one_line(status)}")
        datagram = "\n".join(lines).encode("utf-8", errors="replace")
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                    self._sock.settimeout(SEND_TIMEOUT_S)
                self._sock.sendto(datagram, self._address)
            except OSError as exc:
                where = os.fsdecode(self._address).replace("\0", "@", 1)
                if self._failed_before:
                    log.debug("cannot notify systemd at %s (%s)", where, exc)
                else:
                    log.warning(
                        "cannot notify systemd at %s (%s); later failures are logged at debug",
                        where,
                        exc,
                    )
                self._failed_before = True


__all__ = ["Notifier"]
