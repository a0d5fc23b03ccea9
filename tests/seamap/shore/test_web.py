"""The live map page's server (``seamap shore --web``): a real station and its page on
127.0.0.1, fed by fake boats over real zenoh sessions; the page's HTTP API and its
server-sent events read as a browser would."""

from __future__ import annotations

import http.client
import json
import socket
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Any

import numpy as np
import pytest

from drivers.errors import SeamapError
from seamap.shore.state import ShoreEvent
from seamap.shore.web import WebView, parse_web_address
from tests.ports import free_tcp_port
from tests.seamap.shore.conftest import (
    STATUS,
    WAIT_S,
    Shore,
    coverage_cells,
    coverage_info,
    coverage_png,
    coverage_summary,
    pose,
    wait_until,
)
from tests.seamap.test_shore import COL0, ROW0, seamap_shore, tile_info, tile_values


class EventReader:
    """Reads a page's event stream on its own thread: each event with its arrival time
    (time.monotonic)."""

    def __init__(self, url: str) -> None:
        where = urllib.parse.urlsplit(url)
        self.conn = http.client.HTTPConnection("127.0.0.1", where.port, timeout=WAIT_S)
        self.conn.request("GET", "/api/events")
        self.response = self.conn.getresponse()
        assert self.response.status == 200
        assert self.response.headers["Content-Type"] == "text/event-stream"
        self.events: list[tuple[float, str, Any]] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        kind, data = "", ""
        try:
            for raw in self.response:
                line = raw.decode().rstrip("\n")
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: "):
                    data = line[6:]
                elif not line and kind:
                    with self._lock:
                        self.events.append((time.monotonic(), kind, json.loads(data)))
                    kind, data = "", ""
        except Exception:  # closed under it (http.client then raises odd errors)
            return

    def first(self, match: Any, what: str) -> tuple[float, str, Any]:
        """The first event for which ``match(kind, data)`` holds, waited for."""
        found: list[tuple[float, str, Any]] = []

        def seen() -> bool:
            with self._lock:
                found[:] = [e for e in self.events if match(e[1], e[2])][:1]
            return bool(found)

        wait_until(seen, what)
        return found[0]

    def close(self) -> None:
        # Shut the socket first: closing the response waits for the reader thread's recv.
        if self.conn.sock is not None:
            self.conn.sock.shutdown(socket.SHUT_RDWR)
        self._thread.join(timeout=WAIT_S)
        self.conn.close()


def test_the_page_api_shows_every_boat_its_tiles_track_and_status(make_shore):
    shore: Shore = make_shore()
    boat1, boat2 = shore.boat("boat1"), shore.boat("boat2")
    boat1.wait_heard()
    boat2.wait_heard()
    sent = {(COL0, ROW0): tile_values(1), (COL0 + 1, ROW0): tile_values(2)}
    pngs = {key: boat1.put_tile(*key, values, version=5) for key, values in sent.items()}
    boat2.put_tile(COL0 + 4, ROW0, tile_values(3), version=1, survey="t1")
    for i in range(3):
        boat1.put_pose(pose(i))
    boat1.put_status(STATUS)

    def complete() -> bool:
        vehicles = shore.state()["vehicles"]
        b1 = vehicles.get("boat1", {})
        return (
            len(b1.get("surveys", {}).get("s1", {}).get("tiles", [])) == 2
            and len(b1.get("track", [])) == 3
            and b1.get("status") is not None
            and "t1" in vehicles.get("boat2", {}).get("surveys", {})
        )

    wait_until(complete, "the page's state to hold what the boats sent")
    state = shore.state()
    assert state["epsg"] == 32631
    b1 = state["vehicles"]["boat1"]
    assert b1["alive"] is True and state["vehicles"]["boat2"]["alive"] is True
    assert b1["status"] == STATUS
    assert b1["track"] == [[p["east"], p["north"], p["time"]] for p in map(pose, range(3))]
    assert b1["pose"]["east"] == pose(2)["east"] and b1["pose"]["heading_deg"] == 90.0
    s1 = b1["surveys"]["s1"]
    assert (s1["epsg"], s1["res_m"], s1["size_px"]) == (32631, 0.05, 64)
    for tile in s1["tiles"]:
        info = tile_info(tile["col"], tile["row"], 5)
        assert tile["version"] == 5
        assert (tile["west"], tile["north"]) == pytest.approx((info.west, info.north))
    # The PNG as the boat published it, byte for byte.
    for (col, row), png in pngs.items():
        assert shore.get(f"/api/tile/boat1/s1/{col}/{row}.png?v=5") == png
    with pytest.raises(urllib.error.HTTPError) as missing:
        shore.get(f"/api/tile/boat1/s1/{COL0 + 9}/{ROW0}.png")
    assert missing.value.code == 404

    # The station's files, served for download.
    tif = shore.out_dir / "boat1" / "s1" / "mosaic.tif"
    wait_until(tif.exists, "the mosaic file")
    wait_until(lambda: shore.get("/files/boat1/s1/mosaic.tif") == tif.read_bytes(), "the tif")
    wait_until(lambda: (shore.out_dir / "boat1" / "track.geojson").exists(), "the track file")
    track = json.loads(shore.get("/files/boat1/track.geojson"))
    assert track["type"] == "FeatureCollection"
    page = shore.get("/").decode()
    assert "/static/app.js" in page and "http" not in page.replace(shore.url, "")
    assert b"toLatLon" in shore.get("/static/utm.js")


