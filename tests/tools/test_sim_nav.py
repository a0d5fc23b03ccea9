"""The simulated telemetry: read back with pymavlink, rates, units, stamps, error models."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil
from pyproj import Transformer

from tools.sim import simulate
from tools.sim.sensors import gauss_markov

# A whole quadrats survey with a tiny sonar: the telemetry is what is tested here.
FAST_SONAR = {"n_beams": 16, "range_resolution_m": 0.1}


def read_tlog(path: Path) -> dict[str, list[Any]]:
    conn = mavutil.mavlink_connection(str(path))
    messages: dict[str, list[Any]] = defaultdict(list)
    while (msg := conn.recv_match(blocking=False)) is not None:
        messages[msg.get_type()].append(msg)
    conn.close()
    return messages


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any], dict]:
    out = tmp_path_factory.mktemp("sim_nav")
    simulate("quadrats", 11, out, **FAST_SONAR)
    truth = json.loads((out / "truth.json").read_text())
    return out, truth, read_tlog(out / "nav.tlog")


def truth_at(truth: dict[str, Any], times: np.ndarray, key: str, angle: bool = False):
    """A truth column (per ping, at acquisition time) interpolated to ``times``."""
    t = np.array([p["acquisition_time"] for p in truth["pings"]])
    v = np.array([p[key] for p in truth["pings"]], float)
    if angle:
        return np.degrees(np.interp(times, t, np.unwrap(np.radians(v))))
    return np.interp(times, t, v)


def wrap180(x):
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


def sample_times(truth, msgs, field_name: str, scale: float) -> np.ndarray:
    boot = truth["time"]["autopilot_boot_time"]
    return boot + np.array([getattr(m, field_name) for m in msgs]) * scale


def test_message_types_rates_and_ids(survey):
    out, truth, msgs = survey
    duration = truth["time"]["duration_s"]
    assert set(msgs) == {
        "HEARTBEAT", "SYSTEM_TIME", "RAW_IMU", "GPS_RAW_INT", "ATTITUDE",
        "GLOBAL_POSITION_INT", "VFR_HUD",
    }  # fmt: skip
    assert len(msgs["RAW_IMU"]) / duration == pytest.approx(55.0, rel=0.03)
    assert len(msgs["GPS_RAW_INT"]) / duration == pytest.approx(2.0, rel=0.05)
    assert len(msgs["GLOBAL_POSITION_INT"]) / duration == pytest.approx(2.0, rel=0.05)
    autopilot = [m for m in msgs["HEARTBEAT"] if m.get_srcSystem() == 1]
    gcs = [m for m in msgs["HEARTBEAT"] if m.get_srcSystem() == 255]
    assert len(autopilot) / duration == pytest.approx(1.0, rel=0.05)
    assert gcs and all(m.type == mavutil.mavlink.MAV_TYPE_GCS for m in gcs)
    assert all(m.type == mavutil.mavlink.MAV_TYPE_SURFACE_BOAT for m in autopilot)
    assert all(m.autopilot == mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA for m in autopilot)
    assert all(m.get_srcComponent() == 1 for m in autopilot)
    # MAVLink 2 framing, every packet behind an 8-byte big-endian microsecond stamp.
    raw = (out / "nav.tlog").read_bytes()
    assert raw[8] == 0xFD
    assert int.from_bytes(raw[:8], "big") / 1e6 == pytest.approx(
        truth["time"]["start_time"], abs=0.1
    )


def test_stamps_are_monotonic_and_match_the_boot_clock(survey):
    _, truth, msgs = survey
    stamps = np.array(sorted(m._timestamp for ms in msgs.values() for m in ms))
    assert np.all(np.diff(stamps) >= 0)
    for name, field_name, scale in [
        ("RAW_IMU", "time_usec", 1e-6),
        ("GPS_RAW_INT", "time_usec", 1e-6),
        ("ATTITUDE", "time_boot_ms", 1e-3),
        ("SYSTEM_TIME", "time_boot_ms", 1e-3),
    ]:
        ms = msgs[name]
        delay = np.array([m._timestamp for m in ms]) - sample_times(truth, ms, field_name, scale)
        assert np.all(delay > 0.0) and np.all(delay < 0.03), name
        assert np.all(np.diff(sample_times(truth, ms, field_name, scale)) > 0), name
    for m in msgs["SYSTEM_TIME"]:
        boot = m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3
        assert boot == pytest.approx(truth["time"]["autopilot_boot_time"], abs=0.002)


def test_raw_imu_has_ardupilot_units(survey):
    _, truth, msgs = survey
    imu = msgs["RAW_IMU"]
    acc = np.array([[m.xacc, m.yacc, m.zacc] for m in imu], float)
    mag = np.array([[m.xmag, m.ymag, m.zmag] for m in imu], float)
    # milli-g: about -1000 on z (gravity through small roll/pitch), little on x/y on average.
    assert np.mean(acc[:, 2]) == pytest.approx(-1000.0, abs=15.0)
    assert abs(np.mean(acc[:, 0])) < 30 and abs(np.mean(acc[:, 1])) < 40
    # milligauss: the Chesapeake field, about 520 mG total.
    assert np.mean(np.linalg.norm(mag, axis=1)) == pytest.approx(519.0, rel=0.03)

    # mrad/s: integrating the z gyro over the first U-turn gives about 180 degrees.
    t = sample_times(truth, imu, "time_usec", 1e-6)
    heading = truth_at(truth, t, "heading_deg", angle=True)
    turning = np.abs(np.gradient(heading, t)) > 5.0
    start = int(np.argmax(turning))
    stop = start + int(np.argmin(turning[start:]))
    gz = np.array([m.zgyro for m in imu[start:stop]], float) / 1000.0
    turned = math.degrees(float(np.sum(gz[:-1] * np.diff(t[start:stop]))))
    assert turned == pytest.approx(heading[stop - 1] - heading[start], abs=6.0)
    assert abs(heading[stop - 1] - heading[start]) > 120.0


def test_compass_heading_is_truth_plus_bias_and_noise(survey):
    _, truth, msgs = survey
    compass = truth["sensors"]["compass"]
    for name, get in [
        ("GLOBAL_POSITION_INT", lambda m: m.hdg / 100.0),
        ("ATTITUDE", lambda m: math.degrees(m.yaw)),
        ("VFR_HUD", lambda m: float(m.heading)),
    ]:
        ms = msgs[name]
        if name == "VFR_HUD":  # no time field: take the receive stamp
            t = np.array([m._timestamp for m in ms]) - 0.003
        else:
            t = sample_times(truth, ms, "time_boot_ms", 1e-3)
        err = wrap180(np.array([get(m) for m in ms]) - truth_at(truth, t, "heading_deg", True))
        bias = np.interp(t, compass["samples"]["time"], compass["samples"]["bias_deg"])
        assert np.mean(err) == pytest.approx(compass["bias_deg"], abs=0.6), name
        assert np.std(err - bias) == pytest.approx(compass["noise_deg"], rel=0.35), name


def test_magnetometer_gives_the_heading_through_the_declination(survey):
    """A tilt-compensated heading from RAW_IMU's field, plus the declination, is the true
    heading plus the compass misalignment."""
    _, truth, msgs = survey
    imu = msgs["RAW_IMU"]
    t = sample_times(truth, imu, "time_usec", 1e-6)
    roll = np.radians(truth_at(truth, t, "roll_deg"))
    pitch = np.radians(truth_at(truth, t, "pitch_deg"))
    mx, my, mz = (np.array([getattr(m, k) for m in imu], float) for k in ("xmag", "ymag", "zmag"))
    xh = mx * np.cos(pitch) + (my * np.sin(roll) + mz * np.cos(roll)) * np.sin(pitch)
    yh = my * np.cos(roll) - mz * np.sin(roll)
    heading = np.degrees(np.arctan2(-yh, xh)) + truth["site"]["magnetic"]["declination_deg"]
    err = wrap180(heading - truth_at(truth, t, "heading_deg", True))
    assert np.median(err) == pytest.approx(truth["sensors"]["imu"]["mag_misalignment_deg"], abs=0.5)
    assert np.std(err) < 2.5


def gps_errors(truth, msgs):
    gps = msgs["GPS_RAW_INT"]
    t = sample_times(truth, gps, "time_usec", 1e-6)
    to_utm = Transformer.from_crs("EPSG:4326", f"EPSG:{truth['site']['epsg']}", always_xy=True)
    e, n = to_utm.transform([m.lon / 1e7 for m in gps], [m.lat / 1e7 for m in gps])
    return t, np.array(e) - truth_at(truth, t, "east"), np.array(n) - truth_at(truth, t, "north")


def test_gps_error_is_a_wandering_bias_plus_white_noise(survey):
    _, truth, msgs = survey
    model = truth["sensors"]["gps"]
    t, err_e, err_n = gps_errors(truth, msgs)
    fixes = model["fixes"]
    np.testing.assert_allclose(t, fixes["time"], atol=2e-6)
    # The log carries truth + the documented error (to the 1e-7 degree of the message);
    # the truth is known at the pings, which start a second after the log.
    pinged = t > truth["pings"][0]["acquisition_time"]
    np.testing.assert_allclose(err_e[pinged], np.array(fixes["error_east_m"])[pinged], atol=0.02)
    np.testing.assert_allclose(err_n[pinged], np.array(fixes["error_north_m"])[pinged], atol=0.02)
    # Minus the bias path, what is left is white noise of the configured size...
    bias_e, bias_n = np.array(fixes["bias_east_m"]), np.array(fixes["bias_north_m"])
    white = np.concatenate([(err_e - bias_e)[pinged], (err_n - bias_n)[pinged]])
    assert np.std(white) == pytest.approx(model["noise_m"], rel=0.2)
    # ...and the bias moves slowly: its 0.5 s steps are those of a 300 s Gauss-Markov.
    steps = np.concatenate([np.diff(fixes["bias_east_m"]), np.diff(fixes["bias_north_m"])])
    expected_step = model["bias_sigma_m"] * math.sqrt(2 * 0.5 / model["bias_tau_s"])
    assert np.std(steps) == pytest.approx(expected_step, rel=0.3)
    # Not white: the error keeps its sign over the run (a metre-scale offset).
    assert math.hypot(np.mean(err_e), np.mean(err_n)) > 5 * model["noise_m"] / math.sqrt(len(t))
    gps = msgs["GPS_RAW_INT"]
    assert {m.fix_type for m in gps} == {3}
    assert all(m.satellites_visible >= 10 and 60 <= m.eph <= 150 for m in gps)
    assert all(800 <= m.h_acc <= 3000 for m in gps)
    # Course over ground, not heading: compare with the truth course.
    moving = np.array([m.vel for m in gps]) > 50
    cog = np.array([m.cog / 100.0 for m in gps])
    course = truth_at(truth, t, "course_deg", True)
    assert np.median(np.abs(wrap180(cog - course)[moving])) < 5.0


def test_gauss_markov_has_the_configured_sigma_and_memory():
    times = np.arange(0.0, 20000.0, 0.5)
    x = gauss_markov(np.random.default_rng(5), times, 1.0, 300.0, (4,))
    assert np.std(x) == pytest.approx(1.0, rel=0.15)
    lag = 600  # 300 s: the correlation falls to 1/e
    corr = np.mean([np.corrcoef(x[:-lag, k], x[lag:, k])[0, 1] for k in range(4)])
    assert corr == pytest.approx(math.exp(-1), abs=0.12)


def test_without_bias_the_gps_error_is_white(tmp_path: Path):
    simulate("quadrats", 12, tmp_path, gps_bias_sigma_m=0.0, duration_s=40.0, **FAST_SONAR)
    truth = json.loads((tmp_path / "truth.json").read_text())
    _, err_e, err_n = gps_errors(truth, read_tlog(tmp_path / "nav.tlog"))
    err = np.concatenate([err_e, err_n])
    assert np.std(err) == pytest.approx(0.25, rel=0.2)
    assert abs(np.mean(err)) < 0.1


def test_px4_flavour(tmp_path: Path):
    simulate("quadrats", 13, tmp_path, flavour="px4", duration_s=6.0, **FAST_SONAR)
    msgs = read_tlog(tmp_path / "nav.tlog")
    assert "RAW_IMU" not in msgs and len(msgs["HIGHRES_IMU"]) > 250
    autopilot = [m for m in msgs["HEARTBEAT"] if m.get_srcSystem() == 1]
    assert {m.autopilot for m in autopilot} == {mavutil.mavlink.MAV_AUTOPILOT_PX4}
    zacc = np.array([m.zacc for m in msgs["HIGHRES_IMU"]])
    assert np.mean(zacc) == pytest.approx(-9.81, abs=0.15)  # SI: m/s^2
    assert {m.fields_updated for m in msgs["HIGHRES_IMU"]} == {0x1FFF}
    mag = np.array([[m.xmag, m.ymag, m.zmag] for m in msgs["HIGHRES_IMU"]])
    assert np.mean(np.linalg.norm(mag, axis=1)) == pytest.approx(0.519, rel=0.03)  # gauss


def test_the_project_nav_reader_reads_it(survey):
    navlog = pytest.importorskip("drivers.mavlink.navlog")
    out, truth, _ = survey
    nav = navlog.read_nav_log(out / "nav.tlog")
    assert nav.autopilot == "ardupilot"
    assert len(nav.gnss) == len(truth["sensors"]["gps"]["fixes"]["time"])
    assert nav.imu and nav.heading
    assert nav.imu[0].accel_mps2[2] == pytest.approx(-9.81, abs=0.5)
