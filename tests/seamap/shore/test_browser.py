"""The live map page in a real headless Chromium (Debian's, driven by Playwright): a
station and its page on 127.0.0.1, fed by fake boats over real zenoh sessions."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from pyproj import Proj, Transformer

from tests.seamap.shore import chromium
from tests.seamap.shore.conftest import (
    GAP_HOLE,
    GAP_OUTER,
    GAP_TWO,
    RGB,
    STATUS,
    Shore,
    cell_centre,
    coverage_cells,
    coverage_info,
    coverage_png,
    coverage_summary,
    pose,
    wait_until,
)
from tests.seamap.test_shore import COL0, EPSG, RES_M, ROW0, TILE_M, tile_values

SCREENSHOT_ENV = "SEAMAP_SHORE_SCREENSHOT"
"""When set, the page's screenshot (boats, mosaics, panel) is saved to this path."""
BOAT1_FILL = (0xFF, 0x8C, 0x1A)  # the page's first boat colour
BACKGROUND = (0x0C, 0x1D, 0x2B)  # the map's, where nothing is drawn
COVERAGE_OPACITY = 0.55  # the page's, for the coverage raster

chromium.require()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium.browser() as context:
        yield context


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    yield page
    page.close()
    assert not errors, errors


def open_page(page: Any, shore: Shore) -> None:
    page.goto(shore.url)
    page.wait_for_function("() => window.seamap !== undefined")


def show(page: Any, east: float, north: float, px_per_m: float) -> None:
    page.evaluate(
        "([e, n, s]) => { seamap.view.touched = true; seamap.view.setView(e, n, s); }",
        [east, north, px_per_m],
    )


def screen_of(page: Any, east: float, north: float) -> tuple[float, float]:
    p = page.evaluate("([e, n]) => seamap.view.utmToScreen(e, n)", [east, north])
    return p["x"], p["y"]


def pixel(page: Any, x: float, y: float) -> list[int]:
    """The canvas's RGBA at CSS pixel (x, y)."""
    return page.evaluate(
        """([x, y]) => {
            const c = document.getElementById("canvas");
            const d = window.devicePixelRatio || 1;
            return [...c.getContext("2d").getImageData(Math.floor(x * d), Math.floor(y * d),
                                                         1, 1).data];
        }""",
        [x, y],
    )


def test_the_page_shows_the_boats_and_their_status(make_shore, page):
    shore: Shore = make_shore()
    boat1, boat2 = shore.boat("boat1"), shore.boat("boat2")
    boat1.wait_heard()
    boat2.wait_heard()
    boat1.put_status(STATUS)
    boat1.put_pose(pose(0))
    boat1.put_tile(COL0, ROW0, tile_values(1), version=1)
    boat2.put_tile(COL0 + 3, ROW0 + 1, tile_values(2), version=1, survey="t1")
    boat2.put_pose(pose(0, east=500_012.0, north=4_800_004.0, heading=200.0))
    open_page(page, shore)
    for vehicle in ("boat1", "boat2"):
        page.locator(f'section[data-vehicle="{vehicle}"]').wait_for()
    boat1_panel = page.locator('section[data-vehicle="boat1"]')
    wait_until(lambda: "42 mapped / 1 rejected / 3 skipped" in boat1_panel.inner_text(), "status")
    text = boat1_panel.inner_text()
    for fragment in ("live", "sonar up, mavlink down", "0.3 s", "2.0 GB", "3 / 12 (active)"):
        assert fragment in text, text
    assert page.locator('section[data-vehicle="boat2"] li[data-survey="t1"]').count() == 1
    href = boat1_panel.locator('li[data-survey="s1"] a').get_attribute("href")
    assert href == "/files/boat1/s1/mosaic.tif"
    # Nothing but the station was asked for anything.
    assert all(r.startswith(shore.url) for r in page.evaluate(
        "() => performance.getEntriesByType('resource').map(e => e.name)"))  # fmt: skip
    path = os.environ.get(SCREENSHOT_ENV)
    if path:
        page.evaluate("() => { seamap.view.touched = false; }")
        page.locator("#fit").click()
        page.wait_for_timeout(300)
        page.screenshot(path=path)


