"""Memory given back: large arrays from their own mappings, returned when freed.

glibc serves a block of 128 KiB or more with its own ``mmap`` and returns it when freed,
but raises that threshold each time such a block is freed (up to 32 MiB): from then on the
engine's large arrays (tile stacks, frame layers, FFT buffers) come from the heap, where
their churn leaves holes the process keeps. Over the two-hour hectare the live engine's
memory crept up in steps to 1.33 GB (3.3 MB per 1,000 frames over its second half); with
the threshold fixed at 1 MiB it stayed at about 1.0 GB from 8,000 to 32,000 frames.

The price: every large array is mapped afresh. Side by side, the live engine is 6 to 13 %
slower (quadrats seed 1: 52.2 -> 59.3 ms a frame under load, registration 20.0 -> 25.0;
the hectare's first 6,000 frames: 46.5 -> 49.5 ms). Two cheaper cures gained nothing on
those 6,000 frames (about 1,020 MB at the end against 959): ``malloc_trim`` after tiles
leave, and the tiles' stacks alone in mappings of their own. A daemon that must run two
hours on a 2 GB computer needs the flat curve more than the 10 %. Elsewhere (musl,
macOS) this does nothing.

A worker process (``daemon.workers``: preprocessing, registration, the loop closures'
registrations) holds no tiles: what it allocates are the same few buffer sizes over and
over (the FFTs' 0.7-2.8 MB arrays). glibc's defaults there still map and zero them afresh
(its threshold rises only as far as the blocks freed so far, and the heap's top is given
back whenever 128 KiB of it is free): on quadrats seed 8 at 10 Hz (1,639 frames, one
worker) the worker took 5.7 million page faults, 13.7 s of system time beside 51.3 s of
its own. ``keep_heap`` has it keep its blocks instead (no mapping below 64 MiB, the top
given back only beyond 128 MiB): 49,000 faults, 0.7 s of system time, 44.4 s of its own,
the same peak memory (263 MB against 262).
"""

from __future__ import annotations

import ctypes

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
LARGE_BLOCK = 1 << 20
"""Blocks from this size up get their own mapping (a tile's stacks: 1-2 MB)."""
WORKER_MAP_FROM = 64 << 20
"""In a worker, only blocks from this size up get their own mapping."""
WORKER_TRIM_FROM = 128 << 20
"""In a worker, the heap's free top is given back only beyond this."""


def _mallopt(settings: dict[int, int]) -> bool:
    """glibc's ``mallopt`` for each (parameter, value); whether it took them all (False
    where there is no glibc)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return all([bool(mallopt(key, value)) for key, value in settings.items()])


def return_large_blocks(threshold: int = LARGE_BLOCK) -> bool:
    """Have the C allocator map blocks of ``threshold`` bytes or more on their own (and
    unmap them when freed); whether it took the setting."""
    return _mallopt({M_MMAP_THRESHOLD: threshold})


def keep_heap(map_from: int = WORKER_MAP_FROM, trim_from: int = WORKER_TRIM_FROM) -> bool:
    """A worker's allocator: blocks below ``map_from`` bytes from the heap, whose free top
    goes back to the system only beyond ``trim_from`` bytes (see the module docstring);
    whether it took the settings."""
    return _mallopt({M_MMAP_THRESHOLD: map_from, M_TRIM_THRESHOLD: trim_from})
