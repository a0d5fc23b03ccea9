"""The survey-end pass's registrations, computed ahead in worker processes.

The local registration (``mapping.frames.LocalRegistration``) is a chain: which frame a
frame is registered against (its keyframe) depends on how the frames before it
registered, so its frames cannot simply be handed out. But the survey-end pass knows
every frame's smoothed prior before it starts, and the keyframe rule (0.3 m, 3 degrees or
1 s from the keyframe) is a rule on motion that the priors measure to millimetres: which
pair each frame will ask for can be predicted frames ahead. ``RegisterAhead`` predicts
it, hands each predicted pair's registration (``mapping.frames.register_pair_job``, a
pure task) to the pool as the frames are preprocessed, and the registration chain, run
frame by frame here as before, takes a pair's answer from the pool when it asks for
exactly that pair with exactly that prior, or computes it itself when it asks for another
(a refused registration, a keyframe renewed on the other side of the rule than the
priors said, a frame without the gyro); the prediction then starts again from what the
chain did. Every registration is what the chain would have computed itself, so the
survey's registrations are the same, to the bit, with any number of workers; only their
cost moves.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mapping.fmt import Registration
from mapping.frames import (
    FrameOutcome,
    LocalRegistration,
    PairJob,
    prepare_frame_job,
    register_pair_job,
)
from mapping.preprocess import SonarFrame
from mapping.samples import Ping
from mapping.se2 import RelativePose, relative_pose
from mapping.tasks import TaskHandle, TaskPool

Array = npt.NDArray[np.float64]


@dataclass(slots=True)
class _Frame:
    """A frame preprocessed and waiting for the chain."""

    index: int
    time: float
    frame: SonarFrame
    prior: Array | None
    epoch: int | None


@dataclass(frozen=True, slots=True)
class _Asked:
    """A pair handed to the pool: against which frame, with which prior and sigma."""

    earlier: int
    expected: RelativePose
    sigma_m: float
    yaw_known: bool
    handle: TaskHandle[Registration]


class RegisterAhead:
    """See the module docstring. ``window``: frames preprocessed ahead of the chain."""

    def __init__(self, local: LocalRegistration, pool: TaskPool, window: int) -> None:
        self.local = local
        self.pool = pool
        self.window = max(window, 1)
        self.asked: dict[int, _Asked] = {}
        """Pairs handed out, by the later frame."""
        self.computed_here = 0
        """Registrations the chain asked for that were not asked ahead (or not so)."""
        self.taken = 0
        """Registrations taken from the pool."""
        self._coarse: dict[int, tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_] | None]] = {}
        self._state: tuple[int | None, int | None] = (None, None)
        """The predicted keyframe and last accepted frame, after the newest frame seen."""
        self._after: dict[int, tuple[int | None, int | None]] = {}
        """What the prediction expects the chain's keyframe and last frame to be after each
        frame waiting."""
        self._priors: dict[int, tuple[Array, float, int | None]] = {}
        """Prior, stamp and gyro epoch of the frames the prediction may still use."""
        local.ahead = self._lookup

    # -- the chain asks --------------------------------------------------------------------
    def _lookup(
        self, earlier: int, later: int, expected: RelativePose, sigma_m: float, yaw_known: bool
    ) -> Registration | None:
        asked = self.asked.pop(later, None)
        if (
            asked is None
            or asked.earlier != earlier
            or asked.expected != expected
            or asked.sigma_m != sigma_m
            or asked.yaw_known != yaw_known
        ):
            self.computed_here += 1
            return None
        self.taken += 1
        return asked.handle.result()

    # -- the prediction --------------------------------------------------------------------
    def predict(self, waiting: _Frame) -> None:
        """A frame preprocessed: keep what later pairs need of it, and hand its predicted
        pair to the pool (assumed accepted: a refused registration is the exception)."""
        k = waiting.index
        self._coarse[k] = (waiting.frame.coarse, waiting.frame.coarse_mask)
        if waiting.prior is not None and np.all(np.isfinite(waiting.prior)):
            self._priors[k] = (waiting.prior, waiting.time, waiting.epoch)
            self._state = self._step(k, waiting)
        self._after[k] = self._state

    def _step(self, k: int, here: _Frame) -> tuple[int | None, int | None]:
        key, last = self._state
        p = self.local.params
        assert here.prior is not None
        if key is None or last is None or here.time - self._priors[last][1] > p.max_gap_s:
            return k, k  # a chain restart: no registration
        key_prior, key_time, key_epoch = self._priors[key]
        if here.epoch is not None and here.epoch == key_epoch:
            # The gyro joins them: the prior is the priors' motion (``plain_prior``).
            expected, sigma = self.local.plain_prior(key_prior, here.prior)
            yaw_known = self.local.yaw_from_gyro
            earlier_coarse, earlier_mask = self._coarse[key]
            registrar = self.local.registrar
            assert registrar is not None
            job = PairJob(
                key, k, earlier_coarse, earlier_mask, here.frame.coarse, here.frame.coarse_mask,
                expected, sigma, yaw_known, registrar.grid, registrar.mask, registrar.params,
            )  # fmt: skip
            self.asked[k] = _Asked(
                key, expected, sigma, yaw_known, self.pool.submit(register_pair_job, job)
            )
        moved = relative_pose(key_prior, here.prior)
        renewed = (
            p.keyframe_m <= 0
            or math.hypot(moved.forward_m, moved.starboard_m) >= p.keyframe_m
            or abs(math.degrees(moved.yaw_rad)) >= p.keyframe_deg
            or here.time - key_time >= p.keyframe_s
        )
        return (k if renewed else key), k

    def chained(self, k: int, waiting: Iterable[_Frame]) -> None:
        """The chain has registered frame ``k``: where it went another way than predicted,
        predict the frames still waiting again from where it is (their old pairs are
        dropped unasked)."""
        expected = self._after.pop(k, None)
        actual = (self.local.key_index, self.local.last_index)
        if expected != actual:
            self._state = actual
            for later in waiting:
                self.asked.pop(later.index, None)
                if later.prior is not None and np.all(np.isfinite(later.prior)):
                    self._state = self._step(later.index, later)
                self._after[later.index] = self._state
        # What no pair can ask for any more: frames before the keyframe and last frame
        # the chain or the prediction may still register against.
        keep = [i for i in (*actual, *self._state) if i is not None]
        oldest = min(keep, default=k + 1)
        for old in [i for i in self._coarse if i < oldest and i <= k]:
            del self._coarse[old]
            self._priors.pop(old, None)


def register_frames(
    pings: Iterable[Ping],
    n: int,
    local: LocalRegistration,
    priors: Array,
    valid: npt.NDArray[np.bool_],
    gyro: npt.NDArray[np.int64],
    pool: TaskPool | None,
    timed: Callable[[str, float], float],
    progress: Callable[[str, int, int], None] | None = None,
    counts: dict[str, int] | None = None,
) -> list[FrameOutcome]:
    """Register the survey's first ``n`` frames in order (``LocalRegistration``), the
    pairs it will ask for computed ahead in ``pool`` when one is given. ``timed(stage,
    started)`` counts a stage's time since ``started`` and returns the time now.
    ``counts``: given, it gets how many registrations were taken from the pool
    (``ahead``) and how many computed here (``here``)."""
    ahead = RegisterAhead(local, pool, 3 * pool.workers + 2) if pool is not None else None
    outcomes: list[FrameOutcome] = []
    waiting: deque[_Frame] = deque()
    preparing: deque[tuple[int, float, SonarFrame | TaskHandle[SonarFrame]]] = deque()
    """Frames being preprocessed (in the pool, or here: done), in order, ahead of
    ``waiting``."""
    pings_left: Iterator[tuple[int, Ping]] = iter(enumerate(pings))
    held: tuple[int, Ping] | None = None
    window = ahead.window if ahead is not None else 1
    # One worker has the pairs to register (about four times a frame's preprocessing):
    # the frames are preprocessed here meanwhile. From two, the pool takes both.
    shared = pool if pool is not None and pool.workers >= 2 else None
    lead = 2 * shared.workers + 2 if shared is not None else 1

    def prepare() -> None:
        """Hand the next pings' preprocessing to the pool, up to ``lead`` out at once. A
        ping the pool cannot preprocess as here (the first, one of a new geometry: its
        tables, a new chain) waits until every frame before it is registered, and is
        preprocessed here."""
        nonlocal held
        while len(preparing) < lead:
            if held is None:
                got = next(pings_left, None)
                if got is None or got[0] >= n:
                    return
                held = got
            index, ping = held
            job = local.prepare_job(ping) if shared is not None else None
            if job is not None:
                assert shared is not None
                preparing.append((index, ping.time, shared.submit(prepare_frame_job, job)))
            elif preparing or waiting:
                return  # the frames before it are registered first
            else:
                started = time.perf_counter()
                preparing.append((index, ping.time, local.frame(ping)))
                timed("preprocess", started)
            held = None

    def fill() -> None:
        while len(waiting) < window:
            prepare()
            if not preparing:
                return
            index, stamp, got = preparing.popleft()
            started = time.perf_counter()
            frame = got if isinstance(got, SonarFrame) else got.result()
            timed("preprocess", started)
            prior = priors[index] if valid[index] else None
            epoch = int(gyro[index]) if gyro[index] >= 0 else None
            entry = _Frame(index, stamp, frame, prior, epoch)
            waiting.append(entry)
            if ahead is not None:
                ahead.predict(entry)
        prepare()

    while True:
        fill()
        if not waiting:
            break
        entry = waiting.popleft()
        started = time.perf_counter()
        outcomes.append(
            local.register(
                entry.index, entry.time, entry.frame, entry.prior, gyro_epoch=entry.epoch
            )
        )
        timed("registration", started)
        if ahead is not None:
            ahead.chained(entry.index, waiting)
        if progress is not None:
            progress("registering", entry.index + 1, n)
    local.ahead = None
    if counts is not None and ahead is not None:
        counts["ahead"] = ahead.taken
        counts["here"] = ahead.computed_here
    return outcomes