def test_a_tile_is_drawn_within_a_second_with_its_values_where_the_grid_puts_them(make_shore, page):
    shore: Shore = make_shore()
    boat = shore.boat("boat1")
    boat.wait_heard()
    boat.put_tile(COL0, ROW0, tile_values(1), version=1)
    open_page(page, shore)
    # 4 screen pixels per mosaic pixel, the tile and its east neighbour in view.
    west, north = COL0 * TILE_M, (ROW0 + 1) * TILE_M
    show(page, west + TILE_M, north - TILE_M / 2, 4 / RES_M)
    page.wait_for_function(f"() => seamap.drawnVersion('boat1', 's1', {COL0}, {ROW0}) >= 1")

    latencies = []
    for version, (col, seed) in enumerate([(COL0, 2), (COL0 + 1, 3), (COL0, 4)], start=2):
        values = tile_values(seed)
        started = time.monotonic()
        boat.put_tile(col, ROW0, values, version)
        page.wait_for_function(
            f"() => seamap.drawnVersion('boat1', 's1', {col}, {ROW0}) >= {version}",
            polling="raf",
            timeout=10_000,
        )
        latencies.append(time.monotonic() - started)
        check_pixels(page, col, values)
    print(f"tile published -> drawn on the page: {[f'{x:.3f}' for x in latencies]} s")
    assert max(latencies) < 1.0


def check_pixels(page: Any, col: int, values: np.ndarray) -> None:
    """At a few pixels with data, the canvas shows the tile's value, and the pointer's
    readout gives the pixel's centre (UTM within a pixel, and its WGS84)."""
    to_wgs84 = Transformer.from_crs(EPSG, 4326, always_xy=True)
    rng = np.random.default_rng(col)
    rows, cols = np.nonzero(values)
    for k in rng.choice(len(rows), 4, replace=False):
        i, j = int(rows[k]), int(cols[k])  # image row (from north), column (from west)
        east = col * TILE_M + (j + 0.5) * RES_M
        north = (ROW0 + 1) * TILE_M - (i + 0.5) * RES_M
        x, y = screen_of(page, east, north)
        v = int(values[i, j])
        assert pixel(page, x, y) == [v, v, v, 255], (i, j)
        page.mouse.move(x, y)
        readout = page.locator("#readout")
        got_e = float(readout.get_attribute("data-e"))
        got_n = float(readout.get_attribute("data-n"))
        assert abs(got_e - east) < RES_M and abs(got_n - north) < RES_M
        lon, lat = to_wgs84.transform(got_e, got_n)
        text = readout.inner_text()
        assert f"{lat:.7f}°N" in text and f"{lon:.7f}°E" in text and "UTM 31N" in text, text


def test_inverse_transverse_mercator_matches_pyproj(make_shore, page):
    shore: Shore = make_shore()
    open_page(page, shore)
    points = [
        (500_000.0, 4_800_000.0, 31, False), (166_021.4, 1_000.0, 10, False),
        (833_978.6, 7_000_000.0, 33, False), (200_000.0, 8_300_000.0, 35, False),
        (700_000.0, 9_000_000.0, 56, True), (300_000.0, 1_000_000.0, 20, True),
        (512_345.678, 6_543_210.987, 32, False),
    ]  # fmt: skip
    for east, north, zone, south in points:
        epsg = (32700 if south else 32600) + zone
        got = page.evaluate("([e, n, z, s]) => seamap.utm.toLatLon(e, n, z, s)",
                            [east, north, zone, south])  # fmt: skip
        lon, lat = Transformer.from_crs(epsg, 4326, always_xy=True).transform(east, north)
        # 1e-9 degrees: 0.1 mm of latitude.
        assert got["lat"] == pytest.approx(lat, abs=1e-9)
        assert got["lon"] == pytest.approx(lon, abs=1e-9 / max(np.cos(np.radians(lat)), 0.1))
        convergence = Proj(f"EPSG:{epsg}").get_factors(lon, lat).meridian_convergence
        assert got["convergenceDeg"] == pytest.approx(convergence, abs=1e-7)


