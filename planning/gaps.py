"""What a survey missed of its area: the area less the seabed seen well enough.

Frames and units: positions are metres east/north in the survey's local grid frame
(``mapping.geo.LocalFrame``), areas square metres. The seabed seen is a raster of square
cells meeting the quality bar (``mapping.coverage``: north-up, row 0 northernmost),
turned into polygons along the cells' edges (GDAL's polygonize through
``rasterio.features.shapes``, 4-connected, so the polygons are exactly the cells' union);
the gaps are the area (its holes left out) less those polygons (shapely), each part a
gap. A gap's outline follows the cells' edges: it is exact to the raster, within one cell
of what a finer raster would draw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import shapely

from planning.area import Area


@dataclass(frozen=True)
class AreaCoverage:
    """How much of an area was seen well enough: the area (m²), the part of it in the
    cells meeting the bar (m²) and the gaps of at least the smallest size asked for,
    largest first (shapely polygons, local metres)."""

    area_m2: float
    covered_m2: float
    gaps: tuple[shapely.Polygon, ...]

    @property
    def fraction(self) -> float:
        return self.covered_m2 / self.area_m2 if self.area_m2 > 0 else 0.0

    @property
    def gaps_m2(self) -> float:
        return float(sum(gap.area for gap in self.gaps))


def cells_geometry(
    cells: npt.NDArray[np.bool_], west_m: float, north_m: float, cell_m: float
) -> shapely.Geometry:
    """The union of the True cells of a north-up raster whose top-left corner is at
    (``west_m``, ``north_m``) local metres, as one (Multi)Polygon (empty when none)."""
    if not cells.any():
        return shapely.Polygon()
    # GDAL only here: planning a survey (the rest of the package) does without it.
    from rasterio.features import shapes
    from rasterio.transform import from_origin

    transform = from_origin(west_m, north_m, cell_m, cell_m)
    parts = [
        shapely.geometry.shape(geometry)
        for geometry, _ in shapes(
            cells.astype(np.uint8), mask=cells, connectivity=4, transform=transform
        )
    ]
    return shapely.union_all(parts)


def area_gaps(area: Area, covered: shapely.Geometry, min_gap_m2: float) -> AreaCoverage:
    """The area's covered part and its gaps (parts of the area outside ``covered``) of at
    least ``min_gap_m2``; smaller gaps count as uncovered but are not listed."""
    region = area.geometry
    missed = shapely.difference(region, covered)
    parts = [
        part
        for part in shapely.get_parts(missed)
        if isinstance(part, shapely.Polygon) and part.area > 0 and part.area >= min_gap_m2
    ]
    parts.sort(key=lambda part: part.area, reverse=True)
    covered_m2 = float(shapely.area(shapely.intersection(region, covered)))
    return AreaCoverage(float(shapely.area(region)), covered_m2, tuple(parts))
