"""Keep-out hulls: each hole grown by the clearance and made convex, and how a straight leg
runs through a hull and round its outline instead.

Frames and units: metres east/north in the survey's local grid frame; hulls are
counter-clockwise (n, 2) rings. Why convex hulls, and what they give away, is in
``planning.lawnmower``'s module doc.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from planning.area import EPS_M, Point, convex_hull

FloatArray = npt.NDArray[np.float64]

_HULL_SIDES = 16  # polygon standing in for the clearance circle round each hole vertex


def keepout_hulls(holes: list[FloatArray], clearance_m: float) -> list[FloatArray]:
    """Each hole grown by ``clearance_m`` and made convex (CCW rings); hulls that touch
    are merged. The growth uses a polygon round the clearance circle, so the hull keeps at
    least ``clearance_m`` from its hole everywhere."""
    k = np.arange(_HULL_SIDES) * 2 * math.pi / _HULL_SIDES
    r = clearance_m / math.cos(math.pi / _HULL_SIDES)
    disc = r * np.column_stack([np.cos(k), np.sin(k)]) if clearance_m > 0 else np.zeros((1, 2))
    clouds = [(h[:, None, :] + disc[None, :, :]).reshape(-1, 2) for h in holes]
    merged = True
    while merged:
        merged = False
        hulls = [convex_hull(c) for c in clouds]
        for i in range(len(hulls)):
            for j in range(i):
                if _convex_overlap(hulls[i], hulls[j]):
                    clouds[j] = np.concatenate([clouds[j], clouds[i]])
                    del clouds[i]
                    merged = True
                    break
            if merged:
                break
    return [convex_hull(c) for c in clouds]


def _convex_overlap(a: FloatArray, b: FloatArray) -> bool:
    """Separating-axis test for two convex rings (touching counts as overlap)."""
    for ring in (a, b):
        edges = np.roll(ring, -1, axis=0) - ring
        normals = np.column_stack([edges[:, 1], -edges[:, 0]])
        pa, pb = a @ normals.T, b @ normals.T
        if np.any(
            (pa.max(axis=0) < pb.min(axis=0) - 1e-9) | (pb.max(axis=0) < pa.min(axis=0) - 1e-9)
        ):
            return False
    return True


def clip_to_hull(
    x: FloatArray, y: FloatArray, hull: FloatArray
) -> tuple[float, float, int, int] | None:
    """Where segment x-y runs through the inside of a convex CCW hull (Cyrus-Beck): the
    parameters (t_in, t_out) and the hull edges it enters and leaves by; None if it only
    misses or grazes the hull."""
    d = y - x
    length = float(np.hypot(*d))
    if length < EPS_M:
        return None
    edges = np.roll(hull, -1, axis=0) - hull
    normals = np.column_stack([edges[:, 1], -edges[:, 0]])  # outward for a CCW ring
    normals /= np.hypot(*normals.T)[:, None]
    num = np.einsum("ij,ij->i", normals, x[None, :] - hull)  # > 0: x outside that edge
    den = normals @ d
    parallel = np.abs(den) < 1e-12 * length
    if np.any(parallel & (num >= -1e-7)):
        return None  # parallel to an edge, on or outside it
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -num / den
    entering, leaving = ~parallel & (den < 0), ~parallel & (den > 0)
    if not entering.any() or not leaving.any():
        return None
    e_in = int(np.flatnonzero(entering)[np.argmax(t[entering])])
    e_out = int(np.flatnonzero(leaving)[np.argmin(t[leaving])])
    t_in, t_out = max(float(t[e_in]), 0.0), min(float(t[e_out]), 1.0)
    if (t_out - t_in) * length <= 1e-4:
        return None
    return t_in, t_out, e_in, e_out


def around_hull(
    p: FloatArray, q: FloatArray, e_in: int, e_out: int, hull: FloatArray, full_loop: bool
) -> list[Point]:
    """Vertices from p (on hull edge e_in) to q (on edge e_out) along the hull's outline,
    the shorter way; with ``full_loop`` once all the way round first."""
    n = len(hull)
    ccw = [hull[(e_in + 1 + k) % n] for k in range((e_out - e_in) % n)]
    cw = [hull[(e_in - k) % n] for k in range((e_in - e_out) % n)]

    def length(path: list[FloatArray]) -> float:
        pts = np.array([p, *path, q])
        return float(np.hypot(*np.diff(pts, axis=0).T).sum())

    way, step = (ccw, 1) if length(ccw) <= length(cw) else (cw, -1)
    if full_loop:
        start = e_in + 1 if step == 1 else e_in
        loop = [hull[(start + step * k) % n] for k in range(n)]
        way = loop + way
    return [(float(v[0]), float(v[1])) for v in way]
