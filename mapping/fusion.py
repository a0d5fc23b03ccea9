"""Survey-wide fusion in physical units: registrations, GNSS with a wandering bias, compass
and gyro in one sparse nonlinear least-squares problem.

The paper's objective (Zhang et al., Sec. III.F, Eq. 6-7) weighs registrations against
per-frame EKF priors with one lambda. Those priors are not independent: a u-blox M8N's
error is a Gauss-Markov process of about 1-1.5 m with a correlation time of tens of
seconds, plus 0.5-0.8 m of white noise, and its fixes lag the antenna. A chain weighted
against such priors bends to follow the wander, and the weight that works depends on the
ping rate. Here every measurement enters once, at its own rate, whitened by its own
standard deviation (metres, radians, seconds), and the correlated parts of the errors are
states of the problem (e.g. Barfoot, *State Estimation for Robotics*, 2017, Sec. 3.3 and
9; the GNSS bias as a first-order Gauss-Markov process as in Farrell, *Aided
Navigation*, 2008, Sec. 4.9):

Variables
    frame poses (x east, y north m; psi rad clockwise from grid north) of the vehicle
    reference point (the GPS antenna); GNSS bias knots (east, north m) on a regular time
    grid; the gyro's yaw-rate bias (rad/s) on a coarser grid of knots; the compass
    error's Fourier coefficients in heading (constant, 1 and 2 cycles: a misalignment
    plus hard- and soft-iron deviation, rad); one time offset (s) between the GNSS fixes
    and the frame stamps (receiver lag minus sonar latency).
Factors
    - relative pose i -> j (registration, odometry bridge, loop closure): the pose of j
      in the frame of i minus the measurement, times its square-root information;
      loop closures may carry a Cauchy kernel (iteratively reweighted);
    - GNSS fix z at stamp t: p(t - dt) + b(t) - z over the white sigma, p interpolated
      between the frames that bracket it, b between the knots;
    - its Doppler velocity v: the frames' mean velocity over the span of time the fix
      stands for, minus v, over the velocity sigma (free of the wander b: the course
      over the ground that pins the map's heading, and the way travelled);
    - bias process: b_k+1 - phi b_k over sigma_b sqrt(1 - phi^2), phi = exp(-h / tau),
      and the stationary b_0 over sigma_b;
    - compass h at t: psi(t) + c . f(psi) - h over its sigma, the correlated part of its
      noise inflated by the number of samples per correlation time (so many correlated
      samples count as the few independent ones they are);
    - gyro: psi_j - psi_i - (integral of the yaw rate - g (t_j - t_i)) over the noise
      density times sqrt(t_j - t_i);
    - gyro bias walk: g_k+1 - g_k over its random-walk sigma for the knot spacing;
    - zero-mean priors on the gyro bias, the compass coefficients and the time offset.

Because nothing is weighted per frame, the solution does not depend on the ping rate;
because the GNSS bias is a state, lanes 30-120 s apart may sit on different offsets
without bending the chain between them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from mapping.marginals import pose_covariance_blocks
from mapping.samples import GnssFixType
from mapping.se2 import between, between_jacobian, compose_rows, wrap_pi
from mapping.sparse import SpdFactor, factor_spd, solve_spd

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class GnssErrorModel:
    """A u-blox M8N-class receiver on a small boat (metres, seconds)."""

    white_sigma_m: float = 0.6
    """White part of the error, per axis."""
    bias_sigma_m: float = 1.2
    """Stationary sigma of the Gauss-Markov part, per axis."""
    bias_tau_s: float = 45.0
    """Correlation time of the Gauss-Markov part."""
    knot_spacing_s: float = 2.0
    """Spacing of the bias knots (linear in between): well below the correlation time."""
    time_offset_s: float = 0.1
    """Prior mean of fix lag minus sonar latency (a fix shows the antenna that long ago,
    relative to the frame stamps)."""
    time_offset_sigma_s: float = 0.15
    max_bracket_s: float = 3.0
    """Fixes between frames further apart than this are left out (no pose to tie)."""
    corrected_fix_type: int = GnssFixType.DGPS
    """Fixes of this type or better (DGPS, RTK float, RTK fixed, ...) are weighed by the
    accuracy their receiver reports (``fix_sigmas``); plainer ones by this model alone."""
    accuracy_floor_m: float = 0.005
    """The smallest reported accuracy believed (per axis): a fixed RTK solution is no
    better than its antenna's phase-centre variation and the boat's flex, a few
    millimetres, and a receiver that says less would make its fixes rigid."""
    velocity_sigma_mps: float = 0.1
    """Sigma of a fix's Doppler velocity, per axis (0: not used). A u-blox M8N states
    0.05 m/s; twice that covers the receiver's own smoothing (consecutive fixes are not
    independent) and the antenna's sway on a small boat. The velocity does not share
    the position's wander: it is what ties the map's scale to the ground where the
    registrations' is off (a faint bottom's registrations lock towards no motion)."""
    velocity_span_s: float = 1.0
    """The longest span of time one velocity fix stands for (fixes further apart leave
    gaps between their spans)."""

    def fix_sigmas(
        self, accuracy_m: Array | None, fix_type: IntArray | None, count: int
    ) -> tuple[Array, Array]:
        """Per fix, the sigma of its white error and of the wander around it (metres, per
        axis), from the accuracy its receiver reports (h_acc: metres, 1 sigma per axis;
        NaN or None: not reported) and its fix type (None: unknown).

        A corrected fix (``corrected_fix_type`` or better) has had the errors it shares
        with a base station removed; what is left (carrier-phase noise, multipath, an
        unresolved ambiguity in RTK float) the receiver measures in its own solution, and
        its h_acc is that whole error. It does not say how the error splits into white
        noise and wander, and neither part can be larger than the whole: each is the
        model's, capped at the reported accuracy. An RTK fix reporting 15 mm gets 15 mm
        of each, a float fix 0.2 m, an SBAS fix reporting 1.5 m the model's own.

        An autonomous fix (2-D, 3-D) keeps the model's sigmas: its error is the
        ionosphere's and the orbits', which the receiver cannot see; its h_acc is a guess
        from the satellites' geometry, the one the model's sigmas already make for the
        receiver class. So is a fix that reports no accuracy."""
        white = np.full(count, self.white_sigma_m)
        wander = np.full(count, self.bias_sigma_m)
        if accuracy_m is None or fix_type is None:
            return white, wander
        a = np.asarray(accuracy_m, float)
        reported = np.isfinite(a) & (a > 0) & (np.asarray(fix_type) >= self.corrected_fix_type)
        said = np.maximum(a[reported], self.accuracy_floor_m)
        white[reported] = np.minimum(self.white_sigma_m, said)
        wander[reported] = np.minimum(self.bias_sigma_m, said)
        return white, wander


@dataclass(frozen=True, slots=True)
class CompassModel:
    """A magnetic compass on a small boat (radians, seconds)."""

    white_sigma_rad: float = math.radians(0.7)
    correlated_sigma_rad: float = math.radians(1.0)
    correlation_time_s: float = 10.0
    bias_sigma_rad: float = math.radians(6.0)
    """Prior sigma of the constant misalignment."""
    deviation_sigma_rad: float = math.radians(2.0)
    """Prior sigma of each 1- and 2-cycle deviation coefficient."""


@dataclass(frozen=True, slots=True)
class GyroModel:
    """The autopilot's yaw rate, levelled (radians, seconds)."""

    noise_density: float = math.radians(0.05)
    """Angle random walk, rad/sqrt(s) (MEMS gyros: 0.01-0.05 degrees/sqrt(s); this also
    covers the levelling with a noisy roll and pitch)."""
    floor_rad: float = math.radians(0.02)
    """Added to every factor: stamp jitter and interpolation."""
    bias_sigma_rps: float = math.radians(0.5)
    """Prior sigma of the bias left after the autopilot's boot calibration."""
    bias_walk_rps: float = math.radians(0.05)
    """How far the bias wanders after boot (temperature): a random walk whose variance
    grows by ``2 bias_walk^2 / bias_walk_tau_s`` a second, the short-term growth of a
    Gauss-Markov drift of this sigma and correlation time (MEMS gyros on a small boat in
    the sun: a few hundredths of a degree a second over minutes). A constant bias cannot
    follow it, and a heading that drifts by a degree a minute between lanes was what the
    closures' predictions missed."""
    bias_walk_tau_s: float = 300.0
    knot_spacing_s: float = 10.0
    """Spacing of the gyro bias knots (linear in between)."""
    max_gap_s: float = 0.5
    """Frame pairs over an IMU gap longer than this get no gyro factor."""


