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

from mapping.fmt import Registration
from mapping.frames import LocalRegistration, RegistrationParams, SonarMount
from mapping.se2 import RelativePose, compose, relative_pose
from mapping.single_stage import _internal_drift, _rigid_groups
from mapping.survey_graph import GraphParams, chain_constraints

Array = npt.NDArray[np.float64]

MOUNT = SonarMount()
RATE_HZ = 10.0
SPEED_MPS = 0.4
BIAS_M = 0.001  # every registration measures this much more forward motion than there is


@dataclass
class _Frame:
    """Stands in for a preprocessed frame: its true sonar pose."""

    coarse: Array
    coarse_mask: None = None


@dataclass
class _Registrar:
    """Registers two frames from their true sonar poses, plus BIAS_M forward; refuses
    (score 0) a pair further apart than ``reach_m``."""

    reach_m: float = math.inf
    spans: list[float] = field(default_factory=list)

    def prepare(self, coarse: Array, mask: None = None) -> Array:
        return coarse

    def register(
        self, a: Array, b: Array, expected: Any, prior_sigma_m: float, yaw_known: bool = False
    ) -> Registration:
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


def _outcomes(params: RegistrationParams, n: int = 150) -> tuple[list[Any], Array]:
    truth = _truth(n)
    local = LocalRegistration(MOUNT, params=params)
    local.registrar = _Registrar()  # type: ignore[assignment]
    outcomes = [
        local.register(k, k / RATE_HZ, _Frame(MOUNT.sonar_pose(truth[k])), truth[k])  # type: ignore[arg-type]
        for k in range(n)
    ]
    return outcomes, truth


def _graph(outcomes: list[Any], truth: Array, params: GraphParams) -> tuple[Any, list[Any]]:
    n = truth.shape[0]
    return chain_constraints(
        np.arange(n) / RATE_HZ,
        np.ones(n, bool),
        [o.edge for o in outcomes if o.edge is not None],
        outcomes,
        truth,
        MOUNT,
        params,
    )


def test_the_graph_holds_each_frame_by_its_own_registration() -> None:
    # Each frame is tied to the keyframe it was registered against, by that registration:
    # the edges from the previous frame composed through it share its error, and weighed
    # as independent measurements they would say the chain is weaker than it is.
    outcomes, truth = _outcomes(RegistrationParams(keyframe_m=0.3, keyframe_deg=5.0))
    nodes, chain = _graph(outcomes, truth, GraphParams(keyframe_edges=True))
    assert nodes.size == truth.shape[0]
    assert sorted(c.j for c in chain) == list(range(1, nodes.size))  # one into each node
    assert all(c.i < c.j and c.kind == "registration" for c in chain)
    reach = [c.j - c.i for c in chain]
    assert max(reach) >= 6  # 0.3 m at 4 cm a frame
    for c in chain:
        measured = outcomes[c.j].measured
        assert (c.i, c.forward_m) == (measured.i, measured.forward_m)
    # Composed along the tree, the frames land where the chain of composed edges puts them.
    placed = np.zeros_like(truth)
    placed[0] = truth[0]
    for c in sorted(chain, key=lambda c: c.j):
        placed[c.j] = compose(placed[c.i], RelativePose(c.forward_m, c.starboard_m, c.yaw_rad))
    chained, _ = _run(RegistrationParams(keyframe_m=0.3, keyframe_deg=5.0), _Registrar())
    np.testing.assert_allclose(placed, chained, atol=1e-9)
    # Without keyframe edges (the default): the previous frame's composed edge.
    _, consecutive = _graph(outcomes, truth, GraphParams())
    assert all(c.j == c.i + 1 for c in consecutive)


def test_a_two_stage_submap_drifts_by_its_keyframes_not_its_frames() -> None:
    # A rigid submap's drift from its anchor (what loosens its links and its closures)
    # adds up once a keyframe: the frames of one keyframe do not each add their own.
    outcomes, truth = _outcomes(RegistrationParams(keyframe_m=0.3, keyframe_deg=5.0))
    nodes, chain = _graph(outcomes, truth, GraphParams(keyframe_edges=True))
    times = np.arange(nodes.size) / RATE_HZ
    rigid = _rigid_groups(chain, times, 6.0)
    drift = _internal_drift(rigid, chain, truth)
    _, consecutive = _graph(outcomes, truth, GraphParams())
    per_frame = _internal_drift(_rigid_groups(consecutive, times, 6.0), consecutive, truth)
    last = 59  # the first submap's last frame, 5.9 s from its anchor
    assert rigid.group[last] == 0 and rigid.group[last + 1] == 1
    assert drift[last, 2, 2] < 0.35 * per_frame[last, 2, 2]
    # The submaps' rigid shapes are the same either way (the composed edges telescope).
    np.testing.assert_allclose(
        rigid.offsets, _rigid_groups(consecutive, times, 6.0).offsets, atol=1e-9
    )
