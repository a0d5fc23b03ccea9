"""The live window and the live re-solve (``mapping.stream_window``): which frames stay
live and which become final, what the re-solve is given, and a re-solve over a simulated
survey's frames that keeps the drawn map where it is drawn."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from daemon.replay import mount_from_config, pipeline_params
from mapping.fmt import Registration
from mapping.frames import FrameOutcome, SonarMount
from mapping.live_closures import Closure
from mapping.live_resolve import ResolveParams, pack
from mapping.samples import Ping
from mapping.se2 import RelativePose
from mapping.stream_chain import LiveChain
from mapping.stream_drawing import LiveImage, fan_moved
from mapping.stream_front import Front, FrontJob
from mapping.stream_navigation import NavigationRecord
from mapping.stream_window import LiveWindow
from mapping.streaming import StreamingParams
from mapping.survey_graph import registration_sqrt_info
from tests.mapping.test_stream_navigation import quadrats

Array = npt.NDArray[np.float64]


def _times() -> list[float]:
    return [s.time for s in quadrats().samples if isinstance(s, Ping)]


def _accepted(window: LiveWindow, times: list[float]) -> None:
    """Every frame accepted (its registration aside: the window's bookkeeping only)."""
    for k, t in enumerate(times):
        window.add_frame(k, t, np.zeros(3), FrameOutcome(k, t, True), None, times)


def test_the_last_frames_stay_live_and_the_older_become_final() -> None:
    params = StreamingParams(window_frames=10, solve_every=5)
    window = LiveWindow(SonarMount(), params)
    times = _times()[:23]
    due = []
    for k, t in enumerate(times):
        window.add_frame(k, t, np.zeros(3), FrameOutcome(k, t, True), None, times)
        if window.solve_due:
            due.append(k)
            assert window.start_solve() == list(range(window.final_upto, k + 1))
            assert not window.solve_due
            leaving = window.leaving(False, None, times)
            assert leaving == list(range(len(leaving) and leaving[0], k + 1 - 10))
    assert due == [4, 9, 14, 19]
    assert window.final_upto == 10  # frames 10..19 were the last ten at frame 19
    assert window.newest == 22
    assert window.leaving(True, None, times) == list(range(10, 23))  # the end: all
    assert window.leaving(True, None, times) == []


def test_frames_since_a_pending_closure_stay_live_a_bounded_while() -> None:
    times = _times()[:40]
    window = LiveWindow(SonarMount(), StreamingParams(window_frames=10, closure_hold_frames=15))
    _accepted(window, times)
    # Closures wait since frame 27: frames from there on stay with the live window (the
    # last ten would have: 30 on).
    assert window.leaving(False, times[27], times) == list(range(27))
    window = LiveWindow(SonarMount(), StreamingParams(window_frames=10, closure_hold_frames=15))
    _accepted(window, times)
    # Since frame 5: no more than ``closure_hold_frames`` stay live.
    assert window.leaving(False, times[5], times) == list(range(25))
    # The pair no longer waits: the frames it held follow, but the last ten.
    assert window.leaving(False, None, times) == list(range(25, 30))


def test_a_closure_reaches_the_re_solve_in_its_keyframes_axes() -> None:
    window = LiveWindow(SonarMount(), StreamingParams())
    # Uncertain by 1 cm east and 4 cm north; the keyframe heads north: its forward axis
    # is north, its starboard axis east.
    covariance = np.diag([0.01**2, 0.04**2, math.radians(0.3) ** 2])
    relative = RelativePose(0.2, -0.1, 0.01)
    zeros = np.zeros(3)
    closure = Closure(3, 40, 1.0, 20.0, relative, zeros, covariance, zeros, zeros, 1.0, 0.0)
    window.take_closures([closure])
    [taken] = window.resolver.closures
    assert (taken.i, taken.j) == (3, 40)
    assert (taken.forward_m, taken.starboard_m, taken.yaw_rad) == (0.2, -0.1, 0.01)
    np.testing.assert_allclose(
        taken.covariance, np.diag([0.04**2, 0.01**2, math.radians(0.3) ** 2]), atol=1e-12
    )


@dataclass
class Fed:
    """Windows fed a survey's navigation and accepted frames as the engine feeds them,
    with each frame's live pose and what the re-solve keeps of it when it is drawn."""

    windows: list[LiveWindow]
    chain: LiveChain
    mount: SonarMount
    times: list[float]
    poses: list[Array]
    images: dict[int, LiveImage]
    infos: dict[int, Array]
    """The square-root information each registration should have reached the re-solve
    with."""
    last_fix: float


def _feed(*params: StreamingParams) -> Fed:
    survey = quadrats()
    config = survey.sim.site_config
    mount = mount_from_config(config.sonar)
    first = replace(params[0], pipeline=pipeline_params(config))
    record = NavigationRecord(mount, first.pipeline, first.gnss_time_offset_s)
    times: list[float] = []
    poses: list[Array] = []
    chain = LiveChain(mount, first)
    front = Front(mount, first)
    windows = [LiveWindow(mount, replace(p, pipeline=first.pipeline)) for p in params]
    images, infos = {}, {}
    graph = first.pipeline.single_stage.graph
    last_fix = -math.inf
    registered: list[tuple[int, Registration]] = []
    for sample in survey.samples:
        if not isinstance(sample, Ping):
            measured = record.take(sample)
            for window in windows:
                window.take_navigation(measured)
            if measured.gnss is not None:
                last_fix = measured.gnss[0]
            if measured.chain_fix is not None:
                chain.take_fix(measured.chain_fix)
            continue
        k = len(times)
        at = record.at_ping(sample)
        attitude = record.ping_attitude(sample.time, times, poses)
        result = front.run(FrontJob(k, sample, at, attitude))
        chain.take_front(result)
        outcome = result.outcome
        times.append(sample.time)
        if not outcome.accepted:
            poses.append(np.full(3, np.nan))
            continue
        assert at.prior is not None
        bridge = chain.link(k, sample.time, at, outcome.edge)
        if outcome.edge is not None:
            dt = sample.time - times[outcome.edge.i]
            infos[k] = registration_sqrt_info(outcome, mount, graph, dt)
        for window in windows:
            window.add_frame(k, sample.time, at.prior, outcome, bridge, times)
        # A closure's registration comes back with the next accepted frame (the engine's
        # come back with the ping ``front_depth + 1`` on).
        taken, job = chain.close_loop(k, sample.time, result.image, registered)
        registered = [] if job is None else [(job.index, front.closures.run(job))]
        for window in windows:
            window.take_closures(taken)
        poses.append(chain.live_pose(k))
        images[k] = LiveImage(
            k, sample.time, result.layers, result.mask, chain.grid, [], mount.sonar_pose(poses[-1])
        )
    return Fed(windows, chain, mount, times, poses, images, infos, last_fix)


@functools.cache
def _fed() -> Fed:
    """Windows as the engine's (each test changes its own), and one without keyframe
    edges."""
    default = StreamingParams()
    no_keyframes = replace(default, resolve=replace(ResolveParams(), keyframe_edges=False))
    return _feed(default, no_keyframes, default, default, default)


def test_registrations_reach_the_re_solve_weighed_by_the_time_they_span() -> None:
    fed = _fed()
    window, no_keyframes = fed.windows[:2]
    resolver = window.resolver
    assert resolver.accepted == window.accepted == sorted(fed.images)
    assert len(fed.infos) >= len(fed.images) - 2
    for j, info in fed.infos.items():
        i, edge, w = resolver.registrations[j]
        assert (i, edge.j) == (edge.i, j)
        np.testing.assert_array_equal(w, info)
        assert j in resolver.measured  # the keyframe's registration too
    assert not no_keyframes.resolver.measured


def test_a_re_solve_keeps_the_drawn_map_in_place_and_moves_what_does_not_fit() -> None:
    fed = _fed()
    window = fed.windows[2]
    drawn = sorted(fed.images)[:30]
    for k in drawn:
        assert window.keep_drawn(fed.images[k], fed.chain.chained(k)) == []
    resolution = window.resolve(fed.times[-1], fed.poses)
    assert resolution is not None
    nodes = resolution.nodes
    # The drawn frames and the live tail (``ResolveParams.live_tail``), nothing before.
    assert nodes == sorted(fed.images)
    assert nodes[resolution.last_drawn] == drawn[-1]
    np.testing.assert_array_equal(resolution.last_drawn_pose, fed.poses[drawn[-1]])
    assert resolution.last_drawn_pose is not fed.poses[drawn[-1]]
    assert resolution.compass is not None and resolution.old != resolution.new
    assert window.drawn_frame == resolution.new
    np.testing.assert_allclose(resolution.solved, resolution.new.poses(resolution.in_gnss))
    # Nothing before the stretch holds it: it stays where it is drawn (the mean of its
    # positions), and takes the solution's shape.
    was = np.array([fed.poses[k] for k in nodes])
    np.testing.assert_allclose(
        resolution.solved[:, :2].mean(axis=0), was[:, :2].mean(axis=0), atol=1e-9
    )
    # The drawn frames whose fan the solution moves more than ``redraw_m`` move.
    redraw_m = window.params.resolve.redraw_m
    expected = []
    for m, k in enumerate(nodes):
        sonar, at = fed.mount.sonar_pose(resolution.solved[m]), fed.mount.sonar_pose(was[m])
        if k in drawn and fan_moved(sonar, at) > redraw_m:
            expected.append(k)
    assert expected and [move.index for move in resolution.moves] == expected
    for move in resolution.moves:
        np.testing.assert_array_equal(move.pose, resolution.solved[nodes.index(move.index)])
        np.testing.assert_array_equal(move.chain, fed.chain.chained(move.index))
    # The GNSS silent for a re-solve's interval: no re-solve, the next one later.
    every = window.params.resolve.every_s
    silent = fed.last_fix + every + 1.0
    assert window.resolve(silent, fed.poses) is None
    assert not window.resolve_due(silent + every - 0.1)
    assert window.drawn_frame == resolution.new


def test_the_re_solve_follows_where_the_map_is_drawn() -> None:
    """Drawn 3 m further east and 1 m south, the same stretch re-solves to the same shape
    there: the drawn map's place is its own, the solution gives its shape."""
    fed = _fed()
    here, there = fed.windows[3:5]
    offset = np.array([3.0, -1.0, 0.0])
    shifted = [pose + offset for pose in fed.poses]
    for k in sorted(fed.images)[:30]:
        here.keep_drawn(fed.images[k], fed.chain.chained(k))
        there.keep_drawn(fed.images[k], fed.chain.chained(k))
    a = here.resolve(fed.times[-1], fed.poses)
    b = there.resolve(fed.times[-1], shifted)
    assert a is not None and b is not None and a.nodes == b.nodes
    assert [m.index for m in a.moves] == [m.index for m in b.moves]
    np.testing.assert_allclose(b.solved[:, :2], a.solved[:, :2] + offset[:2], atol=0.002)
    np.testing.assert_allclose(b.solved[:, 2], a.solved[:, 2], atol=1e-5)


def test_images_kept_beyond_the_re_solves_memory_are_let_go_oldest_first() -> None:
    fed = _fed()
    first = fed.images[0]
    size = pack(
        0, 0.0, first.layers[..., 0], first.layers[..., 1], first.mask, first.grid, [],
        np.zeros(3), np.zeros(3),
    ).nbytes  # fmt: skip
    resolve = replace(ResolveParams(), memory_mb=3.5 * size / 2**20)
    window = LiveWindow(fed.mount, StreamingParams(resolve=resolve))
    let_go = []
    for k in range(8):
        let_go += [d.index for d in window.keep_drawn(fed.images[k], fed.chain.chained(k))]
    assert let_go == [0, 1, 2, 3, 4]
    assert list(window.drawn) == [5, 6, 7]
    kept = window.drawn[7]
    np.testing.assert_array_equal(kept.chain, fed.chain.chained(7))
    assert kept.image.dtype == np.uint8 and kept.time == fed.images[7].time
