"""Loop closures on a periodic seabed: the false peak one period away is refused, the
right one taken, and a closure set that fits no prediction is left out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.closures import (
    ClosureCandidate,
    ClosureHypothesis,
    ClosureParams,
    ClosureReport,
    select_closures,
)
from mapping.fusion import Fusion
from mapping.se2 import RelativePose, relative_pose
from tests.mapping.test_fusion import _survey

PERIOD_M = 1.0  # quadrat rows, farm racks
COV = np.diag([0.02**2, 0.02**2, math.radians(0.3) ** 2])


@pytest.fixture(scope="module")
def solved():
    times, truth, data, constraints, initial = _survey(5.0, seed=5)
    fusion = Fusion(times, data)
    solution, _ = fusion.solve(initial, constraints)
    return times, truth, fusion, solution


def _lane_pairs(times: np.ndarray, truth: np.ndarray) -> list[tuple[int, int]]:
    """Frames of lane 0 and the frame of lane 1 nearest each (beside it, 4 m away)."""
    lane0 = np.flatnonzero((truth[:, 0] < 0.1) & (truth[:, 1] > 4) & (truth[:, 1] < 16))
    lane1 = np.flatnonzero(np.abs(truth[:, 0] - 4.0) < 0.1)
    pairs = []
    for i in lane0[::10]:
        j = lane1[np.argmin(np.abs(truth[lane1, 1] - truth[i, 1]))]
        pairs.append((int(i), int(j)))
    return pairs


def _hypothesis(truth: np.ndarray, i: int, j: int, along_m: float, score: float):
    rel = relative_pose(truth[i], truth[j])
    # One period along the row direction (north), expressed in frame i.
    psi = truth[i, 2]
    d_fwd, d_stb = along_m * math.cos(psi), -along_m * math.sin(psi)
    return ClosureHypothesis(
        RelativePose(rel.forward_m + d_fwd, rel.starboard_m + d_stb, rel.yaw_rad), COV, score
    )


def _candidates(times, truth, offsets_scores):
    out = []
    for i, j in _lane_pairs(times, truth):
        hyps = tuple(_hypothesis(truth, i, j, off, sc) for off, sc in offsets_scores)
        out.append(ClosureCandidate(i, j, float(times[i]), float(times[j]), hyps))
    return out


def test_the_right_peak_is_chosen_over_a_stronger_one_a_period_away(solved) -> None:
    times, truth, fusion, solution = solved
    candidates = _candidates(times, truth, [(PERIOD_M, 0.5), (0.0, 0.4)])
    report = ClosureReport()
    kept = select_closures(fusion, solution.poses, candidates, ClosureParams(), report)
    assert len(kept) == len(candidates) > 3
    for c, k in zip(candidates, kept, strict=True):
        rel = relative_pose(truth[c.i], truth[c.j])
        assert math.hypot(k.forward_m - rel.forward_m, k.starboard_m - rel.starboard_m) < 1e-6


def test_only_false_peaks_are_refused(solved) -> None:
    times, truth, fusion, solution = solved
    candidates = _candidates(times, truth, [(PERIOD_M, 0.5), (-PERIOD_M, 0.45)])
    report = ClosureReport()
    kept = select_closures(fusion, solution.poses, candidates, ClosureParams(), report)
    assert kept == []
    assert report.rejected_gate + report.rejected_ambiguous == len(candidates)


def test_a_lone_inconsistent_closure_is_outvoted(solved) -> None:
    times, truth, fusion, solution = solved
    candidates = _candidates(times, truth, [(0.0, 0.4)])
    bad = candidates[2]
    candidates[2] = ClosureCandidate(
        bad.i, bad.j, bad.time_i, bad.time_j, (_hypothesis(truth, bad.i, bad.j, 0.3, 0.6),)
    )
    report = ClosureReport()
    kept = select_closures(fusion, solution.poses, candidates, ClosureParams(), report)
    assert len(kept) == len(candidates) - 1
    assert all((k.i, k.j) != (bad.i, bad.j) for k in kept)


def test_a_rigid_submaps_drift_loosens_its_closures(solved) -> None:
    # Two-stage: a frame held rigidly in its submap carries the drift of the submap's
    # chain from its anchor, which the submap cannot bend to absorb. A closure there is
    # weighed with that drift, or it would turn the whole submap to fit itself.
    times, truth, fusion, solution = solved
    candidates = _candidates(times, truth, [(0.0, 0.4)])
    plain = select_closures(fusion, solution.poses, candidates, ClosureParams(), ClosureReport())
    drift = np.diag([0.03**2, 0.03**2, math.radians(0.5) ** 2])
    internal = np.broadcast_to(drift, (times.size, 3, 3))
    loose = select_closures(
        fusion, solution.poses, candidates, ClosureParams(), ClosureReport(), internal
    )
    assert len(loose) == len(plain) == len(candidates)
    for a, b in zip(plain, loose, strict=True):
        cov_a = np.linalg.inv(a.sqrt_info.T @ a.sqrt_info)
        cov_b = np.linalg.inv(b.sqrt_info.T @ b.sqrt_info)
        np.testing.assert_allclose(cov_b, cov_a + 2 * drift, rtol=1e-6, atol=1e-12)


def _groups_by_scanning_every_member(candidates, gap_s):
    """The pass groups as first defined: each candidate, in order of time_i, joins the
    first group with any member within gap_s in both times."""
    order = sorted(range(len(candidates)), key=lambda k: candidates[k].time_i)
    groups: list[list[int]] = []
    for k in order:
        c = candidates[k]
        home = next(
            (
                g
                for g in groups
                if any(
                    abs(candidates[m].time_i - c.time_i) < gap_s
                    and abs(candidates[m].time_j - c.time_j) < gap_s
                    for m in g
                )
            ),
            None,
        )
        if home is None:
            groups.append([k])
        else:
            home.append(k)
    return groups


@pytest.mark.parametrize("seed", range(6))
def test_pass_groups_keep_only_recent_members_and_group_the_same(seed) -> None:
    """Grouping with only the members within the gap at hand (what keeps a two-hour
    survey's tens of thousands of candidates quick) groups exactly as scanning every
    member did: passes that interleave, touch, restart, and jitter in time."""
    from mapping.closures import ClosureCandidate, _pass_groups

    rng = np.random.default_rng(seed)
    candidates = []
    for _ in range(int(rng.integers(20, 200))):
        lane_i = int(rng.integers(0, 6))
        lane_j = lane_i + int(rng.integers(1, 4))
        t_i = 100.0 * lane_i + rng.uniform(0, 100)
        t_j = 100.0 * lane_j + (100 - (t_i - 100 * lane_i)) + rng.normal(0, 6)
        candidates.append(ClosureCandidate(0, 1, float(t_i), float(t_j), ()))
    for gap in (3.0, 8.0, 30.0):
        assert _pass_groups(candidates, gap) == _groups_by_scanning_every_member(candidates, gap)
