"""Memory given back: large arrays from their own mappings, returned when freed.

glibc serves a block of 128 KiB or more with its own ``mmap`` and returns it when freed,
but raises that threshold each time such a block is freed (up to 32 MiB): from then on a
tile's 1-2 MB stacks come from the heap, where the churn of tiles loaded and spilled leaves
holes the process keeps. Setting the threshold fixes it (and turns the raising off). On
the two-hour hectare's first 5,000 frames through the live engine: 1,013 MB resident at
the end, growing 30 MB per 1,000 frames over the last 1,600; with it, 927 MB and 10 MB.
Elsewhere (musl, macOS) this does nothing.
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
