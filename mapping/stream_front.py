"""The streaming engine's front stage: each ping preprocessed and registered, in order.

The front is the engine's first two stages, preprocessing (its flat field and histogram
reference follow the pings) and local registration (the keyframe and the chain's rate
follow the accepted frames), one stateful ``mapping.frames.LocalRegistration`` fed in
ping order. Everything it needs of a ping comes with the ping (``FrontJob``: the
filter's pose there and the attitude and seabed to project it with), and everything the
later stages need comes back with its result (``FrontResult``: the blending frame, the
registration's outcome, the chain's rate, and the fan's shape when it changed), so that
the front can run where the rest is not, and the live loop closures' registrations
(``mapping.live_closures.ClosureJob``, pure tasks) ride along with the pings, each
answered with the result of the ping it came with: in the engine's own process (``InlineFront``),
or in a worker process of its own (``daemon.workers``) while the engine chains, draws
and re-solves the frames before it. Its results are taken in submission order, never
in order of arrival, so the map is the same wherever it runs.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

from mapping.blend import make_scorer
from mapping.fmt import Registration
from mapping.frames import FrameOutcome, LocalRegistration, SonarMount
from mapping.grid import SonarGrid
from mapping.live_closures import ClosureJob, ClosureRegistrar
from mapping.polar import Attitude
from mapping.preprocess import Preprocessor
from mapping.samples import Ping
from mapping.stream_drawing import drawn_layers
from mapping.stream_navigation import PingNavigation

if TYPE_CHECKING:
    from mapping.stream_params import StreamingParams

ChainRate = tuple[tuple[float, float, float], float, float]
"""The chain's velocity and turn rate (forward, starboard m/s, yaw rad/s), the time of the
last registered step it was measured with, and the span it covers
(``LocalRegistration.rate``)."""


@dataclass(frozen=True, slots=True)
class FrontJob:
    """One ping and what preprocessing and registering it need of the navigation."""

    index: int
    ping: Ping
    at: PingNavigation
    attitude: Attitude | None
    """Roll, pitch and seabed the ping is projected with (``NavigationRecord.ping_attitude``)."""
    closures: tuple[ClosureJob, ...] = ()
    """Loop closures' registrations to run after this ping's."""


@dataclass(frozen=True, slots=True)
class FanShape:
    """What the later stages need of the preprocessor's geometry: the blending grid and its
    fixed fan mask (loop closures register there), the lit band and the fan's half width."""

    grid: SonarGrid
    mask: npt.NDArray[np.bool_]
    min_range_m: float
    max_range_m: float
    half_width_rad: float


@dataclass(slots=True)
class FrontResult:
    """A ping preprocessed and registered: its frame on the blending grid as the tiles draw
    it (``mapping.stream_drawing.drawn_layers``: image, blending score, mask) and its
    mask, the outcome, the chain's rate after it, and the fan's shape when this ping's
    differs from the previous result's (else None)."""

    index: int
    layers: npt.NDArray[np.float32]
    mask: npt.NDArray[np.bool_]
    outcome: FrameOutcome
    rate: ChainRate | None
    shape: FanShape | None
    seconds: dict[str, float]
    """Time the front spent on it, per stage (``preprocess``, ``registration``,
    ``closure registration``)."""
    closures: tuple[tuple[int, Registration], ...] = ()
    """The job's closure registrations answered (the frame each was proposed for)."""

    @property
    def image(self) -> npt.NDArray[np.float32]:
        """The frame's image on the blending grid (a view of the first layer)."""
        return self.layers[..., 0]


def rate_at(
    rate: ChainRate | None, time: float, max_age_s: float
) -> tuple[float, float, float] | None:
    """The chain's velocity and turn rate when measured at most ``max_age_s`` before
    ``time`` (``LocalRegistration.chain_rate`` of a snapshot)."""
    if rate is None or time - rate[1] > max_age_s:
        return None
    return rate[0]


def fan_shape(preprocessor: Preprocessor) -> FanShape:
    grid = preprocessor.grid
    assert grid is not None
    bearings = preprocessor.fan.bearings_rad
    return FanShape(
        grid,
        preprocessor.tables.mask,
        preprocessor.min_range_m,
        preprocessor.fan.max_range_m,
        max(abs(float(bearings[0])), abs(float(bearings[-1]))),
    )


class Front:
    """The front stage itself (see the module docstring): feed it jobs in ping order."""

    def __init__(self, mount: SonarMount, params: StreamingParams) -> None:
        p = params.pipeline
        preprocess = p.preprocess
        if params.live_registration_res_m is not None:
            preprocess = replace(preprocess, registration_res_m=params.live_registration_res_m)
        self._attitude: Attitude | None = None
        self.local = LocalRegistration(
            mount,
            preprocess,
            p.fmt,
            p.registration,
            lambda _stamp: self._attitude,
            params.live_yaw_from_gyro,
        )
        self._shape_of: Preprocessor | None = None
        self.closures = ClosureRegistrar()
        self.scorer = make_scorer(p.blend)

    def run(self, job: FrontJob) -> FrontResult:
        started = time.perf_counter()
        self._attitude = job.attitude
        frame = self.local.frame(job.ping)
        preprocessed = time.perf_counter()
        at = job.at
        outcome = self.local.register(
            job.index, job.ping.time, frame, at.prior, at.odometry, at.gyro
        )
        registered = time.perf_counter()
        preprocessor = self.local.preprocessor
        shape = None
        if preprocessor is not None and preprocessor is not self._shape_of:
            shape = fan_shape(preprocessor)
            self._shape_of = preprocessor
        layers = drawn_layers(self.scorer, frame)
        scored = time.perf_counter()
        seconds = {
            "preprocess": preprocessed - started,
            "registration": registered - preprocessed,
            "scoring": scored - registered,
        }
        closures = tuple((closure.index, self.closures.run(closure)) for closure in job.closures)
        if job.closures:
            seconds["closure registration"] = time.perf_counter() - scored
        return FrontResult(
            job.index,
            layers,
            frame.mask,
            outcome,
            self.local.rate,
            shape,
            seconds,
            closures,
        )


class FrontStage(Protocol):
    """Where the front runs: jobs in, results out in the same order."""

    def submit(self, job: FrontJob) -> None:
        """Hand over the next ping's job."""

    def ready(self) -> bool:
        """The next result can be taken without waiting."""

    def result(self) -> FrontResult:
        """The next result in submission order (waits for it)."""

    def close(self) -> None:
        """No more jobs: let go of what runs them."""


class InlineFront:
    """The front in the engine's own process: each job run as it is submitted."""

    def __init__(self, front: Front) -> None:
        self.front = front
        self._results: deque[FrontResult] = deque()

    def submit(self, job: FrontJob) -> None:
        self._results.append(self.front.run(job))

    def ready(self) -> bool:
        return bool(self._results)

    def result(self) -> FrontResult:
        return self._results.popleft()

    def close(self) -> None:
        self._results.clear()
