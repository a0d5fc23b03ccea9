"""The worker pipe whose arrays go through shared memory (``daemon.channel``): what comes
out equals what went in, arrays through the slots and the rest through the pipe, slots
grown for larger arrays and never written again before the other side took them, and
nothing left in ``/dev/shm``."""

from __future__ import annotations

import multiprocessing
import os
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.channel import SLOTS, Channel


@dataclass
class _Message:
    index: int
    image: npt.NDArray[np.float32]
    mask: npt.NDArray[np.bool_]
    note: str


def _pair() -> tuple[Channel, Channel]:
    a, b = multiprocessing.Pipe()
    return Channel(a), Channel(b)


def _message(index: int, rows: int = 40, cols: int = 30) -> _Message:
    rng = np.random.default_rng(index)
    image = rng.random((rows, cols, 3), dtype=np.float32)
    return _Message(index, image, image[..., 0] > 0.5, f"frame {index}")


def _same(a: _Message, b: _Message) -> None:
    assert a.index == b.index and a.note == b.note
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.mask, b.mask)
    assert a.image.dtype == b.image.dtype and a.mask.dtype == b.mask.dtype


def test_arrays_go_through_shared_memory_and_come_out_equal_and_writable() -> None:
    engine, worker = _pair()
    shm_before = set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()
    for index in range(3 * SLOTS):
        sent = _message(index, rows=40 + 7 * index)  # each larger: slots grow
        engine.send(sent)
        got = worker.recv()
        _same(sent, got)
        got.image[0, 0, 0] = -1.0  # the receiver owns a copy
        assert sent.image[0, 0, 0] != -1.0
        worker.send(("ack", index))  # carries how many the worker has received
        assert engine.recv() == ("ack", index)
    assert engine.shared == 3 * SLOTS
    assert worker.shared == 0  # no arrays: the whole message through the pipe
    if shm_before or os.path.isdir("/dev/shm"):
        assert set(os.listdir("/dev/shm")) == shm_before  # anonymous memory files only
    engine.close()
    worker.close()


def test_a_slot_is_not_written_again_before_the_other_side_took_its_message() -> None:
    engine, worker = _pair()
    sent = [_message(index) for index in range(SLOTS + 3)]
    for message in sent:  # the worker answers nothing meanwhile
        engine.send(message)
    # The first message was never acknowledged, so the ring's first slot could not be
    # reused: what did not fit went through the pipe, and everything arrives intact.
    assert engine.shared < len(sent)
    for message in sent:
        _same(message, worker.recv())
    engine.close()
    worker.close()


def _echo(connection: multiprocessing.connection.Connection) -> None:
    channel = Channel(connection)
    while True:
        message = channel.recv()
        if message is None:
            return
        message.image *= 2.0
        channel.send(message)


def test_a_worker_process_round_trip() -> None:
    context = multiprocessing.get_context("spawn")
    parent, child = context.Pipe()
    process = context.Process(target=_echo, args=(child,), daemon=True)
    process.start()
    child.close()
    engine = Channel(parent)
    try:
        for index in range(2 * SLOTS):
            sent = _message(index, rows=50 + index)
            engine.send(sent)
            back = engine.recv()
            np.testing.assert_array_equal(back.image, 2.0 * sent.image)
            np.testing.assert_array_equal(back.mask, sent.mask)
        assert engine.shared == 2 * SLOTS
        engine.send(None)
    finally:
        process.join(timeout=30)
        if process.is_alive():
            process.kill()
        engine.close()
    assert process.exitcode == 0