def test_the_boat_moves_with_its_poses_and_shows_away_when_it_goes(make_shore, page):
    shore: Shore = make_shore()
    boat = shore.boat("boat1")
    boat.wait_heard()
    open_page(page, shore)
    start = pose(0, east=500_010.0, north=4_800_010.0, heading=90.0)
    show(page, 500_020.0, 4_800_010.0, 10.0)  # 10 px per metre
    for i, heading in ((0, 90.0), (20, 90.0), (20, 0.0)):
        p = {**pose(i, east=start["east"], north=start["north"]), "heading_deg": heading}
        boat.put_pose(p)
        page.wait_for_function(
            f"() => seamap.model.vehicles.get('boat1')?.pose?.heading_deg === {heading} &&"
            f" seamap.model.vehicles.get('boat1')?.pose?.east === {p['east']}"
        )
        page.wait_for_timeout(100)  # a frame
        x, y = screen_of(page, p["east"], p["north"])
        # The arrow: its body at the pose, its tip ahead along the heading (grid north is
        # up; convergence here is under 0.01 degrees), nothing of it behind.
        dx, dy = np.sin(np.radians(heading)), -np.cos(np.radians(heading))
        assert pixel(page, x, y)[:3] == list(BOAT1_FILL)
        assert pixel(page, x + 5 * dx, y + 5 * dy)[:3] == list(BOAT1_FILL)
        assert pixel(page, x - 10 * dx, y - 10 * dy)[:3] != list(BOAT1_FILL)
        if i == 20:
            x0, y0 = screen_of(page, start["east"], start["north"])
            assert pixel(page, x0, y0)[:3] != list(BOAT1_FILL)  # it left the start
    section = page.locator('section[data-vehicle="boat1"]')
    assert "away" not in section.get_attribute("class")
    boat.close()
    page.wait_for_selector('section[data-vehicle="boat1"].away', timeout=20_000)
    assert "away" in section.locator(".badge").inner_text()


def test_wheel_zooms_about_the_pointer_and_drag_pans(make_shore, page):
    shore: Shore = make_shore()
    open_page(page, shore)
    page.evaluate("() => seamap.view.setView(500000, 4800000, 2)")
    x, y = 300.0, 200.0
    before = page.evaluate(f"() => seamap.view.screenToUtm({x}, {y})")
    page.mouse.move(x, y)
    page.mouse.wheel(0, -300)
    page.wait_for_function("() => seamap.view.scale > 2")
    after = page.evaluate(f"() => seamap.view.screenToUtm({x}, {y})")
    assert after["e"] == pytest.approx(before["e"], abs=1e-6)
    assert after["n"] == pytest.approx(before["n"], abs=1e-6)
    scale = page.evaluate("() => seamap.view.scale")
    page.mouse.down()
    page.mouse.move(x + 100, y + 50, steps=5)
    page.mouse.up()
    dragged = page.evaluate(f"() => seamap.view.screenToUtm({x + 100}, {y + 50})")
    assert dragged["e"] == pytest.approx(before["e"], abs=1e-6)  # the point followed the mouse
    assert dragged["n"] == pytest.approx(before["n"], abs=1e-6)
    assert page.evaluate("() => seamap.view.scale") == scale


def test_on_a_phone_the_map_fills_the_screen_and_the_panel_folds(make_shore, browser):
    shore: Shore = make_shore()
    phone = browser.new_page()
    try:
        phone.set_viewport_size({"width": 390, "height": 800})
        open_page(phone, shore)
        canvas = phone.locator("#canvas").bounding_box()
        assert canvas["width"] == 390 and canvas["height"] == 800
        assert not phone.locator("#panel").is_visible()
        phone.locator("#panel-toggle").click()
        assert phone.locator("#panel").is_visible()
    finally:
        phone.close()


