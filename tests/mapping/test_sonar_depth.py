"""The seabed from the sonar's own pings: on the simulator's sloping field day (no
echosounder; the world's beam pattern, backscatter, speckle and noise written from the
physics in ``tools.sim``, never from ``mapping``), where the vertical beam first lights
the bed gives the depth there, and the bottom model's plane through those soundings gives
each ping's altitude and the slope."""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from drivers.oculus.logfile import iter_pings
from mapping.bottom import (
    BottomParams,
    BottomPlane,
    SeabedAttitude,
    SonarGeometry,
    configured_holds,
    seabed_attitude,
)
from mapping.frames import SonarMount
from mapping.polar import Attitude
from mapping.samples import Ping
from mapping.sonar_depth import SonarDepthParams, SonarHead, ping_soundings, sonar_soundings
from mapping.tasks import InlinePool
from tools.sim.survey import simulate

PINGS = 60


@dataclass(frozen=True)
class Day:
    pings: list[Ping]
    truth: list[dict[str, Any]]
    """The truth of each ping, in the order of ``pings``."""
    mount: SonarMount
    slope: tuple[float, float]
    """The bed's depth gained per metre east and north."""


def _day(out: Path, scenario: str, seed: int, count: int, **overrides: Any) -> Day:
    simulate(scenario, seed, out, max_pings=count, n_beams=128, **overrides)
    truth = json.loads((out / "truth.json").read_text())
    drawn = truth.get("field_day", {}).get("drawn", {})
    slope = (drawn.get("seabed_slope_east", 0.0), drawn.get("seabed_slope_north", 0.0))
    sonar = tomllib.loads((out / "site.toml").read_text())["sonar"]
    mount = SonarMount(
        forward_m=sonar["mount_x_m"],
        starboard_m=sonar["mount_y_m"],
        down_m=sonar["mount_z_m"],
        yaw_rad=math.radians(sonar["mount_yaw_deg"]),
        tilt_rad=math.radians(sonar["tilt_deg"]),
        altitude_m=sonar["altitude_m"],
    )
    by_id = {p["ping_id"]: p for p in truth["pings"]}
    pings = list(iter_pings(out / "sonar.oculus"))
    return Day(pings, [by_id[p.ping_id] for p in pings], mount, slope)


@pytest.fixture(scope="module")
def day(tmp_path_factory: pytest.TempPathFactory) -> Day:
    """Field day 1: sand, 4.4 % slope, the sonar 0.4-2.5 m above the bed at 20 degrees of
    tilt and a 9.9 m range, no echosounder; its sonar sending gain rows (the day draws
    none: ``test_without_gain_rows_the_tvg_stays_in_the_profile``)."""
    day = _day(tmp_path_factory.mktemp("field"), "field", 1, PINGS, gain_rows=True)
    assert math.hypot(*day.slope) > 0.03
    return day


def _head(mount: SonarMount) -> SonarHead:
    return SonarHead(
        mount.tilt_rad, (mount.forward_m, mount.starboard_m, mount.down_m), mount.yaw_rad
    )


def _attitude(truth: dict[str, Any]) -> Attitude:
    return Attitude(math.radians(truth["roll_deg"]), math.radians(truth["pitch_deg"]))


def _depth_errors(day: Day) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Soundings found per ping, and each ping's median depth error (m) against the truth."""
    params = SonarDepthParams()
    errors, counts = [], []
    for ping, truth in zip(day.pings, day.truth, strict=True):
        points = ping_soundings(ping, _head(day.mount), _attitude(truth), params)
        counts.append(len(points))
        if not len(points):
            continue
        # The points are in the ping's level frame C (x along the boresight's azimuth);
        # the truth's bed deepens along the slope from under the sonar head.
        heading = math.radians(truth["grid_heading_deg"]) + day.mount.yaw_rad
        s, c = math.sin(heading), math.cos(heading)
        east = points[:, 0] * s + points[:, 1] * c
        north = points[:, 0] * c - points[:, 1] * s
        true_depth = truth["altitude_m"] + day.slope[0] * east + day.slope[1] * north
        errors.append(float(np.median(points[:, 2] - true_depth)))
    return np.array(counts), np.array(errors)


def test_the_first_return_gives_the_depth_where_the_beam_meets_a_slope(day: Day) -> None:
    found, errors_m = _depth_errors(day)
    assert np.mean(found > 0) >= 0.95, "nearly every ping shows the bed"
    assert np.median(found) >= 6, "most sectors within 45 degrees of the boresight find it"
    assert abs(float(np.median(errors_m))) < 0.03, errors_m
    assert float(np.percentile(np.abs(errors_m), 90)) < 0.10, errors_m


