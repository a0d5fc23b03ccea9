"""The live map re-solved: every few seconds of survey the frames already drawn are placed
again by the survey-end pass's fusion (``mapping.fusion``), and those that moved are drawn
again where they now belong.

The live chain (``mapping.live_anchor``) places each frame once, with what is known when
it arrives. The first lane is drawn before any closure or much GNSS has been seen: with
the compass's misalignment (a few degrees, measured 4.8 degrees on one simulated field
day) in its heading, a lane drawn 7-10 degrees off the final map and every later pass
tied to it by the closures. Only a solution over the whole stretch can see that the
compass is biased (its bias and deviation are states of the fusion), where the GNSS
offset went between the lanes, and how the closures hold the lanes together; the
survey-end pass has it, the live chain cannot. So the live map is solved again in the
background, as real-time SLAM systems do after a loop closure (ORB-SLAM's pose-graph
optimisation, Mur-Artal & Tardos 2017, doi:10.1109/TRO.2017.2705103), over a bounded
stretch:

- the frames drawn within ``window_s`` whose images are still kept (``memory_mb``,
  uint8: the blending image and score as the tiles store them) are nodes of the fusion
  with their live registrations (their own covariances), odometry bridges where a frame
  was rejected, the GNSS fixes with their Gauss-Markov bias, the compass with its bias
  and deviation, the gyro with its bias, and the live closures that were applied (robust,
  Cauchy);
- the frame before the oldest node (its image gone: it can no longer be drawn again) is
  held where it is drawn, and so are the closures' keyframes outside the stretch: a
  closure to one of them holds its frame where the keyframe's drawn pose and the
  registration put it;
- a frame whose fan moved by more than ``redraw_m`` from its pose takes the new pose
  (published at once) and is taken out of its tiles and drawn again there within the
  redraw budget (``redraws_per_frame``): the drawn map follows the poses, a little later.

The chain then carries on from the re-solved map: its correction is moved so that the
last frame drawn is where the solution puts it (what the GNSS sees of the chain stays),
and the compass heading reaches the chain less the compass error the solution found.

Everything runs at fixed points of survey time, so a replay of the same logs gives the
same live map whatever the machine's speed.
"""

from __future__ import annotations

import math
from array import array
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import numpy.typing as npt

from mapping.closures import world_rotation
from mapping.fusion import (
    Fusion,
    FusionData,
    FusionParams,
    PosePrior,
    RelativeConstraint,
    compass_basis,
    diagonal_sqrt_info,
    sqrt_information,
)
from mapping.grid import SonarGrid
from mapping.mosaic import TileKey
from mapping.posegraph import Edge
from mapping.se2 import RelativePose, compose
from mapping.survey_graph import GraphParams, gyro_at_frames, odometry_constraint

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ResolveParams:
    enabled: bool = True
    every_s: float = 10.0
    """Survey time between two re-solves."""
    window_s: float = 600.0
    """Frames drawn longer ago than this are no longer moved (their images are let go)."""
    memory_mb: float = 256.0
    """Images of drawn frames kept to draw them again (the oldest go first): 0.32 MB a
    frame on a 5 m fan at 2 cm (uint8 image, uint16 score, mask bits), so about 800
    frames: 80 s of survey at 10 Hz, 160 s at 5 Hz."""
    redraw_m: float = 0.03
    """A frame whose fan moved more than this (its far edge, 5 m out, for a turn) is drawn
    again: one and a half mosaic pixels."""
    redraws_per_frame: float = 0.5
    """Frames drawn again per new frame, on average: a re-solve's moved frames wait in a
    queue and are drawn again as the pings come, so the re-solve's cost per frame is
    bounded by construction, whatever a re-solve moves and at any ping rate (a redraw,
    its tiles' render and their spill cost about 12 ms here, a quarter of a frame at
    5 Hz). The re-solves themselves go on every ``every_s``; a frame still waiting takes
    the newer solution. The live poses do not depend on this (a frame's move is taken
    against its pose, not where it is drawn): it sets only how soon the drawn map
    follows them. Measured on 22 surveys at 0.5: the drawn map 43-86 s behind the poses
    on average, at most 153 s; quadrats seed 1 (5 Hz) redrew 1062 frames where twenty a
    second redrew 2433."""
    max_turn_deg: float = 1.0
    """The re-solved stretch is first moved, and turned by up to this, to fit where it is
    drawn (``align``), and the live chain is drawn in that frame (``DrawnFrame``). A
    stretch's orientation from the GNSS over it moves by half a degree to a degree from
    one re-solve to the next (a metre of wander over 50 m). On ten surveys of the matrix,
    live lanes 7.6 cm at the median with 1 degree, 10.5 with 0.25 (2.5 m GNSS: 6.4
    against 14.6 cm; a 0.15 m/s current: 14.5 against 13.5)."""
    hold_sigma_m: float = 0.01
    """How firmly a frame that can no longer move holds the map (and a closure's
    keyframe outside the stretch): where it is drawn is within a pixel of where its
    last solution put it."""
    hold_sigma_deg: float = 0.05
    keyframe_edges: bool = True
    """Each frame tied to the keyframe it was registered against by that registration
    (``GraphParams.keyframe_edges``), which leaves the frames nothing else hangs on out
    of the solve. On the 22 surveys of the matrix: live lanes 5.7 / 14.0 cm (median /
    worst), 15.5 to 12.5 on the worst before (current seed 3 at 2 Hz)."""
    solve_leaves: bool = False
    """Solve the leaves with the rest (``LiveResolver._fuse_without_leaves``), at
    several times the cost at 10 Hz."""
    live_tail: bool = True
    """Solve the frames of the live window too (not drawn yet: only the drawn frames
    move), so that the stretch's end is solved with the fixes and compass readings the
    live chain has had since. Without them a re-solve's last drawn frame takes only what
    came before it, while the live frames after it are where everything up to now puts
    them: after the autopilot link was silent (quadrats seed 5 at 2 Hz, 30 s over a
    U-turn), the stretch's end took the chain's dead reckoning through the silence and
    the live map jumped by 6 degrees or 0.8 m between two frames."""