def test_forward_transverse_mercator_matches_pyproj(make_shore, page):
    shore: Shore = make_shore()
    open_page(page, shore)
    points = [
        (43.35, 3.0, 31, False), (0.01, -123.0, 10, False), (63.1, 17.9, 33, False),
        (74.8, 27.5, 35, False), (-9.0, 152.8, 56, True), (-81.0, -63.2, 20, True),
        (59.0, 8.9, 32, False), (43.35, 6.2, 31, False),  # east of zone 31: a gap that crosses
    ]  # fmt: skip
    for lat, lon, zone, south in points:
        epsg = (32700 if south else 32600) + zone
        got = page.evaluate("([la, lo, z, s]) => seamap.utm.fromLatLon(la, lo, z, s)",
                            [lat, lon, zone, south])  # fmt: skip
        east, north = Transformer.from_crs(4326, epsg, always_xy=True).transform(lon, lat)
        assert got["e"] == pytest.approx(east, abs=1e-4)  # 0.1 mm
        assert got["n"] == pytest.approx(north, abs=1e-4)
        back = page.evaluate("([e, n, z, s]) => seamap.utm.toLatLon(e, n, z, s)",
                             [got["e"], got["n"], zone, south])  # fmt: skip
        assert (back["lat"], back["lon"]) == pytest.approx((lat, lon), abs=1e-10)


def blend(rgb: tuple[int, ...], alpha: float) -> list[float]:
    """``rgb`` drawn at ``alpha`` over the map's background."""
    return [alpha * c + (1 - alpha) * b for c, b in zip(rgb, BACKGROUND, strict=True)]


def near(got: list[int], expected: list[float] | tuple[int, ...], tol: float = 3) -> bool:
    return all(abs(g - e) <= tol for g, e in zip(got[:3], expected, strict=True))


def test_coverage_raster_gaps_and_covered_fraction_are_shown(make_shore, page):
    shore: Shore = make_shore()
    boat = shore.boat("boat1")
    boat.coverage.wait_heard()
    boat.coverage.put_summary(coverage_summary(2000))
    boat.coverage.put_raster(coverage_png(coverage_cells()), coverage_info(2000))
    open_page(page, shore)
    show(page, 500_007.0, 4_800_006.0, 20.0)  # 20 px per metre: a cell is 5 px
    page.wait_for_function(
        "() => { const d = seamap.coverageDrawn('boat1', 's1');"
        " return d.raster >= 2000 && d.gaps >= 2000; }",
        polling="raf",
    )
    row = page.locator('section[data-vehicle="boat1"] li[data-survey="s1"] .coverage')
    assert row.inner_text() == "covered 63.4 % of 1,200 m² · 2 gaps (420 m²)"

    def at(east: float, north: float) -> list[int]:
        return pixel(page, *screen_of(page, east, north))

    # The raster, north-up, each cell in its colour where its UTM corner and size put it:
    # 0.1 m (2 px) either side of cell edges, and the unseen cells left clear.
    cells = {(10, 5): "below_bar", (10, 15): "at_bar", (23, 25): "above_bar"}
    for (r, c), name in cells.items():
        assert near(at(*cell_centre(r, c)), blend(RGB[name], COVERAGE_OPACITY)), (r, c)
    for r, c in ((2, 5), (23, 39), (2, 25)):
        assert near(at(*cell_centre(r, c)), BACKGROUND), (r, c)
    edge_e, edge_n = 500_002.5, 4_800_009.0  # between columns 9 and 10, rows 3 and 4
    assert near(at(edge_e - 0.1, 4_800_006.0), blend(RGB["below_bar"], COVERAGE_OPACITY))
    assert near(at(edge_e + 0.1, 4_800_006.0), blend(RGB["at_bar"], COVERAGE_OPACITY))
    assert near(at(500_001.0, edge_n + 0.1), BACKGROUND)
    assert near(at(500_001.0, edge_n - 0.1), blend(RGB["below_bar"], COVERAGE_OPACITY))

    # The gaps (WGS84 polygons, one with a hole) filled lightly in red, where their UTM
    # corners are; clear in the hole and outside; a red dashed outline on the edges.
    def tinted(p: list[int]) -> bool:
        return p[0] - BACKGROUND[0] > 25 and abs(p[1] - BACKGROUND[1]) < 20

    west, south = GAP_OUTER[0]
    east, north = GAP_OUTER[2]
    for inside in ((west + 0.2, south + 0.2), (east - 0.2, north - 0.2), (500_013.0, 4_800_004.6)):
        assert tinted(at(*inside)), inside
    hole_e = (GAP_HOLE[0][0] + GAP_HOLE[2][0]) / 2
    hole_n = (GAP_HOLE[0][1] + GAP_HOLE[2][1]) / 2
    for outside in ((hole_e, hole_n), (east + 0.2, north - 1), (west + 1, north + 0.2),
                    (GAP_TWO[2][0], GAP_TWO[2][1] + 0.3)):  # fmt: skip
        assert near(at(*outside), BACKGROUND), outside
    # West of the gap, the raster's last seen column, untinted.
    assert near(at(west - 0.2, south + 1), blend(RGB["above_bar"], COVERAGE_OPACITY))
    outline = [at(west, south + k * 0.05) for k in range(1, 80)]
    red = [p for p in outline if p[0] > 180 and p[1] < 120]
    assert 0.3 < len(red) / len(outline) < 0.9  # dashed: red and gaps along the edge

    # The toggle hides both and shows them again.
    orange_cell = cell_centre(10, 5)
    page.locator("#show-coverage").click()
    page.wait_for_timeout(100)  # a frame
    assert near(at(*orange_cell), BACKGROUND) and near(at(west + 0.2, south + 0.2), BACKGROUND)
    page.locator("#show-coverage").click()
    page.wait_for_timeout(100)
    assert near(at(*orange_cell), blend(RGB["below_bar"], COVERAGE_OPACITY))

    # The final coverage replaces it: new colours, no area (no gaps), marked final.
    boat.coverage.put_summary(coverage_summary(3000, area=False, final=True))
    boat.coverage.put_raster(coverage_png(coverage_cells(("above_bar",) * 3)), coverage_info(3000))
    page.wait_for_function(
        "() => { const d = seamap.coverageDrawn('boat1', 's1');"
        " return d.raster >= 3000 && d.gaps >= 3000; }",
        polling="raf",
    )
    assert near(at(*orange_cell), blend(RGB["above_bar"], COVERAGE_OPACITY))
    assert near(at(west + 0.2, south + 0.2), BACKGROUND)
    wait_until(lambda: "final" in row.inner_text(), "the final coverage in the panel")
    assert row.inner_text() == "seen 813 m² · final"


