"""The single-stage survey graph: the frames of a survey, their registrations and the
navigation measurements handed to ``mapping.fusion``.

Every accepted frame is a node. Consecutive accepted frames are always joined: by their
registration when it was accepted, otherwise (a rejected frame in between, a chain
restart after a gap, a frame that could not be registered) by an odometry edge from the
smoothed EKF, whose covariance grows with the time it spans. The graph therefore never
falls apart into segments that float on the GNSS separately.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mapping.frames import COAST_SPEED_SIGMA_MPS, COAST_YAW_RATE_SIGMA_RPS, FrameOutcome, SonarMount
from mapping.fusion import (
    FusionData,
    RelativeConstraint,
    diagonal_sqrt_info,
    sqrt_information,
)
from mapping.navigation import NavInputs
from mapping.posegraph import Edge
from mapping.se2 import relative_pose

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class GraphParams:
    """Uncertainties of the edges the graph adds itself (metres, radians, seconds)."""

    registration_sigma_m: tuple[float, float] = (0.008, 0.003)
    """Forward and starboard sigma of a consecutive registration when the registrar
    gives no covariance (5 Hz on simulated field days: 7.5 mm along the look direction,
    2.5 mm across)."""
    registration_sigma_rad: float = math.radians(0.12)
    use_registrar_covariance: bool = True
    """Weigh each registration by the registrar's own covariance plus the floor and the
    motion terms below (else the fixed sigmas above)."""
    registration_floor_m: tuple[float, float] = (0.0015, 0.0012)
    """Forward and starboard sigma added to the registrar's own (interpolation, speckle,
    the projection model)."""
    registration_floor_rad: float = math.radians(0.05)
    motion_sigma_mps: tuple[float, float] = (0.025, 0.013)
    """Forward and starboard sigma per second between the two pings: what the chop moves
    that the projection does not know of (heave, and the roll and pitch left after the
    attitude correction). A registration's error grows with the time between its pings:
    measured on simulated field days (light chop: 2-3 degrees of roll and pitch, 4-5 cm
    of heave) at 2, 5 and 10 Hz, 3.0 / 7.3 / 12.4 mm forward, 2.0 / 2.7 / 6.7 mm across,
    0.08 / 0.12 / 0.27 degrees of yaw per pair: floor and motion terms in quadrature fit
    all three rates, so the chain weighs the same survey the same at any ping rate.
    Measured again on 4,420 keyframe registrations of four simulated field days (2, 5,
    10, 10 Hz) against the truth, by span 0.1 / 0.37 / 0.7 / 0.9 s: forward 3.8 / 12.0 /
    17.7 / 20.9 mm (this model 2.9 / 9.4 / 17.6 / 22.5), starboard 2.6 / 7.6 / 10.3 /
    10.1 (1.8 / 4.9 / 9.2 / 11.8), yaw 0.11 / 0.31 / 0.39 / 0.36 degrees (0.07 / 0.20 /
    0.37 / 0.48): the error levels off at half a wave period. A model that levels off
    with it (sigma^2 = cap^2 (1 - exp(-(rate dt / cap)^2))) fitted every span within 10 %
    but made four surveys no better (keyframe edges on: single-stage 3.1-4.5 cm against
    3.1-3.9, the live map on the 2 Hz one 15.4 cm against 13.0): per ping, the chop's
    error is shared by every registration of that ping and cancels along a chain, which
    weights per edge cannot say either way."""
    motion_sigma_rps: float = math.radians(0.53)
    odometry_sigma_m: float = 0.02
    """Odometry bridge: sigma at zero span, growing by ``odometry_velocity_sigma_mps`` a
    second (the smoothed filter's velocity error)."""
    odometry_velocity_sigma_mps: float = 0.05
    odometry_sigma_rad: float = math.radians(0.5)
    odometry_rate_sigma_rps: float = math.radians(0.5)
    coast_velocity_sigma_mps: float = COAST_SPEED_SIGMA_MPS
    """An odometry bridge across frames without the gyro between them (the autopilot link
    silent) grows by this much a second instead (the filter then holds its heading and
    velocity, and the boat need not)..."""
    coast_rate_sigma_rps: float = COAST_YAW_RATE_SIGMA_RPS
    """... and its heading by this much a second."""
    registration_scale: float = 1.0
    """Multiplies the registrations' information (1: as their covariance says). The
    paper's lambda sweep (Table IV) maps onto it as lambda / 1e4."""
    keyframe_edges: bool = False
    """Tie a frame registered against a keyframe to the keyframe by that registration,
    the measurement itself, instead of by the edge from the previous frame composed
    through it (``FrameOutcome.edge``). A composed edge carries two registrations'
    errors, its frame's and the previous frame's, which cancel along the chain: weighed
    as independent measurements, those edges tell the solver the chain across a
    keyframe's frames is several times weaker than it is (about six frames a keyframe at
    10 Hz and 0.4 m/s). Measured on the 22 surveys of the matrix, single-stage: lanes 3.5 cm at the
    median with them, but 10.5 cm against 3.7 on the 0.12 m/s current with PX4, where
    the last lane's tail bent by 1.2 degrees (the gyro bias walked ten times as far) and
    a closure about 22 cm off (a ripple period) was taken there. Why the tail is weaker
    in that graph is not yet known: off until it is. The live re-solve uses them
    (``ResolveParams.keyframe_edges``)."""
    place_rejected: bool = True
    """Every frame with a prior is a node, placed by the odometry bridges where its
    registration was refused (issue 34: a refused frame was left out of the map, a third
    of the seabed seen on a mud bottom); False: only the accepted frames."""
    sonar_latency_s: float = 0.05
    """Prior of the time from a ping's acquisition to its stamp (for the gyro and
    compass factors; the GNSS time offset is estimated)."""


def fusion_data(inputs: NavInputs, frame_times: Array, latency_s: float) -> FusionData:
    """Measurements for ``mapping.fusion`` from the filter inputs: GNSS fixes and grid
    headings as they are (each fix with the accuracy and fix type its receiver reported,
    by which an RTK fix is weighed: ``GnssErrorModel.fix_sigmas``), and the levelled gyro
    yaw rate integrated to each frame's acquisition time (trapezoidal, radians
    clockwise)."""
    gnss_t = np.array([f.time for f in inputs.positions], float)
    gnss_xy = np.array([(f.x, f.y) for f in inputs.positions], float).reshape(-1, 2)
    accuracy = np.array([f.h_acc_m for f in inputs.positions], float)
    fix_type = np.array([int(f.fix_type) for f in inputs.positions], np.int64)
    velocity = np.array([(f.vx, f.vy) for f in inputs.positions], float).reshape(-1, 2)
    head_t = np.array([h.time for h in inputs.headings], float)
    head = np.array([h.heading for h in inputs.headings], float)
    t = np.array([s.time for s in inputs.imu], float)
    rate = np.array([s.yaw_rate_rps for s in inputs.imu], float)
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t))])
    yaw, gap = gyro_at_frames(t, integral, frame_times, latency_s)
    known = np.isfinite(accuracy).any()
    return FusionData(
        gnss_t,
        gnss_xy,
        head_t,
        head,
        yaw,
        gap,
        gnss_accuracy_m=accuracy if known else None,
        gnss_fix_type=fix_type if known else None,
        gnss_velocity=velocity if np.isfinite(velocity).any() else None,
    )