@dataclass(frozen=True, slots=True)
class FusionParams:
    gnss: GnssErrorModel = field(default_factory=GnssErrorModel)
    compass: CompassModel = field(default_factory=CompassModel)
    gyro: GyroModel = field(default_factory=GyroModel)
    max_iterations: int = 25
    tolerance: float = 1e-6
    """Stop when the largest pose update is below this (metres / radians)."""
    cauchy_scale: float = 2.0
    """Robust closures: the Cauchy kernel's scale, in standard deviations."""


@dataclass(frozen=True, slots=True)
class RelativeConstraint:
    """Pose j in the frame of pose i (forward, starboard metres; yaw radians clockwise),
    with its square-root information (3 x 3, upper triangular or any W with
    W^T W = covariance^-1). ``robust``: down-weighted by a Cauchy kernel when it
    disagrees with the rest. ``kind`` names where it came from."""

    i: int
    j: int
    forward_m: float
    starboard_m: float
    yaw_rad: float
    sqrt_info: Array
    robust: bool = False
    kind: str = "registration"


@dataclass(frozen=True, slots=True)
class PosePrior:
    """Pose ``k`` held near ``pose`` (x, y metres, heading radians) with square-root
    information ``sqrt_info`` (3 x 3): a frame already drawn that can no longer move, or
    what a closure to such a frame says. ``robust``: down-weighted by the Cauchy kernel
    when it disagrees with the rest."""

    k: int
    pose: Array
    sqrt_info: Array
    robust: bool = False
    kind: str = "hold"


def sqrt_information(covariance: Array) -> Array:
    """W with W^T W = covariance^-1 (from the Cholesky factor of the inverse)."""
    info = np.linalg.inv(np.asarray(covariance, float))
    info = 0.5 * (info + info.T)
    return np.asarray(np.linalg.cholesky(info).T, float)


def diagonal_sqrt_info(sigmas: Sequence[float]) -> Array:
    return np.diag([1.0 / max(s, 1e-12) for s in sigmas])


@dataclass(frozen=True)
class FusionData:
    """The measurements, in the survey's local frame (metres, radians, UNIX seconds).

    gnss_times (g,), gnss_xy (g, 2); heading_times (h,), headings (h,) grid headings;
    yaw_integral (n,): the gyro's integrated yaw rate at each frame time (radians, NaN
    where unknown), from which consecutive frames get their gyro factors; yaw_gap (n,):
    True where the IMU had a gap between frame k-1 and k.
    """

    gnss_times: Array
    gnss_xy: Array
    heading_times: Array
    headings: Array
    yaw_integral: Array
    yaw_gap: npt.NDArray[np.bool_]
    gnss_accuracy_m: Array | None = None
    """(g,) each fix's accuracy as its receiver reported it (h_acc: metres, 1 sigma per
    axis; NaN where it reported none); None: no fix reported one."""
    gnss_fix_type: IntArray | None = None
    """(g,) each fix's type (``GnssFixType``); None: unknown. With the accuracy, what
    weighs the fix and sizes the wander around it (``GnssErrorModel.fix_sigmas``)."""
    gnss_velocity: Array | None = None
    """(g, 2) each fix's Doppler velocity (east, north m/s, grid); NaN where the receiver
    gave none (or too slow for a course); None: none at all."""


@dataclass(frozen=True)
class RigidGroups:
    """Frames held rigidly in groups: frame k's pose = anchor[group[k]] composed with
    offsets[k] (forward, starboard metres, yaw radians in the anchor's frame)."""

    group: IntArray
    offsets: Array
    n_groups: int


@dataclass(frozen=True)
class FusionSolution:
    poses: Array
    bias_times: Array
    bias_xy: Array
    gyro_bias_rps: float
    """The gyro bias's mean over the survey (rad/s)."""
    gyro_bias_times: Array
    gyro_bias_knots: Array
    """The wandering bias at its knots (rad/s)."""
    compass_coefficients: Array
    """Compass error = c . (1, sin psi, cos psi, sin 2 psi, cos 2 psi), radians."""
    time_offset_s: float
    iterations: int
    chi2: dict[str, float]
    """Sum of squared whitened residuals per kind of factor."""
    counts: dict[str, int]
    robust_weights: Array
    """Per constraint, the final IRLS weight (1 for non-robust ones)."""


_N_COMPASS = 5


class _Layout:
    def __init__(self, n: int, n_knots: int, n_gyro_knots: int) -> None:
        self.n = n
        self.n_knots = n_knots
        self.n_gyro_knots = n_gyro_knots
        self.bias0 = 3 * n
        self.gyro = self.bias0 + 2 * n_knots
        self.compass0 = self.gyro + n_gyro_knots
        self.offset = self.compass0 + _N_COMPASS
        self.size = self.offset + 1


