"""``seamap router``: the zenoh router a fleet's boats and shore stations meet at.

A zenoh session in the library's own router mode (no separate ``zenohd`` to install),
configured like every other session from a site file's ``[zenoh]`` table: its
``config_file`` first (TLS, user/password authentication, access control, in zenoh's own
JSON5), then ``listen`` and ``connect`` (another router, for a chain of them). The mode
is always "router"; boats and shores connect to it as clients (``mode = "client"``,
``connect = ["tcp/ROUTER:7447"]``) or as peers. Vehicles are told apart by their id in
the keys (``seamap/{vehicle}/...``): the router carries them all and holds nothing
itself; a shore that comes late (or after a router restart) catches up from the boats,
which hold their tiles.

Like the daemon, it refuses to listen in plain TCP (UDP, WebSocket) on an address other
hosts reach unless ``[zenoh] allow_insecure`` says so: anyone reaching that port could
publish as any boat. Without a site file it listens on ``tcp/127.0.0.1:7447``.

While it runs it tells, every ``status_interval_s``, which vehicles are alive (their
liveliness tokens, seen through the router).
"""

from __future__ import annotations

import contextlib
import math
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from types import FrameType
from typing import TextIO

import zenoh

from daemon.config import SiteConfig, ZenohConfig
from drivers.errors import SeamapError
from drivers.zenoh_io import (
    ROOT,
    alive_key,
    insecure_listen,
    open_session,
    parse_alive_key,
    with_endpoints,
)

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
STATUS_INTERVAL_S = 10.0


@dataclass(frozen=True)
class RouterSettings:
    zenoh: ZenohConfig
    status_interval_s: float = STATUS_INTERVAL_S


def router_settings(
    config: SiteConfig | None = None,
    *,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
) -> RouterSettings:
    """The router's session: ``config``'s ``[zenoh]`` table (without one: listening on
    ``DEFAULT_LISTEN``, no multicast scouting) in router mode, each given option replacing
    the config's value. SeamapError naming a malformed endpoint, or a plain one open to
    the network without ``allow_insecure``."""
    base = (
        config.zenoh
        if config is not None
        else ZenohConfig(listen=[DEFAULT_LISTEN], connect=[], multicast_scouting=False)
    )
    session = with_endpoints(base, listen, connect, mode="router")
    if not session.listen:
        raise SeamapError("no listen endpoint: give --listen or [zenoh] listen")
    exposed = insecure_listen(session.listen)
    if exposed and not session.allow_insecure:
        raise SeamapError(
            f"listen {exposed[0]!r} is plain, unauthenticated and open to the "
            "network (anyone reaching it could publish as any boat and stop its surveys): "
            "give a [zenoh] config_file with TLS and access control, listen on 127.0.0.1, "
            "or set [zenoh] allow_insecure = true"
        )
    return RouterSettings(session)


class Router:
    """The router's session and the vehicles it has seen (``open``, ``run``, ``close``;
    ``stop`` from any thread or a signal handler)."""

    def __init__(self, settings: RouterSettings, console: TextIO | None = None) -> None:
        self.settings = settings
        self._console = console if console is not None else sys.stderr
        self._session: zenoh.Session | None = None
        self._alive: dict[str, bool] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()

    def __enter__(self) -> Router:
        self.open()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Open the router session (SeamapError in one line: a port in use, a bad
        config file) and follow the vehicles' liveliness."""
        if self._session is not None:
            return
        cfg = self.settings.zenoh
        session = open_session(cfg)
        try:
            session.liveliness().declare_subscriber(
                alive_key("*"), self._on_liveliness, history=True
            )
        except zenoh.ZError as exc:
            session.close()
            raise SeamapError(f"zenoh: cannot follow {ROOT}/*/alive ({exc})") from None
        self._session = session
        links = [f"listening on {', '.join(cfg.listen)}"]
        links += [f"connected to {', '.join(cfg.connect)}"] if cfg.connect else []
        self._tell(f"router {session.info.zid()} {' and '.join(links)}")

    def close(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def stop(self) -> None:
        self._stop.set()

    def run(self, duration_s: float | None = None) -> None:
        """Route until ``stop`` (or ``duration_s``), telling the vehicles alive now and
        then."""
        self.open()
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        interval = self.settings.status_interval_s
        while not self._stop.is_set():
            wait = min(interval, end - time.monotonic())
            if wait <= 0 or self._stop.wait(wait):
                break
            self._tell(self.status_line())

    def vehicles(self) -> dict[str, bool]:
        """Every vehicle seen: whether its liveliness token is up."""
        with self._lock:
            return dict(self._alive)

    def status_line(self) -> str:
        seen = self.vehicles()
        alive = sorted(v for v, up in seen.items() if up)
        away = sorted(v for v, up in seen.items() if not up)
        text = f"router: {len(alive)} vehicle(s) alive" + (f": {', '.join(alive)}" if alive else "")
        return text + (f"; away: {', '.join(away)}" if away else "")

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        vehicle = parse_alive_key(str(sample.key_expr))
        if vehicle is None:
            return
        up = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            changed = self._alive.get(vehicle) != up
            self._alive[vehicle] = up
        if changed:
            self._tell(f"vehicle {vehicle} {'alive' if up else 'away'}")

    def _tell(self, text: str) -> None:
        with contextlib.suppress(OSError, ValueError):  # a closed console never stops it
            print(text, file=self._console, flush=True)


def serve(settings: RouterSettings, duration_s: float | None = None) -> int:
    """``seamap router``: run until SIGINT / SIGTERM (or ``duration_s``); exit status 0."""
    router = Router(settings)

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        router.stop()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with router:
            router.run(duration_s)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
