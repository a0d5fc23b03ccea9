"""mosaic.tif and coverage.tif are Cloud-Optimized GeoTIFFs: GDAL opens them as COG, an
independent TIFF reader finds the layout a range reader relies on, the overviews reach one
tile and hold the right pixels, and every property of the contract stays."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
import rasterio
import tifffile

from drivers.formats.results import (
    COG_BLOCK_PX,
    COVERAGE_BANDS,
    read_coverage_tif,
    write_coverage_tif,
    write_geotiff,
)
from mapping.coverage import CoverageGrid

EPSG = 32632
WEST, NORTH, RES_M = 512_000.0, 6_102_000.0, 0.05


def mosaic(rows: int, cols: int, seed: int = 1) -> npt.NDArray[np.uint8]:
    """Random intensities 1..255 with a no-data border and no-data holes inside."""
    rng = np.random.default_rng(seed)
    image = rng.integers(1, 256, (rows, cols)).astype(np.uint8)
    image[rng.random((rows, cols)) < 0.2] = 0
    image[: rows // 7] = 0
    image[:, cols - cols // 5 :] = 0
    return image


def halved(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """Each pixel the mean of the 2 x 2 block below it over the pixels holding data
    (rounded half up), 0 where none does: what an overview of the mosaic must hold."""
    rows, cols = image.shape[0] // 2, image.shape[1] // 2
    blocks = image[: 2 * rows, : 2 * cols].reshape(rows, 2, cols, 2).astype(np.int64)
    valid = np.count_nonzero(blocks, axis=(1, 3))
    total = blocks.sum(axis=(1, 3))
    mean = np.floor(total / np.maximum(valid, 1) + 0.5)
    return np.where(valid > 0, mean, 0).astype(np.uint8)


def check_cog_layout(path: Path) -> list[tuple[int, ...]]:
    """The COG layout read with tifffile, not GDAL: GDAL's ghost header at the start, the
    IFDs of the full image then of the overviews in decreasing size, every IFD before the
    first tile, and the smaller overviews' tiles before the bigger ones (a reader gets a
    coarse view from the first ranges). Returns the levels' shapes."""
    assert path.read_bytes()[8:38] == b"GDAL_STRUCTURAL_METADATA_SIZE="
    with tifffile.TiffFile(path) as tif:
        pages = [page for page in tif.pages if isinstance(page, tifffile.TiffPage)]
        assert len(pages) == len(tif.pages)
        shapes = [page.shape for page in pages]
        ifds = [page.offset for page in pages]
        tiles = [
            [offset for offset, size in zip(page.dataoffsets, page.databytecounts, strict=True)
             if size > 0]
            for page in pages
        ]  # fmt: skip
        assert all(page.is_tiled for page in pages)
        assert all(page.tilewidth == page.tilelength == COG_BLOCK_PX for page in pages)
        assert all(page.tags["NewSubfileType"].value == 1 for page in pages[1:])
    assert ifds == sorted(ifds)
    sizes = [shape[0] * shape[1] for shape in shapes]
    assert sizes == sorted(sizes, reverse=True) and len(set(sizes)) == len(sizes)
    first_tile = min(offset for level in tiles for offset in level)
    assert max(ifds) < first_tile
    for bigger, smaller in itertools.pairwise(tiles):
        assert max(smaller) < min(bigger)
    return shapes


