"""The simulator as wide as the world: seabed types, slopes, undulation, tide, sonar set-ups,
a downward echosounder, RTK GNSS and the wide field day, each checked against the physics
it stands for (and the old surveys left exactly as they were)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil

from tools.sim import SCENARIOS, resolve_scenario, simulate
from tools.sim.fieldday import FIELD_DAY, OCULUS_RATES_HZ, draw_field_day
from tools.sim.scenarios import SEABED_TYPES
from tools.sim.seabed import Seabed, generate_seabed
from tools.sim.sonar import SonarModel, SonarPose, render_ping
from tools.sim.survey import component_rng, prepare_survey
from tools.sim.swath import lane_spacing_for, range_resolution_for

FAST = {"n_beams": 16, "range_resolution_m": 0.1}


def day(name: str, seed: int, **overrides: object):
    return draw_field_day(resolve_scenario(name, **overrides), component_rng(seed, "field_day"))


# Drawn before the wide world was added (the code at 38b9252): the same seeds must still
# draw exactly these values, so the surveys of the accuracy matrix do not change.
BEFORE = {
    ("quadrats", 1): {
        "gps_bias_sigma_m": 1.0283895124339746,
        "compass_bias_deg": 3.625029833404546,
        "roll_deg": 2.208448346141246,
    },
    ("quadrats", 2): {
        "gps_bias_sigma_m": 1.1211313056454382,
        "compass_bias_deg": -1.519803573474913,
        "ripple_wavelength_m": 0.43751834602857087,
    },
    ("farm", 3): {
        "gps_bias_sigma_m": 1.3416232299606707,
        "compass_bias_deg": 4.236770957478614,
        "ripple2_bearing_deg": 105.55887032451724,
    },
    ("hectare", 4): {
        "gps_bias_sigma_m": 1.0999857049699435,
        "compass_bias_deg": 1.197548168888459,
        "ripple_wavelength_m": 0.2964725940009046,
    },
}


@pytest.mark.parametrize(("name", "seed"), sorted(BEFORE))
def test_old_scenarios_draw_what_they_drew(name: str, seed: int):
    s, record = day(name, seed)
    assert set(record["drawn"]) == {d.field for d in FIELD_DAY}
    assert "wide" not in record
    for field, value in BEFORE[(name, seed)].items():
        assert getattr(s, field) == value, field
    assert s.seabed_type == "sand" and s.gnss_kind == "m8n" and not s.echosounder
    assert s.tide_rate_mps == 0.0 and s.undulation_amplitude_m == 0.0


def test_wide_draws_span_the_world_and_leave_the_old_draws():
    days = [day("field", seed)[0] for seed in range(1, 51)]
    # The wide draws come from a stream of their own: the old table draws what it drew.
    plain = day("quadrats", 7)[0]
    wide7 = days[6]
    assert all(getattr(wide7, d.field) == getattr(plain, d.field) for d in FIELD_DAY)

    def values(name: str) -> np.ndarray:
        return np.array([getattr(d, name) for d in days], dtype=float)

    slope = np.hypot(values("seabed_slope_east"), values("seabed_slope_north"))
    assert slope.max() <= 0.1 + 1e-12 and slope.max() > 0.06 and slope.min() < 0.02
    bearing = np.degrees(np.arctan2(values("seabed_slope_east"), values("seabed_slope_north")))
    assert np.ptp(np.mod(bearing, 360.0)) > 270.0  # every direction
    depth = values("water_depth_m")
    assert 0.8 <= depth.min() < 1.5 and 5.0 < depth.max() <= 6.0
    reach = values("range_m")
    assert 3.0 <= reach.min() < 7.0 and 18.0 < reach.max() <= 20.0
    tilt = values("tilt_deg")
    assert 10.0 <= tilt.min() < 13.0 and 26.0 < tilt.max() <= 30.0
    speed = values("speed_mps")
    assert 0.3 <= speed.min() < 0.45 and 1.05 < speed.max() <= 1.2
    tide = values("tide_rate_mps") * 3600.0
    assert -0.3 <= tide.min() < -0.2 and 0.2 < tide.max() <= 0.3
    assert set(values("ping_rate_hz")) == set(OCULUS_RATES_HZ)
    assert {d.seabed_type for d in days} == set(SEABED_TYPES)
    assert 15 <= sum(d.echosounder for d in days) <= 35
    assert 8 <= sum(d.gnss_kind == "rtk" for d in days) <= 26
    assert all(d.gps_rate_hz in (5.0, 10.0) for d in days if d.gnss_kind == "rtk")
    # How the sonar sends its pings (a stream of its own: the draws above unchanged).
    assert 8 <= sum(d.ping_layout == 1 for d in days) <= 26
    assert 8 <= sum(d.sample_bits == 16 for d in days) <= 26
    assert 8 <= sum(not d.gain_rows for d in days) <= 26
    formats = {(d.ping_layout, d.sample_bits, d.gain_rows) for d in days}
    assert len(formats) >= 6  # of the 8
    undulating = values("undulation_amplitude_m")
    assert 15 <= np.count_nonzero(undulating) <= 35 and undulating.max() <= 0.2
    assert np.all(undulating <= values("undulation_wavelength_m") / 160.0 + 1e-12)
    for d in days:
        altitude = d.water_depth_m - 0.2
        # The boresight meets the bed within the range the crew set, the lanes overlap.
        assert (
            altitude / math.sin(math.radians(d.tilt_deg)) <= d.range_m * 1.0001 or d.range_m == 20
        )
        assert d.range_resolution_m == range_resolution_for(d.range_m)
        assert d.lane_spacing_m == lane_spacing_for(
            d.range_m, altitude, d.tilt_deg, d.fan_deg, d.vertical_aperture_deg
        )
        assert 16.0 <= d.lane_length_m <= 60.0
        # The bed under the lanes stays at least 0.5 m deep.
        half_n = d.lane_length_m / 2 + d.run_in_m  # the lanes run north (lane_bearing 0)
        half_e = d.lane_spacing_m * (d.n_lanes - 1) / 2 + min(d.turn_radius_m, d.lane_spacing_m / 2)
        shallowest = d.water_depth_m - abs(d.seabed_slope_east) * half_e
        shallowest -= abs(d.seabed_slope_north) * half_n + d.undulation_amplitude_m
        assert shallowest >= 0.5 - 1e-9


def test_a_pinned_field_keeps_its_value_and_the_derived_ones_follow():
    s, record = day("field", 3, range_m=5.0, seabed_type="mud")
    assert s.range_m == 5.0 and s.seabed_type == "mud"
    assert s.range_resolution_m == 0.01
    assert "range_m" not in record["drawn"] and "range_m" in record["explicit"]
    assert record["wide"]["draws"]["seabed_type"] in SEABED_TYPES


def test_named_scenarios_are_what_users_reported():
    shore, mud, deep, rtk, field = (SCENARIOS[n] for n in ("shore", "mud", "deep", "rtk", "field"))
    head = shore.mount_z_m - shore.antenna_height_m
    lanes = (shore.n_lanes - 1) / 2 * shore.lane_spacing_m
    low = shore.water_depth_m - shore.seabed_slope_east * lanes - head
    high = shore.water_depth_m + shore.seabed_slope_east * lanes - head
    assert low == pytest.approx(1.1, abs=0.05) and high == pytest.approx(2.1, abs=0.05)
    assert shore.echosounder and shore.flavour == "ardupilot" and shore.gnss_kind == "m8n"
    assert mud.seabed_type == "mud"
    assert deep.range_m == 10.0 and deep.tilt_deg == 25.0 and deep.speed_mps == 0.9
    assert deep.lane_spacing_m > 6.0 and 3.0 <= deep.water_depth_m <= 4.0
    assert rtk.gnss_kind == "rtk" and day("rtk", 1)[0].compass_bias_deg == 3.0
    assert field.wide and field.quadrat_arrays == SCENARIOS["quadrats"].quadrat_arrays


def _bed(kind: str, seed: int = 3) -> Seabed:
    s = dataclasses.replace(resolve_scenario("quadrats", randomise=False), seabed_type=kind)
    return generate_seabed(s, (10.0, 10.0, 22.0, 22.0), np.random.default_rng(seed))


def _ripple_peak(bed: Seabed) -> float:
    """How far the height map's spectral energy (summed over rings, log bands) at its
    strongest wavelength within 0.2-0.5 m stands above the bands 1.6 times longer and
    shorter: a ripple train is a sharp peak there."""
    z = bed.height - bed.height.mean()
    z = np.clip(z, np.percentile(z, 0.5), np.percentile(z, 99.5))  # the objects out
    power = np.abs(np.fft.fft2(z)) ** 2
    ky = np.fft.fftfreq(z.shape[0], bed.resolution)
    kx = np.fft.fftfreq(z.shape[1], bed.resolution)
    k = np.hypot(ky[:, None], kx[None, :]).ravel()
    edges = np.geomspace(1 / 3.0, 1 / 0.04, 30)  # cycles per metre
    which = np.digitize(k, edges)
    energy = np.array([power.ravel()[which == i].sum() for i in range(1, len(edges))])
    wavelength = 1.0 / np.sqrt(edges[1:] * edges[:-1])
    band = np.nonzero((wavelength > 0.2) & (wavelength < 0.5))[0]
    top = band[np.argmax(energy[band])]
    step = round(math.log(1.6) / math.log(edges[1] / edges[0]))
    return float(energy[top] / max(energy[top - step], energy[top + step]))


def test_each_seabed_type_has_its_physics():
    beds = {kind: _bed(kind) for kind in SEABED_TYPES}

    def rel_spread(bed: Seabed) -> float:
        refl = bed.reflectivity.astype(float)
        clean = refl[refl < np.percentile(refl, 99)]  # leave the few objects out
        return float(np.std(clean) / np.mean(clean))

    def fine_roughness(bed: Seabed, where: np.ndarray | None = None) -> float:
        """RMS height (m) about a 5 cm smoothing: the centimetre-scale relief."""
        import cv2

        h = bed.height.astype(np.float32)
        rough = (h - cv2.GaussianBlur(h, (0, 0), 0.05 / bed.resolution)) ** 2
        return float(np.sqrt(np.mean(rough if where is None else rough[where])))

    def in_patches(bed: Seabed) -> np.ndarray:
        rows, cols = np.indices(bed.shape)
        east = bed.west + (cols + 0.5) * bed.resolution
        north = bed.north - (rows + 0.5) * bed.resolution
        inside = np.zeros(bed.shape, bool)
        for patch in bed.gravel_patches:
            d = np.hypot(east - patch.centre_east, north - patch.centre_north)
            inside |= d < 0.6 * patch.radius_m
        return inside

    sand, mud, shell, gravel = beds["sand"], beds["mud"], beds["shell"], beds["gravel"]
    # Soft mud: darker, a few percent of texture (far below sand's), mm of relief.
    assert mud.reflectivity.mean() < 0.6 * sand.reflectivity.mean()
    assert 0.02 < rel_spread(mud) < 0.1 and rel_spread(mud) < 0.35 * rel_spread(sand)
    mud_relief = float(np.std(mud.height[mud.height < np.percentile(mud.height, 99)]))
    assert 0.0008 < mud_relief < 0.0025
    # Ripples make a spectral peak at their wavelength on sand; mud has none.
    assert _ripple_peak(sand) > 5.0 and _ripple_peak(mud) < 1.5
    # Gravel: rougher at centimetre scales, brighter; shell hash: many bright scatterers.
    patches = in_patches(gravel)
    assert fine_roughness(gravel, patches) > 3.0 * fine_roughness(sand)
    assert gravel.reflectivity[patches].mean() > 1.4 * sand.reflectivity.mean()
    assert len(gravel.gravel_patches) >= 1
    bright = 0.5 * 255
    assert np.mean(shell.reflectivity > bright) > 5 * np.mean(sand.reflectivity > bright)
    assert np.std(shell.height) < np.std(sand.height)  # the shell armour damps the ripples
    # Debris on smooth mud: sparse, metres apart, decimetres tall.
    debris = beds["objects"].debris
    assert 3 <= len(debris) <= 25
    centres = np.array([[d.centre_east, d.centre_north] for d in debris])
    gaps = np.hypot(*(centres[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    assert np.min(gaps + 99 * np.eye(len(debris))) >= 2.0
    assert beds["objects"].height.max() > 0.1
    # Same seed, same bed.
    assert np.array_equal(_bed("gravel").reflectivity, gravel.reflectivity)


def _first_echo(model: SonarModel, pose: SonarPose, bed: Seabed, empty: Seabed) -> float:
    """Slant range (m) of the first bin of the centre beam brighter than the empty water."""
    image = render_ping(model, pose, bed, None).astype(int)
    water = render_ping(model, pose, empty, None).astype(int)
    beam = model.n_beams // 2
    rows = np.nonzero(image[:, beam] > water[:, beam] + 1)[0]
    return float(model.ranges_m[rows[0]])


def test_the_near_edge_follows_the_slope():
    s = resolve_scenario("quadrats", randomise=False, n_beams=17, range_m=6.0, tilt_deg=15.0)
    model = SonarModel.from_scenario(s, np.random.default_rng(0))
    pose = SonarPose(np.array([0.0, 0.0, 0.2]), model.mount_rotation)  # level, heading north

    def plane(depth: float, east: float = 0.0, north: float = 0.0) -> Seabed:
        shape = (600, 400)  # 5 cm cells, 30 m x 20 m around the sonar
        return Seabed(
            np.full(shape, 100, np.uint8), np.zeros(shape, np.float32), -10.0, 25.0, 0.05,
            depth, east, north,
        )  # fmt: skip

    empty = plane(100.0)
    flat = _first_echo(model, pose, plane(2.0), empty)
    assert flat == pytest.approx(1.8, abs=0.011)  # the nearest bed: straight down
    # Rising ahead (shallower to the north): the nearest point is the foot of the
    # perpendicular, h / sqrt(1 + s^2) away, inside the beam's plane.
    up = _first_echo(model, pose, plane(2.0, north=-0.3), empty)
    assert up == pytest.approx(1.8 / math.sqrt(1 + 0.3**2), abs=0.011)
    # Sloping across the beam: the centre beam's plane still meets it 1.8 m down.
    across = _first_echo(model, pose, plane(2.0, east=0.3), empty)
    assert across == pytest.approx(1.8, abs=0.011)


def test_the_tide_lifts_the_head():
    small = {**FAST, "randomise": False, "max_pings": 40, "seabed_type": "mud"}
    still = prepare_survey(resolve_scenario("quadrats", **small), 2)
    rising = prepare_survey(resolve_scenario("quadrats", tide_rate_mps=1e-3, **small), 2)
    t = rising.plan.acquisition - rising.motion.start
    lift = rising.frames.state["altitude"] - still.frames.state["altitude"]
    np.testing.assert_allclose(lift, 1e-3 * t, atol=1e-9)
    np.testing.assert_allclose(rising.frames.state["water_level"], 1e-3 * t, atol=1e-12)
    assert np.all(rising.frames.state["altitude_normal"] <= rising.frames.state["altitude"])


@pytest.fixture(scope="module")
def slope_survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("slope")
    simulate(
        "quadrats", 4, out, duration_s=60.0, seabed_type="mud", water_depth_m=2.5,
        seabed_slope_north=0.1, seabed_slope_east=0.0, echosounder=True,
        echosounder_dropout=0.15, gnss_kind="rtk", gps_rate_hz=5.0, rtk_float_interval_s=20.0,
        **FAST,
    )  # fmt: skip
    return out


def test_the_echosounder_reports_the_nearest_bottom_in_nav_tlog(slope_survey: Path):
    truth = json.loads((slope_survey / "truth.json").read_text())
    echo = truth["sensors"]["echosounder"]["soundings"]
    vertical, nearest = np.array(echo["vertical_m"]), np.array(echo["nearest_m"])
    kind = np.array(echo["kind"])
    # On a 10 % slope the nearest bottom in the cone is the perpendicular: cos(slope) of
    # the vertical distance.
    cos_slope = math.cos(math.atan(0.1))
    assert np.median(nearest / vertical) == pytest.approx(cos_slope, abs=0.001)
    ok = kind == "ok"
    reported = np.array([np.nan if v is None else v for v in echo["reported_m"]])
    assert np.median(reported[ok] / vertical[ok]) == pytest.approx(cos_slope, abs=0.006)
    assert {"low_signal", "missing"} <= set(kind.tolist())

    log = mavutil.mavlink_connection(str(slope_survey / "nav.tlog"))
    sensors: list[Any] = []
    finders: list[Any] = []
    while (msg := log.recv_match(type=["DISTANCE_SENSOR", "RANGEFINDER"])) is not None:
        (sensors if msg.get_type() == "DISTANCE_SENSOR" else finders).append(msg)
    assert len(sensors) == int(np.sum(kind != "missing")) and len(finders) == len(sensors)
    assert all(
        m.orientation == 25 and m.min_distance == 30 and m.max_distance == 3000 for m in sensors
    )
    cm = np.array([m.current_distance for m in sensors])
    sent = reported[kind != "missing"]
    np.testing.assert_allclose(cm, np.rint(sent * 100), atol=1)  # centimetres
    np.testing.assert_allclose([m.distance for m in finders], sent, atol=1e-4)  # metres
    quality = np.array([m.signal_quality for m in sensors])
    assert np.all((quality >= 1) & (quality <= 100)) and np.sum(quality <= 10) > 0
    assert all(m.covariance == 255 for m in sensors)  # ArduPilot does not know it

    site = (slope_survey / "site.toml").read_text()
    assert "[echosounder]" in site and "mount_x_m = 0.2" in site


def test_rtk_fixes_are_centimetric(slope_survey: Path):
    log = mavutil.mavlink_connection(str(slope_survey / "nav.tlog"))
    fixes: list[Any] = []
    while (msg := log.recv_match(type="GPS_RAW_INT")) is not None:
        fixes.append(msg)
    kinds = np.array([m.fix_type for m in fixes])
    h_acc = np.array([m.h_acc for m in fixes])  # mm
    assert len(fixes) >= 5 * 55 and set(kinds.tolist()) <= {5, 6}
    assert np.mean(kinds == 6) > 0.6 and np.any(kinds == 5)
    assert np.all((h_acc[kinds == 6] >= 10) & (h_acc[kinds == 6] <= 20))
    assert np.all(h_acc[kinds == 5] > 80)
    truth = json.loads((slope_survey / "truth.json").read_text())
    fix = truth["sensors"]["gps"]["fixes"]
    fixed = np.array(fix["fix_type"]) == 6
    error = np.hypot(fix["error_east_m"], fix["error_north_m"])
    assert np.sqrt(np.mean(error[fixed] ** 2)) < 0.05


def test_a_wide_field_day_is_deterministic(tmp_path: Path):
    small = {**FAST, "max_pings": 5, "range_m": 4.0}
    a = simulate("field", 11, tmp_path / "a", **small)
    b = simulate("field", 11, tmp_path / "b", **small)
    c = simulate("field", 12, tmp_path / "c", **small)
    for name in ("sonar.oculus", "nav.tlog", "truth.json", "seabed.tif", "site.toml"):
        assert (a.out / name).read_bytes() == (b.out / name).read_bytes(), name
    assert (a.out / "truth.json").read_bytes() != (c.out / "truth.json").read_bytes()
    record = json.loads((a.out / "truth.json").read_text())["field_day"]
    assert record["wide"]["draws"]["seabed_type"] in SEABED_TYPES
    assert "range_m" in record["explicit"] and "water_depth_m" in record["drawn"]


@pytest.mark.parametrize(
    ("layout", "bits", "gains"), [(1, 16, False), (1, 8, True), (2, 16, True), (2, 8, False)]
)
def test_the_sonar_sends_its_pings_as_the_day_says(
    tmp_path: Path, layout: int, bits: int, gains: bool
) -> None:
    """The receiver's formats reach the log as a real unit writes them: v1 with msgVersion
    0, 16-bit samples the same echo as the 8-bit ones, gain rows or none."""
    from drivers.oculus import iter_pings, summarize_oculus_log

    common = {**FAST, "max_pings": 4, "randomise": False}
    simulate("quadrats", 3, tmp_path / "a", **common, ping_layout=layout, sample_bits=bits,
             gain_rows=gains)  # fmt: skip
    simulate("quadrats", 3, tmp_path / "b", **common)  # v2, 8-bit, gain rows
    summary = summarize_oculus_log(tmp_path / "a" / "sonar.oculus")
    assert summary["ping_versions"] == [layout]
    assert summary["msg_versions"] == [0 if layout == 1 else 2]
    assert summary["sample_bits"] == [bits] and summary["gain_rows"] == [gains]
    for got, base in zip(
        iter_pings(tmp_path / "a" / "sonar.oculus"),
        iter_pings(tmp_path / "b" / "sonar.oculus"),
        strict=True,
    ):
        assert got.time == base.time and got.ping_id == base.ping_id
        assert (got.gains is not None) == gains and (got.heading_rad is not None) == (layout == 2)
        if bits == 16:
            assert got.image.dtype == np.uint16
            # The same echo, 257 times finer: within half an 8-bit step of the 8-bit image.
            np.testing.assert_allclose(got.image / 257.0, base.image, atol=0.5 + 1e-3)
            assert np.count_nonzero(got.image % 257) > got.image.size // 2
        else:
            np.testing.assert_array_equal(got.image, base.image)
