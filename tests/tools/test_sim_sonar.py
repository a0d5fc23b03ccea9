"""The sonar forward model: geometry, shadows, the bearing table, and the .oculus log."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import cast

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from tools.sim import resolve_scenario, simulate
from tools.sim.seabed import Seabed
from tools.sim.sonar import (
    SonarModel,
    bearing_table,
    footprint,
    render_ping,
    sonar_pose,
)
from tools.sim.trajectory import euler_to_matrix

DEPTH_M = 1.2
SONAR_DEPTH_M = 0.2  # the antenna sits 0.1 m above the water, the sonar 0.3 m below it


def flat_seabed(size_m: float = 14.0, res: float = 0.01, refl: int = 40) -> Seabed:
    """A uniform, flat seabed centred on the local origin."""
    n = round(size_m / res)
    return Seabed(
        reflectivity=np.full((n, n), refl, np.uint8),
        height=np.zeros((n, n), np.float32),
        west=-size_m / 2,
        north=size_m / 2,
        resolution=res,
        depth0=DEPTH_M,
        slope_east=0.0,
        slope_north=0.0,
    )


def model(n_beams: int = 256, range_resolution_m: float = 0.01) -> SonarModel:
    s = resolve_scenario("quadrats", n_beams=n_beams, range_resolution_m=range_resolution_m)
    return SonarModel.from_scenario(s, np.random.default_rng(0))


def pose_for(m: SonarModel, heading: float, pitch: float, roll: float):
    r = euler_to_matrix(np.array(heading), np.array(pitch), np.array(roll))
    antenna = np.array([0.0, 0.0, SONAR_DEPTH_M - 0.3])
    return sonar_pose(antenna, r, m)


def test_bearing_table_is_denser_in_the_centre_and_spans_the_fan():
    b = np.degrees(bearing_table(512, 130.0, 1.3))
    assert b[0] == pytest.approx(-65.0, abs=0.01) and b[-1] == pytest.approx(65.0, abs=0.01)
    assert np.all(np.diff(b) > 0)
    np.testing.assert_allclose(b, -b[::-1], atol=1e-9)
    spacing = np.diff(b)
    centre = spacing[len(spacing) // 2 - 5 : len(spacing) // 2 + 5].mean()
    edge = spacing[:10].mean()
    assert edge / centre == pytest.approx(1.3, abs=0.05)
    # Quantised to 1/100 degree, as the sonar sends them.
    np.testing.assert_allclose(b * 100, np.rint(b * 100), atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(
    heading=st.floats(0.0, 2 * math.pi),
    pitch=st.floats(-0.08, 0.08),
    roll=st.floats(-0.08, 0.08),
    ground_range=st.floats(2.6, 4.6),
    azimuth=st.floats(-0.8, 0.8),
)
def test_a_bright_point_appears_at_its_range_bin_and_beam(
    heading, pitch, roll, ground_range, azimuth
):
    """Place a small bright patch on the seabed; it lights the (range, beam) cell that
    the 3-D geometry (tilt, altitude, roll, pitch) predicts, computed independently here
    by transforming the vector to the target into the sonar frame: the line array's
    bearing is asin(p_y / |p|), the angle about the array axis atan2(p_z, p_x)."""
    m = model()
    pose = pose_for(m, heading, pitch, roll)
    bearing = heading + azimuth
    target_n = pose.position_ned[0] + ground_range * math.cos(bearing)
    target_e = pose.position_ned[1] + ground_range * math.sin(bearing)
    to_target = np.array([target_n, target_e, DEPTH_M]) - pose.position_ned
    in_sonar = pose.rotation.T @ to_target
    slant = float(np.linalg.norm(to_target))
    beam_bearing = math.asin(in_sonar[1] / slant)
    psi = math.atan2(in_sonar[2], in_sonar[0])
    assume(abs(psi) < math.radians(10))  # inside the vertical beam

    plain = flat_seabed()
    bright = flat_seabed()
    col, row = bright.pixel(np.array(target_e), np.array(target_n))
    c, r = int(np.floor(col + 0.5)), int(np.floor(row + 0.5))
    bright.reflectivity[r - 1 : r + 2, c - 1 : c + 2] = 255
    diff = render_ping(m, pose, bright, None).astype(int) - render_ping(m, pose, plain, None)
    peak_row, peak_beam = np.unravel_index(np.argmax(diff), diff.shape)
    expected_row = int(slant / m.range_resolution_m)
    expected_beam = int(np.argmin(np.abs(m.bearings_rad - beam_bearing)))
    assert abs(int(peak_row) - expected_row) <= 2
    assert abs(int(peak_beam) - expected_beam) <= 1


@settings(max_examples=20, deadline=None)
@given(
    heading=st.floats(0.0, 2 * math.pi),
    pitch=st.floats(-0.1, 0.1),
    roll=st.floats(-0.1, 0.1),
    slope_e=st.floats(-0.03, 0.03),
    slope_n=st.floats(-0.03, 0.03),
)
def test_footprint_lies_on_the_seabed_at_the_slant_range(heading, pitch, roll, slope_e, slope_n):
    m = model(n_beams=64, range_resolution_m=0.05)
    bed = flat_seabed(res=0.05)
    bed = Seabed(**{**bed.__dict__, "slope_east": slope_e, "slope_north": slope_n})
    pose = pose_for(m, heading, pitch, roll)
    fp = footprint(m, pose, bed)
    depth = bed.depth_at(fp.east.astype(np.float64), fp.north.astype(np.float64))
    dist = np.sqrt(
        (fp.north - pose.position_ned[0]) ** 2
        + (fp.east - pose.position_ned[1]) ** 2
        + (depth - pose.position_ned[2]) ** 2
    )
    ranges = np.broadcast_to(m.ranges_m[:, None], dist.shape)
    np.testing.assert_allclose(dist[fp.valid], ranges[fp.valid], rtol=1e-4, atol=1e-4)
    # Nearer than the seabed is water: the first valid bin is at about the altitude.
    first = m.ranges_m[np.argmax(fp.valid.any(axis=1))]
    assert first == pytest.approx(fp.altitude, abs=0.1)


def test_the_near_field_is_dark_and_the_swath_is_a_band():
    m = model()
    pose = pose_for(m, 0.0, 0.0, 0.0)
    image = render_ping(m, pose, flat_seabed(refl=90), None)
    profile = image[:, 96:160].mean(axis=1)
    r = m.ranges_m
    # The vertical beam (15 degree tilt, 20 degree aperture) lights slant ranges of about
    # 2.4-5 m from 1 m up; inside about 1.6 m the echo is far below the band.
    assert profile[(r > 0.3) & (r < 1.0)].max() < 25  # water column: noise floor only
    assert profile[(r > 1.2) & (r < 1.6)].mean() < 0.5 * profile[(r > 2.5) & (r < 3.5)].mean()
    assert profile[(r > 2.5) & (r < 3.5)].mean() > 60


def test_a_raised_object_casts_a_shadow_behind_it():
    m = model()
    pose = pose_for(m, 0.0, 0.0, 0.0)
    bed = flat_seabed(refl=120)
    # A 10 cm high, 10 cm deep wall across the centre beams, 3 m ahead on the ground.
    ahead = pose.position_ned[0] + 3.0
    _, row = bed.pixel(np.array(0.0), np.array(ahead))
    r0 = round(float(row))
    bed.height[r0 - 5 : r0 + 5, 600:800] = 0.10
    image = render_ping(m, pose, bed, None).astype(float)
    centre = image[:, 120:136].mean(axis=1)
    flat = render_ping(m, pose, flat_seabed(refl=120), None).astype(float)[:, 120:136].mean(axis=1)
    altitude = DEPTH_M - pose.position_ned[2]
    wall = math.hypot(3.0, altitude)
    # Shadow length on the ground: height * ground_range / (altitude - height) ~ 0.33 m.
    r = m.ranges_m
    behind = (r > wall + 0.1) & (r < wall + 0.25)
    beyond = (r > wall + 0.5) & (r < wall + 0.7)
    assert centre[behind].mean() < 0.35 * flat[behind].mean()
    assert centre[beyond].mean() == pytest.approx(flat[beyond].mean(), rel=0.1)
    # The face towards the sonar is brighter than sand.
    face = (r > wall - 0.08) & (r < wall + 0.02)
    assert centre[face].max() > 1.3 * flat[face].max()


def _spherical_footprint(pose, bearing: float, slant: float) -> np.ndarray:
    """Where the spherical (azimuth/elevation) model would put the echo of ``bearing`` at
    ``slant`` on the flat bed: d = (cos phi cos theta, cos phi sin theta, sin phi), phi
    found by bisection so that the point lies on the bed."""
    lo, hi = -math.pi / 2 + 1e-6, math.pi / 2 - 1e-6  # depth grows with phi here
    for _ in range(80):
        phi = (lo + hi) / 2
        d = np.array([math.cos(phi) * math.cos(bearing), math.cos(phi) * math.sin(bearing),
                      math.sin(phi)])  # fmt: skip
        depth = (pose.position_ned + slant * pose.rotation @ d)[2]
        lo, hi = (phi, hi) if depth < DEPTH_M else (lo, phi)
    return pose.position_ned + slant * pose.rotation @ d


def test_a_beam_is_a_cone_about_the_array_axis():
    """The echo of beam theta at slant range r lies where sin theta = p_y / r (p in the
    sonar frame), on the seabed: at 60 degrees and 2.5 m some 20 cm from where the
    spherical model would put it; the rendered image lights that beam."""
    m = model(n_beams=256)
    pose = pose_for(m, 0.3, 0.02, -0.03)
    bed = flat_seabed()
    fp = footprint(m, pose, bed)
    beam = int(np.argmin(np.abs(m.bearings_rad - math.radians(60.0))))
    row = int(np.argmin(np.abs(m.ranges_m - 2.5)))
    theta, slant = float(m.bearings_rad[beam]), float(m.ranges_m[row])
    assert fp.valid[row, beam]
    point = np.array([fp.north[row, beam], fp.east[row, beam], DEPTH_M])
    p = pose.rotation.T @ (point - pose.position_ned)
    assert np.linalg.norm(p) == pytest.approx(slant, abs=2e-4)
    assert p[1] / slant == pytest.approx(math.sin(theta), abs=2e-5)
    spherical = _spherical_footprint(pose, theta, slant)
    assert 0.15 < float(np.linalg.norm(spherical[:2] - point[:2])) < 0.4

    # A bright patch there lights beam theta, not the spherical model's bearing of it
    # (with a vertical aperture wide enough to see a bed this far down the cone).
    wide = dataclasses.replace(m, vertical_aperture_rad=math.radians(100.0))
    bright = flat_seabed()
    col, r = bright.pixel(np.array(point[1]), np.array(point[0]))
    c0, r0 = int(np.floor(col + 0.5)), int(np.floor(r + 0.5))
    bright.reflectivity[r0 - 1 : r0 + 2, c0 - 1 : c0 + 2] = 255
    diff = render_ping(wide, pose, bright, None).astype(int) - render_ping(wide, pose, bed, None)
    peak_row, peak_beam = np.unravel_index(np.argmax(diff), diff.shape)
    assert abs(int(peak_row) - row) <= 2 and abs(int(peak_beam) - beam) <= 1
    spherical_bearing = math.atan2(p[1], p[0])
    assert abs(spherical_bearing - theta) > math.radians(4.0)


def test_the_lit_swath_bends_away_at_wide_bearings():
    """The vertical beam is a band of psi about the array axis: from a level sonar, the
    bed enters it where cos(theta) sin(psi + tilt) = altitude / r, so the lit band starts
    twice as far out at 60 degrees as ahead (a spherical fan would light both alike)."""
    m = model(n_beams=256, range_resolution_m=0.02)
    pose = pose_for(m, 0.0, 0.0, 0.0)
    shallow = dataclasses.replace(flat_seabed(refl=90), depth0=SONAR_DEPTH_M + 0.5)
    image = render_ping(m, pose, shallow, None).astype(float)
    r = m.ranges_m
    past_ringdown = r > 0.3

    def onset(bearing_deg: float) -> float:
        beam = int(np.argmin(np.abs(m.bearings_rad - math.radians(bearing_deg))))
        profile = np.where(past_ringdown, image[:, beam - 1 : beam + 2].mean(axis=1), 0.0)
        return float(r[np.argmax(profile > 0.5 * profile.max())])

    ratio = onset(60.0) / onset(0.0)
    assert ratio == pytest.approx(1.0 / math.cos(math.radians(60.0)), rel=0.2)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim_sonar")
    simulate("quadrats", 3, out, max_pings=5)
    return out


def test_the_oculus_log_reads_back_with_the_real_layout(short_run: Path):
    import json

    from drivers.oculus.logfile import iter_pings

    pings = list(iter_pings(short_run / "sonar.oculus"))
    truth = json.loads((short_run / "truth.json").read_text())
    assert len(pings) == 5 == len(truth["pings"])
    for ping, row in zip(pings, truth["pings"], strict=True):
        assert ping.n_beams == 512
        assert ping.n_ranges == 500
        assert ping.image.dtype == np.uint8
        assert ping.gains is not None and ping.gains.shape == (500,)
        assert 0.5 * 65536 < np.median(ping.gains) < 2 * 65536
        assert ping.time == pytest.approx(row["time"], abs=1e-6)
        assert ping.ping_id == row["ping_id"]
        assert ping.range_resolution_m == pytest.approx(0.01)
        assert ping.master_mode == 1
        assert ping.extra["layout_version"] == 2
    b = np.degrees(pings[0].bearings_rad)
    assert b[0] == pytest.approx(-65.0, abs=0.01) and b[-1] == pytest.approx(65.0, abs=0.01)
    spacing = np.diff(b)
    assert spacing[0] > 1.2 * spacing[256]
    np.testing.assert_allclose(b, truth["sonar"]["bearings_deg"], atol=1e-6)


def test_overrides_change_the_sonar(tmp_path: Path):
    from drivers.oculus.logfile import iter_pings

    summary = simulate(
        "quadrats", 3, tmp_path, max_pings=3, n_beams=128, range_resolution_m=0.02,
        sonar_latency_s=0.05, sonar_latency_jitter_s=0.0,
    )  # fmt: skip
    pings = list(iter_pings(summary.sonar_path))
    assert [p.n_beams for p in pings] == [128] * 3
    assert pings[0].n_ranges == 250
    import json

    truth = json.loads(summary.truth_path.read_text())
    assert truth["sonar"]["latency_s"] == 0.05  # the override wins the field day's draw
    for row in truth["pings"]:
        assert row["time"] - row["acquisition_time"] == pytest.approx(0.05, abs=1e-6)


@pytest.mark.parametrize("rate_hz", [2.0, 5.0, 10.0])
def test_ping_rates_and_the_latency_of_the_day(tmp_path: Path, rate_hz: float):
    """2, 5 and 10 Hz all work; each ping's receive stamp is its acquisition plus the
    drawn latency (0.03-0.12 s) and a small queueing tail."""
    import json

    from drivers.oculus.logfile import iter_pings
    from drivers.oculus.protocol import PingRate

    summary = simulate(
        "quadrats", 4, tmp_path, duration_s=8.0, ping_rate_hz=rate_hz, n_beams=16,
        range_resolution_m=0.1,
    )  # fmt: skip
    truth = json.loads(summary.truth_path.read_text())
    pings = list(iter_pings(summary.sonar_path))
    acquired = np.array([p["acquisition_time"] for p in truth["pings"]])
    received = np.array([p["time"] for p in truth["pings"]])
    assert len(pings) == len(acquired) == pytest.approx(6.5 * rate_hz, abs=1.0)
    np.testing.assert_allclose(np.diff(acquired), 1.0 / rate_hz, atol=0.01)
    assert [p.time for p in pings] == pytest.approx(received.tolist(), abs=1e-6)
    assert {PingRate(cast(int, p.extra["ping_rate"])).hz for p in pings} == {rate_hz}
    latency = truth["sonar"]["latency_s"]
    assert 0.03 <= latency <= 0.12
    delay = received - acquired - latency
    assert np.all(delay >= 0.0) and np.all(delay <= 10 * truth["sonar"]["latency_jitter_mean_s"])
