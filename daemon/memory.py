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
"""

from __future__ import annotations

import ctypes

M_MMAP_THRESHOLD = -3
LARGE_BLOCK = 1 << 20
"""Blocks from this size up get their own mapping (a tile's stacks: 1-2 MB)."""


def return_large_blocks(threshold: int = LARGE_BLOCK) -> bool:
    """Have the C allocator map blocks of ``threshold`` bytes or more on their own (and
    unmap them when freed); whether it took the setting."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, threshold))