@dataclass(slots=True)
class Drawn:
    """A final frame that may still be drawn again: its blending image as the tiles store
    it, where it went, and its chain pose (for the keyframes' corrections)."""

    index: int
    time: float
    image: npt.NDArray[np.uint8]
    score: npt.NDArray[np.uint16]
    mask: npt.NDArray[np.uint8]  # packed bits
    grid: SonarGrid
    tiles: list[TileKey]
    blended_sonar: Array
    chain: Array  # chain x, y, heading

    @property
    def nbytes(self) -> int:
        # The arrays, and about 200 bytes of the object, its poses and tile list.
        return int(self.image.nbytes + self.score.nbytes + self.mask.nbytes) + 200

    def layers(self) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
        """The (rows, cols, 3) stack of image, score and mask the tile store warps, and
        the mask."""
        size = self.grid.shape[0] * self.grid.shape[1]
        mask = np.unpackbits(self.mask, count=size).reshape(self.grid.shape).astype(bool)
        layers = np.empty((*self.grid.shape, 3), np.float32)
        np.multiply(self.image, np.float32(1 / 255), out=layers[..., 0])
        np.multiply(self.score, np.float32(1 / 65535), out=layers[..., 1])
        layers[..., 2] = mask
        return layers, mask


def pack(
    index: int,
    time: float,
    image: npt.NDArray[np.float32],
    score: npt.NDArray[np.float32],
    mask: npt.NDArray[np.bool_],
    grid: SonarGrid,
    tiles: list[TileKey],
    blended_sonar: Array,
    chain: Array,
) -> Drawn:
    return Drawn(
        index,
        time,
        np.clip(np.rint(image * np.float32(255.0)), 0, 255).astype(np.uint8),
        np.clip(np.rint(score * np.float32(65535.0)), 0, 65535).astype(np.uint16),
        np.packbits(mask.ravel()),
        grid,
        list(tiles),
        np.asarray(blended_sonar, float).copy(),
        np.asarray(chain, float).copy(),
    )


@dataclass(frozen=True, slots=True)
class Bridge:
    """How the live chain bridged frame j from frame i where no registration joined
    them: vehicle j in vehicle i, and its sigmas (metres per axis, radians)."""

    i: int
    forward_m: float
    starboard_m: float
    yaw_rad: float
    sigma_m: float
    sigma_rad: float