def gyro_at_frames(
    imu_times: Array, yaw_integral: Array, frame_times: Array, latency_s: float
) -> tuple[Array, npt.NDArray[np.bool_]]:
    """The integrated yaw rate at each frame's acquisition time (NaN outside the IMU's
    span), and where an IMU gap lies between a frame and the one before (no gyro factor
    across it)."""
    n = frame_times.size
    yaw = np.full(n, np.nan)
    gap = np.zeros(n, bool)
    if imu_times.size >= 2 and n:
        query = frame_times - latency_s
        inside = (query >= imu_times[0]) & (query <= imu_times[-1])
        yaw[inside] = np.interp(query[inside], imu_times, yaw_integral)
        gaps = np.flatnonzero(np.diff(imu_times) > 0.5)
        if gaps.size:
            gap_start, gap_end = imu_times[gaps], imu_times[gaps + 1]
            prev = np.concatenate([[query[0]], query[:-1]])
            for a, b in zip(gap_start, gap_end, strict=True):
                gap |= (prev < b) & (query > a)
    return yaw, gap


def registration_sqrt_info(
    outcome: FrameOutcome | None, mount: SonarMount, params: GraphParams, dt: float
) -> Array:
    """Square-root information of a consecutive registration (vehicle frame) spanning
    ``dt`` seconds: the registrar's own covariance moved through the mount, plus the floor
    and the motion the chop adds in ``dt``; the fixed sigmas when there is none."""
    reg = outcome.registration if outcome is not None else None
    cov = reg.covariance if reg is not None else None
    scale = math.sqrt(params.registration_scale)
    if cov is None or not params.use_registrar_covariance:
        fwd, stb = params.registration_sigma_m
        return diagonal_sqrt_info((fwd, stb, params.registration_sigma_rad)) * scale
    cov_v = mount.vehicle_covariance(cov)
    floor = np.array([*params.registration_floor_m, params.registration_floor_rad])
    rate = np.array([*params.motion_sigma_mps, params.motion_sigma_rps])
    return sqrt_information(cov_v + np.diag(floor**2 + (rate * abs(dt)) ** 2)) * scale


