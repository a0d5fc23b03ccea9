"""What a mapping result is scored against, and the reference trajectory read from a CSV.

A reference gives, at each frame time (UNIX s, the .oculus item stamp), the true pose of
the vehicle reference point (east, north UTM metres; heading radians clockwise from grid
north), the true sonar head (``tools.footprint.Heads``) and the sonar's fan
(``tools.footprint.Fan``): ``Reference.at``. Two kinds: the simulator's truth.json
(``tools.evaluation.truth.SimTruth``) and a trajectory from a better navigation system
(RTK + INS, a total station) in a CSV (``ReferenceTrajectory``, below). The scorer
(``tools.evaluation.truth.evaluate``) takes either and computes every metric one way.

The CSV has the contract's ``trajectory.csv`` columns, by name in a header row, extra
columns ignored: ``time`` (UNIX s, the boat computer's clock), ``lat``, ``lon`` (WGS84
degrees, of the vehicle reference point: the GPS antenna), ``heading_deg`` (degrees
clockwise from TRUE north) required; ``east``, ``north`` optional (UTM metres in the
survey's zone; absent: projected from lat/lon with pyproj in the survey's zone);
``roll_deg``, ``pitch_deg`` (FRD, degrees) and ``altitude_m`` (sonar head above the
seabed, metres) optional: where absent the sonar head is taken level, at the altitude the
replay used (``SonarSetup.altitude_m``). Times must increase strictly.

Matching (``match_times``): a frame between two reference rows no more than ``max_gap_s``
apart takes the pose interpolated between them (position, roll, pitch and altitude
linearly, heading along the shorter arc of the circle); otherwise the nearest row within
``tolerance_s``; otherwise the frame has no reference pose and is left out of every
metric (counted in the report).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from drivers.errors import SeamapError
from mapping.coverage import SonarFan
from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from tools.evaluation.metrics import Quadrat
from tools.footprint import Fan, Heads
from tools.se2 import wrap

Array = npt.NDArray[np.float64]
Index = npt.NDArray[np.int64]

REQUIRED = ("time", "lat", "lon", "heading_deg")
OPTIONAL = ("east", "north", "roll_deg", "pitch_deg", "altitude_m")

MAX_GAP_S = 1.0
"""Default widest gap (s) between two reference rows a frame is interpolated across: a
1 Hz RTK fix or faster. At a survey boat's 0.3-0.5 m/s on a turn of 3 m radius the chord
between rows 1 s apart is within 1 cm of the arc (s^2 / 8 r), and at a constant turn
rate the heading moves linearly between them."""


@dataclass(frozen=True)
class SonarSetup:
    """What the replay knows of the sonar, for a reference without the simulator's own
    geometry: the mount (config: lever arm, yaw, tilt), the fan of its pings as the
    mapper keeps it (``mapping.coverage.SonarFan``: range, half fan, vertical aperture)
    and the altitude of the head above the seabed the replay used (metres)."""

    mount: SonarMount
    fan: SonarFan
    altitude_m: float


@dataclass(frozen=True)
class Matched:
    """A reference at the frames' times: ``poses`` (n, 3) true (east, north, grid heading
    rad) of the antenna, NaN rows where it has none; ``heads`` the true sonar heads (NaN
    east there); ``fan`` the sonar's; ``summary`` how the frames were matched (report)."""

    poses: Array
    heads: Heads
    fan: Fan
    summary: dict[str, Any]


class Reference(Protocol):
    """A source of true poses (module doc)."""

    @property
    def path(self) -> Path: ...

    @property
    def unavailable(self) -> str | None:
        """Why the seabed metrics (quadrats, the mosaic against the seabed) cannot be had
        from it, or None."""

    def at(self, times: Array, epsg: int, sonar: SonarSetup | None) -> Matched: ...

    def quadrats(self) -> list[Quadrat]: ...

    def seabed_on_grid(
        self, shape: tuple[int, int], west: float, north: float, res: float
    ) -> Array | None: ...


def looks_like_csv(path: Path) -> bool:
    """Whether the file's first line is a CSV header naming a reference column (told by
    content, not by name)."""
    try:
        with path.open("rb") as f:
            first = f.readline(4096).decode("utf-8-sig", errors="replace")
    except OSError:
        return False
    if first.lstrip().startswith("{"):
        return False  # JSON, even minified onto one line
    names = {name.strip().lower() for name in first.split(",")}
    return "," in first and bool(names & {*REQUIRED, *OPTIONAL})


