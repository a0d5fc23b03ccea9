"""The seabed under the boat, ping by ping: the sonar's altitude and the bottom's slope.

A fixed ``altitude_m`` for a whole survey is wrong on any sloping shore and through a
tide, and a wrong altitude is a wrong ground range everywhere in the fan (at 2.5 m of
slant range, 1.6 m of altitude assumed against 1.1 m true puts the seabed about 0.3 m
off). This module gives, for each ping, the plane of the seabed under the sonar, from the
best source there is: a downward echosounder's soundings (``RangeSample``) placed in the
local frame by the navigation; else the sonar's own, where its vertical beam first lights
the bed (``mapping.sonar_depth``); else the configured altitude on a level bed.

Soundings (frames and units: local east/north metres, depth metres down from the GPS
antenna's level; heading clockwise from grid north). A Ping2-class echosounder's beam
is a cone some 30 degrees wide: it reports the nearest bottom inside it, which on any
slope a survey meets (up to 10 %, 5.7 degrees) and at any roll and pitch a survey boat
meets (a few degrees) is the perpendicular distance from its transducer to the bottom,
whatever the boat's attitude. The bottom straight below the transducer then lies
``d sqrt(1 + |g|^2)`` below it (g the bottom's gradient). A narrow beam along the body's
down axis would read ``d / cos(tilt)`` instead; at 3 degrees of roll that is 0.14 % (1.4
mm at 1 m), below the sounding noise, so the two are not told apart.

The plane under a ping (``BottomModel.at``) is fitted, by weighted least squares, to
the soundings around the seabed the ping sees (its lit band's centre): depth =
``z0 + g_e (x - x_c) + g_n (y - y_c) + tau (t - t_ping)``, each sounding weighted by a
Gaussian of its distance from the footprint's centre (``fit_radius_m``, or the footprint's
own size, whichever is larger) and by its noise (``sounding_sigma_m``: the sensor, heave,
the navigation), with priors in physical units on the slope (``slope_sigma``) and on the
tide's rate (``tide_rate_sigma_mps``): where the soundings lie along one line the slope
across it stays at its prior, level. Two reweighted passes (Cauchy, ``outlier_sigmas``)
keep a fish, weed or a dropout's stray reading out. The altitude is the plane's depth
under the level sonar position less the sonar's own depth below the antenna (its mount's
``down_m``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from mapping.polar import Attitude
from mapping.samples import Ping, RangeSample
from mapping.sonar_depth import SonarDepthParams, SonarHead, sonar_soundings
from mapping.tasks import TaskPool

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class EchosounderMount:
    """Where a downward echosounder's transducer sits on the vehicle (body FRD, metres
    from the GPS antenna), and the span of distances it reports validly (metres)."""

    forward_m: float = 0.0
    starboard_m: float = 0.0
    down_m: float = 0.3
    min_distance_m: float = 0.3
    max_distance_m: float = 100.0


@dataclass(frozen=True, slots=True)
class BottomParams:
    """How the seabed under each ping is found (metres, seconds)."""

    use_echosounder: bool = True
    """Take the altitude and slope from a downward echosounder's soundings when the
    navigation log has them."""
    use_sonar: bool = True
    """Else take them from the sonar's own pings (``mapping.sonar_depth``); else the
    configured altitude, level."""
    sonar: SonarDepthParams = field(default_factory=SonarDepthParams)
    echosounder: EchosounderMount = EchosounderMount()
    sounding_sigma_m: float = 0.04
    """One sounding's error as a depth under the footprint: a Ping2's 0.5 % of range and
    its centimetre of resolution, the boat's heave (2-5 cm in a light chop, which the
    antenna's level does not see) and the navigation's placement."""
    fit_radius_m: float = 1.5
    """Sigma of the Gaussian weight of a sounding by its distance from the lit band's
    centre, at least; a longer range's wider footprint takes its own size (a third of
    the band's depth plus its half width)."""
    max_soundings: int = 600
    """The nearest soundings (to the footprint's centre) a plane is fitted to."""
    min_soundings: int = 5
    """Fewer soundings within three fit radii: no plane, the configured altitude."""
    slope_sigma: float = 0.15
    """Prior of each slope component (m/m): shores survey boats map slope up to 10 %."""
    tide_rate_sigma_mps: float = 0.3 / 3600.0
    """Prior of the water level's rate (m/s): tides of 0.3-1 m rise at up to 0.3 m an
    hour in the shallows our users survey."""
    outlier_sigmas: float = 3.0
    """Cauchy scale of the reweighting, in sounding sigmas."""
    heave_window_s: float = 3.0
    """The boat's heave (2-5 cm in a light chop, a 2-3 s period; the navigation does not
    see it) is what the soundings' depths below the antenna do faster than this: their
    running median over the window is the bed under the boat, what is left the heave,
    which moves the sonar with the transducer."""
    heave_smoothing_s: float = 0.4
    """The heave at a ping: the soundings' heave averaged over this window about it (a
    sixth of a wave period: the soundings' centimetre of noise halved)."""


