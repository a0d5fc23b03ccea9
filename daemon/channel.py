"""A pipe between the engine and a worker process whose arrays travel through shared memory.

A front result is a frame on the blending grid, about 1.4 MB of arrays; a job is a ping,
a few hundred kB. Pickled through the pipe, each crosses the kernel in 64 kB pieces,
each piece waiting for the other side to read it (and, in a worker busy computing, for
its reading thread to get the interpreter): measured at 2 ms a frame each way, half the
time the engine waited for its front. Here only the pickle's small frame goes through
the pipe; the arrays' bytes (pickle protocol 5's out-of-band buffers) are written into
one of a ring of shared memory slots, and copied out by the receiver as it unpickles
(one copy each side, no kernel round trips).

The slots are anonymous memory files (``memfd``), made and grown by the side that writes
them and handed to the other once, with the file descriptor itself, over the same
socket (``SCM_RIGHTS``): nothing is named in ``/dev/shm``, so nothing is left behind when
either side dies. A slot is written again only when the other side has said (each
message carries how many it has received) that it took the message that was there;
otherwise, and for a message without arrays, the whole message goes through the pipe as
before. Both ways the object that comes out equals the one that went in.
"""

from __future__ import annotations

import mmap
import multiprocessing.connection
import os
import pickle
from multiprocessing import reduction
from typing import Any

SLOTS = 8
"""Messages that may be in shared memory at once, each way."""

_ALIGN = 64


def _aligned(n: int) -> int:
    return (n + _ALIGN - 1) // _ALIGN * _ALIGN


class Channel:
    """One end of a duplex pipe (``multiprocessing.Pipe()``, a Unix socket). Sends go from
    one thread and receives from one thread (they may be two)."""

    def __init__(self, connection: multiprocessing.connection.Connection, slots: int = SLOTS):
        self.connection = connection
        self.slots = slots
        self.sent = 0
        """Messages sent."""
        self.received = 0
        """Messages received (each fully copied out of its slot)."""
        self._peer_received = 0
        """Messages the other side had received when it last sent one."""
        self._mine: list[mmap.mmap | None] = [None] * slots
        self._theirs: list[mmap.mmap | None] = [None] * slots
        self.shared = 0
        """Messages sent through shared memory (the rest went through the pipe whole)."""

    # -- sending ----------------------------------------------------------------------------
    def send(self, obj: Any) -> None:
        buffers: list[pickle.PickleBuffer] = []
        data = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
        slot = self.sent % self.slots
        free = self._peer_received > self.sent - self.slots
        raws = [buffer.raw() for buffer in buffers] if buffers and free else []
        if not raws:
            if buffers:
                data = pickle.dumps(obj, protocol=5)
            self.connection.send(("i", self.received, data))
            self.sent += 1
            return
        spans = []
        offset = 0
        for raw in raws:
            spans.append((offset, raw.nbytes))
            offset += _aligned(raw.nbytes)
        memory = self._slot(slot, offset)
        for raw, (start, length) in zip(raws, spans, strict=True):
            memory[start : start + length] = raw
        self.connection.send(("s", self.received, data, slot, spans))
        self.sent += 1
        self.shared += 1

    def _slot(self, slot: int, size: int) -> mmap.mmap:
        """Slot ``slot``'s memory, at least ``size`` bytes (a new, larger file handed to the
        other side when it is not)."""
        memory = self._mine[slot]
        if memory is not None and len(memory) >= size:
            return memory
        size = max(_aligned(size), 1 << 16) * 5 // 4  # room for a slightly larger frame
        fd = os.memfd_create(f"seamap-slot-{slot}", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, size)
            fresh = mmap.mmap(fd, size)
            self.connection.send(("f", slot, size))
            reduction.send_handle(self.connection, fd, 0)
        finally:
            os.close(fd)
        if memory is not None:
            memory.close()
        self._mine[slot] = fresh
        return fresh

    # -- receiving ----------------------------------------------------------------------------
    def poll(self, timeout: float = 0.0) -> bool:
        return self.connection.poll(timeout)

    def recv(self) -> Any:
        while True:
            message = self.connection.recv()
            kind = message[0]
            if kind == "f":
                _, slot, size = message
                fd = reduction.recv_handle(self.connection)
                try:
                    fresh = mmap.mmap(fd, size)
                finally:
                    os.close(fd)
                old = self._theirs[slot]
                if old is not None:
                    old.close()
                self._theirs[slot] = fresh
                continue
            self._peer_received = max(self._peer_received, message[1])
            if kind == "i":
                obj = pickle.loads(message[2])
            else:
                _, _, data, slot, spans = message
                memory = self._theirs[slot]
                if memory is None:
                    raise RuntimeError(f"a message in shared memory slot {slot}, never handed over")
                with memoryview(memory) as view:
                    copies = [bytearray(view[start : start + length]) for start, length in spans]
                obj = pickle.loads(data, buffers=copies)
            self.received += 1
            return obj

    def close(self) -> None:
        self.connection.close()
        for memory in (*self._mine, *self._theirs):
            if memory is not None:
                memory.close()
        self._mine = [None] * self.slots
        self._theirs = [None] * self.slots
