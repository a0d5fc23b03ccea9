"""The bed's long-wavelength shape: a gentle undulation about the seabed's mean plane.

A shore's profile is not a plane: bars, troughs and the shoulders of old channels bend it
by centimetres to decimetres over tens of metres. The undulation is a sum of three plane
waves (local grid east/north metres, heights in metres ABOVE the mean plane, i.e. the
bed is that much shallower): the main one of ``undulation_amplitude_m`` and
``undulation_wavelength_m`` along grid bearing ``undulation_bearing_deg``, and two
weaker ones (0.15-0.3 of its amplitude, 1-2 times its wavelength, turned 20-50 degrees
either way), so that the crests bend and the relief is not periodic. Their slopes add at
most 1.6 times the main wave's ``2 pi A / L``.

It is analytic, not painted in the height map: the sonar (``sonar._mean_echo``) cuts its
beams with the plane raised by it (a Newton solve per bin, since decimetres of lift move
the footprint by metres at low grazing), the echosounder (``echosounder``) and the pings'
truth (``pings.ping_frames``) see it through ``Seabed.depth_at``. truth.json gives the
waves (``site.seabed_plane.undulation``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Undulation:
    """``height(x) = sum_j amplitude_m_j sin(k_j . x + phase_j)`` (metres above the mean
    plane; x local east/north metres, k in rad/m)."""

    k_east: FloatArray
    k_north: FloatArray
    amplitude_m: FloatArray
    phase: FloatArray

    def height(self, east: npt.ArrayLike, north: npt.ArrayLike) -> FloatArray:
        """Height above the mean plane (m) at local points (any matching shapes)."""
        e = np.asarray(east, np.float64)
        n = np.asarray(north, np.float64)
        out = np.zeros(np.broadcast(e, n).shape)
        for ke, kn, a, c in zip(
            self.k_east, self.k_north, self.amplitude_m, self.phase, strict=True
        ):
            out += a * np.sin(ke * e + kn * n + c)
        return out

    def gradient(self, east: npt.ArrayLike, north: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(d height / d east, d height / d north) at local points (m/m)."""
        e = np.asarray(east, np.float64)
        n = np.asarray(north, np.float64)
        ge = np.zeros(np.broadcast(e, n).shape)
        gn = np.zeros_like(ge)
        for ke, kn, a, c in zip(
            self.k_east, self.k_north, self.amplitude_m, self.phase, strict=True
        ):
            cos = a * np.cos(ke * e + kn * n + c)
            ge += ke * cos
            gn += kn * cos
        return ge, gn


def draw_undulation(
    amplitude_m: float, wavelength_m: float, bearing_deg: float, rng: np.random.Generator
) -> Undulation | None:
    """The undulation of the module doc (None when ``amplitude_m`` is 0)."""
    if amplitude_m <= 0.0:
        return None
    turn = rng.uniform(20.0, 50.0, 2) * np.array([1.0, -1.0])
    bearings = np.radians(np.concatenate([[bearing_deg], bearing_deg + turn]))
    wavelengths = np.concatenate([[wavelength_m], wavelength_m * rng.uniform(1.0, 2.0, 2)])
    weights = np.concatenate([[1.0], rng.uniform(0.15, 0.3, 2)])
    phase = rng.uniform(0.0, 2 * math.pi, 3)
    k = 2 * math.pi / wavelengths
    return Undulation(k * np.sin(bearings), k * np.cos(bearings), amplitude_m * weights, phase)
