"""Loop-closure candidates between overlapping frames of different lanes, registered.

The paper chains consecutive registrations only, so the relative placement of two lanes
rests on the GPS, whose bias wanders by a metre between passes: a quadrat seen from two
lanes is drawn twice. Registering frames of adjacent lanes that see the same seabed (often
from opposite headings) ties the lanes together: the paper's natural next step, and
standard pose-graph practice (e.g. Hurtós et al. 2015, doi:10.1002/rob.21516).

Candidates come from the current pose estimate: frames at least ``min_gap_s`` apart whose
fans share enough lit seabed. Each is registered with the prior from that estimate
(``FmtRegistrar.register_far``), keeping several distinct peaks; which of them, if any,
becomes a closure is ``mapping.closures``'s choice.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from mapping.closures import ClosureHypothesis
from mapping.fmt import FmtParams, FmtRegistrar, cached_registrar
from mapping.frames import LocalRegistration, SonarMount, prepared_frames
from mapping.grid import SonarGrid
from mapping.kernels import compiled
from mapping.overlap import OverlapRefiner
from mapping.polar import FanGeometry
from mapping.preprocess import SonarFrame
from mapping.samples import Ping
from mapping.se2 import RelativePose, relative_pose
from mapping.tasks import InlinePool, TaskPool

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class LoopParams:
    enabled: bool = True
    min_gap_s: float = 8.0
    """Frames closer in time are left to the consecutive chain."""
    min_overlap: float = 0.3
    """Smallest share of the lit fan two frames must have in common."""
    stride_s: float = 0.8
    """At most one closure per this much survey time of each pass over a place (in
    frames: this times the ping rate, at least one), so a survey pinged at 2 or at 10 Hz
    gets as many closures a minute."""
    search_m: float = 1.0
    """Sigma of the prior's translation (the GNSS's relative error between lanes): it
    weighs the correlation peaks, the whole surface is searched."""
    min_score: float = 0.08
    hypotheses: int = 4
    """Distinct correlation peaks kept per candidate pair (periodic seabeds)."""
    sigma_m: float = 0.03
    """Closure sigma per axis when the registrar gives no covariance: registrations
    between lanes see the seabed from other sides and are centimetres, not millimetres."""
    sigma_deg: float = 0.3
    sigma_floor_m: float = 0.01
    """Added to the registrar's own covariance (view-dependent shading)."""
    sigma_floor_deg: float = 0.1
    refine: bool = True
    """Each hypothesis is registered again on the seabed both frames share
    (``mapping.overlap``): the unshared parts of two rippled fans pull the peak by
    centimetres."""


@dataclass
class LoopReport:
    candidates: int = 0
    registered: int = 0
    rejected_score: int = 0
    refined: int = 0
    """Hypotheses registered again on the shared seabed (``LoopParams.refine``)."""
    kept: int = 0
    other_geometry: int = 0
    """Candidate pairs left out because the sonar's range or beams changed between their
    frames (their frames are on grids no registration compares)."""


def _fan_samples(lit_m: tuple[float, float], half_fan_rad: float) -> Array:
    """Sample points spread over the lit part of a fan (forward, starboard metres)."""
    ranges = np.linspace(lit_m[0], lit_m[1], 6)[1:-1]
    bearings = np.linspace(-half_fan_rad, half_fan_rad, 9)[1:-1]
    r, b = np.meshgrid(ranges, bearings)
    return np.column_stack([(r * np.cos(b)).ravel(), (r * np.sin(b)).ravel()])


def _to_world(sonar: Array, points: Array) -> Array:
    """Sonar-frame points (m, 2) of each pose (n, 3) in world east/north: (n, m, 2)."""
    s, c = np.sin(sonar[:, 2])[:, None], np.cos(sonar[:, 2])[:, None]
    f, st = points[None, :, 0], points[None, :, 1]
    return np.stack([sonar[:, 0:1] + f * s + st * c, sonar[:, 1:2] + f * c - st * s], axis=-1)


