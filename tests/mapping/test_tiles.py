"""The tile store: top-N candidates per pixel, frames taken out and put back, versions,
spilling and reloading."""

from __future__ import annotations

import math

import numpy as np

from mapping.blend import BlendParams
from mapping.grid import SonarGrid
from mapping.mosaic import SonarPose, TileGrid
from mapping.tiles import MemorySpill, TileStore

TILES = TileGrid(res_m=0.02, tile_px=64)
GRID = SonarGrid(shape=(32, 32), res_m=0.02, forward_max_m=0.64, starboard_min_m=0.0)


def frame(value: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    image = np.full(GRID.shape, value, np.float32)
    score = np.full(GRID.shape, 0.5, np.float32)
    return image, score, np.ones(GRID.shape, bool)


def pose(east: float, north: float) -> SonarPose:
    # Boresight north: forward = north, starboard = east.
    return SonarPose(east, north, 0.0)


def test_a_frame_lands_in_the_tile_under_it_and_renders() -> None:
    store = TileStore(TILES)
    image, score, mask = frame(0.5)
    touched = store.insert(0, image, score, mask, GRID, pose(0.2, 0.1), time=0.0)
    assert touched == [(0, 0)]
    rendered = store.render((0, 0))
    assert rendered.version == 1
    covered = rendered.values > 0
    # 32 x 32 pixels of the frame, less its interpolated edge.
    assert 28 * 28 <= covered.sum() <= 32 * 32
    assert abs(int(np.median(rendered.values[covered])) - round(0.5 * 254 + 1)) <= 1
    # North-up: the frame spans northings 0.10..0.74 m, i.e. the tile's lower rows.
    rows = np.flatnonzero(covered.any(axis=1))
    assert rows.min() >= (1.28 - 0.76) / 0.02 - 1 and rows.max() <= (1.28 - 0.10) / 0.02


def test_only_the_best_candidates_are_kept_and_a_moved_frame_follows_its_pose() -> None:
    store = TileStore(TILES, BlendParams(top_n=2))
    for index, value in enumerate((0.2, 0.4, 0.6)):
        image, score, mask = frame(value)
        score *= 1 + index  # later frames score higher
        store.insert(index, image, score, mask, GRID, pose(0.2, 0.1), time=float(index))
    tile = store.tile((0, 0))
    centre = (40, 25)
    assert sorted(tile.frame[centre].tolist()) == [1, 2]
    first = store.render((0, 0))
    # Frame 2 moves 10 cm east: take it out and put it back there; the tile's version grows.
    store.remove(2, [(0, 0)])
    image, score, mask = frame(0.6)
    store.insert(2, image, score * 3, mask, GRID, pose(0.3, 0.1), time=3.0)
    second = store.render((0, 0))
    assert second.version > first.version
    assert not np.array_equal(first.values, second.values)
    assert 2 in tile.boxes


def test_idle_tiles_leave_memory_and_come_back() -> None:
    spill = MemorySpill()
    store = TileStore(TILES, spill=spill, evict_after_s=5.0)
    image, score, mask = frame(0.5)
    store.insert(0, image, score, mask, GRID, pose(0.2, 0.1), time=0.0)
    before = store.render((0, 0))
    store.evict_idle(now=3.0)
    assert (0, 0) in store.active
    store.evict_idle(now=10.0)
    assert (0, 0) not in store.active and store.nbytes == 0
    assert list(spill.keys()) == [(0, 0)]
    # Listed and served from the spill while away...
    assert [t.key for t in store.rendered_tiles()] == [(0, 0)]
    # ... and back in memory, candidates intact, when a later lane covers it again.
    image2, score2, mask2 = frame(0.9)
    store.insert(1, image2, score2, mask2, GRID, pose(0.88, 0.1), time=20.0)
    assert (0, 0) in store.active and store.reloaded == 1
    after = store.render((0, 0))
    assert after.version > before.version
    np.testing.assert_array_equal(after.values[before.values > 0], before.values[before.values > 0])


def test_memory_is_bounded_by_the_tiles_being_worked() -> None:
    store = TileStore(TILES, evict_after_s=2.0)
    image, score, mask = frame(0.5)
    peak = 0
    for k in range(400):  # a long straight line east, 5 cm a frame
        store.insert(k, image, score, mask, GRID, pose(0.05 * k, 0.1), time=0.1 * k)
        if k % 10 == 0:
            store.render_dirty()
            store.evict_idle(0.1 * k)
        peak = max(peak, len(store.active))
    assert len(store.all_keys()) >= 15
    assert peak <= 6
    assert math.isfinite(store.nbytes)


def test_a_redraw_shows_at_the_slower_pace_and_whenever_the_tile_leaves() -> None:
    # A re-solve's redraws mark their pixels apart: a refine leaves them, a deferred
    # render (or the tile's last render before it is spilled) blends them.
    store = TileStore(TILES, spill=MemorySpill(), evict_after_s=5.0)
    image, score, mask = frame(0.5)
    keys = store.insert(0, image, score, mask, GRID, pose(0.2, 0.1), time=0.0)
    before = store.render_dirty()[0].values
    store.remove(0, keys, deferred=True)
    keys = store.insert_layers(
        0, np.dstack([image, score, mask.astype(np.float32)]), mask, GRID, pose(0.4, 0.1),
        time=1.0, deferred=True,
    )  # fmt: skip
    assert store.render_dirty(deferred=False) == []
    assert store.tile((0, 0)).dirty
    after = store.render_dirty(deferred=True)[0].values
    moved = (before > 0) != (after > 0)
    assert moved.sum() >= 2 * 10 * 28  # ten columns left behind, ten newly covered
    assert not store.tile((0, 0)).dirty
    # Redrawn again and left: the spill renders it first.
    store.remove(0, keys, deferred=True)
    store.insert(0, image, score, mask, GRID, pose(0.2, 0.1), time=2.0, movable=True)
    store.remove(0, [(0, 0)], deferred=True)
    (last,) = store.evict_idle(now=10.0)
    assert not last.values.any()  # the frame taken out shows as taken out


def test_idle_tiles_stay_within_the_memory_budget_least_recently_used_leaving_first() -> None:
    tile_bytes = TILES.tile_px**2 * (1 + 2 + 2) * BlendParams().top_n + TILES.tile_px**2
    spill = MemorySpill()
    store = TileStore(TILES, spill=spill, evict_after_s=1.0, memory_bytes=2 * tile_bytes)
    image, score, mask = frame(0.5)
    # Four tiles side by side, a frame in each at t = 0..3; the first is used again last.
    for k in range(4):
        store.insert(k, image, score, mask, GRID, pose(1.28 * k + 0.2, 0.1), time=float(k))
    store.tile((0, 0))
    store.render_dirty()
    store.evict_idle(now=3.5)  # idle: tiles 0, 1 and 2; tile 3 is still worked
    # Two tiles' worth stay: the one still worked and the one used last (tile 0).
    assert sorted(store.active) == [(0, 0), (3, 0)]
    assert sorted(spill.keys()) == [(1, 0), (2, 0)]
    store.evict_idle(now=10.0)
    assert sorted(store.active) == [(0, 0), (3, 0)]  # within the budget: nothing leaves


def test_the_memory_budget_changes_where_tiles_wait_not_what_they_show() -> None:
    rng = np.random.default_rng(3)
    image, score, mask = frame(0.5)
    runs = []
    for budget in (0, None, 10**9):
        store = TileStore(
            TILES, spill=MemorySpill(), evict_after_s=1.0,
            memory_bytes=None if budget is None else budget,
        )  # fmt: skip
        where: dict[int, list[tuple[int, int]]] = {}
        rng = np.random.default_rng(3)
        for k in range(120):
            # Frames along lanes back and forth over six tiles, some moved again later.
            east = 0.2 + 0.06 * (k % 60) if (k // 60) % 2 == 0 else 3.8 - 0.06 * (k % 60)
            pixels = image * np.float32(rng.uniform(0.5, 1.5))
            where[k] = store.insert(
                k, pixels, score, mask, GRID, pose(east, 0.1 + 0.5 * (k // 60)), time=0.1 * k
            )
            if k >= 30 and k % 7 == 0:
                moved = k - 30
                store.remove(moved, where[moved], deferred=True)
                where[moved] = store.insert(
                    moved,
                    pixels,
                    score * np.float32(1.1),
                    mask,
                    GRID,
                    pose(0.2 + 0.06 * (moved % 60), 0.12),
                    time=0.1 * moved,
                )
            if k % 5 == 0:
                store.render_dirty()
                store.evict_idle(0.1 * k)
        runs.append({t.key: t.values for t in store.rendered_tiles()})
    assert runs[0].keys() == runs[1].keys() == runs[2].keys() and len(runs[0]) >= 3
    for key in runs[0]:
        np.testing.assert_array_equal(runs[0][key], runs[1][key])
        np.testing.assert_array_equal(runs[0][key], runs[2][key])
