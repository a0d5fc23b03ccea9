"""survey.gpkg read back without GDAL (sqlite3 and the geometry blobs decoded by hand)
holds what trajectory.csv and gaps.geojson hold, in the mosaic's UTM CRS."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely
from pyproj import Transformer

from drivers.formats.geopackage import COVERAGE_FIELDS, write_survey_gpkg
from drivers.formats.results import write_gaps, write_trajectory
from mapping.geo import LocalFrame
from tests.drivers.gpkg_reader import read_gpkg

FRAME = LocalFrame.around(-33.85, 151.21)  # south of the equator: EPSG 327xx
COVERAGE = {
    "cell_m": 0.25,
    "min_passes": 2,
    "cells_seen": 4100,
    "seen_m2": 256.25,
    "covered_m2": 190.5,
    "max_passes": 3,
    "crs": {"epsg": FRAME.epsg, "west": 0.0, "north": 0.0},
}
AREA_REPORT = {
    "file": "area.geojson",
    "area_m2": 1200.0,
    "covered_m2": 180.0,
    "covered_fraction": 0.15,
    "gaps": 2,
    "gaps_m2": 1010.5,
    "min_gap_m2": 1.0,
}


def track(n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """A curving track (local metres, grid heading in radians) with unmapped frames (7, 30, 53)."""
    t = 1_700_000_000.0 + 0.1 * np.arange(n)
    s = np.linspace(0.0, 30.0, n)
    poses = np.column_stack([s, 5.0 * np.sin(s / 10.0), np.linspace(0.1, 6.2, n)])
    poses[np.arange(n) % 23 == 7] = np.nan
    return t, poses


def area_and_gaps() -> tuple[list[shapely.Polygon], list[shapely.Polygon]]:
    outer = shapely.Polygon(
        [(-10, -10), (40, -10), (40, 14), (-10, 14)], [[(-8, -8), (-8, -5), (-5, -5), (-5, -8)]]
    )
    gaps = [
        shapely.Polygon([(-10, 6), (40, 6), (40, 14), (-10, 14)]),
        shapely.Polygon(
            [(0, -10), (20, -10), (20, -4), (0, -4)], [[(5, -8), (6, -8), (6, -7), (5, -7)]]
        ),
    ]
    return [outer], gaps


def test_the_layers_hold_the_track_poses_area_gaps_and_coverage(tmp_path: Path) -> None:
    times, poses = track()
    area, gaps = area_and_gaps()
    path = tmp_path / "survey.gpkg"
    layers = write_survey_gpkg(
        path, FRAME, times, poses, {**COVERAGE, "area": AREA_REPORT}, area, gaps
    )
    assert layers == ["track", "poses", "area", "gaps", "coverage"]
    assert [p.name for p in tmp_path.iterdir()] == ["survey.gpkg"]  # no temporary left
    read, systems = read_gpkg(path)
    assert set(read) == set(layers)
    org, org_id, definition = systems[FRAME.epsg]
    assert (org.upper(), org_id) == ("EPSG", FRAME.epsg) and "UTM zone 56S" in definition
    for name in ("track", "poses", "area", "gaps"):
        assert read[name].data_type == "features" and read[name].srs_id == FRAME.epsg
        assert read[name].description  # QGIS shows it as the layer's abstract
    assert read["coverage"].data_type == "attributes" and read["coverage"].geometry_column is None
    assert read["track"].geometry_type == "LINESTRING"
    assert read["poses"].geometry_type == "POINT"
    assert read["gaps"].geometry_type == "POLYGON"

    # poses: trajectory.csv's rows (the CSV rounds: to 1e-4 m, 1e-9 degrees, 1e-6 s).
    write_trajectory(tmp_path / "trajectory.csv", FRAME, times, poses)
    with open(tmp_path / "trajectory.csv", newline="") as stream:
        csv_rows = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(stream)]
    rows = read["poses"].rows
    assert len(rows) == len(csv_rows) == 57
    tolerance = {"time": 1e-6, "lat": 1e-9, "lon": 1e-9, "east": 1e-4, "north": 1e-4}
    for row, expected, point in zip(rows, csv_rows, read["poses"].geometries, strict=True):
        assert set(row) == {"fid", *expected}
        for name, value in expected.items():
            assert row[name] == pytest.approx(value, abs=tolerance.get(name, 1e-4)), name
        assert isinstance(point, shapely.Point)
        assert (point.x, point.y) == (row["east"], row["north"])

    # track: one line through the poses, in order.
    (line,) = read["track"].geometries
    assert isinstance(line, shapely.LineString)
    np.testing.assert_allclose(
        np.asarray(line.coords), [[r["east"], r["north"]] for r in rows], atol=1e-9
    )
    (summary,) = read["track"].rows
    assert summary["poses"] == 57
    assert summary["start_time"] == rows[0]["time"] and summary["end_time"] == rows[-1]["time"]
    assert summary["length_m"] == pytest.approx(line.length)

    # gaps: gaps.geojson's polygons (WGS84 there, UTM here), ids and areas.
    write_gaps(tmp_path / "gaps.geojson", tuple(gaps), FRAME)
    features = json.loads((tmp_path / "gaps.geojson").read_text())["features"]
    to_utm = Transformer.from_crs(4326, FRAME.epsg, always_xy=True)
    assert len(read["gaps"].rows) == len(features) == 2
    for row, polygon, feature in zip(read["gaps"].rows, read["gaps"].geometries, features,
                                     strict=True):  # fmt: skip
        assert row["id"] == feature["properties"]["id"]
        assert row["area_m2"] == feature["properties"]["area_m2"]
        projected = shapely.transform(
            shapely.geometry.shape(feature["geometry"]),
            lambda lonlat: np.column_stack(to_utm.transform(lonlat[:, 0], lonlat[:, 1])),
        )
        assert shapely.hausdorff_distance(polygon, projected) < 2e-3  # geojson's 1e-8 degrees
        assert isinstance(polygon, shapely.Polygon) and isinstance(projected, shapely.Polygon)
        assert len(polygon.interiors) == len(projected.interiors)

    # area: the polygon with its hole, in UTM.
    (outline,) = read["area"].geometries
    assert isinstance(outline, shapely.Polygon)
    utm_area = shapely.transform(
        area[0], lambda xy: xy + np.array([FRAME.anchor_e, FRAME.anchor_n])
    )
    assert outline.equals(utm_area) and len(outline.interiors) == 1
    assert read["area"].rows[0]["area_m2"] == pytest.approx(area[0].area, abs=1e-3)

    # coverage: report.json's numbers in one row.
    (row,) = read["coverage"].rows
    assert row["covered_fraction"] == 0.15 and row["gaps"] == 2 and row["min_passes"] == 2
    assert row["area_covered_m2"] == 180.0 and row["covered_m2"] == 190.5
    assert set(row) == {"fid", *COVERAGE_FIELDS}


def test_without_an_area_there_are_no_area_nor_gaps_layers(tmp_path: Path) -> None:
    times, poses = track(3)
    path = tmp_path / "survey.gpkg"
    path.write_bytes(b"an older file")
    assert write_survey_gpkg(path, FRAME, times, poses, COVERAGE) == ["track", "poses", "coverage"]
    read, _ = read_gpkg(path)
    assert set(read) == {"track", "poses", "coverage"}
    assert len(read["poses"].rows) == 3
    (row,) = read["coverage"].rows
    assert row["covered_fraction"] is None and row["gaps"] is None  # NULL: not known
    assert row["cells_seen"] == 4100


def test_one_pose_makes_no_line_and_no_gaps_an_empty_layer(tmp_path: Path) -> None:
    times, poses = track(1)
    area, _ = area_and_gaps()
    path = tmp_path / "survey.gpkg"
    write_survey_gpkg(path, FRAME, times, poses, COVERAGE, area, gaps=[])
    read, _ = read_gpkg(path)
    assert read["track"].rows == [] and len(read["poses"].rows) == 1
    assert read["gaps"].rows == [] and read["gaps"].srs_id == FRAME.epsg


def test_a_folder_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    times, poses = track(4)
    with pytest.raises(OSError, match=r"missing/survey\.gpkg: cannot write") as info:
        write_survey_gpkg(tmp_path / "missing" / "survey.gpkg", FRAME, times, poses, COVERAGE)
    assert "\n" not in str(info.value)


COEXIST = """
import sys
from pathlib import Path
import numpy as np
first = sys.argv[2]
if first == "pyogrio":
    import pyogrio, rasterio
