"""The daemon's local control socket: ``state_dir/control.sock``, one JSON object a line.

Requests ``{"command": "status"}``, ``{"command": "start"}`` (open a survey; with
``"area"``, a GeoJSON geometry in WGS84, the area it is to cover),
``{"command": "stop"}`` (end it; the survey-end pass runs in the background); each gets
one reply line ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``. ``seamap ctl``
is its client; access is the socket file's permissions (the daemon's user and group).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
from pathlib import Path
from typing import Any, Protocol

from drivers.errors import SeamapError

log = logging.getLogger(__name__)

MAX_REQUEST = 4 * 2**20
"""A request line's limit (bytes): room for an area's polygons."""
COMMANDS = ("status", "start", "stop")


class Controllable(Protocol):
    """What the control socket drives (``daemon.service.Daemon``)."""

    async def start_survey(self, reason: str, area: dict[str, Any] | None = None) -> str: ...

    async def stop_survey(self, reason: str, *, wait: bool) -> str | None: ...

    def status(self) -> dict[str, Any]: ...


async def serve_control(daemon: Controllable, path: Path) -> None:
    """Serve the control socket at ``path`` until cancelled."""
    with contextlib.suppress(FileNotFoundError):
        path.unlink()  # a stale socket from a crashed run

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                line = await asyncio.wait_for(reader.readline(), 5.0)
            except ValueError:  # longer than MAX_REQUEST
                reply: dict[str, Any] = {
                    "ok": False,
                    "error": f"request longer than {MAX_REQUEST} bytes",
                }
            else:
                reply = await _answer(daemon, line)
            writer.write(json.dumps(reply).encode() + b"\n")
            await writer.drain()
        except (OSError, TimeoutError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_unix_server(handle, path, limit=MAX_REQUEST)
    os.chmod(path, 0o660)
    try:
        async with server:
            await server.serve_forever()
    finally:
        with contextlib.suppress(OSError):
            path.unlink()


async def _answer(daemon: Controllable, line: bytes) -> dict[str, Any]:
    try:
        request = json.loads(line)
        command = request["command"]
    except (ValueError, KeyError, TypeError):
        return {"ok": False, "error": 'expected one JSON line {"command": ...}'}
    if command not in COMMANDS:
        return {"ok": False, "error": f"unknown command {command!r} (known: {', '.join(COMMANDS)})"}
    if command == "start":
        area = request.get("area")
        if area is not None and not isinstance(area, dict):
            return {"ok": False, "error": "area must be a GeoJSON object"}
        try:
            survey = await daemon.start_survey("command", area)
        except SeamapError as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True, "survey": survey}
    if command == "stop":
        stopped = await daemon.stop_survey("command", wait=False)
        return {"ok": True, "survey": stopped}
    return {"ok": True, "status": daemon.status()}


def request(path: Path, command: str, timeout_s: float = 10.0, **fields: Any) -> dict[str, Any]:
    """Send one command (with ``fields``, e.g. ``area``) to the daemon listening at
    ``path``; its reply (blocking client)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.connect(str(path))
            sock.sendall(json.dumps({"command": command, **fields}).encode() + b"\n")
            data = b""
            while not data.endswith(b"\n"):
                chunk = sock.recv(65536)
                if not chunk:
                    break
                data += chunk
        except FileNotFoundError:
            raise SeamapError(
                f"{path}: no daemon control socket (is `seamap run` running?)"
            ) from None
        except ConnectionRefusedError:
            raise SeamapError(f"{path}: the daemon is not listening (not running?)") from None
        except TimeoutError:
            raise SeamapError(f"{path}: the daemon did not answer within {timeout_s:g} s") from None
        except OSError as exc:
            raise SeamapError(f"{path}: {exc.strerror or exc}") from None
    try:
        reply: dict[str, Any] = json.loads(data)
    except ValueError:
        raise SeamapError(f"{path}: the daemon's reply is not JSON") from None
    return reply