def test_a_tile_is_pushed_within_a_second_and_a_boat_going_away_shows_away(make_shore):
    shore: Shore = make_shore()
    boat1, boat2 = shore.boat("boat1"), shore.boat("boat2")
    boat1.wait_heard()
    reader = EventReader(shore.url)
    try:
        _, kind, first = reader.first(lambda k, d: True, "the stream's first event")
        assert kind == "state" and "vehicles" in first
        latencies = []
        for version in range(1, 6):
            sent_at = time.monotonic()
            png = boat1.put_tile(COL0, ROW0, tile_values(version), version)
            at, _, data = reader.first(
                lambda k, d, v=version: k == "tile" and d["version"] == v, f"tile v{version}"
            )
            latencies.append(at - sent_at)
            assert (data["vehicle"], data["survey"], data["col"], data["row"]) == (
                "boat1", "s1", COL0, ROW0,
            )  # fmt: skip
            assert shore.get(f"/api/tile/boat1/s1/{COL0}/{ROW0}.png?v={version}") == png
            time.sleep(0.1)
        print(f"tile published -> event on the page's stream: {[f'{x:.4f}' for x in latencies]} s")
        assert max(latencies) < 1.0

        sent_at = time.monotonic()
        boat1.put_pose(pose(7))
        at, _, data = reader.first(lambda k, d: k == "pose", "a pose event")
        assert data["east"] == pose(7)["east"] and at - sent_at < 1.0
        boat1.put_status(STATUS)
        reader.first(lambda k, d: k == "status" and d["status"] == STATUS, "a status event")

        boat2.wait_heard()
        boat2.close()
        gone = {"vehicle": "boat2", "alive": False}
        reader.first(lambda k, d: k == "alive" and d == gone, "boat2 away")
        state = shore.state()["vehicles"]
        assert state["boat2"]["alive"] is False  # shown away, not removed
        assert state["boat1"]["alive"] is True
    finally:
        reader.close()


