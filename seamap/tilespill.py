"""Tiles the boat has left, kept on disk (``mapping.tiles.TileSpill``).

One compressed ``.npz`` a tile in a folder, written to a temporary name and renamed, so a
crash never leaves half a tile; a spilled tile that comes back into memory is read and
its file kept until the next spill overwrites it. The fastest deflate level: a tile's
candidate stacks are mostly empty slots, so it packs them as small as the default level
(2.4 MB of 5.3) in half the time, and spilling runs on the mapping thread.
"""

from __future__ import annotations

import os
import re
import zipfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from mapping.mosaic import TileKey

_NAME = re.compile(r"^tile_(-?\d+)_(-?\d+)\.npz$")
COMPRESS_LEVEL = 1


class DiskSpill:
    """Spilled tiles as ``folder/tile_{col}_{row}.npz``."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._keys: set[TileKey] = set()
        for entry in self.folder.iterdir():
            match = _NAME.match(entry.name)
            if match:
                self._keys.add((int(match[1]), int(match[2])))
        self.bytes_written = 0

    def _path(self, key: TileKey) -> Path:
        return self.folder / f"tile_{key[0]}_{key[1]}.npz"

    def save(self, key: TileKey, arrays: dict[str, npt.NDArray[np.generic]]) -> None:
        path = self._path(key)
        tmp = path.with_name(f".{path.name}.tmp")
        with zipfile.ZipFile(
            tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=COMPRESS_LEVEL
        ) as archive:
            for name, values in arrays.items():  # the layout np.savez writes
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(values), allow_pickle=False)
        os.replace(tmp, path)
        self.bytes_written += path.stat().st_size
        self._keys.add(key)

    def load(self, key: TileKey) -> dict[str, npt.NDArray[np.generic]] | None:
        if key not in self._keys:
            return None
        with np.load(self._path(key)) as data:
            return {name: data[name] for name in data.files}

    def keys(self) -> Iterable[TileKey]:
        return sorted(self._keys)
