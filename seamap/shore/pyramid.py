"""A survey's overview pyramid for the live map page: its tiles merged at coarser zooms.

Level 0 is the tiles as the boat published them (the contract's grid: tile (col, row)
covers easting [col*T, (col+1)*T) and northing [row*T, (row+1)*T)). Level L's tile
(col, row) covers the 2^L x 2^L level-0 tiles (col*2^L .., row*2^L ..), at the same
``size_px`` and 2^L times the pixel size: each of its pixels is the mean of the valid
pixels (alpha > 0) of the 2 x 2 block of its children below it, weighted by their alpha,
and its alpha the block's mean alpha (rounded up, so a pixel with any data keeps some).
A page then draws the whole of a hectare from a few dozen tiles instead of hundreds.

Built lazily and incrementally: ``put`` (a new or newer level-0 tile) adds the version
step to the ``stamp`` of each of the tile's ancestors, so an ancestor whose built PNG
carries an older stamp is stale, and ``tile`` rebuilds it (and its stale descendants, only
those) when asked. The stamp of a level-L tile is the sum of (version + 1) over the
level-0 tiles under it: it grows whenever any of them is added or republished, so the page
computes the same stamp from the tiles it knows and names it in the URL (``?v=``).

``put`` runs on the page server's loop and only adds numbers; ``tile`` runs on worker
threads. One lock guards the maps; PNG decoding, merging and encoding happen outside it.
Memory: the built PNGs of levels 1 and up, at most a third of the tiles' count.
"""

from __future__ import annotations

import io
import threading

import numpy as np
import numpy.typing as npt
from PIL import Image

MAX_LEVEL = 10
"""Coarsest level: 2^10 level-0 tiles a side (5.2 km at the live 256 px x 2 cm)."""
OVERVIEW_PNG_LEVEL = 1
"""zlib level of the built tiles: fast to make, a few per cent larger than level 6."""

Key = tuple[int, int]
GreyAlpha = npt.NDArray[np.uint8]
"""size x size x 2: grey, alpha (0 = no data), north-up."""


def parent_key(col: int, row: int, levels: int = 1) -> Key:
    """The key ``levels`` levels up of tile (col, row) (floor division, negatives too)."""
    return col >> levels, row >> levels


def decode_grey_alpha(png: bytes) -> GreyAlpha:
    """A grey + alpha PNG as size x size x 2 uint8; ValueError if it is not one."""
    with Image.open(io.BytesIO(png)) as image:
        if image.mode != "LA":
            raise ValueError(f"not a grey + alpha PNG (mode {image.mode})")
        return np.asarray(image, dtype=np.uint8)


def encode_grey_alpha(tile: GreyAlpha) -> bytes:
    out = io.BytesIO()
    Image.fromarray(tile, mode="LA").save(out, format="PNG", compress_level=OVERVIEW_PNG_LEVEL)
    return out.getvalue()


def _block_sums(values: npt.NDArray[np.uint32]) -> npt.NDArray[np.uint32]:
    """The sum of each 2 x 2 block."""
    return values[0::2, 0::2] + values[1::2, 0::2] + values[0::2, 1::2] + values[1::2, 1::2]


