"""The mapping modes on one survey, Table III (quadrat spacing) and Table IV (lambda).

Each mode is a ``seamap replay`` of the survey into ``OUT/modes/{mode}/`` (its own result
folder, and with a truth its accuracy in report.json). Quadrat spacing (the paper's Table
III: MAE and RMSE, metres, of the distances between located quadrats against their true
distances, over the pairs within one array) comes from the truth's quadrats, or from a
quadrats file of taped positions for a real survey (``read_quadrats``), located in each
mode's mosaic the same way (``tools.evaluation.truth.quadrat_section``).

Table IV replays single-stage with the paper's lambda from 1e2 to 1e6: seamap weighs each
registration by its covariance, and lambda / 1e4 scales that information (1e4, the
paper's best, is the pipeline's own weighting); alpha = 1/225 is the paper's fixed
heading-to-distance ratio, which the covariance weighting replaces (it is the pose graph's
``mapping.posegraph`` only). Per lambda: the quadrat spacing when quadrats are known, and
with or without them the relative-pose consistency against fmt-only and gps-only (Table
II's measure), and with a truth the shape error of the trajectory (ATE after the best
rigid alignment).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio

from daemon.config import SiteConfig
from daemon.replay import pipeline_params, replay
from drivers.errors import SeamapError
from mapping.geo import LocalFrame
from tools.evaluation.metrics import Quadrat
from tools.evaluation.truth import MIN_VIEWS, quadrat_section, truth_scorer

MODES = ("fmt-only", "gps-only", "single-stage", "two-stage")
LAMBDAS = (1e2, 1e3, 1e4, 1e5, 1e6)
ALPHA = 1.0 / 225.0


@dataclass(frozen=True)
class ModeRun:
    """One mode's replay: its result folder and report."""

    mode: str
    folder: Path
    report: dict[str, Any]

    @property
    def epsg(self) -> int:
        return _epsg_of(self.folder)


def _epsg_of(folder: Path) -> int:
    with rasterio.open(folder / "mosaic.tif") as dataset:
        return int(dataset.crs.to_epsg())


def run_mode(
    sonar: list[Path],
    nav: list[Path],
    config: SiteConfig,
    mode: str,
    out: Path,
    truth: Path | None,
    *,
    params: Any = None,
    progress: Callable[[str, int, int], None] | None = None,
    truth_matching: dict[str, Any] | None = None,
) -> ModeRun:
    """One mode's replay into ``out``, scored against ``truth`` (a simulator's truth or a
    reference trajectory, matched with ``truth_matching``) when given."""
    matching = truth_matching or {}
    scorer = truth_scorer(truth, **matching) if truth is not None else None
    report = replay(
        sonar, nav, None, mode, out, config=config, scorer=scorer, params=params, progress=progress
    )
    return ModeRun(mode, out, report)


def read_quadrats(path: Path, epsg: int) -> list[Quadrat]:
    """Taped quadrats: JSON ``{"quadrats": [{"lat", "lon", "side_m", "row", "index",
    "side_bearing_deg", "array"}, ...]}`` (centre in WGS84 degrees, the side between bar
    centre lines in metres; ``row`` and ``index`` number it in its array, ``array`` (0 if
    absent) the rigid layout it belongs to, ``side_bearing_deg`` (0 if absent) the true
    bearing of one side). In UTM zone ``epsg``. SeamapError (one line) if it is not one."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such quadrats file") from None
    except (OSError, ValueError) as exc:
        raise SeamapError(f"{path}: not a readable quadrats file ({exc})") from None
    items = doc.get("quadrats") if isinstance(doc, dict) else None
    if not isinstance(items, list) or len(items) < 2:
        raise SeamapError(f'{path}: expected {{"quadrats": [...]}} with at least two quadrats')
    frame = LocalFrame(epsg, 0.0, 0.0)
    out = []
    for k, item in enumerate(items):
        try:
            lat, lon, side = float(item["lat"]), float(item["lon"]), float(item["side_m"])
            bearing = math.radians(float(item.get("side_bearing_deg", 0.0)))
            row, index = int(item.get("row", 0)), int(item.get("index", k))
            array = int(item.get("array", 0))
        except (KeyError, TypeError, ValueError) as exc:
            raise SeamapError(
                f"{path}: quadrat {k + 1}: needs lat, lon and side_m ({exc})"
            ) from None
        if not (abs(lat) <= 90 and abs(lon) <= 180 and 0.05 <= side <= 20.0):
            raise SeamapError(f"{path}: quadrat {k + 1}: position or side out of range")
        east, north = frame.to_utm(*frame.to_local(lat, lon))
        grid = frame.true_to_grid(bearing, lat, lon)
        out.append(Quadrat(float(east), float(north), side, row, index, grid, array))
    return out


def quadrat_spacing(run: ModeRun, quadrats: list[Quadrat] | None) -> dict[str, Any] | None:
    """The mode's quadrat spacing: located in its mosaic for taped quadrats, else its
    report's (truth); None when neither knows the quadrats."""
    if quadrats is not None:
        with rasterio.open(run.folder / "mosaic.tif") as dataset:
            mosaic = dataset.read(1)
            t = dataset.transform
        views = np.full(len(quadrats), MIN_VIEWS, np.int64)
        image = mosaic.astype(np.float64) / 255.0
        return quadrat_section(quadrats, views, image, mosaic > 0, t.c, t.f, t.a)
    spacing = run.report.get("accuracy", {}).get("quadrat_spacing")
    return dict(spacing) if spacing else None


def lambda_params(config: SiteConfig, lam: float) -> Any:
    """The pipeline's parameters with the registrations' information scaled by
    lambda / 1e4."""
    base = pipeline_params(config)
    graph = dataclasses.replace(base.single_stage.graph, registration_scale=lam / 1e4)
    return dataclasses.replace(
        base, single_stage=dataclasses.replace(base.single_stage, graph=graph)
    )
