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
from dataclasses import asdict, dataclass, field, replace
from enum import StrEnum
from itertools import islice
from typing import Any

import numpy as np
import numpy.typing as npt

from mapping.ahead import register_frames
from mapping.blend import BlendParams, make_scorer
from mapping.bottom import BottomParams, SeabedAttitude, SonarGeometry, seabed_attitude
from mapping.ekf import EkfParams
from mapping.fmt import FmtParams
from mapping.frames import (
    FrameOutcome,
    LocalRegistration,
    RegistrationParams,
    SonarMount,
    prepared_frames,
)
from mapping.geo import LocalFrame
from mapping.loops import (
    LoopParams,
    LoopReport,
)
from mapping.mosaic import SonarPose, TileGrid
from mapping.navigation import AttitudeTrack, estimate_at, gyro_epochs, prepare_inputs
from mapping.polar import Attitude
from mapping.posegraph import Edge, OptimiserParams
from mapping.preprocess import PreprocessParams, SonarFrame, lit_min_range
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping, RangeSample
from mapping.se2 import RelativePose, compose, relative_pose
from mapping.single_stage import SingleStageParams, single_stage
from mapping.sonar_depth import SonarHead
from mapping.survey_graph import GraphParams
from mapping.tasks import TaskPool
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
    ranges: Sequence[RangeSample] = ()
    """Soundings of a downward echosounder (``RangeSample``), when the boat carries one."""


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
    subset_s: float = 6.0
    """two-stage: survey seconds per rigid subset (the paper's 60 frames at 10 Hz). In
    frames, a subset at 2 Hz spanned 30 s and a U-turn, whose frozen shape the closures
    of the next lane could not meet (quadrats seed 10 at 2 Hz: 22.5 cm against 4.1
    single-stage)."""
    loops: LoopParams = field(default_factory=LoopParams)
    single_stage: SingleStageParams = field(default_factory=SingleStageParams)
    project_attitude: bool = True
    """Project each ping at the boat's roll and pitch when it was taken (else level)."""
    bottom: BottomParams = field(default_factory=BottomParams)
    """Where the seabed under each ping is found (``mapping.bottom``)."""
    register_ahead: bool = True
    """With a pool, the frames' registrations computed ahead in it (``mapping.ahead``:
    the same registrations to the bit). With the workers keeping the frames they prepared
    and their jobs through shared memory, ``seamap replay`` of quadrats seed 8 at 10 Hz
    (1,639 frames, whole process, this machine's runs spread by 10-25 %) took 68.5 s with
    two workers (median of five) against 80.7 s in one process (median of four), and
    about the same with one worker (80.0, 82.2)."""


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
    bottom: dict[str, Any] = field(default_factory=dict)
    """Where each ping's seabed came from (``mapping.bottom``): ``source`` "echosounder" or
    "configured", the soundings used, how many pings had a plane, their altitudes."""
    ahead: dict[str, int] = field(default_factory=dict)
    """With a pool: the registrations taken from it (``ahead``: computed ahead in worker
    processes) and those computed in the pass's own process (``here``)."""
    fusion: dict[str, Any] = field(default_factory=dict)
    """Single-stage: what the fusion estimated (gyro bias, compass error, GNSS offset)
    and how well each kind of measurement fits."""

    @property
    def frames_read(self) -> int:
        return int(self.times.size)

    @property
    def frames_mapped(self) -> int:
        return int(self.mapped.sum())

    @property
    def frames_unregistered(self) -> int:
        """Frames mapped whose registration was refused: placed by the odometry bridges
        and the navigation, blended below the registered ones (``blend_confidence``)."""
        accepted = np.array([o.accepted for o in self.outcomes], bool)
        return int((self.mapped & ~accepted).sum()) if accepted.size == self.mapped.size else 0


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