def footprint_overlap(
    sonar_a: Array, sonar_b: Array, lit_m: tuple[float, float], half_fan_rad: float
) -> Array:
    """Fraction of fan a's sample points that fall inside fan b, per pair of sonar poses
    (n, 3) each (x, y, yaw): an estimate of how much seabed the two frames share."""
    points = _fan_samples(lit_m, half_fan_rad)
    world = _to_world(sonar_a, points)
    dx = world[..., 0] - sonar_b[:, 0:1]
    dy = world[..., 1] - sonar_b[:, 1:2]
    s, c = np.sin(sonar_b[:, 2])[:, None], np.cos(sonar_b[:, 2])[:, None]
    forward = dx * s + dy * c
    starboard = dx * c - dy * s
    rng = np.hypot(forward, starboard)
    inside = (
        (rng >= lit_m[0])
        & (rng <= lit_m[1])
        & (np.abs(np.arctan2(starboard, forward)) <= half_fan_rad)
    )
    return np.asarray(inside.mean(axis=1), np.float64)


_CHUNK_FRAMES = 2048
"""Earlier frames whose pairs are found at once (about 2 million pairs at 10 Hz)."""


@compiled
def _inside_share(
    a: Array, b: Array, points: Array, near: float, far: float, half_fan_rad: float
) -> float:
    """The share of fan ``a``'s sample points (sonar pose x, y, yaw) inside fan ``b``:
    ``footprint_overlap`` of one pair, its arithmetic in the same order."""
    sa, ca = math.sin(a[2]), math.cos(a[2])
    sb, cb = math.sin(b[2]), math.cos(b[2])
    inside = 0
    for q in range(points.shape[0]):
        f, st = points[q, 0], points[q, 1]
        dx = (a[0] + f * sa + st * ca) - b[0]
        dy = (a[1] + f * ca - st * sa) - b[1]
        forward = dx * sb + dy * cb
        starboard = dx * cb - dy * sb
        rng = math.hypot(forward, starboard)
        if near <= rng <= far and abs(math.atan2(starboard, forward)) <= half_fan_rad:
            inside += 1
    return inside / points.shape[0]


@compiled
def _shared_loop(
    sonar: Array,
    a: IntArray,
    b: IntArray,
    points: Array,
    near: float,
    far: float,
    half_fan_rad: float,
) -> Array:
    out = np.empty(a.size)
    for k in range(a.size):
        pa, pb = sonar[a[k]], sonar[b[k]]
        out[k] = min(
            _inside_share(pa, pb, points, near, far, half_fan_rad),
            _inside_share(pb, pa, points, near, far, half_fan_rad),
        )
    return out


def _shared(
    sonar: Array, a: IntArray, b: IntArray, lit_m: tuple[float, float], half_fan_rad: float
) -> Array:
    """Per pair (a, b) of sonar poses, the smaller of the two fans' shares of each
    other (``footprint_overlap`` both ways, in a compiled loop: no per-point temporaries
    for millions of pairs; the same numbers, ``tests/mapping/test_loops.py``)."""
    if a.size == 0:
        return np.empty(0)
    points = np.ascontiguousarray(_fan_samples(lit_m, half_fan_rad))
    return np.asarray(
        _shared_loop(
            np.ascontiguousarray(sonar, np.float64),
            np.ascontiguousarray(a, np.int64),
            np.ascontiguousarray(b, np.int64),
            points,
            float(lit_m[0]),
            float(lit_m[1]),
            float(half_fan_rad),
        )
    )


