"""Choosing loop closures that are right, on seabeds that repeat.

Periodic seabeds (bedform ripples a third of a metre apart, quadrat rows and farm racks a
metre apart) give strong false correlation peaks one period away, no farther than the
GNSS error between lanes; one wrong closure outweighs a lane's GNSS and the solver bends
the map to fit it. So a closure is taken only when three things agree:

1. **Several hypotheses** per candidate pair (the registrar's best distinct peaks), each
   compared with where the graph without closures puts frame j relative to frame i, in
   that prediction's own covariance (the linearised marginal of the solved graph) plus
   the closure's: a squared Mahalanobis distance d^2.
2. **Mutual consistency** between closures of the same pair of passes (Mangelson et al.,
   "Pairwise Consistent Measurement Set Maximization", ICRA 2018,
   doi:10.1109/ICRA.2018.8460217): two right closures imply the same correction of one
   pass against the other (the GNSS bias and the chain's drift change slowly), two wrong
   ones one period apart from it. Hypotheses are grouped by the correction they imply;
   the group supported by the most candidates wins, and only if no other group, also
   consistent with the prediction, comes close (a periodic seabed the graph cannot tell
   apart is left unclosed rather than closed wrong).
3. **A robust solve**: the kept closures enter with a Cauchy kernel, and any that still
   disagree with the solution beyond the gate are dropped before the final solve.

Each hypothesis has been registered again on the seabed both frames share
(``mapping.overlap``). Closures between opposite headings still carry an extra
uncertainty, measured: shading and shadows move with the view direction.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mapping.fusion import Fusion, RelativeConstraint, relative_chi2, sqrt_information
from mapping.se2 import RelativePose, compose, relative_pose, wrap_pi

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ClosureHypothesis:
    """One peak of a candidate pair: pose of j in i (vehicle frame), its covariance
    (3 x 3, forward m, starboard m, yaw rad) and similarity score."""

    relative: RelativePose
    covariance: Array
    score: float


@dataclass(frozen=True, slots=True)
class ClosureCandidate:
    """Frames i < j (node numbers of the graph) and their hypotheses, best first."""

    i: int
    j: int
    time_i: float
    time_j: float
    hypotheses: tuple[ClosureHypothesis, ...]


@dataclass(frozen=True, slots=True)
class ClosureParams:
    gate_chi2: float = 11.34
    """Squared Mahalanobis distance from the prediction (3 dof, 99 %)."""
    consistency_chi2: float = 9.21
    """Between two closures' implied corrections (2 dof, 99 %)."""
    drift_sigma_m: float = 0.02
    """Change of the inter-pass correction between two closures: at zero time apart..."""
    drift_rate_mps: float = 0.004
    """...growing by this per second apart (GNSS bias wander against the chain)."""
    ambiguity_ratio: float = 0.7
    """A rival group with this share of the winner's support, also within the gate,
    makes the pass pair ambiguous: no closure is taken there."""
    distinct_m: float = 0.1
    """Rival clusters count as another mode only this far apart (the shortest seabed
    period that matters, ripples of 0.2-0.45 m, is more than twice this)."""
    pass_gap_s: float = 8.0
    """Candidates further apart than this in either frame's time belong to other passes."""
    opposite_look_sigma_m: tuple[float, float] = (0.035, 0.03)
    """Extra (forward, starboard) sigma of a closure between headings more than 90
    degrees apart, and..."""
    opposite_yaw_sigma_deg: float = 0.15
    """...its extra yaw sigma. Measured on 278 kept closures between opposite lanes of
    eight surveys of the accuracy matrix, registered again on their shared seabed
    (``mapping.overlap``): 4.4 / 4.2 cm RMS (forward / starboard) and 0.46 degrees against
    the truth, where the registrar's sigmas with the loop floor (median 1.2 / 1.4 cm, 0.18
    degrees) say less: these terms bring the normalised errors' RMS to 1.0 / 0.8 / 1.0.
    About 3 cm of it is shared by the closures of one pair of passes (43 pairs)."""


@dataclass
class ClosureReport:
    candidates: int = 0
    pass_pairs: int = 0
    rejected_gate: int = 0
    rejected_inconsistent: int = 0
    rejected_ambiguous: int = 0
    rejected_residual: int = 0
    kept: int = 0
    details: list[dict[str, float]] = field(default_factory=list)