def test_the_mosaic_is_a_cog_with_overviews_of_means_over_data(tmp_path: Path) -> None:
    image = mosaic(1200, 1600)
    path = tmp_path / "mosaic.tif"
    write_geotiff(path, image, WEST, NORTH, RES_M, EPSG)
    with rasterio.open(path) as dataset:
        assert dataset.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert dataset.tags(ns="IMAGE_STRUCTURE")["COMPRESSION"] == "DEFLATE"
        assert (dataset.count, dataset.dtypes, dataset.nodata) == (1, ("uint8",), 0)
        assert dataset.crs.to_epsg() == EPSG
        assert tuple(dataset.transform)[:6] == (RES_M, 0.0, WEST, 0.0, -RES_M, NORTH)
        np.testing.assert_array_equal(dataset.read(1), image)
        factors = dataset.overviews(1)
    assert factors == [2, 4]  # 1600 -> 800 -> 400: the last fits in a 512 px tile
    assert max(image.shape) // factors[-1] <= COG_BLOCK_PX
    expected = image
    for level, factor in enumerate(factors):
        expected = halved(expected)
        with rasterio.open(path, overview_level=level) as overview:
            assert overview.shape == (image.shape[0] // factor, image.shape[1] // factor)
            np.testing.assert_array_equal(overview.read(1), expected)
    # No data stays no data, and no mean over data is dark as no data.
    assert np.all(halved(image)[: 1200 // 14] == 0)
    shapes = check_cog_layout(path)
    assert shapes == [(1200, 1600), (600, 800), (300, 400)]
    assert not list(tmp_path.glob(".*"))  # the temporary files went


def test_a_mosaic_smaller_than_a_tile_is_a_cog_without_overviews(tmp_path: Path) -> None:
    image = mosaic(90, 200, seed=2)
    path = tmp_path / "mosaic.tif"
    write_geotiff(path, image, WEST, NORTH, RES_M, EPSG)
    with rasterio.open(path) as dataset:
        assert dataset.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert dataset.overviews(1) == []
        assert dataset.nodata == 0 and dataset.crs.to_epsg() == EPSG
        np.testing.assert_array_equal(dataset.read(1), image)
    assert check_cog_layout(path) == [(90, 200)]


def test_rewriting_replaces_the_file_whole(tmp_path: Path) -> None:
    path = tmp_path / "mosaic.tif"
    write_geotiff(path, mosaic(700, 600), WEST, NORTH, RES_M, EPSG)
    second = mosaic(300, 200, seed=3)
    write_geotiff(path, second, WEST, NORTH, RES_M, EPSG)
    with rasterio.open(path) as dataset:
        np.testing.assert_array_equal(dataset.read(1), second)
        assert dataset.overviews(1) == []
    assert [p.name for p in tmp_path.iterdir()] == ["mosaic.tif"]


def test_coverage_is_a_cog_whose_overviews_keep_real_cells(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    passes = rng.integers(0, 5, (1100, 700)).astype(np.uint16)
    hits = (passes * rng.integers(1, 30, passes.shape)).astype(np.uint16)
    grid = CoverageGrid(passes, hits, WEST, NORTH, 0.25)
    path = tmp_path / "coverage.tif"
    write_coverage_tif(path, grid, EPSG, min_passes=2)
    with rasterio.open(path) as dataset:
        assert dataset.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert dataset.descriptions == COVERAGE_BANDS
        assert dataset.tags()["min_passes"] == "2" and dataset.tags()["cell_m"] == "0.25"
        assert dataset.dtypes == ("uint16",) * 3 and dataset.nodata is None
        np.testing.assert_array_equal(dataset.read(1), passes)
        np.testing.assert_array_equal(dataset.read(2), hits)
        factors = dataset.overviews(1)
    assert factors and max(passes.shape) // factors[-1] <= COG_BLOCK_PX
    with rasterio.open(path, overview_level=0) as overview:
        bands = overview.read()
    # Nearest: each overview cell is one real cell (one of its block of four), all
    # three bands the same cell, and the flag stays a flag.
    rows, cols = bands.shape[1:]
    blocks = passes[: 2 * rows, : 2 * cols].reshape(rows, 2, cols, 2)
    picked = [
        (dy, dx) for dy in (0, 1) for dx in (0, 1)
        if np.array_equal(bands[0], blocks[:, dy, :, dx])
    ]  # fmt: skip
    assert len(picked) == 1
    dy, dx = picked[0]
    np.testing.assert_array_equal(bands[1], hits[dy::2, dx::2][:rows, :cols])
    np.testing.assert_array_equal(bands[2], bands[0] >= 2)
    check_cog_layout(path)
    raster = read_coverage_tif(path)
    np.testing.assert_array_equal(raster.meets_bar, passes >= 2)
    assert (raster.epsg, raster.cell_m, raster.min_passes) == (EPSG, 0.25, 2)


def test_an_empty_coverage_is_still_one_readable_cell(tmp_path: Path) -> None:
    empty = np.zeros((0, 0), np.uint16)
    path = tmp_path / "coverage.tif"
    write_coverage_tif(path, CoverageGrid(empty, empty, WEST, NORTH, 0.25), EPSG, 1)
    with rasterio.open(path) as dataset:
        assert dataset.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert dataset.shape == (1, 1)
    assert not read_coverage_tif(path).meets_bar.any()


def test_a_folder_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    folder = tmp_path / "gone"
    with pytest.raises(OSError, match=r"gone/mosaic\.tif: cannot write the GeoTIFF") as info:
        write_geotiff(folder / "mosaic.tif", mosaic(40, 40), WEST, NORTH, RES_M, EPSG)
    assert "\n" not in str(info.value)
