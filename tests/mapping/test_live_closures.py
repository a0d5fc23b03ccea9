"""Live loop closures: a pass over seabed already mapped is pulled onto the map even when
the GNSS bias stepped between the passes, and a seabed that repeats cannot pull it a
period off (the registration is refused, not applied).

The scenes come from the registration test bed (``test_fmt_bed``): a sonar of our own over
a seabed of our own; the mount has no lever arm, so vehicle and sonar poses coincide. The
boat runs north along one line, turns, and comes back south 2 m to the east (its fan
overlaps the first pass); over the turn its chain drifted (as a heading error makes it)
and the GNSS bias stepped."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import pytest

from mapping.fmt import FmtRegistrar
from mapping.frames import SonarMount
from mapping.live_anchor import AnchorParams, LiveAnchor
from mapping.live_closures import ClosureJob, LiveClosureParams, LiveClosures
from tests.mapping import test_fmt_bed as bed

SPEED_MPS = 0.4
PING_S = 0.5
CHAIN_DRIFT_M = (0.5, -0.4)  # the chain's error over the turn (the bias stepped the same way)
MOUNT = SonarMount(forward_m=0.0, starboard_m=0.0, down_m=0.0, tilt_rad=math.radians(15.0))


@dataclass
class Run:
    """What a survey of the two passes leaves: per pass-2 frame the live pose's offset
    from the truth, against pass 1's (the map's) mean offset."""

    map_offset: np.ndarray
    pass2_offsets: list[np.ndarray] = field(default_factory=list)
    """Live pose minus true pose (east, north metres) of each second-pass frame."""
    closures: LiveClosures | None = None

    def disagreement(self, last: int) -> float:
        """RMS distance (m) between pass 2's last ``last`` frames and the map."""
        d = np.array(self.pass2_offsets[-last:]) - self.map_offset
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def _track() -> list[tuple[float, tuple[float, float, float], int]]:
    """(time, true pose, pass) of each ping: north along east = 6 m, a 30 s turn (no
    pings used), south along east = 8 m looking back at the seabed the first pass saw."""
    out = []
    steps = 24
    for k in range(steps):
        out.append((k * PING_S, (6.0, 3.0 + k * SPEED_MPS * PING_S, 0.0), 1))
    t0 = steps * PING_S + 30.0
    for k in range(steps):
        out.append((t0 + k * PING_S, (8.0, 14.5 - k * SPEED_MPS * PING_S, math.pi), 2))
    return out