def test_without_gain_rows_the_tvg_stays_in_the_profile(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """The same day as its sonar sent it (no gain rows): each profile keeps the sonar's
    range gain, which moves the half maximum out, the depths deeper by about a centimetre
    (median -2.2 cm with gain rows, -3.0 without, 90th percentile 6.5 and 6.8 cm)."""
    day = _day(tmp_path_factory.mktemp("nogain"), "field", 1, PINGS)
    assert all(p.gains is None for p in day.pings)
    found, errors_m = _depth_errors(day)
    assert np.mean(found > 0) >= 0.95 and np.median(found) >= 6
    assert abs(float(np.median(errors_m))) < 0.04, errors_m
    assert float(np.percentile(np.abs(errors_m), 90)) < 0.10, errors_m


def _seabed(day: Day) -> SeabedAttitude | None:
    """The bottom model through the sonar's soundings, the pings placed at the truth."""
    times = np.array([p.time for p in day.pings])
    priors = np.array(
        [
            [t["local_east"], t["local_north"], math.radians(t["grid_heading_deg"])]
            for t in day.truth
        ]
    )
    mount = day.mount
    geometry = SonarGeometry(
        down_m=mount.down_m,
        altitude_m=mount.altitude_m,
        max_range_m=day.pings[0].max_range_m,
        half_fan_rad=math.radians(65.0),
        lit_range_m=mount.altitude_m / math.sin(mount.tilt_rad + math.radians(9.0)),
        sonar_pose=mount.sonar_pose,
        head=_head(mount),
    )
    truth_at = {p.time: t for p, t in zip(day.pings, day.truth, strict=True)}

    def tilt_at(stamp: float) -> Attitude:
        return _attitude(truth_at[stamp])

    return seabed_attitude([], times, priors, tilt_at, geometry, BottomParams(), lambda: day.pings)


def test_the_planes_through_the_sonars_soundings_give_altitude_and_slope(day: Day) -> None:
    mount = day.mount
    truth_at = {p.time: t for p, t in zip(day.pings, day.truth, strict=True)}
    attitude = _seabed(day)
    assert attitude is not None and attitude.model.source == "sonar"
    assert not attitude.configured_holds, "the configured level bed is decimetres off"
    altitude_errors, slope_errors = [], []
    for stamp, truth in truth_at.items():
        plane = attitude.planes.get(stamp)
        if plane is None:
            continue
        altitude_errors.append(plane.altitude_m - truth["altitude_m"])
        slope_errors.append((plane.slope_east - day.slope[0], plane.slope_north - day.slope[1]))
    assert len(altitude_errors) >= 0.95 * len(day.pings)
    err = np.abs(np.array(altitude_errors))
    # The configured altitude (the cut's mean) is off by decimetres from one end to the
    # other: the sonar's own soundings follow the bed.
    true_altitudes = np.array([t["altitude_m"] for t in day.truth])
    configured = np.abs(true_altitudes - mount.altitude_m)
    assert float(np.median(configured)) > 0.2
    assert float(np.median(err)) < 0.25 * float(np.median(configured))
    assert float(np.median(err)) < 0.05 and float(np.percentile(err, 90)) < 0.10, err
    slope_err = np.hypot(*np.array(slope_errors).T)
    assert float(np.median(slope_err)) < 0.02, slope_err


def test_on_a_level_bed_at_the_configured_altitude_the_configuration_holds(
    tmp_path: Path,
) -> None:
    """Quadrats seed 2 (150 pings, 15 s): a level bed (0.1-0.3 % slopes), the site's
    altitude right: the sonar's soundings agree with it, and the configured altitude is
    kept (the planes would add their noise)."""
    attitude = _seabed(_day(tmp_path, "quadrats", 2, 150))
    assert attitude is not None and attitude.model.source == "sonar"
    assert attitude.configured_holds


def test_a_ping_of_water_alone_gives_no_soundings() -> None:
    rng = np.random.default_rng(3)
    image = rng.gamma(1.5, 8.0, size=(400, 64)).astype(np.uint8)
    ping = Ping(
        time=0.0,
        ping_id=1,
        master_mode=1,
        frequency_hz=1.2e6,
        range_resolution_m=0.0125,
        bearings_rad=np.linspace(-1.13, 1.13, 64),
        image=image,
    )
    head = SonarHead(math.radians(15.0), (0.0, 0.0, 0.3))
    assert len(ping_soundings(ping, head, None, SonarDepthParams())) == 0


def test_the_site_file_turns_it_off(tmp_path: Path) -> None:
    from daemon.config import load_config
    from daemon.replay import pipeline_params

    site = tmp_path / "site.toml"
    site.write_text("[sonar]\nseabed_from_pings = false\n")
    assert not pipeline_params(load_config(site)).bottom.use_sonar
    site.write_text("[sonar]\naltitude_m = 1.2\n")
    assert pipeline_params(load_config(site)).bottom.use_sonar


def _lawnmower_planes(
    bed: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], seed: int
) -> tuple[dict[float, BottomPlane], np.ndarray]:
    """Planes of a 4-lane lawnmower (36 m lanes 8 m apart, one plane every 0.5 m and 13
    s: an hour) over a bed whose altitude ``bed(east, north, time)`` gives, as the
    sonar's first return reads it: each lane biased by its heading (+-4 %) and each ping
    by 2 % noise."""
    rng = np.random.default_rng(seed)
    east, north, heading = [], [], []
    for lane in range(4):
        along = np.arange(0.0, 36.0, 0.5)
        east.append(np.full(along.size, 8.0 * lane))
        north.append(along if lane % 2 == 0 else along[::-1])
        heading.append(np.full(along.size, 1.0 if lane % 2 == 0 else -1.0))
    e, n, h = (np.concatenate(v) for v in (east, north, heading))
    t = 13.0 * np.arange(e.size, dtype=float)
    altitude = bed(e, n, t) * (1.0 + 0.04 * h + 0.02 * rng.standard_normal(e.size))
    planes = {
        float(stamp): BottomPlane(float(a), 0.0, 0.0, 20)
        for stamp, a in zip(t, altitude, strict=True)
    }
    return planes, np.column_stack([e, n, np.where(h > 0, 0.0, math.pi)])