@dataclass(frozen=True)
class ReferenceTrajectory:
    """Reference poses read from a CSV (module doc); ``tolerance_s`` None: half the median
    interval between the frames' times (so a reference row is nearest to one frame only)."""

    path: Path
    columns: dict[str, Array]
    tolerance_s: float | None = None
    max_gap_s: float = MAX_GAP_S
    unavailable: str | None = (
        "quadrat spacing and the mosaic against the seabed need the simulator's quadrats "
        "and seabed: not available with a reference trajectory"
    )

    @property
    def times(self) -> Array:
        return self.columns["time"]

    def quadrats(self) -> list[Quadrat]:
        return []

    def seabed_on_grid(
        self, shape: tuple[int, int], west: float, north: float, res: float
    ) -> Array | None:
        return None

    def utm_poses(self, epsg: int) -> Array:
        """Every row's (east, north, grid heading rad), UTM zone ``epsg``: east/north as
        given, else projected from lat/lon; the heading turned from true to grid north by
        the meridian convergence at the row."""
        c = self.columns
        frame = LocalFrame(epsg, 0.0, 0.0)
        if "east" in c:
            east, north = c["east"], c["north"]
        else:
            east, north = frame.to_local(c["lat"], c["lon"])
        # The grid azimuth of true north: a short step north through the projection.
        step = 1e-4
        e0, n0 = frame.to_local(c["lat"] - step, c["lon"])
        e1, n1 = frame.to_local(c["lat"] + step, c["lon"])
        convergence = np.arctan2(e1 - e0, n1 - n0)
        heading = np.mod(np.radians(c["heading_deg"]) + convergence, 2 * math.pi)
        return np.stack([np.asarray(east, float), np.asarray(north, float), heading], axis=1)

    def at(self, times: Array, epsg: int, sonar: SonarSetup | None) -> Matched:
        """The reference at ``times`` (module doc); the heads from the poses, the mount's
        lever arm and the roll, pitch and altitude columns where given (else level, at
        ``sonar.altitude_m``); the fan from ``sonar``: the Oculus is a line array, so its
        beams are cones (``Fan.line_array``), as the mapper's polar model takes them."""
        if sonar is None:
            raise SeamapError(f"{self.path}: a reference trajectory needs the sonar's setup")
        tolerance = default_tolerance(times) if self.tolerance_s is None else self.tolerance_s
        left, right, weight, how = match_times(self.times, times, tolerance, self.max_gap_s)
        rows = self.utm_poses(epsg)
        poses = np.full((times.size, 3), np.nan)
        ok = how > 0
        a, b, w = left[ok], right[ok], weight[ok]
        poses[ok, :2] = rows[a, :2] + w[:, None] * (rows[b, :2] - rows[a, :2])
        poses[ok, 2] = np.mod(rows[a, 2] + w * wrap(rows[b, 2] - rows[a, 2]), 2 * math.pi)

        def column(name: str, default: float) -> Array:
            out = np.full(times.size, np.nan)
            values = self.columns.get(name)
            if values is None:
                out[ok] = default
            else:
                out[ok] = values[a] + w * (values[b] - values[a])
            return out

        roll = np.radians(column("roll_deg", 0.0))
        pitch = np.radians(column("pitch_deg", 0.0))
        altitude = column("altitude_m", sonar.altitude_m)
        heads = sonar_heads(poses, roll, pitch, altitude, sonar.mount)
        fan = Fan(
            range_m=sonar.fan.max_slant_m,
            half_fan_rad=sonar.fan.half_angle_rad,
            half_aperture_rad=sonar.fan.vertical_aperture_rad / 2.0,
            tilt_rad=sonar.mount.tilt_rad,
            mount_yaw_rad=sonar.mount.yaw_rad,
            line_array=True,
        )
        given = [name for name in OPTIONAL if name in self.columns]
        summary: dict[str, Any] = {
            "kind": "reference trajectory",
            "path": str(self.path),
            "rows": int(self.times.size),
            "columns": [*REQUIRED, *given],
            "frames": int(times.size),
            "frames_matched": int(ok.sum()),
            "frames_interpolated": int((how == INTERPOLATED).sum()),
            "frames_nearest": int((how == NEAREST).sum()),
            "frames_unmatched": int((~ok).sum()),
            "tolerance_s": tolerance,
            "max_gap_s": self.max_gap_s,
        }
        assumed = []
        if "roll_deg" not in self.columns or "pitch_deg" not in self.columns:
            assumed.append("the head level where roll/pitch are not given")
        if "altitude_m" not in self.columns:
            assumed.append(f"the head {sonar.altitude_m:.2f} m above the seabed (the replay's)")
        if assumed:
            summary["assumed"] = "; ".join(assumed)
        return Matched(poses, heads, fan, summary)


NEAREST = 1
INTERPOLATED = 2


def default_tolerance(times: Array) -> float:
    """Half the median interval (s) between consecutive frame times (0.05 s at 10 Hz):
    within it a reference row is nearer to its frame than to any other."""
    stamps = np.sort(times[np.isfinite(times)])
    steps = np.diff(stamps)
    steps = steps[steps > 0]
    return float(np.median(steps) / 2.0) if steps.size else 0.05


