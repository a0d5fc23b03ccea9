"""The drawn map (``mapping.stream_drawing``): frames of a synthetic seabed (``synth``)
blended into the tiles and rendered at the renders' pace with the frames that reached
each tile, blended again only when their fan moved enough, final frames drawn again
within the redraw budget along the track, and idle tiles let go."""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import numpy.typing as npt
import pytest

from mapping.blend import BlendParams, make_scorer
from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from mapping.grid import SonarGrid
from mapping.live_resolve import Drawn, pack
from mapping.preprocess import SonarFrame
from mapping.stream_drawing import LiveDrawing, RenderedTile, drawn_layers, fan_moved
from mapping.streaming import StreamingParams
from tests.mapping import synth

Array = npt.NDArray[np.float64]
MOUNT = SonarMount()
LOCAL = LocalFrame.around(38.3, -76.5)  # the local frame: (x, y) on the synthetic seabed
SCORER = make_scorer(BlendParams())


@functools.cache
def _scene() -> tuple[npt.NDArray[np.float32], SonarGrid, npt.NDArray[np.bool_]]:
    """A 16 m textured seabed at 1 cm, and the sonar's fan on its grid."""
    grid, mask = synth.fan(0.02)
    return synth.seabed(np.random.default_rng(4)), grid, mask


def _frame(pose: Array) -> SonarFrame:
    """The sonar's frame with the vehicle at ``pose`` (x, y on the seabed, heading)."""
    world, grid, mask = _scene()
    sonar = MOUNT.sonar_pose(pose)
    image = synth.view(world, grid, mask, float(sonar[0]), float(sonar[1]), float(sonar[2]))
    weight = mask.astype(np.float32)
    return SonarFrame(image, mask, weight, image, weight)


def _pose(k: int, y0: float = 1.0) -> Array:
    """Frame ``k`` of a boat heading north at 0.5 m/s, pinging at 5 Hz."""
    return np.array([8.0, y0 + 0.1 * k, 0.0])


def _drawing(**kw: object) -> LiveDrawing:
    return LiveDrawing(MOUNT, replace(StreamingParams(), **kw))  # type: ignore[arg-type]


def _draw(drawing: LiveDrawing, k: int, pose: Array, time: float) -> None:
    _, grid, _ = _scene()
    frame = _frame(pose)
    layers = drawn_layers(SCORER, frame)
    drawing.draw(k, time, layers, frame.mask, grid, MOUNT.sonar_pose(pose), LOCAL)


def _frames_in(rendered: list[RenderedTile]) -> set[int]:
    return {k for tile in rendered for k in tile.frames}


def test_new_frames_show_at_the_renders_pace_with_the_frames_that_reached_each_tile() -> None:
    drawing = _drawing()
    renders: list[tuple[float, list[RenderedTile]]] = []
    for k in range(10):
        t = 0.2 * k
        _draw(drawing, k, _pose(k), t)
        rendered = drawing.render(t, force=False)
        if rendered is not None:
            renders.append((t, rendered))
    # New coverage at most every ``render_every_s`` (0.5 s of survey time).
    assert [t for t, _ in renders] == pytest.approx([0.0, 0.6, 1.2, 1.8])
    assert _frames_in(renders[0][1]) == {0}
    assert _frames_in(renders[1][1]) == {1, 2, 3}
    shown: dict[tuple[int, int], int] = {}
    for _, rendered in renders:
        for tile in rendered:
            assert tile.image.version > shown.get(tile.image.key, 0)  # versions grow
            shown[tile.image.key] = tile.image.version
            assert (tile.image.values > 0).any()
    # Forced (the end of the stream): what came since at once, then nothing is left.
    _draw(drawing, 10, _pose(10), 1.9)
    assert drawing.render(1.9, force=False) is None
    rest = drawing.render(1.9, force=True)
    assert rest is not None and _frames_in(rest) == {10}
    again = drawing.render(2.1, force=True)
    assert again is not None and _frames_in(again) == set()


def test_a_live_frame_is_blended_again_only_when_its_fan_moved_enough() -> None:
    drawing = _drawing()
    pose = _pose(0)
    _draw(drawing, 0, pose, 0.0)
    drawing.render(0.0, force=True)
    near = pose + np.array([0.01, 0.0, 0.0])
    far = pose + np.array([0.10, 0.0, 0.0])
    # While live, under ``live_move_threshold_m`` (0.25 m) it stays where it was blended;
    # leaving the window, over ``move_threshold_m`` (2 cm) it is blended again.
    assert drawing.reblend([far], set(), LOCAL) == []
    assert drawing.reblend([near], {0}, LOCAL) == []
    assert drawing.reblend([far], {0}, LOCAL) == [0]
    live = drawing.live[0]
    np.testing.assert_array_equal(live.blended_pose, MOUNT.sonar_pose(far))
    assert fan_moved(MOUNT.sonar_pose(far), MOUNT.sonar_pose(pose)) == pytest.approx(0.1)
    rendered = drawing.render(1.0, force=True)
    assert rendered is not None and _frames_in(rendered) == {0}  # its tiles changed
    # A turn moves the far edge of the fan (5 m out) the most: 0.5 degree is 4.4 cm.
    turned = far + np.array([0.0, 0.0, math.radians(0.5)])
    assert drawing.reblend([turned], {0}, LOCAL) == [0]
    assert drawing.take_live(0) is live and drawing.take_live(0) is None
    assert drawing.live == {}


