"""Tiles spilled to disk come back exactly, and a new store finds those already there."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.formats.tilespill import DiskSpill, SpillError


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


def test_loaded_tiles_are_writable(tmp_path: Path) -> None:
    """The tile store updates a loaded tile's stacks in place."""
    spill = DiskSpill(tmp_path / "tiles")
    spill.save((0, 0), {"score": np.zeros((4, 4, 2), np.uint16)})
    back = spill.load((0, 0))
    assert back is not None
    back["score"][1, 1, 0] = 7
    assert back["score"][1, 1, 0] == 7


def test_a_damaged_tile_file_is_named_in_one_line(tmp_path: Path) -> None:
    spill = DiskSpill(tmp_path / "tiles")
    spill.save((1, 2), {"score": np.arange(64, dtype=np.uint16).reshape(4, 4, 4)})
    path = tmp_path / "tiles" / "tile_1_2.zst"
    path.write_bytes(path.read_bytes()[:-5])  # cut short, as a full disk might leave it
    with pytest.raises(SpillError, match=r"tile_1_2\.zst: cannot be read back"):
        spill.load((1, 2))
    # A header that parses but does not describe arrays.
    good = tmp_path / "tiles" / "tile_1_2.zst"
    spill.save((1, 2), {"score": np.zeros((2, 2), np.uint16)})
    data = good.read_bytes()
    header = b'[["score", 7, null]]'
    good.write_bytes(b"SEAMAP-TILE 1\n" + len(header).to_bytes(4, "little") + header + data[-9:])
    with pytest.raises(SpillError, match="cannot be read back"):
        spill.load((1, 2))
    path.write_bytes(b"PK\x03\x04 an old npz")
    with pytest.raises(SpillError, match="not a seamap tile"):
        spill.load((1, 2))


def test_large_blocks_are_given_back_to_the_system() -> None:
    from daemon.memory import return_large_blocks

    assert return_large_blocks()  # glibc takes the setting (CI and the boats run glibc)
