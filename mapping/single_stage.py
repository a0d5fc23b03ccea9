"""Single-stage mapping: every frame of a survey placed by one fusion of its registrations,
loop closures and navigation measurements, all weighted in physical units
(``mapping.fusion``), over a graph that never breaks (``mapping.survey_graph``) and with
closures chosen robustly (``mapping.closures``)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from mapping.closures import (
    ClosureCandidate,
    ClosureParams,
    ClosureReport,
    prune_closures,
    select_closures,
)
from mapping.frames import FrameOutcome, LocalRegistration, SonarMount
from mapping.fusion import (
    Fusion,
    FusionParams,
    FusionSolution,
    RelativeConstraint,
    RigidGroups,
    sqrt_information,
)
from mapping.loops import LoopParams, LoopReport, find_candidates, register_hypotheses
from mapping.navigation import NavInputs
from mapping.posegraph import Edge
from mapping.samples import Ping
from mapping.se2 import RelativePose, compose, relative_pose
from mapping.survey_graph import GraphParams, chain_constraints, fusion_data
from mapping.tasks import TaskPool

Array = npt.NDArray[np.float64]


ClosureSource = Callable[
    [Array], tuple[Iterable[Ping], LocalRegistration, tuple[float, float], float]
]


@dataclass(frozen=True, slots=True)
class SingleStageParams:
    fusion: FusionParams = field(default_factory=FusionParams)
    graph: GraphParams = field(default_factory=GraphParams)
    closures: ClosureParams = field(default_factory=ClosureParams)
    closure_rounds: int = 2
    """Closures are chosen this many times, each against the graph the previous choice
    tied together."""
    variance_rounds: int = 4
    """How many times the registrations' and the fixes' covariances may be widened to
    what their residuals say (``variance_components``); 0: taken as stated."""


@dataclass
class SingleStageResult:
    poses: Array  # (n, 3), NaN where not a node
    closures: list[Edge]
    solution: FusionSolution | None
    closure_report: ClosureReport
    summary: dict[str, Any]


def _coast_initial(
    initial: Array, chain: Sequence[RelativeConstraint], silent: npt.NDArray[np.bool_]
) -> Array:
    """Where the gyro was silent (``silent``, per node) the filter held its heading through
    whatever turn the boat made, and Gauss-Newton started there may not find its way
    back: those nodes start where the chain puts them instead, from the node before."""
    out = np.array(initial, float)
    for c in chain:
        if silent[c.j]:
            out[c.j] = compose(out[c.i], RelativePose(c.forward_m, c.starboard_m, c.yaw_rad))
    return out


def _as_edges(
    nodes: npt.NDArray[np.int64], constraints: Sequence[RelativeConstraint]
) -> list[Edge]:
    return [
        Edge(int(nodes[c.i]), int(nodes[c.j]), c.forward_m, c.starboard_m, c.yaw_rad)
        for c in constraints
    ]


def single_stage(
    times: Array,
    accepted: npt.NDArray[np.bool_],
    edges: Sequence[Edge],
    outcomes: Sequence[FrameOutcome],
    priors: Array,
    inputs: NavInputs,
    mount: SonarMount,
    params: SingleStageParams,
    loops: LoopParams,
    closure_source: Callable[
        [Array], tuple[Iterable[Ping], LocalRegistration, tuple[float, float], float]
    ]
    | None,
    loop_report: LoopReport,
    rigid_s: float | None = None,
    gyro: npt.NDArray[np.int64] | None = None,
    pool: TaskPool | None = None,
) -> SingleStageResult:
    """Place the accepted frames. ``closure_source(poses)`` gives what loop closures need
    (a fresh pass over the pings, a registration set-up, the lit range band and half the
    fan) or is None when closures are off.

    rigid_s: two-stage (the paper's baseline): runs of this many seconds of frames are first
    chained into rigid submaps (stage 1, as fmt-only does), and only the submaps' poses
    are solved (stage 2), against the same measurements. Consecutive submaps are tied by
    the registration between their end frames, which is what the paper's half-overlapping
    subsets share (both carry the same chained relative poses).

    gyro: every frame's gyro epoch (``navigation.gyro_epochs``): where the IMU was silent
    the filter held its heading, and the chain, not the priors, is where the solver
    starts from.

    pool: where the loop closures' registrations run (``mapping.tasks``; None: here)."""
    n = times.size
    nodes, chain = chain_constraints(
        times, accepted, edges, outcomes, priors, mount, params.graph, gyro
    )
    out = np.full((n, 3), np.nan)
    report = ClosureReport()
    if nodes.size == 0:
        return SingleStageResult(out, [], None, report, {})
    node_times = times[nodes]
    data = fusion_data(inputs, node_times, params.graph.sonar_latency_s)
    rigid = _rigid_groups(chain, node_times, rigid_s) if rigid_s else None
    if rigid is not None:
        chain = _loosen_links(chain, rigid, _internal_drift(rigid, chain, priors[nodes]))
    fusion = Fusion(node_times, data, params.fusion, rigid)
    initial = priors[nodes] if rigid is None else _anchor_priors(priors[nodes], rigid)
    if gyro is not None and rigid is None:
        initial = _coast_initial(initial, chain, gyro[nodes] < 0)
    solution, state = fusion.solve(initial, chain)
    # Two-stage's rigid submaps are a model the residuals cannot tell from the measurements:
    # what the submaps cannot bend shows as scatter, and re-weighing by it made the deep
    # survey's fixes and registrations thousands of times looser and turned the map by
    # 99 degrees (session 23). The paper's baseline weighs its measurements as stated.
    rounds = params.variance_rounds if rigid is None else 0
    chain, factors, widened = _widen_to_residuals(fusion, initial, chain, rounds)
    if widened is not None:
        solution, state = widened
    poses_nodes = solution.poses
    kept: list[RelativeConstraint] = []
    if closure_source is not None and nodes.size > 1:
        full = np.full((n, 3), np.nan)
        full[nodes] = poses_nodes
        pings, local, lit, half_fan = closure_source(full)
        pairs = find_candidates(times, full, accepted, mount, lit, half_fan, loops)
        found = register_hypotheses(pings, pairs, full, local, loops, loop_report, pool)
        position = {int(k): i for i, k in enumerate(nodes)}
        candidates = [
            ClosureCandidate(position[i], position[j], float(times[i]), float(times[j]), tuple(h))
            for i, j, h in found
            if i in position and j in position
        ]
        internal = _internal_drift(rigid, chain, poses_nodes) if rigid is not None else None
        kept = select_closures(fusion, poses_nodes, candidates, params.closures, report, internal)
        if kept:
            solution, state = fusion.solve(initial, chain + kept, state)
            # Once the passes are tied, the graph predicts every candidate far better
            # than the GNSS could: choose again from all of them against that prediction
            # (a closure taken a period away in the first round falls outside the gate).
            for _ in range(params.closure_rounds - 1):
                again = ClosureReport()
                kept = select_closures(
                    fusion, solution.poses, candidates, params.closures, again, internal
                )
                solution, state = fusion.solve(initial, chain + kept, state)
                report = again
            kept = prune_closures(solution.poses, kept, params.closures, report)
            solution, state = fusion.solve(initial, chain + kept, state)
        report.kept = len(kept)
        loop_report.kept = len(kept)
    out[nodes] = solution.poses
    summary = {
        "nodes": int(nodes.size),
        "registration_edges": sum(c.kind == "registration" for c in chain),
        "odometry_edges": sum(c.kind == "odometry" for c in chain),
        "closures": len(kept),
        "gyro_bias_dps": float(np.degrees(solution.gyro_bias_rps)),
        "compass_coefficients_deg": [float(v) for v in np.degrees(solution.compass_coefficients)],
        "gnss_time_offset_s": solution.time_offset_s,
        "gnss_bias_rms_m": float(np.sqrt(np.mean(solution.bias_xy**2))),
        "iterations": solution.iterations,
        "variance_factors": factors,
        "chi2_per_factor": {
            k: solution.chi2[k] / max(solution.counts.get(k, 1), 1) for k in solution.chi2
        },
    }
    return SingleStageResult(out, _as_edges(nodes, kept), solution, report, summary)


# The fewest rows a group's residuals must be checked by (its redundancy) before its
# variance factor is believed: at 8, a factor's own sigma is sqrt(2 / 8) = 0.5.
MIN_REDUNDANCY = 8.0


def _widen_to_residuals(
    fusion: Fusion, initial: Array, chain: list[RelativeConstraint], rounds: int
) -> tuple[list[RelativeConstraint], dict[str, Any], tuple[FusionSolution, Array] | None]:
    """The registrations' covariances (translation and yaw apart) and the GNSS fixes'
    (position and Doppler velocity apart) widened to what their own residuals say, where
    those say they scatter more than stated (variance component estimation,
    ``Fusion.variance_components``: chi-square over redundancy per group).

    A registration's covariance comes from its correlation peak's sharpness, which does
    not see a peak locked on the sonar's own insonification pattern (deep mud: wrong by
    35 cm at the median where the peak said 4 cm); a receiver's sigmas are the site
    configuration's or its own report.

    The groups are estimated together, both ways, as Foerstner's iteration does (a group
    that takes the blame for another's scatter gives it back in the next round), for at
    most ``rounds`` re-solves; a group moves only where its factor is significant (beyond
    two standard deviations of a chi-square of that redundancy: 1 + 2 sqrt(2 / r)) and
    checked by at least ``MIN_REDUNDANCY`` rows. Then the stated models are the floor: a
    group the iteration narrowed goes back to what it said (a short survey's chi-square
    is too noisy to trust a narrowing). The factors returned are the products over the
    rounds (``rounds``: how many ran), with the last solution (None: none ran)."""
    names = ("translation", "yaw", "gnss", "gnss_velocity")
    total = dict.fromkeys(names, 1.0)
    applied = 0
    solved: tuple[FusionSolution, Array] | None = None
    stated = list(chain)
    mask = np.array([c.kind == "registration" for c in chain], bool)

    def apply(factors: dict[str, float]) -> list[RelativeConstraint]:
        root = np.diag(
            [1.0 / math.sqrt(factors["translation"])] * 2 + [1.0 / math.sqrt(factors["yaw"])]
        )
        fusion.set_gnss_sigma_factors(
            math.sqrt(factors["gnss"]), math.sqrt(factors["gnss_velocity"])
        )
        return [
            replace(c, sqrt_info=c.sqrt_info @ root) if m else c
            for c, m in zip(stated, mask, strict=True)
        ]

    for _ in range(rounds):
        found = fusion.variance_components(
            {"translation": (mask, (0, 1)), "yaw": (mask, (2,))}, ("gnss", "gnss_velocity")
        )
        moved = False
        for name, (chi2, redundancy) in found.items():
            if redundancy < MIN_REDUNDANCY:
                continue
            factor = chi2 / redundancy
            if abs(factor - 1.0) > 2.0 * math.sqrt(2.0 / redundancy):
                total[name] *= factor
                moved = True
        if not moved:
            break
        applied += 1
        solved = fusion.solve(initial, apply(total), fusion.last_state)
    if applied:
        # The stated models are the floor: a group the iteration narrowed goes back.
        floored = {name: max(1.0, value) for name, value in total.items()}
        if floored != total:
            total = floored
            solved = fusion.solve(initial, apply(total), fusion.last_state)
        if any(value != 1.0 for value in total.values()):
            chain = apply(total)
    return chain, {**total, "rounds": applied}, solved


def _parents(chain: Sequence[RelativeConstraint], n: int) -> dict[int, RelativeConstraint]:
    """The chain's constraint into each node from an earlier one, its last
    (``chain_constraints`` gives every node but the first one or two, the last its
    parent)."""
    return {c.j: c for c in chain if c.i < c.j < n}


def _rigid_groups(
    chain: Sequence[RelativeConstraint], node_times: Array, seconds: float
) -> RigidGroups:
    """Stage 1: runs of nodes ``seconds`` of survey long, chained from their first node
    (fmt-only)."""
    n = node_times.size
    slot = np.floor((node_times - node_times[0]) / seconds).astype(np.int64)
    group = np.unique(slot, return_inverse=True)[1].astype(np.int64).reshape(-1)
    chained = np.zeros((n, 3))
    parent = _parents(chain, n)
    for k in range(1, n):
        c = parent.get(k)
        if c is None:
            chained[k] = chained[k - 1]
        else:
            chained[k] = compose(chained[c.i], RelativePose(c.forward_m, c.starboard_m, c.yaw_rad))
    offsets = np.zeros((n, 3))
    first = np.searchsorted(group, group)  # first node of each node's group
    for k in range(n):
        rel = relative_pose(chained[first[k]], chained[k])
        offsets[k] = (rel.forward_m, rel.starboard_m, rel.yaw_rad)
    return RigidGroups(group, offsets, int(group[-1]) + 1 if n else 0)


def _loosen_links(
    chain: Sequence[RelativeConstraint], rigid: RigidGroups, internal: Array
) -> list[RelativeConstraint]:
    """The constraints that join one submap to the next, with the drift the earlier
    submap's frozen chain carries at its end added to their covariance: the submap's
    shape is fixed, its errors are not gone, and a link that did not know of them would
    hold the next submap to the wrong heading against the gyro and the compass.

    One link a pair of submaps: the one into the later submap's first node. Other frames
    of it registered against a keyframe of the earlier submap are tied to it through
    their rigid place (their registrations made that place); links of their own would
    count the drift they share once each."""
    out = []
    first = np.searchsorted(rigid.group, rigid.group)
    for c in chain:
        if rigid.group[c.i] == rigid.group[c.j]:
            out.append(c)
            continue
        if c.j != first[c.j]:
            continue
        cov = np.linalg.inv(c.sqrt_info.T @ c.sqrt_info) + internal[c.i] + internal[c.j]
        out.append(replace(c, sqrt_info=sqrt_information(cov)))
    return out


def _anchor_priors(priors: Array, rigid: RigidGroups) -> Array:
    """Each submap's starting pose: its first frame's prior."""
    first = np.searchsorted(rigid.group, np.arange(rigid.n_groups))
    return np.asarray(priors[first], float)


def _internal_drift(rigid: RigidGroups, chain: Sequence[RelativeConstraint], poses: Array) -> Array:
    """(n, 3, 3) covariance of each node against its submap's anchor: the chained
    registrations' own (random-walk) errors, which a rigid submap holds at zero. Variance
    adds up along the chain's tree from the anchor (a node whose constraint comes from
    before the anchor: from that node through the anchor's own chain); the translation
    also takes the lateral effect of the yaw variance over the distance from the anchor."""
    n = rigid.group.size
    step = np.zeros((n, 3))
    parent = np.arange(n) - 1
    for k, c in _parents(chain, n).items():
        step[k] = np.diag(np.linalg.inv(c.sqrt_info.T @ c.sqrt_info))
        parent[k] = c.i
    total = np.zeros((n, 3))  # from the first node, along the tree
    for k in range(1, n):
        total[k] = total[parent[k]] + step[k]
    out = np.zeros((n, 3, 3))
    first = np.searchsorted(rigid.group, rigid.group)
    var = np.zeros((n, 3))
    for k in range(n):
        a = int(first[k])
        if k == a:
            continue
        p = int(parent[k])
        # From the anchor to the parent, then the step; a parent before the anchor is
        # reached back through the anchor's chain.
        var[k] = step[k] + (var[p] if p >= a else np.abs(total[a] - total[max(p, 0)]))
        distance = float(np.hypot(*(poses[k, :2] - poses[a, :2])))
        lateral = var[k, 2] * distance**2 / 3.0
        out[k] = np.diag([var[k, 0] + lateral, var[k, 1] + lateral, var[k, 2]])
    return out