class _Builder:
    """Accumulates whitened residual rows and their Jacobian triplets."""

    def __init__(self) -> None:
        self.residuals: list[Array] = []
        self.rows: list[IntArray] = []
        self.cols: list[IntArray] = []
        self.vals: list[Array] = []
        self.kinds: list[tuple[str, int, int]] = []
        self.count = 0

    def block(self, kind: str, residual: Array) -> int:
        """Reserve rows for ``residual`` (flat); returns the first row index."""
        start = self.count
        self.residuals.append(np.asarray(residual, float).ravel())
        self.count += self.residuals[-1].size
        self.kinds.append((kind, start, self.count))
        return start

    def add(self, rows: IntArray, cols: IntArray, vals: Array) -> None:
        rows, cols, vals = np.broadcast_arrays(
            np.asarray(rows, np.int64), np.asarray(cols, np.int64), np.asarray(vals, float)
        )
        self.rows.append(rows.ravel())
        self.cols.append(cols.ravel())
        self.vals.append(vals.ravel())

    def assemble(self, size: int) -> tuple[Array, sp.csr_matrix]:
        residual = np.concatenate(self.residuals) if self.residuals else np.zeros(0)
        jac = sp.csr_matrix(
            (
                np.concatenate(self.vals) if self.vals else np.zeros(0),
                (
                    np.concatenate(self.rows) if self.rows else np.zeros(0, np.int64),
                    np.concatenate(self.cols) if self.cols else np.zeros(0, np.int64),
                ),
            ),
            shape=(self.count, size),
        )
        return residual, jac


def _bracket(
    times: Array, query: Array, max_bracket_s: float
) -> tuple[IntArray, Array, npt.NDArray[np.bool_]]:
    """Index k with times[k] <= q <= times[k+1], the fraction w, and which queries are
    usable (inside the frames' span, between frames at most ``max_bracket_s`` apart)."""
    n = times.size
    k = np.clip(np.searchsorted(times, query, side="right") - 1, 0, max(n - 2, 0))
    k1 = np.minimum(k + 1, n - 1)
    span = times[k1] - times[k]
    w = np.where(span > 0, (query - times[k]) / np.where(span > 0, span, 1.0), 0.0)
    usable = (w >= -0.05) & (w <= 1.05) & (span <= max_bracket_s)
    return k.astype(np.int64), np.clip(w, 0.0, 1.0), usable


def _knot_scales(knot_times: Array, spacing_s: float, fix_times: Array, fix_scales: Array) -> Array:
    """Per GNSS bias knot, the largest wander sigma (in units of the model's
    ``bias_sigma_m``: ``fix_scales``, per fix) of the fixes whose bias it helps
    interpolate (those within one spacing of it): a knot beside an RTK-float fix may
    wander as far as that fix says. Knots no fix touches (an outage) take the scale of
    their nearest touched neighbours, linear in time; 1 with no fix at all."""
    n = knot_times.size
    if fix_times.size == 0:
        return np.ones(n)
    kb = np.clip(np.floor((fix_times - knot_times[0]) / spacing_s), 0, n - 2).astype(np.int64)
    out = np.zeros(n)
    np.maximum.at(out, kb, fix_scales)
    np.maximum.at(out, kb + 1, fix_scales)
    touched = out > 0
    if not touched.all():
        out = np.interp(knot_times, knot_times[touched], out[touched])
    return out


def _rebracket_threshold(times: Array, data: FusionData, white_m: Array) -> float:
    """How far (s) the estimated time offset may leave the one the fixes were bracketed
    at before they are bracketed again (``Fusion.solve``): half a frame interval, where
    the fixes are sharper (their median white sigma, metres) than the motion between
    frames (the boat's median speed over 10 s of fixes, above their noise, times the
    median frame interval). Only there does a fix extrapolated beyond its bracket give a
    lever that fits noise; a metre-class fix is never bracketed again, as it never was."""
    if times.size < 2 or data.gnss_times.size < 2:
        return math.inf
    interval = float(np.median(np.diff(times)))
    later = np.searchsorted(data.gnss_times, data.gnss_times + _SPEED_BASELINE_S)
    has = later < data.gnss_times.size
    if not has.any():
        return math.inf
    dt = data.gnss_times[later[has]] - data.gnss_times[has]
    moved = np.hypot(*(data.gnss_xy[later[has]] - data.gnss_xy[has]).T)
    speed = float(np.median(moved / dt))
    return 0.5 * interval if float(np.median(white_m)) < speed * interval else math.inf


_SPEED_BASELINE_S = 10.0


def _bias_steps(model: GnssErrorModel, knot_scales: Array) -> tuple[Array, Array]:
    """The GNSS bias process between consecutive knots: b_k+1 = rho_k b_k + w_k, with
    w_k's sigma (both per knot pair; metres). The bias's sigma at knot k is
    s_k = bias_sigma_m * knot_scales[k]; between knots of equal s it is the stationary
    first-order Gauss-Markov process (Farrell 2008, Sec. 4.9): rho = phi = exp(-h / tau),
    sigma_w = s sqrt(1 - phi^2). Where the receiver reports its accuracy changing, the
    process keeps s_k as the bias's sigma at every knot: a worsening (RTK fixed to float)
    adds an independent error, rho = phi and sigma_w^2 = s_k+1^2 - phi^2 s_k^2; an
    improvement (float back to fixed) leaves the old error behind in proportion, rho =
    phi s_k+1 / s_k and sigma_w = s_k+1 sqrt(1 - phi^2): a receiver that reports
    centimetres again has let go of its decimetres."""
    phi = math.exp(-model.knot_spacing_s / model.bias_tau_s)
    before, after = knot_scales[:-1], knot_scales[1:]
    rho = phi * np.minimum(1.0, after / before)
    # In units of bias_sigma_m, so that a constant scale of 1 gives the stationary
    # process's sigma to the last bit.
    variance = after * after - (rho * before) * (rho * before)
    return rho, model.bias_sigma_m * np.sqrt(np.maximum(variance, 1e-12 * after * after))


