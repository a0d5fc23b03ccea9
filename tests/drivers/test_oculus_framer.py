"""The TCP stream framer: whole messages out of garbage, cuts and any chunking."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.oculus import (
    MessageHeader,
    MessageId,
    OculusFramer,
    SimpleFire,
    StatusMessage,
    build_simple_ping,
)
from tests.drivers.test_oculus_protocol import REAL_PING_SIZE, make_ping, real_pings
from tests.fuzzing import fuzz


def _quiet_tail(message: bytes) -> bytes:
    """The same message with no magic in its last 16 bytes.

    A message ending in bytes that could start a header, followed by garbage that completes
    one, cannot be told from a message cut just before its end; the pool avoids that case.
    """
    assert b"SO" not in message[max(1, len(message) - 17) :] and message[-1:] != b"S"
    return message


def _pool() -> list[bytes]:
    pings = []
    kinds: list[tuple[int, type[np.unsignedinteger], bool]] = [
        (1, np.uint8, False),
        (2, np.uint8, True),
        (2, np.uint16, False),
        (1, np.uint16, True),
    ]
    for k, (version, dtype, gains) in enumerate(kinds):
        ping = make_ping(n_beams=24, n_ranges=12, dtype=dtype, gains=gains, seed=k, ping_id=k)
        ping.image[-1] = 0  # quiet tail, see _quiet_tail
        pings.append(build_simple_ping(ping, version=version))
    others = [
        StatusMessage(device_id=7, ip_addr="10.0.0.2").pack(),
        SimpleFire(version=1).pack(),
        SimpleFire(version=2).pack(),
        MessageHeader(0x1ED4, 0, MessageId.DUMMY, 0, 0).pack(),
    ]
    return [_quiet_tail(m) for m in pings + others]


POOL = _pool()


def feed_in_chunks(framer: OculusFramer, data: bytes, cuts: list[int]) -> list[bytes]:
    out: list[bytes] = []
    start = 0
    for cut in [*sorted(c % (len(data) + 1) for c in cuts), len(data)]:
        out += framer.feed(data[start:cut])
        start = max(start, cut)
    return out + framer.flush()


def accounted(framer: OculusFramer, fed: int, out: list[bytes]) -> bool:
    """Every byte fed was emitted, skipped or is still held."""
    return fed == framer.bytes_skipped + sum(map(len, out)) + framer.pending_bytes


@pytest.mark.parametrize("chunk", [7, 4096, 65536, 10**6])
def test_real_capture_frames_whatever_the_chunk_size(chunk: int) -> None:
    data = real_pings()
    framer = OculusFramer()
    out = feed_in_chunks(framer, data, list(range(chunk, len(data), chunk)))
    assert out == [data[k * REAL_PING_SIZE : (k + 1) * REAL_PING_SIZE] for k in range(3)]
    assert (framer.messages_out, framer.bytes_skipped, framer.resyncs) == (3, 0, 0)


def test_garbage_and_bogus_magics_are_skipped_and_counted() -> None:
    rng = np.random.default_rng(3)
    noise = rng.integers(0, 256, 500, dtype=np.uint8).tobytes().replace(b"SO", b"S.")
    bogus_ping = MessageHeader(0, 0, MessageId.SIMPLE_PING_RESULT, 2, 5000).pack() + bytes(300)
    bogus_id = b"SO" + bytes(14)  # msgId 0: not a message
    stream = noise + POOL[0] + bogus_id + bogus_ping + POOL[1] + b"SO" + noise + POOL[4]
    framer = OculusFramer()
    out = framer.feed(stream)
    assert out == [POOL[0], POOL[1], POOL[4]]
    assert framer.resyncs == 3
    assert framer.bytes_skipped == len(stream) - sum(map(len, out))
    assert framer.pending_bytes == 0


@pytest.mark.parametrize("kept", [1, 2, 9, 16, 60, 122, 150, 250, 2100, -1])
def test_a_cut_message_loses_only_itself(kept: int) -> None:
    """Message A loses its tail (kept bytes remain); B and C right after it are recovered."""
    a, b, c = POOL[1], POOL[2], POOL[4]
    stream = a[:kept] + b + c
    for chunk in (1, 97, len(stream)):
        framer = OculusFramer()
        out = feed_in_chunks(framer, stream, list(range(chunk, len(stream), chunk)))
        assert out == [b, c], chunk
        assert framer.bytes_skipped == len(a[:kept])


def test_absurd_sizes_are_not_buffered() -> None:
    huge = MessageHeader(0, 0, MessageId.SIMPLE_PING_RESULT, 1, 1 << 30).pack()
    framer = OculusFramer()
    assert framer.feed(huge + bytes(1000)) == []
    assert framer.pending_bytes == 0 and framer.bytes_skipped == len(huge) + 1000
    assert framer.feed(POOL[0]) == [POOL[0]]


def test_a_complete_message_held_back_by_a_possible_header_is_flushed() -> None:
    dummy = MessageHeader(0, 0, MessageId.DUMMY, 0, 4).pack() + b"xxSO"
    framer = OculusFramer()
    assert framer.feed(dummy) == []  # "SO" at the end could start the next message
    assert framer.flush() == [dummy]
    framer = OculusFramer()
    assert framer.feed(dummy + POOL[5]) == [dummy, POOL[5]]


@pytest.mark.fuzz
@fuzz(200)
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 3000), max_size=6))
def test_random_bytes_never_crash_the_framer(data: bytes, cuts: list[int]) -> None:
    framer = OculusFramer()
    out = feed_in_chunks(framer, data, cuts)
    assert accounted(framer, len(data), out)
    assert framer.pending_bytes <= len(data)


@pytest.mark.fuzz
@fuzz(100)
@given(
    picks=st.lists(st.integers(0, len(POOL) - 1), min_size=1, max_size=6),
    edits=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=10),
    cuts=st.lists(st.integers(0, 10**6), max_size=6),
)
def test_mutated_streams_never_crash_the_framer(
    picks: list[int], edits: list[tuple[int, int]], cuts: list[int]
) -> None:
    stream = bytearray(b"".join(POOL[i] for i in picks))
    for position, value in edits:
        stream[position % len(stream)] = value
    framer = OculusFramer()
    out = feed_in_chunks(framer, bytes(stream), cuts)
    assert accounted(framer, len(stream), out)


# Garbage: random bytes, sometimes salted with magics and headers that look real.
_fake_header = st.builds(
    lambda msg_id, version, size, tail: MessageHeader(0, 0, msg_id, version, size).pack() + tail,
    st.sampled_from([int(m) for m in MessageId]),
    st.integers(0, 3),
    st.sampled_from([0, 12, 37, 73, 126, 300, 5000, 1 << 20]),
    st.binary(max_size=40),
)
_garbage = st.lists(st.one_of(st.binary(max_size=200), _fake_header, st.just(b"SO")), max_size=4)


def _is_subsequence(wanted: list[bytes], got: list[bytes]) -> bool:
    remaining = iter(got)
    return all(any(m == g for g in remaining) for m in wanted)


@pytest.mark.fuzz
@fuzz(150)
@given(
    picks=st.lists(st.integers(0, len(POOL) - 1), min_size=1, max_size=5),
    garbage=st.lists(_garbage, min_size=6, max_size=6),
    cuts=st.lists(st.integers(0, 10**5), max_size=8),
)
def test_messages_in_garbage_are_all_recovered_in_order(
    picks: list[int], garbage: list[list[bytes]], cuts: list[int]
) -> None:
    """Garbage may hold magics and real-looking headers; a complete fake message in it comes
    out too (nothing can tell it from a real one), so the real ones must form a
    subsequence of the output."""
    messages = [POOL[i] for i in picks]
    gaps = [b"".join(g) for g in garbage]
    stream = gaps[0] + b"".join(m + g for m, g in zip(messages, gaps[1:], strict=False))
    framer = OculusFramer()
    out = feed_in_chunks(framer, stream, cuts)
    assert _is_subsequence(messages, out)
    assert accounted(framer, len(stream), out)


@settings(max_examples=150, deadline=None)
@given(
    picks=st.lists(st.integers(0, len(POOL) - 1), min_size=1, max_size=5),
    gaps=st.lists(st.binary(max_size=300), min_size=6, max_size=6),
    cuts=st.lists(st.integers(0, 10**5), max_size=8),
)
def test_messages_in_magic_free_garbage_come_out_exactly(
    picks: list[int], gaps: list[bytes], cuts: list[int]
) -> None:
    messages = [POOL[i] for i in picks]
    # No magic in the garbage, nor across its edges with a message.
    gaps = [g.replace(b"SO", b"S.").lstrip(b"O") for g in gaps]
    stream = gaps[0] + b"".join(m + g for m, g in zip(messages, gaps[1:], strict=False))
    framer = OculusFramer()
    out = feed_in_chunks(framer, stream, cuts)
    assert out == messages
    assert accounted(framer, len(stream), out) and framer.pending_bytes <= 1