@dataclass(frozen=True, slots=True)
class ResolveClosure:
    """An applied live closure: vehicle j in vehicle i, covariance in i's frame."""

    i: int
    j: int
    forward_m: float
    starboard_m: float
    yaw_rad: float
    covariance: Array


class LiveResolver:
    """Keeps what a re-solve needs: the navigation measurements (small, as they come), the
    accepted frames' priors and registrations, the drawn frames' images (bounded), the
    applied closures. ``solve`` places the kept frames again; the engine redraws."""

    def __init__(self, params: ResolveParams, fusion: FusionParams, graph: GraphParams) -> None:
        self.params = params
        self.fusion = fusion
        self.graph = graph
        # Navigation, compactly.
        self._gnss_t = array("d")
        self._gnss_x = array("d")
        self._gnss_y = array("d")
        self._gnss_vx = array("d")  # Doppler velocity, NaN where none
        self._gnss_vy = array("d")
        self._head_t = array("d")
        self._head = array("d")
        self._imu_t = array("d")
        self._imu_yaw = array("d")  # integrated levelled yaw rate
        self._last_rate = 0.0
        # Frames.
        self.accepted: list[int] = []
        self.times: dict[int, float] = {}
        self.priors: dict[int, Array] = {}
        self.registrations: dict[int, tuple[int, Edge, Array]] = {}  # j -> (i, edge, W)
        self.measured: dict[int, tuple[Edge, Array]] = {}  # j -> (keyframe edge, W)
        self.bridges: dict[int, Bridge] = {}
        self.drawn: OrderedDict[int, Drawn] = OrderedDict()
        self.bytes = 0
        self.closures: list[ResolveClosure] = []
        self.compass: Array | None = None
        """The compass error coefficients of the last solve (1, sin, cos, sin 2, cos 2)."""
        self.next_solve_time = -math.inf
        """Survey time from which the next re-solve may run."""

    # -- what comes in -----------------------------------------------------------------
    def add_gnss(
        self, time: float, x: float, y: float, vx: float = math.nan, vy: float = math.nan
    ) -> None:
        """A fix (local metres) and its Doppler velocity (m/s east, north; NaN: none)."""
        self._gnss_t.append(time)
        self._gnss_x.append(x)
        self._gnss_y.append(y)
        self._gnss_vx.append(vx)
        self._gnss_vy.append(vy)

    def add_heading(self, time: float, grid_heading: float) -> None:
        self._head_t.append(time)
        self._head.append(grid_heading)

    def add_yaw_rate(self, time: float, rate: float) -> None:
        if self._imu_t and time <= self._imu_t[-1]:
            return
        if self._imu_t:
            dt = time - self._imu_t[-1]
            self._imu_yaw.append(self._imu_yaw[-1] + 0.5 * (rate + self._last_rate) * dt)
        else:
            self._imu_yaw.append(0.0)
        self._imu_t.append(time)
        self._last_rate = rate

    def add_frame(
        self,
        index: int,
        time: float,
        prior: Array,
        edge: Edge | None,
        sqrt_info: Array | None,
        bridge: Bridge | None = None,
        measured: Edge | None = None,
        measured_info: Array | None = None,
    ) -> None:
        """An accepted frame: its navigation prior, its registration to the previous
        accepted frame (with its square-root information) when it has one, and how the
        chain bridged it when it has not. ``measured``: the registration itself, from the
        keyframe it was registered against (``FrameOutcome.measured``), which ties the
        frame when the keyframe is in the solved stretch (``ResolveParams.keyframe_edges``)."""
        self.accepted.append(index)
        self.times[index] = time
        self.priors[index] = np.asarray(prior, float).copy()
        if edge is not None and sqrt_info is not None:
            self.registrations[index] = (edge.i, edge, sqrt_info)
        if measured is not None and measured_info is not None:
            self.measured[index] = (measured, measured_info)
        if bridge is not None:
            self.bridges[index] = bridge

    def add_closure(self, closure: ResolveClosure) -> None:
        self.closures.append(closure)

    def keep(self, drawn: Drawn) -> list[Drawn]:
        """Keep a final frame's image; returns the frames let go to make room (oldest
        first, their tiles to be settled)."""
        self.drawn[drawn.index] = drawn
        self.bytes += drawn.nbytes
        out = []
        limit = self.params.memory_mb * 2**20
        while self.drawn and (
            self.bytes > limit
            or drawn.time - next(iter(self.drawn.values())).time > self.params.window_s
            # Tile tags are frame indices modulo 65535: unique among movable frames.
            or drawn.index - next(iter(self.drawn)) >= 60000
        ):
            _, old = self.drawn.popitem(last=False)
            self.bytes -= old.nbytes
            out.append(old)
        return out

    # -- the solve -----------------------------------------------------------------------
    def due(self, now: float) -> bool:
        return self.params.enabled and len(self.drawn) >= 2 and now >= self.next_solve_time

    def gnss_silent(self, now: float) -> bool:
        """No fix for ``every_s`` before ``now`` (the autopilot link cut, the receiver
        lost): a re-solve could only re-fit the stretch to the fixes behind it and move
        the chain's present, which nothing absolute has measured since, by what the
        GNSS bias model then guesses; the chain carries on as it is until fixes return."""
        return not self._gnss_t or now - self._gnss_t[-1] > self.params.every_s

    def solved(self, now: float) -> None:
        """A re-solve ran (or had nothing to solve) at ``now``: the next comes ``every_s``
        later."""
        self.next_solve_time = now + self.params.every_s

    def solve(self, drawn_poses: PoseLookup) -> tuple[list[int], Array] | None:
        """Place the kept frames again. ``drawn_poses[k]``: where frame k is drawn now
        (vehicle pose). Returns the nodes (frame indices) and their solved poses, or
        None when there is nothing to solve."""
        p = self.params
        if not self.drawn:
            return None
        first = next(iter(self.drawn))
        last = next(reversed(self.drawn))
        start = self.accepted.index(first) if first in self.times else 0
        nodes = [k for k in self.accepted[start:] if p.live_tail or k <= last]
        hold_info = diagonal_sqrt_info(
            (p.hold_sigma_m, p.hold_sigma_m, math.radians(p.hold_sigma_deg))
        )
        priors: list[PosePrior] = []
        if start > 0:
            boundary = self.accepted[start - 1]
            nodes.insert(0, boundary)
            priors.append(PosePrior(0, np.asarray(drawn_poses[boundary], float), hold_info))
        self._forget_before(nodes[0])
        if len(nodes) < 2:
            return None
        position = {k: i for i, k in enumerate(nodes)}
        times = np.array([self.times[k] for k in nodes])
        constraints: list[RelativeConstraint] = []
        for a in range(1, len(nodes)):
            k_prev, k = nodes[a - 1], nodes[a]
            reg = self.registrations.get(k)
            measured = self.measured.get(k)
            if reg is not None and reg[0] == k_prev and measured and measured[0].i in position:
                edge, w = measured
                constraints.append(
                    RelativeConstraint(
                        position[edge.i], a, edge.forward_m, edge.starboard_m, edge.yaw_rad, w
                    )
                )
            elif reg is not None and reg[0] == k_prev:
                _, edge, w = reg
                constraints.append(
                    RelativeConstraint(a - 1, a, edge.forward_m, edge.starboard_m, edge.yaw_rad, w)
                )
            elif (bridge := self.bridges.get(k)) is not None and bridge.i == k_prev:
                constraints.append(
                    RelativeConstraint(
                        a - 1, a, bridge.forward_m, bridge.starboard_m, bridge.yaw_rad,
                        diagonal_sqrt_info((bridge.sigma_m, bridge.sigma_m, bridge.sigma_rad)),
                        kind="odometry",
                    )
                )  # fmt: skip
            else:
                constraints.append(
                    odometry_constraint(
                        a - 1, a, self.priors[k_prev], self.priors[k],
                        float(times[a] - times[a - 1]), self.graph,
                    )
                )  # fmt: skip
        hold_cov = np.diag([p.hold_sigma_m**2] * 2 + [math.radians(p.hold_sigma_deg) ** 2])
        for c in self.closures:
            if c.j not in position:
                continue
            if c.i in position:
                constraints.append(
                    RelativeConstraint(
                        position[c.i], position[c.j], c.forward_m, c.starboard_m, c.yaw_rad,
                        sqrt_information(c.covariance), robust=True, kind="closure",
                    )
                )  # fmt: skip
            elif c.i < nodes[0]:
                anchor = np.asarray(drawn_poses[c.i], float)
                if not np.all(np.isfinite(anchor)):
                    continue
                implied = compose(anchor, RelativePose(c.forward_m, c.starboard_m, c.yaw_rad))
                rot = world_rotation(float(anchor[2]))
                cov = rot @ c.covariance @ rot.T + hold_cov
                priors.append(
                    PosePrior(position[c.j], implied, sqrt_information(cov), True, "closure")
                )
        initial = np.array([drawn_poses[k] for k in nodes], float)
        if p.solve_leaves:
            poses = self._fuse(times, initial, constraints, priors)
        else:
            poses = self._fuse_without_leaves(times, initial, constraints, priors)
        return nodes, poses

    def _fuse(
        self,
        times: Array,
        initial: Array,
        constraints: list[RelativeConstraint],
        priors: list[PosePrior],
    ) -> Array:
        fusion = Fusion(times, self._data(times), self.fusion, priors=priors)
        solution, _ = fusion.solve(initial, constraints)
        self.compass = solution.compass_coefficients.copy()
        return solution.poses

    def _fuse_without_leaves(
        self,
        times: Array,
        initial: Array,
        constraints: list[RelativeConstraint],
        priors: list[PosePrior],
    ) -> Array:
        """The solve over the frames something else hangs on; each leaf (a frame tied
        only by its own registration from its keyframe: no frame registered against it,
        no closure, nothing held) placed after it by that registration. A leaf adds one
        pose and its one registration, which only it uses: solved with it, it sits where
        the registration puts it, bar what its own fixes and compass readings would
        add, and those are taken between the frames kept either side of it (at most a
        keyframe, a second, apart). At 0.4 m/s with keyframes 0.3 m apart, about six
        frames in seven at 10 Hz."""
        n = times.size
        into: dict[int, RelativeConstraint] = {}
        used = {0, n - 1, *(q.k for q in priors)}
        for c in constraints:
            used.add(c.i)
            if c.kind == "closure":
                used.add(c.j)
            else:
                into[c.j] = c
        kept = np.array([a for a in range(n) if a in used or a not in into], np.int64)
        if kept.size == n:
            return self._fuse(times, initial, constraints, priors)
        where = np.full(n, -1, np.int64)
        where[kept] = np.arange(kept.size)
        reduced = [
            replace(c, i=int(where[c.i]), j=int(where[c.j])) for c in constraints if where[c.j] >= 0
        ]
        held = [replace(q, k=int(where[q.k])) for q in priors]
        poses = np.full((n, 3), np.nan)
        poses[kept] = self._fuse(times[kept], initial[kept], reduced, held)
        for a in range(n):  # a leaf's keyframe comes before it
            if where[a] < 0:
                c = into[a]
                poses[a] = compose(poses[c.i], RelativePose(c.forward_m, c.starboard_m, c.yaw_rad))
        return poses

    def compass_error(self, heading: float) -> float:
        """What the compass adds to a true grid heading, by the last solve (radians)."""
        if self.compass is None:
            return 0.0
        f, _ = compass_basis(np.array([heading]))
        return float(f[0] @ self.compass)

    def _data(self, times: Array) -> FusionData:
        t0, t1 = float(times[0]) - 5.0, float(times[-1]) + 5.0
        gt = np.frombuffer(self._gnss_t, float)
        g_in = (gt >= t0) & (gt <= t1)
        gnss_xy = np.column_stack(
            [np.frombuffer(self._gnss_x, float)[g_in], np.frombuffer(self._gnss_y, float)[g_in]]
        )
        velocity = np.column_stack(
            [np.frombuffer(self._gnss_vx, float)[g_in], np.frombuffer(self._gnss_vy, float)[g_in]]
        )
        ht = np.frombuffer(self._head_t, float)
        h_in = (ht >= t0) & (ht <= t1)
        yaw, gap = gyro_at_frames(
            np.frombuffer(self._imu_t, float),
            np.frombuffer(self._imu_yaw, float),
            times,
            self.graph.sonar_latency_s,
        )
        return FusionData(
            gt[g_in].copy(),
            gnss_xy,
            ht[h_in].copy(),
            np.frombuffer(self._head, float)[h_in].copy(),
            yaw,
            gap,
            gnss_velocity=velocity if np.isfinite(velocity).any() else None,
        )

    def _forget_before(self, first: int) -> None:
        """Frames before the oldest node will not be solved again: their priors and
        registrations go (their drawn poses stay with the engine), and so do the
        measurements older than they need."""
        if not self.accepted or self.accepted[0] >= first:
            return
        cut = self.accepted.index(first) if first in self.times else 0
        for k in self.accepted[:cut]:
            self.times.pop(k, None)
            self.priors.pop(k, None)
            self.registrations.pop(k, None)
            self.measured.pop(k, None)
            self.bridges.pop(k, None)
        del self.accepted[:cut]
        self.closures = [c for c in self.closures if c.j >= first]
        t0 = self.times[first] - 10.0
        for ts, others in (
            (self._gnss_t, (self._gnss_x, self._gnss_y, self._gnss_vx, self._gnss_vy)),
            (self._head_t, (self._head,)),
            (self._imu_t, (self._imu_yaw,)),
        ):
            drop = int(np.searchsorted(np.frombuffer(ts, float), t0)) if ts else 0
            if drop > 1000:
                del ts[:drop]
                for other in others:
                    del other[:drop]


