"""A UDP relay on 127.0.0.1 that can go silent: the MAVLink link cut between an autopilot and
the daemon, without either of them knowing (a radio out of range, a cable pulled).

The autopilot sends to the relay's port; the relay forwards each datagram to the daemon's
port from its own second socket, and whatever the daemon answers goes back to where the
autopilot last sent from. While ``cut`` the relay drops everything both ways and counts it.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

__all__ = ["UdpRelay"]


@dataclass
class RelayCounts:
    forwarded: int = 0
    returned: int = 0
    dropped: int = 0
    cuts: list[tuple[float, float]] = field(default_factory=list)
    """Each cut: from, to (``time.time()``; to is inf while it lasts)."""


class _Side(asyncio.DatagramProtocol):
    def __init__(self, on_datagram: object) -> None:
        self._on = on_datagram

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self._on(data, addr)  # type: ignore[operator]


class UdpRelay:
    """``async with UdpRelay(target_port) as relay``: send to ``relay.port``; ``relay.cut(s)``
    silences the link for ``s`` seconds (or until ``restore()``)."""

    def __init__(self, target_port: int, host: str = "127.0.0.1") -> None:
        if host not in ("127.0.0.1", "localhost"):
            raise ValueError("UdpRelay: loopback only")
        self.host = host
        self.target_port = target_port
        self.port = 0
        self.counts = RelayCounts()
        self._front: asyncio.DatagramTransport | None = None
        self._back: asyncio.DatagramTransport | None = None
        self._peer: tuple[str, int] | None = None
        self._cut_until = 0.0

    async def __aenter__(self) -> UdpRelay:
        loop = asyncio.get_running_loop()
        front, _ = await loop.create_datagram_endpoint(
            lambda: _Side(self._from_autopilot), local_addr=(self.host, 0)
        )
        back, _ = await loop.create_datagram_endpoint(
            lambda: _Side(self._from_daemon),
            local_addr=(self.host, 0),
            remote_addr=(self.host, self.target_port),
        )
        self._front, self._back = front, back
        self.port = int(front.get_extra_info("sockname")[1])
        return self

    async def __aexit__(self, *exc: object) -> None:
        for transport in (self._front, self._back):
            if transport is not None:
                transport.close()

    @property
    def is_cut(self) -> bool:
        return time.monotonic() < self._cut_until

    def cut(self, seconds: float) -> None:
        """Drop everything both ways for ``seconds`` from now."""
        self._cut_until = time.monotonic() + seconds
        now = time.time()
        self.counts.cuts.append((now, now + seconds))

    def restore(self) -> None:
        if self.is_cut and self.counts.cuts:
            start, _ = self.counts.cuts[-1]
            self.counts.cuts[-1] = (start, time.time())
        self._cut_until = 0.0

    def _from_autopilot(self, data: bytes, addr: tuple[str, int]) -> None:
        self._peer = addr
        if self.is_cut:
            self.counts.dropped += 1
        elif self._back is not None:
            self.counts.forwarded += 1
            try:
                self._back.sendto(data)
            except OSError:  # nobody listening yet: as a radio link would, lose it
                self.counts.dropped += 1

    def _from_daemon(self, data: bytes, addr: tuple[str, int]) -> None:
        if self.is_cut or self._peer is None or self._front is None:
            self.counts.dropped += 1
            return
        self.counts.returned += 1
        self._front.sendto(data, self._peer)
