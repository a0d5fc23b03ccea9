"""The paper's pipeline over a whole survey (Zhang et al., Algorithm 1), in four modes.

- ``fmt-only``: the baseline, frames placed by chaining the accepted registrations;
- ``gps-only``: frames placed on the EKF-smoothed global priors alone;
- ``single-stage``: registrations and priors fused by the least-squares optimisation;
- ``two-stage``: 50%-overlapping subsets mapped as the baseline (stage 1), then the
  subsets, as rigid submaps, placed by the same optimisation against the priors, with the
  registrations between overlapping subsets (stage 2).

The core does no I/O: pings come from a callable that yields them afresh for each pass
(the first pass reads times, the second registers, the last blends), so memory stays
bounded by the mosaic, not the survey.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from mapping.blend import BlendParams, FeatureScorer
from mapping.ekf import EkfParams
from mapping.fmt import FmtParams, RelativePose
from mapping.frames import (
    FrameOutcome,
    LocalRegistration,
    RegistrationParams,
    SonarMount,
    compose,
    relative_pose,
)
from mapping.geo import LocalFrame
from mapping.loops import (
    LoopParams,
    LoopReport,
    find_candidates,
    optimise_with_closures,
    register_candidates,
    solve_with_closures,
)
from mapping.mosaic import SonarPose, TileGrid
from mapping.navigation import estimate_at, prepare_inputs
from mapping.posegraph import Edge, OptimiserParams, optimise
from mapping.preprocess import PreprocessParams
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping
from mapping.tiles import TileSpill, TileStore

Array = npt.NDArray[np.float64]


class Mode(StrEnum):
    SINGLE_STAGE = "single-stage"
    TWO_STAGE = "two-stage"
    FMT_ONLY = "fmt-only"
    GPS_ONLY = "gps-only"


@dataclass(frozen=True)
class NavSamples:
    imu: Sequence[ImuSample]
    gnss: Sequence[GnssFix]
    heading: Sequence[HeadingSample]
    attitude: Sequence[AttitudeSample] = ()


@dataclass(frozen=True)
class PipelineParams:
    preprocess: PreprocessParams = field(default_factory=PreprocessParams)
    fmt: FmtParams = field(default_factory=FmtParams)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    optimiser: OptimiserParams = field(default_factory=OptimiserParams)
    blend: BlendParams = field(default_factory=BlendParams)
    ekf: EkfParams = field(default_factory=EkfParams)
    mosaic_res_m: float = 0.02
    tile_px: int = 256
    smooth_nav: bool = True
    subset_frames: int = 60
    loops: LoopParams = field(default_factory=LoopParams)
    """two-stage: frames per subset (consecutive subsets overlap by half)."""


@dataclass
class SurveyResult:
    """Everything a replay reports: poses of the mapped frames, why others were not
    mapped, the mosaic tiles, timings per stage (seconds)."""

    frame: LocalFrame
    mode: Mode
    times: Array
    priors: Array  # (n, 3) EKF poses, NaN before the filter started
    poses: Array  # (n, 3) final vehicle poses (NaN where not mapped)
    mapped: npt.NDArray[np.bool_]
    outcomes: list[FrameOutcome]
    rejected: Counter[str]
    timings: dict[str, float]
    mosaic: TileStore
    edges: list[Edge]
    mount: SonarMount
    closures: list[Edge] = field(default_factory=list)
    loops: LoopReport = field(default_factory=LoopReport)

    @property
    def frames_read(self) -> int:
        return int(self.times.size)

    @property
    def frames_mapped(self) -> int:
        return int(self.mapped.sum())


class _Clock:
    def __init__(self) -> None:
        self.totals: dict[str, float] = {}

    def add(self, stage: str, started: float) -> float:
        now = time.perf_counter()
        self.totals[stage] = self.totals.get(stage, 0.0) + now - started
        return now


def _chain(n: int, accepted: npt.NDArray[np.bool_], edges: Sequence[Edge], priors: Array) -> Array:
    """Poses from chaining registrations; a chain restart (an accepted frame with no
    edge) bridges the gap with the EKF's relative motion."""
    poses = np.full((n, 3), np.nan)
    incoming = {e.j: e for e in edges}
    last: int | None = None
    for k in np.flatnonzero(accepted):
        edge = incoming.get(int(k))
        if last is None:
            poses[k] = priors[k]
        elif edge is not None:
            poses[k] = compose(
                poses[edge.i], RelativePose(edge.forward_m, edge.starboard_m, edge.yaw_rad)
            )
        else:
            poses[k] = compose(poses[last], relative_pose(priors[last], priors[k]))
        last = int(k)
    return poses