class PoseLookup(Protocol):
    def __getitem__(self, k: int, /) -> Array: ...


@dataclass(frozen=True, slots=True)
class DrawnFrame:
    """Where the live map is drawn against the GNSS's frame: ``x_drawn = to + R(turn) (x
    - origin)``, R the clockwise turn (headings gain ``turn``). The identity until a
    re-solve holds the drawn map's place and orientation against a solution that moved."""

    turn: float = 0.0
    origin: tuple[float, float] = (0.0, 0.0)
    to: tuple[float, float] = (0.0, 0.0)

    def point(self, x: float, y: float) -> tuple[float, float]:
        s, c = math.sin(self.turn), math.cos(self.turn)
        dx, dy = x - self.origin[0], y - self.origin[1]
        return self.to[0] + dx * c + dy * s, self.to[1] - dx * s + dy * c

    def poses(self, poses: Array) -> Array:
        """(n, 3) poses of the GNSS's frame in the drawn one."""
        a = np.asarray(poses, float)
        out = a.copy()
        s, c = math.sin(self.turn), math.cos(self.turn)
        dx, dy = a[:, 0] - self.origin[0], a[:, 1] - self.origin[1]
        out[:, 0] = self.to[0] + dx * c + dy * s
        out[:, 1] = self.to[1] - dx * s + dy * c
        out[:, 2] = (a[:, 2] + self.turn) % (2 * math.pi)
        return out

    def inverse(self) -> DrawnFrame:
        # x = origin + R(-turn) (x_drawn - to)
        return DrawnFrame(-self.turn, self.to, self.origin)