def test_a_slow_page_neither_holds_the_intake_nor_grows_without_bound(make_shore):
    shore: Shore = make_shore(client_queue=8, write_timeout_s=1.0)
    boat = shore.boat("boat1")
    boat.wait_heard()
    # A page that reads nothing, with a tiny receive window.
    slow = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    slow.connect(("127.0.0.1", urllib.parse.urlsplit(shore.url).port))
    slow.sendall(b"GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n")
    wait_until(lambda: shore.web.stats.pages == 1, "the slow page's stream")
    reader = EventReader(shore.url)
    try:
        count, pad = 200, "x" * 20_000  # 4 MB of statuses
        started = time.monotonic()
        for i in range(count):
            boat.put_status({**STATUS, "seq": i, "pad": pad})
        wait_until(lambda: shore.station.stats.statuses == count, "the station's intake")
        intake_s = time.monotonic() - started

        def last_seen(kind: str, data: Any) -> bool:
            if kind == "status":
                return data["status"]["seq"] == count - 1
            if kind == "state" and "boat1" in data["vehicles"]:
                return (data["vehicles"]["boat1"]["status"] or {}).get("seq") == count - 1
            return False

        reader.first(last_seen, "the last status on the reading page")
        print(f"{count} statuses of 20 kB taken in {intake_s:.2f} s beside a stalled page")
        assert shore.web.stats.resyncs >= 1  # the stalled page fell behind: queue dropped
        # Once the socket buffers are full, the stalled page's writes wait; past the write
        # timeout it is dropped, and the reading page stays.
        deadline = time.monotonic() + WAIT_S
        while shore.web.stats.dropped_pages == 0 and time.monotonic() < deadline:
            for _ in range(50):
                boat.put_status({**STATUS, "seq": count, "pad": pad})
                count += 1
            time.sleep(0.1)
        assert shore.web.stats.dropped_pages == 1
        wait_until(lambda: shore.station.stats.statuses == count, "the station's intake")
        reader.first(last_seen, "the last status on the reading page")
        assert shore.web.stats.pages == 1
    finally:
        slow.close()
        reader.close()


def test_the_page_api_holds_each_surveys_coverage_and_pushes_newer_ones(make_shore):
    shore: Shore = make_shore()
    boat = shore.boat("boat1")
    boat.coverage.wait_heard()
    summary, png = coverage_summary(2000), coverage_png(coverage_cells())
    boat.coverage.put_summary(summary)
    boat.coverage.put_raster(png, coverage_info(2000))

    def held() -> dict[str, Any]:
        held = shore.state()["vehicles"].get("boat1", {}).get("coverage", {}).get("s1", {})
        return held if held.get("summary") and held.get("raster") else {}

    wait_until(lambda: bool(held()), "the coverage in the page's state")
    info = coverage_info(2000)
    assert held() == {
        "summary": summary,
        "raster": {"version": 2000, "epsg": info.epsg, "cell_m": info.cell_m, "west": info.west,
                   "north": info.north, "cols": info.cols, "rows": info.rows},
    }  # fmt: skip
    # The raster as the boat published it, byte for byte.
    assert shore.get("/api/coverage/boat1/s1.png?v=2000") == png
    with urllib.request.urlopen(shore.url + "api/coverage/boat1/s1.png?v=2000") as response:
        assert response.headers["Content-Type"] == "image/png"
        assert response.headers["X-Coverage-Version"] == "2000"
        assert "immutable" in response.headers["Cache-Control"]
    with pytest.raises(urllib.error.HTTPError) as missing:
        shore.get("/api/coverage/boat1/s9.png")
    assert missing.value.code == 404

    # A newer summary and raster are pushed to an open page as `coverage` events; an older
    # one (a late catch-up reply) is not.
    reader = EventReader(shore.url)
    try:
        _, kind, first = reader.first(lambda k, d: True, "the stream's first event")
        assert kind == "state" and first["vehicles"]["boat1"]["coverage"]["s1"] == held()
        boat.coverage.put_summary(coverage_summary(1000))
        final, final_png = coverage_summary(3000, final=True), coverage_png(coverage_cells()[::-1])
        boat.coverage.put_summary(final)
        _, _, data = reader.first(lambda k, d: k == "coverage", "a coverage event")
        assert data["vehicle"] == "boat1" and data["survey"] == "s1"
        assert data["summary"] == final and data["raster"]["version"] == 2000
        boat.coverage.put_raster(final_png, coverage_info(3000))
        _, _, data = reader.first(
            lambda k, d: k == "coverage" and d["raster"]["version"] == 3000, "the newer raster"
        )
        assert data["summary"]["version"] == 3000
        assert shore.get("/api/coverage/boat1/s1.png?v=3000") == final_png
        with reader._lock:
            versions = [d["summary"]["version"] for _, k, d in reader.events if k == "coverage"]
        assert 1000 not in versions
    finally:
        reader.close()


