"""Cut a TCP byte stream from an Oculus sonar into whole messages.

The protocol has no checksum and no end marker: a message is its 16-byte header plus
``payloadSize`` bytes. The framer finds the magic ``53 4F``, checks that the header could be
real (known msgId, plausible size for that msgId, small msgVersion) and, for
SimplePingResult, that the fixed struct's sizes agree (``read_ping_info``). Anything that
fails is dropped one byte at a time and the stream rescanned, so a real message hidden
behind a bogus magic is still found.

A cut (message A loses its tail, message B follows at once) leaves A's header claiming
bytes that belong to B. Before emitting a candidate, the framer therefore looks inside the
span it claims for the start of another message that passes the same checks; if one is
there, the candidate is taken as cut and dropped, and framing resumes at that message.

What is recovered: every message after garbage, after a bogus magic, after a candidate
whose header or ping struct is inconsistent, and after a cut message (B and everything
after it), whatever the chunking of the input.

Framed but not recognised: a candidate that fails those checks (an unknown msgId, a
version out of range, a ping whose struct disagrees with its size: a corrupt message) is
still emitted when its own header frames it, that is when no plausible message starts
inside the span it claims and one does start right where it ends (or the link goes
quiet there). The receiver records it with the rest, so nothing the sonar framed is
lost before parsing, and the parser then rejects it (``messages_unrecognised`` counts
them). Without that confirmation its bytes are skipped as garbage.

What is not: the cut message itself (its tail is gone). A cut message followed by bytes
that start no valid message within the span it claims (e.g. the sonar restarted
mid-message and the next message begins later) is emitted with a wrong tail: there is no
checksum, and only a ping's fixed struct can be checked. A corrupted header whose size is
still plausible swallows the bytes it claims unless a valid message starts inside them. A
real message whose payload holds bytes that pass every header check would be split: for
random payload bytes about 2**-48 per byte (dominated by PingResult headers), i.e. about
once in three years of 180 kB pings at 10 Hz. A complete message whose last bytes could
start a header is held back until the next bytes arrive (or ``flush()``). After a
reconnect, call ``reset()``: the old connection's partial message is then dropped.
"""

from __future__ import annotations

from drivers.oculus.ping import PING_V1_STRUCT_SIZE, PING_V2_STRUCT_SIZE, read_ping_info
from drivers.oculus.protocol import (
    HEADER_SIZE,
    OCULUS_MAGIC,
    SIMPLE_FIRE_V1_SIZE,
    SIMPLE_FIRE_V2_SIZE,
    STATUS_SIZE,
    MessageHeader,
    MessageId,
    OculusFormatError,
)

MAX_PAYLOAD = 16 * 1024 * 1024
_MAX_MSG_VERSION = 0xFF
# Smallest SimplePingResult: v1 struct, one bearing, one 8-bit sample.
_MIN_PING_PAYLOAD = PING_V1_STRUCT_SIZE + 2 + 1 - HEADER_SIZE

# Payload sizes a real message of each type can have: exact sizes or (min, max).
_EXACT_SIZES: dict[int, tuple[int, ...]] = {
    MessageId.STATUS: (STATUS_SIZE - HEADER_SIZE,),
    MessageId.SIMPLE_FIRE: (SIMPLE_FIRE_V1_SIZE - HEADER_SIZE, SIMPLE_FIRE_V2_SIZE - HEADER_SIZE),
}
_SIZE_RANGES: dict[int, tuple[int, int]] = {
    MessageId.SIMPLE_PING_RESULT: (_MIN_PING_PAYLOAD, MAX_PAYLOAD),
    MessageId.PING_RESULT: (0, MAX_PAYLOAD),
    MessageId.USER_CONFIG: (0, 1024),
    MessageId.LOGS: (0, 1 << 20),
    MessageId.DUMMY: (0, 1024),
}

_VALID, _INVALID, _NEED_MORE = 0, 1, 2


def header_is_plausible(header: MessageHeader, max_payload: int = MAX_PAYLOAD) -> bool:
    """Whether a header could have come from a sonar (known msgId, size fits that msgId)."""
    if header.msg_version > _MAX_MSG_VERSION or header.payload_size > max_payload:
        return False
    exact = _EXACT_SIZES.get(header.msg_id)
    if exact is not None:
        return header.payload_size in exact
    bounds = _SIZE_RANGES.get(header.msg_id)
    return bounds is not None and bounds[0] <= header.payload_size <= bounds[1]


