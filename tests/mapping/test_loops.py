"""The loop closures' candidate search (``mapping.loops``)."""

from __future__ import annotations

import math

import numpy as np

from mapping.loops import _shared, footprint_overlap


def test_the_compiled_shares_are_the_footprint_overlaps_both_ways() -> None:
    """``_shared`` (a compiled loop over pairs) gives, pair by pair, the smaller of
    ``footprint_overlap`` (the numpy reference) taken both ways, to the bit: fans close
    enough to share some seabed, some not at all, some the same pose."""
    rng = np.random.default_rng(7)
    n = 4000
    sonar = np.column_stack(
        [rng.uniform(0, 12, n), rng.uniform(0, 12, n), rng.uniform(-math.pi, math.pi, n)]
    )
    a = rng.integers(0, n, 20000)
    b = rng.integers(0, n, 20000)
    b[:50] = a[:50]  # the same pose: the whole fan shared
    lit = (1.2, 5.0)
    half = math.radians(65.0)
    expected = np.minimum(
        footprint_overlap(sonar[a], sonar[b], lit, half),
        footprint_overlap(sonar[b], sonar[a], lit, half),
    )
    got = _shared(sonar, a, b, lit, half)
    assert np.array_equal(got, expected)
    assert np.all(got[:50] == 1.0)
    assert 0.0 < np.mean(got > 0) < 1.0  # both kinds of pair were compared
    assert _shared(sonar, a[:0], b[:0], lit, half).size == 0