else:
    import rasterio, pyogrio
from drivers.formats.geopackage import write_survey_gpkg
from drivers.formats.results import write_geotiff
from mapping.geo import LocalFrame
out = Path(sys.argv[1])
frame = LocalFrame.around(59.9, 10.7)
poses = np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)])
write_geotiff(out / "mosaic.tif", np.full((600, 600), 9, np.uint8), 1e5, 7e6, 0.1, frame.epsg)
write_survey_gpkg(out / "survey.gpkg", frame, np.arange(5.0), poses, {"cell_m": 0.25})
with rasterio.open(out / "mosaic.tif") as dataset:
    assert dataset.crs.to_epsg() == frame.epsg and dataset.overviews(1) == [2]
info = pyogrio.read_info(out / "survey.gpkg", layer="poses")
assert info["crs"] == f"EPSG:{frame.epsg}" and info["features"] == 5, info
print("ok")
"""


@pytest.mark.parametrize("first", ["pyogrio", "rasterio"])
def test_pyogrio_and_rasterio_share_a_process(tmp_path: Path, first: str) -> None:
    """Both wheels bundle their own GDAL and PROJ: either imported first, each writes and
    reads its file with the right CRS."""
    done = subprocess.run(
        [sys.executable, "-c", COEXIST, str(tmp_path), first],
        capture_output=True, text=True, timeout=120, cwd=Path(__file__).parents[2],
    )  # fmt: skip
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