def align(solved: Array, drawn: Array, max_turn_rad: float) -> DrawnFrame:
    """The move of ``solved`` (n, 3), and its turn up to ``max_turn_rad``, that bring its
    positions nearest (least squares, 2-D Procrustes) to ``drawn``.

    A new fix moves a whole stretch by a centimetre or two and turns it by a tenth of a
    degree or more (a stretch's orientation is the GNSS's over it: a metre of wander over
    50 m is a degree): the drawn map should change where its shape does, not chase that
    (each chase is a redraw of every frame). The live chain is then drawn in the same
    frame (``DrawnFrame``: the fixes and the compass it is tied to are taken into it),
    so that new lanes meet the drawn ones. The turn is bounded: the map's orientation is
    the GNSS's over the whole survey."""
    a = np.asarray(solved, float)
    b = np.asarray(drawn, float)
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    if not ok.any():
        return DrawnFrame()
    ca, cb = a[ok, :2].mean(axis=0), b[ok, :2].mean(axis=0)
    da, db = a[ok, :2] - ca, b[ok, :2] - cb
    # The clockwise turn taking da to db: x' = x cos + y sin, y' = -x sin + y cos.
    theta = math.atan2(
        float(np.sum(da[:, 1] * db[:, 0] - da[:, 0] * db[:, 1])),
        float(np.sum(da[:, 0] * db[:, 0] + da[:, 1] * db[:, 1])),
    )
    theta = min(max(theta, -max_turn_rad), max_turn_rad)
    return DrawnFrame(theta, (float(ca[0]), float(ca[1])), (float(cb[0]), float(cb[1])))
