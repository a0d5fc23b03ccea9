"""SE(2) poses of the vehicle reference point for scoring against a simulator's truth.

A pose is (east, north, heading): UTM metres and radians clockwise from grid north; the
body frame has x forward (along the heading) and y to starboard. Arrays are (n, 3); NaN
rows are frames without a pose.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def wrap(angle: Array) -> Array:
    """Angles (radians) wrapped to [-pi, pi)."""
    return np.asarray((np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi, dtype=np.float64)


def to_body(pose: Array, east: Array, north: Array) -> tuple[Array, Array]:
    """World points (metres) in the body frame of each pose: (forward, starboard)."""
    d_east, d_north = east - pose[:, 0], north - pose[:, 1]
    s, c = np.sin(pose[:, 2]), np.cos(pose[:, 2])
    return d_east * s + d_north * c, d_east * c - d_north * s


def placement_shift(true: Array, estimate: Array, east: Array, north: Array) -> Array:
    """Where the estimated pose puts a seabed point the true pose saw at (east, north),
    minus where it is: ``T_est o T_true^-1 (p) - p`` (n, 2 metres, east/north).

    Written as the translation error plus the rotation error acting on the point's offset
    from the true pose, so that an estimate equal to the truth gives exactly zero."""
    d_east, d_north = east - true[:, 0], north - true[:, 1]
    delta = estimate[:, 2] - true[:, 2]
    sin_d = np.sin(delta)
    cos_d_minus_1 = -2.0 * np.sin(delta / 2.0) ** 2
    # A clockwise turn by delta: (e, n) -> (e cos + n sin, -e sin + n cos).
    shift_east = estimate[:, 0] - true[:, 0] + cos_d_minus_1 * d_east + sin_d * d_north
    shift_north = estimate[:, 1] - true[:, 1] - sin_d * d_east + cos_d_minus_1 * d_north
    return np.stack([shift_east, shift_north], axis=1)


def relative_pose_error(
    times: Array, estimate: Array, true: Array, window_s: float = 10.0, slack_s: float = 1.0
) -> dict[str, float]:
    """Relative pose error over ``window_s`` (Sturm et al. 2012, "A benchmark for the
    evaluation of RGB-D SLAM systems", doi:10.1109/IROS.2012.6385773, eq. 2), in SE(2):
    for each frame i with a pose in both trajectories and the first such frame j at least
    ``window_s`` later (within ``slack_s`` more), E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j).
    Returns the RMS of |trans(E)| (metres) and of the yaw of E (degrees), and the pairs."""
    ok = np.all(np.isfinite(estimate), axis=1) & np.all(np.isfinite(true), axis=1)
    idx = np.flatnonzero(ok)
    idx = idx[np.argsort(times[idx], kind="stable")]
    t = times[idx]
    later = np.searchsorted(t, t + window_s, side="left")
    has = later < t.size
    i, j = idx[has], idx[later[has]]
    close = times[j] - times[i] <= window_s + slack_s
    i, j = i[close], j[close]
    if i.size == 0:
        return {"translation_rms_m": math.nan, "yaw_rms_deg": math.nan, "pairs": 0}
    est_f, est_s = to_body(estimate[i], estimate[j, 0], estimate[j, 1])
    true_f, true_s = to_body(true[i], true[j, 0], true[j, 1])
    # |trans(E)| is the norm of the two relative translations' difference (rotating
    # by the true relative yaw keeps the norm).
    translation = np.hypot(est_f - true_f, est_s - true_s)
    yaw = wrap((estimate[j, 2] - estimate[i, 2]) - (true[j, 2] - true[i, 2]))
    return {
        "translation_rms_m": float(math.sqrt(float(np.mean(translation**2)))),
        "yaw_rms_deg": float(math.degrees(math.sqrt(float(np.mean(yaw**2))))),
        "pairs": int(i.size),
    }
