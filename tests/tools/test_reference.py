"""A reference trajectory CSV as the truth: matched to the frames by time (interpolated
between rows, else the nearest within the tolerance, else left out and counted), its
east/north projected from lat/lon when absent, its sonar heads from the mount, and a
malformed file is one line naming the row and column (through the real CLI too)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import SeamapError
from drivers.formats.results import write_trajectory
from mapping.coverage import SonarFan
from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from tools.evaluation.reference import SonarSetup, match_times, read_reference_csv
from tools.evaluation.truth import SimTruth, load_reference
from tools.se2 import wrap

EPSG = 32618  # UTM 18N
FRAME = LocalFrame(EPSG, 0.0, 0.0)
CENTRE = (500_010.0, 4_500_000.0)
RADIUS = 6.0
SPEED = 0.4
SONAR = SonarSetup(SonarMount(), SonarFan(math.radians(65.0), 1.5, 5.0), 1.0)


def circle(t: np.ndarray) -> np.ndarray:
    """A boat turning clockwise on a 6 m circle at 0.4 m/s: (east, north, grid heading),
    UTM metres and radians; it crosses north (heading 0 / 2 pi) on the way."""
    angle = SPEED * t / RADIUS  # clockwise from north, seen from the centre
    east = CENTRE[0] + RADIUS * np.sin(angle)
    north = CENTRE[1] + RADIUS * np.cos(angle)
    heading = np.mod(angle + math.pi / 2, 2 * math.pi)
    return np.stack([east, north, heading], axis=1)


def write_csv(path: Path, t: np.ndarray, poses: np.ndarray, east_north: bool = True) -> None:
    """Rows of the contract's trajectory.csv columns for poses (UTM, grid heading): lat/lon
    by pyproj, heading turned to true north by the convergence at the row."""
    lat, lon = FRAME.to_latlon(poses[:, 0], poses[:, 1])
    heading_true = [
        math.degrees(FRAME.grid_to_true(h, la, lo))
        for h, la, lo in zip(poses[:, 2], lat, lon, strict=True)
    ]
    lines = ["time,lat,lon,east,north,heading_deg" if east_north else "time,lat,lon,heading_deg"]
    for k in range(t.size):
        pos = f"{poses[k, 0]:.4f},{poses[k, 1]:.4f}," if east_north else ""
        lines.append(f"{t[k]:.6f},{lat[k]:.9f},{lon[k]:.9f},{pos}{heading_true[k]:.4f}")
    path.write_text("\n".join(lines) + "\n")


def test_a_faster_reference_is_interpolated_between_its_rows(tmp_path: Path) -> None:
    # The reference at 20 Hz, the frames at 10 Hz half-way between its rows; over 90 s the
    # boat turns 344 degrees, crossing north (heading 360 -> 0) once.
    rows_t = 1.7e9 + np.arange(0.0, 90.0, 0.05)
    write_csv(tmp_path / "ref.csv", rows_t, circle(rows_t - rows_t[0]))
    frames_t = 1.7e9 + 0.025 + np.arange(0.0, 89.9, 0.1)
    reference = load_reference(tmp_path / "ref.csv")
    matched = reference.at(frames_t, EPSG, SONAR)
    expected = circle(frames_t - rows_t[0])
    # A chord of 2 cm on a 6 m circle strays 0.01 mm from the arc.
    np.testing.assert_allclose(matched.poses[:, :2], expected[:, :2], atol=2e-4)
    heading_error = np.angle(np.exp(1j * (matched.poses[:, 2] - expected[:, 2])))
    assert np.abs(heading_error).max() < math.radians(0.001)
    assert matched.summary["frames_interpolated"] == frames_t.size
    assert matched.summary["frames_unmatched"] == 0


def test_heading_is_interpolated_on_the_circle() -> None:
    rows = np.array([0.0, 1.0])
    left, right, weight, how = match_times(rows, np.array([0.25]), 0.05, 1.0)
    assert (left[0], right[0], how[0]) == (0, 1, 2) and weight[0] == pytest.approx(0.25)


def test_sparse_rows_take_the_nearest_within_the_tolerance_else_none() -> None:
    rows = np.array([0.0, 5.0, 10.0])  # 5 s apart: wider than the 1 s gap
    times = np.array([0.03, 4.9, 7.0, 10.0, 10.2])
    left, right, _, how = match_times(rows, times, 0.05, 1.0)
    assert how.tolist() == [1, 0, 0, 1, 0]
    assert left[0] == right[0] == 0 and left[3] == right[3] == 2


def test_without_east_north_the_poses_come_from_lat_lon(tmp_path: Path) -> None:
    t = 1.7e9 + np.arange(0.0, 60.0, 0.1)
    poses = circle(t - t[0])
    write_csv(tmp_path / "with.csv", t, poses)
    write_csv(tmp_path / "without.csv", t, poses, east_north=False)
    with_en = load_reference(tmp_path / "with.csv").at(t, EPSG, SONAR)
    without = load_reference(tmp_path / "without.csv").at(t, EPSG, SONAR)
    # lat/lon to 1e-9 degrees: 0.1 mm.
    np.testing.assert_allclose(without.poses, with_en.poses, atol=2e-4)
    np.testing.assert_allclose(without.heads.east, with_en.heads.east, atol=2e-4)
    np.testing.assert_allclose(with_en.poses[:, :2], poses[:, :2], atol=1e-4)


def test_the_sonar_head_is_the_lever_arm_turned_by_the_heading(tmp_path: Path) -> None:
    t = np.array([100.0, 100.1])
    path = tmp_path / "ref.csv"
    lat, lon = FRAME.to_latlon(np.array([500_000.0] * 2), np.array([4_500_000.0] * 2))
    east_heading = math.degrees(FRAME.grid_to_true(math.pi / 2, lat[0], lon[0]))
    path.write_text(
        "time,lat,lon,heading_deg,altitude_m\n"
        + "".join(f"{t[k]},{lat[k]:.10f},{lon[k]:.10f},{east_heading:.6f},2.5\n" for k in (0, 1))
    )
    heads = load_reference(path).at(t, EPSG, SONAR).heads
    # The sonar 0.45 m aft of the antenna; the boat heads grid east: the head is west of it.
    np.testing.assert_allclose(heads.east, 500_000.0 - 0.45, atol=1e-4)
    np.testing.assert_allclose(heads.north, 4_500_000.0, atol=1e-4)
    np.testing.assert_allclose(heads.altitude, 2.5)


HEADER = "time,lat,lon,heading_deg\n"
ROW = "1700000000.0,40.6,-74.0,90.0\n"


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("time,lat,lon\n1700000000.0,40.6,-74.0\n", "row 1 (the header): no column 'heading_deg'"),
        (HEADER + ROW + "1700000000.1,40.6,x,90.0\n", "row 3, column lon: 'x' is not a number"),
        (HEADER, "no rows of reference poses under the header"),
        (HEADER + ROW + ROW, "row 3, column time: 1700000000.0 is not after"),
        (HEADER + "1700000000.0,40.6,-74.0\n", "row 2: 3 fields, the header has 4"),
        (HEADER + "1700000000.0,140.6,-74.0,9\n", "row 2, column lat: 140.6 is outside -90..90"),
        ("time,lat,lon,heading_deg,east\n" + ROW, "column 'east' without 'north'"),
        (HEADER + "1700000000.0,40.6,-74.0,nan\n", "column heading_deg: 'nan' is not finite"),
    ],
)  # fmt: skip
def test_a_malformed_csv_is_one_line_naming_row_and_column(
    tmp_path: Path, text: str, reason: str
) -> None:
    path = tmp_path / "ref.csv"
    path.write_text(text)
    with pytest.raises(SeamapError) as caught:
        read_reference_csv(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ") and reason in message and "\n" not in message


def test_a_truth_json_is_told_from_a_csv_by_content(tmp_path: Path) -> None:
    truth = tmp_path / "reference.csv"  # a simulator's truth under a CSV's name
    truth.write_text('{"format": "seamap-sim-truth", "pings": []}')
    assert isinstance(load_reference(truth), SimTruth)
    csv = tmp_path / "truth.json"  # and a CSV under truth.json's
    csv.write_text(HEADER + ROW)
    assert load_reference(csv).unavailable is not None
    other = tmp_path / "site.toml"
    other.write_text("[sonar]\ntilt_deg = 15.0\n")
    with pytest.raises(SeamapError, match="nor a reference trajectory CSV"):
        load_reference(other)


@pytest.mark.parametrize("command", ["replay", "evaluate"])
def test_a_malformed_csv_through_the_cli_is_one_line_and_status_2(
    tmp_path: Path, command: str
) -> None:
    sonar, nav, bad = tmp_path / "s.oculus", tmp_path / "n.tlog", tmp_path / "ref.csv"
    sonar.write_bytes(b"\0" * 64)
    nav.write_bytes(b"\0" * 64)
    bad.write_text(HEADER + ROW + "1700000000.1,40.6,-74.0,east\n")
    done = subprocess.run(
        [sys.executable, "-m", "seamap", command, "--sonar", str(sonar), "--nav", str(nav),
         "--truth", str(bad), "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert f"{bad}: row 3, column heading_deg: 'east' is not a number" in lines[0]


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.floats(0.01, 2.0), min_size=2, max_size=40),
    where=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=20),
    velocity=st.tuples(st.floats(-2.0, 2.0), st.floats(-2.0, 2.0)),
    start_heading=st.floats(0.0, 2 * math.pi, exclude_max=True),
    turn_rate=st.floats(-0.5, 0.5),
)
def test_a_steady_motion_is_interpolated_exactly_between_any_rows(
    steps: list[float], where: list[float], velocity: tuple[float, float],
    start_heading: float, turn_rate: float,
) -> None:  # fmt: skip
    rows = 1000.0 + np.concatenate([[0.0], np.cumsum(steps)])
    times = rows[0] + np.asarray(where) * (rows[-1] - rows[0])
    left, right, weight, how = match_times(rows, times, 0.0, math.inf)
    assert (how == 2).all() or rows[-1] in times
    assert ((weight >= 0) & (weight <= 1)).all()
    assert (rows[left] <= times + 1e-9).all() and (rows[right] >= times - 1e-9).all()

    def heading(t: np.ndarray) -> np.ndarray:
        return np.mod(start_heading + turn_rate * (t - 1000.0), 2 * math.pi)

    h_rows = heading(rows)
    got = np.mod(h_rows[left] + weight * wrap(h_rows[right] - h_rows[left]), 2 * math.pi)
    error = np.angle(np.exp(1j * (got - heading(times))))
    # Linear in time: exact wherever no two rows are a half-turn apart in heading.
    assert np.abs(error).max() < 1e-9
    east = velocity[0] * (rows - 1000.0)
    got_east = east[left] + weight * (east[right] - east[left])
    np.testing.assert_allclose(got_east, velocity[0] * (times - 1000.0), atol=1e-9)


def test_a_trajectory_csv_of_another_run_is_a_reference(tmp_path: Path) -> None:
    t = 1.7e9 + np.arange(0.0, 30.0, 0.2)
    poses = circle(t - t[0])
    local = LocalFrame(EPSG, 500_000.0, 4_500_000.0)
    write_trajectory(tmp_path / "trajectory.csv", local, t, poses - [500_000.0, 4_500_000.0, 0.0])
    matched = load_reference(tmp_path / "trajectory.csv").at(t, EPSG, SONAR)
    np.testing.assert_allclose(matched.poses[:, :2], poses[:, :2], atol=1e-4)
    error = np.angle(np.exp(1j * (matched.poses[:, 2] - poses[:, 2])))
    assert np.abs(error).max() < math.radians(2e-4)
