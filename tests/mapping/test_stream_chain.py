"""The live chain (``mapping.stream_chain``): how a step is measured (registered, at the
velocity held, dead reckoned), the chain over a simulated survey against the truth, a
frame without a registration bridged rather than jumped, final frames forgotten, and a
re-solve's outcome followed."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
import pytest

from daemon.replay import mount_from_config, pipeline_params
from mapping.fmt import Registration
from mapping.fusion import FusionParams
from mapping.live_resolve import Bridge, DrawnFrame, LiveResolver, ResolveParams
from mapping.posegraph import Edge
from mapping.samples import Ping
from mapping.se2 import relative_pose
from mapping.stream_chain import LiveChain, Motion, compass_error, measure_step
from mapping.stream_front import Front, FrontJob
from mapping.stream_navigation import NavigationRecord
from mapping.stream_window import Resolution
from mapping.streaming import StreamingParams
from mapping.survey_graph import GraphParams
from tests.mapping.test_stream_navigation import Survey, quadrats

Array = npt.NDArray[np.float64]
PARAMS = StreamingParams()


# -- a step ------------------------------------------------------------------------------
def test_a_registered_step_is_the_registration_turned_by_the_gyro() -> None:
    edge = Edge(4, 5, 0.08, -0.01, 0.004)
    reckoned = (0.07, 0.0, 0.002)
    step = measure_step(edge, reckoned, None, None, True, 0.2, 10.0, PARAMS)
    assert (step.forward_m, step.starboard_m) == (0.08, -0.01)
    assert step.yaw_rad == 0.002  # the gyro's turn, a registration's yaw errs more
    assert step.motion is Motion.REGISTERED and not step.bridged and step.scaled
    assert step.sigma_m == 0.0
    without_gyro = measure_step(edge, reckoned, None, None, False, 0.2, 10.0, PARAMS)
    assert without_gyro.yaw_rad == 0.004 and not without_gyro.gyro


def test_a_bridge_holds_the_registered_velocity_while_it_is_recent() -> None:
    reckoned = (0.5, 0.1, 0.02)  # the filter in a GNSS outage: decimetres off
    velocity = (0.4, 0.0, 9.0)  # m/s forward, measured at 9 s
    span = 0.5
    step = measure_step(None, reckoned, None, velocity, True, span, 10.0, PARAMS)
    assert step.motion is Motion.HELD_VELOCITY and step.bridged and step.scaled
    assert step.yaw_rad == 0.02  # the gyro's turn
    # 0.2 m ahead, turned by half the turn (the chord of the arc).
    assert math.hypot(step.forward_m, step.starboard_m) == pytest.approx(0.2)
    assert math.atan2(step.starboard_m, step.forward_m) == pytest.approx(0.01)
    assert step.sigma_m == pytest.approx(PARAMS.bridge_velocity_sigma_mps * span)
    # Measured too long ago: the filter's dead reckoning, not scaled, less certain.
    old = (0.4, 0.0, 10.0 - PARAMS.bridge_velocity_age_s - 0.1)
    reckoned_step = measure_step(None, reckoned, None, old, True, span, 10.0, PARAMS)
    assert reckoned_step.motion is Motion.DEAD_RECKONED and not reckoned_step.scaled
    assert (reckoned_step.forward_m, reckoned_step.starboard_m) == (0.5, 0.1)
    assert reckoned_step.sigma_m == pytest.approx(PARAMS.bridge_filter_sigma_mps * span)


def test_without_the_gyro_a_bridge_holds_the_chains_own_velocity_and_turn() -> None:
    rate = (0.3, 0.05, 0.1)  # the chain's forward, starboard m/s and turn rad/s
    reckoned = (0.5, 0.1, 0.0)  # the filter held its heading: no turn
    step = measure_step(None, reckoned, rate, None, False, 0.5, 10.0, PARAMS)
    assert step.motion is Motion.HELD_VELOCITY and not step.gyro
    assert step.yaw_rad == pytest.approx(0.05)
    assert math.hypot(step.forward_m, step.starboard_m) == pytest.approx(math.hypot(0.15, 0.025))
    # Nothing at all measured the motion: the frame stays where the last one was.
    still = measure_step(None, None, None, None, False, 0.5, 10.0, PARAMS)
    assert (still.forward_m, still.starboard_m, still.yaw_rad) == (0.0, 0.0, 0.0)
    assert still.motion is Motion.DEAD_RECKONED


# -- the chain over a survey -------------------------------------------------------------
@dataclass
class Chained:
    """A survey's frames through the navigation record and the chain, as the engine
    passes them: per accepted frame its index, live pose when chained, bridge and
    registration."""

    survey: Survey
    record: NavigationRecord
    chain: LiveChain
    frames: list[tuple[int, Array, Bridge | None, Edge | None]]
    times: list[float]
    front: Front
    poses: list[Array]

    def truth(self, k: int) -> Array:
        """Frame ``k``'s true pose in the local frame."""
        frame = self.record.frame
        assert frame is not None
        east, north, heading = self.survey.sim.truth_pose(k)
        return np.array([east - frame.anchor_e, north - frame.anchor_n, heading])


