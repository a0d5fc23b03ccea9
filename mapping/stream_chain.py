"""The streaming engine's live chain: each sonar frame preprocessed, registered, and laid
onto its predecessor, the chain tied to the GNSS, the compass and the loop closures.

A frame comes in with the filter's pose at its stamp (``mapping.stream_navigation``). It is
preprocessed and registered against the keyframe and validated against the filter's
motion (``mapping.frames.LocalRegistration``); an accepted frame is then chained onto the
last accepted one: by its registration, else bridged (a rejection, or a restart, never
jumps to the filter's prior). How a step was measured is its ``Motion``: registered, at the
velocity the registrations last measured, or by the filter's dead reckoning. The chain
drifts; its anchor (``mapping.live_anchor``) carries the correction the fixes, the compass
heading and the live loop closures (``mapping.live_closures``, against keyframes of the
final map) say it needs, and a frame's live pose is its chained pose so corrected.

Each frame comes preprocessed and registered from the front stage
(``mapping.stream_front``), with the chain's rate and the fan's shape. What the chain
needs of the later stages comes to it as inputs: the frames that became
final (they offer keyframes, and are forgotten unless the chain goes on from them), and
each live re-solve's outcome (``mapping.stream_window.Resolution``: keyframes moved, the
drawn map's frame, the compass error, where the chain carries on from).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from mapping.fmt import Registration
from mapping.frames import SonarMount
from mapping.fusion import compass_basis
from mapping.grid import SonarGrid
from mapping.live_anchor import LiveAnchor
from mapping.live_closures import Closure, ClosureJob, LiveClosures
from mapping.live_resolve import Bridge, DrawnFrame
from mapping.posegraph import Edge
from mapping.se2 import to_body, to_world, turn
from mapping.stream_front import ChainRate, FanShape, FrontResult, rate_at
from mapping.stream_navigation import PingNavigation
from mapping.stream_window import Resolution

if TYPE_CHECKING:
    from mapping.stream_params import StreamingParams

Array = npt.NDArray[np.float64]


class Motion(enum.Enum):
    """How a frame's step from the last chained frame was measured."""

    REGISTERED = "registered"
    """Its registration joins it to the last chained frame."""
    HELD_VELOCITY = "held velocity"
    """Bridged at the speed the registrations last measured (or, with the gyro silent,
    the chain's own velocity), turned by half the step's turn."""
    DEAD_RECKONED = "dead reckoned"
    """Bridged by the filter's dead-reckoned motion (no motion when it has none)."""


@dataclass(frozen=True, slots=True)
class Step:
    """A frame's step from the last chained frame, in that frame's vehicle axes (forward,
    starboard metres, yaw radians), before the anchor's scale."""

    forward_m: float
    starboard_m: float
    yaw_rad: float
    motion: Motion
    gyro: bool
    """The filter's gyro carried the heading since the last frame (the same gyro epoch):
    the turn is the gyro's; else the chain's own (the registration's, or its held rate)."""
    sigma_m: float
    """Error of a bridge per axis (0 for a registered step)."""

    @property
    def bridged(self) -> bool:
        """No registration joins the two frames."""
        return self.motion is not Motion.REGISTERED

    @property
    def scaled(self) -> bool:
        """Measured by the registrations, whose length the anchor's scale corrects."""
        return self.motion is not Motion.DEAD_RECKONED


