"""The live map page's overview pyramid (``seamap.shore.pyramid``): a small site's tiles
(8 x 8, with holes) merged at coarser levels, each level's tile the alpha-aware 2 x 2
merge of its children, rebuilt only where a tile changed, and served by the page's server."""

from __future__ import annotations

import urllib.request

import numpy as np
import numpy.typing as npt

from drivers.zenoh_io import encode_tile
from seamap.shore.pyramid import MAX_LEVEL, Pyramid, decode_grey_alpha
from seamap.shore.state import ShoreEvent
from seamap.shore.web import WebServer
from tests.seamap.shore.conftest import wait_until
from tests.seamap.test_shore import SIZE_PX, tile_info

SITE = 8
"""Tiles a side."""
COL0, ROW0 = 156248, 1500000
"""The site's south-west tile (easting 499 994 m, northing 4 800 000 m), on a corner of
the level-3 grid, so each level's tiles cover the site exactly."""


def site_values(seed: int) -> dict[tuple[int, int], npt.NDArray[np.uint8]]:
    """8 x 8 tiles of random texture (1..255) with no data (0) in patches and along a
    diagonal edge, as a swath's edge leaves it; one tile missing altogether."""
    rng = np.random.default_rng(seed)
    tiles = {}
    for dc in range(SITE):
        for dr in range(SITE):
            values = rng.integers(1, 256, (SIZE_PX, SIZE_PX), dtype=np.uint8)
            values[rng.random((SIZE_PX, SIZE_PX)) < 0.3] = 0
            y, x = np.mgrid[0:SIZE_PX, 0:SIZE_PX]
            values[x + y < (dc * 7 + dr * 3) % SIZE_PX] = 0
            tiles[(COL0 + dc, ROW0 + dr)] = values
    del tiles[(COL0 + 3, ROW0 + 5)]
    return tiles


def mosaic(tiles: dict[tuple[int, int], npt.NDArray[np.uint8]]) -> npt.NDArray[np.uint8]:
    """The site north-up: image row 0 is the northern edge of row ROW0 + SITE - 1."""
    image = np.zeros((SITE * SIZE_PX, SITE * SIZE_PX), np.uint8)
    for (col, row), values in tiles.items():
        y = (ROW0 + SITE - 1 - row) * SIZE_PX
        x = (col - COL0) * SIZE_PX
        image[y : y + SIZE_PX, x : x + SIZE_PX] = values
    return image


def block_means(image: npt.NDArray[np.uint8], k: int) -> tuple[np.ndarray, np.ndarray]:
    """Each k x k block's mean over its pixels with data, and the fraction with data."""
    h, w = image.shape[0] // k, image.shape[1] // k
    valid = (image > 0).reshape(h, k, w, k)
    total = (image.astype(float) * valid.reshape(image.shape)).reshape(h, k, w, k).sum((1, 3))
    count = valid.sum((1, 3))
    mean = np.divide(total, count, out=np.zeros_like(total), where=count > 0)
    return mean, count / (k * k)


def built(pyramid: Pyramid, level: int, col: int, row: int) -> npt.NDArray[np.uint8]:
    held = pyramid.tile(level, col, row)
    assert held is not None
    return decode_grey_alpha(held[1])


def test_each_level_is_the_alpha_aware_merge_of_the_one_below() -> None:
    tiles = site_values(1)
    pyramid = Pyramid(SIZE_PX)
    for (col, row), values in tiles.items():
        pyramid.put(col, row, 1, encode_tile(values))
    image = mosaic(tiles)
    for level in (1, 2, 3):
        k = 2**level
        mean, fraction = block_means(image, k)
        n = SITE // k  # tiles a side at this level
        for dc in range(n):
            for dr in range(n):
                col, row = (COL0 >> level) + dc, (ROW0 >> level) + dr
                tile = built(pyramid, level, col, row)
                y = (n - 1 - dr) * SIZE_PX
                want_mean = mean[y : y + SIZE_PX, dc * SIZE_PX : (dc + 1) * SIZE_PX]
                want_fraction = fraction[y : y + SIZE_PX, dc * SIZE_PX : (dc + 1) * SIZE_PX]
                has_data = want_fraction > 0
                # Where any pixel below has data: some alpha, the mean of those with
                # data (no-data pixels never pull it towards black); elsewhere none.
                assert np.array_equal(tile[:, :, 1] > 0, has_data), (level, dc, dr)
                grey = tile[:, :, 0].astype(float)
                tolerance = 0.5 * level + 0.01  # a rounding per level merged
                assert np.abs(grey - want_mean)[has_data].max() <= tolerance, (level, dc, dr)
                alpha = tile[:, :, 1].astype(float)
                assert np.abs(alpha - 255 * want_fraction).max() <= level + 0.01
    # The level-1 tile over the missing one: that quarter without data.
    tile = built(pyramid, 1, (COL0 + 3) >> 1, (ROW0 + 5) >> 1)
    half = SIZE_PX // 2
    assert not tile[:half, half:, 1].any()  # the missing tile is the north-east child
    assert tile[half:, half:, 1].any()
    # Nothing above the site's tiles, and no level beyond the coarsest.
    assert pyramid.tile(1, (COL0 >> 1) + SITE, ROW0 >> 1) is None
    assert pyramid.tile(MAX_LEVEL + 1, 0, 0) is None