@dataclass(frozen=True, slots=True)
class BottomPlane:
    """The seabed under one ping: ``altitude_m`` of the level sonar position above the
    bottom straight below it; ``slope_east`` / ``slope_north`` the depth gained per
    metre east and north (m/m); ``soundings`` the number it was fitted to."""

    altitude_m: float
    slope_east: float
    slope_north: float
    soundings: int
    heave_m: float = 0.0
    """The boat's heave at the ping (m, up), in ``altitude_m``."""


class BottomModel:
    """The seabed plane under each ping, from soundings placed by the navigation.

    points: (n, 4) each sounding's transducer (east, north, depth below the antenna's
    level) and its distance to the bottom, times (n,) their stamps; ``sonar_down_m``
    the sonar's depth below the antenna on a level boat; ``footprint``: the lit band's
    (near, far) ground range ahead of the sonar and its half width (metres), where the
    ping's plane is fitted.
    """

    def __init__(
        self,
        points: Array,
        times: Array,
        sonar_down_m: float,
        footprint: tuple[float, float, float],
        params: BottomParams,
        source: str = "echosounder",
    ) -> None:
        self.points = np.asarray(points, float).reshape(-1, 4).copy()
        self.times = np.asarray(times, float)
        self.source = source
        """"echosounder" or "sonar". The sonar's soundings of one ping lie across a fan
        metres wide, on a slope at depths decimetres apart: the heave is told from each
        ping's median (``_ping_heave``)."""
        self.heave = (
            _heave(self.times, self.points[:, 2] + self.points[:, 3], params)
            if source == "echosounder"
            else _ping_heave(self.times, self.points[:, 2], params)
        )
        """The boat's heave at each sounding (m, up), taken out of the depths below."""
        self.points[:, 2] -= self.heave
        order = np.argsort(self.times, kind="stable")
        self._heave_t, self._heave_v = self.times[order], self.heave[order]
        self.sonar_down_m = float(sonar_down_m)
        near, far, half_width = footprint
        self.look_ahead_m = 0.5 * (near + far)
        self.radius_m = max(params.fit_radius_m, (far - near) / 3.0 + 0.5 * half_width)
        self.params = params
        self._tree = cKDTree(self.points[:, :2]) if len(self.points) else None

    def __len__(self) -> int:
        return len(self.points)

    def heave_at(self, time: float) -> float:
        """The boat's heave (m, up) at ``time``: the soundings' within
        ``heave_smoothing_s`` of it, averaged (0 where there are none); the sonar's,
        sounded some pings apart, between the pings sounded."""
        if self.source == "sonar":
            if not self._heave_t.size:
                return 0.0
            return float(np.interp(time, self._heave_t, self._heave_v))
        half = 0.5 * self.params.heave_smoothing_s
        a = int(np.searchsorted(self._heave_t, time - half, side="left"))
        b = int(np.searchsorted(self._heave_t, time + half, side="right"))
        return float(np.mean(self._heave_v[a:b])) if b > a else 0.0

    def at(self, time: float, sonar_pose: Array) -> BottomPlane | None:
        """The plane under a ping taken at ``time`` with the sonar's level position and
        boresight azimuth ``sonar_pose`` (east, north, radians clockwise from grid north);
        None where too few soundings lie near its footprint."""
        if self._tree is None:
            return None
        p = self.params
        x, y, azimuth = (float(v) for v in sonar_pose)
        centre = np.array(
            [x + self.look_ahead_m * math.sin(azimuth), y + self.look_ahead_m * math.cos(azimuth)]
        )
        k = min(p.max_soundings, len(self.points))
        distance, index = self._tree.query(centre, k=k, distance_upper_bound=3.0 * self.radius_m)
        distance, index = np.atleast_1d(distance), np.atleast_1d(index)
        near = np.isfinite(distance)
        if int(near.sum()) < p.min_soundings:
            return None
        index = index[near]
        pts = self.points[index]
        dt = self.times[index] - time
        # depth = z0 + g_e dx + g_n dy + tau dt; priors on g and tau (z0 free).
        design = np.column_stack(
            [np.ones(len(index)), pts[:, 0] - centre[0], pts[:, 1] - centre[1], dt]
        )
        spatial = np.exp(-0.5 * (distance[near] / self.radius_m) ** 2)
        prior_info = np.diag([0.0, p.slope_sigma**-2, p.slope_sigma**-2, p.tide_rate_sigma_mps**-2])
        robust = np.ones(len(index))
        solution = np.zeros(4)
        for _ in range(3):
            # The nearest bottom in the cone is the perpendicular: straight below the
            # transducer it lies sqrt(1 + |g|^2) times deeper (g from the pass before).
            depth = pts[:, 2] + pts[:, 3] * math.sqrt(1.0 + solution[1] ** 2 + solution[2] ** 2)
            w = spatial * robust / p.sounding_sigma_m**2
            info = design.T @ (design * w[:, None]) + prior_info
            solution = np.linalg.solve(info, design.T @ (w * depth))
            residual = (depth - design @ solution) / (p.outlier_sigmas * p.sounding_sigma_m)
            robust = 1.0 / (1.0 + residual * residual)
        z0, g_e, g_n = solution[:3]
        below = z0 + g_e * (x - centre[0]) + g_n * (y - centre[1])
        heave = self.heave_at(time)
        altitude = below - self.sonar_down_m + heave
        if not math.isfinite(altitude) or altitude <= 0.0:
            return None
        return BottomPlane(float(altitude), float(g_e), float(g_n), len(index), heave)