def _place_frames(
    mode: Mode,
    accepted: npt.NDArray[np.bool_],
    edges: Sequence[Edge],
    priors: Array,
) -> Array:
    """Vehicle poses of the accepted frames by a baseline ``mode`` (NaN for the others)."""
    if mode is Mode.GPS_ONLY:
        return np.where(accepted[:, None], priors, np.nan)
    return _chain(len(priors), accepted, edges, priors)


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
    attitude: Callable[[float], Attitude | None] | None = None,
    confidence: Array | None = None,
    pool: TaskPool | None = None,
) -> TileStore:
    """Warp every mapped frame to its pose and blend it into the tile mosaic (Algorithm 1,
    lines 15-26). ``poses`` are vehicle poses in ``frame``'s local coordinates;
    ``attitude`` the roll and pitch of each ping by its stamp; ``confidence`` each frame's
    factor on its blending score (``blend_confidence``; None: 1); ``pool``: where the
    frames are preprocessed (``prepared_frames``; None: here), the mosaic the same."""
    clock = clock or _Clock()
    mosaic = TileStore(TileGrid(params.mosaic_res_m, params.tile_px), params.blend, spill)
    scorer = make_scorer(params.blend)
    preprocessing = LocalRegistration(
        mount, params.preprocess, params.fmt, params.registration, attitude
    )
    sonar_poses = mount.sonar_pose(poses)
    n = len(mapped)
    chosen = ((i, ping) for i, ping in enumerate(islice(pings, n)) if mapped[i])
    t0 = time.perf_counter()  # preprocessing: here, or waiting for the pool
    for index, ping, prepared, preprocessor in prepared_frames(chosen, preprocessing, pool):
        sonar_frame = prepared if isinstance(prepared, SonarFrame) else prepared.result()
        t1 = clock.add("preprocess", t0)
        assert preprocessor.grid is not None
        score = scorer(
            sonar_frame.image, sonar_frame.mask, sonar_frame.weight, sonar_frame.fan_weight
        )
        if confidence is not None and confidence[index] < 1.0:
            score = score * np.float32(confidence[index])
        east, north = frame.to_utm(sonar_poses[index, 0], sonar_poses[index, 1])
        pose = SonarPose(float(east), float(north), float(sonar_poses[index, 2]))
        mosaic.insert(
            index,
            sonar_frame.image,
            score,
            sonar_frame.mask,
            preprocessor.grid,
            pose,
            ping.time,
            movable=False,
        )
        if index % 50 == 0:
            # Tiles the boat has left leave memory (a no-op in short surveys).
            mosaic.evict_idle(ping.time)
        if progress is not None:
            progress("blending", index + 1, n)
        t0 = clock.add("blending", t1)
    return mosaic


def blend_confidence(
    times: Array,
    accepted: npt.NDArray[np.bool_],
    mapped: npt.NDArray[np.bool_],
    graph: GraphParams,
    mount: SonarMount,
    cell_m: float,
) -> Array:
    """Each frame's factor on its blending score: 1 for a registered frame; for one placed
    without a registration, cell^2 / (cell^2 + sigma^2), sigma the spread of its seabed
    against the registered frames around it. That is the odometry bridges' sigma
    (``GraphParams.odometry_*``) from the nearest registered frame before and after it,
    the two combined as independent, its heading's share taken at twice the sonar's
    altitude (about the middle of a fan's lit band). A pose error within a mosaic cell
    costs nothing; a frame placed a few centimetres less surely than its neighbours
    gives way to them where they cover the seabed, and is the map where nothing else is.
    """
    n = times.size
    out = np.ones(n)
    loose = mapped & ~accepted
    if not loose.any():
        return out
    anchors = np.flatnonzero(accepted & mapped)
    lever = 2.0 * max(mount.altitude_m, 0.5)

    def variance(dt: Array) -> Array:
        sigma_p = graph.odometry_sigma_m + graph.odometry_velocity_sigma_mps * dt
        sigma_a = graph.odometry_sigma_rad + graph.odometry_rate_sigma_rps * dt
        return sigma_p**2 + (lever * sigma_a) ** 2

    index = np.flatnonzero(loose)
    total = np.zeros(index.size)
    if anchors.size:
        after = np.searchsorted(anchors, index)
        before_t = np.where(after > 0, times[anchors[np.maximum(after - 1, 0)]], -np.inf)
        after_t = np.where(
            after < anchors.size, times[anchors[np.minimum(after, anchors.size - 1)]], np.inf
        )
        info = 1.0 / variance(np.abs(times[index] - before_t)) + 1.0 / variance(
            np.abs(after_t - times[index])
        )
        total = np.where(info > 0, 1.0 / np.maximum(info, 1e-300), np.inf)
    else:
        total[:] = np.inf
    out[index] = np.maximum(cell_m**2 / (cell_m**2 + total), CONFIDENCE_FLOOR)
    return out


