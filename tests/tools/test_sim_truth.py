"""truth.json, seabed.tif and site.toml: the paper's site, frames, and consistency with the
sonar log (what later stages score against)."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
from pyproj import Proj, Transformer

from daemon.config import load_config
from tools.sim import simulate
from tools.sim.truth import TRUTH_FORMAT, TRUTH_VERSION


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """The whole quadrats survey, with 128 beams to keep it quick."""
    out = tmp_path_factory.mktemp("sim_truth")
    summary = simulate("quadrats", 21, out, n_beams=128)
    assert 700 <= summary.ping_count <= 950  # under 3 minutes at 5 pings a second
    return out, json.loads((out / "truth.json").read_text())


def test_truth_header_and_site(survey):
    _, truth = survey
    assert truth["format"] == TRUTH_FORMAT and truth["version"] == TRUTH_VERSION
    site = truth["site"]
    assert site["epsg"] == 32618  # UTM 18N: the Chesapeake Bay
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32618", always_xy=True)
    e, n = to_utm.transform(site["origin_lon_deg"], site["origin_lat_deg"])
    assert (site["utm_origin_east"], site["utm_origin_north"]) == (round(e), round(n))
    factors = Proj("EPSG:32618").get_factors(site["origin_lon_deg"], site["origin_lat_deg"])
    assert site["meridian_convergence_deg"] == pytest.approx(factors.meridian_convergence, abs=1e-6)
    assert 0.8 <= site["seabed_plane"]["depth_at_origin_m"] <= 1.25  # 3-4 ft of water
    # A slow boat: three 16 m lanes at 0.4 m/s, under 3 minutes.
    assert 120.0 < truth["time"]["duration_s"] < 200.0
    assert truth["vehicle"]["speed_mps"] == 0.4


def test_quadrats_are_the_papers_array(survey):
    _, truth = survey
    layout = truth["features"]["quadrat_layout"]
    assert (layout["aluminium_side_m"], layout["pvc_side_m"]) == (0.43, 0.62)
    assert (layout["row_gap_m"], layout["frame_spacing_m"]) == (1.52, 1.0)
    quadrats = truth["features"]["quadrats"]
    assert len(quadrats) == 8
    rows: dict[int, list[dict[str, Any]]] = {0: [], 1: []}
    for q in quadrats:
        rows[q["row"]].append(q)
        side = {"aluminium": 0.43, "pvc": 0.62}[q["material"]]
        assert q["side_m"] == side
        corners = np.array(q["corners"])
        edges = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
        np.testing.assert_allclose(edges, side, atol=1e-5)
        np.testing.assert_allclose(corners.mean(axis=0), [q["centre_east"], q["centre_north"]])
        assert q["oysters"] > 0  # oysters inside every frame
    assert {q["material"] for q in rows[0]} == {"aluminium"}
    assert {q["material"] for q in rows[1]} == {"pvc"}
    for row in rows.values():
        row.sort(key=lambda q: q["index"])
        centres = np.array([[q["centre_east"], q["centre_north"]] for q in row])
        np.testing.assert_allclose(np.linalg.norm(np.diff(centres, axis=0), axis=1), 1.0, atol=1e-5)
    # Rows parallel; nearest sides 1.52 m apart.
    al = np.array([[q["centre_east"], q["centre_north"]] for q in rows[0]])
    pvc = np.array([[q["centre_east"], q["centre_north"]] for q in rows[1]])
    axis = (al[-1] - al[0]) / np.linalg.norm(al[-1] - al[0])
    normal = np.array([axis[1], -axis[0]])
    offsets = (pvc - al) @ normal
    np.testing.assert_allclose(np.abs(offsets), 1.52 + 0.43 / 2 + 0.62 / 2, atol=1e-5)
    np.testing.assert_allclose((pvc - al) @ axis, 0.0, atol=1e-5)


def test_ping_truth_is_consistent(survey):
    _, truth = survey
    conv = truth["site"]["meridian_convergence_deg"]
    sonar = truth["sonar"]
    mount = np.array([sonar["mount_x_m"], sonar["mount_y_m"], sonar["mount_z_m"]])
    for p in truth["pings"][::25]:
        grid = (p["heading_deg"] - conv) % 360.0
        assert (
            min(abs(grid - p["grid_heading_deg"]), 360 - abs(grid - p["grid_heading_deg"])) < 1e-3
        )
        assert p["east"] - p["local_east"] == truth["site"]["utm_origin_east"]
        # The sonar sits at the mount offset from the antenna, turned by the attitude
        # at acquisition (roll, pitch and heave of the chop).
        h, pt, rl = (math.radians(p[k]) for k in ("grid_heading_deg", "pitch_deg", "roll_deg"))
        offset = _rotation(h, pt, rl) @ mount
        de, dn = p["sonar_east"] - p["east"], p["sonar_north"] - p["north"]
        assert math.hypot(de - offset[1], dn - offset[0]) < 1e-3
        antenna_depth = -(truth["vehicle"]["antenna_height_m"] + p["heave_m"])
        assert p["sonar_depth_m"] == pytest.approx(antenna_depth + offset[2], abs=1e-3)
        assert 0.8 < p["altitude_m"] < 1.2
        # Received 0.03-0.12 s after it was taken (the field day's latency).
        assert sonar["latency_s"] <= p["time"] - p["acquisition_time"] < sonar["latency_s"] + 0.05
    times = [p["time"] for p in truth["pings"]]
    period = 1.0 / sonar["ping_rate_hz"]
    assert np.all(np.diff(times) > 0.8 * period) and np.all(np.diff(times) < 1.2 * period)
    # Roll and pitch of a small boat in a light chop: 2-3 degrees RMS, changing ping to ping.
    roll = np.array([p["roll_deg"] for p in truth["pings"]])
    assert 1.5 < np.std(roll) < 3.5 and np.std(np.diff(roll)) > 0.5


def test_seabed_geotiff_is_the_truth_map(survey):
    out, truth = survey
    with rasterio.open(out / "seabed.tif") as src:
        assert src.crs.to_epsg() == truth["site"]["epsg"]
        assert src.count == 1 and src.dtypes == ("uint8",)
        t = src.transform
        assert (t.a, t.b, t.d, t.e) == (0.01, 0.0, 0.0, -0.01)  # north-up, square, 1 cm
        seabed = truth["seabed"]
        assert (src.bounds.left, src.bounds.top) == (seabed["west"], seabed["north"])
        image = src.read(1)
        # The aluminium bars are the brightest thing there; the sand is mid-grey.
        bars = []
        for q in truth["features"]["quadrats"]:
            corners = np.array(q["corners"])
            for a, b in itertools.pairwise([*corners, corners[0]]):
                for f in np.linspace(0.1, 0.9, 9):
                    bars.append(a + f * (b - a))
        rows, cols = rasterio.transform.rowcol(t, *np.array(bars).T)
        assert np.median(image[rows, cols]) > 200
        assert 60 < np.median(image) < 120
    with rasterio.open(out / "seabed_height.tif") as src:
        height = src.read(1) * src.scales[0]
        # The bars stand 25-33 mm proud of the ripple crests they rest on.
        assert height[rows, cols].min() > 0.015
        assert np.median(height[rows, cols]) > 0.024


def test_site_toml_loads_and_matches_the_mount(survey):
    out, truth = survey
    config = load_config(out / "site.toml")
    sonar = truth["sonar"]
    for key in ("mount_x_m", "mount_y_m", "mount_z_m", "mount_yaw_deg", "tilt_deg"):
        assert getattr(config.sonar, key) == sonar[key]
    assert (sonar["mount_x_m"], sonar["mount_z_m"], sonar["tilt_deg"]) == (-0.45, 0.3, 15.0)
    mean_altitude = np.mean([p["altitude_m"] for p in truth["pings"]])
    assert config.sonar.altitude_m == pytest.approx(mean_altitude, abs=1e-3)
    assert config.mavlink.declination_deg == truth["site"]["magnetic"]["declination_deg"]
    assert config.mavlink.imu_source == "raw"


def _rotation(h: float, p: float, r: float) -> np.ndarray:
    """Body FRD -> grid north/east/down for grid heading h, pitch p, roll r (radians)."""
    rz = np.array([[math.cos(h), -math.sin(h), 0], [math.sin(h), math.cos(h), 0], [0, 0, 1]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    return rz @ ry @ rx


def project(truth: dict[str, Any], ping: dict[str, Any], east, north):
    """(range m, bearing rad) in the sonar frame of ground points (UTM), from the truth
    alone: sonar position, grid heading, roll, pitch, tilt and the seabed plane; the
    bearing of the line array's cone, asin(y / range)."""
    site, plane = truth["site"], truth["site"]["seabed_plane"]
    local_e = np.asarray(east) - site["utm_origin_east"]
    local_n = np.asarray(north) - site["utm_origin_north"]
    depth = (
        plane["depth_at_origin_m"] + plane["slope_east"] * local_e + plane["slope_north"] * local_n
    )
    v = np.stack(
        [np.asarray(north) - ping["sonar_north"], np.asarray(east) - ping["sonar_east"],
         depth - ping["sonar_depth_m"]],
    )  # fmt: skip
    h, p, r = (math.radians(ping[k]) for k in ("grid_heading_deg", "pitch_deg", "roll_deg"))
    t = math.radians(truth["sonar"]["tilt_deg"])
    tilt = np.array([[math.cos(t), 0, -math.sin(t)], [0, 1, 0], [math.sin(t), 0, math.cos(t)]])
    s = (_rotation(h, p, r) @ tilt).T @ v
    slant = np.linalg.norm(v, axis=0)
    return slant, np.arcsin(s[1] / slant)