def test_at_the_whole_site_the_page_asks_for_overview_tiles_only(make_shore, browser):
    shore: Shore = make_shore()
    boat = shore.boat("boat1")
    boat.wait_heard()
    site = 8  # tiles a side: 25.6 m
    for dc in range(site):
        for dr in range(site):
            boat.put_tile(COL0 + dc, ROW0 + dr, tile_values(dc * site + dr), version=1)
    wait_until(lambda: len(shore.state()["vehicles"]["boat1"]["surveys"]["s1"]["tiles"]) == 64,
               "the site's tiles at the shore")  # fmt: skip
    # A small screen: the whole site fits at about 6 px per metre, 3 mosaic pixels a screen
    # pixel, so level 1 (10 cm pixels) is the finest the screen shows.
    page = browser.new_page()
    page.set_viewport_size({"width": 320, "height": 240})
    tiles: list[list[int]] = []

    def on_request(request: Any) -> None:
        # /api/tile/VEHICLE/SURVEY/[LEVEL/]COL/ROW.png: as [level, col, row]
        parts = request.url.split("?")[0].removesuffix(".png").split("/api/tile/")
        if len(parts) == 2:
            numbers = [int(x) for x in parts[1].split("/")[2:]]
            tiles.append(numbers if len(numbers) == 3 else [0, *numbers])

    page.on("request", on_request)
    try:
        open_page(page, shore)
        page.wait_for_function(
            "() => { const s = seamap.viewStatus(); return s.wanted > 0 && s.drawn === s.wanted; }",
            polling="raf",
        )
        status = page.evaluate("() => seamap.viewStatus()")
        assert status["level"] == 1
        levels = [level for level, _, _ in tiles]
        # The 4 x 4 level-1 tiles over the site (COL0 and ROW0 are even), no level-0 tile.
        assert levels and set(levels) == {1}, tiles
        assert sorted({(c, r) for _, c, r in tiles}) == sorted(
            ((COL0 >> 1) + dc, (ROW0 >> 1) + dr) for dc in range(4) for dr in range(4)
        )
        # The site is drawn: its middle holds the mosaic's grey, not the background.
        x, y = screen_of(page, (COL0 + 4) * TILE_M, (ROW0 + 4) * TILE_M)
        assert pixel(page, x + 0.5, y + 0.5)[:3] != list(BACKGROUND)
        # Every tile counts as drawn (within the overview tiles that hold it).
        for dc, dr in ((0, 0), (7, 7), (3, 5)):
            drawn = f"() => seamap.drawnVersion('boat1', 's1', {COL0 + dc}, {ROW0 + dr})"
            assert page.evaluate(drawn) == 1

        # A republished tile reaches the overview: its level-1 tile asked for again.
        tiles.clear()
        boat.put_tile(COL0 + 3, ROW0 + 5, tile_values(99), version=2)
        page.wait_for_function(
            f"() => seamap.drawnVersion('boat1', 's1', {COL0 + 3}, {ROW0 + 5}) >= 2",
            polling="raf",
        )
        assert tiles == [[1, (COL0 + 3) >> 1, (ROW0 + 5) >> 1]]

        # Zoomed in on one tile: level 0, only the tiles in view.
        tiles.clear()
        show(page, (COL0 + 0.5) * TILE_M, (ROW0 + 0.5) * TILE_M, 2 / RES_M)
        page.wait_for_function(
            "() => { const s = seamap.viewStatus();"
            " return s.level === 0 && s.drawn === s.wanted && s.wanted > 0; }",
            polling="raf",
        )
        assert tiles and all(level == 0 for level, _, _ in tiles)
        assert 1 <= len(tiles) <= 4, tiles  # 160 x 120 px of a 128 px tile
    finally:
        page.close()