CONFIDENCE_FLOOR = 1e-4
"""Least blending factor of a placed frame: however loosely placed, a patch of seabed
only it saw still shows (no holes where a frame covers)."""


def sonar_geometry(first: Ping, mount: SonarMount, params: PipelineParams) -> SonarGeometry:
    """What the bottom model needs of the sonar (``bottom.SonarGeometry``), from a ping of
    the survey and the mount."""
    bearings = np.asarray(first.bearings_rad, float)
    p = params.preprocess
    return SonarGeometry(
        down_m=mount.down_m,
        altitude_m=mount.altitude_m,
        max_range_m=first.max_range_m,
        half_fan_rad=float(np.max(np.abs(bearings))) if bearings.size else 0.0,
        lit_range_m=lit_min_range(
            mount.altitude_m,
            math.degrees(mount.tilt_rad),
            p.vertical_aperture_deg,
            p.near_margin_deg,
        ),
        sonar_pose=mount.sonar_pose,
        head=SonarHead(
            mount.tilt_rad, (mount.forward_m, mount.starboard_m, mount.down_m), mount.yaw_rad
        ),
    )


def _seabed(
    pings: Callable[[], Iterable[Ping]],
    nav: NavSamples,
    times: Array,
    priors: Array,
    tilt_at: Callable[[float], Attitude | None] | None,
    mount: SonarMount,
    params: PipelineParams,
    pool: TaskPool | None = None,
) -> SeabedAttitude | None:
    """Each ping's altitude and bottom slope from the echosounder, else the sonar's own
    pings (``mapping.bottom``), or None (the mount's altitude, level)."""
    b = params.bottom
    echosounder = bool(nav.ranges) and b.use_echosounder
    if times.size == 0 or not (echosounder or b.use_sonar) or mount.altitude_m <= 0:
        return None
    geometry = sonar_geometry(next(iter(pings())), mount, params)
    p = params.preprocess
    # The sonar's vertical beam as the preprocessing takes it.
    aperture = math.radians(p.vertical_aperture_deg)
    b = replace(b, sonar=replace(b.sonar, vertical_aperture_rad=aperture))
    return seabed_attitude(nav.ranges, times, priors, tilt_at, geometry, b, pings, pool)