def _heave(times: Array, depth: Array, params: BottomParams) -> Array:
    """The boat's heave (m, up) at each sounding: its depth below the antenna's level
    less the running median over ``heave_window_s`` (the bed under the boat; a median, so
    a false short return neither moves it nor counts as heave: its own heave is set to 0
    when it stands out by more than ``outlier_sigmas`` sounding sigmas)."""
    heave = np.zeros(times.size)
    if times.size < 3:
        return heave
    order = np.argsort(times, kind="stable")
    t, d = times[order], depth[order]
    half = 0.5 * params.heave_window_s
    lo = np.searchsorted(t, t - half, side="left")
    hi = np.searchsorted(t, t + half, side="right")
    trend = np.array([np.median(d[a:b]) for a, b in zip(lo, hi, strict=True)])
    residual = d - trend
    spread = params.outlier_sigmas * params.sounding_sigma_m
    residual[np.abs(residual) > spread] = 0.0
    heave[order] = residual
    return heave


def _ping_heave(times: Array, depth: Array, params: BottomParams) -> Array:
    """The boat's heave (m, up) at each of the sonar's soundings: ``_heave`` of each
    ping's median depth (its soundings share its stamp), given to its soundings."""
    stamps, ping_of = np.unique(times, return_inverse=True)
    order = np.argsort(ping_of, kind="stable")
    groups = np.split(depth[order], np.cumsum(np.bincount(ping_of, minlength=stamps.size))[:-1])
    medians = np.array([np.median(g) for g in groups])
    return _heave(stamps, medians, params)[ping_of]


