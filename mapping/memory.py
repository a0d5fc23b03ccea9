"""Freed memory handed back to the system (glibc's ``malloc_trim``).

The tiles' stacks (1-2 MB each) come and go as tiles are loaded and spilled. glibc raises
its mmap threshold each time such a block is freed, so after the first few they come from
the heap, and the holes the churn leaves stay with the process: over the two-hour hectare
the live engine's memory crept up in steps, 3.3 MB per 1,000 frames over its second half.
``trim()`` after tiles leave memory gives the whole free pages of those holes back
(``malloc_trim`` releases interior pages since glibc 2.8). Fixing the threshold instead
(mallopt ``M_MMAP_THRESHOLD``, 1 MiB) kept the memory as flat, but mapped every FFT buffer
afresh: the live engine was 13 % slower (registration 20.0 -> 25.0 ms a frame).
Elsewhere (musl, macOS) this does nothing.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable


def _malloc_trim() -> Callable[[int], int] | None:
    try:
        function = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_size_t]
    function.restype = ctypes.c_int
    return function


_trim = _malloc_trim()


def trim() -> bool:
    """Give the allocator's free pages back to the system; whether it could."""
    return bool(_trim(0)) if _trim is not None else False


def available() -> bool:
    return _trim is not None