def _survey(
    seabed: bed.Seabed, gnss_bias_2: tuple[float, float], enabled: bool, lag: int = 0
) -> Run:
    """``lag``: frames between a closure's proposal and its conclusion (the engine's
    registrations come back with the ping ``front_depth + 1`` on); 0: at once."""
    sonar = bed.Sonar(seed=1)
    pre = sonar.preprocessor
    assert pre.grid is not None
    registrar = FmtRegistrar(pre.grid, pre.tables.mask)
    bearings = pre.fan.bearings_rad
    closures = LiveClosures(
        LiveClosureParams(enabled=enabled, keyframe_spacing_m=0.3, attempt_every_s=0.9),
        MOUNT,
        (pre.min_range_m, pre.fan.max_range_m),
        max(abs(float(bearings[0])), abs(float(bearings[-1]))),
    )
    anchor = LiveAnchor(AnchorParams())
    rng = np.random.default_rng(3)
    track = _track()
    # Ten minutes of survey before: the anchor has settled (its correction moves slowly).
    for second in range(-600, 0):
        residual = rng.normal(0.0, 0.6, 2)
        anchor.update_position(float(second), (float(residual[0]), float(residual[1])))
        anchor.update_heading(float(second), float(rng.normal(0.0, math.radians(1.0))))
    chain_prev: np.ndarray | None = None
    map_offsets = []
    run = Run(np.zeros(2), closures=closures)
    waiting: deque[ClosureJob] = deque()
    for index, (time, pose, which) in enumerate(track):
        truth = np.array(pose)
        chain = truth[:2] + (np.array(CHAIN_DRIFT_M) if which == 2 else 0.0)
        anchor.predict(time)
        if chain_prev is not None:
            step = chain - chain_prev
            anchor.chain_step((float(step[0]), float(step[1])))
        chain_prev = chain
        # The receiver: 0.6 m white noise around a bias that steps between the passes.
        bias = np.zeros(2) if which == 1 else np.array(gnss_bias_2)
        for sub in range(3):
            fix = truth[:2] + bias + rng.normal(0.0, 0.6, 2)
            anchor.update_position(
                time - sub * 0.2, (float(fix[0] - chain[0]), float(fix[1] - chain[1]))
            )
        if which == 2 and track[index - 1][2] == 1:
            # The turn: 30 s of fixes with the new bias, the chain carried round.
            for second in range(30):
                t = time - 30.0 + second
                fix = truth[:2] + bias + rng.normal(0.0, 0.6, 2)
                anchor.update_position(t, (float(fix[0] - chain[0]), float(fix[1] - chain[1])))
        # The compass: the chain's heading is exact, the compass good to a degree.
        anchor.update_heading(time, float(rng.normal(0.0, math.radians(1.0))))
        image = pre(sonar.ping(seabed, *pose, rng)).image
        ce, cn = anchor.correction
        live = np.array([chain[0] + ce, chain[1] + cn, truth[2] + anchor.heading])
        if which == 1:
            map_offsets.append(live[:2] - truth[:2])
            heading_var = float(anchor.correction_covariance()[2, 2])
            closures.offer_keyframe(
                index, time, live, np.array([ce, cn, anchor.heading]), heading_var, image, pre.grid
            )
            continue
        if lag == 0:
            closures.consider(index, time, live, chain, float(truth[2]), image, registrar, anchor)
        else:
            while waiting and waiting[0].index <= index - lag:
                job = waiting.popleft()
                closures.conclude(job.index, closures.registrar.run(job), chain, time, anchor)
            proposed = closures.propose(
                index, time, live, chain, float(truth[2]), image,
                registrar.grid, registrar.mask, registrar.params, anchor,
            )  # fmt: skip
            if proposed is not None:
                waiting.append(proposed)
        ce, cn = anchor.correction
        run.pass2_offsets.append(chain + np.array([ce, cn]) - truth[:2])
    run.map_offset = np.mean(map_offsets[-8:], axis=0)
    return run


@pytest.fixture(scope="module")
def textured() -> bed.Seabed:
    return bed.make_seabed(np.random.default_rng(5), 16.0)


@pytest.fixture(scope="module")
def racks() -> bed.Seabed:
    """Rows of identical racks a metre apart and nothing else to tell them apart."""
    return bed.make_seabed(
        np.random.default_rng(6), 16.0, ripples=0.0, bars=1.0, bars_period_m=1.0, texture=0.0
    )


@pytest.mark.parametrize("lag", [0, 5])
def test_a_revisited_lane_is_pulled_onto_the_earlier_one(textured: bed.Seabed, lag: int) -> None:
    step = (0.9, -0.6)  # the GNSS bias between the passes, metres
    alone = _survey(textured, step, enabled=False)
    closed = _survey(textured, step, enabled=True, lag=lag)
    assert closed.closures is not None
    stats = closed.closures.stats
    # Without closures the second pass sits where the new bias pulls it...
    assert alone.disagreement(8) > 0.3, alone.disagreement(8)
    # ...with them, on the first pass, once a few agreeing closures confirmed the pair.
    assert stats.confirmed_pairs >= 1 and stats.applied >= 3, stats
    assert closed.disagreement(8) < 0.05, closed.disagreement(8)


def test_a_closure_a_period_away_on_racks_is_refused(racks: bed.Seabed) -> None:
    step = (0.9, -0.6)
    alone = _survey(racks, step, enabled=False)
    closed = _survey(racks, step, enabled=True)
    assert closed.closures is not None
    stats = closed.closures.stats
    # Rows a metre apart along east: the true peak and the ones a period away are about
    # as strong, and which is strongest changes from one registration to the next
    # (three in a row a period off happen). Nothing may be applied that moves the pass
    # by a period; refusing is the right answer.
    assert stats.attempts >= 5
    assert stats.rejected_ambiguous >= 2, stats
    assert stats.confirmed_pairs == 0 and stats.applied == 0, stats
    np.testing.assert_allclose(
        np.array(closed.pass2_offsets[-1]), np.array(alone.pass2_offsets[-1]), atol=1e-9
    )
