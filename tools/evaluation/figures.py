"""The paper's figures for one survey: Fig. 3 (a frame under each preprocessing), Fig. 4
(fmt-only, single-stage and two-stage side by side) and Fig. 5 (the four blendings side
by side), with the quadrats boxed where they are known (truth or taped).

Mosaics are drawn north-up on their UTM coordinates (metres, the axes), so a quadrat's
box is its true (or taped) square: where the mosaic draws the frame inside or beside the
box is the map's error there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
import rasterio
from matplotlib.axes import Axes
from matplotlib.patches import Polygon as PolygonPatch

from tools.evaluation.metrics import Quadrat

Panel = tuple[str, npt.NDArray[np.uint8], float, float, float]
"""(title, mosaic uint8 (0 = no data), west, north, pixel m)."""


def read_mosaic(path: Path) -> tuple[npt.NDArray[np.uint8], float, float, float]:
    """A result folder's mosaic.tif: the image, west and north (UTM m) and pixel (m)."""
    with rasterio.open(path) as dataset:
        t = dataset.transform
        return dataset.read(1), float(t.c), float(t.f), float(t.a)


def _draw_quadrats(ax: Axes, quadrats: Sequence[Quadrat]) -> None:
    for q in quadrats:
        half = q.side_m / 2
        s, c = math.sin(q.orientation_rad), math.cos(q.orientation_rad)
        # Corners: along the side (bearing) and across it.
        corners = [
            (q.east + a * half * s + b * half * c, q.north + a * half * c - b * half * s)
            for a, b in ((-1, -1), (-1, 1), (1, 1), (1, -1))
        ]
        # The paper's colours: its aluminium row orange, its PVC row yellow.
        colour = "tab:orange" if q.row == 0 else "gold"
        ax.add_patch(PolygonPatch(corners, closed=True, fill=False, lw=0.8, ec=colour))


def mosaics_figure(
    path: Path, panels: Sequence[Panel], quadrats: Sequence[Quadrat], title: str
) -> None:
    """The panels side by side on one shared UTM extent (metres from the common corner)."""
    west = min(p[2] for p in panels)
    north = max(p[3] for p in panels)
    east = max(p[2] + p[1].shape[1] * p[4] for p in panels)
    south = min(p[3] - p[1].shape[0] * p[4] for p in panels)
    for q in quadrats:  # the boxes in view too: a mosaic may miss them
        west, east = min(west, q.east - q.side_m), max(east, q.east + q.side_m)
        south, north = min(south, q.north - q.side_m), max(north, q.north + q.side_m)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.6), squeeze=False)
    for ax, (name, image, w, n, res) in zip(axes[0], panels, strict=True):
        shown = np.ma.masked_equal(image, 0)
        extent = (w - west, w - west + image.shape[1] * res, n - image.shape[0] * res - south,
                  n - south)  # fmt: skip
        ax.set_facecolor("black")
        ax.imshow(shown, cmap="gray", vmin=0, vmax=255, extent=extent, interpolation="nearest")
        ax.set_xlim(0, east - west)
        ax.set_ylim(0, north - south)
        shifted = [
            Quadrat(q.east - west, q.north - south, q.side_m, q.row, q.index,
                    q.orientation_rad, q.array)
            for q in quadrats
        ]  # fmt: skip
        _draw_quadrats(ax, shifted)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("east (m)")
        ax.set_aspect("equal")
    axes[0][0].set_ylabel("north (m)")
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def preprocessing_figure(
    path: Path, frames: Sequence[tuple[str, npt.NDArray[np.float32], npt.NDArray[np.bool_]]]
) -> None:
    """One frame under each preprocessing (Cartesian, far range at the top), 3 a row."""
    columns = 3
    rows = math.ceil(len(frames) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.6 * columns, 2.6 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (name, image, mask) in zip(axes.ravel(), frames, strict=False):
        shown = np.ma.masked_where(~mask, image)
        ax.set_facecolor("black")
        ax.imshow(shown, cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
        ax.set_title(name, fontsize=9)
    fig.suptitle("Fig. 3: one frame under each preprocessing of Table I", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