def sounding_points(
    soundings: Sequence[RangeSample],
    vehicle_at: Callable[[Array], tuple[Array, npt.NDArray[np.bool_]]],
    tilt_at: Callable[[float], Attitude | None],
    mount: EchosounderMount,
) -> tuple[Array, Array]:
    """Each usable sounding's transducer (east, north, depth below the antenna's level)
    and distance to the bottom, (n, 4), and its time. ``vehicle_at(times)`` gives the
    vehicle poses (x east, y north, heading) at the soundings' times and which are
    known; ``tilt_at`` the roll and pitch. Readings outside the mount's valid span, or
    not finite, are left out."""
    times = np.array([s.time for s in soundings], float)
    dist = np.array([s.distance_m for s in soundings], float)
    ok = np.isfinite(times) & np.isfinite(dist)
    ok &= (dist >= mount.min_distance_m) & (dist <= mount.max_distance_m)
    poses, known = vehicle_at(times)
    ok &= known
    times, dist, poses = times[ok], dist[ok], poses[ok]
    tilts = [tilt_at(float(t)) for t in times]
    roll = np.array([a.roll_rad if a is not None else 0.0 for a in tilts])
    pitch = np.array([a.pitch_rad if a is not None else 0.0 for a in tilts])
    # The transducer in the level, heading-aligned frame (FRD): R_LB = Ry(pitch) Rx(roll).
    x, y, z = mount.forward_m, mount.starboard_m, mount.down_m
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    fwd = cp * x + sp * sr * y + sp * cr * z
    stb = cr * y - sr * z
    down = -sp * x + cp * sr * y + cp * cr * z
    s, c = np.sin(poses[:, 2]), np.cos(poses[:, 2])
    east = poses[:, 0] + fwd * s + stb * c
    north = poses[:, 1] + fwd * c - stb * s
    points = np.column_stack([east, north, down, dist]).reshape(-1, 4)
    return points, times


def slope_in_heading(plane: BottomPlane, heading_rad: float) -> tuple[float, float]:
    """The plane's slope along a heading and to its starboard (m/m)."""
    s, c = math.sin(heading_rad), math.cos(heading_rad)
    return (
        plane.slope_east * s + plane.slope_north * c,
        plane.slope_east * c - plane.slope_north * s,
    )


def footprint_band(
    altitude_m: float, max_range_m: float, half_fan_rad: float, lit_range_m: float
) -> tuple[float, float, float]:
    """The lit band's (near, far) ground range ahead of the sonar and its half width
    (metres) on a level bed ``altitude_m`` below it; ``lit_range_m`` the slant range where
    the vertical beam first lights the bed (the tilt is in it)."""
    h = max(altitude_m, 0.0)
    near = math.sqrt(max(lit_range_m**2 - h * h, 0.0))
    far = math.sqrt(max(max_range_m**2 - h * h, 0.0))
    return near, far, far * math.sin(min(half_fan_rad, math.pi / 2))


