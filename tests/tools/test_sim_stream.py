"""The in-process survey stream: the same samples the drivers read from the simulator's
files, in arrival order; the hectare scenario streams at once and in bounded memory."""

from __future__ import annotations

import itertools
import json
import math
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from daemon.config import load_config
from drivers.errors import SeamapError
from drivers.mavlink.navlog import read_nav_log
from drivers.oculus.logfile import iter_pings
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping
from tools.sim import SCENARIOS, simulate
from tools.sim.stream import SimStream, survey_events

SHORT = {"max_pings": 30, "n_beams": 128}
PING_FIELDS = (
    "time",
    "ping_id",
    "master_mode",
    "frequency_hz",
    "range_resolution_m",
    "speed_of_sound_mps",
    "gain_percent",
    "gamma",
    "heading_rad",
    "pitch_rad",
    "roll_rad",
    "extra",
)


def by_kind(events: list[tuple[float, object]]) -> dict[type, list[Any]]:
    kinds: dict[type, list[Any]] = defaultdict(list)
    for _, sample in events:
        kinds[type(sample)].append(sample)
    return kinds


@pytest.mark.parametrize(
    ("scenario", "overrides"),
    [("quadrats", SHORT), ("quadrats-current", {**SHORT, "flavour": "px4"})],
)
def test_stream_equals_what_the_drivers_read_from_the_files(
    tmp_path: Path, scenario: str, overrides: dict[str, Any]
):
    summary = simulate(scenario, 5, tmp_path, **overrides)
    nav = read_nav_log(summary.nav_path)
    pings = list(iter_pings(summary.sonar_path))
    stream = survey_events(scenario, 5, **overrides)
    events = list(stream.events)

    times = [t for t, _ in events]
    assert all(a <= b for a, b in itertools.pairwise(times))
    assert all(t == sample.time for t, sample in events)  # type: ignore[attr-defined]
    kinds = by_kind(events)
    assert set(kinds) == {ImuSample, GnssFix, HeadingSample, AttitudeSample, Ping}
    assert kinds[ImuSample] == nav.imu
    assert kinds[GnssFix] == nav.gnss
    assert kinds[HeadingSample] == nav.heading
    assert kinds[AttitudeSample] == nav.attitude
    assert (stream.nav_sources.imu, stream.nav_sources.heading) == (
        nav.imu_source,
        nav.heading_source,
    )
    assert stream.nav_sources.gnss == nav.gnss_source

    assert len(kinds[Ping]) == len(pings) == stream.ping_count == 30
    for ours, theirs in zip(kinds[Ping], pings, strict=True):
        for name in PING_FIELDS:
            assert getattr(ours, name) == getattr(theirs, name), name
        assert ours.image.dtype == theirs.image.dtype
        assert ours.image.tobytes() == theirs.image.tobytes()
        assert np.array_equal(ours.bearings_rad, theirs.bearings_rad)
        assert theirs.gains is not None and np.array_equal(ours.gains, theirs.gains)

    truth = json.loads(summary.truth_path.read_text())
    assert stream.site_config == load_config(summary.config_path)
    assert stream.epsg == truth["site"]["epsg"]
    assert stream.duration_s == pytest.approx(truth["time"]["duration_s"], abs=1e-6)
    for k in (0, 29):
        east, north, heading = stream.truth_pose(k)
        ping = truth["pings"][k]
        assert (east, north) == pytest.approx((ping["east"], ping["north"]), abs=1e-4)
        assert math.degrees(heading) == pytest.approx(ping["grid_heading_deg"], abs=1e-4)


def test_the_hectare_survey_needs_a_cut_to_be_written(tmp_path: Path):
    assert "hectare" in SCENARIOS
    with pytest.raises(SeamapError, match="max_pings or duration_s"):
        simulate("hectare", 0, tmp_path)


def _rss_mb() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096 / 2**20


@pytest.fixture(scope="module")
def hectare() -> tuple[SimStream, float]:
    started = time.perf_counter()
    return survey_events("hectare", 3, n_beams=128), started


def test_hectare_is_a_two_hour_hectare(hectare: tuple[SimStream, float]):
    stream, _ = hectare
    s = stream.scenario
    assert s.n_lanes * s.lane_spacing_m == pytest.approx(95.2)
    assert s.lane_length_m == 100.0 and s.speed_mps == 0.5
    assert 1.8 * 3600 < stream.duration_s < 2.2 * 3600
    assert 65_000 < stream.ping_count < 75_000
    assert stream.truth.east.shape == (stream.ping_count,)
    assert np.ptp(stream.truth.east) > 90 and np.ptp(stream.truth.north) > 95


def test_hectare_streams_at_once_in_bounded_memory(hectare: tuple[SimStream, float]):
    stream, _ = hectare
    # CPU time of this test, not wall time: what the stream costs, whatever else runs.
    started = time.process_time()
    rss: dict[int, float] = {}
    pings = nav = 0
    last = -math.inf
    for arrival, sample in stream.events:
        assert arrival >= last
        last = arrival
        if not isinstance(sample, Ping):
            nav += 1
            continue
        pings += 1
        if pings == 50:
            # Not the whole two hours first: ~400 pings/s once it streams.
            assert time.process_time() - started < 15.0
        if pings in (300, 1000):
            rss[pings] = _rss_mb() if Path("/proc/self/statm").exists() else math.nan
        if pings == 1000:
            break
    assert 5 * pings < nav < 7 * pings  # 55 Hz IMU and three 2 Hz streams, 10 Hz pings
    growth = rss[1000] - rss[300]
    if not math.isnan(growth):
        assert growth < 20.0, f"memory grew {growth:.1f} MB over 700 pings"
    # After 100 s the boat is still on the first lane: 46.2 m west of the centre, heading
    # about grid north, some 48 m north of where it started.
    east, north, heading = stream.truth_pose(pings - 1)
    assert east - stream.utm_origin[0] == pytest.approx(-46.2, abs=0.5)
    assert north - stream.truth_pose(0)[1] == pytest.approx(48.0, abs=4.0)
    assert min(heading, 2 * math.pi - heading) < 0.3
