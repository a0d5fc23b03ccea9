"""The Cartesian sonar frame's grid (``SonarGrid``): the type that preprocessing,
projection, registration, blending and the tiles share, in a room of its own."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Matrix = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SonarGrid:
    """Geometry of a Cartesian sonar frame.

    shape: (rows, cols). res_m: pixel size (metres). forward_max_m: forward coordinate of
    the top edge of row 0. starboard_min_m: starboard coordinate of the left edge of col 0.
    Pixel (col, row) centre is at forward = forward_max_m - (row + 0.5) * res_m,
    starboard = starboard_min_m + (col + 0.5) * res_m (metres, sonar frame).
    """

    shape: tuple[int, int]
    res_m: float
    forward_max_m: float
    starboard_min_m: float

    def pixel_to_metric(self) -> Matrix:
        """3x3 homogeneous matrix taking (col, row, 1) to (forward, starboard, 1)."""
        r = self.res_m
        return np.array(
            [
                [0.0, -r, self.forward_max_m - 0.5 * r],
                [r, 0.0, self.starboard_min_m + 0.5 * r],
                [0.0, 0.0, 1.0],
            ]
        )
