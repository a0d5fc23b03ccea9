"""End to end: a simulated survey replayed into a georeferenced mosaic whose quadrats lie
where the truth puts them."""

from __future__ import annotations

import csv
import json
import struct
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
import shapely
from pyproj import Transformer

from drivers.oculus import iter_log_items
from seamap.cli import main
from tests.drivers.gpkg_reader import read_gpkg
from tools.evaluation.metrics import locate_quadrats, quadrat_spacing_error
from tools.evaluation.truth import quadrats_of
from tools.sim import simulate


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("survey")
    simulate("quadrats", 2, folder, max_pings=220, n_beams=256)
    write_area(folder)
    return folder


AREA_MARGIN_M = 8.0
"""The area reaches this far beyond the sonar's track: wider than the fan sees (4.5 m)."""


def write_area(folder: Path) -> None:
    """area.geojson: the rectangle (grid-aligned in UTM) round the sonar's true track,
    ``AREA_MARGIN_M`` wider on every side, with a keep-out hole near one corner."""
    truth = json.loads((folder / "truth.json").read_text())
    east = np.array([p["sonar_east"] for p in truth["pings"]])
    north = np.array([p["sonar_north"] for p in truth["pings"]])
    w, s = east.min() - AREA_MARGIN_M, north.min() - AREA_MARGIN_M
    e, n = east.max() + AREA_MARGIN_M, north.max() + AREA_MARGIN_M
    to_wgs84 = Transformer.from_crs(truth["site"]["epsg"], 4326, always_xy=True)

    def ring(points: list[tuple[float, float]]) -> list[list[float]]:
        lon, lat = to_wgs84.transform(*np.array(points + points[:1]).T)
        return np.column_stack([lon, lat]).tolist()

    outer = ring([(w, s), (e, s), (e, n), (w, n)])
    hole = ring([(w + 1, s + 1), (w + 1, s + 3), (w + 3, s + 3), (w + 3, s + 1)])
    geometry = {"type": "Polygon", "coordinates": [outer, hole]}
    (folder / "area.geojson").write_text(json.dumps({"type": "Feature", "geometry": geometry}))


@pytest.fixture(scope="module")
def result(survey: Path) -> Path:
    out = survey / "result"
    status = main(
        [
            "replay",
            "--sonar", str(survey / "sonar.oculus"),
            "--nav", str(survey / "nav.tlog"),
            "--config", str(survey / "site.toml"),
            "--out", str(out),
            "--truth", str(survey / "truth.json"),
            "--area", str(survey / "area.geojson"),
        ]
    )  # fmt: skip
    assert status == 0
    return out


