"""The mosaic's tiles: per-pixel blending candidates on the contract's UTM tile grid, in
bounded memory.

Each tile keeps, per pixel, the ``top_n`` best (intensity, score) candidates of the frames
that covered it (all the paper's robust blending ever uses), each tagged with the frame
that gave it, so a frame whose pose moves can be taken out and put back where it now
belongs. Intensities are stored as uint8, scores as uint16 (score x 65535; 0 = empty
slot) and tags as uint16 (frame index modulo 65535: unique among the frames that can
still move): 80 bytes a pixel, 5.2 MB for a 256 x 256 tile. How a pixel's candidates
make its value is ``BlendParams.method``'s (``mapping.blend``): the robust blend, the
plain mean of the candidates ("average"), or of those Su's threshold keeps ("su").

Hurtós's blend ("hurtos") is a weighted mean over every frame, not over N of them: a
tile then also keeps, per pixel, the sums of w and w I of the candidates the full stack
had no room for (two float32, 8 bytes more a pixel), so stack and sums together hold
every frame however many pass, still in bounded memory and in any grouping. Only frames
that can no longer move go into the sums (they cannot be taken out again); a movable
frame's candidate without room is dropped, as for the other methods.

A tile the boat has left behind (no frame for ``evict_after_s`` of survey time) may be
handed to a ``TileSpill`` — on disk in the daemon, in memory in tests — and leave
memory; when a later lane comes back over it, it is loaded again. With a memory budget
(``memory_bytes``) such idle tiles stay while all tiles fit in it, the least recently used
leaving first: the live re-solve redraws frames of the lanes behind the boat again and
again, and leaving at once, their tiles went to disk and back every few seconds (on the
two-hour hectare's first 6,000 frames: 2,390 spills of 84 tiles, 6.1 GB written; within
300 MB: 0.1 GB). Memory therefore depends on the area being worked and the budget, not
on the survey's length.

Taking a frame out cannot bring back a weaker candidate it had pushed out of a full
stack; the live map accepts that small loss, and the survey-end pass renders from scratch.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from mapping import kernels
from mapping.blend import BlendParams, su_blend, weighted_mean_blend
from mapping.grid import SonarGrid
from mapping.mosaic import (
    SonarPose,
    TileGrid,
    TileKey,
    sonar_to_utm,
    tile_box,
    warp_to_tile,
)

FloatImage = npt.NDArray[np.float32]
NO_FRAME = np.uint16(0xFFFF)
FanPoints = npt.NDArray[np.float64]


def frame_layers(image: FloatImage, score: FloatImage, mask: npt.NDArray[np.bool_]) -> FloatImage:
    """A frame as the tiles warp it: one (rows, cols, 3) stack of image, score, mask."""
    return np.dstack([image, score, mask.astype(np.float32)])


SPILL_RETRY_S = 30.0
"""Survey time after a failed spill before tiles are spilled again."""


class TileSpill(Protocol):
    """Where tiles go when they leave memory."""

    def save(self, key: TileKey, arrays: dict[str, npt.NDArray[np.generic]]) -> None: ...

    def load(self, key: TileKey) -> dict[str, npt.NDArray[np.generic]] | None: ...

    def keys(self) -> Iterable[TileKey]: ...


class MemorySpill:
    """A ``TileSpill`` that keeps spilled tiles in memory (tests, short surveys)."""

    def __init__(self) -> None:
        self._store: dict[TileKey, dict[str, npt.NDArray[np.generic]]] = {}

    def save(self, key: TileKey, arrays: dict[str, npt.NDArray[np.generic]]) -> None:
        self._store[key] = {k: v.copy() for k, v in arrays.items()}

    def load(self, key: TileKey) -> dict[str, npt.NDArray[np.generic]] | None:
        return self._store.get(key)

    def keys(self) -> Iterable[TileKey]:
        return list(self._store)


@dataclass
class Tile:
    """One tile's candidate stacks and bookkeeping. Stacks are pixel-major (rows, cols,
    N): a pixel's N slots are contiguous (32 bytes of uint16 scores), which the compiled
    loops (``mapping.kernels``) visit one pixel at a time. Slot-major (N, rows, cols)
    suited numpy's whole-plane operations, but a per-pixel loop over it touched N cache
    lines a pixel: the offering loop took 0.57 ms a call there."""

    key: TileKey
    intensity: npt.NDArray[np.uint8]
    score: npt.NDArray[np.uint16]
    frame: npt.NDArray[np.uint16]
    rest_weight: FloatImage | None = None
    """Hurtós's blend only (else None): per pixel, the summed weight of the candidates
    kept outside the stack (see the module docstring)."""
    rest_value: FloatImage | None = None
    """... and their summed weighted intensity (w I, I in 0..1)."""
    version: int = 0
    last_touch: float = 0.0
    """Survey time of the latest frame offered to the tile."""
    last_use: int = 0
    """When the tile was last used (``TileStore``'s count of uses): least recently used
    tiles leave memory first."""
    changed: npt.NDArray[np.bool_] | None = None  # pixels to render again (None: none)
    deferred: npt.NDArray[np.bool_] | None = None
    """Pixels frames drawn again changed (a re-solve's redraws): rendered with the rest
    at a slower pace (``render(..., deferred=True)``)."""
    rendered: npt.NDArray[np.uint8] | None = None  # last rendered values, 0 = no data
    boxes: dict[int, tuple[int, int, int, int]] = field(default_factory=dict)
    """Where each frame that may still move put its candidates (row0, row1, col0, col1)."""

    @classmethod
    def empty(cls, key: TileKey, size: int, n: int, keep_all: bool = False) -> Tile:
        """An empty tile; ``keep_all``: with the sums outside the stack (Hurtós)."""
        return cls(
            key,
            np.zeros((size, size, n), np.uint8),
            np.zeros((size, size, n), np.uint16),
            np.full((size, size, n), NO_FRAME, np.uint16),
            np.zeros((size, size), np.float32) if keep_all else None,
            np.zeros((size, size), np.float32) if keep_all else None,
        )

    @property
    def dirty(self) -> bool:
        return self.changed is not None or self.deferred is not None

    def mark(
        self, box: tuple[int, int, int, int], pixels: npt.NDArray[np.bool_], deferred: bool = False
    ) -> None:
        """Note that ``pixels`` (a mask over ``box``) changed and need rendering."""
        if not pixels.any():
            return
        r0, r1, c0, c1 = box
        if deferred:
            if self.deferred is None:
                self.deferred = np.zeros(self.score.shape[:2], bool)
            self.deferred[r0:r1, c0:c1] |= pixels
            return
        if self.changed is None:
            self.changed = np.zeros(self.score.shape[:2], bool)
        self.changed[r0:r1, c0:c1] |= pixels

    @property
    def nbytes(self) -> int:
        extra = 0 if self.rendered is None else self.rendered.nbytes
        for rest in (self.rest_weight, self.rest_value):
            extra += 0 if rest is None else rest.nbytes
        return self.intensity.nbytes + self.score.nbytes + self.frame.nbytes + extra


@dataclass(frozen=True, slots=True)
class TileImage:
    """A rendered tile: grey values 1..255 with 0 = no data, and its version."""

    key: TileKey
    values: npt.NDArray[np.uint8]
    version: int


class TileStore:
    """The live mosaic: tiles created, updated, rendered, spilled and reloaded on demand."""

    def __init__(
        self,
        tiles: TileGrid,
        params: BlendParams | None = None,
        spill: TileSpill | None = None,
        evict_after_s: float = 20.0,
        memory_bytes: int | None = None,
    ) -> None:
        self.grid = tiles
        self.params = params or BlendParams()
        self.spill: TileSpill = spill or MemorySpill()
        self.evict_after_s = evict_after_s
        self.memory_bytes = memory_bytes
        """Idle tiles stay in memory while the tiles take no more than this (None: idle
        tiles leave at once)."""
        self.spill_failures = 0
        self.spill_error: str | None = None
        """Why the latest spill failed (a full disk, say; None once one succeeds): the
        tile stayed in memory."""
        self._spill_retry_at = -math.inf
        self._uses = 0
        self.active: dict[TileKey, Tile] = {}
        self.versions: dict[TileKey, int] = {}
        self.spilled = 0
        self.reloaded = 0
        self._fan_samples: dict[int, tuple[npt.NDArray[np.bool_], FanPoints, float]] = {}
        self.movable: set[int] = set()
        """Frames that may still be taken out (inserted and not settled)."""
        self.keep_all = self.params.method == "hurtos"
        """Every frame counts (Hurtós): tiles keep the sums outside the stacks."""
        self._movable_tags = np.zeros(0x10000, bool)
        """``movable`` by tag, for the compiled offering loop (Hurtós)."""
        # s^gamma for every quantised score.
        levels = np.arange(65536, dtype=np.float64) / 65535.0
        self._weight_lut = (levels**self.params.gamma).astype(np.float32)

    # -- tiles in and out of memory -------------------------------------------------
    def tile(self, key: TileKey) -> Tile:
        self._uses += 1
        tile = self.active.get(key)
        if tile is not None:
            tile.last_use = self._uses
            return tile
        stored = self.spill.load(key)
        if stored is None:
            tile = Tile.empty(key, self.grid.tile_px, self.params.top_n, self.keep_all)
        else:
            tile = Tile(
                key,
                np.asarray(stored["intensity"], np.uint8),
                np.asarray(stored["score"], np.uint16),
                np.asarray(stored["frame"], np.uint16),
                rendered=np.asarray(stored["rendered"], np.uint8),
            )
            if self.keep_all:
                tile.rest_weight = np.asarray(stored["rest_weight"], np.float32)
                tile.rest_value = np.asarray(stored["rest_value"], np.float32)
            boxes = stored.get("boxes")
            if boxes is not None:
                tile.boxes = {
                    int(r[0]): (int(r[1]), int(r[2]), int(r[3]), int(r[4]))
                    for r in np.asarray(boxes).tolist()
                    if int(r[0]) in self.movable
                }
            self.reloaded += 1
        tile.version = self.versions.get(key, 0)
        tile.last_use = self._uses
        self.active[key] = tile
        return tile

    def evict_idle(self, now: float, keep: set[TileKey] | None = None) -> list[TileImage]:
        """Spill the tiles no frame has touched for ``evict_after_s`` (rendering them one
        last time if they changed), the least recently used first and, with a
        ``memory_bytes`` budget, only while the tiles in memory take more; returns those
        final renders."""
        out: list[TileImage] = []
        if now < self._spill_retry_at:
            return out
        idle = [
            t
            for k, t in self.active.items()
            if now - t.last_touch > self.evict_after_s and (keep is None or k not in keep)
        ]
        if not idle:
            return out
        idle.sort(key=lambda t: t.last_use)
        held = self.nbytes
        for tile in idle:
            if self.memory_bytes is not None and held <= self.memory_bytes:
                break
            key = tile.key
            held -= tile.nbytes
            if tile.dirty or tile.rendered is None:
                out.append(self.render(key))
            assert tile.rendered is not None
            arrays: dict[str, npt.NDArray[np.generic]] = {
                "intensity": tile.intensity,
                "score": tile.score,
                "frame": tile.frame,
                "rendered": tile.rendered,
            }
            if tile.rest_weight is not None and tile.rest_value is not None:
                arrays["rest_weight"] = tile.rest_weight
                arrays["rest_value"] = tile.rest_value
            moving = [(k, *box) for k, box in tile.boxes.items() if k in self.movable]
            if moving:
                # Frames that may still move (the live re-solve) keep where they went.
                arrays["boxes"] = np.array(moving, np.int64).reshape(-1, 5)
            try:
                self.spill.save(key, arrays)
            except OSError as exc:
                # The disk is full (say): tiles stay in memory and the map goes on; the
                # spill is tried again SPILL_RETRY_S later.
                self.spill_failures += 1
                self.spill_error = f"{exc.strerror or exc}"
                self._spill_retry_at = now + SPILL_RETRY_S
                break
            self.spill_error = None
            del self.active[key]
            self.spilled += 1
        return out

    @property
    def nbytes(self) -> int:
        return sum(t.nbytes for t in self.active.values())

    # -- frames in and out ----------------------------------------------------------
    def _boxes(
        self, grid: SonarGrid, mask: npt.NDArray[np.bool_], pose: SonarPose
    ) -> dict[TileKey, tuple[int, int, int, int]]:
        """For each tile the fan reaches, the box of its pixels the fan can cover: from a
        sparse sample of the fan's pixels, so a fan seen at 45 degrees does not drag in
        the whole square around it."""
        samples = self._fan_samples.get(id(mask))
        if samples is None or samples[0] is not mask:
            step = 6
            rows, cols = np.nonzero(mask[::step, ::step])
            points = np.vstack([cols * step, rows * step, np.ones_like(rows)]).astype(float)
            samples = (mask, grid.pixel_to_metric() @ points, step * grid.res_m)
            self._fan_samples = {id(mask): samples}
        _, metric, spacing = samples
        world = sonar_to_utm(pose) @ metric
        t = self.grid.tile_m
        margin = spacing + 2 * self.grid.res_m
        boxes: dict[TileKey, tuple[int, int, int, int]] = {}
        # Each tile within a margin of a sample, and the samples' extent near it.
        for col, row, e0, n0, e1, n1 in kernels.tiles_near(world[0], world[1], t, margin):
            key = (int(col), int(row))
            box = tile_box(self.grid, key, (e0 - margin, n0 - margin, e1 + margin, n1 + margin))
            if box is not None:
                boxes[key] = box
        return boxes

    def insert(
        self,
        frame_index: int,
        image: FloatImage,
        score: FloatImage,
        mask: npt.NDArray[np.bool_],
        grid: SonarGrid,
        pose: SonarPose,
        time: float,
        movable: bool = True,
    ) -> list[TileKey]:
        """Offer one frame's pixels at ``pose`` to the tiles it covers; ``movable``: it
        may be taken out again (``remove``) until it is settled."""
        layers = frame_layers(image, score, mask)
        return self.insert_layers(frame_index, layers, mask, grid, pose, time, movable)

    def insert_layers(
        self,
        frame_index: int,
        layers: FloatImage,
        mask: npt.NDArray[np.bool_],
        grid: SonarGrid,
        pose: SonarPose,
        time: float,
        movable: bool = True,
        deferred: bool = False,
    ) -> list[TileKey]:
        """``insert`` with the frame as one (rows, cols, 3) stack: image, score, mask;
        ``deferred``: what it changes is rendered at the slower pace (a redraw)."""
        tag = np.uint16(frame_index % 0xFFFF)
        if movable:
            self.movable.add(frame_index)
            self._movable_tags[tag] = True
        touched = []
        for key, box in self._boxes(grid, mask, pose).items():
            warped = warp_to_tile(layers, grid, pose, self.grid, key, box)
            if not kernels.any_valid(warped):
                continue
            tile = self.tile(key)
            r0, _, c0, _ = box
            # Only pixels wholly inside the fan (interpolation across the fan's edge would
            # mix in the zeros outside it); each improved pixel's candidate goes into its
            # first slot holding the weakest one.
            if tile.rest_weight is not None and tile.rest_value is not None:
                better = kernels.offer_warped_keeping_all(
                    tile.score, tile.intensity, tile.frame, tile.rest_weight,
                    tile.rest_value, r0, c0, warped, int(tag), self._movable_tags,
                )  # fmt: skip
            else:
                better = kernels.offer_warped(
                    tile.score, tile.intensity, tile.frame, r0, c0, warped, int(tag)
                )
            tile.mark(box, better, deferred)
            if movable:
                tile.boxes[frame_index] = box
            tile.last_touch = max(tile.last_touch, time)
            touched.append(key)
        return touched

    def remove(self, frame_index: int, keys: Iterable[TileKey], deferred: bool = False) -> None:
        """Take a frame's candidates out of the given tiles (``deferred``: see
        ``insert_layers``)."""
        tag = np.uint16(frame_index % 0xFFFF)
        for key in keys:
            tile = self.tile(key)
            box = tile.boxes.pop(frame_index, None)
            if box is None:
                continue
            r0, r1, c0, c1 = box
            # A slot is empty where its score is 0: its intensity is never read.
            hit = kernels.take_out(tile.score, tile.frame, r0, r1, c0, c1, int(tag))
            tile.mark(box, hit, deferred)

    def settle(self, frame_index: int, keys: Iterable[TileKey]) -> None:
        """A frame will not move again: forget where it went (in a spilled tile, when it
        is next loaded)."""
        self.movable.discard(frame_index)
        self._movable_tags[frame_index % 0xFFFF] = False
        for key in keys:
            tile = self.active.get(key)
            if tile is not None:
                tile.boxes.pop(frame_index, None)

    # -- rendering ------------------------------------------------------------------
    def render(self, key: TileKey, new_only: bool = False, deferred: bool = True) -> TileImage:
        """Blend the tile's changed pixels; the version grows with each render.

        new_only: render just the changed pixels that had no data yet (new coverage, which
        must show at once), leaving refinements of covered pixels for a full render.
        deferred: render the pixels redraws changed too (not with ``new_only``).
        """
        tile = self.active.get(key)  # rendering is not a use (``Tile.last_use``)
        if tile is None:
            tile = self.tile(key)
        size = self.grid.tile_px
        keep_changed: npt.NDArray[np.bool_] | None = None
        deferred = deferred and not new_only
        if tile.rendered is None:
            tile.rendered = np.zeros((size, size), np.uint8)
            held = (tile.score > 0).any(axis=2)
            if tile.rest_weight is not None:
                held |= tile.rest_weight > 0
            rows, cols = np.nonzero(held)
            tile.deferred = None
        elif tile.changed is not None or (deferred and tile.deferred is not None):
            todo = tile.changed if tile.changed is not None else np.zeros((size, size), bool)
            if new_only:
                todo = todo & (tile.rendered == 0)
                keep_changed = tile.changed & ~todo
            if deferred and tile.deferred is not None:
                todo = todo | tile.deferred
                tile.deferred = None
            rows, cols = np.nonzero(todo)
        else:
            rows = cols = np.zeros(0, np.intp)
        if rows.size:
            tile.rendered[rows, cols] = self._blend(tile, rows, cols)
        tile.changed = keep_changed if keep_changed is not None and keep_changed.any() else None
        tile.version += 1
        self.versions[key] = tile.version
        return TileImage(key, tile.rendered.copy(), tile.version)

    def _blend(
        self, tile: Tile, rows: npt.NDArray[np.intp], cols: npt.NDArray[np.intp]
    ) -> npt.NDArray[np.uint8]:
        """Grey values (1..255, 0 = no data) of the tile's pixels (rows[i], cols[i]) by
        ``BlendParams.method``."""
        p = self.params
        if p.method == "robust":
            values, _ = kernels.blend(
                tile.intensity, tile.score, rows, cols, self._weight_lut, p.rho, p.eta, p.top_n
            )
            return values
        # The candidate lists (pixels, N) of just the pixels to render.
        intensity = tile.intensity[rows, cols].astype(np.float32) * np.float32(1 / 255)
        score = tile.score[rows, cols].astype(np.float32) * np.float32(1 / 65535)
        if p.method == "average":
            present = score > 0
            count = present.sum(axis=-1)
            covered = count > 0
            blended = np.where(
                covered, (intensity * present).sum(axis=-1) / np.maximum(count, 1), 0.0
            ).astype(np.float32)
        elif p.method == "su":
            blended, covered = su_blend(intensity, score, p)
        else:  # "hurtos": the score is the weight
            rest_weight = rest_value = None
            if tile.rest_weight is not None and tile.rest_value is not None:
                rest_weight, rest_value = tile.rest_weight[rows, cols], tile.rest_value[rows, cols]
            blended, covered = weighted_mean_blend(intensity, score, rest_weight, rest_value)
        values = np.clip(np.rint(blended * 254.0) + 1.0, 1, 255).astype(np.uint8)
        values[~covered] = 0
        return values

    def render_dirty(self, new_only: bool = False, deferred: bool = True) -> list[TileImage]:
        """Render every changed tile (``new_only``: only where coverage is new, and only
        tiles that have some; ``deferred``: the pixels redraws changed too)."""
        out = []
        for key, tile in list(self.active.items()):
            redrawn = deferred and not new_only and tile.deferred is not None
            if tile.changed is None and not redrawn:
                continue
            changed, rendered = tile.changed, tile.rendered
            if (
                new_only
                and changed is not None
                and rendered is not None
                and not (changed & (rendered == 0)).any()
            ):
                continue
            out.append(self.render(key, new_only, deferred))
        return out

    def all_keys(self) -> list[TileKey]:
        return sorted(set(self.active) | set(self.spill.keys()))

    def rendered_tiles(self) -> Iterator[TileImage]:
        """Every tile's latest rendering, active or spilled (rendering what changed)."""
        for key in self.all_keys():
            tile = self.active.get(key)
            if tile is not None:
                yield (
                    self.render(key)
                    if tile.dirty or tile.rendered is None
                    else TileImage(key, tile.rendered.copy(), tile.version)
                )
                continue
            stored = self.spill.load(key)
            if stored is not None:
                yield TileImage(
                    key, np.asarray(stored["rendered"], np.uint8), self.versions.get(key, 0)
                )
