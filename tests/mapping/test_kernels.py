"""The compiled tile loops give what the numpy expressions they replaced give."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapping import kernels
from mapping.blend import BlendParams, robust_blend

N, SIZE = 16, 64


def _stacks(rng: np.random.Generator, fill: float) -> tuple[np.ndarray, ...]:
    """Candidate stacks (rows, cols, N) with ``fill`` of the slots taken, scores with many
    ties (the quantised scores of a real tile repeat)."""
    shape = (SIZE, SIZE, N)
    taken = rng.random(shape) < fill
    score = np.where(taken, rng.integers(1, 400, shape) * 160, 0).astype(np.uint16)
    intensity = rng.integers(0, 256, shape).astype(np.uint8)
    frame = np.where(taken, rng.integers(0, 5, shape), 0xFFFF).astype(np.uint16)
    return score, intensity, frame


def _quantise_valid(score, valid):
    """Scores as tiles.py quantised them with numpy: 1..65535 where valid."""
    q = np.multiply(score, np.float32(65535.0))
    np.rint(q, out=q)
    np.clip(q, 0.0, 65535.0, out=q)
    return np.maximum(q.astype(np.uint16), valid.view(np.uint8))


def _grey(image):
    values = np.multiply(image, np.float32(255.0))
    np.rint(values, out=values)
    np.clip(values, 0.0, 255.0, out=values)
    return values.astype(np.uint8)


def _offer_numpy(score, intensity, frame, r0, c0, warped, tag):
    """The update as tiles.py made it with numpy before the kernels."""
    valid = (warped[..., 2] >= 0.999) & (warped[..., 1] > 0.0)
    new_score = _quantise_valid(warped[..., 1], valid)
    new_value = _grey(warped[..., 0])
    rows_n, cols_n = new_score.shape
    box = (slice(r0, r0 + rows_n), slice(c0, c0 + cols_n))
    weakest = score[box].min(axis=2)
    better = valid & (new_score > weakest)
    rows, cols = np.nonzero(better)
    for r, c in zip(rows, cols, strict=True):
        slot = int(np.argmax(score[r0 + r, c0 + c] == weakest[r, c]))  # the first
        score[r0 + r, c0 + c, slot] = new_score[r, c]
        intensity[r0 + r, c0 + c, slot] = new_value[r, c]
        frame[r0 + r, c0 + c, slot] = tag
    return better


@pytest.mark.parametrize("fill", [0.0, 0.4, 1.0])
def test_offering_a_frame_fills_the_first_weakest_slot(fill: float) -> None:
    rng = np.random.default_rng(1)
    score, intensity, frame = _stacks(rng, fill)
    r0, c0, rows, cols = 5, 9, 40, 50
    # A warped frame: scores on the tiles' quantisation steps and between them, some 0
    # or tiny; the fan's edge interpolated (mask between 0 and 1), intensities anywhere.
    warped = np.empty((rows, cols, 3), np.float32)
    warped[..., 0] = rng.random((rows, cols)) * 1.02 - 0.01
    steps = rng.integers(0, 400, (rows, cols)) * 160 / 65535.0
    warped[..., 1] = np.where(rng.random((rows, cols)) < 0.5, steps, rng.random((rows, cols)))
    warped[..., 1][rng.random((rows, cols)) < 0.05] = 1e-7
    warped[..., 2] = rng.choice(
        [0.0, 0.5, 0.9989, 0.999, 1.0], (rows, cols), p=[0.1, 0.05, 0.05, 0.1, 0.7]
    )
    expected = [a.copy() for a in (score, intensity, frame)]
    want = _offer_numpy(expected[0], expected[1], expected[2], r0, c0, warped, 7)
    assert kernels.any_valid(warped) == bool(want.any())
    got = kernels.offer_warped(score, intensity, frame, r0, c0, warped, 7)
    np.testing.assert_array_equal(got, want)
    assert want.any() and (fill == 0.0 or not want.all())
    for a, b in zip((score, intensity, frame), expected, strict=True):
        np.testing.assert_array_equal(a, b)


def test_taking_a_frame_out_empties_its_slots_and_only_them() -> None:
    rng = np.random.default_rng(2)
    score, _, frame = _stacks(rng, 0.7)
    want_score, want_frame = score.copy(), frame.copy()
    box = (slice(3, 50), slice(10, 60))
    hit = want_frame[box] == 3
    want_score[box][hit] = 0
    want_frame[box][hit] = 0xFFFF
    got = kernels.take_out(score, frame, 3, 50, 10, 60, 3)
    np.testing.assert_array_equal(got, hit.any(axis=2))
    np.testing.assert_array_equal(score, want_score)
    np.testing.assert_array_equal(frame, want_frame)
    assert (frame == 3).sum() > 0  # outside the box it stays


@pytest.mark.parametrize("fill", [0.1, 0.5, 1.0])
def test_the_compiled_blend_renders_what_the_paper_blend_renders(fill: float) -> None:
    """Grey levels equal but for float32 rounding (sums in float64 here): within one
    level everywhere, equal on all but a few pixels in ten thousand."""
    rng = np.random.default_rng(3)
    score, intensity, _ = _stacks(rng, fill)
    # Outliers among similar values, as a pixel seen by many frames has.
    base = rng.integers(40, 200, (SIZE, SIZE, 1))
    similar = np.clip(base + rng.normal(0, 6, (SIZE, SIZE, N)), 0, 255)
    intensity = np.where(rng.random((SIZE, SIZE, N)) < 0.8, similar, intensity).astype(np.uint8)
    params = BlendParams()
    lut = ((np.arange(65536) / 65535.0) ** params.gamma).astype(np.float32)
    rows, cols = np.nonzero(np.ones((SIZE, SIZE), bool))
    values = intensity[rows, cols].astype(np.float32) * np.float32(1 / 255)
    quantised = score[rows, cols]
    blended, covered = robust_blend(
        values, quantised.astype(np.float32) * np.float32(1 / 65535), params, lut[quantised]
    )
    want = np.clip(np.rint(blended * 254.0) + 1.0, 1, 255).astype(np.uint8)
    want[~covered] = 0
    got, got_covered = kernels.blend(
        intensity, score, rows, cols, lut, params.rho, params.eta, params.top_n
    )
    np.testing.assert_array_equal(got_covered, covered)
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1
    assert np.mean(got != want) < 1e-3
    assert covered.any()


def test_the_top_n_of_a_wider_stack_are_the_best_scores() -> None:
    """With more slots than ``top_n`` only the best scores are blended."""
    score = np.zeros((1, 1, 4), np.uint16)
    intensity = np.zeros((1, 1, 4), np.uint8)
    score[0, 0] = [60000, 65000, 62000, 64000]
    intensity[0, 0] = [10, 200, 10, 200]
    lut = np.ones(65536, np.float32)
    rows = cols = np.zeros(1, np.intp)
    got, covered = kernels.blend(intensity, score, rows, cols, lut, 0.5, 2.7, 2)
    assert covered[0]
    assert got[0] == round(200 / 255 * 254) + 1


def test_a_loop_numba_cannot_cache_is_compiled_all_the_same() -> None:
    """Where numba finds no folder to cache in (a read-only installation run by a user
    without a home), the loops are compiled at each start instead of failing to import.
    A function from a string has no file to cache next to: the same refusal."""
    namespace: dict[str, object] = {}
    exec(compile("def double(x):\n    return 2 * x\n", "<string>", "exec"), namespace)
    double = kernels._compiled(namespace["double"])
    assert double(21) == 42


def test_warm_compiles_every_loop_for_the_tiles_types() -> None:
    """In a fresh process (here the other tests have compiled them already), ``warm``
    leaves every loop compiled for the types the tiles call it with, so that the first
    frame does not compile."""
    code = (
        "from mapping import kernels\n"
        "loops = (\n"
        "    kernels.any_valid, kernels.offer_warped, kernels.take_out, kernels.blend,\n"
        "    kernels.tiles_near, kernels.offer_warped_keeping_all,\n"
        ")\n"
        "assert not any(loop.signatures for loop in loops)\n"
        "kernels.warm()\n"
        "warmed = [len(loop.signatures) for loop in loops]\n"
        "from tests.mapping.test_tiles import GRID, TILES, frame, pose\n"
        "from mapping.tiles import TileStore\n"
        "store = TileStore(TILES)\n"
        "image, score, mask = frame(0.5)\n"
        "keys = store.insert(1, image, score, mask, GRID, pose(0.2, 0.1), time=0.0)\n"
        "store.render_dirty()\n"
        "store.remove(1, keys)\n"
        "from mapping.blend import BlendParams\n"
        "store = TileStore(TILES, BlendParams(method='hurtos'))\n"
        "store.insert(2, image, score, mask, GRID, pose(0.2, 0.1), time=0.0, movable=False)\n"
        "print(warmed, [len(loop.signatures) for loop in loops])\n"
    )
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    # One signature each, and the tiles' own calls needed no other.
    assert done.stdout.strip() == "[1, 1, 1, 1, 1, 1] [1, 1, 1, 1, 1, 1]"


def test_a_box_the_fan_only_grazes_offers_nothing() -> None:
    """Interpolated across the fan's edge (mask below 0.999) or without a score: not a
    pixel to offer, and the tile is not even loaded for it."""
    warped = np.zeros((6, 8, 3), np.float32)
    warped[..., 0] = 0.5
    warped[..., 1] = 0.3
    warped[..., 2] = 0.998
    assert not kernels.any_valid(warped)
    warped[2, 3, 2] = 1.0
    warped[2, 3, 1] = 0.0
    assert not kernels.any_valid(warped)
    warped[2, 3, 1] = 0.3
    assert kernels.any_valid(warped)


def _tiles_near_numpy(x, y, t, margin):
    """The tiles near a fan's samples as tiles.py found them with numpy masks."""
    found = []
    for col in range(math.floor((x.min() - margin) / t), math.floor((x.max() + margin) / t) + 1):
        x0 = col * t
        in_col = (x >= x0 - margin) & (x < x0 + t + margin)
        if not in_col.any():
            continue
        xc, yc = x[in_col], y[in_col]
        for row in range(
            math.floor((yc.min() - margin) / t), math.floor((yc.max() + margin) / t) + 1
        ):
            y0 = row * t
            near = (yc >= y0 - margin) & (yc < y0 + t + margin)
            if near.any():
                xn, yn = xc[near], yc[near]
                found.append((col, row, xn.min(), yn.min(), xn.max(), yn.max()))
    return np.array(found, float).reshape(-1, 6)