def _pass_groups(candidates: Sequence[ClosureCandidate], gap_s: float) -> list[list[int]]:
    """Groups of candidates close in both frames' times: in order of the earlier frame's
    time, each candidate joins the first group (in the order they began) with a member
    less than ``gap_s`` from it in both times, else begins a group. Only members less
    than ``gap_s`` before it can qualify, so each group keeps just those at hand (a
    survey of hours has tens of thousands of candidates)."""
    order = sorted(range(len(candidates)), key=lambda k: candidates[k].time_i)
    groups: list[list[int]] = []
    recent: list[deque[int]] = []  # per group, its members within gap_s of the present
    open_groups: list[int] = []  # groups with recent members, in the order they began
    for k in order:
        c = candidates[k]
        home = None
        still_open = []
        for g in open_groups:
            window = recent[g]
            while window and c.time_i - candidates[window[0]].time_i >= gap_s:
                window.popleft()
            if not window:
                continue
            still_open.append(g)
            if home is None and any(
                abs(candidates[m].time_i - c.time_i) < gap_s
                and abs(candidates[m].time_j - c.time_j) < gap_s
                for m in window
            ):
                home = g
        open_groups = still_open
        if home is None:
            home = len(groups)
            groups.append([])
            recent.append(deque())
            open_groups.append(home)
        groups[home].append(k)
        recent[home].append(k)
    return groups


def _look_covariance(poses: Array, c: ClosureCandidate, params: ClosureParams) -> Array:
    """Extra covariance (vehicle frame of i) of a closure between opposite headings."""
    dpsi = abs(float(wrap_pi(poses[c.j, 2] - poses[c.i, 2])))
    if dpsi <= math.pi / 2:
        return np.zeros((3, 3))
    forward, starboard = params.opposite_look_sigma_m
    return np.diag([forward**2, starboard**2, math.radians(params.opposite_yaw_sigma_deg) ** 2])


def _correction(poses: Array, c: ClosureCandidate, h: ClosureHypothesis) -> Array:
    """Where the hypothesis puts frame j minus where the graph has it (world east/north
    metres, yaw radians)."""
    implied = compose(poses[c.i], h.relative)
    d = implied - poses[c.j]
    d[2] = wrap_pi(d[2])
    return d


def world_rotation(heading: float) -> Array:
    """(forward, starboard, yaw) in the frame of a pose at ``heading`` to (east, north,
    yaw): east = f sin + st cos, north = f cos - st sin."""
    s, c = math.sin(heading), math.cos(heading)
    return np.array([[s, c, 0.0], [c, -s, 0.0], [0.0, 0.0, 1.0]])


def _world_cov(poses: Array, i: int, cov: Array) -> Array:
    """A covariance in the frame of pose i turned into world east/north (2 x 2)."""
    rot = world_rotation(float(poses[i, 2]))[:2, :2]
    return np.asarray(rot @ cov[:2, :2] @ rot.T, float)


def select_closures(
    fusion: Fusion,
    poses: Array,
    candidates: Sequence[ClosureCandidate],
    params: ClosureParams,
    report: ClosureReport,
    internal: Array | None = None,
) -> list[RelativeConstraint]:
    """The closures to add to the solved graph (``fusion``'s last solution, ``poses``
    its node poses), as robust constraints.

    internal: (n, 3, 3) covariance each node carries that the graph does not know of
    (two-stage: its drift from its rigid submap's anchor), added to the prediction and to
    the closures' own covariance: a rigid submap cannot bend to a closure at its far end,
    so a closure that did not know of that drift would turn the whole submap to fit it."""
    report.candidates = len(candidates)
    live = [c for c in candidates if c.hypotheses]
    if not live:
        return []
    predicted = fusion.relative_covariances([(c.i, c.j) for c in live])
    if internal is not None:
        predicted = predicted + np.stack([internal[c.i] + internal[c.j] for c in live])
    # Per candidate and hypothesis: distance to the prediction and implied correction.
    d2: list[list[float]] = []
    corr: list[list[Array]] = []
    cov_total: list[list[Array]] = []
    for c, sigma_pred in zip(live, predicted, strict=True):
        rel = relative_pose(poses[c.i], poses[c.j])
        look = _look_covariance(poses, c, params)
        row_d2, row_corr, row_cov = [], [], []
        for hyp in c.hypotheses:
            e = np.array(
                [
                    hyp.relative.forward_m - rel.forward_m,
                    hyp.relative.starboard_m - rel.starboard_m,
                    wrap_pi(hyp.relative.yaw_rad - rel.yaw_rad),
                ]
            )
            total = sigma_pred + hyp.covariance + look
            row_d2.append(float(e @ np.linalg.solve(total, e)))
            row_corr.append(_correction(poses, c, hyp))
            row_cov.append(hyp.covariance + look)
        d2.append(row_d2)
        corr.append(row_corr)
        cov_total.append(row_cov)

    chosen: list[tuple[int, int]] = []  # (candidate, hypothesis)
    groups = _pass_groups(live, params.pass_gap_s)
    report.pass_pairs = len(groups)
    for group in groups:
        # Every hypothesis of the group seeds a cluster of consistent corrections.
        g_corr, g_cov, g_valid = _group_arrays(poses, live, group, corr, cov_total)
        t_i = np.array([live[k].time_i for k in group])
        t_j = np.array([live[k].time_j for k in group])
        clusters: list[tuple[int, float, list[tuple[int, int]]]] = []
        for s0, k0 in enumerate(group):
            for h0 in range(len(live[k0].hypotheses)):
                dt = np.maximum(np.abs(t_i - t_i[s0]), np.abs(t_j - t_j[s0]))
                drift = (params.drift_sigma_m + params.drift_rate_mps * dt) ** 2
                diff = g_corr - g_corr[s0, h0]
                cov = g_cov + g_cov[s0, h0] + drift[:, None, None, None] * np.eye(2)
                dist = _mahalanobis_2d(diff, cov)
                # Of a candidate's hypotheses consistent with the seed, the registrar's
                # strongest (they come best first), not the nearest: a broad, weak peak
                # is always near in its own covariance.
                consistent = g_valid & (dist < params.consistency_chi2)
                first = np.argmax(consistent, axis=1)
                members = [
                    (group[m], int(first[m])) for m in np.flatnonzero(consistent.any(axis=1))
                ]
                gate = float(np.median([d2[k][h] for k, h in members]))
                clusters.append((len(members), gate, members))
        inside = [cl for cl in clusters if cl[1] < params.gate_chi2]
        if not inside:
            report.rejected_gate += len(group)
            continue
        inside.sort(key=lambda cl: (-cl[0], cl[1]))
        winner = inside[0]
        winner_set = {k for k, _ in winner[2]}
        # A rival: a cluster within the gate that shares no hypothesis with the winner and
        # implies another correction (a different mode, e.g. a period away), nearly as
        # well supported.
        winner_members = set(winner[2])
        rival = next(
            (
                cl
                for cl in inside[1:]
                if cl[0] >= params.ambiguity_ratio * winner[0]
                and not winner_members & set(cl[2])
                and _distinct(winner[2], cl[2], corr, params.distinct_m)
            ),
            None,
        )
        if rival is not None:
            report.rejected_ambiguous += len(group)
            continue
        report.rejected_inconsistent += len(group) - len(winner_set)
        for k, h in winner[2]:
            if d2[k][h] < params.gate_chi2:
                chosen.append((k, h))
            else:
                report.rejected_gate += 1
    constraints = []
    for k, h in chosen:
        c = live[k]
        hyp = c.hypotheses[h]
        cov = hyp.covariance + _look_covariance(poses, c, params)
        if internal is not None:
            cov = cov + internal[c.i] + internal[c.j]
        constraints.append(
            RelativeConstraint(
                c.i,
                c.j,
                hyp.relative.forward_m,
                hyp.relative.starboard_m,
                hyp.relative.yaw_rad,
                sqrt_information(cov),
                robust=True,
                kind="closure",
            )
        )
        report.details.append(
            {"i": float(c.i), "j": float(c.j), "d2": d2[k][h], "score": hyp.score}
        )
    return constraints