class OculusFramer:
    """Incremental framer: ``feed`` bytes as they arrive, get whole messages back.

    Never raises on any input. Counters: ``bytes_skipped`` (bytes dropped as not part of a
    message), ``messages_out`` (all emitted), ``messages_unrecognised`` (emitted though
    they fail the checks, see the module doc), ``resyncs`` (times framing was lost and
    searched for again).
    The buffer never holds more than one message of at most ``max_payload`` bytes plus the
    bytes of the latest ``feed``.
    """

    def __init__(self, max_payload: int = MAX_PAYLOAD) -> None:
        self.max_payload = max_payload
        self.bytes_skipped = 0
        self.messages_out = 0
        self.messages_unrecognised = 0
        self.resyncs = 0
        self._buf = bytearray()
        self._scan_from = 2  # where the embedded-header scan of the current candidate resumes
        self._skipping = False

    @property
    def pending_bytes(self) -> int:
        """Bytes held, waiting for the rest of a message."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        """Add received bytes; return the messages (header + payload) completed by them."""
        self._buf += data
        return self._drain(final=False)

    def holds_complete_message(self) -> bool:
        """Whether the held bytes begin with a whole message, held back only because its
        last bytes could start the next header (it comes out with the next bytes or
        ``flush()``; a receiver stamps it with the time its bytes arrived)."""
        buf = self._buf
        if len(buf) < HEADER_SIZE or not buf.startswith(OCULUS_MAGIC):
            return False
        return len(buf) >= HEADER_SIZE + MessageHeader.unpack(buf[:HEADER_SIZE]).payload_size

    def flush(self) -> list[bytes]:
        """Emit a complete held-back message (end of stream or idle link); keep partials."""
        return self._drain(final=True)

    def reset(self) -> None:
        """Forget buffered bytes (e.g. after reconnecting); counters are kept."""
        self._skip(len(self._buf))

    def _drain(self, final: bool) -> list[bytes]:
        out: list[bytes] = []
        while True:
            message = self._next(final)
            if message is None:
                return out
            if message:
                out.append(message)

    def _skip(self, count: int) -> None:
        if count <= 0:
            return
        if not self._skipping:
            self.resyncs += 1
            self._skipping = True
        self.bytes_skipped += count
        del self._buf[:count]
        self._scan_from = 2

    def _next(self, final: bool) -> bytes | None:
        """One framing step: a message, b"" to go on, or None when more bytes are needed."""
        buf = self._buf
        start = buf.find(OCULUS_MAGIC)
        if start < 0:
            # Keep a trailing 0x53: it may be the first half of the next magic.
            self._skip(len(buf) - (1 if buf.endswith(OCULUS_MAGIC[:1]) else 0))
            return None
        if start > 0:
            self._skip(start)
            return b""
        verdict = self._check_at(0)
        if verdict == _INVALID:
            framed = self._framed_unrecognised(final)
            if framed is None:
                return None
            if not framed:
                self._skip(1)
                return b""
            total = HEADER_SIZE + MessageHeader.unpack(buf[:HEADER_SIZE]).payload_size
            message = bytes(buf[:total])
            del buf[:total]
            self._scan_from = 2
            self._skipping = False
            self.messages_out += 1
            self.messages_unrecognised += 1
            return message
        if len(buf) < HEADER_SIZE:
            return None
        total = HEADER_SIZE + MessageHeader.unpack(buf).payload_size
        # Even while the candidate's own checks wait for bytes, a message starting inside
        # its span proves it bogus or cut.
        embedded = self._find_embedded(total, final)
        if embedded is None:
            return None
        if embedded > 0:
            self._skip(embedded)  # resume at the message inside the candidate
            return b""
        if verdict == _NEED_MORE or len(buf) < total:
            return None
        message = bytes(buf[:total])
        del buf[:total]
        self._scan_from = 2
        self._skipping = False
        self.messages_out += 1
        return message

    def _check_at(self, pos: int) -> int:
        """Whether a real message could start at ``pos`` (given the bytes held so far)."""
        buf = self._buf
        if len(buf) - pos < HEADER_SIZE:
            return _NEED_MORE if self._partial_header_ok(pos) else _INVALID
        # Copies, not memoryviews: a live export would stop the buffer from shrinking.
        header = MessageHeader.unpack(bytes(buf[pos : pos + HEADER_SIZE]))
        if not header_is_plausible(header, self.max_payload):
            return _INVALID
        if header.msg_id != MessageId.SIMPLE_PING_RESULT:
            return _VALID
        need = min(header.message_size, PING_V2_STRUCT_SIZE)
        if len(buf) - pos < need:
            return _NEED_MORE
        try:
            read_ping_info(bytes(buf[pos : pos + need]))
        except OculusFormatError:
            return _INVALID
        return _VALID

    def _framed_unrecognised(self, final: bool) -> bool | None:
        """Whether the candidate at 0, which fails the checks, is framed by its header
        all the same (see the module doc); None while that depends on bytes to come."""
        buf = self._buf
        if len(buf) < HEADER_SIZE:
            return None if not final and self._magic_frames_partial() else False
        header = MessageHeader.unpack(bytes(buf[:HEADER_SIZE]))
        if header.payload_size > self.max_payload:
            return False
        total = header.message_size
        embedded = self._find_embedded(total, final)
        if embedded is None:
            return None
        if embedded > 0:
            return False  # a plausible message inside: the candidate is garbage or cut
        if len(buf) < total:
            return None if not final else False
        if len(buf) == total:
            return True if final else None  # the link went quiet right at its end
        rest = bytes(buf[total : total + 2])
        if not OCULUS_MAGIC.startswith(rest):
            return False
        if len(rest) < 2:
            return None if not final else False
        after = self._check_at(total)
        if after == _NEED_MORE:
            return None if not final else False
        return after == _VALID

    def _magic_frames_partial(self) -> bool:
        """Whether a header cut short at the end of the buffer may still frame a message."""
        part = bytes(self._buf[:HEADER_SIZE])
        return len(part) < 16 and part.startswith(OCULUS_MAGIC)

    def _partial_header_ok(self, pos: int) -> bool:
        """Whether the header bytes present at ``pos`` (fewer than 16) could still be real."""
        part = bytes(self._buf[pos : pos + HEADER_SIZE])
        if len(part) >= 8:
            msg_id = int.from_bytes(part[6:8], "little")
            if msg_id not in _EXACT_SIZES and msg_id not in _SIZE_RANGES:
                return False
        return len(part) < 10 or int.from_bytes(part[8:10], "little") <= _MAX_MSG_VERSION

    def _find_embedded(self, total: int, final: bool) -> int | None:
        """Offset of a plausible message starting inside the candidate at 0 (its span being
        ``total`` bytes), 0 if there is none, None if that depends on bytes still to come.

        A position that needs more bytes to be judged blocks the scan only up to the end of
        the span its own header claims: a plausible message inside that span would win
        whatever the blocked position turns out to be (it would be dropped as cut).
        """
        buf = self._buf
        end = min(total, len(buf))
        pos = self._scan_from
        blocked_at: int | None = None
        limit = end
        while True:
            pos = buf.find(OCULUS_MAGIC, pos, limit + 1)
            if pos < 0 or pos >= limit:
                break
            verdict = self._check_at(pos)
            if verdict == _VALID:
                return pos
            if verdict == _NEED_MORE and not final:
                if blocked_at is None:
                    blocked_at = pos
                span = len(buf) - pos
                if span >= HEADER_SIZE:
                    span = (
                        HEADER_SIZE
                        + MessageHeader.unpack(buf[pos : pos + HEADER_SIZE]).payload_size
                    )
                limit = min(limit, pos + span)
            pos += 1
        if blocked_at is not None:
            self._scan_from = blocked_at
            return None
        # Every magic before `end - 1` has been checked; one may straddle `end`.
        self._scan_from = max(2, end - 1)
        straddle = len(buf) == end and buf[end - 1 : end] == OCULUS_MAGIC[:1]
        return None if straddle and not final and end > 2 else 0