def test_bad_values_never_reach_the_page_as_bad_json(make_shore):
    shore: Shore = make_shore()
    boat = shore.boat("boat1")
    boat.wait_heard()
    boat.put_status(b'{"survey": "s1", "lag_s": NaN, "disk_free_mb": Infinity}')
    boat.put_pose({**pose(0), "epsg": "not a code"})
    boat.put_tile(COL0, ROW0, np.zeros((64, 64), np.uint8), version=1)  # an empty tile
    wait_until(lambda: shore.station.stats.poses == 1 and shore.station.stats.statuses == 1, "in")
    wait_until(lambda: shore.station.stats.tiles_taken == 1, "the empty tile")

    def strict(text: str) -> Any:
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))

    state = strict(shore.get("/api/state").decode())
    b1 = state["vehicles"]["boat1"]
    assert b1["status"] == {"survey": "s1", "lag_s": None, "disk_free_mb": None}
    assert b1["pose"]["epsg"] is None and b1["track_epsg"] is None
    assert shore.station.stats.listener_errors == 0


def test_the_view_takes_anything_the_station_might_hand_it():
    view = WebView()
    odd = [
        ShoreEvent("tile", "boat1", "s1", 1, 2, None, b""),
        ShoreEvent("tile", "a/b", "s1", 1, 2, tile_info(1, 2, 1), b"png"),
        ShoreEvent("pose", "boat1"),
        ShoreEvent("status", "boat1", status=None),
        ShoreEvent("alive", "boat1"),
        ShoreEvent("nonsense", "boat1"),
        ShoreEvent("pose", "", payload=b"{"),
        ShoreEvent("coverage", "boat1", "s1", summary=None),
        ShoreEvent("coverage", "boat1", "s1", summary={"version": "1"}),
        ShoreEvent("coverage", "boat1", "a/b", summary={"version": 1}),
        ShoreEvent("coverage_raster", "boat1", "s1", coverage_info=None, payload=b"png"),
        ShoreEvent("coverage_raster", "boat1", "s1", coverage_info=coverage_info(1)),
    ]
    assert [view.apply(event) for event in odd] == [None] * len(odd)
    json.dumps(view.snapshot(), allow_nan=False)


@pytest.mark.parametrize(
    ("text", "expected"),
    [("8080", ("127.0.0.1", 8080)), ("0.0.0.0:0", ("0.0.0.0", 0)), ("[::1]:80", ("::1", 80))],
)
def test_web_address_forms(text, expected):
    assert parse_web_address(text) == expected


@pytest.mark.parametrize("value", ["http", "127.0.0.1:99999", ":", "a b:80"])
def test_cli_bad_web_value_is_one_line_and_status_2(tmp_path, value):
    with pytest.raises(SeamapError):
        parse_web_address(value)
    proc = seamap_shore("--out", tmp_path, "--web", value, "--duration", "1")
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "--web" in lines[0] and value in lines[0], stderr


def test_cli_port_in_use_is_one_line_and_status_2(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = seamap_shore("--out", tmp_path, "--web", f"127.0.0.1:{port}", "--duration", "1")
        _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and f"127.0.0.1:{port}" in lines[0] and "in use" in lines[0], stderr


def test_cli_serves_the_page_and_prints_its_address(tmp_path):
    zenoh_port = free_tcp_port()
    proc = seamap_shore(
        "--out", tmp_path, "--web", "0", "--duration", "4",
        "--listen", f"tcp/127.0.0.1:{zenoh_port}", "--connect", f"tcp/127.0.0.1:{free_tcp_port()}",
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().strip()
        assert line.startswith("web: http://127.0.0.1:") and line.endswith("/"), line
        url = line.removeprefix("web: ")
        with urllib.request.urlopen(url + "api/state", timeout=10) as response:
            assert json.loads(response.read()) == {"epsg": None, "vehicles": {}}
        _, stderr = proc.communicate(timeout=60)
        assert proc.returncode == 0, stderr
    finally:
        proc.kill()
        proc.wait()
