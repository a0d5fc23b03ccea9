"""Which seabed points a ping really saw: the TRUE sonar fan of a simulated survey.

Written from truth.json alone (``sonar`` geometry, per-ping ``pings`` poses), never from
the mapper's geometry, so that a modelling error in the mapper cannot agree with itself.
A reference trajectory of a real survey (``tools.evaluation.reference``) has no such
geometry: it builds the same ``Heads`` and ``Fan`` from its poses, the config's mount and
the pings' fan.

Model: the sonar frame is the body frame (FRD) yawed by ``mount_yaw_deg`` and pitched
down by ``tilt_deg``; the body frame is the grid north/east/down frame turned by the
ping's grid heading, pitch and roll (ZYX Euler). A seabed point ``altitude_m`` below the
head (the seabed taken flat under the head) at sonar-frame vector p is seen when it is
within ``range_m`` (slant), within the fan (bearing theta within ``fan_deg / 2``) and
inside the lit band of the vertical beam (vertical angle within
``vertical_aperture_deg / 2`` of the boresight: the near edge is where the beam's lower
edge reaches the seabed). With a line array (truth ``sonar.beam_geometry`` says so, as
the simulator's does) a beam is a cone about the array's y axis:
``sin theta = p_y / |p|`` and the vertical angle is ``atan2(p_z, p_x)``; otherwise the
spherical model: ``theta = atan2(p_y, p_x)``, vertical angle ``asin(p_z / |p|)``.

Positions are UTM metres (east, north); angles radians unless the name says ``_deg``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
Index = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Fan:
    """The sonar's fixed geometry (metres, radians)."""

    range_m: float
    half_fan_rad: float
    half_aperture_rad: float
    tilt_rad: float
    mount_yaw_rad: float
    line_array: bool = False
    """Beams are cones about the array axis (``sin theta = p_y / |p|``)."""

    @classmethod
    def from_truth(cls, truth: dict[str, Any]) -> Fan:
        sonar = truth["sonar"]
        return cls(
            range_m=float(sonar["range_m"]),
            half_fan_rad=math.radians(float(sonar["fan_deg"])) / 2.0,
            half_aperture_rad=math.radians(float(sonar.get("vertical_aperture_deg", 20.0))) / 2,
            tilt_rad=math.radians(float(sonar["tilt_deg"])),
            mount_yaw_rad=math.radians(float(sonar.get("mount_yaw_deg", 0.0))),
            line_array="line array" in str(sonar.get("beam_geometry", "")).lower(),
        )


@dataclass(frozen=True)
class Heads:
    """The sonar head at each ping: UTM position, grid heading, pitch, roll (radians) of
    the vehicle, and the head's height above the seabed (metres)."""

    east: Array
    north: Array
    heading: Array
    pitch: Array
    roll: Array
    altitude: Array

    @classmethod
    def from_pings(cls, pings: Sequence[dict[str, Any]]) -> Heads:
        def column(key: str, default: float = 0.0) -> Array:
            return np.array([float(p.get(key, default)) for p in pings], dtype=np.float64)

        return cls(
            east=column("sonar_east"),
            north=column("sonar_north"),
            heading=np.radians(column("grid_heading_deg")),
            pitch=np.radians(column("pitch_deg")),
            roll=np.radians(column("roll_deg")),
            altitude=column("altitude_m", 1.0),
        )

    def __len__(self) -> int:
        return int(self.east.size)

    def take(self, index: npt.NDArray[np.int64]) -> Heads:
        """The heads at the pings ``index``."""
        return Heads(
            self.east[index],
            self.north[index],
            self.heading[index],
            self.pitch[index],
            self.roll[index],
            self.altitude[index],
        )

    @classmethod
    def missing(cls, n: int) -> Heads:
        """``n`` pings without a known head (NaN)."""
        nan = np.full(n, np.nan)
        return cls(nan, nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy())


def grid_to_sonar(fan: Fan, heads: Heads) -> Array:
    """Per ping, the rotation (n, 3, 3) from grid north/east/down to the sonar frame:
    (R_grid_body R_body_sonar)^T, R_grid_body = Rz(heading) Ry(pitch) Rx(roll),
    R_body_sonar = Rz(mount_yaw) Ry(-tilt)."""
    ch, sh = np.cos(heads.heading), np.sin(heads.heading)
    cp, sp = np.cos(heads.pitch), np.sin(heads.pitch)
    cr, sr = np.cos(heads.roll), np.sin(heads.roll)
    body = np.empty((len(heads), 3, 3))
    body[:, 0] = np.stack([ch * cp, ch * sp * sr - sh * cr, ch * sp * cr + sh * sr], axis=1)
    body[:, 1] = np.stack([sh * cp, sh * sp * sr + ch * cr, sh * sp * cr - ch * sr], axis=1)
    body[:, 2] = np.stack([-sp, cp * sr, cp * cr], axis=1)
    cy, sy = math.cos(fan.mount_yaw_rad), math.sin(fan.mount_yaw_rad)
    ct, st = math.cos(-fan.tilt_rad), math.sin(-fan.tilt_rad)
    yaw = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    pitch_down = np.array([[ct, 0.0, st], [0.0, 1.0, 0.0], [-st, 0.0, ct]])
    return np.transpose(body @ (yaw @ pitch_down), (0, 2, 1))


def fan_hits(
    fan: Fan, heads: Heads, east: Array, north: Array, chunk: int = 2_000_000
) -> tuple[Index, Index]:
    """Every (ping, point) pair where the ping's true fan saw the seabed point (UTM
    ``east``/``north``, metres), as two index arrays sorted by point then ping."""
    rotation = grid_to_sonar(fan, heads)
    frames_out: list[Index] = []
    points_out: list[Index] = []
    step = max(1, chunk // max(east.size, 1))
    for start in range(0, len(heads), step):
        stop = min(start + step, len(heads))
        d_north = north[None, :] - heads.north[start:stop, None]
        d_east = east[None, :] - heads.east[start:stop, None]
        down = np.broadcast_to(heads.altitude[start:stop, None], d_north.shape)
        # A cheap cut first: beyond the range on the ground, nothing to rotate.
        near = d_north**2 + d_east**2 + down**2 <= fan.range_m**2
        f, p = np.nonzero(near)
        if f.size == 0:
            continue
        v = np.stack([d_north[f, p], d_east[f, p], down[f, p]], axis=1)
        s = np.einsum("kij,kj->ki", rotation[start + f], v)
        slant = np.maximum(np.linalg.norm(s, axis=1), 1e-9)
        if fan.line_array:
            bearing = np.arcsin(np.clip(s[:, 1] / slant, -1.0, 1.0))
            vertical = np.arctan2(s[:, 2], s[:, 0])
        else:
            bearing = np.arctan2(s[:, 1], s[:, 0])
            vertical = np.arcsin(np.clip(s[:, 2] / slant, -1.0, 1.0))
        seen = (
            (s[:, 0] > 0)
            & (np.abs(bearing) <= fan.half_fan_rad)
            & (np.abs(vertical) <= fan.half_aperture_rad)
        )
        frames_out.append((start + f[seen]).astype(np.int64))
        points_out.append(p[seen].astype(np.int64))
    if not frames_out:
        empty = np.zeros(0, np.int64)
        return empty, empty.copy()
    frames, points = np.concatenate(frames_out), np.concatenate(points_out)
    order = np.lexsort((frames, points))
    return frames[order], points[order]