def _chain(survey: Survey, unregistered: range = range(0)) -> Chained:
    """The survey chained; the frames ``unregistered`` are given to the chain without
    their registration (as when it joined them to a frame the chain never had)."""
    config = survey.sim.site_config
    params = StreamingParams(pipeline=pipeline_params(config))
    mount = mount_from_config(config.sonar)
    record = NavigationRecord(mount, params.pipeline, params.gnss_time_offset_s)
    times: list[float] = []
    poses: list[Array] = []
    chain = LiveChain(mount, params)
    front = Front(mount, params)
    frames = []
    registered: list[tuple[int, Registration]] = []
    for sample in survey.samples:
        if not isinstance(sample, Ping):
            fix = record.take(sample).chain_fix
            if fix is not None:
                chain.take_fix(fix)
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
        edge = None if k in unregistered else outcome.edge
        bridge = chain.link(k, sample.time, at, edge)
        _, job = chain.close_loop(k, sample.time, result.image, registered)
        registered = [] if job is None else [(job.index, front.closures.run(job))]
        poses.append(chain.live_pose(k))
        frames.append((k, poses[-1], bridge, edge))
    return Chained(survey, record, chain, frames, times, front, poses)


@functools.cache
def _chained() -> Chained:
    return _chain(quadrats())


def test_registered_frames_are_chained_by_their_registrations() -> None:
    run = _chained()
    assert len(run.frames) >= 38
    errors = []
    for (i, _, _, _), (j, _, bridge, edge) in zip(run.frames, run.frames[1:], strict=False):
        assert edge is not None and edge.i == i and bridge is None
        step = relative_pose(run.chain.chained(i), run.chain.chained(j))
        true = relative_pose(run.truth(i), run.truth(j))
        errors.append(
            (
                math.hypot(step.forward_m - true.forward_m, step.starboard_m - true.starboard_m),
                abs(math.degrees(step.yaw_rad - true.yaw_rad)),
            )
        )
    e = np.array(errors)
    # Steps of 7 cm, each good to a couple of centimetres and a few tenths of a degree.
    assert float(np.median(e[:, 0])) < 0.03 and float(e[:, 0].max()) < 0.08
    assert float(e[:, 1].max()) < 0.5
    # Where the anchor puts the frames: the GNSS's metre or so from the truth.
    for k, pose, _, _ in run.frames:
        assert math.hypot(*(pose[:2] - run.truth(k)[:2])) < 2.0