def odometry_constraint(
    i: int,
    j: int,
    prior_i: Array,
    prior_j: Array,
    dt: float,
    params: GraphParams,
    coasting: bool = False,
) -> RelativeConstraint:
    """The filter's relative motion from ``prior_i`` to ``prior_j``, as uncertain as the
    time it spans makes it; ``coasting``: without the gyro between them (``coast_*``)."""
    rel = relative_pose(prior_i, prior_j)
    velocity = params.coast_velocity_sigma_mps if coasting else params.odometry_velocity_sigma_mps
    rate = params.coast_rate_sigma_rps if coasting else params.odometry_rate_sigma_rps
    sigma_p = params.odometry_sigma_m + velocity * abs(dt)
    sigma_a = params.odometry_sigma_rad + rate * abs(dt)
    return RelativeConstraint(
        i,
        j,
        rel.forward_m,
        rel.starboard_m,
        rel.yaw_rad,
        diagonal_sqrt_info((sigma_p, sigma_p, sigma_a)),
        kind="odometry",
    )


def chain_constraints(
    times: Array,
    accepted: npt.NDArray[np.bool_],
    edges: Sequence[Edge],
    outcomes: Sequence[FrameOutcome],
    priors: Array,
    mount: SonarMount,
    params: GraphParams,
    gyro: npt.NDArray[np.int64] | None = None,
) -> tuple[npt.NDArray[np.int64], list[RelativeConstraint]]:
    """The nodes and the constraints into each node but the first, from earlier nodes, in
    node numbering: the registration itself where one was accepted (from the keyframe it
    was registered against, with ``keyframe_edges``; else the edge from the last accepted
    frame composed through it), an odometry bridge from the previous node otherwise.
    Every node is thus tied to an earlier one: the constraints span the survey, and a
    node's last constraint is its parent in a tree. ``gyro``: the gyro epoch of every
    frame (``navigation.gyro_epochs``), to loosen the bridges the gyro does not span.

    The nodes are every frame with a prior when ``place_rejected`` (a frame whose
    registration was refused is placed by the bridge and the navigation at its time;
    the registered frames after it keep their registrations, from the last accepted
    frame), else the accepted frames only."""
    placeable = np.all(np.isfinite(priors), axis=1)
    if not params.place_rejected:
        placeable &= accepted
    nodes = np.flatnonzero(placeable).astype(np.int64)
    position = {int(k): i for i, k in enumerate(nodes)}
    by_j = {e.j: e for e in edges}
    constraints: list[RelativeConstraint] = []
    for a in range(1, nodes.size):
        k = int(nodes[a])
        edge = by_j.get(k) if accepted[k] else None
        outcome = outcomes[k] if k < len(outcomes) else None
        if edge is not None and edge.i in position and edge.i < k:
            if params.place_rejected and position[edge.i] != a - 1:
                # The refused frames between hang on the bridges from behind; one more
                # from the last of them ties them to this frame too, so they lie between
                # their registered neighbours rather than trail off the first. (Before
                # the registration: a node's last constraint is the one it hangs on.)
                constraints.append(_bridge(a - 1, a, nodes, times, priors, params, gyro))
            measured = outcome.measured if outcome is not None else None
            if params.keyframe_edges and measured is not None and measured.i in position:
                edge = measured
            constraints.append(
                RelativeConstraint(
                    position[edge.i],
                    position[edge.j],
                    edge.forward_m,
                    edge.starboard_m,
                    edge.yaw_rad,
                    registration_sqrt_info(outcome, mount, params, float(times[k] - times[edge.i])),
                    kind="registration",
                )
            )
        else:
            constraints.append(_bridge(a - 1, a, nodes, times, priors, params, gyro))
    return nodes, constraints


def _bridge(
    a: int,
    b: int,
    nodes: npt.NDArray[np.int64],
    times: Array,
    priors: Array,
    params: GraphParams,
    gyro: npt.NDArray[np.int64] | None,
) -> RelativeConstraint:
    """The odometry bridge from node ``a`` to node ``b`` (node numbering)."""
    k_prev, k = int(nodes[a]), int(nodes[b])
    coasting = gyro is not None and (gyro[k] < 0 or gyro[k] != gyro[k_prev])
    return odometry_constraint(
        a, b, priors[k_prev], priors[k], float(times[k] - times[k_prev]), params, coasting
    )
