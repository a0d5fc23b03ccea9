"""The live re-solve (``mapping.live_resolve``): the frames already drawn placed again by
the fusion, on the synthetic lawnmower of ``test_fusion`` (GNSS wander and lag, a biased
compass, a gyro bias, registrations good to millimetres)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from mapping.fusion import Fusion, FusionParams, PosePrior, diagonal_sqrt_info
from mapping.grid import SonarGrid
from mapping.live_resolve import Bridge, LiveResolver, ResolveParams, align, pack
from mapping.mosaic import SonarPose, TileGrid
from mapping.posegraph import Edge
from mapping.se2 import RelativePose, compose, relative_pose
from mapping.survey_graph import GraphParams
from mapping.tiles import MemorySpill, TileStore
from tests.mapping.test_fusion import _shape_error, _survey

GRID = SonarGrid((8, 8), 0.02, 0.16, -0.08)


def _resolver(
    params: ResolveParams,
    rate_hz: float = 2.0,
    lanes: int = 3,
    unregistered: range = range(0),
    bridged: bool = True,
    keyframe_every: int = 0,
):
    """A resolver fed the synthetic survey as the engine would feed it, every frame
    drawn at ``initial`` (the GNSS bias and the compass's misalignment in it). Frames
    ``unregistered`` have no registration: the live filter's priors there drift at
    0.3 m/s (dead reckoning in a GNSS outage), and the chain bridged them (``bridged``)
    at the speed last registered, good to 6 cm/s. ``keyframe_every``: each frame also
    comes with its registration from the keyframe before it (every so many frames), as
    the registration's consecutive edges composed."""
    times, truth, data, constraints, initial = _survey(rate_hz, lanes=lanes)
    priors = initial.copy()
    if len(unregistered):
        start = unregistered[0]
        drift = 0.3 * (times[unregistered] - times[start])
        priors[unregistered, 0] += drift
        priors[unregistered.stop :, 0] += drift[-1]
    resolver = LiveResolver(params, FusionParams(), GraphParams())
    for t, (x, y) in zip(data.gnss_times, data.gnss_xy, strict=True):
        resolver.add_gnss(float(t), float(x), float(y))
    for t, h in zip(data.heading_times, data.headings, strict=True):
        resolver.add_heading(float(t), float(h))
    # The gyro: the yaw integral's slope between frames as rate samples.
    rates = np.diff(data.yaw_integral) / np.diff(times)
    for k in range(1, times.size):
        for u in np.linspace(times[k - 1], times[k], 5, endpoint=False):
            resolver.add_yaw_rate(float(u), float(rates[k - 1]))
    dropped = []
    for k, t in enumerate(times):
        c = constraints[k - 1] if k else None
        edge = Edge(k - 1, k, c.forward_m, c.starboard_m, c.yaw_rad) if c else None
        bridge = None
        if k in unregistered:
            edge = None
            if bridged:
                rel = relative_pose(truth[k - 1], truth[k])
                span = float(t - times[k - 1])
                bridge = Bridge(
                    k - 1, rel.forward_m, rel.starboard_m, rel.yaw_rad,
                    0.02 + 0.06 * span, math.radians(0.5 + 0.5 * span),
                )  # fmt: skip
        measured = info = None
        if keyframe_every and edge is not None and c is not None:
            key = (k - 1) // keyframe_every * keyframe_every
            pose = np.zeros(3)
            for step in constraints[key:k]:
                pose = compose(pose, RelativePose(step.forward_m, step.starboard_m, step.yaw_rad))
            rel = relative_pose(np.zeros(3), pose)
            measured = Edge(key, k, rel.forward_m, rel.starboard_m, rel.yaw_rad)
            info = c.sqrt_info / math.sqrt(k - key)
        resolver.add_frame(
            k, float(t), priors[k], edge, c.sqrt_info if c and edge else None, bridge,
            measured, info,
        )  # fmt: skip
        image = np.full(GRID.shape, 0.5, np.float32)
        drawn = pack(k, float(t), image, image, image > 0, GRID, [], initial[k], initial[k])
        dropped += resolver.keep(drawn)
    return times, truth, initial, resolver, dropped


def test_the_drawn_map_takes_its_shape_and_the_compass_bias_from_the_re_solve() -> None:
    """Drawn with a 4 degree compass misalignment and the GNSS bias of each moment, the
    lanes do not fit; re-solved, the map is the survey-end fusion's (the same problem,
    assembled from what the engine kept), in its true shape, and the compass's error is
    known (for the chain's heading from then on): eight lanes, 9 minutes, as in
    ``test_fusion``."""
    times, truth, initial, resolver, _ = _resolver(ResolveParams(), lanes=8)
    assert _shape_error(initial, truth) > 0.3
    out = resolver.solve(list(initial))
    assert out is not None
    nodes, solved = out
    assert nodes == list(range(times.size))
    _, _, data, constraints, _ = _survey(2.0, lanes=8)
    direct, _ = Fusion(times, data).solve(initial, constraints)
    # The same map within a centimetre (the gyro is integrated here from rate samples a
    # sonar latency earlier, not given at the frames).
    assert _shape_error(solved, direct.poses) < 0.01
    assert np.abs(solved[:, :2] - direct.poses[:, :2]).max() < 0.02
    assert _shape_error(solved, truth) < 0.1
    assert resolver.compass is not None
    assert abs(math.degrees(resolver.compass[0]) - 4.0) < 1.2  # the misalignment


def test_frames_let_go_hold_the_map_where_it_is_drawn() -> None:
    """With room for half the survey's images, the older half is let go (its tiles to be
    settled) and the frame before the stretch holds it: the re-solved stretch starts
    where that frame is drawn."""
    zeros = np.zeros(GRID.shape, np.float32)
    per_frame = pack(0, 0.0, zeros, zeros, zeros > 0, GRID, [], np.zeros(3), np.zeros(3)).nbytes
    times, _truth, initial, resolver, dropped = _resolver(
        ResolveParams(memory_mb=per_frame * 60 / 2**20)
    )
    assert len(dropped) == times.size - 60
    assert [d.index for d in dropped] == list(range(len(dropped)))
    nodes, solved = resolver.solve(list(initial)) or ([], np.zeros((0, 3)))
    boundary = len(dropped) - 1
    assert nodes[0] == boundary and len(nodes) == 61
    assert np.hypot(*(solved[0, :2] - initial[boundary, :2])) < 0.02
    # Its priors and registrations are let go too: the resolver stays small.
    assert min(resolver.times) == boundary


def test_a_held_pose_is_kept() -> None:
    times, truth, data, constraints, initial = _survey(2.0)
    target = initial[10] + np.array([0.3, -0.2, 0.0])
    hold = PosePrior(10, target, diagonal_sqrt_info((0.005, 0.005, math.radians(0.05))))
    free, _ = Fusion(times, data).solve(initial, constraints)
    solution, _ = Fusion(times, data, priors=[hold]).solve(initial, constraints)
    assert np.hypot(*(solution.poses[10, :2] - target[:2])) < 0.01
    # The rest of the map follows it (the GNSS bias takes the offset): its shape stays.
    assert _shape_error(solution.poses, truth) < _shape_error(free.poses, truth) + 0.005


def test_a_wrong_closure_hold_is_down_weighted() -> None:
    times, _truth, data, constraints, initial = _survey(2.0)
    free, _ = Fusion(times, data).solve(initial, constraints)
    # A frame that can no longer move holds the map; a closure to another frame that
    # would put this one a metre off the rest is outweighed, not followed.
    held = PosePrior(40, free.poses[40], diagonal_sqrt_info((0.01, 0.01, math.radians(0.05))))
    wrong = free.poses[200] + np.array([1.0, 0.0, 0.0])
    closure = PosePrior(
        200, wrong, diagonal_sqrt_info((0.02, 0.02, math.radians(0.3))), robust=True
    )
    solution, _ = Fusion(times, data, priors=[held, closure]).solve(initial, constraints)
    assert np.hypot(*(solution.poses[200, :2] - free.poses[200, :2])) < 0.1


def test_translation_alignment_keeps_the_shape_and_the_orientation() -> None:
    rng = np.random.default_rng(2)
    drawn = np.column_stack([rng.uniform(0, 20, 40), rng.uniform(0, 20, 40), rng.uniform(0, 6, 40)])
    solved = drawn + np.array([0.05, -0.03, 0.0])
    solved[7, :2] += 0.5
    out = align(solved, drawn, 0.0).poses(solved)
    np.testing.assert_allclose(out[:, 2], solved[:, 2])
    np.testing.assert_allclose(
        out[:, :2] - solved[:, :2], np.broadcast_to(out[0, :2] - solved[0, :2], (40, 2))
    )
    moved = np.hypot(*(out[:, :2] - drawn[:, :2]).T)
    assert np.argmax(moved) == 7 and np.sort(moved)[-2] < 0.02


def test_a_spilled_tile_remembers_the_frames_that_may_still_move() -> None:
    """A tile that leaves memory while a frame in it may still be redrawn: loaded again,
    the frame can be taken out (its candidates do not stay behind as a ghost)."""
    grid = SonarGrid((60, 60), 0.02, 1.2, -0.6)
    store = TileStore(TileGrid(0.02, 64), spill=MemorySpill(), evict_after_s=1.0)
    image = np.full(grid.shape, 0.6, np.float32)
    mask = np.ones(grid.shape, bool)
    pose = SonarPose(500_000.5, 6_000_000.5, 0.3)
    keys = store.insert(7, image, image, mask, grid, pose, 0.0)
    store.insert(8, image, image, mask, grid, pose, 0.0, movable=False)
    store.evict_idle(10.0)
    assert not store.active
    store.remove(7, keys)
    for key in keys:
        tile = store.tile(key)
        assert not (tile.frame == 7).any()
        assert (tile.frame == 8).any()
    # A settled frame is forgotten everywhere.
    store.settle(8, keys)
    assert 8 not in store.movable


def test_alignment_turns_the_stretch_back_by_a_bounded_angle() -> None:
    rng = np.random.default_rng(3)
    drawn = np.column_stack([rng.uniform(0, 20, 40), rng.uniform(0, 20, 40), rng.uniform(0, 6, 40)])
    for turn_deg, expected in ((0.1, 0.1), (2.0, 0.25)):
        t = math.radians(turn_deg)
        s, c = math.sin(t), math.cos(t)
        solved = drawn.copy()
        solved[:, 0] = drawn[:, 0] * c - drawn[:, 1] * s + 0.3
        solved[:, 1] = drawn[:, 0] * s + drawn[:, 1] * c - 0.2
        solved[:, 2] = drawn[:, 2] - t
        frame = align(solved, drawn, math.radians(0.25))
        out = frame.poses(solved)
        back = np.degrees(np.remainder(out[:, 2] - solved[:, 2] + math.pi, 2 * math.pi) - math.pi)
        np.testing.assert_allclose(back, expected, atol=1e-9)
        if turn_deg < 0.25:
            np.testing.assert_allclose(out, drawn, atol=1e-9)
        # Points go as the poses do, and back.
        x, y = frame.point(float(solved[5, 0]), float(solved[5, 1]))
        np.testing.assert_allclose((x, y), out[5, :2], atol=1e-9)
        np.testing.assert_allclose(frame.inverse().poses(out)[:, :2], solved[:, :2], atol=1e-9)


def test_frames_the_chain_bridged_are_bridged_as_it_did() -> None:
    """40 s without registrations (a GNSS outage over a featureless patch): bridged as
    the chain bridged them, the re-solved lanes keep their shape; bridged by the live
    filter's drifting poses (what the survey-end pass does with its smoothed filter), they
    would not."""
    gap = range(60, 140)
    shapes = {}
    for bridged in (True, False):
        _, truth, initial, resolver, _ = _resolver(
            ResolveParams(), unregistered=gap, bridged=bridged
        )
        out = resolver.solve(list(initial))
        assert out is not None
        shapes[bridged] = _shape_error(out[1], truth)
    assert shapes[True] < 0.1
    assert shapes[False] > 2 * shapes[True]


def test_leaves_are_placed_by_their_registration_after_the_solve() -> None:
    """Frames registered against a keyframe and that nothing else hangs on (six in seven
    at 10 Hz) are left out of the solve and placed by their registration afterwards: the
    map is as true as the one solved with them (on this survey 4.6 against 4.6 cm at 5
    Hz, 6.4 against 10.2 at 10 Hz; the two 3.4-5.1 cm apart in shape)."""
    for rate_hz, every in ((5.0, 4), (10.0, 7)):
        params = ResolveParams(solve_leaves=True)
        times, truth, initial, with_leaves, _ = _resolver(
            params, rate_hz=rate_hz, keyframe_every=every
        )
        _, _, _, without, _ = _resolver(
            replace(params, solve_leaves=False), rate_hz=rate_hz, keyframe_every=every
        )
        solved = with_leaves.solve(list(initial))
        sizes: list[int] = []

        def counted(
            times: np.ndarray, *rest: Any, sizes: list[int] = sizes, fuse: Any = without._fuse
        ) -> np.ndarray:
            sizes.append(times.size)
            return fuse(times, *rest)

        without._fuse = counted
        reduced = without.solve(list(initial))
        # Only the keyframes (and the last frame) were solved.
        assert sizes == [len(range(0, times.size - 1, every)) + 1]
        assert solved is not None and reduced is not None
        assert solved[0] == reduced[0] == list(range(times.size))
        assert np.all(np.isfinite(reduced[1]))
        assert _shape_error(reduced[1], truth) < _shape_error(solved[1], truth) + 0.01
        assert _shape_error(reduced[1], truth) < 0.1
        assert with_leaves.compass is not None and without.compass is not None
        assert abs(math.degrees(with_leaves.compass[0] - without.compass[0])) < 0.2