def test_a_frame_without_its_registration_is_bridged_at_the_speed_measured() -> None:
    survey = quadrats()
    gap = range(20, 25)
    run = _chain(survey, gap)
    graph = run.chain.params.pipeline.single_stage.graph
    for (i, _, _, _), (j, _, bridge, _) in zip(run.frames, run.frames[1:], strict=False):
        if j not in gap:
            assert bridge is None
            continue
        assert bridge is not None and bridge.i == i
        # At the registrations' speed (recent), as uncertain as such a bridge is.
        span = run.times[j] - run.times[i]
        sigma = graph.odometry_sigma_m + PARAMS.bridge_velocity_sigma_mps * span
        assert bridge.sigma_m == pytest.approx(sigma)
        step = relative_pose(run.chain.chained(i), run.chain.chained(j))
        true = relative_pose(run.truth(i), run.truth(j))
        assert (
            math.hypot(step.forward_m - true.forward_m, step.starboard_m - true.starboard_m) < 0.05
        )
        assert (bridge.forward_m, bridge.starboard_m) == pytest.approx(
            (step.forward_m, step.starboard_m), abs=1e-3
        )
    # Across the gap the chain moved as the boat did (each bridged step holds the last
    # registered one's error: centimetres), not by nothing and not by the filter's jumps.
    before, after = gap.start - 1, gap.stop
    moved = relative_pose(run.chain.chained(before), run.chain.chained(after))
    true = relative_pose(run.truth(before), run.truth(after))
    assert math.hypot(true.forward_m, true.starboard_m) > 0.35
    assert math.hypot(moved.forward_m - true.forward_m, moved.starboard_m - true.starboard_m) < 0.15


def test_final_frames_are_forgotten_but_the_one_the_chain_goes_on_from() -> None:
    run = _chain(quadrats())
    chain = run.chain
    indices = [k for k, *_ in run.frames]
    last = indices[-1]
    for k in indices:
        assert chain.holds(k)
        chain.finalise(k)
    assert not any(chain.holds(k) for k in indices[:-1])
    assert chain.holds(last)  # the next frame is chained onto it
    chained = chain.chained(last)
    assert np.all(np.isfinite(chained))


def test_a_final_frame_is_offered_as_a_keyframe_with_the_correction_it_is_drawn_with() -> None:
    run = _chain(quadrats())
    chain = run.chain
    closures = chain.closures
    assert closures is not None  # made with the first frame's geometry
    k, _, _, _ = run.frames[5]
    pose = chain.live_pose(k)
    grid = chain.grid
    image = np.zeros(grid.shape, np.float32)
    chain.offer_keyframe(k, 1.0, pose, image, grid)
    keyframe = closures.store.frames[k]
    correction = pose - chain.chained(k)
    assert keyframe.correction[:2] == pytest.approx(correction[:2])
    assert keyframe.correction[2] == pytest.approx(math.remainder(correction[2], 2 * math.pi))
    # Moved by a re-solve: the keyframe and its correction move with it.
    moved = pose + np.array([0.3, -0.1, 0.0])
    chain.move_keyframe(k, moved, chain.chained(k))
    assert keyframe.pose[:2] == pytest.approx(moved[:2])
    assert keyframe.correction[:2] == pytest.approx(correction[:2] + np.array([0.3, -0.1]))


def _resolution(
    poses: dict[int, Array], nodes: list[int], last_drawn: int, offset: Array, drawn_at: Array
) -> Resolution:
    """A re-solve that moved ``nodes`` from ``poses`` by ``offset`` (the drawn map's frame
    unchanged), its newest drawn frame ``nodes[last_drawn]`` drawn at ``drawn_at``."""
    solved = np.array([poses[k] + offset for k in nodes])
    return Resolution(
        nodes, solved, solved.copy(), DrawnFrame(), DrawnFrame(), None, last_drawn, drawn_at, []
    )


