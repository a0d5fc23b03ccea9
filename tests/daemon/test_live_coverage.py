"""The daemon's live coverage (``daemon.live_coverage.LiveCoverage``): frames given one at a
time, as the live map turns them final, count as the survey-end pass counts them; an
engine started afresh in another local frame lands on the same cells; the publication's
summary, raster and gaps; and the ``[mission]`` table and ``seamap ctl start --area``."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from PIL import Image

from daemon.config import CoverageConfig, load_config
from daemon.coverage import area_coverage, coverage_params
from daemon.live_coverage import LiveCoverage, coverage_message
from drivers.formats.area import SurveyArea, area_geojson, parse_area
from drivers.zenoh_io import CoverageInfo, parse_coverage_summary
from mapping.coverage import CoverageParams, SeabedCoverage, SonarFan
from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from mapping.preprocess import lit_min_range
from seamap.cli import main

FRAME = LocalFrame.around(43.1, 5.9)
TILT = math.radians(15.0)
MOUNT = SonarMount(0.0, 0.0, 0.0, 0.0, TILT, 1.0)
FAN = SonarFan(math.radians(65.0), lit_min_range(1.0, 15.0, 20.0, 1.0), 5.0, TILT)
CONFIG = CoverageConfig()


def _area() -> SurveyArea:
    """A 30 m x 20 m area with a 2 m square hole, in FRAME's local metres."""
    outer = [(0.0, 0.0), (30.0, 0.0), (30.0, 20.0), (0.0, 20.0)]
    hole = [(14.0, 9.0), (14.0, 11.0), (16.0, 11.0), (16.0, 9.0)]

    def lonlat(ring: list[tuple[float, float]]) -> list[list[float]]:
        lat, lon = FRAME.to_latlon([p[0] for p in ring], [p[1] for p in ring])
        points = [[float(a), float(b)] for a, b in zip(lon, lat, strict=True)]
        return [*points, points[0]]

    geometry = {"type": "Polygon", "coordinates": [lonlat(outer), lonlat(hole)]}
    return parse_area(json.dumps(geometry), "area")


def _lanes(eastings: list[float], t0: float = 1000.0) -> tuple[np.ndarray, np.ndarray]:
    """Frames at 5 Hz along north-south lanes at ``eastings`` (alternating), 0.5 m/s."""
    times, poses, t = [], [], t0
    for k, east in enumerate(eastings):
        north = np.arange(-6.0, 26.0, 0.1)
        if k % 2:
            north = north[::-1]
        heading = 0.0 if k % 2 == 0 else math.pi
        poses.append(np.column_stack([np.full(north.size, east), north,
                                      np.full(north.size, heading)]))  # fmt: skip
        times.append(t + np.arange(north.size) * 0.2)
        t += north.size * 0.2 + 30.0
    return np.concatenate(times), np.concatenate(poses)


def test_frames_one_at_a_time_count_as_the_survey_end_pass_counts_them() -> None:
    times, poses = _lanes([3.0, 10.0, 24.0, 31.0])  # the lane at 17 m skipped
    live = LiveCoverage(MOUNT, CONFIG, _area())
    live.add(FRAME, float(times[0]), poses[0])  # no fan yet: nothing counted
    assert live.frames == 0 and live.message("s") is None
    live.set_fan(FAN)
    live.set_fan(SonarFan(math.radians(30.0), 1.0, 2.0, TILT))  # the first fan stays
    assert live.fan == FAN
    for t, pose in zip(times, poses, strict=True):
        live.add(FRAME, float(t), pose)
    batch = SeabedCoverage(
        MOUNT, FAN, coverage_params(CONFIG), anchor_e=FRAME.anchor_e, anchor_n=FRAME.anchor_n
    )
    batch.add_frames(times, poses)
    grid = batch.grid()
    message = live.message("20261205-060000")
    assert message is not None and live.frames == len(times)
    found = area_coverage(grid, 1, FRAME, _area(), CONFIG.min_gap_m2)
    summary = parse_coverage_summary(json.dumps(message.summary).encode(), survey="20261205-060000")
    assert summary["area"]["fraction"] == round(found.fraction, 5)
    assert summary["covered_m2"] == round(grid.covered_m2(1), 3)
    assert not summary["final"] and summary["epsg"] == FRAME.epsg
    # The skipped lane's stripe is the one gap; the hole is not a gap.
    assert summary["area"]["gaps"] == len(summary["gaps"]["features"]) == 1
    (gap,) = summary["gaps"]["features"]
    lon, lat = np.array(gap["geometry"]["coordinates"][0]).T
    x, y = FRAME.to_local(lat, lon)
    outline = shapely.Polygon(np.column_stack([x, y]))
    reach = math.sqrt(4.9**2 - (1.0 / math.tan(math.radians(24.0))) ** 2)
    stripe = shapely.box(10.0 + reach, 0.0, 24.0 - reach, 20.0) - shapely.box(14, 9, 16, 11)
    assert shapely.hausdorff_distance(outline, stripe) < 0.5
    # The raster: one RGBA pixel a cell, where the attachment says.
    image = Image.open(io.BytesIO(message.png))
    info = CoverageInfo.from_json(message.info.to_json())
    assert image.mode == "RGBA" and image.size == (info.cols, info.rows) == grid.passes.shape[::-1]
    assert (info.west, info.north, info.cell_m) == (grid.west_m, grid.north_m, grid.cell_m)
    alpha = np.asarray(image)[:, :, 3]
    np.testing.assert_array_equal(alpha > 0, grid.passes > 0)
    later = live.message("20261205-060000")
    assert later is not None and later.info.version > message.info.version


