"""Scoring against the truth: the true fan's footprint, lane disagreement (zero for the
true poses, the shift for a shifted pass), the relative pose error over 10 s, and the
whole ``evaluate`` on a synthetic truth and result."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import cv2
import numpy as np
import pytest

from mapping.geo import LocalFrame
from mapping.pipeline import SurveyResult
from tools.evaluation.truth import evaluate, truth_heads, truth_index, truth_poses
from tools.footprint import Fan, Heads, fan_hits
from tools.lanes import lane_disagreement, pass_disagreements
from tools.se2 import placement_shift, relative_pose_error

SONAR = {
    "range_m": 5.0,
    "fan_deg": 130.0,
    "tilt_deg": 15.0,
    "vertical_aperture_deg": 20.0,
    "mount_yaw_deg": 0.0,
}


def lane_pings(t0: float, east: float, north0: float, heading_deg: float, seconds: float):
    """Pings at 10 Hz of a boat at 1 m/s on a straight lane, the sonar 0.45 m aft of the
    antenna, 1 m above the seabed."""
    h = math.radians(heading_deg)
    out = []
    for k in range(round(seconds * 10)):
        t = t0 + k / 10
        e = east + math.sin(h) * (t - t0)
        n = north0 + math.cos(h) * (t - t0)
        out.append(
            {
                "time": round(t, 6),
                "east": e,
                "north": n,
                "grid_heading_deg": heading_deg,
                "pitch_deg": 0.0,
                "roll_deg": 0.0,
                "sonar_east": e - 0.45 * math.sin(h),
                "sonar_north": n - 0.45 * math.cos(h),
                "altitude_m": 1.0,
            }
        )
    return out


def two_lanes() -> dict[str, Any]:
    """Up a lane at east 500 and, after a turn not pinged, down one 4 m east of it."""
    pings = lane_pings(1000.0, 500.0, 490.0, 0.0, 20.0) + lane_pings(
        1030.0, 504.0, 510.0, 180.0, 20.0
    )
    return {"format": "seamap-sim-truth", "sonar": SONAR, "pings": pings}


def frame_arrays(truth: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, Heads]:
    times = np.array([p["time"] for p in truth["pings"]])
    return times, truth_poses(truth, times), truth_heads(truth, times)


def test_the_fan_sees_the_lit_band_within_the_fan() -> None:
    # Level sonar 1 m up, tilted 15 degrees, 20 degree beam: lit from slant 1/sin 25
    # (ground 2.14 m) to the 5 m range (ground 4.90 m), bearings within +-65 degrees.
    fan = Fan.from_truth({"sonar": SONAR})
    heads = Heads.from_pings(
        [{"sonar_east": 0.0, "sonar_north": 0.0, "grid_heading_deg": 90.0, "altitude_m": 1.0}]
    )
    ground = np.array([2.0, 2.3, 4.8, 5.0, 3.5, 3.5, 3.5, 3.5])
    bearing = np.radians([0, 0, 0, 0, 60, -60, 70, -70]) + math.pi / 2
    frames, points = fan_hits(fan, heads, ground * np.sin(bearing), ground * np.cos(bearing))
    assert frames.tolist() == [0] * 4
    assert points.tolist() == [1, 2, 4, 5]
    # Turned to starboard by the mount: the boresight looks south.
    yawed = replace(fan, mount_yaw_rad=math.pi / 2)
    _, points = fan_hits(yawed, heads, np.array([0.0, 3.0]), np.array([-3.0, 0.0]))
    assert points.tolist() == [0]
    # A line array's beams are cones about its axis, and the vertical angle is measured
    # about that axis too: off the boresight the lit band moves out (3.5 m on the ground
    # 60 degrees off is lit for a spherical fan, not for the cones; 4.7 m 55 off is both).
    cones = Fan.from_truth({"sonar": {**SONAR, "beam_geometry": "line array along y"}})
    assert cones.line_array and not fan.line_array
    ground = np.array([2.0, 2.3, 4.8, 5.0, 3.5, 3.5, 4.7, 4.7])
    bearing = np.radians([0, 0, 0, 0, 60, -60, 55, -55]) + math.pi / 2
    east, north = ground * np.sin(bearing), ground * np.cos(bearing)
    assert fan_hits(fan, heads, east, north)[1].tolist() == [1, 2, 4, 5, 6, 7]
    _, points = fan_hits(cones, heads, east, north)
    assert points.tolist() == [1, 2, 6, 7]


def test_the_true_poses_give_exactly_zero() -> None:
    truth = two_lanes()
    times, true, heads = frame_arrays(truth)
    report = lane_disagreement(
        times, true, true.copy(), heads, Fan.from_truth(truth), np.array([[502.0, 500.0]])
    )
    assert report["pairs"] > 50 and report["quadrats"]["pairs"] == 1
    assert report["rms_m"] == 0.0 and report["max_m"] == 0.0
    assert report["quadrats"]["rms_m"] == 0.0


def test_a_shifted_pass_shows_its_shift() -> None:
    truth = two_lanes()
    times, true, heads = frame_arrays(truth)
    estimate = true.copy()
    estimate[times > 1025.0, :2] += (0.3, -0.1)
    estimate[5:9] = np.nan  # unmapped frames place nothing and split no pass
    report = lane_disagreement(times, true, estimate, heads, Fan.from_truth(truth))
    assert report["pairs"] > 50
    for key in ("rms_m", "median_m", "p90_m", "max_m"):
        assert report[key] == pytest.approx(math.hypot(0.3, 0.1), abs=1e-9)
    # A heading error of a pass turns its placements about the antenna.
    turned = true.copy()
    turned[times > 1025.0, 2] += math.radians(1.0)
    report = lane_disagreement(times, true, turned, heads, Fan.from_truth(truth))
    assert 0.02 < report["median_m"] < 0.09  # 1 degree at 1.5-5 m


def test_passes_split_at_gaps_of_two_seconds() -> None:
    times = np.array([0.0, 0.1, 0.2, 0.3, 5.0, 5.1, 7.2])
    true = np.zeros((7, 3))
    estimate = true.copy()
    estimate[4:6, 0] = 1.0
    estimate[6, 1] = 2.0
    estimate[2] = np.nan
    frames = np.arange(7)
    distance, owner = pass_disagreements(
        frames, np.zeros(7, np.int64), times, true, estimate, np.zeros(1), np.zeros(1)
    )
    np.testing.assert_allclose(np.sort(distance), [1.0, 2.0, math.sqrt(5.0)])
    assert owner.tolist() == [0, 0, 0]


def test_placement_shift_is_the_composed_pose() -> None:
    rng = np.random.default_rng(7)
    true = rng.uniform([-50, -50, -np.pi], [50, 50, np.pi], (40, 3))
    estimate = true + rng.normal(0, [0.5, 0.5, 0.05], (40, 3))
    point = rng.uniform(-60, 60, (40, 2))

    def matrix(pose: np.ndarray) -> np.ndarray:
        # Body (forward, starboard) -> (east, north), heading clockwise from north.
        s, c = math.sin(pose[2]), math.cos(pose[2])
        return np.array([[s, c, pose[0]], [c, -s, pose[1]], [0, 0, 1]])

    for k in range(40):
        p = np.r_[point[k], 1.0]
        moved = matrix(estimate[k]) @ np.linalg.inv(matrix(true[k])) @ p
        shift = placement_shift(true[k : k + 1], estimate[k : k + 1], point[k : k + 1, 0],
                                point[k : k + 1, 1])  # fmt: skip
        np.testing.assert_allclose(point[k] + shift[0], moved[:2], atol=1e-9)


def test_relative_pose_error_over_ten_seconds() -> None:
    times = np.arange(0.0, 60.0, 0.5)
    true = np.stack([np.sin(times / 9) * 20, times, times / 30], axis=1)
    # A rigid move of the whole trajectory is no relative error.
    a, shift = 0.3, np.array([4.0, -2.0])
    rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    rigid = np.c_[true[:, :2] @ rot.T + shift, true[:, 2] + a]
    rpe = relative_pose_error(times, rigid, true)
    assert rpe["pairs"] == 100
    assert rpe["translation_rms_m"] < 1e-9 and rpe["yaw_rms_deg"] < 1e-9
    # A gyro drift of 0.01 rad/s is 0.1 rad of yaw over every 10 s.
    drifting = true.copy()
    drifting[:, 2] += 0.01 * times
    assert relative_pose_error(times, drifting, true)["yaw_rms_deg"] == pytest.approx(
        math.degrees(0.1)
    )


def test_truth_is_found_by_the_frame_times() -> None:
    truth = two_lanes()
    times = np.array([1030.1, 999.0, 1000.0 + 1e-6])
    assert truth_index(truth, times).tolist() == [201, -1, 0]
    assert np.isnan(truth_heads(truth, times).east[1])


def quadrat_entry(east: float, north: float, side: float, row: int, index: int, array: int):
    half = side / 2
    corners = [[east - half, north - half], [east - half, north + half],
               [east + half, north + half], [east + half, north - half]]  # fmt: skip
    return {"row": row, "index": index, "side_m": side, "centre_east": east,
            "centre_north": north, "corners": corners, "array": array}  # fmt: skip


def test_evaluate_reports_lanes_rpe_and_each_arrays_offset(tmp_path: Path) -> None:
    truth = two_lanes()
    quadrats = [
        quadrat_entry(500.5 + i, 496.0 + 1.5 * row, (0.43, 0.62)[row], row, i, 0)
        for row in (0, 1)
        for i in range(4)
    ] + [quadrat_entry(501.0 + i, 504.0, 0.43, 0, i, 1) for i in range(3)]
    truth["features"] = {"quadrats": quadrats}
    path = tmp_path / "truth.json"
    path.write_text(json.dumps(truth))
    # A mosaic of the site with the arrays 1.7 m and 1.2 m off (a GNSS offset).
    res, west, north = 0.02, 490.0, 515.0
    rng = np.random.default_rng(1)
    image = np.clip(rng.normal(90, 15, (round(30 / res), round(25 / res))), 1, 255)
    for q in quadrats:
        de, dn = (1.7, 0.0) if q["array"] == 0 else (0.0, -1.2)
        corners = np.array([[(e + de - west) / res - 0.5, (north - n - dn) / res - 0.5]
                            for e, n in q["corners"]])  # fmt: skip
        cv2.polylines(image, [np.round(corners * 4).astype(np.int32)], True, 240, 2,
                      cv2.LINE_AA, 2)  # fmt: skip
    times, true, _ = frame_arrays(truth)
    result = SimpleNamespace(
        frame=LocalFrame(32618, 500.0, 500.0),
        times=times,
        poses=true - [500.0, 500.0, 0.0],
    )
    report = evaluate(path, cast(SurveyResult, result), image.astype(np.uint8), west, north, res)
    assert report["lanes"]["rms_m"] < 1e-9 and report["lanes"]["pairs"] > 50
    assert report["trajectory"]["rpe_10s_m"] < 1e-9 and report["trajectory"]["rmse"] < 1e-9
    spacing = report["quadrat_spacing"]
    assert spacing["located"] == 11 and spacing["rmse"] < 0.01
    offsets = {a["array"]: (a["offset_east_m"], a["offset_north_m"]) for a in spacing["arrays"]}
    np.testing.assert_allclose(offsets[0], (1.7, 0.0), atol=0.02)
    np.testing.assert_allclose(offsets[1], (0.0, -1.2), atol=0.02)
    assert spacing["array_offset_max_m"] == pytest.approx(1.7, abs=0.02)