def find_candidates(
    times: Array,
    poses: Array,
    mapped: npt.NDArray[np.bool_],
    mount: SonarMount,
    lit_m: tuple[float, float],
    half_fan_rad: float,
    params: LoopParams,
) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, of mapped frames at least ``min_gap_s`` apart whose fans share
    at least ``min_overlap`` of their lit seabed; one pair, the best, per block of
    ``stride_s`` of survey time on each side."""
    index = np.flatnonzero(mapped & np.all(np.isfinite(poses), axis=1))
    if index.size < 2:
        return []
    sonar = mount.sonar_pose(poses[index])
    mid = 0.5 * (lit_m[0] + lit_m[1])
    centres = np.column_stack(
        [sonar[:, 0] + mid * np.sin(sonar[:, 2]), sonar[:, 1] + mid * np.cos(sonar[:, 2])]
    )
    reach = 2.0 * lit_m[1] * math.sin(min(half_fan_rad, math.pi / 2))
    interval = float(np.median(np.diff(times[index]))) if index.size > 1 else 1.0
    stride = max(1, round(params.stride_s / max(interval, 1e-3)))
    tree = cKDTree(centres)
    block = index // stride
    found: list[IntArray] = []
    start = 0
    # A two-hour survey has tens of millions of pairs within reach: they are taken a
    # chunk of earlier frames at a time, whole stride blocks in each, so that memory
    # stays bounded and each block's best pair is final when its chunk ends.
    while start < index.size:
        end = min(start + _CHUNK_FRAMES, index.size)
        while end < index.size and block[end] == block[end - 1]:
            end += 1
        near = cKDTree(centres[start:end]).sparse_distance_matrix(
            tree, reach, output_type="ndarray"
        )
        a = near["i"].astype(np.int64) + start
        b = near["j"].astype(np.int64)
        apart = np.asarray(near["v"], float)
        keep = (b > a) & (times[index[b]] - times[index[a]] >= params.min_gap_s)
        a, b, apart = a[keep], b[keep], apart[keep]
        share = _shared(sonar, a, b, lit_m, half_fan_rad)
        good = share >= params.min_overlap
        a, b, share, apart = a[good], b[good], share[good], apart[good]
        i, j = index[a], index[b]
        # The best pair per (i block, j block): the largest share (in steps of the fan's
        # sample points, so often tied), then the nearest fan centres, then the earliest.
        order = np.lexsort((j, i, apart, -share, j // stride, i // stride))
        i, j = i[order], j[order]
        ki, kj = i // stride, j // stride
        first = np.ones(i.size, bool)
        first[1:] = (ki[1:] != ki[:-1]) | (kj[1:] != kj[:-1])
        found.append(np.column_stack([i[first], j[first]]))
        start = end
    pairs = np.concatenate(found) if found else np.zeros((0, 2), np.int64)
    chosen = [(int(i), int(j)) for i, j in pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]]
    # Adjacent j-blocks of one i-block see nearly the same thing: keep one per i-block and
    # pass (a pass being a run of j's without a gap of min_gap_s).
    thinned: list[tuple[int, int]] = []
    for i, j in chosen:
        same_block = thinned and thinned[-1][0] // stride == i // stride
        if same_block and abs(times[j] - times[thinned[-1][1]]) < params.min_gap_s:
            continue
        thinned.append((i, j))
    return thinned


@dataclass(frozen=True, slots=True)
class ClosureJob:
    """One candidate pair to register: frame ``j``'s blending image against frame ``i``'s
    (with the masks where each has data), the prior (sonar ``j`` in sonar ``i``), and the
    grid and fan the registrar works on (``LocalRegistration.fine_registrar``)."""

    i: int
    j: int
    earlier: npt.NDArray[np.float32]
    earlier_mask: npt.NDArray[np.bool_] | None
    later: npt.NDArray[np.float32]
    later_mask: npt.NDArray[np.bool_] | None
    prior: RelativePose
    grid: SonarGrid
    fan: npt.NDArray[np.bool_]
    fmt: FmtParams
    params: LoopParams
    mount: SonarMount


@dataclass(frozen=True, slots=True)
class ClosureFound:
    """A pair registered: its hypotheses that passed ``min_score`` (vehicle frame), and
    how many of them the overlap refined."""

    i: int
    j: int
    hypotheses: list[ClosureHypothesis]
    refined: int


_REFINERS: dict[tuple[SonarGrid, bytes], OverlapRefiner] = {}


def _registrar(job: ClosureJob) -> tuple[FmtRegistrar, OverlapRefiner]:
    """The registrar and refiner for the job's grid and fan, built once per process."""
    key = (job.grid, job.fan.tobytes())
    refiner = _REFINERS.get(key)
    if refiner is None:
        _REFINERS.clear()
        refiner = OverlapRefiner(job.grid, job.fan)
        _REFINERS[key] = refiner
    return cached_registrar(job.grid, job.fan, job.fmt), refiner


def register_pair(job: ClosureJob) -> ClosureFound:
    """Register one candidate pair (a pure task: its answer depends on the job alone),
    keeping up to ``hypotheses`` distinct peaks whose similarity passes ``min_score``."""
    params, mount = job.params, job.mount
    registrar, refiner = _registrar(job)
    reg = registrar.register_far(
        registrar.prepare(job.earlier, job.earlier_mask),
        job.later,
        job.prior,
        prior_sigma_m=params.search_m,
        n_hypotheses=params.hypotheses,
        later_mask=job.later_mask,
    )
    found: list[ClosureHypothesis] = []
    refined = 0
    for hyp in reg.hypotheses or (reg,):
        if hyp.score < params.min_score:
            continue
        relative = hyp.relative
        if params.refine:
            better = refiner.refine(job.earlier, job.later, relative)
            if better is not None:
                relative = better
                refined += 1
        vehicle = mount.vehicle_relative(relative)
        cov = _closure_cov(hyp.covariance, mount, params)
        found.append(ClosureHypothesis(vehicle, cov, float(hyp.score)))
    return ClosureFound(job.i, job.j, found, refined)