def test_a_fresh_engine_in_another_frame_lands_on_the_same_cells() -> None:
    times, poses = _lanes([3.0, 10.0])
    whole = LiveCoverage(MOUNT, CONFIG, _area())
    split = LiveCoverage(MOUNT, CONFIG, _area())
    for live in (whole, split):
        live.set_fan(FAN)
    # After a failure the live map starts a new engine, whose frame is anchored elsewhere.
    other = LocalFrame(FRAME.epsg, FRAME.anchor_e + 37.0, FRAME.anchor_n - 12.0)
    half = len(times) // 2
    for k, (t, pose) in enumerate(zip(times, poses, strict=True)):
        whole.add(FRAME, float(t), pose)
        if k < half:
            split.add(FRAME, float(t), pose)
        else:
            moved = pose - [37.0, -12.0, 0.0]
            split.add(other, float(t), moved)
    a, b = whole.message("s"), split.message("s")
    assert a is not None and b is not None
    assert a.png == b.png and a.summary["area"] == b.summary["area"]
    # A frame in another UTM zone is not counted (and said so by the counter).
    elsewhere = LocalFrame(FRAME.epsg + 1, FRAME.anchor_e, FRAME.anchor_n)
    split.add(elsewhere, float(times[-1]) + 1.0, poses[-1])
    assert split.other_zone == 1 and split.frames == len(times)


def test_without_an_area_only_what_was_seen_is_said() -> None:
    times, poses = _lanes([3.0])
    live = LiveCoverage(MOUNT, CONFIG)
    live.set_fan(FAN)
    for t, pose in zip(times, poses, strict=True):
        live.add(FRAME, float(t), pose)
    message = live.message("s")
    assert message is not None
    assert message.summary["area"] is None and message.summary["gaps"]["features"] == []
    assert message.summary["seen_m2"] > 200.0  # a 32 m lane, 8.7 m wide
    assert "gaps" not in message.status() and message.status()["seen_m2"] > 200.0


def test_a_grid_with_nothing_seen_publishes_an_empty_raster() -> None:
    grid = SeabedCoverage(MOUNT, FAN, CoverageParams()).grid()
    message = coverage_message(
        "s", grid, coverage_params(CONFIG), FRAME, _area(), 1.0, final=True, version=5
    )
    assert message.summary["area"]["fraction"] == 0.0
    assert message.summary["area"]["gaps"] == 1  # the whole area (less its hole)
    assert Image.open(io.BytesIO(message.png)).size == (1, 1)


def test_the_mission_area_is_read_from_the_config_files_folder(tmp_path: Path) -> None:
    (tmp_path / "lease.geojson").write_text(json.dumps(area_geojson(_area())))
    site = tmp_path / "site.toml"
    site.write_text('[mission]\narea = "lease.geojson"\nreplan_at_end = true\n')
    config = load_config(site)
    assert config.mission.area == str(tmp_path / "lease.geojson")
    assert config.mission.replan_at_end
    site.write_text('[mission]\narea = "/srv/lease.geojson"\n')
    assert load_config(site).mission.area == "/srv/lease.geojson"
    assert load_config(None).mission.area == ""
    site.write_text("[mission]\nreplan = true\n")
    with pytest.raises(Exception, match="unknown key 'replan' in \\[mission\\]"):
        load_config(site)


def test_ctl_start_with_a_bad_area_is_one_line_and_asks_nothing(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f'[daemon]\nstate_dir = "{tmp_path / "state"}"\n')
    bad = tmp_path / "area.geojson"
    bad.write_text('{"type": "Polygon", "coordinates": [[[5.9, 43.1], [5.9001, 43.1]]]}')
    assert main(["ctl", "start", "--config", str(site), "--area", str(bad)]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"seamap ctl: {bad}: "), err
    assert main(["ctl", "stop", "--config", str(site), "--area", str(bad)]) == 2
    assert "--area goes with start" in capfd.readouterr().err
