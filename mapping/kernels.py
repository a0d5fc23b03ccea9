"""Compiled per-pixel loops of the tiles (numba): what numpy can only say with a dozen
whole-stack temporaries a call.

A tile keeps, per pixel, ``N`` candidate slots, contiguous (``mapping.tiles``: stacks
(rows, cols, N)). Offering a frame's pixel, taking a frame out and blending a pixel's
candidates each visit the pixel's N slots once here; numpy needed a whole-stack
temporary for every step (the weakest slot, its first index, the comparison, the masked
sorts of the median and the MAD).

The results are those of the numpy expressions they replace: the candidate updates
exactly (integers), the blend to float32 rounding (its sums are taken in float64 here,
pairwise in float32 there). On a whole survey (quadrats seed 13, single-stage) the
mosaic differed on one pixel in 2.3 million, by one grey level; the tests
(``tests/mapping/test_kernels.py``) bound it at one in a thousand on random stacks.
``mapping.blend.robust_blend`` stays the reference they are checked against.

Compiled on first use and cached on disk (``cache=True``: next to this file,
``NUMBA_CACHE_DIR`` or the user's cache; compiled at each start where none is writable),
so a daemon pays the compile once per installation, not per start.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import numpy.typing as npt

NO_FRAME = 0xFFFF


def _compiled(function: Any) -> Any:
    """``numba.njit``, cached on disk where numba finds a writable cache folder (next to
    this file, ``NUMBA_CACHE_DIR``, or the user's cache); compiled at each start where it
    finds none (a read-only installation run by a user without a home), not an error."""
    try:
        return numba.njit(cache=True, nogil=True)(function)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return numba.njit(nogil=True)(function)


compiled = _compiled
"""The compile other modules' loops use (``mapping.marginals``)."""

U8 = npt.NDArray[np.uint8]
U16 = npt.NDArray[np.uint16]
F32 = npt.NDArray[np.float32]
Mask = npt.NDArray[np.bool_]
Index = npt.NDArray[np.intp]
F64 = npt.NDArray[np.float64]

INSIDE = np.float32(0.999)
"""A warped pixel is inside the fan where its interpolated mask is at least this: across
the fan's edge interpolation mixes in the zeros outside it."""


@_compiled
def any_valid(warped: F32) -> bool:
    """Whether any pixel of a warped frame stack (rows, cols, [image, score, mask]) is
    wholly inside the fan with a score (``offer_warped``'s test), stopping at the first."""
    rows, cols = warped.shape[0], warped.shape[1]
    for i in range(rows):
        for j in range(cols):
            if warped[i, j, 2] >= INSIDE and warped[i, j, 1] > np.float32(0.0):
                return True
    return False


@_compiled
def offer_warped(
    score: U16,
    intensity: U8,
    frame: U16,
    r0: int,
    c0: int,
    warped: F32,
    tag: int,
) -> Mask:
    """Offer a frame's pixels to a tile's candidate stacks ((rows, cols, N) each): the
    frame as warped into the box at (r0, c0) of the tile, (rows, cols, [image, score,
    mask]) in float32, in one pass. A pixel is offered where it is wholly inside the fan
    (mask >= ``INSIDE``) and has a score; its score is quantised to 1..65535 and its
    image to grey levels 0..255 as ``mapping.tiles`` did with numpy (the same float32
    steps), which took ten whole-box passes. Where a pixel's quantised score beats its
    weakest candidate, it goes into the first slot holding that weakest one. Returns
    where it went in (the pixels to render again)."""
    n = score.shape[2]
    rows, cols = warped.shape[0], warped.shape[1]
    better = np.zeros((rows, cols), np.bool_)
    for i in range(rows):
        r = r0 + i
        for j in range(cols):
            s = warped[i, j, 1]
            if not (warped[i, j, 2] >= INSIDE and s > np.float32(0.0)):
                continue
            q = min(max(np.rint(s * np.float32(65535.0)), np.float32(0.0)), np.float32(65535.0))
            new_score = max(np.uint16(q), np.uint16(1))
            c = c0 + j
            slots = score[r, c]
            weakest = slots[0]
            slot = 0
            for k in range(1, n):
                if slots[k] < weakest:
                    weakest = slots[k]
                    slot = k
            if new_score > weakest:
                g = min(
                    max(np.rint(warped[i, j, 0] * np.float32(255.0)), np.float32(0.0)),
                    np.float32(255.0),
                )
                slots[slot] = new_score
                intensity[r, c, slot] = np.uint8(g)
                frame[r, c, slot] = tag
                better[i, j] = True
    return better


@_compiled
def offer_warped_keeping_all(
    score: U16,
    intensity: U8,
    frame: U16,
    rest_weight: F32,
    rest_value: F32,
    r0: int,
    c0: int,
    warped: F32,
    tag: int,
    movable: Mask,
) -> Mask:
    """``offer_warped`` for a blend over every frame (Hurtós's weighted mean): a
    candidate the stack has no room for (the offered one when it is the weakest, else the
    weakest it pushes out) is not lost but added to the pixel's sums outside the stack,
    ``rest_weight`` += w and ``rest_value`` += w I ((rows, cols) each; w and I as the
    slots quantise them), so the stack and the sums together hold every frame. A
    candidate of a frame that may still be taken out (``movable[tag]``, over the 65536
    tags) is dropped instead, as ``offer_warped`` drops it: the sums cannot give it back,
    and left in them it would stay where the frame no longer is. Returns the pixels whose
    blend changed."""
    n = score.shape[2]
    rows, cols = warped.shape[0], warped.shape[1]
    changed = np.zeros((rows, cols), np.bool_)
    inv_score = np.float32(1.0 / 65535.0)
    inv_value = np.float32(1.0 / 255.0)
    for i in range(rows):
        r = r0 + i
        for j in range(cols):
            s = warped[i, j, 1]
            if not (warped[i, j, 2] >= INSIDE and s > np.float32(0.0)):
                continue
            q = min(max(np.rint(s * np.float32(65535.0)), np.float32(0.0)), np.float32(65535.0))
            new_score = max(np.uint16(q), np.uint16(1))
            g = min(
                max(np.rint(warped[i, j, 0] * np.float32(255.0)), np.float32(0.0)),
                np.float32(255.0),
            )
            c = c0 + j
            slots = score[r, c]
            weakest = slots[0]
            slot = 0
            for k in range(1, n):
                if slots[k] < weakest:
                    weakest = slots[k]
                    slot = k
            if new_score > weakest:
                if weakest > 0 and not movable[frame[r, c, slot]]:
                    w = np.float32(weakest) * inv_score
                    rest_weight[r, c] += w
                    rest_value[r, c] += w * (np.float32(intensity[r, c, slot]) * inv_value)
                slots[slot] = new_score
                intensity[r, c, slot] = np.uint8(g)
                frame[r, c, slot] = tag
                changed[i, j] = True
            elif not movable[tag]:
                w = np.float32(new_score) * inv_score
                rest_weight[r, c] += w
                rest_value[r, c] += w * (g * inv_value)
                changed[i, j] = True
    return changed


@_compiled
def take_out(score: U16, frame: U16, r0: int, r1: int, c0: int, c1: int, tag: int) -> Mask:
    """Empty the slots ``tag`` holds in the box rows r0:r1, cols c0:c1 (score 0, no
    frame); returns the pixels it held (to render again).

    Without a branch in the slot loop (a select and a store per slot), which the compiler
    vectorises: 0.17 ms for a 190 x 200 box of 16 slots against 0.43 with one."""
    n = score.shape[2]
    hit = np.zeros((r1 - r0, c1 - c0), np.bool_)
    mine = np.uint16(tag)
    empty = np.uint16(NO_FRAME)
    for r in range(r0, r1):
        for c in range(c0, c1):
            tags = frame[r, c]
            scores = score[r, c]
            found = False
            for k in range(n):
                held = tags[k] == mine
                found |= held
                scores[k] = 0 if held else scores[k]
                tags[k] = empty if held else tags[k]
            hit[r - r0, c - c0] = found
    return hit


def _batcher_network(n: int) -> npt.NDArray[np.int64]:
    """Batcher's odd-even merge sorting network for ``n`` (a power of two) inputs: the
    (low, high) index pairs to compare and exchange, in order (63 for 16)."""
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return np.array(pairs, np.int64).reshape(-1, 2)


NETWORK_SIZE = 16
_NETWORK = _batcher_network(NETWORK_SIZE)


@_compiled
def _sort_by_network(values: npt.NDArray[np.float32], count: int) -> None:
    """Sort values[:count] (count <= 16, values of length 16) in place without a branch:
    the rest is filled with +inf and the whole goes through the network, each step a
    min and a max (insertion sort mispredicted its way through a full stack)."""
    for a in range(count, NETWORK_SIZE):
        values[a] = np.inf
    for q in range(_NETWORK.shape[0]):
        low = _NETWORK[q, 0]
        high = _NETWORK[q, 1]
        x = values[low]
        y = values[high]
        values[low] = min(x, y)
        values[high] = max(x, y)


@_compiled
def _median_of(values: npt.NDArray[np.float32], count: int) -> np.float32:
    """The median of values[:count] (sorted in place, insertion sort: count <= N)."""
    for a in range(1, count):
        x = values[a]
        b = a - 1
        while b >= 0 and values[b] > x:
            values[b + 1] = values[b]
            b -= 1
        values[b + 1] = x
    low = (count - 1) // 2
    high = count // 2
    return np.float32(0.5) * (values[low] + values[high])


@_compiled
def _median_deviation(
    ordered: npt.NDArray[np.float32], count: int, median: np.float32
) -> np.float32:
    """The median of |ordered[:count] - median| for ``ordered`` sorted ascending: the
    deviations fall towards the median on its left and rise on its right, so merging the
    two runs outwards from it gives them in order without sorting them (the same values
    as sorting, ties and all)."""
    low = (count - 1) // 2
    high = count // 2
    right = 0
    while right < count and ordered[right] < median:
        right += 1
    left = right - 1
    at_low = np.float32(0.0)
    deviation = np.float32(0.0)
    for rank in range(high + 1):
        if right >= count or (left >= 0 and median - ordered[left] <= ordered[right] - median):
            deviation = abs(ordered[left] - median)
            left -= 1
        else:
            deviation = abs(ordered[right] - median)
            right += 1
        if rank == low:
            at_low = deviation
    return np.float32(0.5) * (at_low + deviation)


@_compiled
def blend(
    intensity: U8,
    score: U16,
    rows: Index,
    cols: Index,
    weight_lut: F32,
    rho: float,
    eta: float,
    top_n: int,
) -> tuple[U8, Mask]:
    """The paper's robust blend (``mapping.blend.robust_blend``, Eq. 11) of the pixels
    (rows[i], cols[i]) of a tile's candidate stacks ((rows, cols, N)): candidates at
    least ``rho`` times the best score, the ``top_n`` best of them, those within ``eta``
    MADs of their median, averaged with weights s^gamma (``weight_lut`` over quantised
    scores).
    Returns the grey values (1..255; 0 where nothing is left) and where there were."""
    n = score.shape[2]
    count_px = rows.shape[0]
    out = np.zeros(count_px, np.uint8)
    covered = np.zeros(count_px, np.bool_)
    inv_score = np.float32(1.0 / 65535.0)
    inv_value = np.float32(1.0 / 255.0)
    rho32 = np.float32(rho)
    eta32 = np.float32(eta)
    tiny = np.float32(1e-6)
    s = np.empty(n, np.float32)
    kept = np.empty(n, np.int64)
    v = np.empty(n, np.float32)
    buf = np.empty(n, np.float32)
    dev = np.empty(n, np.float32)
    for p in range(count_px):
        slots = score[rows[p], cols[p]]
        best = slots[0]
        for k in range(1, n):
            best = max(best, slots[k])
        if best == 0:
            continue
        floor = rho32 * (np.float32(best) * inv_score)
        # Which slots are kept, without a branch (a store and a count per slot): the
        # outcome of the test is random from slot to slot, which a branch mispredicts.
        m = 0
        for k in range(n):
            sk = np.float32(slots[k]) * inv_score
            s[k] = sk
            kept[m] = k
            m += (slots[k] > 0) & (sk >= floor)
        if m > top_n:
            # The top_n best scores of the kept (ties: the earlier slot first).
            for a in range(1, m):
                x = kept[a]
                b = a - 1
                while b >= 0 and s[kept[b]] < s[x]:
                    kept[b + 1] = kept[b]
                    b -= 1
                kept[b + 1] = x
            m = top_n
        values = intensity[rows[p], cols[p]]
        for a in range(m):
            v[a] = np.float32(values[kept[a]]) * inv_value
            buf[a] = v[a]
        if m > 6 and n == NETWORK_SIZE:
            _sort_by_network(buf, m)
            median = np.float32(0.5) * (buf[(m - 1) // 2] + buf[m // 2])
        else:
            median = _median_of(buf, m)
        # buf[:m] is now in order.
        for a in range(m):
            dev[a] = abs(v[a] - median)
        mad = _median_deviation(buf, m, median)
        limit = eta32 * mad
        total = 0.0
        weighted = 0.0
        for a in range(m):
            # Trimmed candidates add nothing (an exact 0: the same sums as a branch).
            keep = (dev[a] <= limit) | (mad <= tiny)
            w = np.float64(weight_lut[slots[kept[a]]]) if keep else 0.0
            total += w
            weighted += w * np.float64(v[a])
        if total > 0.0:
            blended = np.float32(weighted / total)
            level = np.rint(blended * np.float32(254.0)) + np.float32(1.0)
            if level < 1.0:
                level = np.float32(1.0)
            elif level > 255.0:
                level = np.float32(255.0)
            out[p] = np.uint8(level)
            covered[p] = True
    return out, covered


@_compiled
def tiles_near(x: F64, y: F64, t: float, margin: float) -> F64:
    """The tiles (side ``t``) within ``margin`` of the points (x[i], y[i]) and the extent
    of those near points: rows (col, row, x min, y min, x max, y max), by column then
    row. A point is near tile (col, row) where col t - margin <= x < (col + 1) t +
    margin, and the same for y; a column's rows are searched over its near points' y
    span: what ``mapping.tiles`` did with a dozen masks a column (0.28 ms a frame
    drawn)."""
    out = np.empty((0, 6), np.float64)
    if x.size == 0:
        return out
    found = []
    x_low, x_high = x.min(), x.max()
    for col in range(int(np.floor((x_low - margin) / t)), int(np.floor((x_high + margin) / t)) + 1):
        x0 = col * t
        y_low, y_high, any_in = np.inf, -np.inf, False
        for i in range(x.size):
            if x[i] >= x0 - margin and x[i] < x0 + t + margin:
                any_in = True
                y_low = min(y_low, y[i])
                y_high = max(y_high, y[i])
        if not any_in:
            continue
        for row in range(
            int(np.floor((y_low - margin) / t)), int(np.floor((y_high + margin) / t)) + 1
        ):
            y0 = row * t
            e0, n0, e1, n1, near = np.inf, np.inf, -np.inf, -np.inf, False
            for i in range(x.size):
                if (
                    x[i] >= x0 - margin
                    and x[i] < x0 + t + margin
                    and y[i] >= y0 - margin
                    and y[i] < y0 + t + margin
                ):
                    near = True
                    e0, e1 = min(e0, x[i]), max(e1, x[i])
                    n0, n1 = min(n0, y[i]), max(n1, y[i])
            if near:
                found.append((float(col), float(row), e0, n0, e1, n1))
    out = np.empty((len(found), 6), np.float64)
    for k in range(len(found)):
        for j in range(6):
            out[k, j] = found[k][j]
    return out


def warm() -> None:
    """Compile (or load from the cache) every loop on a tiny tile, so that the first
    frame does not pay it: about 2 s the first time on this machine, 0.3 s from the
    cache. The daemon calls it at start-up."""
    score = np.zeros((2, 2, 4), np.uint16)
    intensity = np.zeros((2, 2, 4), np.uint8)
    frame = np.full((2, 2, 4), NO_FRAME, np.uint16)
    ones = np.ones((2, 2), np.uint16)
    warped = np.ones((2, 2, 3), np.float32)
    any_valid(warped)
    offer_warped(score, intensity, frame, 0, 0, warped, 1)
    rest = np.zeros((2, 2), np.float32)
    offer_warped_keeping_all(
        score, intensity, frame, rest, rest.copy(), 0, 0, warped, 1, np.zeros(65536, np.bool_)
    )
    points = np.zeros(2, np.float64)
    tiles_near(points, points, 1.0, 0.1)
    # As the tiles give them: np.nonzero's views (strided, not contiguous).
    rows, cols = np.nonzero(ones > 0)
    blend(intensity, score, rows, cols, np.ones(65536, np.float32), 0.68, 2.7, 4)
    take_out(score, frame, 0, 2, 0, 2, 1)
