"""Poses in the plane, once: SE(2) composition, the pose of one frame in another, angle
wrapping, and the Jacobians the solvers take.

A pose is (x east, y north, heading clockwise from north), metres and radians; a relative
pose (``RelativePose``) is a later frame's (forward, starboard, yaw) in an earlier one's
frame. The array forms work on rows of poses (the fusion's and the pose graph's factors);
their arithmetic is written in one order so that every caller gets the same bits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
TWO_PI = 2.0 * math.pi
AngleT = TypeVar("AngleT", float, npt.NDArray[np.float64])


def wrap_pi(angle: AngleT) -> AngleT:
    """Wrap radians to [-pi, pi)."""
    return (angle + math.pi) % TWO_PI - math.pi


def turn(angle: float) -> float:
    """The nearest equivalent of an angle difference, in [-pi, pi], exactly (IEEE
    remainder: no rounding, where ``wrap_pi``'s sum may round): the live engine's."""
    return math.remainder(angle, TWO_PI)


def wrap_2pi(angle: float) -> float:
    """Wrap radians to [0, 2*pi) (exactly: ``x % 2pi`` rounds to 2pi for tiny negative x)."""
    wrapped = angle % TWO_PI
    return 0.0 if wrapped >= TWO_PI else wrapped


@dataclass(frozen=True, slots=True)
class RelativePose:
    """Pose of a later sonar frame in the frame of an earlier one.

    forward_m, starboard_m: translation (metres, earlier sonar frame);
    yaw_rad: heading change (radians, clockwise positive).
    """

    forward_m: float
    starboard_m: float
    yaw_rad: float

    def matrix(self) -> Array:
        """3x3 homogeneous matrix taking later-frame (forward, starboard) to earlier-frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, -s, self.forward_m], [s, c, self.starboard_m], [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, m: Array) -> RelativePose:
        return cls(float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0]))


def to_world(forward: float, starboard: float, heading: float) -> tuple[float, float]:
    """A displacement (forward, starboard) of a frame heading ``heading`` as (east, north)."""
    s, c = math.sin(heading), math.cos(heading)
    return forward * s + starboard * c, forward * c - starboard * s


def to_body(dx: float, dy: float, heading: float) -> tuple[float, float]:
    """A displacement (east, north) as (forward, starboard) of a frame heading ``heading``
    (the inverse of ``to_world``)."""
    s, c = math.sin(heading), math.cos(heading)
    return s * dx + c * dy, c * dx - s * dy


def relative_pose(a: Array, b: Array) -> RelativePose:
    """Pose b in the frame of pose a; poses (x east, y north, heading clockwise from north)."""
    forward, starboard = to_body(b[0] - a[0], b[1] - a[1], a[2])
    return RelativePose(forward, starboard, wrap_pi(b[2] - a[2]))


def compose(a: Array, rel: RelativePose) -> Array:
    """The pose at ``rel`` from pose ``a`` (inverse of ``relative_pose``)."""
    s, c = math.sin(a[2]), math.cos(a[2])
    x = a[0] + rel.forward_m * s + rel.starboard_m * c
    y = a[1] + rel.forward_m * c - rel.starboard_m * s
    return np.array([x, y, (a[2] + rel.yaw_rad) % TWO_PI])


def compose_rows(a: Array, offsets: Array) -> Array:
    """``compose`` over rows: poses (n, 3) moved by relative poses (n, 3) of (forward,
    starboard, yaw); headings in [0, 2 pi)."""
    s, c = np.sin(a[:, 2]), np.cos(a[:, 2])
    return np.column_stack(
        [
            a[:, 0] + offsets[:, 0] * s + offsets[:, 1] * c,
            a[:, 1] + offsets[:, 0] * c - offsets[:, 1] * s,
            (a[:, 2] + offsets[:, 2]) % TWO_PI,
        ]
    )


@dataclass(frozen=True, slots=True)
class Between:
    """Poses j in the frames of poses i, over rows (``between``): ``forward``,
    ``starboard`` (m) and the unwrapped heading change ``turn`` (rad), with the sine and
    cosine of pose i's heading that the Jacobian takes."""

    forward: Array
    starboard: Array
    turn: Array
    sin: Array
    cos: Array

    def jacobian(self) -> Array:
        """d(forward, starboard, turn) / d(x_i, y_i, psi_i, x_j, y_j, psi_j): (m, 3, 6)."""
        s, c = self.sin, self.cos
        jr = np.zeros((s.size, 3, 6))
        jr[:, 0, 0], jr[:, 0, 1], jr[:, 0, 2], jr[:, 0, 3], jr[:, 0, 4] = (
            -s, -c, self.starboard, s, c,
        )  # fmt: skip
        jr[:, 1, 0], jr[:, 1, 1], jr[:, 1, 2], jr[:, 1, 3], jr[:, 1, 4] = (
            -c, s, -self.forward, c, -s,
        )  # fmt: skip
        jr[:, 2, 2], jr[:, 2, 5] = -1.0, 1.0
        return jr


def between(poses: Array, i: npt.NDArray[np.int64], j: npt.NDArray[np.int64]) -> Between:
    """Rows ``j`` of ``poses`` (n, 3) in the frames of rows ``i`` (``relative_pose`` over
    pairs; the heading change left unwrapped for the caller's residual)."""
    dx = poses[j, 0] - poses[i, 0]
    dy = poses[j, 1] - poses[i, 1]
    psi = poses[i, 2]
    s, c = np.sin(psi), np.cos(psi)
    return Between(s * dx + c * dy, c * dx - s * dy, poses[j, 2] - psi, s, c)


def between_jacobian(a: Array, b: Array) -> Array:
    """The 3 x 6 Jacobian of ``relative_pose(a, b)`` over (a, b), for one pair."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    psi = a[2]
    s, c = math.sin(psi), math.cos(psi)
    fwd, stb = s * dx + c * dy, c * dx - s * dy
    return np.array(
        [
            [-s, -c, stb, s, c, 0.0],
            [-c, s, -fwd, c, -s, 0.0],
            [0.0, 0.0, -1.0, 0.0, 0.0, 1.0],
        ]
    )