@pytest.mark.parametrize(
    ("bed", "holds"),
    [
        (lambda e, n, t: np.full(e.size, 1.0), True),  # level, at the configured 1 m
        (lambda e, n, t: 1.0 + 0.03 * (n - 18.0), False),  # a 3 % slope along the lanes
        (lambda e, n, t: 1.0 + 0.02 * (e - 12.0), False),  # 2 % across them
        (lambda e, n, t: 1.0 + 0.3 / 3600.0 * t, False),  # a tide of 0.3 m an hour
        (lambda e, n, t: np.full(e.size, 1.1), False),  # level, 10 % deeper than said
    ],
)
def test_the_configured_level_bed_holds_unless_a_bed_or_a_tide_explains_the_planes(
    bed: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], holds: bool
) -> None:
    # The lanes' biases and the noise vary the planes as much as a slope does; what tells
    # a slope or a tide is that position or time explains it.
    planes, positions = _lawnmower_planes(bed, seed=7)
    assert configured_holds(planes, positions, 1.0, SonarDepthParams()) is holds


def test_the_pings_sounded_ahead_in_a_pool_give_the_same_soundings(day: Day) -> None:
    """``sonar_soundings`` with a pool picks the pings ahead, assuming each gives
    soundings; where one gives none (water alone) or the pose is unknown, it picks the
    pings after it again: the same soundings, from the same pings, as one by one."""
    rng = np.random.default_rng(3)
    pings = list(day.pings)
    for k in (3, 4, 17, 30):  # water alone: no soundings
        water = rng.gamma(1.5, 8.0, size=pings[k].image.shape).astype(np.uint8)
        pings[k] = replace(pings[k], image=water)
    times = np.array([p.time for p in pings])
    unknown = (times > times[40]) & (times < times[44])
    truth_at = {p.time: t for p, t in zip(pings, day.truth, strict=True)}

    def vehicle_at(stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        poses = np.array(
            [
                [
                    truth_at[s]["local_east"],
                    truth_at[s]["local_north"],
                    math.radians(truth_at[s]["grid_heading_deg"]),
                ]
                for s in stamps
            ]
        )
        return poses, ~np.isin(stamps, times[unknown])

    def tilt_at(stamp: float) -> Attitude:
        return _attitude(truth_at[stamp])

    class Counting(InlinePool):
        """Counts the answers taken from it."""

        taken = 0

        def submit(self, task: Any, job: Any) -> Any:
            done = super().submit(task, job)
            pool = self

            class Taken:
                def result(self) -> Any:
                    pool.taken += 1
                    return done.result()

            return Taken()

    mount = day.mount
    args = (vehicle_at, mount.sonar_pose, tilt_at, _head(mount), mount.down_m)
    for interval in (0.0, 0.5, 1.3):
        params = replace(SonarDepthParams(), sounding_interval_s=interval)
        here = sonar_soundings(pings, *args, params)
        pool = Counting()
        pooled = sonar_soundings(pings, *args, params, pool)
        assert len(here[0]) > 100
        np.testing.assert_array_equal(pooled[0], here[0])
        np.testing.assert_array_equal(pooled[1], here[1])
        # Nearly every ping sounded was sounded ahead (those right after water alone or
        # an unknown pose are sounded here).
        sounded_pings = len(set(here[1]))
        assert pool.taken >= sounded_pings - 4, (interval, pool.taken, sounded_pings)
    sounded = set(here[1])
    assert not sounded & {pings[k].time for k in (3, 4, 17, 30)}
    assert not sounded & set(times[unknown])