def _velocity_factors(b: _Builder, fusion: Fusion, poses: Array, reference: float) -> None:
    """Each fix's Doppler velocity against the frames' mean velocity over the span of
    time it stands for: half-way to the fixes either side, at most ``velocity_span_s``
    (the spans tile the survey, so no frame interval between fixes escapes them and no
    fix counts twice), its ends interpolated between the frames around them and slid
    by the reference offset, as a position fix is."""
    d = fusion.data
    g = fusion.params.gnss
    if d.gnss_velocity is None or g.velocity_sigma_mps <= 0 or d.gnss_times.size < 2:
        return
    t = d.gnss_times - reference
    edges = np.concatenate([[t[0] - (t[1] - t[0])], t, [t[-1] + (t[-1] - t[-2])]])
    before = np.minimum(0.5 * (edges[1:-1] - edges[:-2]), 0.5 * g.velocity_span_s)
    after = np.minimum(0.5 * (edges[2:] - edges[1:-1]), 0.5 * g.velocity_span_s)
    k0, w0, ok0 = _bracket(fusion.times, t - before, g.max_bracket_s)
    k1, w1, ok1 = _bracket(fusion.times, t + after, g.max_bracket_s)
    usable = ok0 & ok1 & np.isfinite(d.gnss_velocity).all(axis=1) & (before + after > 1e-3)
    if not usable.any():
        return
    k0, w0, k1, w1 = k0[usable], w0[usable], k1[usable], w1[usable]
    span = (before + after)[usable]
    v = d.gnss_velocity[usable]
    inv = 1.0 / (g.velocity_sigma_mps * fusion._velocity_scale[usable])
    start_pos = (1 - w0)[:, None] * poses[k0, :2] + w0[:, None] * poses[k0 + 1, :2]
    end_pos = (1 - w1)[:, None] * poses[k1, :2] + w1[:, None] * poses[k1 + 1, :2]
    predicted = (end_pos - start_pos) / span[:, None]
    start = b.block("gnss_velocity", inv[:, None] * (predicted - v))
    m = k0.size
    per = inv / span
    for axis in range(2):
        rows = start + 2 * np.arange(m) + axis
        b.add(rows, 3 * k1 + axis, per * (1 - w1))
        b.add(rows, 3 * (k1 + 1) + axis, per * w1)
        b.add(rows, 3 * k0 + axis, -per * (1 - w0))
        b.add(rows, 3 * (k0 + 1) + axis, -per * w0)


def compass_basis(psi: Array) -> tuple[Array, Array]:
    """f(psi) (m, 5) and df/dpsi (m, 5)."""
    s1, c1 = np.sin(psi), np.cos(psi)
    s2, c2 = np.sin(2 * psi), np.cos(2 * psi)
    one = np.ones_like(psi)
    zero = np.zeros_like(psi)
    f = np.stack([one, s1, c1, s2, c2], axis=1)
    df = np.stack([zero, c1, -s1, 2 * c2, -2 * s2], axis=1)
    return f, df


def _relative_factors(
    b: _Builder,
    poses: Array,
    constraints: Sequence[RelativeConstraint],
    weights: Array,
) -> None:
    if not constraints:
        return
    ei = np.array([c.i for c in constraints], np.int64)
    ej = np.array([c.j for c in constraints], np.int64)
    meas = np.array([(c.forward_m, c.starboard_m, c.yaw_rad) for c in constraints], float)
    sqrt_w = np.sqrt(weights)[:, None, None]
    wmat = np.stack([c.sqrt_info for c in constraints]) * sqrt_w  # (m, 3, 3)
    rel = between(poses, ei, ej)
    raw = np.column_stack(
        [rel.forward - meas[:, 0], rel.starboard - meas[:, 1], wrap_pi(rel.turn - meas[:, 2])]
    )
    m = len(constraints)
    # Raw Jacobian (m, 3, 6) over (x_i, y_i, psi_i, x_j, y_j, psi_j).
    jr = rel.jacobian()
    start = b.block("relative", np.einsum("mab,mb->ma", wmat, raw))
    jw = np.einsum("mab,mbk->mak", wmat, jr)
    rows = start + 3 * np.arange(m)[:, None, None] + np.arange(3)[None, :, None]
    cols_i = 3 * ei[:, None] + np.arange(3)[None, :]
    cols_j = 3 * ej[:, None] + np.arange(3)[None, :]
    cols = np.concatenate([cols_i, cols_j], axis=1)[:, None, :]
    b.add(np.broadcast_to(rows, jw.shape), np.broadcast_to(cols, jw.shape), jw)


def _prior_factors(b: _Builder, poses: Array, priors: Sequence[PosePrior], weights: Array) -> None:
    if not priors:
        return
    k = np.array([p.k for p in priors], np.int64)
    target = np.array([p.pose for p in priors], float)
    wmat = np.stack([p.sqrt_info for p in priors]) * np.sqrt(weights)[:, None, None]
    raw = poses[k] - target
    raw[:, 2] = wrap_pi(raw[:, 2])
    start = b.block("prior", np.einsum("mab,mb->ma", wmat, raw))
    m = len(priors)
    rows = start + 3 * np.arange(m)[:, None, None] + np.arange(3)[None, :, None]
    cols = (3 * k[:, None] + np.arange(3)[None, :])[:, None, :]
    b.add(np.broadcast_to(rows, wmat.shape), np.broadcast_to(cols, wmat.shape), wmat)


def prior_chi2(poses: Array, priors: Sequence[PosePrior]) -> Array:
    """Squared Mahalanobis residual of each pose prior at ``poses``."""
    if not priors:
        return np.zeros(0)
    b = _Builder()
    _prior_factors(b, poses, priors, np.ones(len(priors)))
    return _squared_norms(b)


def _squared_norms(b: _Builder) -> Array:
    """Per 3-row factor of the builder's one block, its squared whitened residual."""
    r = b.residuals[0].reshape(-1, 3)
    return np.asarray((r * r).sum(axis=1), float)


def relative_chi2(poses: Array, constraints: Sequence[RelativeConstraint]) -> Array:
    """Squared Mahalanobis residual of each constraint at ``poses``."""
    if not constraints:
        return np.zeros(0)
    b = _Builder()
    _relative_factors(b, poses, constraints, np.ones(len(constraints)))
    return _squared_norms(b)


# What an exact prediction of closure covariances may cost (flops: about a minute here).
EXACT_COVARIANCE_WORK = 6e10
# Beyond it, the time around a pair whose factors its windowed covariance keeps (s), and
# the shortest window a batch of pairs shares. The GNSS bias decorrelates in 45 s and the
# gyro bias wanders over minutes: what lies further from both frames barely moves their
# relative pose.
COVARIANCE_MARGIN_S = 120.0
COVARIANCE_WINDOW_S = 600.0
# Right-hand sides solved at once: bounded memory (columns x unknowns x 8 bytes).
_RHS_BYTES = 64 * 2**20


