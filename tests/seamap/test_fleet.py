"""A fleet through one router on 127.0.0.1: ``seamap router`` (the real command, a child
process), two boats (the daemon's own zenoh publisher, each a client of the router) and
shore stations (clients too). Each shore sees both boats' tiles, poses and status; the
router restarting loses nothing the boats hold (the shores catch up when the boats'
tokens come back); a shore that comes late catches up with both boats.

A shore has seen the boats' tokens only after the router took its subscriptions (they
went first on its link), so a put after that reaches it unless dropped: the publisher
puts live tiles, poses and status with congestion control DROP, and two boats' tiles
(~70 kB each) fill the router's queue to a shore (two batches of 64 kB). So poses and
status go out while no tile is on the way, and tiles are checked through the shore's
catch-up (a ``get``; its replies are BLOCK)."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from daemon.config import ZenohConfig
from daemon.publisher import ZenohPublisher
from drivers.errors import SeamapError
from drivers.zenoh_io import open_session
from mapping.mosaic import TileGrid
from mapping.streaming import PoseUpdate, TileUpdate
from seamap.router import Router, router_settings
from seamap.shore import ShoreSettings, ShoreStation
from tests.ports import free_tcp_port

SEAMAP = str(Path(sys.executable).parent / "seamap")
BOATS = ("boat1", "boat2")
SURVEY, EPSG = "s1", 32618
GRID = TileGrid(res_m=0.02, tile_px=256)
COL0, ROW0 = 97656, 843750  # easting 500 000 m, northing 4 320 000 m
WAIT_S = 20.0


def _client(endpoint: str) -> ZenohConfig:
    return ZenohConfig(mode="client", listen=[], connect=[endpoint], multicast_scouting=False)


def _values(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(1, 256, (GRID.tile_px, GRID.tile_px), dtype=np.uint8)


def _tile(boat: int, n: int, seed: int) -> TileUpdate:
    """Boat ``boat``'s ``n``-th tile (the boats map neighbouring rows)."""
    key = (COL0 + n, ROW0 - boat)
    west, north = GRID.tile_west_north(key)
    return TileUpdate(key, _values(seed), 0, EPSG, GRID.res_m, GRID.tile_px, west, north)


def _pose(boat: int, t: float) -> PoseUpdate:
    return PoseUpdate(
        int(t), t, 500_000.0 + t, 4_320_000.0 - 6.0 * boat, 90.0, 39.0, -76.0, EPSG, False
    )


class RouterProcess:
    """``seamap router`` on 127.0.0.1:port as a child; ``start`` / ``stop`` again."""

    def __init__(self, port: int, log: Path) -> None:
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.log = log
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        """Start the router; return once this process (not an earlier one) has written
        that it listens."""
        with open(self.log, "ab") as log:
            earlier = log.tell()
            self.proc = subprocess.Popen(
                [SEAMAP, "router", "--listen", self.endpoint], stdout=log, stderr=log
            )
        deadline = time.monotonic() + WAIT_S
        while b"listening on" not in self.log.read_bytes()[earlier:]:
            assert self.proc.poll() is None, self.log.read_text()
            assert time.monotonic() < deadline, "the router did not start"
            time.sleep(0.05)

    def stop(self) -> int:
        assert self.proc is not None
        self.proc.terminate()
        return self.proc.wait(WAIT_S)


@dataclass
class Boat:
    publisher: ZenohPublisher
    loop: asyncio.AbstractEventLoop

    def close(self) -> None:
        session = self.publisher.detach()
        self.publisher.close()
        if session is not None:
            session.close()
        self.loop.close()


@pytest.fixture
def fleet(tmp_path: Path) -> Iterator[tuple[RouterProcess, list[Boat]]]:
    router = RouterProcess(free_tcp_port(), tmp_path / "router.log")
    router.start()
    boats = []
    try:
        for vehicle in BOATS:
            loop = asyncio.new_event_loop()
            publisher = ZenohPublisher(vehicle, tmp_path / vehicle / "surveys", loop)
            publisher.attach(open_session(_client(router.endpoint)))
            boats.append(Boat(publisher, loop))
        yield router, boats
    finally:
        for boat in boats:
            boat.close()
        if router.proc is not None and router.proc.poll() is None:
            router.stop()


def _shore(tmp_path: Path, name: str, router: RouterProcess) -> ShoreStation:
    station = ShoreStation(
        ShoreSettings(out_dir=tmp_path / name, zenoh=_client(router.endpoint), write_interval_s=1)
    )
    station.open()
    return station