def test_frames_appear_in_the_pings_where_the_truth_puts_them(survey):
    """End to end: from truth.json alone, predict the polar cells of the frame bars in
    every logged ping; the echo, summed over all of them, peaks at the predicted cell
    (within the bar's width) and the bars' shadows fall just behind it."""
    from drivers.oculus.logfile import iter_pings

    out, truth = survey
    shifts_r, shifts_b = np.arange(-6, 7), np.arange(-3, 4)
    response = np.zeros((len(shifts_r), len(shifts_b)))
    count = 0
    pings = list(iter_pings(out / "sonar.oculus"))
    for ping, row in zip(pings, truth["pings"], strict=True):
        for q in truth["features"]["quadrats"]:
            corners = np.array(q["corners"])
            for a, b in itertools.pairwise([*corners, corners[0]]):
                pts = a + np.linspace(0.15, 0.85, 8)[:, None] * (b - a)
                rng, brg = project(truth, row, pts[:, 0], pts[:, 1])
                ok = (rng > 2.6) & (rng < 4.6) & (np.abs(brg) < math.radians(55))
                if not np.any(ok):
                    continue
                i = np.floor(rng[ok] / ping.range_resolution_m).astype(int)
                j = np.argmin(np.abs(ping.bearings_rad[None, :] - brg[ok][:, None]), axis=1)
                rows = i[None, None, :] + shifts_r[:, None, None]
                cols = np.clip(j[None, None, :] + shifts_b[None, :, None], 0, ping.n_beams - 1)
                response += ping.image[rows, cols].sum(axis=2)
                count += int(ok.sum())
    assert count > 2000
    response /= count
    peak_r, peak_b = np.unravel_index(np.argmax(response), response.shape)
    assert abs(shifts_r[peak_r]) <= 2 and abs(shifts_b[peak_b]) <= 1
    background = np.median(response[:, [0, -1]])
    assert response[peak_r, peak_b] > 1.3 * background
    shadow = response[peak_r + 3 : peak_r + 6, peak_b].mean()
    assert shadow < 0.85 * background
