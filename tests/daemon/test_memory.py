"""The allocator's settings (``daemon.memory``): what each costs in page faults, counted
by the kernel in a fresh process (not timed)."""

from __future__ import annotations

import subprocess
import sys

import pytest

CHURN = """
import resource, sys
import numpy as np
from daemon.memory import keep_heap, return_large_blocks
took = {setting}()
buffer = np.ones(1)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):
    buffer = np.ones(2 << 17)  # 2 MiB, as an FFT's buffer: freed and asked for again
    del buffer
print(int(took), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(setting: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", CHURN.format(setting=setting)],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    took, faults = (int(v) for v in done.stdout.split())
    if not took:
        pytest.skip("not glibc: the allocator's settings do nothing here")
    return faults


def test_a_worker_keeps_its_buffers_where_the_engine_gives_them_back() -> None:
    mapped = _faults("return_large_blocks")  # the engine's: tiles' stacks go back
    kept = _faults("keep_heap")  # a worker's: the same buffers again and again
    # Mapped afresh each time: 512 pages zeroed per buffer; kept: touched once.
    assert mapped > 200 * 400
    assert kept < mapped / 20