class SeabedAttitude:
    """Each ping's roll, pitch, altitude and bottom slope (``polar.Attitude``), by its
    stamp: the roll and pitch from ``tilt_at`` (the autopilot's attitude track), the
    altitude and slope from the bottom model under the sonar's level position at the
    vehicle's pose then (``vehicle_at``: pose and whether it is known, for an array of
    stamps). Where the model has no plane the fan's configured altitude stays, level.
    The results of the ping stamps given up front are kept (``prepare``)."""

    def __init__(
        self,
        model: BottomModel,
        vehicle_at: Callable[[Array], tuple[Array, npt.NDArray[np.bool_]]],
        sonar_pose: Callable[[Array], Array],
        tilt_at: Callable[[float], Attitude | None] | None,
    ) -> None:
        self.model = model
        self.vehicle_at = vehicle_at
        self.sonar_pose = sonar_pose
        self.tilt_at = tilt_at
        self._kept: dict[float, Attitude | None] = {}
        self.planes: dict[float, BottomPlane] = {}
        """The plane found under each ping stamp asked for (for the report)."""
        self.configured_holds = False
        """The sonar's soundings agree with the configured level bed (``configured_holds``):
        the configured altitude is to be used."""

    def prepare(self, stamps: Array) -> None:
        """Work out the attitudes of these ping stamps at once (the poses in one call)."""
        stamps = np.asarray(stamps, float)
        poses, known = self.vehicle_at(stamps)
        for k, stamp in enumerate(stamps):
            self._kept[float(stamp)] = self._attitude(float(stamp), poses[k] if known[k] else None)

    def __call__(self, stamp: float) -> Attitude | None:
        if stamp in self._kept:
            return self._kept[stamp]
        poses, known = self.vehicle_at(np.array([stamp]))
        attitude = self._attitude(stamp, poses[0] if known[0] else None)
        self._kept[stamp] = attitude
        return attitude

    def _attitude(self, stamp: float, vehicle: Array | None) -> Attitude | None:
        tilt = self.tilt_at(stamp) if self.tilt_at is not None else None
        if vehicle is None:
            return tilt
        sonar = self.sonar_pose(vehicle)
        plane = self.model.at(stamp, sonar)
        if plane is None:
            return tilt
        self.planes[stamp] = plane
        forward, starboard = slope_in_heading(plane, float(vehicle[2]))
        roll, pitch = (tilt.roll_rad, tilt.pitch_rad) if tilt is not None else (0.0, 0.0)
        return Attitude(roll, pitch, plane.altitude_m, forward, starboard)


def pose_interpolator(
    times: Array, poses: Array
) -> Callable[[Array], tuple[Array, npt.NDArray[np.bool_]]]:
    """Vehicle poses (x, y, heading) at any stamps within the span of known ``poses`` at
    ``times`` (rows with NaN unknown), linearly (heading unwrapped); outside: unknown."""
    ok = np.all(np.isfinite(poses), axis=1)
    t, p = np.asarray(times, float)[ok], np.asarray(poses, float)[ok]
    heading = np.unwrap(p[:, 2]) if len(p) else p[:, 2]

    def at(stamps: Array) -> tuple[Array, npt.NDArray[np.bool_]]:
        stamps = np.asarray(stamps, float)
        out = np.full((stamps.size, 3), np.nan)
        if t.size < 2:
            return out, np.zeros(stamps.size, bool)
        known = (stamps >= t[0]) & (stamps <= t[-1])
        out[:, 0] = np.interp(stamps, t, p[:, 0])
        out[:, 1] = np.interp(stamps, t, p[:, 1])
        out[:, 2] = np.interp(stamps, t, heading) % (2 * math.pi)
        return out, known

    return at


