"""Table II: relative-pose consistency of the registration methods (Zhang et al., Sec. IV).

Every method is asked the same question: where is each frame relative to the one before
it? For the mapping modes (fmt-only, gps-only, single-stage, two-stage) the answer is
their trajectory's step between consecutive mapped frames; for the registration baselines
(ORB + RANSAC, SIFT + RANSAC, ECC maximisation: ``tools.evaluation.baselines``) and FMT itself it
is the pairwise registration of the two frames, from identity, with no navigation prior
and no validation (the paper's use of them). A step is the later vehicle pose in the
earlier one's frame: forward and starboard metres, yaw radians (``mapping.frames``).

The consistency of a method against a reference (fmt-only, or the global prior alone,
gps-only) is the distance between their steps' translations over the pairs both answer:
its mean (MAE) and root mean square (RMSE), metres. A baseline that gives no answer for a
pair (too few matches, no RANSAC model, ECC not converged) is counted as failed there and
left out of both; how many failed is in the table.

With a truth, each baseline also becomes a trajectory: its steps chained from the first
frame's gps-only pose, a failed step bridged by the gps-only step, so that its ATE, RPE
and lane disagreement stand beside the modes' (the paper: "ECC ... collapses on long
sequences").
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mapping.fmt import FmtParams, FmtRegistrar
from mapping.frames import LocalRegistration, SonarMount
from mapping.geo import LocalFrame
from mapping.preprocess import PreprocessParams
from mapping.samples import Ping
from mapping.se2 import RelativePose, compose, relative_pose
from tools.evaluation.baselines import REGISTRATION_BASELINES

Array = npt.NDArray[np.float64]

BASELINE_NAMES = {"orb": "ORB + RANSAC", "sift": "SIFT + RANSAC", "ecc": "ECC maximisation"}


@dataclass(frozen=True)
class Trajectory:
    """A result folder's trajectory.csv: frame times (s) and vehicle poses (east, north
    UTM metres, grid heading radians clockwise from grid north)."""

    times: Array
    poses: Array
    epsg: int

    def by_time(self) -> dict[float, Array]:
        return {round(float(t), 4): p for t, p in zip(self.times, self.poses, strict=True)}


def read_trajectory(path: Path, epsg: int) -> Trajectory:
    """trajectory.csv (``time,lat,lon,east,north,heading_deg``, heading from true north)
    with the heading turned to the grid of zone ``epsg``."""
    frame = LocalFrame(epsg, 0.0, 0.0)
    times, poses = [], []
    with open(path, newline="", encoding="utf-8") as stream:
        for row in csv.DictReader(stream):
            lat, lon = float(row["lat"]), float(row["lon"])
            grid = frame.true_to_grid(math.radians(float(row["heading_deg"])), lat, lon)
            times.append(float(row["time"]))
            poses.append((float(row["east"]), float(row["north"]), grid))
    return Trajectory(np.array(times), np.array(poses, float).reshape(-1, 3), epsg)


def trajectory_steps(trajectory: Trajectory, pairs: list[tuple[float, float]]) -> Array:
    """Each pair's step (forward, starboard m, yaw rad) from the trajectory; NaN where it
    lacks either frame."""
    poses = trajectory.by_time()
    out = np.full((len(pairs), 3), np.nan)
    for k, (a, b) in enumerate(pairs):
        pa, pb = poses.get(round(a, 4)), poses.get(round(b, 4))
        if pa is not None and pb is not None:
            r = relative_pose(pa, pb)
            out[k] = (r.forward_m, r.starboard_m, r.yaw_rad)
    return out


def consistency(steps: Array, reference: Array) -> dict[str, float]:
    """MAE and RMSE (metres) of the steps' translations against the reference's, over the
    pairs both have, and how many those are."""
    both = np.isfinite(steps[:, 0]) & np.isfinite(reference[:, 0])
    if not both.any():
        return {"mae_m": math.nan, "rmse_m": math.nan, "pairs": 0}
    error = np.hypot(*(steps[both, :2] - reference[both, :2]).T)
    return {
        "mae_m": float(error.mean()),
        "rmse_m": float(math.sqrt(float(np.mean(error**2)))),
        "pairs": int(both.sum()),
    }


@dataclass
class PairwiseSteps:
    """One registration method over the pairs: its steps (NaN where it failed) and the
    seconds each registration took."""

    name: str
    steps: Array
    seconds: list[float] = field(default_factory=list)

    @property
    def failed(self) -> int:
        return int(np.count_nonzero(~np.isfinite(self.steps[:, 0])))

    @property
    def ms_per_pair(self) -> float:
        return 1000.0 * float(np.mean(self.seconds)) if self.seconds else math.nan


def pairwise_steps(
    pings: Callable[[], Iterable[Ping]],
    mount: SonarMount,
    pairs: list[tuple[float, float]],
    methods: tuple[str, ...] = ("fmt", *REGISTRATION_BASELINES),
    preprocess: PreprocessParams | None = None,
    fmt_params: FmtParams | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, PairwiseSteps]:
    """Register each pair (consecutive pings by time) with each method on the frames the
    pipeline registers (``SonarFrame.coarse``, its grid and fan, the pipeline's
    ``preprocess`` and ``fmt_params``; level: the pairs' roll and pitch are small and
    alike for every method); the steps in the vehicle frame (the mount's lever arm and
    yaw taken out). Each method's time per pair is all it does with the two frames: FMT
    prepares both (window, spectra) and registers; the baselines detect and describe in
    both (or, for ECC, build both pyramids) and register. None keeps work between pairs,
    so the times compare like for like (the pipeline itself reuses FMT's prepared earlier
    frame)."""
    wanted = {round(a, 4): k for k, (a, _) in enumerate(pairs)}
    out = {m: PairwiseSteps(m, np.full((len(pairs), 3), np.nan)) for m in methods}
    local = LocalRegistration(mount, preprocess or PreprocessParams(), fmt_params or FmtParams())
    registrars: dict[str, Any] = {}
    geometry: object = None
    earlier: tuple[int, Any] | None = None  # (pair index, coarse image)
    done = 0
    for ping in pings():
        key = round(float(ping.time), 4)
        frame = local.frame(ping)
        fmt = local.registrar
        assert isinstance(fmt, FmtRegistrar) and local.preprocessor is not None
        if fmt is not geometry:  # a new fan geometry: new registrars on its grid
            geometry = fmt
            grid = local.preprocessor.registration_grid
            mask = local.preprocessor.registration_tables.mask
            registrars = {m: REGISTRATION_BASELINES[m](grid, mask) for m in methods if m != "fmt"}
            earlier = None
        if earlier is not None and round(pairs[earlier[0]][1], 4) == key:
            index, image = earlier
            for method in methods:
                started = time.perf_counter()
                relative: RelativePose | None
                if method == "fmt":
                    prepared = fmt.prepare(image), fmt.prepare(frame.coarse)
                    relative = fmt.register(*prepared).relative
                    seconds = time.perf_counter() - started
                else:
                    result = registrars[method].register(image, frame.coarse)
                    seconds = time.perf_counter() - started
                    relative = None if result is None else result.relative
                out[method].seconds.append(seconds)
                if relative is not None:
                    step = mount.vehicle_relative(relative)
                    out[method].steps[index] = (step.forward_m, step.starboard_m, step.yaw_rad)
            done += 1
            if progress is not None and done % 20 == 0:
                progress("Table II: registering pairs", done, len(pairs))
        earlier = None
        if key in wanted:
            earlier = (wanted[key], frame.coarse)
    return out


def chained(steps: Array, reference: Array) -> Array:
    """A trajectory (n + 1, 3) through the frames of n consecutive pairs, from the first
    pose of ``reference`` (the gps-only poses at the n + 1 frames, NaN where it has none)
    by the steps; a missing step is the reference's own, and where the chain cannot go on
    (neither has the step) it starts again at the reference's pose."""
    poses = np.full((len(steps) + 1, 3), np.nan)
    poses[0] = reference[0]
    for k, step in enumerate(steps):
        if not np.isfinite(poses[k, 0]):
            poses[k + 1] = reference[k + 1]
            continue
        if np.isfinite(step[0]):
            poses[k + 1] = compose(poses[k], RelativePose(*map(float, step)))
        elif np.isfinite(reference[k, 0]) and np.isfinite(reference[k + 1, 0]):
            poses[k + 1] = compose(poses[k], relative_pose(reference[k], reference[k + 1]))
        else:
            poses[k + 1] = reference[k + 1]
    return poses
