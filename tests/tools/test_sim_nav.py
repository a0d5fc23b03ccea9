"""The simulated telemetry: read back with pymavlink, rates, units, stamps, error models."""

from __future__ import annotations

import itertools
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

    # mrad/s: integrating the z gyro over the first U-turn gives about 180 degrees (the
    # turn found on the course over ground: the heading wobbles in the chop).
    t = sample_times(truth, imu, "time_usec", 1e-6)
    heading = truth_at(truth, t, "heading_deg", angle=True)
    course = truth_at(truth, t, "course_deg", angle=True)
    turning = np.abs(np.gradient(course, t)) > 5.0
    # The first stretch of turning that lasts (not a twitch of the course at the start).
    edges = np.flatnonzero(np.diff(turning.astype(int)))
    runs = [(a + 1, b + 1) for a, b in itertools.pairwise(edges) if turning[a + 1]]
    start, stop = next((a, b) for a, b in runs if t[b] - t[a] > 5.0)
    gz = np.array([m.zgyro for m in imu[start:stop]], float) / 1000.0
    turned = math.degrees(float(np.sum(gz[:-1] * np.diff(t[start:stop]))))
    assert turned == pytest.approx(heading[stop - 1] - heading[start], abs=6.0)
    assert abs(heading[stop - 1] - heading[start]) > 120.0


def test_compass_heading_is_truth_plus_its_documented_error(survey):
    """Every heading message is the true heading plus the truth's per-sample error (to
    the message's quantisation), and that error is bias + deviation + noise."""
    _, truth, msgs = survey
    compass = truth["sensors"]["compass"]
    samples = {k: np.array(v) for k, v in compass["samples"].items()}
    np.testing.assert_allclose(
        samples["error_deg"],
        samples["bias_deg"] + samples["deviation_deg"] + samples["noise_deg"],
        atol=3e-4,
    )
    for name, get, quantum in [
        ("GLOBAL_POSITION_INT", lambda m: m.hdg / 100.0, 0.01),
        ("ATTITUDE", lambda m: math.degrees(m.yaw), 1e-4),
        ("VFR_HUD", lambda m: float(m.heading), 1.0),
    ]:
        ms = msgs[name]
        if name == "VFR_HUD":  # no time field: the k-th message is the k-th sample
            t = samples["time"][: len(ms)]
        else:
            t = sample_times(truth, ms, "time_boot_ms", 1e-3)
            np.testing.assert_allclose(t, samples["time"], atol=1e-3)
        true_heading = samples["heading_deg"][: len(ms)]
        err = wrap180(np.array([get(m) for m in ms]) - true_heading)
        left = wrap180(err - samples["error_deg"][: len(ms)])
        assert np.max(np.abs(left)) < 0.51 * quantum + 2e-4, name
        # ...and the true heading is the pings' (interpolated between them).
        pinged = t > truth["pings"][0]["acquisition_time"]
        between = wrap180(true_heading - truth_at(truth, t, "heading_deg", True))[pinged]
        assert np.median(np.abs(between)) < 0.05, name
    # The parts: a constant bias (plus a slow wander), a deviation that follows the
    # magnetic heading, and noise of the drawn size.
    assert np.mean(samples["bias_deg"]) == pytest.approx(compass["bias_deg"], abs=0.5)
    psi = np.radians(truth_at(truth, samples["time"], "heading_deg", True))
    psi -= math.radians(truth["site"]["magnetic"]["declination_deg"])
    c = compass["deviation_coefficients"]
    deviation = (
        c["A_deg"] * np.sin(psi) + c["B_deg"] * np.cos(psi)
        + c["C_deg"] * np.sin(2 * psi) + c["D_deg"] * np.cos(2 * psi)
    )  # fmt: skip
    pinged = (samples["time"] > truth["pings"][0]["acquisition_time"]) & (
        samples["time"] < truth["pings"][-1]["acquisition_time"]
    )
    np.testing.assert_allclose(deviation[pinged], samples["deviation_deg"][pinged], atol=0.01)
    sigma = math.hypot(compass["gm_sigma_deg"], compass["noise_deg"])
    assert np.std(samples["noise_deg"]) == pytest.approx(sigma, rel=0.4)


