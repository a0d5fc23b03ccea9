"""A shore station with its live map page, fed by fake boats that speak the contract over
real zenoh sessions on 127.0.0.1 (peer mode, no multicast scouting, free ports)."""

from __future__ import annotations

import io
import json
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from seamap.shore.station import ShoreSettings, ShoreStation
from seamap.shore.web import WebServer
from seamap.zenoh_io import (
    TileInfo,
    alive_key,
    encode_tile,
    json_bytes,
    open_session,
    pose_key,
    status_key,
    tile_key,
    tiles_selector,
)
from tests.ports import free_tcp_port
from tests.test_shore import (  # the same grid and tiles as the station's own tests
    EPSG,
    Tile,
    loopback_peer,
    tile_info,
)

WAIT_S = 20.0


def wait_until(condition: Callable[[], bool], what: str, timeout: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def pose(i: int, east: float = 500_010.0, north: float = 4_800_010.0, heading: float = 90.0):
    """The i-th pose of a boat going east 1 m per pose from (east, north)."""
    return {"time": 1.7e9 + i, "lat": 43.35, "lon": 3.0, "east": east + i, "north": north,
            "heading_deg": heading, "epsg": EPSG}  # fmt: skip


STATUS = {
    "survey": "s1",
    "links": {"sonar": {"up": True}, "mavlink": {"up": False}},
    "frames": {"received": 50, "mapped": 42, "rejected": 1, "skipped": 3},
    "lag_s": 0.25,
    "disk_free_mb": 2048.0,
    "mission": {"current": 3, "total": 12, "state": "active"},
}


class Boat:
    """A boat after the contract, in plain zenoh, connecting to the shore's port: a
    liveliness token, tiles, poses, status and a queryable serving its current tiles."""

    def __init__(self, vehicle: str, shore_port: int) -> None:
        self.vehicle = vehicle
        self.session = open_session(loopback_peer(connect=[f"tcp/127.0.0.1:{shore_port}"]))
        self.tiles: dict[tuple[str, int, int], tuple[bytes, TileInfo]] = {}
        self.pose_pub = self.session.declare_publisher(pose_key(vehicle))
        self.queryable = self.session.declare_queryable(
            tiles_selector(vehicle), self._serve, complete=True
        )
        self.token = self.session.liveliness().declare_token(alive_key(vehicle))

    def _serve(self, query: zenoh.Query) -> None:
        for (survey, col, row), (png, info) in list(self.tiles.items()):
            key = tile_key(self.vehicle, survey, col, row)
            if query.key_expr.intersects(key):
                query.reply(key, png, encoding=zenoh.Encoding.IMAGE_PNG, attachment=info.to_json())

    def wait_heard(self) -> None:
        """Until the shore's pose subscription has reached this boat."""
        wait_until(lambda: bool(self.pose_pub.matching_status.matching), "the shore")  # type: ignore[attr-defined]

    def put_tile(self, col: int, row: int, values: Tile, version: int, survey: str = "s1") -> bytes:
        png, info = encode_tile(values), tile_info(col, row, version)
        self.tiles[(survey, col, row)] = (png, info)
        self.session.put(
            tile_key(self.vehicle, survey, col, row),
            png,
            encoding=zenoh.Encoding.IMAGE_PNG,
            attachment=info.to_json(),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        return png

    def put_pose(self, value: dict[str, Any]) -> None:
        self.pose_pub.put(json_bytes(value))

    def put_status(self, value: dict[str, Any] | bytes) -> None:
        payload = value if isinstance(value, bytes) else json_bytes(value)
        self.session.put(
            status_key(self.vehicle), payload, congestion_control=zenoh.CongestionControl.BLOCK
        )

    def close(self) -> None:
        self.session.close()


@dataclass
class Shore:
    """A station running on its own thread, its page's server and the boats it follows."""

    station: ShoreStation
    web: WebServer
    thread: threading.Thread
    port: int
    boats: list[Boat]
    out_dir: Path

    @property
    def url(self) -> str:
        return self.web.url

    def boat(self, vehicle: str) -> Boat:
        """A new boat, connected to the station."""
        boat = Boat(vehicle, self.port)
        self.boats.append(boat)
        return boat

    def get(self, path: str) -> bytes:
        with urllib.request.urlopen(self.url + path.lstrip("/"), timeout=10) as response:
            return bytes(response.read())

    def state(self) -> dict[str, Any]:
        return json.loads(self.get("/api/state"))


@pytest.fixture
def make_shore(tmp_path: Path) -> Iterator[Callable[..., Shore]]:
    """Start a station following every vehicle (listening for boats on a free port) with
    its page on 127.0.0.1, a free port; ``web_options`` go to ``WebServer``."""
    made: list[Shore] = []

    def make(**web_options: Any) -> Shore:
        port = free_tcp_port()
        out_dir = tmp_path / "shore"
        settings = ShoreSettings(
            out_dir=out_dir,
            zenoh=loopback_peer(listen=[f"tcp/127.0.0.1:{port}"]),
            write_interval_s=0.2,
        )
        web = WebServer("127.0.0.1", 0, out_dir, **web_options)
        web.start()
        station = ShoreStation(settings, console=io.StringIO(), on_event=web.on_event)
        station.open()
        thread = threading.Thread(target=station.run, name="shore-run", daemon=True)
        thread.start()
        shore = Shore(station, web, thread, port, [], out_dir)
        made.append(shore)
        return shore

    yield make
    for shore in made:
        shore.station.stop()
        shore.thread.join(timeout=10)
        shore.station.close()
        shore.web.close()
        for boat in shore.boats:
            boat.close()