def merge_children(children: dict[Key, GreyAlpha], size_px: int) -> GreyAlpha:
    """One tile of the level above from its (up to four) children, keyed by their
    (dx, dy) offset: dx 0 west, 1 east; dy 0 south, 1 north (rows grow northward, the
    image is north-up). Each 2 x 2 block of a child becomes one pixel: grey the
    alpha-weighted mean of the block's grey (no-data pixels weigh nothing), alpha the
    block's mean alpha rounded up. Absent children leave their quarter without data."""
    half = size_px // 2
    out = np.zeros((size_px, size_px, 2), np.uint8)
    for (dx, dy), child in children.items():
        alpha = child[:, :, 1].astype(np.uint32)
        weighted = child[:, :, 0] * alpha
        # Sums over each 2 x 2 block, in integers (exact).
        alpha_sum = _block_sums(alpha)
        grey_sum = _block_sums(weighted)
        mean = (grey_sum + alpha_sum // 2) // np.maximum(alpha_sum, 1)  # rounded
        y0, x0 = (0 if dy else half), (half if dx else 0)
        quarter = out[y0 : y0 + half, x0 : x0 + half]
        quarter[:, :, 0] = mean
        quarter[:, :, 1] = (alpha_sum + 3) // 4  # rounded up: any data keeps some alpha
    return out


class Pyramid:
    """One survey's levels 1..``MAX_LEVEL`` over its level-0 PNGs. ``put`` each level-0
    tile as it is held; ``stamp`` and ``tile`` read any level (0 included)."""

    def __init__(self, size_px: int) -> None:
        self.size_px = size_px
        self._lock = threading.Lock()
        self._level0: dict[Key, tuple[int, bytes]] = {}
        """By key: version, PNG as received."""
        self._stamps: list[dict[Key, int]] = [{} for _ in range(MAX_LEVEL + 1)]
        self._built: list[dict[Key, tuple[int, bytes]]] = [{} for _ in range(MAX_LEVEL + 1)]
        """By level (1 up), by key: the stamp it was built at, its PNG."""
        self.builds = 0
        """Tiles of levels 1 and up built so far."""

    def top_level(self) -> int:
        """The finest level at which the survey lies within a 2 x 2 of tiles: the
        coarsest a page showing it whole is likely to ask for."""
        with self._lock:
            for level in range(1, MAX_LEVEL + 1):
                if len(self._stamps[level]) <= 4:
                    return level
        return MAX_LEVEL

    def warm(self) -> int:
        """Build every stale tile of levels 1 to ``top_level``, finest first (so each
        level is made from fresh children); how many were built."""
        built = 0
        for level in range(1, self.top_level() + 1):
            with self._lock:
                stale = [
                    key
                    for key, stamp in self._stamps[level].items()
                    if self._built[level].get(key, (None,))[0] != stamp
                ]
            for key in stale:
                self.tile(level, *key)
                built += 1
        return built

    def put(self, col: int, row: int, version: int, png: bytes) -> None:
        """Hold a level-0 tile (newer than the one held: the caller checks) and mark its
        ancestors stale."""
        with self._lock:
            held = self._level0.get((col, row))
            if held is not None and version <= held[0]:
                return
            step = version - (held[0] if held is not None else -1)
            self._level0[(col, row)] = (version, png)
            self._stamps[0][(col, row)] = version + 1
            for level in range(1, MAX_LEVEL + 1):
                key = parent_key(col, row, level)
                stamps = self._stamps[level]
                stamps[key] = stamps.get(key, 0) + step

    def stamp(self, level: int, col: int, row: int) -> int | None:
        """The tile's stamp: the sum of (version + 1) of the level-0 tiles under it;
        None when it has none."""
        if not 0 <= level <= MAX_LEVEL:
            return None
        with self._lock:
            return self._stamps[level].get((col, row))

    def tile(self, level: int, col: int, row: int) -> tuple[int, bytes] | None:
        """The tile's (stamp, PNG), built now if stale (level 0: its version + 1 and the
        PNG as received); None where no level-0 tile lies under it."""
        if not 0 <= level <= MAX_LEVEL:
            return None
        key = (col, row)
        with self._lock:
            stamp = self._stamps[level].get(key)
            if stamp is None:
                return None
            if level == 0:
                return stamp, self._level0[key][1]
            built = self._built[level].get(key)
        if built is not None and built[0] == stamp:
            return built
        children: dict[Key, GreyAlpha] = {}
        for dx in (0, 1):
            for dy in (0, 1):
                child = self.tile(level - 1, 2 * col + dx, 2 * row + dy)
                if child is None:
                    continue
                try:
                    pixels = decode_grey_alpha(child[1])
                except (ValueError, OSError):
                    continue  # the station held it; a tile it cannot read stays blank
                if pixels.shape == (self.size_px, self.size_px, 2):
                    children[(dx, dy)] = pixels
        # Built from children at least as new as ``stamp`` says: if one came meanwhile,
        # the page asks with the newer stamp and it is built again.
        png = encode_grey_alpha(merge_children(children, self.size_px))
        with self._lock:
            self._built[level][key] = (stamp, png)
            self.builds += 1
        return stamp, png


__all__ = [
    "MAX_LEVEL",
    "Pyramid",
    "decode_grey_alpha",
    "encode_grey_alpha",
    "merge_children",
    "parent_key",
]
