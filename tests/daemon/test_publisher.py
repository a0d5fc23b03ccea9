"""The boat's zenoh publisher and a shore station on 127.0.0.1: after the survey-end pass
the shore's mosaic is the result folder's, even where the final mosaic no longer covers
a tile the live map published, and no live tile follows the final ones."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import rasterio

from daemon.config import ZenohConfig
from daemon.publisher import TILES_DIR, ZenohPublisher, read_tiles
from daemon.publishing import Publishing
from daemon.surveys import OpenSurvey
from drivers.formats.results import write_geotiff
from drivers.zenoh_io import decode_tile, open_session
from mapping.mosaic import TileGrid, assemble
from mapping.streaming import PoseUpdate, TileUpdate
from seamap.shore import ShoreSettings, ShoreStation
from tests.ports import free_tcp_port

VEHICLE, SURVEY, EPSG = "boat1", "s1", 32631
GRID = TileGrid(res_m=0.02, tile_px=256)
COL0, ROW0 = 97656, 937500  # easting 500 000 m, northing 4 800 000 m
WAIT_S = 20.0


def _peer(listen: list[str] | None = None, connect: list[str] | None = None) -> ZenohConfig:
    return ZenohConfig(
        mode="peer", listen=listen or [], connect=connect or [], multicast_scouting=False
    )


def _values(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    values = rng.integers(1, 256, (GRID.tile_px, GRID.tile_px), dtype=np.uint8)
    values[rng.random(values.shape) < 0.3] = 0
    return values


def _update(key: tuple[int, int], values: np.ndarray) -> TileUpdate:
    west, north = GRID.tile_west_north(key)
    return TileUpdate(key, values, 0, EPSG, GRID.res_m, GRID.tile_px, west, north)


def _until(station: ShoreStation, condition: Callable[[ShoreStation], bool], what: str) -> None:
    assert station.run(WAIT_S, until=condition), f"timed out waiting for {what}"


@pytest.fixture
def boat_and_shore(tmp_path: Path) -> Iterator[tuple[ZenohPublisher, ShoreStation]]:
    port = free_tcp_port()
    loop = asyncio.new_event_loop()
    publisher = ZenohPublisher(VEHICLE, tmp_path / "surveys", loop)
    publisher.attach(open_session(_peer(listen=[f"tcp/127.0.0.1:{port}"])))
    station = ShoreStation(
        ShoreSettings(
            out_dir=tmp_path / "shore",
            zenoh=_peer(connect=[f"tcp/127.0.0.1:{port}"]),
            vehicle=VEHICLE,
            write_interval_s=0.2,
        )
    )
    station.open()
    yield publisher, station
    station.close()
    session = publisher.detach()
    publisher.close()
    if session is not None:
        session.close()
    loop.close()


def test_final_tiles_replace_every_live_tile_and_the_shore_holds_the_result(
    tmp_path: Path, boat_and_shore: tuple[ZenohPublisher, ShoreStation]
) -> None:
    publisher, station = boat_and_shore
    _until(station, lambda s: s.alive(VEHICLE) is True, "the boat's token")
    # The live map: three tiles in a row, the easternmost only grazed by a fan.
    live_keys = [(COL0, ROW0), (COL0 + 1, ROW0), (COL0 + 2, ROW0)]
    grazed = np.zeros((GRID.tile_px, GRID.tile_px), np.uint8)
    grazed[100:110, :5] = 77
    for key, values in zip(live_keys, [_values(1), _values(2), grazed], strict=True):
        publisher.tile(SURVEY, _update(key, values))
    _until(station, lambda s: len(s.tiles(VEHICLE, SURVEY)) == 3, "the live tiles")

    # The survey-end pass placed the frames a little west: its mosaic has no data in the
    # third tile, and one tile row more to the south (empty in its west tile).
    survey_dir = tmp_path / "surveys" / SURVEY
    survey_dir.mkdir(parents=True)
    south = np.zeros((GRID.tile_px, GRID.tile_px), np.uint8)
    south[:40, 200:] = 9
    final = {(COL0, ROW0): _values(3), (COL0 + 1, ROW0): _values(4), (COL0 + 1, ROW0 - 1): south}
    image, (west, north) = assemble(GRID, final)
    write_geotiff(survey_dir / "mosaic.tif", image, west, north, GRID.res_m, EPSG)
    assert publisher.final_tiles(SURVEY, survey_dir) == 4  # 3 with data, 1 emptied
    publisher.survey_ended(SURVEY)
    publisher.tile(SURVEY, _update(live_keys[2], grazed))  # late: dropped

    def final_held(s: ShoreStation) -> bool:
        held = s.tiles(VEHICLE, SURVEY)
        return len(held) == 4 and not held[live_keys[2]].values.any()

    _until(station, final_held, "the final tiles")
    # A shore catching up now (from the survey's tiles/ folder) gets the same set.
    assert set(read_tiles(survey_dir / TILES_DIR)) == set(final) | {live_keys[2]}
    done = station.stats.catchups_done
    station.catch_up()
    _until(station, lambda s: s.stats.catchups_done > done, "the catch-up")
    # The publisher answers a query after the tiles handed over before it: a late live
    # tile, had it been put, would have arrived by now.
    station.run(0.2)
    assert not station.tiles(VEHICLE, SURVEY)[live_keys[2]].values.any()
    for key, values in final.items():
        np.testing.assert_array_equal(station.tiles(VEHICLE, SURVEY)[key].values, values)

    station.write_files()
    shore_tif = tmp_path / "shore" / VEHICLE / SURVEY / "mosaic.tif"
    with rasterio.open(shore_tif) as a, rasterio.open(survey_dir / "mosaic.tif") as b:
        assert (a.transform, a.shape, a.crs) == (b.transform, b.shape, b.crs)
        np.testing.assert_array_equal(a.read(1), b.read(1))
    assert decode_tile((survey_dir / TILES_DIR / f"{COL0 + 2}_{ROW0}.png").read_bytes()).max() == 0


def test_frames_placed_anew_reach_the_shores_track(
    boat_and_shore: tuple[ZenohPublisher, ShoreStation],
) -> None:
    """The live map places each frame first by chaining registrations, then again as its
    window is solved and re-solved; the shore's track is to end at the frames' latest
    poses (the map's), not at their first estimates, which zigzag about them."""
    publisher, station = boat_and_shore
    _until(station, lambda s: s.alive(VEHICLE) is True, "the boat's token")
    publishing = Publishing(ZenohConfig(), OpenSurvey())
    publishing.publisher = publisher
    east0, north0 = 500_010.0, 4_800_010.0

    def update(frame: int, off_m: float) -> PoseUpdate:
        # 10 cm a frame eastward, ``off_m`` north of the line.
        return PoseUpdate(frame, 1.7e9 + frame / 5, east0 + 0.1 * frame, north0 + off_m,
                          90.0, 43.35, 3.0, EPSG, False)  # fmt: skip

    first = {k: 0.15 * (-1) ** k for k in range(20)}  # the chain's first estimates
    for k in range(20):
        publishing.on_pose(update(k, first[k]))
        poses = k + 1
        _until(station, lambda s: len(s.track(VEHICLE)) == poses, f"pose {k}")  # noqa: B023
        if k >= 3:  # the window's solve: the frame 3 back placed anew, on the line
            publishing.on_pose(update(k - 3, 0.0))
    publishing.on_pose(update(19, 0.01))  # the newest, refined: in place, not a new point
    for k in (17, 18):
        publishing.on_pose(update(k, 0.0))  # after the last pose: sent with it again

    def settled(s: ShoreStation) -> bool:
        track = s.track(VEHICLE)
        return len(track) == 20 and all(abs(p.north - north0) < 0.02 for p in track)

    _until(station, settled, "the track on the map's line")
    track = station.track(VEHICLE)
    assert [round(p.east - east0, 3) for p in track] == [round(0.1 * k, 3) for k in range(20)]
    assert track[-1].north == pytest.approx(north0 + 0.01)
    assert publishing.latest_pose == update(19, 0.01)