def test_a_republished_tile_rebuilds_only_its_ancestors() -> None:
    tiles = site_values(2)
    pyramid = Pyramid(SIZE_PX)
    for (col, row), values in tiles.items():
        pyramid.put(col, row, 3, encode_tile(values))
    for level in (1, 2, 3):
        for dc in range(SITE >> level):
            for dr in range(SITE >> level):
                built(pyramid, level, (COL0 >> level) + dc, (ROW0 >> level) + dr)
    builds = pyramid.builds
    stamps = {level: pyramid.stamp(level, COL0 >> level, ROW0 >> level) for level in (1, 2, 3)}
    newer = np.full((SIZE_PX, SIZE_PX), 200, np.uint8)
    pyramid.put(COL0, ROW0, 4, encode_tile(newer))
    pyramid.put(COL0, ROW0, 2, encode_tile(newer // 2))  # an older version: ignored
    for level in (1, 2, 3):
        key = (COL0 >> level, ROW0 >> level)
        assert pyramid.stamp(level, *key) == stamps[level] + 1  # type: ignore[operator]
        # Its south-west corner (the tile republished, scaled down) is now all 200.
        side = SIZE_PX >> level
        corner = built(pyramid, level, *key)[SIZE_PX - side :, :side]
        assert (corner[:, :, 0] == 200).all() and (corner[:, :, 1] == 255).all()
    assert pyramid.builds == builds + 3  # one ancestor a level, nothing else
    # Asked again without a change: served as built.
    built(pyramid, 3, COL0 >> 3, ROW0 >> 3)
    assert pyramid.builds == builds + 3


def test_the_server_serves_each_level_at_its_stamp(tmp_path) -> None:
    tiles = site_values(3)
    server = WebServer("127.0.0.1", 0, tmp_path)
    url = server.start()
    try:
        for (col, row), values in tiles.items():
            info = tile_info(col, row, 5)
            server.on_event(ShoreEvent("tile", "boat1", "s1", col, row, info, encode_tile(values)))
        pyramid = server.view.pyramid
        wait_until(lambda: pyramid("boat1", "s1") is not None
                   and pyramid("boat1", "s1").stamp(3, COL0 >> 3, ROW0 >> 3) == 63 * 6,  # type: ignore[union-attr]
                   "the tiles on the server's loop")  # fmt: skip
        stamp = 63 * 6  # 63 tiles, version 5
        with urllib.request.urlopen(
            f"{url}api/tile/boat1/s1/3/{COL0 >> 3}/{ROW0 >> 3}.png?v={stamp}", timeout=10
        ) as response:
            assert response.headers["X-Tile-Stamp"] == str(stamp)
            assert "immutable" in response.headers["Cache-Control"]
            tile = decode_grey_alpha(response.read())
        mean, _ = block_means(mosaic(tiles), 8)
        has_data = tile[:, :, 1] > 0
        assert np.abs(tile[:, :, 0].astype(float) - mean)[has_data].max() <= 1.51
        # The tiles as received, as before, at level 0 too.
        with urllib.request.urlopen(f"{url}api/tile/boat1/s1/{COL0}/{ROW0}.png", timeout=10) as r:
            assert r.read() == encode_tile(tiles[(COL0, ROW0)])
        for missing in (f"3/{(COL0 >> 3) + 1}/{ROW0 >> 3}", f"{MAX_LEVEL + 1}/0/0", "x/0/0"):
            try:
                urllib.request.urlopen(f"{url}api/tile/boat1/s1/{missing}.png", timeout=10)
                raise AssertionError(f"{missing} served")
            except urllib.error.HTTPError as exc:
                assert exc.code == 404
    finally:
        server.close()
