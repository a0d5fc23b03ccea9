"""A shore station with its live map page, fed by fake boats that speak the contract over
real zenoh sessions on 127.0.0.1 (peer mode, no multicast scouting, free ports), and a
survey's coverage as a boat publishes it."""

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

import numpy as np
import numpy.typing as npt
import pytest
import zenoh
from PIL import Image
from pyproj import Transformer

from drivers.formats.results import COVERAGE_COLOURS
from drivers.zenoh_io import (
    CoverageInfo,
    TileInfo,
    alive_key,
    coverage_key,
    coverage_raster_key,
    coverage_selector,
    encode_tile,
    json_bytes,
    open_session,
    pose_key,
    status_key,
    tile_key,
    tiles_selector,
)
from seamap.shore.station import ShoreSettings, ShoreStation
from seamap.shore.web import WebServer
from tests.ports import free_tcp_port
from tests.seamap.test_shore import (  # the same grid and tiles as the station's own tests
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


# --- a survey's coverage, as the boat publishes it ---------------------------------------

CELL_M = 0.25
COVERAGE_WEST, COVERAGE_NORTH = 500_000.0, 4_800_010.0
"""The raster's top-left corner (UTM 31N metres): north of the test tiles, not on them."""
COVERAGE_COLS, COVERAGE_ROWS = 40, 24  # 10 m x 6 m
RGB = {name: tuple(reversed(bgr)) for name, bgr in COVERAGE_COLOURS.items()}
"""The raster's colours (``drivers.formats.results`` keeps them as BGR for OpenCV)."""


def coverage_cells(order: tuple[str, str, str] = ("below_bar", "at_bar", "above_bar")):
    """RGBA, north-up: the 4 northern rows never seen (transparent), then columns 0-9,
    10-19 and 20-29 in the colours of ``order``, columns 30-39 never seen."""
    rgba = np.zeros((COVERAGE_ROWS, COVERAGE_COLS, 4), np.uint8)
    for k, name in enumerate(order):
        rgba[4:, 10 * k : 10 * (k + 1)] = (*RGB[name], 255)
    return rgba


def cell_centre(row: int, col: int) -> tuple[float, float]:
    """The UTM (east, north) of a raster cell's centre."""
    return COVERAGE_WEST + (col + 0.5) * CELL_M, COVERAGE_NORTH - (row + 0.5) * CELL_M


def coverage_png(rgba: npt.NDArray[np.uint8]) -> bytes:
    out = io.BytesIO()
    Image.fromarray(rgba, mode="RGBA").save(out, format="PNG")
    return out.getvalue()


def coverage_info(version: int, cols: int = COVERAGE_COLS) -> CoverageInfo:
    return CoverageInfo(EPSG, CELL_M, COVERAGE_WEST, COVERAGE_NORTH, cols, COVERAGE_ROWS, version)


GAP_OUTER = [(500_007.5, 4_800_004.5), (500_009.5, 4_800_004.5), (500_009.5, 4_800_008.5),
             (500_007.5, 4_800_008.5)]  # fmt: skip
"""The first gap (UTM metres, counterclockwise), in the raster's unseen columns..."""
GAP_HOLE = [(500_008.25, 4_800_006.25), (500_008.25, 4_800_006.75), (500_008.75, 4_800_006.75),
            (500_008.75, 4_800_006.25)]  # fmt: skip
"""...with a hole (clockwise)."""
GAP_TWO = [(500_012.0, 4_800_004.0), (500_014.0, 4_800_004.0), (500_013.0, 4_800_006.0)]


def lonlat_ring(ring: list[tuple[float, float]]) -> list[list[float]]:
    """A closed GeoJSON ring ([lon, lat], 1e-9 degrees) of UTM 31N points."""
    to_wgs84 = Transformer.from_crs(EPSG, 4326, always_xy=True)
    return [[round(c, 9) for c in to_wgs84.transform(e, n)] for e, n in [*ring, ring[0]]]


def coverage_summary(version: int, *, area: bool = True, final: bool = False) -> dict[str, Any]:
    """A summary as the boat publishes it: 63.4 % of 1,200 m² covered, 2 gaps (420 m²)
    when ``area``; else only what was seen (812 m²)."""
    features = [
        {"type": "Feature", "id": k, "properties": {"id": k, "area_m2": m2},
         "geometry": {"type": "Polygon", "coordinates": rings}}
        for k, m2, rings in (
            (1, 400.0, [lonlat_ring(GAP_OUTER), lonlat_ring(GAP_HOLE)]),
            (2, 20.1, [lonlat_ring(GAP_TWO)]),
        )
    ]  # fmt: skip
    return {
        "survey": "s1", "time": version / 1000, "final": final, "version": version,
        "epsg": EPSG, "cell_m": CELL_M, "min_passes": 1, "seen_m2": 812.5, "covered_m2": 812.5,
        "area": {"area_m2": 1200.0, "covered_m2": 760.25, "fraction": 0.63354, "gaps": 2,
                 "gaps_m2": 420.1, "min_gap_m2": 1.0} if area else None,
        "gaps": {"type": "FeatureCollection", "features": features if area else []},
    }  # fmt: skip


class CoverageSource:
    """A boat's coverage of one survey on its zenoh session: the summary and raster
    publishers, and a complete queryable answering ``coverage_selector`` with the latest
    of each (declare it before the boat's liveliness token, as the boat would)."""

    def __init__(self, session: zenoh.Session, vehicle: str, survey: str = "s1") -> None:
        self.summary_key = coverage_key(vehicle, survey)
        self.raster_key = coverage_raster_key(vehicle, survey)
        # Every put is to arrive (the tests count them): blocking, not dropped when the
        # link is congested (a loaded machine dropped the two stale versions of
        # test_station_coverage, which then waited for them in vain).
        block = zenoh.CongestionControl.BLOCK
        self.summary_pub = session.declare_publisher(self.summary_key, congestion_control=block)
        self.raster_pub = session.declare_publisher(self.raster_key, congestion_control=block)
        self.latest: dict[str, tuple[bytes, bytes | None]] = {}
        self.queryable = session.declare_queryable(
            coverage_selector(vehicle), self._serve, complete=True
        )

    def _serve(self, query: zenoh.Query) -> None:
        for key, (payload, attachment) in list(self.latest.items()):
            if query.key_expr.intersects(key):
                query.reply(key, payload, attachment=attachment)

    def wait_heard(self) -> None:
        """Until the shore's coverage subscription has reached this boat."""
        wait_until(
            lambda: all(bool(p.matching_status.matching)  # type: ignore[attr-defined]
                        for p in (self.summary_pub, self.raster_pub)),
            "the shore's coverage subscriber",
        )  # fmt: skip

    def put_summary(self, summary: dict[str, Any] | bytes) -> None:
        payload = summary if isinstance(summary, bytes) else json_bytes(summary)
        self.latest[self.summary_key] = (payload, None)
        self.summary_pub.put(payload, encoding=zenoh.Encoding.APPLICATION_JSON)

    def put_raster(self, png: bytes, attachment: CoverageInfo | bytes | None) -> None:
        raw = attachment.to_json() if isinstance(attachment, CoverageInfo) else attachment
        self.latest[self.raster_key] = (png, raw)
        self.raster_pub.put(png, encoding=zenoh.Encoding.IMAGE_PNG, attachment=raw)


class Boat:
    """A boat after the contract, in plain zenoh, connecting to the shore's port: a
    liveliness token, tiles, poses, status, a queryable serving its current tiles, and
    the coverage of survey s1 (``coverage``)."""

    def __init__(self, vehicle: str, shore_port: int) -> None:
        self.vehicle = vehicle
        self.session = open_session(loopback_peer(connect=[f"tcp/127.0.0.1:{shore_port}"]))
        self.tiles: dict[tuple[str, int, int], tuple[bytes, TileInfo]] = {}
        self.pose_pub = self.session.declare_publisher(pose_key(vehicle))
        self.queryable = self.session.declare_queryable(
            tiles_selector(vehicle), self._serve, complete=True
        )
        self.coverage = CoverageSource(self.session, vehicle)
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