def _group_arrays(
    poses: Array,
    live: Sequence[ClosureCandidate],
    group: Sequence[int],
    corr: list[list[Array]],
    cov_total: list[list[Array]],
) -> tuple[Array, Array, npt.NDArray[np.bool_]]:
    """A group's corrections (g, h, 2), their world covariances (g, h, 2, 2) and which
    of the (candidate, hypothesis) slots hold one (g, h)."""
    width = max(len(live[k].hypotheses) for k in group)
    g_corr = np.zeros((len(group), width, 2))
    g_cov = np.tile(np.eye(2), (len(group), width, 1, 1))
    valid = np.zeros((len(group), width), bool)
    for m, k in enumerate(group):
        for h in range(len(live[k].hypotheses)):
            g_corr[m, h] = corr[k][h][:2]
            g_cov[m, h] = _world_cov(poses, live[k].i, cov_total[k][h])
            valid[m, h] = True
    return g_corr, g_cov, valid


def _mahalanobis_2d(diff: Array, cov: Array) -> Array:
    """diff^T cov^-1 diff over the leading axes (diff (..., 2), cov (..., 2, 2))."""
    a, b, c, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 0], cov[..., 1, 1]
    x, y = diff[..., 0], diff[..., 1]
    det = a * d - b * c
    return np.asarray((d * x * x - (b + c) * x * y + a * y * y) / det, float)


def _distinct(
    a: list[tuple[int, int]], b: list[tuple[int, int]], corr: list[list[Array]], apart_m: float
) -> bool:
    """Two clusters imply corrections further apart than ``apart_m`` on average."""
    ma = np.mean([corr[k][h][:2] for k, h in a], axis=0)
    mb = np.mean([corr[k][h][:2] for k, h in b], axis=0)
    return bool(np.linalg.norm(ma - mb) > apart_m)


def prune_closures(
    poses: Array,
    closures: Sequence[RelativeConstraint],
    params: ClosureParams,
    report: ClosureReport,
) -> list[RelativeConstraint]:
    """Closures that still disagree with the solution beyond the gate (their own
    covariance only, which is strict) are dropped."""
    if not closures:
        return []
    chi2 = relative_chi2(poses, closures)
    keep = chi2 < 4.0 * params.gate_chi2
    report.rejected_residual += int((~keep).sum())
    return [c for c, k in zip(closures, keep, strict=True) if k]
