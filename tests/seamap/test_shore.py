"""The shore station against a fake boat that speaks the contract over real zenoh sessions
on 127.0.0.1 (peer mode, no multicast scouting, a free TCP port per test)."""

from __future__ import annotations

import csv
import io
import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import rasterio
import zenoh

from daemon.config import ZenohConfig, config_from_dict
from drivers.errors import SeamapError
from drivers.zenoh_io import (
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
from seamap.shore import ShoreSettings, ShoreStation, shore_settings
from tests.ports import free_tcp_port as free_port

VEHICLE = "boat1"
SURVEY = "s1"
EPSG = 32631
RES_M = 0.05
SIZE_PX = 64
TILE_M = RES_M * SIZE_PX
COL0, ROW0 = 156250, 1500000  # easting 500 000 m, northing 4 800 000 m
WAIT_S = 20.0  # generous: conditions are waited for, never assumed after a fixed time

Tile = npt.NDArray[np.uint8]


def loopback_peer(listen: list[str] | None = None, connect: list[str] | None = None) -> ZenohConfig:
    return ZenohConfig(
        mode="peer", listen=listen or [], connect=connect or [], multicast_scouting=False
    )


def tile_values(seed: int) -> Tile:
    """A tile with data (1..255) and holes (0)."""
    rng = np.random.default_rng(seed)
    values = rng.integers(1, 256, (SIZE_PX, SIZE_PX), dtype=np.uint8)
    values[rng.random((SIZE_PX, SIZE_PX)) < 0.2] = 0
    return values


def tile_info(col: int, row: int, version: int) -> TileInfo:
    return TileInfo(EPSG, RES_M, col * TILE_M, (row + 1) * TILE_M, SIZE_PX, version)


def wait_until(condition: Callable[[], bool], what: str, timeout: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def has_subscribers(publisher: zenoh.Publisher) -> bool:
    # zenoh 1.10's stub says bool; it is a MatchingStatus (always truthy) with .matching.
    status: Any = publisher.matching_status
    return bool(status.matching)


class FakeBoat:
    """A boat after the contract, in plain zenoh: a liveliness token, tiles (PNG, attachment,
    image/png), poses, status, and a complete queryable serving its current tiles."""

    def __init__(self, port: int, tiles: dict[tuple[int, int], tuple[Tile, int]] | None = None):
        self.session = open_session(loopback_peer(listen=[f"tcp/127.0.0.1:{port}"]))
        self.tiles: dict[tuple[int, int], tuple[bytes, TileInfo]] = {}
        self.stale: dict[tuple[int, int], tuple[bytes, TileInfo]] | None = None
        """When set, the queryable serves these instead (a late, out-of-date reply)."""
        for (col, row), (values, version) in (tiles or {}).items():
            self.put_tile(col, row, values, version, publish=False)
        self.pose_pub = self.session.declare_publisher(pose_key(VEHICLE))
        self.status_pub = self.session.declare_publisher(status_key(VEHICLE))
        self.tile_pub = self.session.declare_publisher(tile_key(VEHICLE, SURVEY, COL0, ROW0))
        # The queryable goes first, so a shore that sees the token can already query.
        self.queryable = self.session.declare_queryable(
            tiles_selector(VEHICLE), self._serve, complete=True
        )
        self.token = self.session.liveliness().declare_token(alive_key(VEHICLE))

    def _serve(self, query: zenoh.Query) -> None:
        tiles = self.stale if self.stale is not None else self.tiles
        for (col, row), (png, info) in list(tiles.items()):
            key = tile_key(VEHICLE, SURVEY, col, row)
            if query.key_expr.intersects(key):
                query.reply(key, png, encoding=zenoh.Encoding.IMAGE_PNG, attachment=info.to_json())

    def wait_heard(self) -> None:
        """Until the shore's subscriptions have reached this boat."""
        publishers = (self.pose_pub, self.status_pub, self.tile_pub)
        wait_until(lambda: all(map(has_subscribers, publishers)), "the shore's subscribers")

    def put_tile(self, col: int, row: int, values: Tile, version: int, publish: bool = True):
        png, info = encode_tile(values), tile_info(col, row, version)
        self.tiles[(col, row)] = (png, info)
        if publish:
            self.put_raw(tile_key(VEHICLE, SURVEY, col, row), png, info.to_json())

    def put_raw(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        self.session.put(key, payload, encoding=zenoh.Encoding.IMAGE_PNG, attachment=attachment)

    def put_pose(self, pose: dict[str, float]) -> None:
        self.pose_pub.put(json_bytes({**pose, "epsg": EPSG}))

    def put_status(self, status: dict[str, Any]) -> None:
        self.status_pub.put(json_bytes(status))

    def close(self) -> None:
        self.session.close()


POSES = [
    {"time": 1.7e9 + i, "lat": 43.3 + i * 1e-5, "lon": 5.37 + i * 2e-5, "east": 500_001.0 + i,
     "north": 4_800_001.0 + 1.1 * i, "heading_deg": 45.0 + i}
    for i in range(3)
]  # fmt: skip
STATUS = {
    "survey": SURVEY,
    "links": {"sonar": {"up": True}, "mavlink": {"up": False}},
    "frames": {"received": 50, "mapped": 42, "rejected": 1},
    "lag_s": 0.25,
}


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def boats() -> Iterator[list[FakeBoat]]:
    made: list[FakeBoat] = []
    yield made
    for boat in made:
        boat.close()


@pytest.fixture
def shore(tmp_path: Path, port: int) -> Iterator[Callable[[], tuple[ShoreStation, io.StringIO]]]:
    """A shore station following VEHICLE on the port, and what it tells (its stderr)."""
    stations: list[ShoreStation] = []

    def make() -> tuple[ShoreStation, io.StringIO]:
        settings = ShoreSettings(
            out_dir=tmp_path / "shore",
            zenoh=loopback_peer(connect=[f"tcp/127.0.0.1:{port}"]),
            vehicle=VEHICLE,
            write_interval_s=0.2,
        )
        told = io.StringIO()
        station = ShoreStation(settings, console=told)
        stations.append(station)
        station.open()
        return station, told

    yield make
    for station in stations:
        station.close()


def held_values(station: ShoreStation, key: tuple[int, int]) -> Tile | None:
    tile = station.tiles(VEHICLE, SURVEY).get(key)
    return None if tile is None else tile.values


def mosaic_file(out_dir: Path) -> tuple[Tile, Any]:
    with rasterio.open(out_dir / VEHICLE / SURVEY / "mosaic.tif") as dataset:
        assert (dataset.count, dataset.dtypes[0], dataset.nodata) == (1, "uint8", 0)
        assert dataset.crs.to_epsg() == EPSG
        return dataset.read(1), dataset.transform


def test_live_tiles_poses_and_status_end_up_in_the_files(tmp_path, port, boats, shore):
    boats.append(boat := FakeBoat(port))
    station, told = shore()
    assert station.run(WAIT_S, until=lambda s: s.alive(VEHICLE) is True)
    boat.wait_heard()
    sent = {(COL0, ROW0): tile_values(1), (COL0 + 1, ROW0): tile_values(2)}
    sent[(COL0, ROW0 + 1)] = tile_values(3)
    for (col, row), values in sent.items():
        boat.put_tile(col, row, values, version=1)
    for pose in POSES:
        boat.put_pose(pose)
    boat.put_status(STATUS)
    # Bad payloads are counted, told, and change nothing.
    bad_key = tile_key(VEHICLE, SURVEY, COL0 + 3, ROW0)
    boat.put_raw(bad_key, b"not a png", tile_info(COL0 + 3, ROW0, 1).to_json())
    boat.put_raw(bad_key, encode_tile(tile_values(4)), b"{not json")
    small = encode_tile(np.full((SIZE_PX // 2, SIZE_PX // 2), 7, np.uint8))
    boat.put_raw(bad_key, small, tile_info(COL0 + 3, ROW0, 1).to_json())
    boat.pose_pub.put(b'{"lat": "north"}')

    def all_in(s: ShoreStation) -> bool:
        # Ordered per key, not across keys: wait for each.
        held = len(s.tiles(VEHICLE, SURVEY)) == 3 and s.status(VEHICLE) is not None
        return held and s.stats.bad == 4 and s.stats.poses == 3

    assert station.run(WAIT_S, until=all_in)
    assert station.status(VEHICLE) == STATUS
    assert "bad payload on" in told.getvalue()

    # The GeoTIFF holds the tiles' values exactly, north-up, on the tiles' grid.
    image, transform = mosaic_file(tmp_path / "shore")
    assert image.shape == (2 * SIZE_PX, 2 * SIZE_PX)
    assert transform.a == pytest.approx(RES_M) and transform.e == pytest.approx(-RES_M)
    assert transform.b == 0 and transform.d == 0
    assert transform.c == pytest.approx(COL0 * TILE_M)  # west of the top-left tile
    assert transform.f == pytest.approx((ROW0 + 2) * TILE_M)  # its north
    n = SIZE_PX
    np.testing.assert_array_equal(image[:n, :n], sent[(COL0, ROW0 + 1)])
    np.testing.assert_array_equal(image[n:, :n], sent[(COL0, ROW0)])
    np.testing.assert_array_equal(image[n:, n:], sent[(COL0 + 1, ROW0)])
    assert not image[:n, n:].any()  # no tile there: no data
    png = cv2.imread(str(tmp_path / "shore" / VEHICLE / SURVEY / "mosaic.png"), 0)
    np.testing.assert_array_equal(png, image)

    folder = tmp_path / "shore" / VEHICLE
    with open(folder / "track.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert list(rows[0]) == ["time", "lat", "lon", "east", "north", "heading_deg"]
    assert [{k: float(v) for k, v in row.items()} for row in rows] == [
        pytest.approx(pose) for pose in POSES
    ]
    track = json.loads((folder / "track.geojson").read_text())
    assert track["type"] == "FeatureCollection" and len(track["features"]) == 1
    line = track["features"][0]["geometry"]
    assert line["type"] == "LineString"
    expected = [[p["lon"], p["lat"]] for p in POSES]  # RFC 7946: longitude first
    np.testing.assert_allclose(line["coordinates"], expected, rtol=0, atol=1e-9)
    assert json.loads((folder / "status.json").read_bytes()) == STATUS

    status_line = station.status_line()
    for fragment in (VEHICLE, f"survey {SURVEY}", "mapped 42", "lag 0.2 s", "tiles 3"):
        assert fragment in status_line
    assert "sonar up" in status_line and "mavlink down" in status_line
    assert "boat away" not in status_line


def test_a_late_shore_catches_up_and_keeps_the_newest_version(tmp_path, port, boats, shore):
    first, second = tile_values(10), tile_values(11)
    boats.append(boat := FakeBoat(port))
    boat.put_tile(COL0, ROW0, first, version=1)  # nobody listens yet: only a get finds them
    boat.put_tile(COL0 + 1, ROW0, second, version=1)
    station, _ = shore()
    assert station.run(WAIT_S, until=lambda s: len(s.tiles(VEHICLE, SURVEY)) == 2)
    np.testing.assert_array_equal(held_values(station, (COL0, ROW0)), first)
    np.testing.assert_array_equal(held_values(station, (COL0 + 1, ROW0)), second)

    # A republished tile with a higher version replaces the one held.
    boat.wait_heard()
    newer = tile_values(12)
    boat.put_tile(COL0, ROW0, newer, version=2)

    def newer_held(s: ShoreStation) -> bool:
        return s.tiles(VEHICLE, SURVEY)[(COL0, ROW0)].info.version == 2

    assert station.run(WAIT_S, until=newer_held)
    np.testing.assert_array_equal(held_values(station, (COL0, ROW0)), newer)

    # A catch-up reply older than the tile held does not overwrite it.
    assert station.run(WAIT_S, until=lambda s: s.stats.catchups_done == s.stats.catchups_started)
    stale_before, done_before = station.stats.tiles_stale, station.stats.catchups_done
    boat.stale = {(COL0, ROW0): (encode_tile(first), tile_info(COL0, ROW0, 1))}
    station.catch_up()
    assert station.run(WAIT_S, until=lambda s: s.stats.catchups_done > done_before)
    assert station.stats.tiles_stale == stale_before + 1
    assert station.tiles(VEHICLE, SURVEY)[(COL0, ROW0)].info.version == 2
    image, _ = mosaic_file(tmp_path / "shore")
    np.testing.assert_array_equal(image[:, :SIZE_PX], newer)
    np.testing.assert_array_equal(image[:, SIZE_PX:], second)


def test_the_boat_goes_away_and_comes_back(tmp_path, port, boats, shore):
    old, new = tile_values(20), tile_values(21)
    boats.append(boat := FakeBoat(port, tiles={(COL0, ROW0): (old, 1)}))
    station, told = shore()
    assert station.run(WAIT_S, until=lambda s: len(s.tiles(VEHICLE, SURVEY)) == 1)

    boat.close()
    assert station.run(WAIT_S, until=lambda s: s.alive(VEHICLE) is False)
    assert station.stats.departures == 1
    assert "boat away" in station.status_line()
    assert "boat away" in told.getvalue()

    # The daemon restarts on the same port, holding one more tile, published while the
    # shore was not connected: only the catch-up on the token's return brings it.
    tiles = {(COL0, ROW0): (old, 1), (COL0, ROW0 + 1): (new, 1)}
    boats.append(FakeBoat(port, tiles=tiles))

    def caught_up(s: ShoreStation) -> bool:
        return s.alive(VEHICLE) is True and len(s.tiles(VEHICLE, SURVEY)) == 2

    assert station.run(WAIT_S, until=caught_up)
    assert station.stats.arrivals == 2
    assert "boat away" not in station.status_line()
    image, transform = mosaic_file(tmp_path / "shore")
    assert transform.f == pytest.approx((ROW0 + 2) * TILE_M)
    np.testing.assert_array_equal(image[:SIZE_PX], new)
    np.testing.assert_array_equal(image[SIZE_PX:], old)


def said(lines: list[str], fragment: str) -> bool:
    return any(fragment in line for line in lines)


def test_settings_come_from_the_config_with_options_overriding(tmp_path):
    plain = shore_settings(tmp_path)
    assert (plain.zenoh.mode, plain.zenoh.connect, plain.zenoh.listen) == (
        "peer", ["tcp/127.0.0.1:7447"], []
    )  # fmt: skip
    assert not plain.zenoh.multicast_scouting and plain.vehicle == "*"
    site = config_from_dict(
        {"daemon": {"vehicle": "b2"}, "zenoh": {"listen": ["tcp/0.0.0.0:7447"], "connect": []}}
    )
    settings = shore_settings(tmp_path, site, connect=["tcp/10.0.0.2:7447"], survey="s9")
    assert settings.zenoh.connect == ["tcp/10.0.0.2:7447"]
    assert settings.zenoh.listen == ["tcp/0.0.0.0:7447"]
    assert (settings.vehicle, settings.survey) == ("b2", "s9")
    # A connect endpoint without a port is refused where the site file is read.
    with pytest.raises(
        SeamapError, match=r"\[zenoh\] connect = 'tcp/boat' is not a zenoh endpoint"
    ):
        config_from_dict({"zenoh": {"connect": ["tcp/boat"]}})


def seamap_shore(*args: str | Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "seamap", "shore", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_cli_follows_the_boat_for_a_duration(tmp_path, port, boats):
    values = tile_values(30)
    boats.append(boat := FakeBoat(port, tiles={(COL0, ROW0): (values, 1)}))
    out = tmp_path / "out"
    proc = seamap_shore("--out", out, "--connect", f"tcp/127.0.0.1:{port}", "--duration", "3")
    deadline = time.monotonic() + 60
    i = 0
    while proc.poll() is None and time.monotonic() < deadline:  # a boat publishing at 10 Hz
        boat.put_pose({**POSES[0], "time": POSES[0]["time"] + i})
        boat.put_status(STATUS)
        i += 1
        time.sleep(0.1)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    folder = out / VEHICLE
    for name in ("track.csv", "track.geojson", "status.json"):
        assert (folder / name).is_file(), name
    assert len((folder / "track.csv").read_text().splitlines()) >= 2
    image, _ = mosaic_file(out)
    np.testing.assert_array_equal(image, values)
    assert (folder / SURVEY / "mosaic.png").is_file()


@pytest.mark.parametrize("endpoint", ["bogus", "tcp/127.0.0.1", "tcp/127.0.0.1:70000"])
def test_cli_malformed_endpoint_is_one_line_and_status_2(tmp_path, endpoint):
    proc = seamap_shore("--out", tmp_path / "out", "--connect", endpoint, "--duration", "1")
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert endpoint in lines[0] and "--connect" in lines[0]


def test_cli_writes_its_files_on_sigterm_and_exits_0(tmp_path, port, boats):
    boats.append(boat := FakeBoat(port))
    out = tmp_path / "out"
    proc = seamap_shore("--out", out, "--connect", f"tcp/127.0.0.1:{port}")
    lines: list[str] = []
    assert proc.stderr is not None
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr or ()), daemon=True)
    reader.start()
    try:
        boat.wait_heard()
        # Samples of one key arrive in order: once the shore tells of the garbage after the
        # pose and after the status, it holds them.
        boat.put_pose(POSES[0])
        boat.pose_pub.put(b"garbage")
        boat.put_status(STATUS)
        boat.status_pub.put(b"garbage")
        for key in (pose_key(VEHICLE), status_key(VEHICLE)):
            wait_until(partial(said, lines, f"bad payload on {key}:"), f"the line on {key}")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0, "".join(lines)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(timeout=10)
    assert (out / VEHICLE / "track.csv").read_text().count("\n") == 2
    assert json.loads((out / VEHICLE / "status.json").read_text()) == STATUS