def test_result_folder_follows_the_contract(survey: Path, result: Path) -> None:
    truth = json.loads((survey / "truth.json").read_text())
    with rasterio.open(result / "mosaic.tif") as mosaic:
        assert mosaic.count == 1 and mosaic.dtypes[0] == "uint8"
        assert mosaic.crs.to_epsg() == truth["site"]["epsg"]
        assert mosaic.nodata == 0
        t = mosaic.transform
        assert t.b == 0 and t.d == 0 and t.a == -t.e > 0  # north-up, square pixels
        image = mosaic.read(1)
    assert (image > 0).mean() > 0.3
    assert (result / "mosaic.png").stat().st_size > 1000
    with (result / "trajectory.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    assert list(rows[0]) == ["time", "lat", "lon", "east", "north", "heading_deg"]
    report = json.loads((result / "report.json").read_text())
    assert len(rows) == report["frames"]["mapped"] > 200
    first = truth["pings"][0]
    assert float(rows[0]["time"]) == pytest.approx(first["time"], abs=1e-6)
    assert 0 <= float(rows[0]["heading_deg"]) < 360
    for key in ("read", "mapped", "rejected"):
        assert key in report["frames"]
    for stage in ("preprocess", "registration", "ekf", "optimisation", "blending", "total"):
        assert stage in report["timings_s"]


def test_survey_gpkg_holds_the_track_area_gaps_and_coverage(result: Path) -> None:
    """survey.gpkg read without GDAL: its poses are trajectory.csv's rows, its track runs
    through them, its gaps are gaps.geojson's, all in the mosaic's CRS."""
    report = json.loads((result / "report.json").read_text())
    assert report["files"][-2:] == ["survey.gpkg", "report.json"]
    layers, systems = read_gpkg(result / "survey.gpkg")
    assert set(layers) == {"track", "poses", "area", "gaps", "coverage"}
    with rasterio.open(result / "mosaic.tif") as mosaic:
        epsg = mosaic.crs.to_epsg()
        assert mosaic.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
    assert systems[epsg][1] == epsg
    assert all(layers[name].srs_id == epsg for name in ("track", "poses", "area", "gaps"))
    with (result / "trajectory.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    poses = layers["poses"].rows
    assert len(poses) == len(rows) == report["frames"]["mapped"]
    for pose, row in zip(poses, rows, strict=True):
        assert pose["time"] == pytest.approx(float(row["time"]), abs=1e-6)
        assert pose["east"] == pytest.approx(float(row["east"]), abs=1e-4)
        assert pose["north"] == pytest.approx(float(row["north"]), abs=1e-4)
        assert pose["heading_deg"] == pytest.approx(float(row["heading_deg"]), abs=1e-4)
    (line,) = layers["track"].geometries
    assert isinstance(line, shapely.LineString) and len(line.coords) == len(rows)
    gaps = json.loads((result / "gaps.geojson").read_text())["features"]
    assert [g["id"] for g in layers["gaps"].rows] == [f["id"] for f in gaps]
    to_wgs84 = Transformer.from_crs(epsg, 4326, always_xy=True)
    for polygon, feature in zip(layers["gaps"].geometries, gaps, strict=True):
        lonlat = shapely.transform(
            polygon, lambda en: np.column_stack(to_wgs84.transform(en[:, 0], en[:, 1]))
        )
        # geojson rounds to 1e-8 degrees: a millimetre.
        assert (
            shapely.hausdorff_distance(lonlat, shapely.geometry.shape(feature["geometry"])) < 1e-7
        )
    (outline,) = layers["area"].geometries
    area = report["coverage"]["area"]
    assert shapely.area(outline) == pytest.approx(area["area_m2"], rel=1e-6)
    # The lane and the gaps lie in the area.
    assert shapely.buffer(outline, 1e-6).contains(shapely.union_all(layers["gaps"].geometries))
    (summary,) = layers["coverage"].rows
    assert summary["covered_fraction"] == area["covered_fraction"]
    assert summary["covered_m2"] == report["coverage"]["covered_m2"]
    assert summary["gaps"] == len(gaps)


def _rigid_fit(true: np.ndarray, found: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation (radians) and residuals (n, 2) of the 2-D rigid transform that best takes
    the true points onto the found ones (least squares, Kabsch)."""
    a, b = true - true.mean(axis=0), found - found.mean(axis=0)
    angle = float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)))
    c, s = np.cos(angle), np.sin(angle)
    rotated = a @ np.array([[c, s], [-s, c]])
    return angle, b - rotated


def test_quadrats_lie_where_the_truth_puts_them(survey: Path, result: Path) -> None:
    truth = json.loads((survey / "truth.json").read_text())
    quadrats = quadrats_of(truth)
    with rasterio.open(result / "mosaic.tif") as mosaic:
        image = mosaic.read(1)
        t = mosaic.transform
    found = locate_quadrats(image / 255.0, image > 0, t.c, t.f, t.a, quadrats)
    located = [(q, f) for q, f in zip(quadrats, found, strict=True) if f is not None]
    assert len(located) >= 4
    # Georeferenced by a GPS with a metre of bias: within a few metres.
    offsets = np.array([(f[0] - q.east, f[1] - q.north) for q, f in located])
    assert np.all(np.linalg.norm(offsets, axis=1) < 3.0)
    # A 44-second lane cannot tell a magnetic compass's misalignment from a heading
    # better than a few degrees (the GNSS track wanders by a metre over it): the map may
    # turn as a whole, a few degrees, but its geometry holds: the quadrats sit where one
    # rigid transform of the truth puts them, to a few centimetres.
    angle, residuals = _rigid_fit(
        np.array([(q.east, q.north) for q, _ in located]), np.array([f[:2] for _, f in located])
    )
    assert abs(np.degrees(angle)) < 10.0
    assert float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) < 0.05
    spacing = quadrat_spacing_error(quadrats, found)
    assert spacing["rmse"] < 0.05


def test_bad_inputs_end_in_one_line(
    tmp_path: Path, survey: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    junk = tmp_path / "junk.tlog"
    junk.write_text("not a log\n")
    args = [
        "replay",
        "--sonar",
        str(survey / "sonar.oculus"),
        "--nav",
        str(junk),
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "junk.tlog" in err[0]
    args = [
        "replay",
        "--sonar",
        str(junk),
        "--nav",
        str(survey / "nav.tlog"),
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "junk.tlog" in err[0]


def test_coverage_is_on_the_mosaics_grid_where_the_mosaic_is(result: Path) -> None:
    report = json.loads((result / "report.json").read_text())
    coverage = report["coverage"]
    with rasterio.open(result / "mosaic.tif") as mosaic:
        epsg, image, m = mosaic.crs.to_epsg(), mosaic.read(1), mosaic.transform
    with rasterio.open(result / "coverage.tif") as raster:
        assert raster.count == 3 and set(raster.dtypes) == {"uint16"}
        assert raster.crs.to_epsg() == epsg
        assert raster.descriptions == ("passes", "hits", "meets_bar")
        t = raster.transform
        passes, hits, bar = raster.read()
    cell = coverage["cell_m"]
    assert t.b == 0 and t.d == 0 and t.a == -t.e == cell == 0.25  # north-up, square
    for edge in (t.c, t.f):  # on the UTM grid of the cell size
        assert edge / cell == pytest.approx(round(edge / cell), abs=1e-6)
    assert np.array_equal(bar, passes >= coverage["min_passes"])
    assert np.all(hits >= passes)
    # report.json rounds areas to 3 decimals (164.5625 m^2 is written 164.562).
    assert coverage["covered_m2"] == pytest.approx(bar.sum() * cell**2, abs=5e-4)
    # One lane of 44 s: a single pass, a swath about 8.7 m wide and 20 m long.
    assert passes.max() == 1 and 100 < coverage["covered_m2"] < 400
    # Where the coverage says seen, the mosaic holds data.
    rows, cols = np.nonzero(bar)
    east, north = t.c + (cols + 0.5) * cell, t.f - (rows + 0.5) * cell
    u = np.floor((east - m.c) / m.a).astype(int)
    v = np.floor((north - m.f) / m.e).astype(int)
    inside = (u >= 0) & (u < image.shape[1]) & (v >= 0) & (v < image.shape[0])
    assert inside.mean() > 0.99
    assert (image[v[inside], u[inside]] > 0).mean() > 0.95
    assert (result / "coverage.png").stat().st_size > 100
    for name in ("coverage.tif", "coverage.png", "gaps.geojson", "mosaic.tif"):
        assert name in report["files"] and (result / name).exists()


def test_the_areas_gaps_are_what_the_lane_left(survey: Path, result: Path) -> None:
    report = json.loads((result / "report.json").read_text())
    area = report["coverage"]["area"]
    gaps = json.loads((result / "gaps.geojson").read_text())
    assert gaps["type"] == "FeatureCollection"
    features = gaps["features"]
    assert len(features) == area["gaps"] >= 1
    assert [f["properties"]["id"] for f in features] == list(range(1, len(features) + 1))
    sizes = [f["properties"]["area_m2"] for f in features]
    assert sizes == sorted(sizes, reverse=True) and min(sizes) >= 1.0
    assert sum(sizes) == pytest.approx(area["gaps_m2"], abs=0.01 * len(sizes))
    outline = json.loads((survey / "area.geojson").read_text())["geometry"]
    region = shapely.geometry.shape(outline)
    keepout = shapely.Polygon(outline["coordinates"][1])
    polygons = [shapely.geometry.shape(f["geometry"]) for f in features]
    islands = []
    for polygon in polygons:
        assert isinstance(polygon, shapely.Polygon)
        assert polygon.is_valid and polygon.exterior.is_ccw  # RFC 7946's right-hand rule
        assert not any(ring.is_ccw for ring in polygon.interiors)
        assert region.buffer(1e-7).contains(polygon)  # lon/lat, inside the area
        # The keep-out near the corner is not a gap: the gap goes round it (to a millimetre).
        assert shapely.area(shapely.intersection(polygon, keepout)) < 1e-3 * keepout.area
        islands += [
            ring
            for ring in polygon.interiors
            if not keepout.buffer(1e-7).contains(shapely.Polygon(ring))
        ]
    # The lane's swath lies inside the area: an island in the one gap round it.
    assert len(islands) == 1
    # The area is the track's rectangle 8 m wider on every side: the lane sees its middle.
    assert 0.05 < area["covered_fraction"] < 0.6
    assert area["covered_m2"] + area["gaps_m2"] == pytest.approx(area["area_m2"], rel=0.02)
    assert area["covered_m2"] <= report["coverage"]["covered_m2"] + 1e-6


@pytest.mark.parametrize(
    ("setting", "fragment"),
    [
        ("[coverage]\ncell_m = 0\n", "[coverage] cell_m = 0 is outside 0.05..5"),
        ("[coverage]\nmin_grazing_deg = -1\n", "[coverage] min_grazing_deg = -1 is outside"),
        ("[coverage]\nmin_range_m = 3\nmax_range_m = 2\n", "min_range_m = 3 is not below"),
    ],
)
def test_a_bad_coverage_setting_ends_in_one_line(
    tmp_path: Path, survey: Path, capsys: pytest.CaptureFixture[str], setting: str, fragment: str
) -> None:
    site = tmp_path / "site.toml"
    site.write_text(setting)
    args = ["replay", "--sonar", str(survey / "sonar.oculus"), "--nav", str(survey / "nav.tlog"),
            "--config", str(site), "--out", str(tmp_path / "o")]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and fragment in err[0] and str(site) in err[0]
    assert not (tmp_path / "o").exists()


def test_a_bad_area_ends_in_one_line_before_mapping(
    tmp_path: Path, survey: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    area = tmp_path / "area.geojson"
    area.write_text('{"type": "Point", "coordinates": [5.9, 43.1]}')
    args = ["replay", "--sonar", str(survey / "sonar.oculus"), "--nav", str(survey / "nav.tlog"),
            "--area", str(area), "--out", str(tmp_path / "o")]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "area.geojson" in err[0] and "no polygon" in err[0]
    assert not (tmp_path / "o").exists()


# --- a downward echosounder -----------------------------------------------------------------

ECHOSOUNDER_TOML = """
[echosounder]
use = {use}
mount_x_m = 0.4
mount_y_m = -0.1
mount_z_m = 0.35
"""


def site_with_echosounder(survey: Path, path: Path, *, use: bool = True) -> Path:
    """The survey's site.toml with the echosounder's table set (mount 0.4, -0.1, 0.35 m)."""
    text = (survey / "site.toml").read_text()
    start = text.find("[echosounder]")
    if start >= 0:  # drop the simulator's own table
        end = text.find("\n[", start + 1)
        text = text[:start] + text[end + 1 :]
    path.write_text(text + ECHOSOUNDER_TOML.format(use=str(use).lower()))
    return path


def nav_with_soundings(survey: Path, path: Path) -> tuple[Path, list[float]]:
    """The survey's nav.tlog with what ArduPilot sends for a downward echosounder at 10 Hz
    (DISTANCE_SENSOR and RANGEFINDER of the same sensor, from the autopilot), recorded
    among the rest; the tlog and the distances (m) sent."""
    from pymavlink.dialects.v20 import all as mavlink

    from drivers.mavlink.framing import ScanTally, open_log, scan_tlog

    with open_log(survey / "nav.tlog") as (_, buf):
        records = [(t, bytes(msg.get_msgbuf())) for t, msg in scan_tlog(buf, ScanTally())]
    sender = mavlink.MAVLink(None, 1, 1)
    first, last = records[0][0], records[-1][0]
    distances: list[float] = []
    for k in range(int((last - first) * 10)):
        t = first + 0.05 + 0.1 * k
        cm = 90 + k % 40
        distances.append(cm / 100)
        for msg in (
            mavlink.MAVLink_distance_sensor_message(
                k * 100, 30, 5000, cm, 1, 0, 25, 4, 0.5, 0.5, (0, 0, 0, 0), 90
            ),
            mavlink.MAVLink_rangefinder_message(cm / 100, 1.2),
        ):
            records.append((t, bytes(msg.pack(sender))))
            sender.seq = (sender.seq + 1) % 256
    records.sort(key=lambda record: record[0])
    path.write_bytes(b"".join(struct.pack(">Q", round(t * 1e6)) + frame for t, frame in records))
    return path, distances


def test_replay_gets_the_soundings_and_the_echosounders_mount(survey: Path, tmp_path: Path) -> None:
    from daemon.config import load_config
    from daemon.replay import pipeline_params, read_navigation
    from mapping.bottom import BottomParams, EchosounderMount

    nav, distances = nav_with_soundings(survey, tmp_path / "nav.tlog")
    config = load_config(site_with_echosounder(survey, tmp_path / "site.toml"))
    samples, info = read_navigation(nav, config)
    # DISTANCE_SENSOR only: ArduPilot's RANGEFINDER repeats it.
    assert [s.distance_m for s in samples.ranges] == distances
    assert {s.source for s in samples.ranges} == {"DISTANCE_SENSOR"}
    assert (info["soundings"], info["soundings_source"]) == (len(distances), "DISTANCE_SENSOR")
    assert len(samples.imu) > 2000 and len(samples.gnss) == 91  # the rest as before

    bottom = pipeline_params(config).bottom
    assert bottom == BottomParams(
        use_echosounder=True,
        echosounder=EchosounderMount(forward_m=0.4, starboard_m=-0.1, down_m=0.35),
    )
    off = load_config(site_with_echosounder(survey, tmp_path / "off.toml", use=False))
    assert pipeline_params(off).bottom.use_echosounder is False


def test_the_streaming_engines_survey_end_pass_gets_the_soundings(
    survey: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Soundings fed to the live engine with the rest reach its survey-end pass (the
    daemon's), as replay's own NavSamples do."""
    import itertools

    import mapping.streaming
    from daemon.config import load_config
    from daemon.replay import (
        mount_from_config,
        ping_source,
        pipeline_params,
        read_navigation,
        stream_survey,
    )

    nav, distances = nav_with_soundings(survey, tmp_path / "nav.tlog")
    config = load_config(site_with_echosounder(survey, tmp_path / "site.toml"))
    samples, _ = read_navigation(nav, config)
    every_ping = ping_source(survey / "sonar.oculus", {})

    def pings() -> Any:
        return itertools.islice(every_ping(), 25)

    seen: list[Any] = []
    real = mapping.streaming.map_survey

    def map_survey(pings: Any, nav: Any, *args: Any, **kwargs: Any) -> Any:
        seen.append(nav)
        return real(pings, nav, *args, **kwargs)

    monkeypatch.setattr(mapping.streaming, "map_survey", map_survey)
    params = replace(
        pipeline_params(config), loops=replace(pipeline_params(config).loops, enabled=False)
    )
    stream_survey(pings, samples, mount_from_config(config.sonar), params)
    [final] = seen
    assert list(final.ranges) == list(samples.ranges)
    assert [s.distance_m for s in final.ranges] == distances


def test_a_sonar_that_never_reaches_the_seabed_ends_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 3.6 m above the bed, tilted 25 deg with a 20 deg vertical beam: the bed is first lit
    # at about 6.3 m slant range, and the sonar is set to 5 m. Every frame is placed and
    # none shows the seabed: one line that says why, not a raster library's traceback.
    sim = tmp_path / "sim"
    simulate("field", 6, sim, max_pings=25, range_m=5.0)
    args = ["replay", "--sonar", str(sim / "sonar.oculus"), "--nav", str(sim / "nav.tlog"),
            "--config", str(sim / "site.toml"), "--out", str(tmp_path / "o")]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no ping shows the seabed" in err[0], err
    assert "range_m" in err[0] and "sonar.oculus" in err[0]


def _trajectory(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1)


def test_a_raw_capture_replays_as_its_log_does(
    survey: Path, result: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The survey's pings as a raw network capture (no log framing, no receipt times),
    stamped from the first ping's time and the sonar's own clock: the same frames mapped
    to the same places (the stamps differ from the receipt times by the link's jitter)."""
    items = list(iter_log_items(survey / "sonar.oculus"))
    capture = tmp_path / "capture.raw"
    capture.write_bytes(b"".join(item.message for item in items))
    common = ["--nav", str(survey / "nav.tlog"), "--config", str(survey / "site.toml")]
    out = tmp_path / "from-capture"
    args = ["replay", "--sonar", str(capture), *common, "--out", str(out)]
    assert main([*args, "--sonar-start", repr(items[0].time)]) == 0
    capsys.readouterr()
    logged, captured = _trajectory(result / "trajectory.csv"), _trajectory(out / "trajectory.csv")
    assert captured.shape == logged.shape
    np.testing.assert_allclose(captured[:, 0], logged[:, 0], atol=0.01)  # stamps: jitter only
    shift = np.hypot(captured[:, 3] - logged[:, 3], captured[:, 4] - logged[:, 4])
    assert float(np.median(shift)) < 0.01 and float(shift.max()) < 0.05
    with rasterio.open(out / "mosaic.tif") as mosaic:
        assert np.count_nonzero(mosaic.read(1)) > 0
    # Without a start time, or with one for a log that has its own: one line each.
    logged_with_start = ["replay", "--sonar", str(survey / "sonar.oculus"), *common]
    logged_with_start += ["--out", str(tmp_path / "o"), "--sonar-start", "2026-05-03T10:15:02Z"]
    for bad in (args, logged_with_start):
        assert main(bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--sonar-start" in err[0], err