@pytest.mark.parametrize("seed", range(6))
def test_the_tiles_near_a_fan_are_those_the_masks_found(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # A fan's samples somewhere in UTM, some on tile edges exactly (t = 5.12 m).
    t, margin = 5.12, 0.16
    centre = rng.uniform(-1e3, 1e3, 2) + 4.0e5
    radius = rng.uniform(0.5, 12.0, 400)
    bearing = rng.uniform(-1.2, 1.2, 400) + rng.uniform(0, 2 * np.pi)
    x = centre[0] + radius * np.cos(bearing)
    y = centre[1] + radius * np.sin(bearing)
    x[:20] = np.round(x[:20] / t) * t + rng.choice([-margin, 0.0, margin], 20)
    got = kernels.tiles_near(x, y, t, margin)
    np.testing.assert_array_equal(got, _tiles_near_numpy(x, y, t, margin))
    assert kernels.tiles_near(x[:0], y[:0], t, margin).shape == (0, 6)


def test_the_sorting_network_sorts_every_count_ties_and_all() -> None:
    rng = np.random.default_rng(9)
    for count in range(kernels.NETWORK_SIZE + 1):
        for _ in range(50):
            values = (rng.integers(0, 6, kernels.NETWORK_SIZE) / 255.0).astype(np.float32)
            want = np.sort(values[:count])
            kernels._sort_by_network(values, count)
            np.testing.assert_array_equal(values[:count], want)
    # Every 0/1 input of 16 (the 0-1 principle: then it sorts anything).
    bits = (np.arange(2**16)[:, None] >> np.arange(16)) & 1
    for row in bits:
        values = row.astype(np.float32)
        kernels._sort_by_network(values, 16)
        assert np.all(np.diff(values) >= 0)
