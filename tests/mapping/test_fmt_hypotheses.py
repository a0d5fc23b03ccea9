"""On a seabed that repeats (rows of racks a metre apart) the registrar returns the
distinct peaks, the true motion and the one a period away among them, each scored."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.fmt import Hypothesis
from mapping.se2 import RelativePose
from tests.mapping import test_fmt_bed as bed

PERIOD_M = 1.0


@pytest.fixture(scope="module")
def racks() -> tuple[bed.Sonar, bed.Seabed]:
    seabed = bed.make_seabed(
        np.random.default_rng(2), 16.0, ripples=0.6, bars=1.0, bars_period_m=PERIOD_M, texture=0.3
    )
    return bed.Sonar(), seabed


def _near(h: Hypothesis, truth: RelativePose, tolerance_m: float) -> bool:
    return (
        math.hypot(
            h.relative.forward_m - truth.forward_m, h.relative.starboard_m - truth.starboard_m
        )
        < tolerance_m
    )


def test_consecutive_frames_give_the_motion_first_and_the_rack_one_period_away(racks):
    sonar, seabed = racks
    rng = np.random.default_rng(4)
    registrar = sonar.registrar()
    start = (4.0, 8.0, math.radians(90.0))  # looking east, across the rows of racks
    truth = RelativePose(0.20, 0.05, math.radians(1.0))
    earlier = registrar.prepare(sonar.frame(seabed, start, rng))
    later = registrar.prepare(sonar.frame(seabed, bed.moved(start, truth), rng))
    # The prior half a period off: it must not decide.
    prior = RelativePose(truth.forward_m + 0.45, truth.starboard_m, truth.yaw_rad)
    result = registrar.register(earlier, later, prior, prior_sigma_m=0.3, n_hypotheses=3)

    hypotheses = result.hypotheses
    assert len(hypotheses) == 3
    assert hypotheses[0].relative == result.relative
    # The true motion is first: its peak is the highest (the whole overlap agrees, not
    # just the racks), and its similarity too.
    assert _near(hypotheses[0], truth, 0.01)
    assert abs(math.degrees(result.relative.yaw_rad - truth.yaw_rad)) < 0.1
    period_away = [
        h
        for h in hypotheses[1:]
        if _near(h, RelativePose(truth.forward_m - PERIOD_M, 0.05, 0), 0.03)
    ]
    assert period_away, [h.relative for h in hypotheses]
    assert hypotheses[0].peak > period_away[0].peak
    assert hypotheses[0].score > period_away[0].score > 0.05
    # Distinct, and each with its own covariance.
    positions = [(h.relative.forward_m, h.relative.starboard_m) for h in hypotheses]
    gaps = [math.dist(a, b) for i, a in enumerate(positions) for b in positions[i + 1 :]]
    assert min(gaps) > 0.05
    for h in hypotheses:
        assert np.all(np.linalg.eigvalsh(h.covariance) > 0)


def test_a_loop_closure_half_a_turn_apart_keeps_the_true_peak_among_its_hypotheses(racks):
    sonar, seabed = racks
    rng = np.random.default_rng(4)
    registrar = sonar.registrar()
    # Two lanes: one looking east, the next looking back west at the same racks.
    earlier_pose = (3.5, 8.0, math.radians(90.0))
    later_pose = (10.8, 8.2, math.radians(272.0))
    truth = bed.relative(earlier_pose, later_pose)
    earlier = registrar.prepare(sonar.frame(seabed, earlier_pose, rng))
    later = sonar.frame(seabed, later_pose, rng)
    # The lanes' GNSS 0.45 m and a degree apart.
    prior = RelativePose(truth.forward_m - 0.45, truth.starboard_m + 0.1, truth.yaw_rad + 0.017)
    result = registrar.register_far(earlier, later, prior, prior_sigma_m=0.5, n_hypotheses=3)

    hypotheses = result.hypotheses
    assert len(hypotheses) == 3
    true = [h for h in hypotheses if _near(h, truth, 0.03)]
    period_away = [
        h
        for h in hypotheses
        if _near(h, RelativePose(truth.forward_m - PERIOD_M, truth.starboard_m, 0), 0.05)
    ]
    assert true and period_away, [h.relative for h in hypotheses]
    # Scored on the original frames: the true one is the most similar.
    assert true[0].score == max(h.score for h in hypotheses)
    # Its yaw is a fraction of a degree off, and its covariance says so.
    yaw_error = (true[0].relative.yaw_rad - truth.yaw_rad + math.pi) % (2 * math.pi) - math.pi
    yaw_sigma = math.sqrt(true[0].covariance[2, 2])
    assert abs(yaw_error) < 3 * yaw_sigma < math.radians(1.5)