def test_the_track_follows_the_frames_as_the_boat_places_them_anew(make_shore, page):
    """The boat's first estimate of each frame zigzags 20 cm about its line; as its live
    map places the frames anew (``refined`` with a later pose), the drawn track is the
    line, at the scale of the map (50 px a metre: the zigzag would be 10 px either side)."""
    shore: Shore = make_shore()
    boat = shore.boat("boat1")
    boat.wait_heard()
    open_page(page, shore)
    east0, north0, step = 500_010.0, 4_800_010.0, 0.2

    def at(k: int, off: float) -> list[float]:
        return [1.7e9 + k / 5, 43.35, 3.0, east0 + step * k, north0 + off, 90.0]

    def message(k: int, off: float, refined: list[list[float]] | None = None) -> dict[str, Any]:
        row = at(k, off)
        sent = {name: row[i] for i, name in enumerate(("time", "lat", "lon", "east", "north",
                                                       "heading_deg"))}  # fmt: skip
        return {**sent, "epsg": EPSG, **({"refined": refined} if refined else {})}

    show(page, east0 + 3.0, north0, 50.0)
    for k in range(30):
        boat.put_pose(message(k, 0.2 * (-1) ** k))
        page.wait_for_function(
            f"() => seamap.model.vehicles.get('boat1')?.track.length === {k + 1}"
        )
    boat.put_pose(message(30, 0.0, refined=[at(k, 0.0) for k in range(30)]))
    page.wait_for_function(
        "() => { const t = seamap.model.vehicles.get('boat1')?.track || [];"
        f" return t.length === 31 && t.every((p) => Math.abs(p[1] - {north0}) < 1e-6); }}"
    )
    page.wait_for_timeout(100)  # a frame

    def tinted(east: float, north: float) -> bool:
        p = pixel(page, *screen_of(page, east, north))
        return p[0] - BACKGROUND[0] > 100  # the boat's orange, at the track's alpha

    for k in range(2, 26):
        east = east0 + step * k
        assert tinted(east, north0), k  # on the line at every frame...
        assert not tinted(east, north0 + 0.2) and not tinted(east, north0 - 0.2), k  # ...only
    # The page's state after a resync holds the same (the server's view of the track).
    state = shore.state()["vehicles"]["boat1"]
    assert [round(p[1] - north0, 6) for p in state["track"]] == [0.0] * 31
