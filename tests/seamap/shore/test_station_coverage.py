"""The shore station takes each survey's coverage (summary and raster) from a fake boat
over real zenoh sessions on 127.0.0.1, live and through its catch-up, and keeps the newest
of each on disk next to the survey's mosaic."""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.zenoh_io import CoverageKeyParts, json_bytes
from seamap.shore import ShoreSettings, ShoreStation
from seamap.shore.state import ShoreState
from tests.ports import free_tcp_port
from tests.seamap.shore.conftest import (
    CoverageSource,
    coverage_cells,
    coverage_info,
    coverage_png,
    coverage_summary,
)
from tests.seamap.test_shore import SURVEY, VEHICLE, WAIT_S, FakeBoat, loopback_peer

MakeStation = Callable[[], tuple[ShoreStation, io.StringIO]]


@pytest.fixture
def port() -> int:
    return free_tcp_port()


@pytest.fixture
def boat(port: int) -> Iterator[tuple[FakeBoat, CoverageSource]]:
    """A boat listening on the port, with the coverage of survey s1."""
    fake = FakeBoat(port)
    try:
        yield fake, CoverageSource(fake.session, VEHICLE, SURVEY)
    finally:
        fake.close()


@pytest.fixture
def make_station(tmp_path: Path, port: int) -> Iterator[MakeStation]:
    """A shore station following VEHICLE on the port, and what it tells."""
    stations: list[ShoreStation] = []

    def make() -> tuple[ShoreStation, io.StringIO]:
        settings = ShoreSettings(
            out_dir=tmp_path / "shore",
            zenoh=loopback_peer(connect=[f"tcp/127.0.0.1:{port}"]),
            vehicle=VEHICLE,
            write_interval_s=0.2,
        )
        told = io.StringIO()
        station = ShoreStation(settings, console=told)
        stations.append(station)
        station.open()
        return station, told

    yield make
    for station in stations:
        station.close()


def held_versions(station: ShoreStation) -> tuple[int, int]:
    """The versions of the summary and raster held (-1: none)."""
    coverage = station.coverage(VEHICLE, SURVEY)
    if coverage is None:
        return -1, -1
    summary = coverage.summary["version"] if coverage.summary is not None else -1
    raster = coverage.raster_info.version if coverage.raster_info is not None else -1
    return summary, raster


def files_hold(folder: Path, summary: dict[str, Any], png: bytes) -> bool:
    """Whether the station's files hold this summary and raster, as published."""
    try:
        raster = (folder / "coverage.png").read_bytes()
        written = json.loads((folder / "coverage.json").read_bytes())
    except (OSError, ValueError):
        return False
    return raster == png and written == {k: v for k, v in summary.items() if k != "gaps"}


