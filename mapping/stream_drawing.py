"""The streaming engine's drawn map: frames blended into the tiles at their poses, taken out
and put back when their poses move, and the tiles rendered and let go.

A new frame is blended at once where the chain puts it (``draw``) and kept, while it is in
the live window, with what blending it again needs (``LiveImage``). When the window is
solved, a live frame whose fan moved further than a threshold is taken out of its tiles
and blended again (``reblend``). A final frame that a live re-solve moved waits in the
redraw queue and is drawn again from its kept image (``mapping.live_resolve.Drawn``) within
the redraw budget as the pings come (``redraw``). Tiles are rendered at most every
``render_every_s`` of survey time (new coverage), ``refine_every_s`` (refinements) and
``redraw_render_every_s`` (what redraws changed); tiles idle for ``evict_after_s`` leave
memory (``mapping.tiles.TileStore``). Each render comes out with the frames whose pixels
reached the tile since its last one (``RenderedTile``), for the engine to publish.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Container, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from mapping.blend import FrameScorer
from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from mapping.grid import SonarGrid
from mapping.live_resolve import Drawn
from mapping.mosaic import SonarPose, TileGrid, TileKey
from mapping.preprocess import SonarFrame
from mapping.se2 import turn
from mapping.tiles import TileImage, TileSpill, TileStore, frame_layers

if TYPE_CHECKING:
    from mapping.stream_params import StreamingParams

Array = npt.NDArray[np.float64]

MOST_REDRAWS = 3.0
"""Frames drawn again with one new frame, at most."""


@dataclass
class LiveImage:
    """A frame still in the window: what re-blending it needs."""

    index: int
    time: float
    layers: npt.NDArray[np.float32]  # (rows, cols, 3): image, score, mask
    mask: npt.NDArray[np.bool_]
    grid: SonarGrid
    tiles: list[TileKey]
    blended_pose: Array  # sonar (x, y, yaw) it was blended at

    @property
    def image(self) -> npt.NDArray[np.float32]:
        """Its blending image (a view of the first layer)."""
        return self.layers[..., 0]


@dataclass(frozen=True, slots=True)
class RenderedTile:
    """A tile rendered (or rendered one last time as it left memory), and the frames whose
    pixels reached it since its previous render (for latency)."""

    image: TileImage
    frames: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class Redraw:
    """A final frame drawn again where a re-solve put it, and how long (survey time) it
    waited in the queue for that."""

    index: int
    wait_s: float


@dataclass(frozen=True, slots=True)
class RedrawPass:
    """What one turn of the redraw queue did: the frames drawn again, and the tiles that
    left memory meanwhile (rendered one last time)."""

    redrawn: list[Redraw]
    rendered: list[RenderedTile]


def drawn_layers(scorer: FrameScorer, frame: SonarFrame) -> npt.NDArray[np.float32]:
    """A preprocessed frame as the tiles draw it: its image, its blending score
    (``scorer``, ``mapping.blend``) and its mask, one (rows, cols, 3) stack."""
    score = scorer(frame.image, frame.mask, frame.weight, frame.fan_weight)
    return frame_layers(frame.image, score, frame.mask)


def fan_moved(sonar: Array, was: Array) -> float:
    """How far a fan moved from sonar pose ``was`` to ``sonar`` (x, y, yaw): its apex,
    plus a yaw error turning the far edge of the fan (5 m away) the most."""
    moved = math.hypot(sonar[0] - was[0], sonar[1] - was[1])
    moved += 5.0 * abs(turn(sonar[2] - was[2]))
    return moved


class LiveDrawing:
    """See the module docstring. The local frame (``frame``) places the tiles on the UTM
    grid; it is the navigation's, known before any frame is drawn."""

    def __init__(
        self, mount: SonarMount, params: StreamingParams, spill: TileSpill | None = None
    ) -> None:
        self.mount = mount
        self.params = params
        p = params.pipeline
        memory = None if params.tile_memory_mb is None else int(params.tile_memory_mb * 2**20)
        blend = p.blend
        if params.live_candidates is not None:
            blend = replace(blend, top_n=params.live_candidates)
        self.tiles = TileStore(
            TileGrid(p.mosaic_res_m, p.tile_px), blend, spill, params.evict_after_s, memory
        )
        self.live: dict[int, LiveImage] = {}
        """The frames in the live window, with what blending them again needs."""
        self._pending_frames: dict[TileKey, list[int]] = {}
        self._last_render = -math.inf
        self._last_refine = -math.inf
        self._last_redrawn_render = -math.inf
        self.to_redraw: dict[int, Array] = {}
        """Frames re-solves moved that are still to be drawn again, and their poses."""
        self._queued_at: dict[int, float] = {}
        self._redraw_credit = 0.0
        self._redraw_cursor = -1
        """The frame last drawn again: the queue is swept from the oldest frame on, from
        just after this one."""
        self._redraw_recent: deque[list[TileKey]] = deque(maxlen=10)
        """The tiles of the last redraws: kept in memory while redraws go on."""

    # -- frames in the window ----------------------------------------------------------------
    def draw(
        self,
        index: int,
        time: float,
        layers: npt.NDArray[np.float32],
        mask: npt.NDArray[np.bool_],
        grid: SonarGrid,
        sonar: Array,
        local: LocalFrame | None,
    ) -> None:
        """Blend a new frame (``drawn_layers``, its ``mask``) at once at sonar pose
        ``sonar`` (local), and keep it live."""
        touched = self._insert(index, layers, mask, grid, sonar, time, local)
        self.live[index] = LiveImage(index, time, layers, mask, grid, touched, sonar)

    def reblend(
        self, poses: Sequence[Array], leaving: Container[int], local: LocalFrame | None
    ) -> list[int]:
        """Blend again the live frames whose fan at their pose (``poses[k]``) moved from
        where they were blended: by more than ``move_threshold_m`` for those ``leaving``
        the window (their pose becomes final), ``live_move_threshold_m`` for the others.
        Returns the frames blended again, in order."""
        moved = []
        for k in list(self.live):
            threshold = (
                self.params.move_threshold_m if k in leaving else self.params.live_move_threshold_m
            )
            if self._reblend_if_moved(k, poses[k], threshold, local):
                moved.append(k)
        return moved

    def _reblend_if_moved(
        self, k: int, pose: Array, threshold: float, local: LocalFrame | None
    ) -> bool:
        live = self.live[k]
        sonar = self.mount.sonar_pose(pose)
        if fan_moved(sonar, live.blended_pose) <= threshold:
            return False
        self.tiles.remove(k, live.tiles)
        live.tiles = self._insert(k, live.layers, live.mask, live.grid, sonar, live.time, local)
        live.blended_pose = sonar
        return True

    def take_live(self, k: int) -> LiveImage | None:
        """Frame ``k`` leaves the window: what was kept of it live."""
        return self.live.pop(k, None)

    def settle(self, k: int, tiles: list[TileKey]) -> None:
        """Frame ``k`` will not be drawn again: its tiles forget where it went."""
        self.tiles.settle(k, tiles)

    # -- final frames drawn again ------------------------------------------------------------
    def queue_redraw(self, k: int, pose: Array, now: float) -> None:
        """A re-solve moved final frame ``k`` to ``pose`` at survey time ``now``: it is
        drawn again there as the redraw budget allows (or at its newer pose, should a later
        re-solve move it again first)."""
        self.to_redraw[k] = pose
        self._queued_at.setdefault(k, now)

    def let_go(self, old: Drawn, now: float, local: LocalFrame | None) -> Redraw | None:
        """Frame ``old``'s image goes (``LiveResolver.keep`` made room): drawn at its pose
        now if it was waiting, on the redraw budget's account (at 10 Hz, 487 of 835
        frames let go were still waiting: 2.3 ms a frame beyond the budget); its tiles
        forget it."""
        pose = self.to_redraw.pop(old.index, None)
        redrawn = None
        if pose is not None:
            redrawn = self.redraw_one(old, pose, now, local)
            self._redraw_credit -= 1.0
        self.tiles.settle(old.index, old.tiles)
        return redrawn

    def redraw(
        self,
        now: float,
        credit: float,
        drawn: Mapping[int, Drawn],
        local: LocalFrame | None,
        everything: bool = False,
    ) -> RedrawPass | None:
        """Draw again frames re-solves moved: ``credit`` more of them (a new frame's
        ``resolve.redraws_per_frame``; what is left over carries to the next frame, up
        to three), or all of them with ``everything``. ``drawn``: the frames whose images
        are kept (``LiveResolver.drawn``); one let go meanwhile is not drawn again. None
        when none was waiting.

        The queue is swept along the track, from the oldest frame to the newest and round
        again: consecutive redraws use the same tiles (drawn in order of how far they
        moved, a redraw loaded tiles from all over the stretch: 21 tiles in memory at
        once where 16 sufficed), no frame waits more than a sweep while new re-solves
        queue others, and the oldest, whose images go first (``resolve.memory_mb``), are
        drawn before they must be at once (newest first, those let go while waiting
        were 3 ms a frame at 10 Hz beyond the budget)."""
        if not self.to_redraw:
            self._redraw_credit = 0.0
            return None
        self._redraw_credit = min(self._redraw_credit + credit, MOST_REDRAWS)
        recent = self._redraw_recent
        queue = self.to_redraw
        done = RedrawPass([], [])
        while queue and (everything or self._redraw_credit >= 1.0):
            cursor = self._redraw_cursor
            k = min((j for j in queue if j > cursor), default=-1)
            if k < 0:
                k = min(queue)
            self._redraw_cursor = k
            pose = queue.pop(k)
            self._redraw_credit -= 1.0
            frame = drawn.get(k)
            if frame is None:
                self._queued_at.pop(k, None)
                continue
            done.redrawn.append(self.redraw_one(frame, pose, now, local))
            recent.append(frame.tiles)
            if len(self.tiles.active) > self.params.resolve_tiles_in_memory:
                # Tiles of a stretch the boat has left were loaded to be redrawn: they
                # leave memory again as the redraw moves on (memory follows the area),
                # but not those the last few redraws used (``evict``: the next ones use
                # them too).
                done.rendered.extend(self.evict(now))
        if not queue:
            self._redraw_credit = 0.0
            recent.clear()
        return done

    def redraw_one(self, drawn: Drawn, pose: Array, now: float, local: LocalFrame | None) -> Redraw:
        """Take final frame ``drawn`` out of its tiles and draw it again at ``pose``."""
        k = drawn.index
        wait = max(now - self._queued_at.pop(k, now), 0.0)
        sonar = self.mount.sonar_pose(pose)
        self.tiles.remove(k, drawn.tiles, deferred=True)
        layers, mask = drawn.layers()
        drawn.tiles = self._insert(
            k, layers, mask, drawn.grid, sonar, drawn.time, local, deferred=True
        )
        drawn.blended_sonar = sonar
        return Redraw(k, wait)

    def _insert(
        self,
        index: int,
        layers: npt.NDArray[np.float32],
        mask: npt.NDArray[np.bool_],
        grid: SonarGrid,
        sonar: Array,
        time: float,
        local: LocalFrame | None,
        deferred: bool = False,
    ) -> list[TileKey]:
        """Offer a frame (its stack of image, score and mask) to the tiles at sonar pose
        ``sonar`` (local); ``deferred``: a redraw (rendered at ``redraw_render_every_s``)."""
        assert local is not None
        east, north = local.to_utm(sonar[0], sonar[1])
        pose = SonarPose(float(east), float(north), float(sonar[2]))
        touched = self.tiles.insert_layers(index, layers, mask, grid, pose, time, deferred=deferred)
        for key in touched:
            self._pending_frames.setdefault(key, []).append(index)
        return touched

    # -- tiles out ---------------------------------------------------------------------------
    def render(self, now: float, force: bool) -> list[RenderedTile] | None:
        """Render what changed, as often as the ``render_every_s``, ``refine_every_s`` and
        ``redraw_render_every_s`` paces allow at survey time ``now`` (``force``: all of
        it now), and let idle tiles go; None when no render was due."""
        if not force and now - self._last_render < self.params.render_every_s:
            return None
        self._last_render = now
        full = force or now - self._last_refine >= self.params.refine_every_s
        if full:
            self._last_refine = now
        redrawn = force or now - self._last_redrawn_render >= self.params.redraw_render_every_s
        if redrawn and full:
            self._last_redrawn_render = now
        out = [
            self.rendered(image)
            for image in self.tiles.render_dirty(new_only=not full, deferred=redrawn)
        ]
        out.extend(self.evict(now))
        return out

    def evict(self, now: float) -> list[RenderedTile]:
        """Let tiles idle at survey time ``now`` leave memory (``TileStore.evict_idle``),
        but those of the live frames and of the last redraws (the next ones use them)."""
        keep = {key for live in self.live.values() for key in live.tiles}
        # Tiles the last redraws loaded stay while redraws go on (the next ones use them).
        keep.update(key for tiles in self._redraw_recent for key in tiles)
        return [self.rendered(image) for image in self.tiles.evict_idle(now, keep)]

    def rendered(self, image: TileImage) -> RenderedTile:
        """A render of a tile, with the frames that reached it since the previous one."""
        return RenderedTile(image, tuple(self._pending_frames.pop(image.key, ())))
