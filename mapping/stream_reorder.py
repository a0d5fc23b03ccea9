"""The streaming engine's first stage: samples put back in time order.

The sensors' samples reach the engine in the order their links deliver them: the sonar's
pings over Ethernet, the autopilot's messages over MAVLink, each with its own latency, and
now and then one twice (a retransmission, a log segment replayed). Everything after this
stage wants them in time order, each once. So a sample is held ``hold_s`` of survey time
(``StreamingParams.reorder_s``) past the newest one seen on any stream, in a heap keyed by
its stamp, and released in stamp order; a sample stamped at or before what has already
been released is late (counted, never used: the navigation has moved on), and one seen
before (the same kind and stamp) is a duplicate. Nothing waits for a silent sensor: the
newest sample of any stream moves the release on.
"""

from __future__ import annotations

import enum
import heapq
import itertools
import math
from collections import deque
from collections.abc import Iterator

from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping, RangeSample

Sample = ImuSample | GnssFix | HeadingSample | AttitudeSample | RangeSample | Ping

KINDS: dict[type, int] = {
    ImuSample: 0,
    AttitudeSample: 1,
    HeadingSample: 2,
    GnssFix: 3,
    Ping: 4,
    RangeSample: 5,
}
"""Each sample type's rank among samples of the same stamp (and its duplicate key): the
filter takes the IMU, attitude, heading and fix of an instant before a ping of the same
instant is placed."""


class Admission(enum.Enum):
    """What became of a sample offered to the buffer."""

    HELD = "held"
    """Held, to be released in time order."""
    LATE = "late"
    """Stamped at or before what was already released: not used."""
    DUPLICATE = "duplicate"
    """The same kind and stamp as a sample seen recently: not used again."""


class ReorderBuffer:
    """Samples held ``hold_s`` (survey time) past the newest seen, released in stamp order;
    ``remember`` recent (kind, stamp) pairs catch duplicates."""

    def __init__(self, hold_s: float, remember: int = 4096) -> None:
        self.hold_s = hold_s
        self._heap: list[tuple[float, int, int, Sample]] = []
        self._seq = itertools.count()
        self.latest = -math.inf
        """The newest stamp seen on any stream."""
        self._released = -math.inf
        self._recent: deque[tuple[int, float]] = deque(maxlen=remember)  # (kind, time) seen
        self._recent_set: set[tuple[int, float]] = set()

    @property
    def released(self) -> float:
        """Every sample stamped at or before this time (s) has been released; while a
        released sample is being processed, its stamp."""
        return self._released

    @property
    def held(self) -> int:
        """Samples waiting to be released."""
        return len(self._heap)

    def offer(self, sample: Sample) -> Admission:
        """Take one sample (any type) as it arrives; ``Admission.HELD`` when it is kept."""
        kind = KINDS[type(sample)]
        t = float(sample.time)
        if t <= self._released:
            return Admission.LATE
        key = (kind, t)
        if key in self._recent_set:
            return Admission.DUPLICATE
        if len(self._recent) == self._recent.maxlen:
            self._recent_set.discard(self._recent[0])
        self._recent.append(key)
        self._recent_set.add(key)
        heapq.heappush(self._heap, (t, kind, next(self._seq), sample))
        if t > self.latest:
            self.latest = t
        return Admission.HELD

    def due(self) -> Iterator[Sample]:
        """The samples ``hold_s`` older than the newest seen, in time order (``release``)."""
        return self.release(self.latest - self.hold_s)

    def release(self, upto: float) -> Iterator[Sample]:
        """The held samples stamped at or before ``upto``, in time order (of one stamp, in
        ``KINDS`` order, then as they came). ``released`` moves to each as it is handed
        out, so that what processes it sees its stamp as the present; once all are out,
        to ``upto`` (unless that is infinite: the end of the stream)."""
        while self._heap and self._heap[0][0] <= upto:
            t, _, _, sample = heapq.heappop(self._heap)
            self._released = t
            yield sample
        if upto > self._released and upto != math.inf:
            self._released = upto