class Fusion:
    """Builds and solves the problem for one set of frames (``times`` ascending)."""

    def __init__(
        self,
        times: Array,
        data: FusionData,
        params: FusionParams | None = None,
        rigid: RigidGroups | None = None,
        priors: Sequence[PosePrior] = (),
    ):
        """rigid: frames held rigidly in groups (two-stage's submaps): each frame's pose is
        its group's anchor pose composed with a fixed offset, and the anchors are what is
        solved for. priors: poses held near given values (the live re-solve's frames that
        can no longer move, and its closures to them)."""
        self.params = params or FusionParams()
        self.times = np.asarray(times, float)
        self.data = data
        self.rigid = rigid
        self.priors = list(priors)
        self._prior_weights = np.ones(len(self.priors))
        g = self.params.gnss
        n = self.times.size
        if n == 0:
            raise ValueError("no frames to fuse")
        t0 = float(
            min(self.times[0], data.gnss_times[0] if data.gnss_times.size else self.times[0])
        )
        t1 = float(
            max(self.times[-1], data.gnss_times[-1] if data.gnss_times.size else self.times[-1])
        )
        n_knots = max(2, math.ceil((t1 - t0) / g.knot_spacing_s) + 1)
        self.knot_times: Array = t0 + np.arange(n_knots, dtype=np.float64) * g.knot_spacing_s
        gm = self.params.gyro
        n_gyro = max(2, math.ceil((t1 - t0) / gm.knot_spacing_s) + 1)
        self.gyro_knot_times: Array = t0 + np.arange(n_gyro, dtype=np.float64) * gm.knot_spacing_s
        # Each fix's white sigma and the wander's sigma at the knots around it, from the
        # accuracy its receiver reports; the wander's in units of bias_sigma_m.
        self._fix_white, wander = g.fix_sigmas(
            data.gnss_accuracy_m, data.gnss_fix_type, data.gnss_times.size
        )
        self._fix_white_stated = self._fix_white
        self._knot_scale = _knot_scales(
            self.knot_times, g.knot_spacing_s, data.gnss_times, wander / g.bias_sigma_m
        )
        self._bracket_offset_s = g.time_offset_s
        self._velocity_scale = np.ones(data.gnss_times.size)
        self._rebracket_s = _rebracket_threshold(self.times, data, self._fix_white)
        self.layout = _Layout(n if rigid is None else rigid.n_groups, n_knots, n_gyro)
        self._frame_layout = _Layout(n, n_knots, n_gyro)
        # Gyro factors between consecutive frames with a known integral. Rigid groups
        # fix the yaw between their own frames: there the gyro spans whole groups, from
        # one group's first frame to the next's (inside a group it would only fight the
        # chain it cannot move, and pull the bias to the chain's rotation error).
        yaw = data.yaw_integral
        ok = np.isfinite(yaw[1:]) & np.isfinite(yaw[:-1]) & ~data.yaw_gap[1:]
        if rigid is None:
            self._gyro_a = np.flatnonzero(ok).astype(np.int64)
            self._gyro_b = self._gyro_a + 1
        else:
            first = np.flatnonzero(np.diff(rigid.group, prepend=-1) != 0).astype(np.int64)
            broken = np.concatenate([[0], np.cumsum(~ok)])  # pairs without a factor, so far
            a, b = first[:-1], first[1:]
            whole = broken[b] - broken[a] == 0
            self._gyro_a, self._gyro_b = a[whole], b[whole]

    # -- residuals ------------------------------------------------------------------
    def _build(
        self,
        state: Array,
        constraints: Sequence[RelativeConstraint],
        weights: Array,
    ) -> tuple[Array, sp.csr_matrix, list[tuple[str, int, int]]]:
        p = self.params
        frame_state, to_state = self._frame_state(state)
        state = frame_state
        lay = self._frame_layout
        n = lay.n
        poses = state[: 3 * n].reshape(n, 3)
        bias = state[lay.bias0 : lay.gyro].reshape(lay.n_knots, 2)
        gyro_knots = state[lay.gyro : lay.compass0]
        coeffs = state[lay.compass0 : lay.offset]
        offset = state[lay.offset]
        b = _Builder()

        _relative_factors(b, poses, constraints, weights)
        _prior_factors(b, poses, self.priors, self._prior_weights)

        # GNSS fixes.
        d = self.data
        if d.gnss_times.size and n >= 2:
            # The frames bracketing each fix are chosen at a reference offset (the prior's,
            # until the estimate leaves it by half a frame interval: ``solve``): the
            # estimated offset moves the fix along that bracket (linearly, beyond it if it
            # must). Re-bracketing at each iteration made the problem jump between frame
            # intervals and Gauss-Newton wander by millimetres without converging; never
            # re-bracketing let centimetre fixes, extrapolated brackets away, be met by
            # the brackets' frames moving a fraction as far (a lever that fits noise).
            reference = self._bracket_offset_s
            query = d.gnss_times - reference
            k, w, usable = _bracket(self.times, query, p.gnss.max_bracket_s)
            k, w, z, tq = k[usable], w[usable], d.gnss_xy[usable], d.gnss_times[usable]
            white = self._fix_white[usable]
            if k.size:
                k1 = k + 1
                w = w - (offset - reference) / np.maximum(self.times[k1] - self.times[k], 1e-6)
                pos = (1 - w)[:, None] * poses[k, :2] + w[:, None] * poses[k1, :2]
                kb = np.clip(
                    np.floor((tq - self.knot_times[0]) / p.gnss.knot_spacing_s), 0, lay.n_knots - 2
                ).astype(np.int64)
                u = np.clip((tq - self.knot_times[kb]) / p.gnss.knot_spacing_s, 0.0, 1.0)
                bxy = (1 - u)[:, None] * bias[kb] + u[:, None] * bias[kb + 1]
                per_m = 1.0 / white
                start = b.block("gnss", per_m[:, None] * (pos + bxy - z))
                m = k.size
                span = self.times[k1] - self.times[k]
                velocity = (poses[k1, :2] - poses[k, :2]) / np.maximum(span, 1e-6)[:, None]
                for axis in range(2):
                    rows = start + 2 * np.arange(m) + axis
                    b.add(rows, 3 * k + axis, per_m * (1 - w))
                    b.add(rows, 3 * k1 + axis, per_m * w)
                    b.add(rows, lay.bias0 + 2 * kb + axis, per_m * (1 - u))
                    b.add(rows, lay.bias0 + 2 * (kb + 1) + axis, per_m * u)
                    b.add(rows, np.full(m, lay.offset), -per_m * velocity[:, axis])
            _velocity_factors(b, self, poses, reference)

        # The bias as a Gauss-Markov process between knots, its sigma at each knot the
        # model's scaled by the reported accuracy there (``_bias_steps``), stationary at
        # the first.
        g = p.gnss
        nk = lay.n_knots
        rho, bias_step = _bias_steps(g, self._knot_scale)
        start = b.block("bias_process", (bias[1:] - rho[:, None] * bias[:-1]) / bias_step[:, None])
        for axis in range(2):
            rows = start + 2 * np.arange(nk - 1) + axis
            b.add(rows, lay.bias0 + 2 * np.arange(1, nk) + axis, 1 / bias_step)
            b.add(rows, lay.bias0 + 2 * np.arange(nk - 1) + axis, -rho / bias_step)
        first_sigma = g.bias_sigma_m * self._knot_scale[0]
        start = b.block("bias_prior", bias[0] / first_sigma)
        b.add(start + np.arange(2), lay.bias0 + np.arange(2), np.full(2, 1 / first_sigma))

        # Compass headings.
        cm = p.compass
        if d.heading_times.size and n >= 2:
            k, w, usable = _bracket(self.times, d.heading_times, p.gnss.max_bracket_s)
            k, w, h = k[usable], w[usable], d.headings[usable]
            if k.size:
                k1 = k + 1
                psi = poses[k, 2] + w * wrap_pi(poses[k1, 2] - poses[k, 2])
                f, df = compass_basis(psi)
                spacing = (
                    float(np.median(np.diff(d.heading_times))) if d.heading_times.size > 1 else 1.0
                )
                inflate = max(1.0, 2.0 * cm.correlation_time_s / max(spacing, 1e-3))
                sigma = math.sqrt(cm.white_sigma_rad**2 + cm.correlated_sigma_rad**2 * inflate)
                inv = 1.0 / sigma
                start = b.block("compass", inv * wrap_pi(psi + f @ coeffs - h))
                rows = start + np.arange(k.size)
                slope = 1.0 + df @ coeffs
                b.add(rows, 3 * k + 2, inv * (1 - w) * slope)
                b.add(rows, 3 * k1 + 2, inv * w * slope)
                for c in range(_N_COMPASS):
                    b.add(rows, np.full(k.size, lay.compass0 + c), inv * f[:, c])
        compass_sigmas = np.array([cm.bias_sigma_rad] + [cm.deviation_sigma_rad] * (_N_COMPASS - 1))
        start = b.block("compass_prior", coeffs / compass_sigmas)
        b.add(
            start + np.arange(_N_COMPASS), lay.compass0 + np.arange(_N_COMPASS), 1 / compass_sigmas
        )

        # Gyro yaw increments between consecutive frames, the bias interpolated between
        # its knots at the pair's middle.
        gm = p.gyro
        kk, kb = self._gyro_a, self._gyro_b
        ng = lay.n_gyro_knots
        if kk.size:
            dt = self.times[kb] - self.times[kk]
            measured = d.yaw_integral[kb] - d.yaw_integral[kk]
            sigma = np.sqrt(gm.noise_density**2 * np.maximum(dt, 0.0) + gm.floor_rad**2)
            inv = 1.0 / sigma
            middle = 0.5 * (self.times[kb] + self.times[kk])
            kg = np.clip(
                np.floor((middle - self.gyro_knot_times[0]) / gm.knot_spacing_s), 0, ng - 2
            ).astype(np.int64)
            ug = np.clip((middle - self.gyro_knot_times[kg]) / gm.knot_spacing_s, 0.0, 1.0)
            gyro_bias = (1 - ug) * gyro_knots[kg] + ug * gyro_knots[kg + 1]
            raw = wrap_pi(poses[kb, 2] - poses[kk, 2] - (measured - gyro_bias * dt))
            start = b.block("gyro", inv * raw)
            rows = start + np.arange(kk.size)
            b.add(rows, 3 * kb + 2, inv)
            b.add(rows, 3 * kk + 2, -inv)
            b.add(rows, lay.gyro + kg, inv * dt * (1 - ug))
            b.add(rows, lay.gyro + kg + 1, inv * dt * ug)
        # The bias wanders as a random walk between knots from its boot-calibration prior.
        step_sigma = gm.bias_walk_rps * math.sqrt(2.0 * gm.knot_spacing_s / gm.bias_walk_tau_s)
        start = b.block("gyro_walk", np.diff(gyro_knots) / step_sigma)
        rows = start + np.arange(ng - 1)
        b.add(rows, lay.gyro + np.arange(1, ng), np.full(ng - 1, 1 / step_sigma))
        b.add(rows, lay.gyro + np.arange(ng - 1), np.full(ng - 1, -1 / step_sigma))
        start = b.block("gyro_prior", np.array([gyro_knots[0] / gm.bias_sigma_rps]))
        b.add(np.array([start]), np.array([lay.gyro]), np.array([1 / gm.bias_sigma_rps]))

        start = b.block(
            "offset_prior", np.array([(offset - g.time_offset_s) / g.time_offset_sigma_s])
        )
        b.add(np.array([start]), np.array([lay.offset]), np.array([1 / g.time_offset_sigma_s]))

        residual, jac = b.assemble(lay.size)
        if to_state is not None:
            jac = (jac @ to_state).tocsr()
        return residual, jac, b.kinds

    def _frame_state(self, state: Array) -> tuple[Array, sp.csr_matrix | None]:
        """The state with every frame's pose (from its anchor, when rigid), and the
        Jacobian of that state with respect to the solved one (None: the same)."""
        rigid = self.rigid
        if rigid is None:
            return state, None
        lay, fl = self.layout, self._frame_layout
        anchors = state[: 3 * lay.n].reshape(lay.n, 3)
        a = anchors[rigid.group]
        o = rigid.offsets
        frames = compose_rows(a, o)
        s, c = np.sin(a[:, 2]), np.cos(a[:, 2])  # the composition's Jacobian takes them
        out = np.concatenate([frames.ravel(), state[3 * lay.n :]])
        n = fl.n
        k = np.arange(n)
        g = rigid.group
        rows = [3 * k, 3 * k + 1, 3 * k + 2, 3 * k, 3 * k + 1]
        cols = [3 * g, 3 * g + 1, 3 * g + 2, 3 * g + 2, 3 * g + 2]
        vals = [
            np.ones(n),
            np.ones(n),
            np.ones(n),
            o[:, 0] * c - o[:, 1] * s,
            -o[:, 0] * s - o[:, 1] * c,
        ]
        extra = fl.size - 3 * n
        rows.append(3 * n + np.arange(extra))
        cols.append(3 * lay.n + np.arange(extra))
        vals.append(np.ones(extra))
        t = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(fl.size, lay.size),
        )
        return out, t

    def frame_poses(self, state: Array) -> Array:
        """(n, 3) frame poses of a solved state."""
        frames, _ = self._frame_state(state)
        n = self._frame_layout.n
        return frames[: 3 * n].reshape(n, 3).copy()

    # -- solving --------------------------------------------------------------------
    def initial_state(self, poses: Array) -> Array:
        """The state to start from: ``poses`` are frame poses, or anchor poses when the
        frames are rigid groups."""
        lay = self.layout
        state = np.zeros(lay.size)
        state[: 3 * lay.n] = np.asarray(poses, float).ravel()
        state[lay.offset] = self.params.gnss.time_offset_s
        return state

    def solve(
        self,
        initial_poses: Array,
        constraints: Sequence[RelativeConstraint],
        state: Array | None = None,
    ) -> tuple[FusionSolution, Array]:
        """Gauss-Newton (with IRLS weights for robust constraints) from ``initial_poses``
        (or a previous ``state``); returns the solution and its state vector."""
        p = self.params
        lay = self.layout
        x = self.initial_state(initial_poses) if state is None else np.array(state, float)
        robust = np.array([c.robust for c in constraints], bool)
        robust_priors = np.array([h.robust for h in self.priors], bool)
        weights = np.ones(len(constraints))
        self._prior_weights = np.ones(len(self.priors))
        iterations = 0
        for iterations in range(1, p.max_iterations + 1):  # noqa: B007
            # Cauchy: w = 1 / (1 + e^2 / c^2), e the Mahalanobis residual.
            if robust.any():
                sq = relative_chi2(self.frame_poses(x), constraints)
                weights = np.where(robust, 1.0 / (1.0 + sq / p.cauchy_scale**2), 1.0)
            if robust_priors.any():
                sq = prior_chi2(self.frame_poses(x), self.priors)
                self._prior_weights = np.where(
                    robust_priors, 1.0 / (1.0 + sq / p.cauchy_scale**2), 1.0
                )
            residual, jac, _ = self._build(x, constraints, weights)
            step = solve_spd(jac.T @ jac, -(jac.T @ residual))
            x = x + step
            x[2 : 3 * lay.n : 3] %= 2 * math.pi
            if abs(x[lay.offset] - self._bracket_offset_s) > self._rebracket_s:
                # The fixes have slid half a frame along their brackets: choose them
                # again at the estimate (a few times a survey, not every iteration).
                self._bracket_offset_s = float(x[lay.offset])
                continue
            if float(np.max(np.abs(step[: 3 * lay.n]), initial=0.0)) < p.tolerance:
                break
        residual, jac, kinds = self._build(x, constraints, weights)
        self._last = (x, constraints, weights, jac)
        self._last_rows = (residual, kinds)
        self.last_state = x
        chi2: dict[str, float] = {}
        counts: dict[str, int] = {}
        for kind, a, z in kinds:
            chi2[kind] = chi2.get(kind, 0.0) + float(residual[a:z] @ residual[a:z])
            counts[kind] = counts.get(kind, 0) + (z - a)
        solution = FusionSolution(
            poses=self.frame_poses(x),
            bias_times=self.knot_times.copy(),
            bias_xy=x[lay.bias0 : lay.gyro].reshape(lay.n_knots, 2).copy(),
            gyro_bias_rps=float(np.mean(x[lay.gyro : lay.compass0])),
            gyro_bias_times=self.gyro_knot_times.copy(),
            gyro_bias_knots=x[lay.gyro : lay.compass0].copy(),
            compass_coefficients=x[lay.compass0 : lay.offset].copy(),
            time_offset_s=float(x[lay.offset]),
            iterations=iterations,
            chi2=chi2,
            counts=counts,
            robust_weights=weights,
        )
        return solution, x

    def set_gnss_sigma_factors(self, position: float, velocity: float = 1.0) -> None:
        """Every fix's white sigma ``position`` times what its model or report gives,
        its velocity's ``velocity`` times (variance components: ``single_stage``)."""
        self._fix_white = self._fix_white_stated * position
        self._velocity_scale = np.full(self.data.gnss_times.size, velocity)

    def variance_components(
        self,
        constraint_groups: dict[str, tuple[npt.NDArray[np.bool_], tuple[int, ...]]],
        factor_kinds: Sequence[str] = (),
        probes: int = 48,
    ) -> dict[str, tuple[float, float]]:
        """At the last solution: per group, its chi-square and its redundancy (how many of
        its rows the rest of the problem checks: rows less the trace of its share of the
        hat matrix J (J^T J)^-1 J^T). Their ratio is the group's variance factor: 1 where
        its covariances are right, more where its measurements scatter more than they
        said (Helmert / Foerstner variance component estimation).

        constraint_groups: names to (a mask over the last solve's constraints, which of
        their whitened rows: 0 and 1 translation, 2 yaw); factor_kinds: kinds of factor
        taken whole ("gnss", "gnss_velocity"). The hat matrix's diagonal is estimated with
        ``probes`` Rademacher vectors (Hutchinson), drawn from a fixed seed: the same
        problem gives the same factors."""
        jac = self._last[3]
        residual, kinds = self._last_rows
        rows: dict[str, IntArray] = {}
        for name in factor_kinds:
            spans = [np.arange(a, z) for kind, a, z in kinds if kind == name]
            rows[name] = np.concatenate(spans).astype(np.int64) if spans else np.zeros(0, np.int64)
        start = next((a for kind, a, _ in kinds if kind == "relative"), 0)
        for name, (mask, components) in constraint_groups.items():
            k = np.flatnonzero(np.asarray(mask, bool))
            picked = np.asarray(components, np.int64)
            rows[name] = (start + 3 * k[:, None] + picked[None, :]).ravel().astype(np.int64)
        chosen = np.unique(np.concatenate(list(rows.values()) or [np.zeros(0, np.int64)]))
        out: dict[str, tuple[float, float]] = {}
        if chosen.size == 0:
            return {name: (0.0, 0.0) for name in rows}
        jac = sp.csr_matrix(jac)
        lu = factor_spd(jac.T @ jac)
        rng = np.random.default_rng(20240611)
        sub = jac[chosen]
        leverage = np.zeros(chosen.size)
        for b0 in range(0, probes, 16):
            z = rng.choice((-1.0, 1.0), size=(chosen.size, min(16, probes - b0)))
            hz = sub @ np.asarray(lu.solve(np.asarray(sub.T @ z)))
            leverage += (z * hz).sum(axis=1)
        leverage /= probes
        for name, r in rows.items():
            if not r.size:
                out[name] = (0.0, 0.0)
                continue
            idx = np.searchsorted(chosen, r)
            chi2 = float(residual[r] @ residual[r])
            redundancy = float(r.size - np.clip(leverage[idx], 0.0, 1.0).sum())
            out[name] = (chi2, redundancy)
        return out

    def relative_covariances(
        self,
        pairs: Sequence[tuple[int, int]],
        *,
        max_exact_work: float = EXACT_COVARIANCE_WORK,
        margin_s: float = COVARIANCE_MARGIN_S,
        window_s: float = COVARIANCE_WINDOW_S,
    ) -> Array:
        """Covariance (k, 3, 3) of the relative pose j in i (forward, starboard, yaw) for
        each pair, from the information matrix at the last solution (the linearised
        marginal: J_rel Sigma_{ij} J_rel^T).

        Exact (from the whole problem's factor) while that costs at most
        ``max_exact_work`` (one solve per involved pose coordinate, each as long as the
        factor: a flop count). Beyond it (a survey of hours, frames not rigid) each batch
        of pairs close in time gets the marginal of the sub-problem around it: the frames
        from ``margin_s`` before the earlier frame to ``margin_s`` after the later, with
        every factor among them and the knots and global terms they touch. Factors that
        leave the window are left out, so this covariance is never smaller than the exact
        one: a prediction that errs wide, for a gate. A batch's window is at most twice
        its longest pair's, and at least ``window_s``."""
        x, _, _, jac = self._last
        out = np.zeros((len(pairs), 3, 3))
        if not pairs:
            return out
        frames, to_state = self._frame_state(x)
        n = self._frame_layout.n
        poses = frames[: 3 * n].reshape(n, 3)
        pair_array = np.asarray(pairs, np.int64).reshape(-1, 2)
        lu = factor_spd(jac.T @ jac)
        involved = np.unique(pair_array)
        work = 3.0 * involved.size * 2.0 * float(lu.L.nnz + lu.U.nnz)
        if to_state is not None or work <= max_exact_work:
            t = sp.identity(jac.shape[1], format="csr") if to_state is None else to_state
            blocks = _pose_covariance_blocks(lu, sp.csr_matrix(t), pair_array)
        else:
            del lu  # the windows' factors take its room
            blocks = self._windowed_blocks(jac, pair_array, margin_s, window_s)
        for m, (i, j) in enumerate(pair_array):
            jr = between_jacobian(poses[i], poses[j])
            out[m] = jr @ blocks[m] @ jr.T
        return out

    def _windowed_blocks(
        self, jac: sp.csr_matrix, pairs: IntArray, margin_s: float, window_s: float
    ) -> Array:
        """Per pair, the 6 x 6 covariance of poses i and j from sub-problems in windows of
        time around batches of pairs (``relative_covariances``)."""
        n = self._frame_layout.n
        times = self.times
        # Each row's first and last frame (rows without a frame: none).
        jac = sp.csr_matrix(jac)
        coo = jac.tocoo()
        is_frame = coo.col < 3 * n
        first = np.full(jac.shape[0], n, np.int64)
        last = np.full(jac.shape[0], -1, np.int64)
        np.minimum.at(first, coo.row[is_frame], coo.col[is_frame] // 3)
        np.maximum.at(last, coo.row[is_frame], coo.col[is_frame] // 3)
        frameless = np.flatnonzero(last < 0)
        lo_t = np.minimum(times[pairs[:, 0]], times[pairs[:, 1]]) - margin_s
        hi_t = np.maximum(times[pairs[:, 0]], times[pairs[:, 1]]) + margin_s
        order = np.argsort(lo_t, kind="stable")
        out = np.zeros((len(pairs), 6, 6))
        k = 0
        while k < order.size:
            # A batch: pairs in time order while the window stays within twice the
            # longest pair's own, and at least window_s.
            batch = [order[k]]
            start, end = lo_t[order[k]], hi_t[order[k]]
            k += 1
            while k < order.size:
                p = order[k]
                limit = max(window_s, 2.0 * (hi_t[p] - lo_t[p]))
                if max(end, hi_t[p]) - start > limit:
                    break
                batch.append(p)
                end = max(end, hi_t[p])
                k += 1
            a = int(np.searchsorted(times, start, side="left"))
            b = int(np.searchsorted(times, end, side="right")) - 1
            rows = np.flatnonzero((first >= a) & (last <= b) & (last >= 0))
            cols = np.unique(jac[rows].indices)
            inside = np.zeros(jac.shape[1], bool)
            inside[cols] = True
            free = jac[frameless]
            outside = np.asarray((free[:, ~inside] != 0).sum(axis=1)).ravel()
            rows = np.concatenate([rows, frameless[outside == 0]])
            sub = jac[rows][:, cols]
            # The frames' unknowns as the sub-problem's (those outside: none).
            frame_cols = cols[cols < 3 * n]
            t = sp.csr_matrix(
                (np.ones(frame_cols.size), (frame_cols, np.arange(frame_cols.size))),
                shape=(3 * n, cols.size),
            )
            chosen = np.asarray(batch)
            out[chosen] = _pose_covariance_blocks(factor_spd(sub.T @ sub), t, pairs[chosen])
        return out


def _pose_covariance_blocks(lu: SpdFactor, t: sp.csr_matrix, pairs: IntArray) -> Array:
    """Per pair (i, j), the 6 x 6 covariance of poses i and j (x, y, psi each) from the
    factor ``lu`` of the information matrix, with ``t`` the frames' unknowns (rows: 3k,
    3k + 1, 3k + 2 for frame k) as linear in the factored problem's (columns): over each
    pose's reach in a symmetric factor (``mapping.marginals``), else by whole columns."""
    if lu.symmetric:
        return pose_covariance_blocks(lu, t, pairs)
    return _column_covariance_blocks(lu, t, pairs)


def _column_covariance_blocks(lu: SpdFactor, t: sp.csr_matrix, pairs: IntArray) -> Array:
    """``_pose_covariance_blocks`` by whole columns of the inverse, solved for a bounded
    batch of poses at a time, so memory does not grow with the survey."""
    size = lu.shape[0]
    involved = np.unique(pairs)
    per_batch = max(1, _RHS_BYTES // (8 * 3 * size))
    three = np.arange(3)
    # Rows of t for every pose the pairs name, in one small sparse matrix.
    t_rows = sp.csr_matrix(t[(3 * involved[:, None] + three).ravel()])
    blocks = np.zeros((len(pairs), 6, 6))
    pos_i = np.searchsorted(involved, pairs[:, 0])
    pos_j = np.searchsorted(involved, pairs[:, 1])
    for b0 in range(0, involved.size, per_batch):
        b1 = min(b0 + per_batch, involved.size)
        rhs = np.asarray(t_rows[3 * b0 : 3 * b1].toarray().T)
        # Covariance of every involved pose's unknowns with the batch's (3 per pose).
        cov = np.asarray(t_rows @ np.asarray(lu.solve(rhs)))
        for side, pos in ((0, pos_i), (1, pos_j)):
            m = np.flatnonzero((pos >= b0) & (pos < b1))
            if m.size == 0:
                continue
            col = (3 * (pos[m] - b0))[:, None, None] + three[None, None, :]
            for half, other in ((0, pos_i), (1, pos_j)):
                row = (3 * other[m])[:, None, None] + three[None, :, None]
                blocks[m, 3 * half : 3 * half + 3, 3 * side : 3 * side + 3] = cov[row, col]
    return blocks