def measure_step(
    edge: Edge | None,
    reckoned: tuple[float, float, float] | None,
    rate: tuple[float, float, float] | None,
    velocity: tuple[float, float, float] | None,
    gyro: bool,
    span: float,
    time: float,
    params: StreamingParams,
) -> Step:
    """The step to a frame at ``time``, ``span`` seconds after the last chained one.

    edge: the registration from the last chained frame (None: bridged). reckoned: the
    filter's motion since it (``LiveChain.dead_reckoned``; None without odometry). rate:
    the chain's velocity and turn rate (``LocalRegistration.chain_rate``; asked for a
    bridge only). velocity: the registrations' last measured velocity (forward, starboard
    m/s, and when). gyro: the filter's gyro carried the heading between the frames."""
    if edge is not None:
        forward, starboard, dyaw = edge.forward_m, edge.starboard_m, edge.yaw_rad
    else:
        forward, starboard, dyaw = reckoned or (0.0, 0.0, 0.0)
    if reckoned is not None and gyro:
        # The heading follows the gyro (through the filter): over a ping it is good to a
        # hundredth of a degree, where a registration's yaw is good to a few hundredths
        # and its errors add up along the chain.
        dyaw = reckoned[2]
    elif edge is None:
        # No gyro and no registration: the chain's turn rate, held.
        dyaw = rate[2] * span if rate is not None else 0.0
    if edge is not None:
        return Step(forward, starboard, dyaw, Motion.REGISTERED, gyro, 0.0)
    recent = velocity is not None and time - velocity[2] <= params.bridge_velocity_age_s
    if not gyro and rate is not None:
        # The filter held its heading and velocity (no IMU): the chain's own, held.
        velocity, recent = (rate[0], rate[1], time), True
    if velocity is not None and recent:
        # Bridge at the speed the registrations last measured, turned by half the gyro's
        # turn (the chord of the arc): the boat's speed through a rejection changes by
        # centimetres a second, the filter's velocity (a GNSS outage: the accelerometers
        # alone) by decimetres.
        turn_s, turn_c = math.sin(0.5 * dyaw), math.cos(0.5 * dyaw)
        forward_v, starboard_v = velocity[0] * span, velocity[1] * span
        return Step(
            forward_v * turn_c - starboard_v * turn_s,
            forward_v * turn_s + starboard_v * turn_c,
            dyaw,
            Motion.HELD_VELOCITY,
            gyro,
            params.bridge_velocity_sigma_mps * span,
        )
    return Step(
        forward,
        starboard,
        dyaw,
        Motion.DEAD_RECKONED,
        gyro,
        params.bridge_filter_sigma_mps * span,
    )


def compass_error(coefficients: Array | None, heading: float) -> float:
    """What the compass adds to a true grid heading by a re-solve's compass error
    ``coefficients`` (``LiveResolver.compass``; None: none yet), radians."""
    if coefficients is None:
        return 0.0
    f, _ = compass_basis(np.array([heading]))
    return float(f[0] @ coefficients)