def _two_stage(
    accepted: npt.NDArray[np.bool_],
    edges: Sequence[Edge],
    closures: Sequence[Edge],
    priors: Array,
    prior_weights: Array,
    params: PipelineParams,
) -> Array:
    """Stage 1: subsets of ``subset_frames`` accepted frames, consecutive subsets sharing
    half their frames, each chained from its first frame (the baseline) into a rigid
    submap. Stage 2: the submap poses optimised with the paper's objective: a global prior
    per submap (the rigid fit of its frames to their EKF priors, weighted by their number)
    and a local edge between consecutive submaps from the frames they share."""
    index = np.flatnonzero(accepted)
    if index.size == 0:
        return np.full_like(priors, np.nan)
    size = max(params.subset_frames, 4)
    stride = size // 2
    subsets = [index[s : s + size] for s in range(0, max(index.size - stride, 1), stride)]
    chained = _chain(len(priors), accepted, edges, priors)
    offsets = [
        np.array([_relative_array(chained[sub[0]], chained[k]) for k in sub]) for sub in subsets
    ]
    submap_priors = np.array(
        [_fit_rigid(offs, priors[sub]) for sub, offs in zip(subsets, offsets, strict=True)]
    )
    submap_edges: list[Edge] = []
    for s in range(len(subsets) - 1):
        shared = np.intersect1d(subsets[s], subsets[s + 1])
        if shared.size == 0:
            continue
        k = int(shared[shared.size // 2])
        in_a = _as_relative(offsets[s][int(np.flatnonzero(subsets[s] == k)[0])])
        in_b = _as_relative(offsets[s + 1][int(np.flatnonzero(subsets[s + 1] == k)[0])])
        # Submap s+1 in submap s: frame k in s, then back from k to the anchor of s+1.
        between = RelativePose.from_matrix(in_a.matrix() @ np.linalg.inv(in_b.matrix()))
        submap_edges.append(
            Edge(s, s + 1, between.forward_m, between.starboard_m, between.yaw_rad, shared.size)
        )
    # A loop closure between frames of two submaps ties the submaps the same way.
    home = {}
    for s in range(len(subsets) - 1, -1, -1):
        for position, k in enumerate(subsets[s]):
            home[int(k)] = (s, position)
    for closure in closures:
        if closure.i not in home or closure.j not in home:
            continue
        (sa, pa), (sb, pb) = home[closure.i], home[closure.j]
        if sa == sb:
            continue
        link = RelativePose(closure.forward_m, closure.starboard_m, closure.yaw_rad)
        between = RelativePose.from_matrix(
            _as_relative(offsets[sa][pa]).matrix()
            @ link.matrix()
            @ np.linalg.inv(_as_relative(offsets[sb][pb]).matrix())
        )
        submap_edges.append(
            Edge(sa, sb, between.forward_m, between.starboard_m, between.yaw_rad, closure.weight)
        )
    weights = np.array([prior_weights[sub].sum(axis=0) for sub in subsets], float)
    solution = optimise(submap_priors, submap_priors, submap_edges, params.optimiser, weights)
    poses = np.full_like(priors, np.nan)
    for s in range(len(subsets) - 1, -1, -1):
        # Earlier submaps win where subsets overlap (written last).
        for k, off in zip(subsets[s], offsets[s], strict=True):
            poses[k] = _compose_array(solution.poses[s], off)
    return poses


def _relative_array(a: Array, b: Array) -> Array:
    r = relative_pose(a, b)
    return np.array([r.forward_m, r.starboard_m, r.yaw_rad])


def _compose_array(a: Array, rel: Array) -> Array:
    return compose(a, RelativePose(float(rel[0]), float(rel[1]), float(rel[2])))


def _as_relative(rel: Array) -> RelativePose:
    return RelativePose(float(rel[0]), float(rel[1]), float(rel[2]))


def _fit_rigid(offsets: Array, targets: Array) -> Array:
    """Submap pose (its first frame's) whose frames at ``offsets`` best fit ``targets``
    (least squares on positions: 2-D Procrustes; Umeyama 1991, doi:10.1109/34.88573)."""
    src = np.array([_compose_array(np.zeros(3), o)[:2] for o in offsets])
    dst = targets[:, :2]
    src_c, dst_c = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - src_c, dst - dst_c
    # Counter-clockwise rotation (east-north axes) taking a onto b.
    theta = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b)))
    c, s = math.cos(theta), math.sin(theta)
    anchor_xy = np.array([[c, -s], [s, c]]) @ (-src_c) + dst_c
    # A counter-clockwise turn of the east-north axes lowers a clockwise heading.
    return np.array([anchor_xy[0], anchor_xy[1], (-theta) % (2 * math.pi)])