def test_magnetometer_gives_the_heading_through_the_declination(survey):
    """A tilt-compensated heading from RAW_IMU's field, plus the declination, is the true
    heading plus the compass's bias and deviation (not its fused-heading noise)."""
    _, truth, msgs = survey
    imu = msgs["RAW_IMU"]
    t = sample_times(truth, imu, "time_usec", 1e-6)
    roll = np.radians(truth_at(truth, t, "roll_deg"))
    pitch = np.radians(truth_at(truth, t, "pitch_deg"))
    mx, my, mz = (np.array([getattr(m, k) for m in imu], float) for k in ("xmag", "ymag", "zmag"))
    xh = mx * np.cos(pitch) + (my * np.sin(roll) + mz * np.cos(roll)) * np.sin(pitch)
    yh = my * np.cos(roll) - mz * np.sin(roll)
    heading = np.degrees(np.arctan2(-yh, xh)) + truth["site"]["magnetic"]["declination_deg"]
    true_heading = truth_at(truth, t, "heading_deg", True)
    err = wrap180(heading - true_heading)
    compass = truth["sensors"]["compass"]
    samples = compass["samples"]
    bias = np.interp(t, samples["time"], samples["bias_deg"])
    psi = np.radians(true_heading - truth["site"]["magnetic"]["declination_deg"])
    deviation = compass["deviation_1_deg"] * np.sin(
        psi + math.radians(compass["deviation_1_phase_deg"])
    ) + compass["deviation_2_deg"] * np.sin(
        2 * psi + math.radians(compass["deviation_2_phase_deg"])
    )
    pinged = t > truth["pings"][0]["acquisition_time"]
    left = (err - bias - deviation)[pinged]
    # Integer milligauss of a 214 mG horizontal field: a quarter of a degree per count.
    assert abs(np.median(left)) < 0.1
    assert np.std(left) < 1.2  # 3 mG of noise in 214 mG of horizontal field: 0.8 degrees
    assert np.median(bias - truth["sensors"]["imu"]["mag_misalignment_deg"]) == pytest.approx(
        0.0, abs=0.5
    )


def gps_errors(truth, msgs, lag_s: float | None = None):
    """Fix stamps and the reported position minus the antenna ``lag_s`` before the stamp
    (the truth's lag when None), grid east/north metres."""
    gps = msgs["GPS_RAW_INT"]
    t = sample_times(truth, gps, "time_usec", 1e-6)
    seen = t - (truth["sensors"]["gps"]["lag_s"] if lag_s is None else lag_s)
    to_utm = Transformer.from_crs("EPSG:4326", f"EPSG:{truth['site']['epsg']}", always_xy=True)
    e, n = to_utm.transform([m.lon / 1e7 for m in gps], [m.lat / 1e7 for m in gps])
    return (
        t,
        np.array(e) - truth_at(truth, seen, "east"),
        np.array(n) - truth_at(truth, seen, "north"),
    )


def test_gps_error_is_a_wandering_bias_plus_white_noise(survey):
    _, truth, msgs = survey
    model = truth["sensors"]["gps"]
    t, err_e, err_n = gps_errors(truth, msgs)
    fixes = model["fixes"]
    np.testing.assert_allclose(t, fixes["time"], atol=2e-6)
    # The log carries truth + the documented error (to the 1e-7 degree of the message);
    # the truth is known at the pings, which start a second after the log.
    pinged = t - model["lag_s"] > truth["pings"][0]["acquisition_time"]
    np.testing.assert_allclose(err_e[pinged], np.array(fixes["error_east_m"])[pinged], atol=0.02)
    np.testing.assert_allclose(err_n[pinged], np.array(fixes["error_north_m"])[pinged], atol=0.02)
    # Minus the bias path, what is left is white noise of the configured size...
    bias_e, bias_n = np.array(fixes["bias_east_m"]), np.array(fixes["bias_north_m"])
    white = np.concatenate([(err_e - bias_e)[pinged], (err_n - bias_n)[pinged]])
    assert np.std(white) == pytest.approx(model["noise_m"], rel=0.2)
    # ...and the bias moves slowly: its 0.5 s steps are those of its Gauss-Markov.
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
    assert truth["sensors"]["gps"]["bias_sigma_m"] == 0.0  # the override wins the draw
    t, err_e, err_n = gps_errors(truth, read_tlog(tmp_path / "nav.tlog"))
    pinged = t - truth["sensors"]["gps"]["lag_s"] > truth["pings"][0]["acquisition_time"]
    err = np.concatenate([err_e[pinged], err_n[pinged]])
    assert np.std(err) == pytest.approx(truth["sensors"]["gps"]["noise_m"], rel=0.2)
    assert abs(np.mean(err)) < 0.15


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