class LiveChain:
    """See the module docstring."""

    def __init__(self, mount: SonarMount, params: StreamingParams) -> None:
        self.mount = mount
        self.params = params
        self._rate: ChainRate | None = None
        """The chain's rate the front measured, as of the frame last taken."""
        self._shape: FanShape | None = None
        self.anchor = LiveAnchor(params.anchor)
        self.closures: LiveClosures | None = None  # once the sonar's geometry is known
        # Per chained frame (dropped when it becomes final, but the last): its chained
        # position (local east/north), raw chained heading, and the filter's odometry and
        # gyro epoch there (to bridge rejections).
        self._xy: dict[int, Array] = {}
        self._heading: dict[int, float] = {}
        self._bends_at: dict[int, Array] = {}  # the anchor's bends when each was chained
        self._odometry: dict[int, Array] = {}
        self._gyro: dict[int, int | None] = {}
        self._last: int | None = None
        self._last_time = -math.inf
        self._registered_velocity: tuple[float, float, float] | None = None  # fwd, stbd, time
        self._fixes: deque[tuple[float, float, float]] = deque(maxlen=256)
        """Fixes (lagged time, x, y) not yet reached by the chain."""
        self._drawn = DrawnFrame()
        """The drawn map's frame against the GNSS's, from the last re-solve."""
        self._compass: Array | None = None
        """The compass error the last re-solve found (``compass_error``)."""

    # -- frames in -------------------------------------------------------------------------
    def take_fix(self, fix: tuple[float, float, float]) -> None:
        """A fix (time less its lag, local x, y) to tie the chain to once it reaches it."""
        self._fixes.append(fix)

    def take_front(self, result: FrontResult) -> None:
        """A frame from the front stage: the chain's rate as it measured it there, and
        the fan's shape when it changed."""
        self._rate = result.rate
        if result.shape is not None:
            self._shape = result.shape

    @property
    def shape(self) -> FanShape:
        """The fan of the frames taken last."""
        assert self._shape is not None
        return self._shape

    @property
    def grid(self) -> SonarGrid:
        """The blending grid of the frames taken last."""
        return self.shape.grid

    def link(self, index: int, time: float, at: PingNavigation, edge: Edge | None) -> Bridge | None:
        """Chain an accepted frame onto the previous one: by its registration, else by the
        speed the registrations measured or the filter's dead-reckoned motion (a rejection
        or a restart never jumps to the prior); then give the anchor the fixes and the
        heading residual up to here. Returns how it was bridged (None: registered, or the
        first frame), for the live re-solve.

        ``at.gyro``: the filter's gyro epoch here. Where it is not the previous frame's,
        the filter held its heading (the autopilot link silent): the turn is the chain's,
        and the filter's heading is no measurement for the anchor until the compass
        speaks."""
        assert at.prior is not None
        prior = at.prior
        last = self._last
        bridge: Bridge | None = None
        if last is None:
            self._xy[index] = prior[:2].copy()
            self._heading[index] = float(prior[2])
            self.anchor.update_heading(time, 0.0)
        else:
            heading = self._heading[last] + self.anchor.heading
            reckoned = self.dead_reckoned(last, at.odometry)
            span = time - self._last_time
            gyro = at.gyro is not None and self._gyro.get(last) == at.gyro
            if not gyro:
                # The chain's turn since the last frame is the registrations', not the
                # gyro's: the anchor's heading rate error does not act over it.
                self.anchor.predict(time, gyro=False)
            registered = edge if edge is not None and edge.i == last else None
            rate = None
            if registered is None:
                rate = rate_at(self._rate, time, self.params.bridge_velocity_age_s)
            elif span > 0:
                self._registered_velocity = (
                    registered.forward_m / span,
                    registered.starboard_m / span,
                    time,
                )
            step = measure_step(
                registered, reckoned, rate, self._registered_velocity, gyro, span, time,
                self.params,
            )  # fmt: skip
            forward, starboard = step.forward_m, step.starboard_m
            if step.scaled:
                forward *= 1.0 + self.anchor.scale
                starboard *= 1.0 + self.anchor.scale
            moved = np.array(to_world(forward, starboard, heading))
            self._xy[index] = self._xy[last] + moved
            self._heading[index] = self._heading[last] + step.yaw_rad
            if step.bridged:
                # The re-solve bridges it as the chain did, as uncertain as the chain
                # takes it (a live filter in a GNSS outage drifts by decimetres a
                # second: its poses are no odometry to bridge with).
                graph = self.params.pipeline.single_stage.graph
                rate_sigma = (
                    graph.odometry_rate_sigma_rps if step.gyro else graph.coast_rate_sigma_rps
                )
                bridge = Bridge(
                    last, forward, starboard, step.yaw_rad,
                    graph.odometry_sigma_m + step.sigma_m,
                    graph.odometry_sigma_rad + rate_sigma * span,
                )  # fmt: skip
            self.anchor.chain_step((float(moved[0]), float(moved[1])), step.sigma_m, step.scaled)
            self._tie_to_fixes(last, index, time)
            self._tie_to_compass(index, time, at)
        if at.odometry is not None:
            self._odometry[index] = at.odometry
        self._gyro[index] = at.gyro
        self._last = index
        self._last_time = time
        return bridge

    def _tie_to_fixes(self, last: int, index: int, time: float) -> None:
        """Fixes whose (lagged) time lies up to this frame: residual against the chain,
        interpolated between the last frame and this one."""
        t0 = self._last_time
        while self._fixes and self._fixes[0][0] <= time:
            t_fix, x, y = self._fixes.popleft()
            if t_fix < t0 - 1.0:
                continue
            x, y = self._drawn.point(x, y)
            w = min(max((t_fix - t0) / max(time - t0, 1e-6), 0.0), 1.0)
            at = (1 - w) * self._xy[last] + w * self._xy[index]
            self.anchor.update_position(t_fix, (x - float(at[0]), y - float(at[1])))

    def _tie_to_compass(self, index: int, time: float, at: PingNavigation) -> None:
        """The filter's heading as a measurement of the chain's, while the compass is
        fresh or the gyro has carried the heading since it spoke. The filter's heading
        carries the compass's error; the last re-solve estimated it (misalignment and
        deviation)."""
        if time - at.compass_time <= self.params.heading_fresh_s or (
            at.gyro is not None and at.gyro == at.compass_epoch
        ):
            assert at.prior is not None
            prior = float(at.prior[2])
            heading = prior - compass_error(self._compass, prior)
            heading += self._drawn.turn
            self.anchor.update_heading(time, turn(heading - self._heading[index]))

    def dead_reckoned(self, last: int, odometry: Array | None) -> tuple[float, float, float] | None:
        """The filter's motion since frame ``last`` in that frame (forward, starboard, yaw),
        None when the filter has no odometry there."""
        before = self._odometry.get(last)
        if odometry is None or before is None:
            return None
        dx, dy, dyaw = odometry - before
        forward, starboard = to_body(dx, dy, self._heading[last] + self.anchor.heading)
        return float(forward), float(starboard), float(dyaw)

    def close_loop(
        self,
        index: int,
        time: float,
        image: npt.NDArray[np.float32],
        registered: Sequence[tuple[int, Registration]] = (),
    ) -> tuple[list[Closure], ClosureJob | None]:
        """The closures' registrations ``registered`` since the last accepted frame (frame,
        registration) are gated and applied (``mapping.live_closures``: a confirmed
        closure updates the anchor); then this frame may be registered against a
        keyframe of an earlier pass that overlaps: the job for that, to run wherever the
        engine puts it and come back here. Returns the closures the anchor took (for the
        live re-solve) and the job (or None)."""
        job = None
        if self.params.closures.enabled:
            if self.closures is None:
                shape = self.shape
                self.closures = LiveClosures(
                    self.params.closures,
                    self.mount,
                    (shape.min_range_m, shape.max_range_m),
                    shape.half_width_rad,
                )
            xy = self._xy[index]
            for frame, registration in registered:
                self.closures.conclude(frame, registration, xy, time, self.anchor)
            shape = self.shape
            job = self.closures.propose(
                index, time, self.live_pose(index), xy, self._heading[index], image,
                shape.grid, shape.mask, self.params.pipeline.fmt, self.anchor,
            )  # fmt: skip
        taken: list[Closure] = []
        if self.closures is not None and self.closures.taken:
            taken = list(self.closures.taken)
            self.closures.taken.clear()
        self._bends_at[index] = self.anchor.bends.copy()
        return taken, job

    # -- what the chain says ---------------------------------------------------------------
    def live_pose(self, k: int) -> Array:
        """The chained frame where the anchor puts it now (local metres, grid heading):
        the anchor's correction, less the map's bends it followed since the frame was
        chained (those belong to other places of the map)."""
        ce, cn = self.anchor.correction
        bends = self.anchor.bends - self._bends_at.get(k, self.anchor.bends)
        xy = self._xy[k]
        heading = (self._heading[k] + self.anchor.heading - bends[2]) % (2 * math.pi)
        return np.array([xy[0] + ce - bends[0], xy[1] + cn - bends[1], heading])

    def holds(self, k: int) -> bool:
        """Frame ``k`` is still chained (not final, or the last chained)."""
        return k in self._xy

    def chained(self, k: int) -> Array:
        """Frame ``k``'s raw chained pose (x, y, heading: without the anchor)."""
        return np.array([*self._xy[k], self._heading[k]])

    def holding(self, now: float) -> float | None:
        """While closures of a new pair of passes wait for agreement: the time from which
        the live frames should stay movable (``LiveClosures.holding``), else None."""
        return self.closures.holding(now) if self.closures is not None else None

    # -- frames out ------------------------------------------------------------------------
    def offer_keyframe(
        self,
        k: int,
        time: float,
        pose: Array,
        image: npt.NDArray[np.float32],
        grid: SonarGrid,
    ) -> None:
        """Frame ``k`` became final at ``pose`` with its blending ``image``: a keyframe
        for later closures, with the correction it is drawn with (its pose less its
        chained one)."""
        if self.closures is None:
            return
        drawn_with = np.array(
            [
                pose[0] - self._xy[k][0],
                pose[1] - self._xy[k][1],
                turn(float(pose[2]) - self._heading[k]),
            ]
        )
        self.closures.offer_keyframe(
            k,
            time,
            pose,
            drawn_with,
            float(self.anchor.correction_covariance()[2, 2]),
            np.ascontiguousarray(image),
            grid,
        )

    def finalise(self, k: int) -> None:
        """Frame ``k`` is final: it is never chained onto again, unless it is the last."""
        if k != self._last:
            self._xy.pop(k, None)
            self._heading.pop(k, None)
            self._odometry.pop(k, None)
            self._gyro.pop(k, None)
            self._bends_at.pop(k, None)

    # -- re-solves -------------------------------------------------------------------------
    def move_keyframe(self, k: int, pose: Array, chain: Array) -> None:
        """A re-solve moved final frame ``k`` to ``pose``; ``chain``: its chained pose
        when it was kept. Its keyframe (if it is one) moves, with its correction."""
        if self.closures is None:
            return
        correction = np.array(
            [
                pose[0] - chain[0],
                pose[1] - chain[1],
                turn(float(pose[2]) - chain[2]),
            ]
        )
        self.closures.store.move(k, pose, self.mount.sonar_pose(pose), correction)

    def follow(self, resolution: Resolution) -> None:
        """A re-solve's outcome (its keyframes already moved, ``move_keyframe``): the
        closures take the moved keyframes, and the chain carries on from the re-solved
        map in its frame, with the compass error it found.

        The live window moves so that its first frame is where the solution puts it,
        next to the last drawn frame (moved with the last drawn frame instead, the live
        window kept what the anchor's corrections between two finalised blocks had put
        between them: 0.2-0.7 m steps in the live map after the autopilot link came
        back). They keep their own heading: the solution's end is its least certain part,
        and turned with it the chain on quadrats seed 6 at 2 Hz took a 2.6 degree turn at
        the last re-solve and drew the last lane 0.5 m off (live lanes 25 cm; 14
        without)."""
        if self.closures is not None:
            self.closures.rebase()
        nodes, solved = resolution.nodes, resolution.solved
        # Where the chain joins the solution: the first frame of the live window (solved
        # with the rest: ``ResolveParams.live_tail``), else the last drawn frame.
        m_join = resolution.last_drawn
        if m_join + 1 < len(nodes) and nodes[m_join + 1] in self._xy:
            m_join += 1
            was_join = self.live_pose(nodes[m_join])
        else:
            was_join = resolution.last_drawn_pose
        n = self._last
        if n is not None and n in self._xy:
            move_e = float(solved[m_join][0] - was_join[0])
            move_n = float(solved[m_join][1] - was_join[1])
            self.anchor.x[0] += move_e
            self.anchor.x[1] += move_n
            # What the GNSS sees of the chain stays: the fixes since the joining frame were
            # taken against it, and the solution's bias is not known beyond that frame
            # (there it decays towards zero). Taking the solution's bias and its
            # covariance instead made quadrats seed 6 at 2 Hz 19 -> 42 cm live. The
            # fixes are taken into the new drawn frame: where the boat is, they move by
            # what the frame moved there.
            q = resolution.in_gnss[m_join]
            e0, n0 = resolution.old.point(float(q[0]), float(q[1]))
            e1, n1 = resolution.new.point(float(q[0]), float(q[1]))
            self.anchor.x[2] += (e1 - e0) - move_e
            self.anchor.x[3] += (n1 - n0) - move_n
        self._drawn = resolution.new
        self._compass = resolution.compass