def match_times(
    rows: Array, times: Array, tolerance_s: float, max_gap_s: float
) -> tuple[Index, Index, Array, npt.NDArray[np.int8]]:
    """Per frame time, the reference rows (``rows``: increasing times, s) its pose comes
    from: ``left``, ``right`` and the weight of ``right`` (pose = left + w (right - left)),
    and how: INTERPOLATED between two rows no more than ``max_gap_s`` apart, else NEAREST
    row within ``tolerance_s`` (``left == right``, w = 0), else 0 (no pose)."""
    n = rows.size
    right = np.searchsorted(rows, times, side="right")  # the first row after the frame
    left = right - 1
    lc, rc = np.clip(left, 0, n - 1), np.clip(right, 0, n - 1)
    gap = rows[rc] - rows[lc]
    between = (left >= 0) & (right < n) & (gap <= max_gap_s)
    weight = np.where(between, (times - rows[lc]) / np.where(gap > 0, gap, 1.0), 0.0)
    to_left = np.where(left >= 0, times - rows[lc], np.inf)
    to_right = np.where(right < n, rows[rc] - times, np.inf)
    nearest = np.where(to_left <= to_right, lc, rc)
    near = ~between & (np.minimum(to_left, to_right) <= tolerance_s)
    how = np.where(between, INTERPOLATED, np.where(near, NEAREST, 0)).astype(np.int8)
    left_out = np.where(between, lc, nearest).astype(np.int64)
    right_out = np.where(between, rc, nearest).astype(np.int64)
    return left_out, right_out, weight, how


def sonar_heads(
    poses: Array, roll: Array, pitch: Array, altitude: Array, mount: SonarMount
) -> Heads:
    """The sonar heads of antenna ``poses`` (n, 3: UTM east, north m, grid heading rad):
    the mount's lever arm (body FRD, m) turned into grid north/east/down by
    Rz(heading) Ry(pitch) Rx(roll) (radians), its horizontal part added to the antenna."""
    heading = poses[:, 2]
    ch, sh = np.cos(heading), np.sin(heading)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    x, y, z = mount.forward_m, mount.starboard_m, mount.down_m
    d_north = ch * cp * x + (ch * sp * sr - sh * cr) * y + (ch * sp * cr + sh * sr) * z
    d_east = sh * cp * x + (sh * sp * sr + ch * cr) * y + (sh * sp * cr - ch * sr) * z
    return Heads(
        east=poses[:, 0] + d_east,
        north=poses[:, 1] + d_north,
        heading=heading,
        pitch=pitch,
        roll=roll,
        altitude=altitude,
    )


def read_reference_csv(
    path: Path, tolerance_s: float | None = None, max_gap_s: float = MAX_GAP_S
) -> ReferenceTrajectory:
    """A reference trajectory CSV (module doc). SeamapError, one line naming the file, the
    row (the file's line) and column, and why, if it is not one."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such reference trajectory") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SeamapError(f"{path}: not a readable reference trajectory CSV ({exc})") from None
    reader = csv.reader(io.StringIO(text))
    header = [name.strip() for name in next(reader, [])]
    for name in REQUIRED:
        if name not in header:
            raise SeamapError(
                f"{path}: row 1 (the header): no column {name!r} (a reference trajectory "
                f"needs {','.join(REQUIRED)})"
            )
    if ("east" in header) != ("north" in header):
        given, other = ("east", "north") if "east" in header else ("north", "east")
        raise SeamapError(f"{path}: row 1 (the header): column {given!r} without {other!r}")
    used = [name for name in (*REQUIRED, *OPTIONAL) if name in header]
    for name in used:
        if header.count(name) > 1:
            raise SeamapError(f"{path}: row 1 (the header): column {name!r} twice")
    where = {name: header.index(name) for name in used}
    values: dict[str, list[float]] = {name: [] for name in used}
    lines: list[int] = []
    for row in reader:
        if not any(cell.strip() for cell in row):
            continue
        line = reader.line_num
        if len(row) != len(header):
            raise SeamapError(
                f"{path}: row {line}: {len(row)} fields, the header has {len(header)}"
            )
        for name, k in where.items():
            cell = row[k].strip()
            try:
                value = float(cell)
            except ValueError:
                raise SeamapError(
                    f"{path}: row {line}, column {name}: {cell!r} is not a number"
                ) from None
            if not math.isfinite(value):
                raise SeamapError(f"{path}: row {line}, column {name}: {cell!r} is not finite")
            values[name].append(value)
        lines.append(line)
    if not lines:
        raise SeamapError(f"{path}: no rows of reference poses under the header")
    columns = {name: np.asarray(v, dtype=np.float64) for name, v in values.items()}
    _check_range(path, columns, lines, "lat", 90.0)
    _check_range(path, columns, lines, "lon", 180.0)
    steps = np.diff(columns["time"])
    if (steps <= 0).any():
        k = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise SeamapError(
            f"{path}: row {lines[k]}, column time: {float(columns['time'][k])!r} is not after the "
            f"row before's {float(columns['time'][k - 1])!r} (times must increase)"
        )
    return ReferenceTrajectory(path, columns, tolerance_s, max_gap_s)


def _check_range(
    path: Path, columns: dict[str, Array], lines: list[int], name: str, limit: float
) -> None:
    bad = np.flatnonzero(np.abs(columns[name]) > limit)
    if bad.size:
        k = int(bad[0])
        raise SeamapError(
            f"{path}: row {lines[k]}, column {name}: {float(columns[name][k])!r} is outside "
            f"-{limit:g}..{limit:g} degrees"
        )
