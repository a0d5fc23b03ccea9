"""Tiles spilled to disk come back exactly, and a new store finds those already there."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seamap.tilespill import DiskSpill


def test_tiles_round_trip_through_disk(tmp_path: Path) -> None:
    spill = DiskSpill(tmp_path / "tiles")
    rng = np.random.default_rng(1)
    arrays: dict[str, np.ndarray] = {
        "intensity": rng.integers(0, 255, (16, 8, 8), dtype=np.uint8),
        "score": rng.integers(0, 65535, (16, 8, 8), dtype=np.uint16),
        "frame": rng.integers(0, 65535, (16, 8, 8), dtype=np.uint16),
        "rendered": rng.integers(0, 255, (8, 8), dtype=np.uint8),
    }
    spill.save((3, -2), arrays)
    assert spill.load((0, 0)) is None
    back = spill.load((3, -2))
    assert back is not None
    for name, value in arrays.items():
        np.testing.assert_array_equal(back[name], value)
        assert back[name].dtype == value.dtype
    again = DiskSpill(tmp_path / "tiles")
    assert list(again.keys()) == [(3, -2)]
    assert not list((tmp_path / "tiles").glob(".*tmp"))
