"""The streaming engine's live window and live re-solve: which accepted frames are still
live and which become final, and the drawn map placed again every few seconds.

Every ``solve_every`` accepted frames the window is solved: its frames take the poses the
chain's anchor gives them now (frames move with its correction, never against each
other), and the frames older than the last ``window_frames`` leave it, their poses final
(``leaving``), unless a pair of passes waits for agreeing closures (then the frames drawn
since just before its first one stay live, up to ``closure_hold_frames``). A final frame's
image is kept (``keep_drawn``, uint8, bounded: ``mapping.live_resolve``) so that the live
re-solve can draw it again where it belongs.

The re-solve (``resolve``: every ``resolve.every_s`` of survey time) takes what
``LiveResolver`` was given, the navigation's measurements, the accepted frames with their
registrations or bridges, the closures the chain's anchor took, and places the drawn
frames again in the GNSS's frame, the drawn map kept in place within a bounded turn
(``mapping.live_resolve.align``). Out comes a ``Resolution``: the frames that moved (to be
drawn again and their poses published), and what the chain needs to carry on from the new
map.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from mapping.closures import world_rotation
from mapping.frames import FrameOutcome, SonarMount
from mapping.live_closures import Closure
from mapping.live_resolve import (
    Bridge,
    Drawn,
    DrawnFrame,
    LiveResolver,
    ResolveClosure,
    align,
    pack,
)
from mapping.stream_drawing import LiveImage, fan_moved
from mapping.stream_navigation import Measured
from mapping.survey_graph import registration_sqrt_info

if TYPE_CHECKING:
    from mapping.stream_params import StreamingParams

Array = npt.NDArray[np.float64]


class _PosesIn:
    """Drawn poses looked up one at a time and taken into another frame."""

    def __init__(self, frame: DrawnFrame, poses: Sequence[Array]) -> None:
        self.frame = frame
        self.drawn = poses

    def __getitem__(self, k: int) -> Array:
        return self.frame.poses(np.asarray(self.drawn[k], float)[None, :])[0]


@dataclass(frozen=True, slots=True)
class Move:
    """A drawn frame the re-solve moved: its new pose (vehicle, in the drawn map's frame)
    and its chained pose when it became final (for its keyframe's correction)."""

    index: int
    pose: Array
    chain: Array


@dataclass(frozen=True, slots=True)
class Resolution:
    """What a re-solve did: the frames it solved (``nodes``) and their poses in the drawn
    map's new frame (``solved``) and in the GNSS's (``in_gnss``), the drawn map's frame
    before and after, the compass error it found, the newest drawn frame (its position
    in ``nodes``, and its pose before anything moved), and the frames that moved."""

    nodes: list[int]
    solved: Array
    in_gnss: Array
    old: DrawnFrame
    new: DrawnFrame
    compass: Array | None
    last_drawn: int
    last_drawn_pose: Array
    moves: list[Move]


class LiveWindow:
    """See the module docstring."""

    def __init__(self, mount: SonarMount, params: StreamingParams) -> None:
        self.mount = mount
        self.params = params
        single = params.pipeline.single_stage
        self.resolver = LiveResolver(params.resolve, single.fusion, single.graph)
        self.drawn_frame = DrawnFrame()
        """The live map's frame against the GNSS's (``mapping.live_resolve.align``)."""
        self.accepted: list[int] = []
        """Indices of the accepted frames, in order."""
        self.final_upto = 0
        """``accepted[: this]`` are final."""
        self._since_solve = 0

    # -- what comes in -----------------------------------------------------------------------
    def take_navigation(self, measured: Measured) -> None:
        """A navigation sample's measurements (``NavigationRecord.take``), for re-solves."""
        if measured.yaw_rate is not None:
            self.resolver.add_yaw_rate(*measured.yaw_rate)
        if measured.heading is not None:
            self.resolver.add_heading(*measured.heading)
        if measured.gnss is not None:
            self.resolver.add_gnss(*measured.gnss)

    def add_frame(
        self,
        index: int,
        time: float,
        prior: Array,
        outcome: FrameOutcome,
        bridge: Bridge | None,
        times: Sequence[float],
    ) -> None:
        """An accepted frame: its filter prior, its registration (``outcome``, with the
        registrar's covariance still in it), and how the chain bridged it where no
        registration joined it to the previous frame. ``times``: every frame's stamp so
        far, for the time a registration spans."""
        graph = self.params.pipeline.single_stage.graph
        sqrt_info = measured_info = None
        if outcome.edge is not None:
            sqrt_info = registration_sqrt_info(
                outcome, self.mount, graph, time - times[outcome.edge.i]
            )
        if outcome.measured is not None and self.params.resolve.keyframe_edges:
            measured_info = registration_sqrt_info(
                outcome, self.mount, graph, time - times[outcome.measured.i]
            )
        self.resolver.add_frame(
            index, time, prior, outcome.edge, sqrt_info, bridge, outcome.measured, measured_info
        )
        self.accepted.append(index)
        self._since_solve += 1

    def take_closures(self, closures: Iterable[Closure]) -> None:
        """Closures the live anchor took are kept for the re-solve (covariance in the
        keyframe's vehicle frame)."""
        for c in closures:
            rot = world_rotation(c.heading_i)
            cov = rot.T @ c.covariance @ rot
            r = c.relative
            self.resolver.add_closure(
                ResolveClosure(c.i, c.j, r.forward_m, r.starboard_m, r.yaw_rad, cov)
            )

    # -- the window --------------------------------------------------------------------------
    @property
    def solve_due(self) -> bool:
        """``solve_every`` frames were accepted since the window was last solved."""
        return self._since_solve >= self.params.solve_every

    @property
    def newest(self) -> int | None:
        """The last accepted frame (None: none yet)."""
        return self.accepted[-1] if self.accepted else None

    def start_solve(self) -> list[int]:
        """The window is solved now (``solve_due`` counts afresh): the frames in it, not
        final yet, in order."""
        self._since_solve = 0
        return self.accepted[self.final_upto :]

    def leaving(self, final: bool, held: float | None, times: Sequence[float]) -> list[int]:
        """The frames that leave the window and become final, in order: all of them
        (``final``: the end of the stream), else those before the last ``window_frames``,
        but not those drawn since ``held`` (``LiveChain.holding``: a pair of passes waits
        for its closures to agree; bounded by ``closure_hold_frames``). ``times``: every
        frame's stamp."""
        accepted = self.accepted
        keep = 0 if final else self.params.window_frames
        upto = max(len(accepted) - keep, self.final_upto)
        if held is not None:
            # A pair of passes waits for its closures to agree: the frames drawn since
            # just before its first one stay live, so that they move with it when it is
            # applied instead of staying where the GNSS put them (bounded).
            oldest = max(len(accepted) - self.params.closure_hold_frames, self.final_upto)
            while upto > oldest and times[accepted[upto - 1]] >= held:
                upto -= 1
        out = accepted[self.final_upto : upto]
        self.final_upto = upto
        return out

    def keep_drawn(self, live: LiveImage, chain: Array) -> list[Drawn]:
        """A frame became final: its image is kept to draw it again after a re-solve, with
        its chained pose ``chain``; returns the frames whose images go to make room (their
        tiles to be settled, ``LiveDrawing.let_go``)."""
        drawn = pack(
            live.index, live.time, live.layers[..., 0], live.layers[..., 1], live.mask,
            live.grid, live.tiles, live.blended_pose, chain,
        )  # fmt: skip
        return self.resolver.keep(drawn)

    @property
    def drawn(self) -> Mapping[int, Drawn]:
        """The final frames whose images are kept to be drawn again."""
        return self.resolver.drawn

    # -- the live re-solve -------------------------------------------------------------------
    def resolve_due(self, now: float) -> bool:
        """A re-solve is due at survey time ``now`` (every ``resolve.every_s``, with at
        least two drawn frames kept)."""
        return self.resolver.due(now)

    def resolve(self, now: float, poses: Sequence[Array]) -> Resolution | None:
        """Re-solve the drawn frames (``mapping.live_resolve``) at survey time ``now``;
        ``poses``: every frame's pose where it is drawn (or is to be drawn once its turn
        in the redraw queue comes). None when there was nothing to solve, or the GNSS is
        silent (``LiveResolver.gnss_silent``)."""
        resolver = self.resolver
        if resolver.gnss_silent(now):
            resolver.solved(now)
            return None
        old = self.drawn_frame
        back = old.inverse()
        # The solution is in the GNSS's frame: what holds it (the frame before the
        # stretch, keyframes outside it) is taken there from where it is drawn.
        out = resolver.solve(_PosesIn(back, poses))
        resolver.solved(now)
        if out is None:
            return None
        nodes, in_gnss = out
        rp = self.params.resolve
        if nodes[0] in resolver.drawn:
            # Nothing holds the stretch (no frame before it is fixed): keep the drawn
            # map's place and (within a bound) its orientation; change its shape.
            drawn_poses = np.array([poses[k] for k in nodes])
            new = align(in_gnss, drawn_poses, math.radians(rp.max_turn_deg))
        else:
            new = old
        solved = new.poses(in_gnss)
        last_drawn = nodes.index(next(reversed(resolver.drawn)))
        moves: list[Move] = []
        for m, k in enumerate(nodes):
            drawn = resolver.drawn.get(k)
            if drawn is None:
                continue
            # Against its pose (where it is drawn, or is to be drawn once its turn in the
            # queue comes): the live poses do not depend on how soon frames are drawn.
            sonar = self.mount.sonar_pose(solved[m])
            was = self.mount.sonar_pose(poses[k])
            # Every frame that moved is drawn again: redrawing only those that moved most
            # left neighbours drawn apart (quadrats seed 6 at 2 Hz: live lanes 8.0 ->
            # 11.9 / 10.4 cm, quadrat spacing 2.1 -> 4.4 / 6.5 cm). Its pose and its
            # keyframe move now; it is drawn again as the next frames come
            # (``LiveDrawing.redraw``), so that no frame waits for a stretch's worth of
            # redraws (seconds: the daemon would skip frames) and the redraws take a
            # bounded share of the engine's time.
            if fan_moved(sonar, was) > rp.redraw_m:
                moves.append(Move(k, solved[m], drawn.chain))
        self.drawn_frame = new
        return Resolution(
            nodes, solved, in_gnss, old, new, resolver.compass, last_drawn,
            poses[nodes[last_drawn]].copy(), moves,
        )  # fmt: skip
