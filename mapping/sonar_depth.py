"""The seabed's depth from the imaging sonar's own pings: where its vertical beam first
lights the bed.

Without an echosounder the sonar is its own: the seabed enters each beam where the lower
rim of the vertical beam meets it, and how far out that is says how far down the bed is.
Along one beam (a cone about the line array, bearing theta) the echo at slant range r
comes from the elevation psi(r) at which the cone meets the bed (``mapping.polar``'s
geometry), and its strength is, to first order,

    I(r) ~ B(psi(r)) x sin(grazing)^lambert x (the bed's reflectivity, the TVG's residue)

with B the two-way vertical beam pattern (a Gaussian main lobe whose -3 dB full width is
the vertical aperture: 20 degrees on an Oculus M1200d at 1.2 MHz) and Lambert's law for
the bed's backscatter (``lambert`` = 2). On a level bed both factors depend on r only
through r / h (h the sonar's height above the bed: sin(grazing) = h / r), so the profile
has one shape, stretched by h: its near half maximum, the edge of the lit band, lies at
``r = u_half h`` with u_half found from the model at the ping's tilt, roll and pitch. The
edge is found in each sector of the fan (beams averaged, so speckle averages out), its
range divided by u_half gives h, and the point where the edge ray meets the bed, placed
by the head's attitude, is a sounding of the seabed there, like an echosounder's. The
bottom model (``mapping.bottom``) fits a plane through these soundings around each ping's
footprint: the altitude and both slopes.

Measured on 8 simulated surveys (sand, mud, shell, gravel, objects; the sonar 1-6 m
above the bed, tilts 15-27 degrees, ranges 5-17 m; 60-120 pings each), a ping's
soundings against the truth's depth where they lie: median -1 to -2.5 % at 1-2 m, -1 to
-4 % at 3-6 m; 2-4 cm a ping (sd) at 1-2 m, 2-10 cm at 3-6 m. The edge taken at the
-3 dB rim without the model lay 10-18 % short (Lambert's law pulls the half maximum in).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.ndimage import median_filter

from mapping.polar import Attitude, FanGeometry, head_pose
from mapping.samples import Ping
from mapping.tasks import TaskHandle, TaskPool

Array = npt.NDArray[np.float64]

_GAUSS = 4.0 * math.log(2.0)
PEAK_SPAN = 0.05
"""Half width of the running median the lobe's peak is taken from, as a fraction of its
range: the largest sample of a noisy profile stands above the lobe by its noise, and a
bright target (a quadrat's frame, a rock) in the sector above it by much more. Measured
on 8 surveys (edge depth against the truth's): the peak's sample put the edge 5 cm deep
at 2 m with 8 beams a sector, a quadrat's frame 30 cm deep; a median over 0.05 of the
range, -1 to -2.5 % at 1-2 m and -1 to -4 % at 3-6 m, its frames within 20 cm; over 0.1,
3 % shallow everywhere (the median flattens the lobe more than the model's)."""


@dataclass(frozen=True, slots=True)
class SonarDepthParams:
    """How the seabed is found in the sonar's own pings (metres, radians)."""

    vertical_aperture_rad: float = math.radians(20.0)
    """-3 dB full width of the two-way vertical beam (the sonar's datasheet)."""
    lambert: float = 2.0
    """Exponent of sin(grazing) in the bed's backscatter (Lambert's law)."""
    sectors: int = 16
    """Sectors the fan is cut into (beams averaged in each)."""
    max_bearing_rad: float = math.radians(45.0)
    """Sectors beyond this bearing are left out: their edge lies far out and the cone's
    bend makes it shallow."""
    smoothing_m: float = 0.03
    """Half width of the box the sector's profile is smoothed over (a few range bins)."""
    min_range_m: float = 0.4
    """The transmit's ring-down: no seabed is looked for nearer."""
    min_contrast: float = 6.0
    """The lit band's peak must stand this many noise sigmas (one range bin of the water
    column, the sector's beams averaged) above the water: else the sector has no bed in
    view."""
    depth_sigma_fraction: float = 0.04
    """One sector's depth error as a fraction of the depth (measured: a ping's median
    within 2-4 cm at 1-2 m, up to 10 cm at 6 m; a sector's spread about it wider)."""
    altitude_tolerance: float = 0.06
    """The configured level bed holds where the planes' median altitude (the heave
    aside) is within this fraction of it (level beds at the configured altitude: -0.5
    to +4.1 % on quadrats seeds 2, 8, 10 and 14, the sonar's own bias), ..."""
    bed_explained: float = 0.9
    """... unless a bed that slopes or a tide that moves explains their altitudes: a
    plane in position and a line in time, fitted to every plane's altitude over the
    survey with a term in the boat's heading (the first return's own bias, which the bed
    cannot have), explains at least this fraction of their variance (R^2) ... Measured
    (without the heading term): field days 1, 5 and 6 (slopes of 2.6-6.6 %, a 29 m
    undulation, tides) 0.97-1.00; level quadrats seeds 2, 8 and 14 0.33-0.39 (with it
    0.39-0.52), seed 11 (a GNSS outage; with it) 0.79, its lanes' altitudes drifting with
    time and east alike. Their altitudes vary by as much as a field day's (p5-p95 of 8-38
    %, the lanes' and headings' biases of the first return, not the bed's), so the span
    alone did not tell them apart (field day 5: 26 %). At 0.7, seed 11 was mapped on the
    planes: lanes 3.2 -> 8.7 cm."""
    bed_span: float = 0.05
    """... and moves the altitude by more than this fraction of it over the survey
    (p5-p95 of the fitted bed): 5 % of 1 m is 1 cm of ground range at 5 m."""
    sounding_interval_s: float = 0.5
    """Pings are sounded this far apart at least: a faster sonar's neighbours see the same
    bed, and the bottom model's nearest soundings then span the same stretch of it at
    every ping rate (measured on a level bed, 600 soundings: at 10 Hz every ping gave
    slopes of 3.5 % at the median, at 2 Hz 1.9 %)."""
    model_points: int = 2000
    """Samples of r / h (from 1 to 12) the model profile is evaluated at."""


@dataclass(frozen=True, slots=True)
class SonarHead:
    """What is needed of the sonar's mounting: tilt (rad, boresight below horizontal),
    lever arm (forward, starboard, down metres from the antenna), mount yaw (rad)."""

    tilt_rad: float
    lever_arm_m: tuple[float, float, float]
    mount_yaw_rad: float = 0.0


def _profiles(ping: Ping, sectors: int, max_bearing: float) -> tuple[Array, Array]:
    """Each kept sector's mean intensity by range (n_ranges, k), gains taken out, and its
    mean bearing (k,)."""
    image = ping.image.astype(np.float64)
    if ping.gains is not None and len(ping.gains) == ping.n_ranges:
        gains = np.asarray(ping.gains, float)
        positive = gains > 0
        if positive.any():
            gains = np.where(positive, gains / float(np.median(gains[positive])), 1.0)
            image = image / gains[:, None]
    bearings = np.asarray(ping.bearings_rad, float)
    columns = [c for c in np.array_split(np.arange(ping.n_beams), sectors) if c.size]
    means = np.array([float(np.mean(bearings[c])) for c in columns])
    keep = np.abs(means) <= max_bearing
    profiles = np.column_stack(
        [np.median(image[:, c], axis=1) for c, k in zip(columns, keep, strict=True) if k]
    )
    return profiles.reshape(ping.n_ranges, -1), means[keep]


def _model_edge(
    rotation: Array, theta: float, params: SonarDepthParams
) -> tuple[float, float, float, float] | None:
    """In the cone ``theta`` of a head turned by ``rotation`` (R_CS) over a level bed: the
    model profile's near half maximum as (u = r / h, the elevation psi there), and the
    span (u_lo, u_hi) of its main lobe (from 2.5 half widths below the boresight to a
    half width above). None when the cone does not meet the bed in the lobe."""
    u = np.linspace(1.0, 12.0, params.model_points)
    c = math.cos(theta)
    a, b = c * rotation[2, 0], c * rotation[2, 2]
    rhs = 1.0 / u - math.sin(theta) * rotation[2, 1]
    hyp = math.hypot(a, b)
    if hyp <= 0.0:
        return None
    meets = np.abs(rhs) <= hyp
    psi = np.full(u.size, np.nan)
    psi[meets] = math.atan2(b, a) - np.arccos(rhs[meets] / hyp)
    half = 0.5 * params.vertical_aperture_rad
    lobe = meets & (psi <= 2.5 * half) & (psi >= -half)
    if np.count_nonzero(lobe) < 4:
        return None
    profile = np.where(meets, np.exp(-_GAUSS * (np.nan_to_num(psi) / (2 * half)) ** 2), 0.0)
    profile *= u ** (-params.lambert)
    # The peak as ``_edge`` takes it: averaged over PEAK_SPAN of its range.
    k = int(np.argmax(profile))
    du = float(u[1] - u[0])
    half_width = max(2, int(PEAK_SPAN * u[k] / du))
    wide = median_filter(profile, size=2 * half_width + 1, mode="nearest")
    k = int(np.argmax(wide))
    peak = wide[k]
    below = np.nonzero(profile[:k] < 0.5 * peak)[0]
    if below.size == 0 or peak <= 0.0:
        return None
    i = int(below[-1])
    step = (0.5 * peak - profile[i]) / max(profile[i + 1] - profile[i], 1e-12)
    u_half = float(u[i] + step * (u[1] - u[0]))
    psi_half = float(psi[i] + step * (psi[i + 1] - psi[i]))
    inside = np.nonzero(lobe)[0]
    return u_half, psi_half, float(u[inside[0]]), float(u[inside[-1]])


def _edge(
    raw: Array,
    profile: Array,
    resolution_m: float,
    water_m: float,
    span_m: tuple[float, float],
    contrast: float,
) -> float | None:
    """Slant range (m) of the near half maximum of the strongest return between
    ``span_m``, above the water column from ``water_m`` to it; None without a clear
    return. ``raw``: the sector's profile, ``profile`` the same smoothed."""
    n = profile.size
    w = max(0, int(water_m / resolution_m))
    a = max(w, int(span_m[0] / resolution_m))
    b = min(n, int(span_m[1] / resolution_m) + 1)
    if b - a < 6:
        return None
    # The lobe's peak from the profile averaged over PEAK_SPAN of its range: the largest
    # of a noisy profile stands above the lobe by its noise (measured: 8 beams a sector
    # put the edge 5 cm deep at 2 m without it, 32 beams none).
    k = a + int(np.argmax(profile[a:b]))
    half = max(2, int(PEAK_SPAN * k))
    wide = median_filter(profile, size=2 * half + 1, mode="nearest")
    k = a + int(np.argmax(wide[a:b]))
    if k - w < 16:
        return None  # too little water before it to tell a return from the noise
    water = profile[w:k]
    floor = float(np.percentile(water, 20))
    # The water column's noise, one range bin (the sector's beams averaged), from the
    # differences of neighbouring bins: the rising edge is smooth beside it.
    steps = np.diff(raw[w:k])
    noise = 1.4826 * float(np.median(np.abs(steps - np.median(steps)))) / math.sqrt(2.0)
    peak = float(wide[k]) - floor
    if peak <= 0.0 or peak < contrast * noise:
        return None
    level = floor + 0.5 * peak
    below = np.nonzero(profile[a:k] < level)[0]
    if below.size == 0:
        return None
    i = a + int(below[-1])
    step = (level - profile[i]) / max(float(profile[i + 1] - profile[i]), 1e-12)
    return (i + step + 0.5) * resolution_m


def ping_soundings(
    ping: Ping, head: SonarHead, attitude: Attitude | None, params: SonarDepthParams
) -> Array:
    """The seabed points where this ping's vertical beam first lights the bed: (k, 3)
    forward, starboard (m, in the ping's level Cartesian frame C, ``mapping.polar``) and
    depth below the level sonar position (m)."""
    fan = FanGeometry.of(
        ping.bearings_rad,
        ping.n_ranges,
        ping.range_resolution_m,
        1.0,
        head.tilt_rad,
        lever_arm_m=head.lever_arm_m,
        mount_yaw_rad=head.mount_yaw_rad,
    )
    level = Attitude(attitude.roll_rad, attitude.pitch_rad) if attitude is not None else None
    pose = head_pose(fan, level)
    profiles, thetas = _profiles(ping, params.sectors, params.max_bearing_rad)
    half = max(1, round(params.smoothing_m / ping.range_resolution_m))
    box = np.ones(2 * half + 1) / (2 * half + 1)
    points = []
    for j, theta in enumerate(thetas):
        model = _model_edge(pose.rotation, float(theta), params)
        if model is None:
            continue
        u_half, psi, u_lo, u_hi = model
        profile = np.convolve(profiles[:, j], box, mode="same")
        # First over the whole beam (the strongest return is the lit band), then within
        # the main lobe where that puts it, until the altitude settles.
        raw = profiles[:, j]
        water = params.min_range_m
        edge = _edge(
            raw,
            profile,
            ping.range_resolution_m,
            water,
            (water, ping.max_range_m),
            params.min_contrast,
        )
        for _ in range(3):
            if edge is None:
                break
            h = edge / u_half
            again = _edge(
                raw,
                profile,
                ping.range_resolution_m,
                water,
                (h * u_lo, h * u_hi),
                params.min_contrast,
            )
            if again is None or abs(again - edge) < 0.5 * ping.range_resolution_m:
                break
            edge = again
        if edge is None:
            continue
        ray = np.array(
            [math.cos(theta) * math.cos(psi), math.sin(theta), math.cos(theta) * math.sin(psi)]
        )
        points.append(pose.rotation @ (edge * ray) + pose.offset_m)
    return np.array(points, float).reshape(-1, 3)


@dataclass(frozen=True, slots=True)
class SoundingJob:
    """One ping's soundings (``ping_soundings``) as a pure task (``mapping.tasks``)."""

    ping: Ping
    head: SonarHead
    attitude: Attitude | None
    params: SonarDepthParams


def sounding_job(job: SoundingJob) -> Array:
    return ping_soundings(job.ping, job.head, job.attitude, job.params)


@dataclass(slots=True)
class _Pending:
    """A ping read and not yet sounded or passed over: its vehicle pose, whether it is
    known, and its soundings asked of the pool (None: not asked)."""

    ping: Ping
    pose: Array
    known: bool
    handle: TaskHandle[Array] | None = None


def sonar_soundings(
    pings: Iterable[Ping],
    vehicle_at: Callable[[Array], tuple[Array, npt.NDArray[np.bool_]]],
    sonar_pose: Callable[[Array], Array],
    tilt_at: Callable[[float], Attitude | None] | None,
    head: SonarHead,
    sonar_down_m: float,
    params: SonarDepthParams,
    pool: TaskPool | None = None,
) -> tuple[Array, Array]:
    """The soundings of every ping (``ping_soundings``) in the local frame, as
    ``mapping.bottom.BottomModel`` takes them: (n, 4) east, north, depth below the
    antenna's level and distance (0: the point is on the bed), and their pings' stamps.
    Pings whose vehicle pose is unknown give none.

    A ping is sounded ``sounding_interval_s`` after the last one that gave soundings, so
    which ping comes next depends on what the last gave. ``pool``: the pings the interval
    picks, assuming each gives soundings (nearly all do), are sounded there a few ahead;
    where one gives none, the pings after it are picked again from what it did, the
    soundings the same as one by one here."""
    rows: list[Array] = []
    stamps: list[Array] = []
    last = -math.inf
    interval = params.sounding_interval_s

    def attitude_of(ping: Ping) -> Attitude | None:
        return tilt_at(ping.time) if tilt_at is not None else None

    def record(ping: Ping, pose: Array, local: Array) -> bool:
        if not len(local):
            return False
        x, y, azimuth = (float(v) for v in sonar_pose(pose))
        s, c = math.sin(azimuth), math.cos(azimuth)
        east = x + local[:, 0] * s + local[:, 1] * c
        north = y + local[:, 0] * c - local[:, 1] * s
        depth = sonar_down_m + local[:, 2]
        rows.append(np.column_stack([east, north, depth, np.zeros(len(local))]))
        stamps.append(np.full(len(local), ping.time))
        return True

    if pool is None:
        for ping in pings:
            if ping.time - last < interval:
                continue
            pose, known = vehicle_at(np.array([ping.time]))
            if not known[0]:
                continue
            if record(ping, pose[0], ping_soundings(ping, head, attitude_of(ping), params)):
                last = ping.time
        return _stacked(rows, stamps)

    pending: deque[_Pending] = deque()
    predicted = -math.inf
    """``last`` after the newest pending ping, had every ping asked of the pool given
    soundings."""
    lead = 2 * pool.workers + 2

    def ask(entry: _Pending) -> None:
        nonlocal predicted
        if entry.known and entry.ping.time - predicted >= interval:
            if entry.handle is None:
                job = SoundingJob(entry.ping, head, attitude_of(entry.ping), params)
                entry.handle = pool.submit(sounding_job, job)
            predicted = entry.ping.time
        else:
            entry.handle = None  # asked too early: its answer is dropped

    def decide(entry: _Pending) -> None:
        nonlocal last, predicted
        if not entry.known or entry.ping.time - last < interval:
            return
        if entry.handle is not None:
            local = entry.handle.result()
        else:
            local = ping_soundings(entry.ping, head, attitude_of(entry.ping), params)
        if record(entry.ping, entry.pose, local):
            last = entry.ping.time
        if entry.handle is None or not len(local):
            # Not as predicted: the pings waiting are picked again from here.
            predicted = last
            for waiting in pending:
                ask(waiting)

    for ping in pings:
        pose, known = vehicle_at(np.array([ping.time]))
        entry = _Pending(ping, pose[0], bool(known[0]))
        pending.append(entry)
        ask(entry)
        while sum(e.handle is not None for e in pending) > lead:
            decide(pending.popleft())
    while pending:
        decide(pending.popleft())
    return _stacked(rows, stamps)


def _stacked(rows: list[Array], stamps: list[Array]) -> tuple[Array, Array]:
    if not rows:
        return np.zeros((0, 4)), np.zeros(0)
    return np.concatenate(rows), np.concatenate(stamps)
