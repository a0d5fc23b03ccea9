"""Running the real daemon (``seamap run``) as a child process against emulators on loopback."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from daemon.config import ZenohConfig, config_from_dict, dump_config
from daemon.control import request
from drivers.errors import SeamapError
from drivers.zenoh_io import open_session
from tests.ports import free_tcp_port, free_udp_port

SEAMAP = str(Path(sys.executable).parent / "seamap")


def zenoh_table(port: int | None = None) -> dict[str, Any]:
    """A zenoh peer on 127.0.0.1 only (a free port unless given), no multicast scouting."""
    port = free_tcp_port() if port is None else port
    return {"listen": [f"tcp/127.0.0.1:{port}"], "multicast_scouting": False}


def write_config(
    sim_dir: Path,
    path: Path,
    state_dir: Path,
    sonar_port: int,
    mavlink_url: str,
    zenoh_port: int | None = None,
    mapping: dict[str, Any] | None = None,
    tables: dict[str, dict[str, Any]] | None = None,
    **daemon: Any,
) -> Path:
    """The simulated survey's site config pointed at the emulators and ``state_dir``, its
    zenoh endpoint on 127.0.0.1; ``mapping`` and ``daemon`` override keys of those tables,
    ``tables`` keys of any table (``{"mission": {"replan_at_end": True}}``)."""
    data = tomllib.loads((sim_dir / "site.toml").read_text())
    data.setdefault("mapping", {}).update(mapping or {})
    for table, keys in (tables or {}).items():
        data.setdefault(table, {}).update(keys)
    data.setdefault("daemon", {}).update(
        {"state_dir": str(state_dir), "survey_autostart": True, "health_interval_s": 2.0, **daemon}
    )
    data.setdefault("sonar", {}).update(
        address="127.0.0.1", tcp_port=sonar_port, status_port=free_udp_port()
    )
    data.setdefault("mavlink", {}).update(url=mavlink_url)
    data["zenoh"] = zenoh_table(zenoh_port)
    path.write_text(dump_config(config_from_dict(data)))
    return path


@dataclass
class DaemonRun:
    """What a daemon run under test left: its survey folder, exit code, log and status
    snapshots (a test's outcome adds what it measured)."""

    survey: Path
    exit_code: int
    log: str
    statuses: list[dict[str, Any]]


class DaemonProcess:
    """``seamap run --config`` as a child; stderr goes to ``log_path`` (appended)."""

    def __init__(self, config: Path, state_dir: Path, log_path: Path) -> None:
        self.config = config
        self.state_dir = state_dir
        self.log_path = log_path
        self.proc: asyncio.subprocess.Process | None = None
        self.statuses: list[dict[str, Any]] = []
        self._poller: asyncio.Task[None] | None = None

    async def start(self) -> None:
        with open(self.log_path, "ab") as log:
            self.proc = await asyncio.create_subprocess_exec(
                SEAMAP, "run", "--config", str(self.config), stderr=log, stdout=log,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )  # fmt: skip
        self._poller = asyncio.create_task(self._poll_status())

    async def _poll_status(self) -> None:
        """Keep every status snapshot the control socket gives, twice a second."""
        sock = self.state_dir / "control.sock"
        while True:
            await asyncio.sleep(0.5)
            try:
                reply = await asyncio.to_thread(request, sock, "status", 2.0)
            except SeamapError:
                continue
            if reply.get("ok"):
                self.statuses.append(reply["status"])

    async def wait_status(self, check: Any, timeout_s: float) -> dict[str, Any]:
        """Wait until a status snapshot taken from now on satisfies ``check``; that snapshot."""
        deadline = time.monotonic() + timeout_s
        seen = len(self.statuses)
        while time.monotonic() < deadline:
            for status in self.statuses[seen:]:
                if check(status):
                    return status
            seen = len(self.statuses)
            assert self.proc is not None and self.proc.returncode is None, self.log()
            await asyncio.sleep(0.2)
        raise AssertionError(f"no status met the condition in {timeout_s} s\n{self.log()}")

    async def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 180.0) -> int:
        assert self.proc is not None
        if self._poller is not None:
            self._poller.cancel()
            await asyncio.gather(self._poller, return_exceptions=True)
        self.proc.send_signal(sig)
        return await asyncio.wait_for(self.proc.wait(), timeout_s)

    async def ensure_stopped(self) -> None:
        """Kill the daemon if it still runs (a test that failed half way leaves none)."""
        if self._poller is not None:
            self._poller.cancel()
            await asyncio.gather(self._poller, return_exceptions=True)
        if self.proc is not None and self.proc.returncode is None:
            self.proc.kill()
            await asyncio.wait_for(self.proc.wait(), 30)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


@dataclass
class Heard:
    key: str
    payload: bytes
    attachment: bytes | None
    encoding: str
    at: float


class ZenohObserver:
    """A shore-side zenoh client on 127.0.0.1 that keeps everything under ``seamap/**``."""

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self.heard: list[Heard] = []
        self.session: Any = None
        self._subscriber: Any = None

    def open(self) -> None:
        self.session = open_session(ZenohConfig(mode="client", listen=[], connect=[self.endpoint]))
        self._subscriber = self.session.declare_subscriber("seamap/**", self._keep)

    def _keep(self, sample: Any) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        self.heard.append(
            Heard(str(sample.key_expr), sample.payload.to_bytes(), attachment,
                  str(sample.encoding), time.monotonic())
        )  # fmt: skip

    def get(self, selector: str, payload: bytes | None = None) -> list[Heard]:
        replies = []
        for reply in self.session.get(selector, payload=payload, timeout=10.0):
            if reply.ok is None:
                continue
            sample = reply.ok
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            replies.append(
                Heard(str(sample.key_expr), sample.payload.to_bytes(), attachment,
                      str(sample.encoding), time.monotonic())
            )  # fmt: skip
        return replies

    def alive(self, vehicle: str) -> bool:
        return any(True for _ in self.session.liveliness().get(f"seamap/{vehicle}/alive"))

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None
