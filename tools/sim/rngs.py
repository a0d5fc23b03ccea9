"""Child generators: a stream of its own from a generator's seed, without drawing from it.

``child_rng(rng, key)`` builds a generator from ``rng``'s ``SeedSequence`` with ``key``
appended to its spawn key: independent of ``rng`` and of other keys, the same for the
same seed and key, and ``rng``'s own draws are left exactly as they were (new
components of a survey draw from children, so that existing surveys keep every byte).
"""

from __future__ import annotations

import numpy as np


def child_rng(rng: np.random.Generator, key: int) -> np.random.Generator:
    """The child generator ``key`` of ``rng``'s seed (module doc)."""
    seq = rng.bit_generator.seed_seq
    if not isinstance(seq, np.random.SeedSequence):
        raise TypeError("child_rng needs a generator made from a seed (np.random.default_rng)")
    return np.random.default_rng(
        np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, key))
    )
