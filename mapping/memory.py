"""Tile stacks in mappings of their own, given back to the system when a tile leaves.

The tiles' stacks (1-2 MB each) come and go as tiles are loaded and spilled. glibc raises
its mmap threshold each time such a block is freed, so after the first few they came from
the heap, and the holes the churn left stayed with the process: over the two-hour hectare
the live engine's memory crept up in steps, 3.3 MB per 1,000 frames over its second half.
A tile's stacks are therefore anonymous mappings of their own (``mapped``), unmapped when
the tile is freed. Alternatives measured on the hectare's first 6,000 frames, side by side:

- fixing glibc's threshold (mallopt ``M_MMAP_THRESHOLD`` 1 MiB): memory flat (959 MB at the
  end), but every FFT buffer mapped afresh: 49.5 ms a frame against 46.5 (13 % slower
  side by side on quadrats: registration 20.0 -> 25.0 ms);
- ``malloc_trim`` after tiles leave: as fast, but 1,026 MB at the end: nothing gained.
"""

from __future__ import annotations

import mmap

import numpy as np
import numpy.typing as npt


def mapped(shape: tuple[int, ...], dtype: npt.DTypeLike, fill: int = 0) -> npt.NDArray[np.generic]:
    """A writable array of ``shape`` in an anonymous mapping of its own (zeros, or
    ``fill``), unmapped when the array and its views are freed."""
    count = int(np.prod(shape))
    itemsize = np.dtype(dtype).itemsize
    buffer = mmap.mmap(-1, max(count * itemsize, 1))
    array = np.frombuffer(buffer, dtype, count).reshape(shape)
    if fill:
        array.fill(fill)
    return array