def test_the_chain_carries_on_from_a_re_solve_keeping_what_the_gnss_sees() -> None:
    run = _chain(quadrats())
    chain = run.chain
    indices = [k for k, *_ in run.frames]
    before = {k: chain.live_pose(k) for k in indices}
    seen = chain.anchor.x[0:2] + chain.anchor.x[2:4]  # correction plus the GNSS's bias
    # The solution moved the drawn frames and the first live one by 0.4 m east, 0.2 south:
    # the chain joins it at that live frame.
    offset = np.array([0.4, -0.2, 0.0])
    chain.follow(_resolution(before, indices[:31], 29, offset, before[indices[29]]))
    for k in indices:
        assert chain.live_pose(k) == pytest.approx(before[k] + offset, abs=1e-9)
    assert chain.anchor.x[0:2] + chain.anchor.x[2:4] == pytest.approx(seen, abs=1e-9)


def test_without_a_live_frame_after_it_the_chain_joins_the_last_drawn_frame() -> None:
    run = _chain(quadrats())
    chain = run.chain
    indices = [k for k, *_ in run.frames]
    poses = {k: chain.live_pose(k) for k in indices}
    for k in indices[:-1]:
        chain.finalise(k)
    join = indices[-2]  # drawn and final: where it is drawn is what the solution moves
    drawn_at = poses[join] - np.array([0.1, 0.0, 0.0])
    correction = chain.anchor.x[0:2].copy()
    chain.follow(_resolution(poses, indices[-6:-1], 4, np.array([0.3, 0.0, 0.0]), drawn_at))
    assert chain.anchor.x[0:2] == pytest.approx(correction + np.array([0.4, 0.0]), abs=1e-9)


def test_the_compass_error_is_the_re_solves() -> None:
    resolver = LiveResolver(ResolveParams(), FusionParams(), GraphParams())
    coefficients = np.radians([3.0, 0.5, -0.4, 0.2, 0.1])
    resolver.compass = coefficients
    for heading in np.linspace(0.0, 2 * math.pi, 9):
        error = compass_error(coefficients, float(heading))
        assert error == resolver.compass_error(float(heading))
    assert compass_error(None, 1.0) == 0.0
    assert abs(compass_error(coefficients, 1.0)) > math.radians(2.0)


def test_a_re_solves_compass_error_reaches_the_chains_heading() -> None:
    """Followed, a re-solve's compass error is taken out of the filter's heading before
    it measures the chain's: 5 degrees less from the compass, the anchor turns the chain
    back by degrees over the next seconds."""
    survey = quadrats()
    half = replace(survey, samples=survey.samples[: len(survey.samples) // 2])
    headings = []
    for coefficients in (None, np.radians([5.0, 0.0, 0.0, 0.0, 0.0])):
        run = _chain(half)
        nodes = [k for k, *_ in run.frames][-5:]
        poses = {k: run.chain.live_pose(k) for k in nodes}
        resolution = _resolution(poses, nodes, 3, np.zeros(3), poses[nodes[3]])
        run.chain.follow(replace(resolution, compass=coefficients))
        assert _continue(run, survey) >= 15
        headings.append(run.chain.anchor.heading)
    assert headings[1] < headings[0] - math.radians(1.0)


def _continue(run: Chained, survey: Survey) -> int:
    """Feed the rest of ``survey`` (after what ``run`` had) through its record and chain;
    returns the frames chained."""
    record, chain, times = run.record, run.chain, run.times
    front, poses = run.front, run.poses
    chained = 0
    for sample in survey.samples[len(run.survey.samples) :]:
        if not isinstance(sample, Ping):
            fix = record.take(sample).chain_fix
            if fix is not None:
                chain.take_fix(fix)
            continue
        k = len(times)
        at = record.at_ping(sample)
        attitude = record.ping_attitude(sample.time, times, poses)
        result = front.run(FrontJob(k, sample, at, attitude))
        chain.take_front(result)
        outcome = result.outcome
        times.append(sample.time)
        if outcome.accepted:
            chain.link(k, sample.time, at, outcome.edge)
            chained += 1
    return chained