def test_gps_fix_lags_the_antenna(survey):
    """Searched for, the delay that best explains the logged fixes (less their recorded
    error) as the antenna's track is the field day's lag, 0.1-0.2 s, not zero: at 0.4 m/s
    that is 4-8 cm along the track."""
    _, truth, msgs = survey
    model = truth["sensors"]["gps"]
    fixes = model["fixes"]
    assert 0.1 <= model["lag_s"] <= 0.2
    np.testing.assert_allclose(
        np.array(fixes["time"]) - np.array(fixes["antenna_time"]), model["lag_s"], atol=1e-6
    )
    error = np.stack([fixes["error_east_m"], fixes["error_north_m"]])
    residual = []
    candidates = np.arange(0.0, 0.301, 0.005)
    for lag in candidates:
        t, err_e, err_n = gps_errors(truth, msgs, lag_s=float(lag))
        inside = (t - 0.3 > truth["pings"][0]["acquisition_time"]) & (
            t < truth["pings"][-1]["acquisition_time"]
        )
        left = np.stack([err_e, err_n])[:, inside] - error[:, inside]
        residual.append(float(np.sqrt(np.mean(left**2))))
    best = float(candidates[int(np.argmin(residual))])
    assert best == pytest.approx(model["lag_s"], abs=0.011)
    assert residual[0] > 0.03  # ignoring the lag costs centimetres
    # The recorded antenna positions are the truth's, and the stamp error adds the lag.
    t = np.array(fixes["time"])
    inside = (t - 0.3 > truth["pings"][0]["acquisition_time"]) & (
        t < truth["pings"][-1]["acquisition_time"]
    )
    seen = np.array(fixes["antenna_time"])[inside]
    np.testing.assert_allclose(
        np.array(fixes["antenna_east"])[inside], truth_at(truth, seen, "east"), atol=2e-3
    )
    stamp_error = np.array(fixes["stamp_error_north_m"]) - np.array(fixes["error_north_m"])
    along = truth_at(truth, seen, "north") - truth_at(truth, t[inside], "north")
    np.testing.assert_allclose(stamp_error[inside], along, atol=2e-3)


def test_a_gnss_outage_reports_no_fix(tmp_path: Path):
    simulate(
        "quadrats", 14, tmp_path, duration_s=40.0, gps_outage_start_s=12.0,
        gps_outage_duration_s=10.0, **FAST_SONAR,
    )  # fmt: skip
    truth = json.loads((tmp_path / "truth.json").read_text())
    outage = truth["sensors"]["gps"]["outage"]
    start = truth["time"]["start_time"]
    assert (outage["start_time"], outage["end_time"]) == pytest.approx((start + 12, start + 22))
    msgs = read_tlog(tmp_path / "nav.tlog")
    gps = msgs["GPS_RAW_INT"]
    t = sample_times(truth, gps, "time_usec", 1e-6)
    lost = (t >= outage["start_time"]) & (t < outage["end_time"])
    fix_type = np.array([m.fix_type for m in gps])
    assert lost.sum() == 20 and set(fix_type[lost]) == {1} and set(fix_type[~lost]) == {3}
    assert all(
        m.satellites_visible <= 3 and m.eph > 5000 for m, x in zip(gps, lost, strict=True) if x
    )
    assert truth["sensors"]["gps"]["fixes"]["fix_type"] == fix_type.tolist()
    # The fixes stay where the last one was; the autopilot's estimate carries on.
    held = np.array([[m.lat, m.lon] for m in gps])[lost]
    assert np.all(held == held[0])
    _, err_e, err_n = gps_errors(truth, msgs)
    fixes = truth["sensors"]["gps"]["fixes"]
    seen = t - truth["sensors"]["gps"]["lag_s"]
    inside = (seen > truth["pings"][0]["acquisition_time"]) & (
        seen < truth["pings"][-1]["acquisition_time"]
    )
    np.testing.assert_allclose(err_e[inside], np.array(fixes["error_east_m"])[inside], atol=0.02)
    np.testing.assert_allclose(err_n[inside], np.array(fixes["error_north_m"])[inside], atol=0.02)
    navlog = pytest.importorskip("drivers.mavlink.navlog")
    nav = navlog.read_nav_log(tmp_path / "nav.tlog")
    assert sum(not f.usable for f in nav.gnss) == 20
    position = msgs["GLOBAL_POSITION_INT"]
    tp = sample_times(truth, position, "time_boot_ms", 1e-3)
    assert np.sum((tp >= outage["start_time"]) & (tp < outage["end_time"])) == 20