def map_survey(
    pings: Callable[[], Iterable[Ping]],
    nav: NavSamples,
    mount: SonarMount,
    params: PipelineParams | None = None,
    mode: Mode = Mode.SINGLE_STAGE,
    progress: Callable[[str, int, int], None] | None = None,
    registrations: Sequence[FrameOutcome] | None = None,
    spill: TileSpill | None = None,
    pool: TaskPool | None = None,
) -> SurveyResult:
    """Map a survey: ``pings()`` yields the pings in time order, afresh on each call.

    registrations: the local registration of every frame, when already done (the
    streaming engine's survey-end pass reuses its own); otherwise they are computed.
    spill: where tiles the boat has left go (default: kept in memory, compressed).
    pool: where the pure tasks run (the loop closures' registrations; ``mapping.tasks``,
    None: here): the map is the same wherever they do.
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
    gyro = gyro_epochs(inputs, times, params.ekf.max_imu_gap_s)
    started = clock.add("ekf", started)

    outcomes: list[FrameOutcome] = list(registrations) if registrations is not None else []
    ahead: dict[str, int] = {}
    track = AttitudeTrack(nav.attitude, params.single_stage.graph.sonar_latency_s)
    attitude: Callable[[float], Attitude | None] | None = (
        track.at if params.project_attitude else None
    )
    seabed = _seabed(pings, nav, times, priors, attitude, mount, params, pool)
    agrees: SeabedAttitude | None = None
    if seabed is not None and seabed.configured_holds:
        agrees, seabed = seabed, None
    if seabed is not None:
        attitude = seabed
    started = clock.add("bottom", started)
    registration = LocalRegistration(
        mount, params.preprocess, params.fmt, params.registration, attitude
    )
    if registrations is None and mode is Mode.GPS_ONLY:
        for index, ping in enumerate(pings()):
            # Placed by its prior alone: its image is first looked at when blending.
            prior = priors[index] if estimate.valid[index] else None
            reason = "" if prior is not None else "no navigation prior"
            outcomes.append(FrameOutcome(index, ping.time, prior is not None, reason))
    elif registrations is None:
        outcomes = register_frames(
            pings(), n, registration, priors, estimate.valid, gyro,
            pool if params.register_ahead else None, clock.add, progress, ahead,
        )  # fmt: skip
    if len(outcomes) != n:
        raise ValueError(f"{len(outcomes)} registrations for {n} frames")
    accepted = np.array([o.accepted for o in outcomes], bool)
    edges = [o.edge for o in outcomes if o.edge is not None]
    rejected = Counter(o.reason for o in outcomes if not o.accepted)

    t0 = time.perf_counter()
    loop_report = LoopReport()
    closures: list[Edge] = []
    fusion_summary: dict[str, Any] = {}
    uses_closures = mode in (Mode.SINGLE_STAGE, Mode.TWO_STAGE) and params.loops.enabled

    def closure_source(
        current: Array,
    ) -> tuple[Iterable[Ping], LocalRegistration, tuple[float, float], float]:
        closer = LocalRegistration(
            mount, params.preprocess, params.fmt, params.registration, attitude
        )
        closer.frame(next(iter(pings())))  # the sonar's geometry
        preprocessor = closer.preprocessor
        assert preprocessor is not None
        lit = (preprocessor.min_range_m, preprocessor.fan.max_range_m)
        bearings = preprocessor.fan.bearings_rad
        half_fan = max(abs(bearings[0]), abs(bearings[-1]))
        return pings(), closer, lit, half_fan

    if mode in (Mode.SINGLE_STAGE, Mode.TWO_STAGE):
        placed = single_stage(
            times,
            accepted,
            edges,
            outcomes,
            priors,
            inputs,
            mount,
            params.single_stage,
            params.loops,
            closure_source if uses_closures and n > 0 else None,
            loop_report,
            rigid_s=params.subset_s if mode is Mode.TWO_STAGE else None,
            gyro=gyro,
            pool=pool,
        )
        poses, closures = placed.poses, placed.closures
        fusion_summary = {**placed.summary, "closures": asdict(placed.closure_report)}
    else:
        poses = _place_frames(mode, accepted, edges, priors)
    clock.add("optimisation", t0)
    placed = np.all(np.isfinite(poses), axis=1)
    graph = params.single_stage.graph
    if mode in (Mode.SINGLE_STAGE, Mode.TWO_STAGE) and graph.place_rejected:
        mapped = placed  # a frame whose registration was refused is placed all the same
    else:
        mapped = accepted & placed
    confidence = blend_confidence(times, accepted, mapped, graph, mount, params.mosaic_res_m)

    mosaic = blend_frames(
        pings(),
        poses,
        mapped,
        mount,
        frame,
        params,
        clock,
        progress,
        spill,
        attitude,
        confidence,
        pool,
    )
    bottom: dict[str, Any] = {"source": "configured", "altitude_m": mount.altitude_m}
    if agrees is not None:
        # The sonar's own soundings found the bed level at the configured altitude.
        found = np.array([plane.altitude_m for plane in agrees.planes.values()])
        bottom["sonar_agrees"] = {
            "pings": int(found.size),
            "median_altitude_m": float(np.median(found)),
        }
    if seabed is not None:
        altitudes = np.array([plane.altitude_m for plane in seabed.planes.values()])
        bottom = {
            "source": seabed.model.source,
            "soundings": len(seabed.model),
            "pings_with_plane": int(altitudes.size),
            "altitude_m": {
                "min": float(altitudes.min()) if altitudes.size else None,
                "median": float(np.median(altitudes)) if altitudes.size else None,
                "max": float(altitudes.max()) if altitudes.size else None,
            },
        }
    return SurveyResult(
        bottom=bottom,
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
        fusion=fusion_summary,
        ahead=ahead,
    )