def _place_frames(
    mode: Mode,
    accepted: npt.NDArray[np.bool_],
    edges: Sequence[Edge],
    closures: Sequence[Edge],
    priors: Array,
    weights: Array,
    params: PipelineParams,
) -> Array:
    """Vehicle poses of the accepted frames by ``mode`` (NaN for the others)."""
    if mode is Mode.GPS_ONLY:
        return np.where(accepted[:, None], priors, np.nan)
    if mode is Mode.FMT_ONLY:
        return _chain(len(priors), accepted, edges, priors)
    if mode is Mode.SINGLE_STAGE:
        return optimise_with_closures(priors, accepted, edges, closures, params.optimiser, weights)
    return _two_stage(accepted, edges, closures, priors, weights, params)


def blend_frames(
    pings: Iterable[Ping],
    poses: Array,
    mapped: npt.NDArray[np.bool_],
    mount: SonarMount,
    frame: LocalFrame,
    params: PipelineParams,
    clock: _Clock | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    spill: TileSpill | None = None,
) -> TileStore:
    """Warp every mapped frame to its pose and blend it into the tile mosaic (Algorithm 1,
    lines 15-26). ``poses`` are vehicle poses in ``frame``'s local coordinates."""
    clock = clock or _Clock()
    mosaic = TileStore(TileGrid(params.mosaic_res_m, params.tile_px), params.blend, spill)
    scorer = FeatureScorer(params.blend)
    preprocessing = LocalRegistration(mount, params.preprocess, params.fmt, params.registration)
    sonar_poses = mount.sonar_pose(poses)
    n = len(mapped)
    for index, ping in enumerate(pings):
        if index >= n:
            break
        if not mapped[index]:
            continue
        t0 = time.perf_counter()
        sonar_frame = preprocessing.frame(ping)
        t1 = clock.add("preprocess", t0)
        preprocessor = preprocessing.preprocessor
        assert preprocessor is not None and preprocessor.grid is not None
        score = scorer(sonar_frame.image, sonar_frame.mask, sonar_frame.weight)
        east, north = frame.to_utm(sonar_poses[index, 0], sonar_poses[index, 1])
        pose = SonarPose(float(east), float(north), float(sonar_poses[index, 2]))
        mosaic.insert(
            index, sonar_frame.image, score, sonar_frame.mask, preprocessor.grid, pose, ping.time
        )
        if index % 50 == 0:
            # Tiles the boat has left leave memory (a no-op in short surveys).
            mosaic.evict_idle(ping.time)
        clock.add("blending", t1)
        if progress is not None:
            progress("blending", index + 1, n)
    return mosaic