def _until(stations: list[ShoreStation], condition: Callable[[ShoreStation], bool], what: str):
    for station in stations:
        assert station.run(WAIT_S, until=condition), f"timed out waiting for {what}"


def _holds(tiles: dict[str, list[TileUpdate]]) -> Callable[[ShoreStation], bool]:
    def held(station: ShoreStation) -> bool:
        for vehicle, updates in tiles.items():
            have = station.tiles(vehicle, SURVEY)
            for update in updates:
                tile = have.get(update.key)
                if tile is None or not np.array_equal(tile.values, update.values):
                    return False
        return True

    return held


def test_two_boats_two_shores_one_router_and_a_restart(
    tmp_path: Path, fleet: tuple[RouterProcess, list[Boat]]
) -> None:
    router, boats = fleet
    shores = [_shore(tmp_path, f"shore{n}", router) for n in (1, 2)]
    try:
        _until(shores, lambda s: all(s.alive(v) is True for v in BOATS), "both boats' tokens")
        for b, (vehicle, boat) in enumerate(zip(BOATS, boats, strict=True)):
            boat.publisher.pose(_pose(b, 100.0))
            boat.publisher.status({"vehicle": vehicle, "frames": {"mapped": 7 + b}})

        def poses_and_status(station: ShoreStation) -> bool:
            return all(
                [p.time for p in station.track(v)] == [100.0]
                and (station.status(v) or {}).get("frames", {}).get("mapped") == 7 + b
                for b, v in enumerate(BOATS)
            )

        _until(shores, poses_and_status, "both boats' poses and status on both shores")
        sent: dict[str, list[TileUpdate]] = {v: [] for v in BOATS}
        for b, (vehicle, boat) in enumerate(zip(BOATS, boats, strict=True)):
            update = _tile(b, 0, seed=10 * b)
            boat.publisher.tile(SURVEY, update)
            sent[vehicle].append(update)
        for shore in shores:  # asked after the hand-over: answered with the tiles
            shore.catch_up()
        _until(shores, _holds(sent), "both boats' tiles on both shores")
        for b, vehicle in enumerate(BOATS):
            assert shores[0].track(vehicle)[-1].north == pytest.approx(4_320_000.0 - 6.0 * b)

        # The router goes away: the boats keep mapping; what they hold reaches the shores
        # once it is back (they catch up when the boats' tokens return).
        assert router.stop() == 0
        _until(shores, lambda s: not any(s.alive(v) for v in BOATS), "the boats away")
        for b, (vehicle, boat) in enumerate(zip(BOATS, boats, strict=True)):
            for n in (1, 2):
                update = _tile(b, n, seed=10 * b + n)
                boat.publisher.tile(SURVEY, update)
                sent[vehicle].append(update)
        time.sleep(1.0)  # the puts go nowhere
        router.start()
        _until(shores, lambda s: all(s.alive(v) is True for v in BOATS), "the boats back")
        _until(shores, _holds(sent), "the tiles mapped while the router was down")
        for b, boat in enumerate(boats):
            boat.publisher.pose(_pose(b, 200.0))
        _until(
            shores,
            lambda s: all(s.track(v)[-1].time == 200.0 for v in BOATS),
            "poses after the restart",
        )

        # A shore that comes late catches up with both boats.
        late = _shore(tmp_path, "late", router)
        try:
            _until([late], _holds(sent), "the late shore's catch-up")
        finally:
            late.close()
    finally:
        for shore in shores:
            shore.close()
    assert "vehicle boat1 alive" in router.log.read_text()


def test_router_refuses_a_plain_endpoint_open_to_the_network() -> None:
    with pytest.raises(SeamapError, match="plain, unauthenticated"):
        router_settings(listen=["tcp/0.0.0.0:7447"])
    with pytest.raises(SeamapError, match="not a zenoh endpoint"):
        router_settings(listen=["tcp/127.0.0.1"])
    settings = router_settings(listen=["tcp/127.0.0.1:7447"])
    assert settings.zenoh.mode == "router" and not settings.zenoh.multicast_scouting


def test_router_in_use_port_is_one_clear_line(tmp_path: Path) -> None:
    port = free_tcp_port()
    with Router(router_settings(listen=[f"tcp/127.0.0.1:{port}"])):
        out = subprocess.run(
            [SEAMAP, "router", "--listen", f"tcp/127.0.0.1:{port}", "--duration", "1"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr
    assert out.stderr.startswith("seamap router: zenoh: cannot open a router session")
