"""Registration against keyframes: a frame's error does not add up along the chain.

The registrar is replaced by one that knows the truth and errs by a set amount on every
registration (what a peak's sub-pixel bias does): only the bookkeeping of
``LocalRegistration`` is under test, its edges composed as every consumer composes them
(each edge from the previous accepted frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from mapping.fmt import Registration, RelativePose
from mapping.frames import LocalRegistration, RegistrationParams, SonarMount, compose, relative_pose

Array = npt.NDArray[np.float64]

MOUNT = SonarMount()
RATE_HZ = 10.0
SPEED_MPS = 0.4
BIAS_M = 0.001  # every registration measures this much more forward motion than there is


@dataclass
class _Frame:
    """Stands in for a preprocessed frame: its true sonar pose."""

    coarse: Array


@dataclass
class _Registrar:
    """Registers two frames from their true sonar poses, plus BIAS_M forward; refuses
    (score 0) a pair further apart than ``reach_m``."""

    reach_m: float = math.inf
    spans: list[float] = field(default_factory=list)

    def prepare(self, coarse: Array) -> Array:
        return coarse

    def register(self, a: Array, b: Array, expected: Any, prior_sigma_m: float) -> Registration:
        rel = relative_pose(a, b)
        span = math.hypot(rel.forward_m, rel.starboard_m)
        self.spans.append(span)
        far = span > self.reach_m
        return Registration(
            RelativePose(rel.forward_m + BIAS_M, rel.starboard_m, rel.yaw_rad),
            score=0.0 if far else 0.8,
            peak=0.5,
            overlap=0.9,
        )


def _truth(n: int) -> Array:
    """Vehicle poses (east, north, heading) of a boat at SPEED_MPS in a gentle turn."""
    t = np.arange(n) / RATE_HZ
    heading = math.radians(10.0) + math.radians(2.0) * t
    step = SPEED_MPS / RATE_HZ
    east = np.cumsum(step * np.sin(heading))
    north = np.cumsum(step * np.cos(heading))
    return np.stack([east, north, heading], axis=1)


def _run(params: RegistrationParams, registrar: _Registrar, n: int = 150) -> tuple[Array, Array]:
    """Chained vehicle poses (from the first frame's truth) and the truth."""
    truth = _truth(n)
    local = LocalRegistration(MOUNT, params=params)
    local.registrar = registrar  # type: ignore[assignment]
    chained = np.full((n, 3), np.nan)
    for k in range(n):
        outcome = local.register(k, k / RATE_HZ, _Frame(MOUNT.sonar_pose(truth[k])), truth[k])  # type: ignore[arg-type]
        assert outcome.accepted, outcome.reason
        if k == 0:
            chained[k] = truth[k]
            continue
        edge = outcome.edge
        assert edge is not None and edge.i == k - 1 and edge.j == k
        chained[k] = compose(
            chained[k - 1], RelativePose(edge.forward_m, edge.starboard_m, edge.yaw_rad)
        )
    return chained, truth


def test_every_frame_against_the_previous_adds_every_error() -> None:
    chained, truth = _run(RegistrationParams(keyframe_m=0.0), _Registrar())
    drift = float(np.hypot(*(chained[-1, :2] - truth[-1, :2])))
    assert drift == pytest.approx(149 * BIAS_M, rel=0.05)


def test_keyframes_add_one_error_a_keyframe() -> None:
    registrar = _Registrar()
    params = RegistrationParams(keyframe_m=0.3, keyframe_deg=5.0, keyframe_s=1.0)
    chained, truth = _run(params, registrar)
    # Every frame's pose is its keyframe's plus one registration: the error is one
    # BIAS_M per keyframe passed, 0.3 m apart (0.4 m/s: 8 frames), not one per frame.
    keyframes = 149 * SPEED_MPS / RATE_HZ / 0.3
    drift = float(np.hypot(*(chained[-1, :2] - truth[-1, :2])))
    assert drift < (keyframes + 2) * BIAS_M
    assert drift > (keyframes - 2) * BIAS_M
    # The pairs registered reach back to the keyframe: up to 0.3 m (plus one frame).
    spans = np.array(registrar.spans)
    assert spans.max() < 0.3 + SPEED_MPS / RATE_HZ
    assert spans.max() > 0.25


def test_a_keyframe_out_of_reach_falls_back_to_the_previous_frame() -> None:
    # The registrar cannot reach 0.15 m: every frame that the keyframe cannot register is
    # registered against the previous one, and the chain never breaks.
    registrar = _Registrar(reach_m=0.15)
    chained, truth = _run(RegistrationParams(keyframe_m=0.3), registrar)
    assert np.all(np.isfinite(chained))
    drift = float(np.hypot(*(chained[-1, :2] - truth[-1, :2])))
    assert drift < 149 * BIAS_M
