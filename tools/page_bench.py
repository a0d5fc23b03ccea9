"""``python -m tools.page_bench`` (``make page-bench``): the shore's live map page at farm
scale, in headless Chromium.

A synthetic survey of ``--site-m`` metres a side (default 100: a hectare) at the live
tile grid (256 px tiles at 2 cm: 5.12 m, 400 tiles) is published by a fake boat over
zenoh on 127.0.0.1 (the contract's keys, PNG grey + alpha, attachment JSON) to a real
``ShoreStation`` with its ``WebServer``: the station's real input path. The tiles are
sonar-like texture (speckle over a smooth bed) with the alpha a survey leaves: lanes with
no-data strips between them, the nadir gap, holes.

Then Chromium (Debian's ``/usr/bin/chromium`` through Playwright) opens the page in a
tablet-sized window; the page fits the whole site by itself. Measured, each run in a
fresh browser:

- ``load_s``: from asking for the page to every tile it wants in view drawn at its
  newest version (the page's own bookkeeping: ``seamap.viewStatus()`` where it has one,
  else every tile's ``drawnVersion``);
- ``requests`` and ``bytes``: the tile images fetched (Resource Timing);
- ``js_heap_mb``: ``JSHeapUsedSize`` (CDP ``Performance.getMetrics``) after a garbage
  collection (``HeapProfiler.collectGarbage``);
- ``renderer_rss_mb`` / ``renderer_peak_mb``: the page's renderer process, VmRSS and
  VmHWM from ``/proc/PID/status`` (the pid from CDP ``SystemInfo.getProcessInfo``), which
  holds the decoded images; ``gpu_rss_mb`` the GPU process's (software raster here);
  ``browser_total_mb`` every Chromium process's RSS summed.

Run it from another tree (``PYTHONPATH=OLD_TREE python -m tools.page_bench``, the file
copied there) to measure an older page the same way.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import socket
import statistics
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import zenoh

from drivers.zenoh_io import (
    TileInfo,
    ZenohConfig,
    alive_key,
    encode_tile,
    open_session,
    tile_key,
)
from seamap.shore.station import ShoreSettings, ShoreStation
from seamap.shore.web import WebServer

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
VEHICLE, SURVEY = "bench", "hectare"
EPSG = 32631
WEST, SOUTH = 500_000.0, 4_800_000.0
"""The site's south-west corner (UTM 31N metres)."""
LOAD_TIMEOUT_S = 180.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def site_tiles(
    site_m: float, res_m: float, size_px: int, seed: int
) -> dict[tuple[int, int], npt.NDArray[np.uint8]]:
    """The site's tiles (values 1..255, 0 = no data) by (col, row) on the contract's grid:
    sonar-like texture; lanes 8 m wide, 10 m apart (2 m strips never seen), the nadir gap
    (30 cm) down each lane's middle, and holes."""
    rng = np.random.default_rng(seed)
    tile_m = res_m * size_px
    cols = range(int(WEST // tile_m), int((WEST + site_m) // tile_m) + 1)
    rows = range(int(SOUTH // tile_m), int((SOUTH + site_m) // tile_m) + 1)
    tiles = {}
    pixel = (np.arange(size_px) + 0.5) * res_m
    for col in cols:
        for row in rows:
            east = col * tile_m + pixel[None, :]  # columns west to east
            north = (row + 1) * tile_m - pixel[:, None]  # rows north to south
            shape = (size_px, size_px)
            bed = cv2.resize(rng.random((8, 8), np.float32), shape, interpolation=cv2.INTER_CUBIC)
            bed = 90 + 120 * (bed - 0.5)
            speckle = rng.gamma(4.0, 0.25, (size_px, size_px))
            values = np.clip(bed * speckle, 1, 255).astype(np.uint8)
            x = np.broadcast_to(east - WEST, (size_px, size_px))
            y = np.broadcast_to(north - SOUTH, (size_px, size_px))
            in_lane = (x % 10.0) < 8.0
            nadir = np.abs((x % 10.0) - 4.0) < 0.15
            holes = cv2.resize(rng.random((24, 24), np.float32), shape)
            seen = in_lane & ~nadir & (holes > 0.1) & (x >= 0) & (x < site_m)
            seen &= (y >= 0) & (y < site_m)
            values[~seen] = 0
            if values.any():
                tiles[(col, row)] = values
    return tiles


class Boat:
    """The fake boat: a zenoh peer connecting to the station, publishing tiles."""

    def __init__(self, port: int) -> None:
        cfg = ZenohConfig(mode="peer", listen=[], connect=[f"tcp/127.0.0.1:{port}"])
        self.session = open_session(cfg)
        self.token = self.session.liveliness().declare_token(alive_key(VEHICLE))

    def put(self, col: int, row: int, png: bytes, info: TileInfo) -> None:
        self.session.put(
            tile_key(VEHICLE, SURVEY, col, row), png, encoding=zenoh.Encoding.IMAGE_PNG,
            attachment=info.to_json(), congestion_control=zenoh.CongestionControl.BLOCK,
        )  # fmt: skip

    def close(self) -> None:
        self.session.close()


@contextlib.contextmanager
def shore(tiles: dict[tuple[int, int], bytes], res_m: float, size_px: int) -> Iterator[str]:
    """A station and its page, every tile published to it; yields the page's URL."""
    out = Path(tempfile.mkdtemp(prefix="seamap-page-bench-"))
    port = free_port()
    zcfg = ZenohConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], connect=[])
    settings = ShoreSettings(out_dir=out, zenoh=zcfg, write_interval_s=3600.0)
    web = WebServer("127.0.0.1", 0, out)
    url = web.start()
    station = ShoreStation(settings, console=io.StringIO(), on_event=web.on_event)
    station.open()
    thread = threading.Thread(target=station.run, name="shore-run", daemon=True)
    thread.start()
    boat = Boat(port)
    try:
        held = lambda: len(web.view.vehicles[VEHICLE].tiles.get(SURVEY, {}))  # noqa: E731
        # The station's subscriber reaches the boat within seconds; tiles put before it
        # did are put again.
        deadline = time.monotonic() + 60
        tile_m = res_m * size_px
        while True:
            for (col, row), png in tiles.items():
                info = TileInfo(EPSG, res_m, col * tile_m, (row + 1) * tile_m, size_px, 1)
                boat.put(col, row, png, info)
            settle = time.monotonic() + 5
            while time.monotonic() < settle:
                if VEHICLE in web.view.vehicles and held() == len(tiles):
                    break
                time.sleep(0.1)
            if VEHICLE in web.view.vehicles and held() == len(tiles):
                break
            if time.monotonic() > deadline:
                raise RuntimeError("the station did not take every tile")
        yield url
    finally:
        boat.close()
        station.stop()
        thread.join(timeout=10)
        station.close()
        web.close()
        shutil.rmtree(out, ignore_errors=True)


DONE_JS = """([vehicle, survey, count]) => {
  const s = window.seamap && seamap.model.vehicles.get(vehicle)?.surveys.get(survey);
  if (!s || s.tiles.size < count) return false;
  if (seamap.viewStatus) {
    const v = seamap.viewStatus();
    return v.wanted > 0 && v.drawn === v.wanted;
  }
  return [...s.tiles.values()].every((t) => t.drawnVersion >= t.version);
}"""

IN_VIEW_JS = """([w, s, e, n]) => {
  const v = seamap.view, a = v.utmToScreen(w, n), b = v.utmToScreen(e, s);
  return a.x >= 0 && a.y >= 0 && b.x <= v.width && b.y <= v.height;
}"""


def rss_mb(pid: int) -> tuple[float, float]:
    """VmRSS and VmHWM of a process, MB (0 when it is gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0, 0.0
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    kb = lambda name: float(fields.get(name, "0 kB").split()[0])  # noqa: E731
    return kb("VmRSS") / 1024, kb("VmHWM") / 1024


def one_run(url: str, count: int, site: tuple[float, ...], width: int, height: int,
            dpr: float) -> dict[str, Any]:  # fmt: skip
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            context = browser.new_context(
                viewport={"width": width, "height": height}, device_scale_factor=dpr
            )
            page = context.new_page()
            # Room for every tile's entry (the default buffer keeps 250).
            page.add_init_script("performance.setResourceTimingBufferSize(100000)")
            cdp = context.new_cdp_session(page)
            cdp.send("Performance.enable")
            started = time.monotonic()
            page.goto(url)
            page.wait_for_function(
                DONE_JS, arg=[VEHICLE, SURVEY, count], polling="raf",
                timeout=LOAD_TIMEOUT_S * 1e3,
            )  # fmt: skip
            load_s = time.monotonic() - started
            whole = bool(page.evaluate(IN_VIEW_JS, list(site)))
            page.wait_for_timeout(1000)  # images decoded after the last draw settle
            cdp.send("HeapProfiler.enable")
            cdp.send("HeapProfiler.collectGarbage")
            metrics = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
            resources = page.evaluate(
                "() => performance.getEntriesByType('resource')"
                ".filter((e) => e.name.includes('/api/tile/'))"
                ".map((e) => [e.name, e.encodedBodySize])"
            )
            status = page.evaluate("() => seamap.viewStatus ? seamap.viewStatus() : null")
            info = browser.new_browser_cdp_session().send("SystemInfo.getProcessInfo")
            processes = [(proc["type"], int(proc["id"])) for proc in info["processInfo"]]
            renderers = [rss_mb(pid) for kind, pid in processes if kind == "renderer"]
            gpu = [rss_mb(pid)[0] for kind, pid in processes if kind == "gpu"]
            return {
                "load_s": round(load_s, 3),
                "whole_site_in_view": whole,
                "level": status["level"] if status else 0,
                "requests": len(resources),
                "bytes_mb": round(sum(size for _, size in resources) / 2**20, 1),
                "js_heap_mb": round(metrics.get("JSHeapUsedSize", 0) / 2**20, 1),
                "renderer_rss_mb": round(max((r for r, _ in renderers), default=0), 1),
                "renderer_peak_mb": round(max((h for _, h in renderers), default=0), 1),
                "gpu_rss_mb": round(sum(gpu), 1),
                "browser_total_mb": round(sum(rss_mb(pid)[0] for _, pid in processes), 1),
            }
        finally:
            browser.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tools.page_bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site-m", type=float, default=100.0, help="site side, metres")
    parser.add_argument("--res-m", type=float, default=0.02, help="tile pixel, metres")
    parser.add_argument("--size-px", type=int, default=256, help="tile side, pixels")
    parser.add_argument("--width", type=int, default=1280, help="window, CSS pixels")
    parser.add_argument("--height", type=int, default=800)
    parser.add_argument("--dpr", type=float, default=1.0, help="device pixel ratio")
    parser.add_argument("--runs", type=int, default=3, help="fresh browsers, one load each")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--settle-s", type=float, default=10.0,
                        help="wait after the tiles are in, before the first page")  # fmt: skip
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = parser.parse_args(argv)

    made = time.monotonic()
    values = site_tiles(args.site_m, args.res_m, args.size_px, args.seed)
    pngs = {key: encode_tile(v) for key, v in values.items()}
    made_s = time.monotonic() - made
    site = (WEST, SOUTH, WEST + args.site_m, SOUTH + args.site_m)
    runs = []
    fed = time.monotonic()
    with shore(pngs, args.res_m, args.size_px) as url:
        fed_s = time.monotonic() - fed
        time.sleep(args.settle_s)  # the station's own work after the tiles (its warm-up)
        for _ in range(args.runs):
            runs.append(one_run(url, len(pngs), site, args.width, args.height, args.dpr))
            if not args.json:
                print(json.dumps(runs[-1]), flush=True)
    result = {
        "site_m": args.site_m,
        "tiles": len(pngs),
        "tile_png_mb": round(sum(map(len, pngs.values())) / 2**20, 1),
        "window": f"{args.width}x{args.height}@{args.dpr}",
        "tiles_made_s": round(made_s, 1),
        "tiles_fed_s": round(fed_s, 1),
        "median": {
            key: statistics.median(r[key] for r in runs)
            for key in runs[0]
            if isinstance(runs[0][key], int | float) and not isinstance(runs[0][key], bool)
        },
        "runs": runs,
    }
    print(json.dumps(result, indent=None if args.json else 2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