def map_survey(
    pings: Callable[[], Iterable[Ping]],
    nav: NavSamples,
    mount: SonarMount,
    params: PipelineParams | None = None,
    mode: Mode = Mode.SINGLE_STAGE,
    progress: Callable[[str, int, int], None] | None = None,
    registrations: Sequence[FrameOutcome] | None = None,
    spill: TileSpill | None = None,
) -> SurveyResult:
    """Map a survey: ``pings()`` yields the pings in time order, afresh on each call.

    registrations: the local registration of every frame, when already done (the
    streaming engine's survey-end pass reuses its own); otherwise they are computed.
    spill: where tiles the boat has left go (default: kept in memory, compressed).
    """
    params = params or PipelineParams()
    clock = _Clock()
    started = time.perf_counter()

    usable = [f for f in nav.gnss if f.usable]
    if not usable:
        raise ValueError("the navigation log has no usable GNSS fix: frames cannot be placed")
    frame = LocalFrame.around(usable[0].lat_deg, usable[0].lon_deg)
    inputs = prepare_inputs(frame, nav.imu, nav.gnss, nav.heading, nav.attitude, params.ekf)
    times = np.array([p.time for p in pings()], float)
    started = clock.add("read", started)
    n = times.size
    estimate = estimate_at(inputs, times, params.ekf, smooth=params.smooth_nav)
    priors = estimate.poses
    weights = estimate.prior_weights()
    started = clock.add("ekf", started)

    outcomes: list[FrameOutcome] = list(registrations) if registrations is not None else []
    registration = LocalRegistration(mount, params.preprocess, params.fmt, params.registration)
    for index, ping in enumerate(pings() if registrations is None else ()):
        if index >= n:
            break
        t0 = time.perf_counter()
        sonar_frame = registration.frame(ping)
        t1 = clock.add("preprocess", t0)
        prior = priors[index] if estimate.valid[index] else None
        if mode is Mode.GPS_ONLY:
            reason = "" if prior is not None else "no navigation prior"
            outcomes.append(FrameOutcome(index, ping.time, prior is not None, reason))
        else:
            outcomes.append(registration.register(index, ping.time, sonar_frame, prior))
        clock.add("registration", t1)
        if progress is not None:
            progress("registering", index + 1, n)
    if len(outcomes) != n:
        raise ValueError(f"{len(outcomes)} registrations for {n} frames")
    accepted = np.array([o.accepted for o in outcomes], bool)
    edges = [o.edge for o in outcomes if o.edge is not None]
    rejected = Counter(o.reason for o in outcomes if not o.accepted)

    t0 = time.perf_counter()

    def solve(closures: Sequence[Edge]) -> Array:
        return _place_frames(mode, accepted, edges, closures, priors, weights, params)

    poses = solve([])
    clock.add("optimisation", t0)
    loop_report = LoopReport()
    closures: list[Edge] = []
    uses_closures = mode in (Mode.SINGLE_STAGE, Mode.TWO_STAGE) and params.loops.enabled
    if uses_closures and n > 0:
        t0 = time.perf_counter()
        closer = LocalRegistration(mount, params.preprocess, params.fmt, params.registration)
        closer.frame(next(iter(pings())))  # the sonar's geometry
        preprocessor = closer.preprocessor
        assert preprocessor is not None
        lit = (preprocessor.min_range_m, preprocessor.fan.max_range_m)
        bearings = preprocessor.fan.bearings_rad
        half_fan = max(abs(bearings[0]), abs(bearings[-1]))
        pairs = find_candidates(times, poses, accepted, mount, lit, half_fan, params.loops)
        found = register_candidates(pings(), pairs, poses, closer, params.loops, loop_report)
        t1 = clock.add("loop_closure", t0)
        poses, closures = solve_with_closures(solve, found, params.loops, loop_report)
        clock.add("optimisation", t1)
    mapped = accepted & np.all(np.isfinite(poses), axis=1)

    mosaic = blend_frames(pings(), poses, mapped, mount, frame, params, clock, progress, spill)
    return SurveyResult(
        frame=frame,
        mode=mode,
        times=times,
        priors=priors,
        poses=np.where(mapped[:, None], poses, np.nan),
        mapped=mapped,
        outcomes=outcomes,
        rejected=rejected,
        timings=clock.totals,
        mosaic=mosaic,
        edges=edges,
        mount=mount,
        closures=closures,
        loops=loop_report,
    )