def seabed_attitude(
    soundings: Sequence[RangeSample],
    times: Array,
    priors: Array,
    tilt_at: Callable[[float], Attitude | None] | None,
    sonar: SonarGeometry,
    params: BottomParams,
    pings: Callable[[], Iterable[Ping]] | None = None,
    pool: TaskPool | None = None,
) -> SeabedAttitude | None:
    """The per-ping attitude with the seabed from the echosounder's soundings, else from
    the sonar's own ``pings`` (yielded afresh on each call), the pings at ``times`` with
    the vehicle ``priors`` (x, y, heading; NaN unknown) placing both; None when neither
    is to be used or too few soundings are found. ``pool``: where the sonar's pings are
    sounded (``sonar_soundings``; None: here), the soundings the same."""
    vehicle_at = pose_interpolator(times, priors)
    model: BottomModel | None = None
    if params.use_echosounder and soundings:
        points, stamps = sounding_points(
            soundings, vehicle_at, tilt_at or (lambda _t: None), params.echosounder
        )
        if len(points) >= params.min_soundings:
            model = BottomModel(points, stamps, sonar.down_m, sonar.footprint(), params)
    if model is None and params.use_sonar and pings is not None and sonar.head is not None:
        points, stamps = sonar_soundings(
            pings(),
            vehicle_at,
            sonar.sonar_pose,
            tilt_at,
            sonar.head,
            sonar.down_m,
            params.sonar,
            pool,
        )
        if len(points) >= params.min_soundings:
            # Each sounding's error grows with the depth (a fraction of it, measured).
            depth = float(np.median(points[:, 2])) - sonar.down_m
            sigma = params.sonar.depth_sigma_fraction * max(depth, params.sonar.min_range_m)
            fitted = replace(params, sounding_sigma_m=sigma)
            model = BottomModel(points, stamps, sonar.down_m, sonar.footprint(), fitted, "sonar")
    if model is None:
        return None
    attitude = SeabedAttitude(model, vehicle_at, sonar.sonar_pose, tilt_at)
    attitude.prepare(np.asarray(times, float))
    if model.source == "sonar":
        stamps = np.array(sorted(attitude.planes), float)
        attitude.configured_holds = configured_holds(
            attitude.planes, vehicle_at(stamps)[0], sonar.altitude_m, params.sonar
        )
    return attitude


def configured_holds(
    planes: Mapping[float, BottomPlane],
    poses: Array,
    altitude_m: float,
    params: SonarDepthParams,
) -> bool:
    """Whether the configured level bed ``altitude_m`` below the sonar agrees with the
    planes through the sonar's own soundings (by stamp; ``poses`` the vehicle's (x, y,
    heading) at each, in time order) within their accuracy, as a survey: their median
    altitude (the heave aside: the configured altitude is the calm water's) near it, and
    no sloping bed or tide that explains how they vary (``SonarDepthParams.bed_*``): a
    plane in position and a line in time fitted to them, alongside a term in the boat's
    heading (the bed's depth cannot depend on it: that part is the first return's own
    bias). A level bed at the right altitude then maps better than planes that carry the
    soundings' noise and bias."""
    stamps = np.array(sorted(planes), float)
    if altitude_m <= 0 or stamps.size < 8:
        return False
    relative = np.array([planes[t].altitude_m - planes[t].heave_m for t in stamps]) / altitude_m
    relative -= 1.0
    if abs(float(np.median(relative))) > params.altitude_tolerance:
        return False
    poses = np.asarray(poses, float)
    ok = np.all(np.isfinite(poses[:, :3]), axis=1)
    if ok.sum() < 8:
        return True
    xy, heading = poses[ok, :2], poses[ok, 2]
    bed = np.column_stack([xy - xy.mean(axis=0), stamps[ok] - stamps[ok].mean()])
    design = np.column_stack([np.ones(bed.shape[0]), bed, np.cos(heading), np.sin(heading)])
    values = relative[ok]
    solution, *_ = np.linalg.lstsq(design, values, rcond=None)
    total = float(np.var(values))
    explained = 1.0 - float(np.var(values - design @ solution)) / total if total > 0 else 0.0
    low, high = np.percentile(bed @ solution[1:4], [5, 95])
    return not (explained >= params.bed_explained and high - low > params.bed_span)


@dataclass(frozen=True, slots=True)
class SonarGeometry:
    """What the bottom model needs of the sonar: its depth below the antenna on a level
    boat (m), where its lit band lies on a level bed (``footprint_band``'s arguments) and
    the level sonar pose of a vehicle pose (``frames.SonarMount.sonar_pose``)."""

    down_m: float
    altitude_m: float
    max_range_m: float
    half_fan_rad: float
    lit_range_m: float
    sonar_pose: Callable[[Array], Array]
    head: SonarHead | None = None
    """The sonar's tilt, lever arm and mount yaw (to read the seabed in its pings)."""

    def footprint(self) -> tuple[float, float, float]:
        return footprint_band(
            self.altitude_m, self.max_range_m, self.half_fan_rad, self.lit_range_m
        )