def test_coverage_reaches_the_files_and_older_versions_are_dropped(tmp_path, boat, make_station):
    _, coverage = boat
    station, told = make_station()
    assert station.run(WAIT_S, until=lambda s: s.alive(VEHICLE) is True)
    coverage.wait_heard()
    summary, png = coverage_summary(2000), coverage_png(coverage_cells())
    coverage.put_summary(summary)
    coverage.put_raster(png, coverage_info(2000))

    folder = tmp_path / "shore" / VEHICLE / SURVEY
    assert station.run(WAIT_S, until=lambda s: files_hold(folder, summary, png))
    assert held_versions(station) == (2000, 2000)
    gaps = json.loads((folder / "gaps.geojson").read_bytes())
    assert gaps == summary["gaps"] and len(gaps["features"]) == 2
    # The world file places the PNG: the centre of its top-left cell, 0.25 m cells.
    world = [float(v) for v in (folder / "coverage.pgw").read_text().split()]
    assert world == pytest.approx([0.25, 0, 0, -0.25, 500_000.125, 4_800_009.875])
    assert "covered 63.4 %" in station.status_line()

    # Bad payloads on either key are counted, told in a line, and change nothing.
    coverage.put_summary(b"{not json")
    coverage.put_summary(json_bytes({**coverage_summary(3000), "version": "3000"}))
    coverage.put_summary(json_bytes({**coverage_summary(3000), "survey": "other"}))
    coverage.put_raster(png, b'{"epsg": 32631}')
    coverage.put_raster(png, coverage_info(3000, cols=41))  # a size the PNG does not have
    coverage.put_raster(b"not a png", coverage_info(3000))
    coverage.put_raster(png, None)
    assert station.run(WAIT_S, until=lambda s: s.stats.bad == 7)
    for key in (coverage.summary_key, coverage.raster_key):
        assert f"bad payload on {key}:" in told.getvalue()
    assert held_versions(station) == (2000, 2000)

    # Older versions arriving late (a slow catch-up reply) are dropped... (counted from
    # here: on a loaded machine the first catch-up's replies, the version held, can come
    # after the live puts of that version and be counted as stale themselves)
    stale = station.stats.coverage_stale
    coverage.put_summary(coverage_summary(1000, area=False))
    coverage.put_raster(coverage_png(coverage_cells(("above_bar",) * 3)), coverage_info(1000))
    assert station.run(WAIT_S, until=lambda s: s.stats.coverage_stale == stale + 2)
    assert held_versions(station) == (2000, 2000)
    # ...and the final one, after them on the same keys, replaces what is held: without
    # an area, its gaps are unknown and gaps.geojson goes.
    final, final_png = (
        coverage_summary(4000, area=False, final=True),
        coverage_png(coverage_cells(("at_bar", "at_bar", "above_bar"))),
    )
    coverage.put_summary(final)
    coverage.put_raster(final_png, coverage_info(4000))
    assert station.run(WAIT_S, until=lambda s: files_hold(folder, final, final_png))
    assert held_versions(station) == (4000, 4000)
    assert not (folder / "gaps.geojson").exists()
    assert json.loads((folder / "coverage.json").read_bytes())["final"] is True
    assert "seen 812 m² (final)" in station.status_line()
    assert station.stats.coverage_taken == 4 and station.stats.bad == 7


def test_a_late_station_catches_up_on_the_coverage(tmp_path, boat, make_station):
    _, coverage = boat
    # Published while no shore listened: only the catch-up's get can bring them.
    summary, png = coverage_summary(5000), coverage_png(coverage_cells())
    coverage.put_summary(summary)
    coverage.put_raster(png, coverage_info(5000))
    station, _ = make_station()
    assert station.run(WAIT_S, until=lambda s: held_versions(s) == (5000, 5000))
    folder = tmp_path / "shore" / VEHICLE / SURVEY
    assert station.run(WAIT_S, until=lambda s: files_hold(folder, summary, png))
    assert json.loads((folder / "gaps.geojson").read_bytes()) == summary["gaps"]
    # A catch-up ends once both its gets (tiles, coverage) have.
    assert station.run(WAIT_S, until=lambda s: s.stats.catchups_done == s.stats.catchups_started)
    assert station.stats.catchups_started >= 1


def test_state_refuses_a_summary_that_strict_json_cannot_hold():
    state = ShoreState()
    where = CoverageKeyParts(VEHICLE, SURVEY, raster=False)
    payload = json_bytes(coverage_summary(1)).replace(b'"seen_m2":812.5', b'"seen_m2":NaN')
    with pytest.raises(Exception, match="seen_m2 is not finite"):
        state.take_coverage_summary(where, payload)
    payload = json_bytes(coverage_summary(1)).replace(b'"min_gap_m2":1.0', b'"min_gap_m2":NaN')
    with pytest.raises(Exception, match="NaN or Infinity"):
        state.take_coverage_summary(where, payload)
    assert state.coverage(VEHICLE, SURVEY) is None
    assert state.take_coverage_summary(where, json_bytes(coverage_summary(1)))
    assert not state.take_coverage_summary(where, json_bytes(coverage_summary(1)))  # a repeat