def closure_jobs(
    pings: Iterable[Ping],
    pairs: Sequence[tuple[int, int]],
    poses: Array,
    local: LocalRegistration,
    params: LoopParams,
    report: LoopReport,
    pool: TaskPool | None = None,
) -> Iterator[ClosureJob]:
    """The candidate pairs' jobs, in one pass over the pings (preprocessed in order, as
    the registration pass preprocessed them: the flat field follows the pings; in
    ``pool`` where it gives the same frames, ``mapping.frames.prepared_frames``)."""
    mount = local.mount
    partners: dict[int, list[int]] = {}
    for i, j in pairs:
        partners.setdefault(j, []).append(i)
    wanted = {i for i, _ in pairs}
    last_use: dict[int, int] = {}
    for i, j in pairs:
        last_use[i] = max(last_use.get(i, -1), j)
    held: dict[int, tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_] | None, FanGeometry]] = {}
    sonar = mount.sonar_pose(poses)

    def chosen() -> Iterator[tuple[int, Ping]]:
        for index, ping in enumerate(pings):
            if index in wanted or index in partners:
                yield index, ping
            else:
                local.observe(ping)  # flattened as the registration pass flattened it

    # One worker has the registrations; from two, the pool preprocesses too.
    shared = pool if pool is not None and pool.workers >= 2 else None
    for index, _ping, prepared, preprocessor in prepared_frames(chosen(), local, shared):
        frame = prepared if isinstance(prepared, SonarFrame) else prepared.result()
        image, mask = frame.image, frame.own_mask
        if index in wanted:
            held[index] = (image, mask, preprocessor.fan)
        # The blending grid and fan (``LocalRegistration.fine_registrar``'s), for the
        # registrar the task builds where it runs.
        assert preprocessor.grid is not None
        grid, fan = preprocessor.grid, preprocessor.tables.mask
        for i in partners.get(index, []):
            kept = held.get(i)
            if kept is None:
                continue
            earlier, earlier_mask, earlier_fan = kept
            if earlier_fan != preprocessor.fan:
                # The sonar's range or beams changed between them: two grids that no
                # registration compares (it raised, and the whole pass with it).
                report.other_geometry += 1
                continue
            report.candidates += 1
            yield ClosureJob(
                i, index, earlier, earlier_mask, image, mask,
                relative_pose(sonar[i], sonar[index]), grid, fan, local.fmt, params, mount,
            )  # fmt: skip
        for i in [k for k in held if last_use.get(k, -1) <= index]:
            del held[i]


def register_hypotheses(
    pings: Iterable[Ping],
    pairs: Sequence[tuple[int, int]],
    poses: Array,
    local: LocalRegistration,
    params: LoopParams,
    report: LoopReport,
    pool: TaskPool | None = None,
) -> list[tuple[int, int, list[ClosureHypothesis]]]:
    """Register every candidate pair in one pass over the pings, keeping up to
    ``hypotheses`` distinct peaks per pair whose similarity passes ``min_score``: pose of
    j in i in the vehicle frame, with a covariance (the registrar's, when it gives one).
    ``pool``: where the registrations run (``mapping.tasks``; None: here); the answer is
    the same wherever they do."""
    if not pairs:
        return []
    jobs = closure_jobs(pings, pairs, poses, local, params, report, pool)
    out: list[tuple[int, int, list[ClosureHypothesis]]] = []
    for found in (pool or InlinePool()).run(register_pair, jobs):
        report.registered += 1
        report.refined += found.refined
        if not found.hypotheses:
            report.rejected_score += 1
            continue
        out.append((found.i, found.j, found.hypotheses))
    return out


def _closure_cov(cov: Array | None, mount: SonarMount, params: LoopParams) -> Array:
    """A closure's covariance in the vehicle frame: the registrar's (moved through the
    mount, with a floor) or the default sigmas."""
    floor = np.diag(
        [
            params.sigma_floor_m**2,
            params.sigma_floor_m**2,
            math.radians(params.sigma_floor_deg) ** 2,
        ]
    )
    if cov is None:
        return np.diag([params.sigma_m**2, params.sigma_m**2, math.radians(params.sigma_deg) ** 2])
    return mount.vehicle_covariance(cov) + floor