def _final_frames(drawing: LiveDrawing, n: int) -> dict[int, Drawn]:
    """``n`` frames drawn, then final: their images kept as a re-solve keeps them."""
    drawn = {}
    for k in range(n):
        _draw(drawing, k, _pose(k), 0.2 * k)
    for k in range(n):
        live = drawing.take_live(k)
        assert live is not None
        drawn[k] = pack(
            k, live.time, live.layers[..., 0], live.layers[..., 1], live.mask, live.grid,
            live.tiles, live.blended_pose, np.zeros(3),
        )  # fmt: skip
    return drawn


def test_frames_a_re_solve_moved_are_drawn_again_within_the_budget_along_the_track() -> None:
    drawing = _drawing()
    drawn = _final_frames(drawing, 6)
    moved = {k: _pose(k) + np.array([0.05, 0.0, 0.0]) for k in drawn}
    for k in (3, 0, 5, 1):
        drawing.queue_redraw(k, moved[k], 10.0)
    # Half a frame's worth per new frame: one every other frame, oldest first.
    order = []
    waits = {}
    for now, credit in ((11.0, 0.5), (12.0, 0.5), (13.0, 0.5), (14.0, 0.5)):
        done = drawing.redraw(now, credit, drawn, LOCAL)
        assert done is not None
        order += [r.index for r in done.redrawn]
        waits.update({r.index: r.wait_s for r in done.redrawn})
    assert order == [0, 1]
    assert waits == {0: 2.0, 1: 4.0}  # survey time in the queue
    # Swept along the track: a frame queued behind the sweep comes in its turn.
    drawing.queue_redraw(2, moved[2], 14.5)
    done = drawing.redraw(15.0, 1.0, drawn, LOCAL)
    assert done is not None and [r.index for r in done.redrawn] == [2]
    # A frame whose image was let go meanwhile is not drawn again; the end draws the rest.
    del drawn[5]
    done = drawing.redraw(16.0, 0.0, drawn, LOCAL, everything=True)
    assert done is not None and [(r.index, r.wait_s) for r in done.redrawn] == [(3, 6.0)]
    assert drawing.to_redraw == {}
    assert drawing.redraw(17.0, 0.5, drawn, LOCAL) is None  # nothing waits
    for k in (0, 1, 2, 3):
        np.testing.assert_array_equal(drawn[k].blended_sonar, MOUNT.sonar_pose(moved[k]))
    np.testing.assert_array_equal(drawn[4].blended_sonar, MOUNT.sonar_pose(_pose(4)))


def test_a_frame_let_go_while_waiting_is_drawn_at_its_pose_first() -> None:
    drawing = _drawing()
    drawn = _final_frames(drawing, 3)
    moved = _pose(1) + np.array([0.0, 0.05, 0.0])
    drawing.queue_redraw(1, moved, 5.0)
    assert {0, 1, 2} <= drawing.tiles.movable
    redrawn = drawing.let_go(drawn[1], 7.0, LOCAL)
    assert redrawn is not None and (redrawn.index, redrawn.wait_s) == (1, 2.0)
    np.testing.assert_array_equal(drawn[1].blended_sonar, MOUNT.sonar_pose(moved))
    assert drawing.let_go(drawn[2], 7.0, LOCAL) is None  # not waiting: only settled
    assert drawing.tiles.movable == {0}
    assert drawing.to_redraw == {}


def test_idle_tiles_leave_memory_but_not_those_of_live_frames() -> None:
    drawing = _drawing(evict_after_s=1.0, tile_memory_mb=None)
    _draw(drawing, 0, _pose(0), 0.0)  # at the south of the seabed
    _draw(drawing, 1, _pose(0, y0=9.0), 0.2)  # 8 m north: other tiles
    first = drawing.live[0].tiles
    drawing.take_live(0)  # final: its tiles may go
    kept = set(drawing.live[1].tiles)
    assert set(first) - kept
    rendered = drawing.render(5.0, force=True)
    assert rendered is not None
    assert drawing.tiles.spilled == len(set(first) - kept)
    assert set(drawing.tiles.active) == kept
    # Those that left were rendered one last time (with the frames that reached them).
    assert {t.image.key for t in rendered} >= set(first) - kept
    assert _frames_in(rendered) == {0, 1}
