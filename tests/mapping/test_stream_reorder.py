"""The reorder buffer (``mapping.stream_reorder``): a simulated survey's samples, shuffled
within the hold and some sent twice, come out in time order and each once; a sample
older than what was released is refused; nothing waits for a silent stream."""

from __future__ import annotations

import functools
import math
import random
from collections import Counter
from dataclasses import replace

from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping
from mapping.stream_reorder import KINDS, Admission, ReorderBuffer, Sample
from tools.sim.stream import survey_events


@functools.cache
def _survey() -> tuple[Sample, ...]:
    """A short survey's samples in arrival order (4 s, 20 pings)."""
    stream = survey_events("quadrats", 4, max_pings=20, n_beams=16)
    return tuple(sample for _, sample in stream.events)  # type: ignore[misc]


def _time_order(samples: tuple[Sample, ...] | list[Sample]) -> list[Sample]:
    return sorted(samples, key=lambda s: (float(s.time), KINDS[type(s)]))


def _same(a: list[Sample], b: list[Sample]) -> bool:
    return len(a) == len(b) and all(x is y for x, y in zip(a, b, strict=True))


def test_shuffled_and_repeated_samples_come_out_in_time_order_each_once() -> None:
    samples = _survey()
    rng = random.Random(3)
    # Late by up to 0.2 s (inside the 0.25 s hold), and every 25th sample twice.
    arrivals = sorted(samples, key=lambda s: s.time + rng.uniform(0.0, 0.2))
    assert not _same(arrivals, _time_order(samples))  # the shuffle did something
    buffer = ReorderBuffer(0.25)
    admitted: Counter[Admission] = Counter()
    out: list[Sample] = []
    for k, sample in enumerate(arrivals):
        for _ in range(2 if k % 25 == 0 else 1):
            admitted[buffer.offer(sample)] += 1
            for released in buffer.due():
                # What processes a sample sees its stamp as the present.
                assert buffer.released == float(released.time)
                out.append(released)
    assert buffer.held > 0  # the last 0.25 s wait for newer samples
    out.extend(buffer.release(math.inf))
    assert buffer.held == 0
    assert admitted[Admission.DUPLICATE] == len(range(0, len(arrivals), 25))
    assert admitted[Admission.LATE] == 0
    assert admitted[Admission.HELD] == len(samples)
    assert _same(out, _time_order(samples))


def test_a_sample_no_newer_than_what_was_released_is_late_and_never_comes_out() -> None:
    samples = _time_order(_survey())
    buffer = ReorderBuffer(0.25)
    for sample in samples[:200]:
        buffer.offer(sample)
    upto = float(samples[150].time)
    out = list(buffer.release(upto))
    assert _same(out, [s for s in samples[:200] if s.time <= upto])
    assert buffer.released == upto
    late = replace(samples[100], time=samples[100].time + 1e-6)
    assert buffer.offer(late) is Admission.LATE
    assert buffer.offer(replace(samples[150], time=upto)) is Admission.LATE  # at: late too
    rest = list(buffer.release(math.inf))
    assert _same(rest, samples[151:200])
    assert all(s is not late for s in rest)


def test_released_moves_to_each_sample_then_to_the_limit_but_not_to_the_end() -> None:
    samples = _time_order(_survey())[:50]
    buffer = ReorderBuffer(0.25)
    for sample in samples:
        buffer.offer(sample)
    limit = float(samples[20].time) + 1e-4  # between two samples
    stamps = []
    for sample in buffer.release(limit):
        stamps.append(buffer.released)
        assert buffer.released == float(sample.time)
    assert stamps == [float(s.time) for s in samples[:21]]
    assert buffer.released == limit  # everything up to the limit is done
    list(buffer.release(math.inf))
    assert buffer.released == float(samples[-1].time)  # the end of the stream is no time


def test_samples_of_one_instant_come_out_navigation_first_and_the_ping_last() -> None:
    samples = _survey()
    ping = next(s for s in samples if isinstance(s, Ping))
    instant = float(ping.time)
    kinds = (ImuSample, AttitudeSample, HeadingSample, GnssFix)
    at_once = [
        replace(next(s for s in samples if isinstance(s, kind)), time=instant) for kind in kinds
    ]
    buffer = ReorderBuffer(0.25)
    for sample in [ping, *reversed(at_once)]:  # the ping first, the IMU last
        assert buffer.offer(sample) is Admission.HELD
    out = list(buffer.release(instant))
    assert [type(s) for s in out] == [*kinds, Ping]


def test_pings_are_released_while_the_navigation_is_silent() -> None:
    pings = [s for s in _survey() if isinstance(s, Ping)]
    buffer = ReorderBuffer(0.25)
    out: list[Sample] = []
    for ping in pings:
        buffer.offer(ping)
        out.extend(buffer.due())
    # Each ping comes out once the pings themselves are ``hold_s`` past it.
    newest = float(pings[-1].time)
    assert _same(out, [p for p in pings if p.time <= newest - 0.25])
    assert len(out) >= len(pings) - 2  # 5 Hz: only the last ping or two wait


def test_duplicates_are_caught_among_the_last_remembered_samples() -> None:
    samples = _time_order(_survey())[:20]
    buffer = ReorderBuffer(1000.0, remember=8)  # nothing is released: only memory counts
    assert buffer.offer(samples[0]) is Admission.HELD
    for sample in samples[1:8]:
        buffer.offer(sample)
    assert buffer.offer(samples[0]) is Admission.DUPLICATE  # 8 remembered, it among them
    buffer.offer(samples[8])
    assert buffer.offer(samples[0]) is Admission.HELD  # forgotten: held once more
    assert buffer.held == 10
