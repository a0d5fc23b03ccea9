"""Table V: the blending methods on the same poses (Zhang et al., Sec. IV, Table V).

The single-stage trajectory (its result folder's trajectory.csv) is rendered again with
each blending (``mapping.blend``: plain averaging, Hurtós et al.'s distance weighting, Su
et al.'s variance scores over fixed windows with a plain mean, and the paper's robust
variance blending), the frames preprocessed and projected at their roll and pitch exactly
as the survey-end pass does; per method the image metrics of the mosaic
(``tools.evaluation.metrics.image_metrics``, intensities in [0, 1] over the pixels with data) and
the mosaic itself (for Fig. 5).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from mapping.mosaic import assemble
from mapping.navigation import AttitudeTrack
from mapping.pipeline import NavSamples, PipelineParams, blend_frames
from mapping.samples import Ping
from tools.evaluation.metrics import image_metrics
from tools.evaluation.registration import Trajectory

BLENDINGS = ("average", "hurtos", "su", "robust")
"""Table V's rows, in the paper's order."""
BLENDING_NAMES = {
    "average": "Averaging",
    "hurtos": "Hurtós et al. (distance)",
    "su": "Su et al. (fixed windows)",
    "robust": "Ours (robust variance)",
}


@dataclass(frozen=True)
class Rendered:
    """A mosaic (uint8, 0 = no data), the UTM (west, north) of its top-left corner, its
    pixel (m), the seconds the render took."""

    image: npt.NDArray[np.uint8]
    west: float
    north: float
    res_m: float
    seconds: float


def render_trajectory(
    pings: Callable[[], Iterable[Ping]],
    times: Iterable[float],
    trajectory: Trajectory,
    mount: SonarMount,
    params: PipelineParams,
    nav: NavSamples,
    method: str,
) -> Rendered:
    """The mosaic of the trajectory's frames (matched to the pings by time) blended by
    ``method``."""
    started = time.perf_counter()
    stamps = np.asarray(list(times), float)
    by_time = trajectory.by_time()
    poses = np.full((stamps.size, 3), np.nan)
    for k, t in enumerate(stamps):
        pose = by_time.get(round(float(t), 4))
        if pose is not None:
            poses[k] = pose
    mapped = np.all(np.isfinite(poses), axis=1)
    first = poses[np.argmax(mapped)]
    # A local frame anchored near the survey (on the trajectory's zone and grid).
    frame = LocalFrame(
        trajectory.epsg,
        float(math.floor(first[0] / 100) * 100),
        float(math.floor(first[1] / 100) * 100),
    )
    local = poses.copy()
    local[:, 0] -= frame.anchor_e
    local[:, 1] -= frame.anchor_n
    chosen = dataclasses.replace(params, blend=dataclasses.replace(params.blend, method=method))
    track = AttitudeTrack(nav.attitude, params.single_stage.graph.sonar_latency_s)
    attitude = track.at if params.project_attitude else None
    mosaic = blend_frames(pings(), local, mapped, mount, frame, chosen, attitude=attitude)
    rendered = {tile.key: tile.values for tile in mosaic.rendered_tiles()}
    image, (west, north) = assemble(mosaic.grid, rendered)
    return Rendered(image, west, north, params.mosaic_res_m, time.perf_counter() - started)


def blending_table(rendered: dict[str, Rendered]) -> dict[str, dict[str, Any]]:
    """Per method: the mosaic's image metrics and the render's seconds."""
    out: dict[str, dict[str, Any]] = {}
    for method, mosaic in rendered.items():
        covered = mosaic.image > 0
        metrics = image_metrics(mosaic.image.astype(np.float64) / 255.0, covered)
        out[method] = {**metrics, "seconds": round(mosaic.seconds, 2)}
    return out
