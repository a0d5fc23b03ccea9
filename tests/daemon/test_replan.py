"""Re-planning the gaps: lanes over what a survey missed, in the order that shortens the
way from the boat, never through a keep-out, written as a plan the start command takes."""

from __future__ import annotations

import itertools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely

from daemon.config import SiteConfig
from daemon.plan_files import read_plan, swath_from_config
from daemon.replan_files import replan_survey
from drivers.formats.results import write_coverage_tif, write_geotiff, write_trajectory
from drivers.mission import load_plan
from mapping.coverage import CoverageGrid, SeabedCoverage, SonarFan
from mapping.frames import SonarMount
from mapping.geo import LocalFrame
from mapping.preprocess import lit_min_range
from planning import Area, LegKind, Polygon, cells_geometry
from planning.replan import plan_gaps
from seamap.cli import main

REPO = Path(__file__).resolve().parents[2]
FRAME = LocalFrame.around(43.1, 5.9)
HALF = swath_from_config(SiteConfig()).half_width_m
CLEARANCE = 2.0

# The survey's sonar, at the antenna: a lane's footprint is centred on its track and, at
# 1 m altitude, 15 degrees tilt and 5 m range, sees 4.35 m to either side.
TILT = math.radians(15.0)
MOUNT = SonarMount(0.0, 0.0, 0.0, 0.0, TILT, 1.0)
FAN = SonarFan(math.radians(65.0), lit_min_range(1.0, 15.0, 20.0, 1.0), 5.0, TILT)
REACH_M = math.sqrt(5.0**2 - 1.0 - (1.0 / math.tan(math.radians(24.0))) ** 2)

# A 60 m x 40 m area surveyed by lanes 6 m apart, north and south in turn, each 8 m beyond
# its ends; the lane at 27 m skipped: a stripe 3.3 m wide no lane saw. A hole east of it
# whose keep-out (2 m round it) reaches over the stripe's middle.
OUTER = np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 40.0], [0.0, 40.0]])
HOLE = np.array([[27.5, 15.0], [30.5, 15.0], [30.5, 25.0], [27.5, 25.0]])
LANES = [3.0 + 6.0 * k for k in range(10)]
SKIPPED = 27.0
STRIPE = shapely.difference(
    shapely.box(SKIPPED - 6.0 + REACH_M, 0.0, SKIPPED + 6.0 - REACH_M, 40.0), shapely.Polygon(HOLE)
)


def track(
    points: list[tuple[float, float]], t0: float, speed: float = 0.5, rate: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """Times and vehicle poses (local x, y, grid heading) driving straight from point to
    point at ``speed``, a frame every 1 / ``rate`` seconds."""
    times, poses, t = [], [], t0
    for a, b in itertools.pairwise(np.asarray(points, float)):
        length = float(np.hypot(*(b - a)))
        n = max(int(length / speed * rate), 1)
        f = np.arange(n) / n
        heading = math.atan2(b[0] - a[0], b[1] - a[1])
        poses.append(np.column_stack([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]),
                                      np.full(n, heading)]))  # fmt: skip
        times.append(t + np.arange(n) / rate)
        t += n / rate
    return np.concatenate(times), np.concatenate(poses)


def lawnmower(skip: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    times, poses, t0 = [], [], 1000.0
    for k, east in enumerate(LANES):
        if east not in skip:
            ends = [(east, -8.0), (east, 48.0)]
            t, p = track(ends if k % 2 == 0 else ends[::-1], t0)
            times.append(t)
            poses.append(p)
        t0 += 56.0 / 0.5 + 30.0  # the lane, then a turn
    return np.concatenate(times), np.concatenate(poses)


def seen(times: np.ndarray, poses: np.ndarray) -> CoverageGrid:
    coverage = SeabedCoverage(MOUNT, FAN, anchor_e=FRAME.anchor_e, anchor_n=FRAME.anchor_n)
    coverage.add_frames(times, poses)
    return coverage.grid()


def latlon_ring(local: np.ndarray) -> list[list[float]]:
    lat, lon = FRAME.to_latlon(local[:, 0], local[:, 1])
    positions = [[float(b), float(a)] for a, b in zip(lat, lon, strict=True)]
    return [*positions, positions[0]]


def write_area(path: Path, outer: np.ndarray, *holes: np.ndarray) -> Path:
    rings = [latlon_ring(outer), *(latlon_ring(h) for h in holes)]
    path.write_text(json.dumps({"type": "Polygon", "coordinates": rings}))
    return path


def write_survey(folder: Path, skip: tuple[float, ...]) -> Path:
    """A survey's result folder: coverage.tif of the lawnmower and its trajectory.csv."""
    folder.mkdir(parents=True, exist_ok=True)
    times, poses = lawnmower(skip)
    write_coverage_tif(folder / "coverage.tif", seen(times, poses), FRAME.epsg, 1)
    write_trajectory(folder / "trajectory.csv", FRAME, times, poses)
    return folder


def local_path(plan: Path) -> np.ndarray:
    """The .plan's waypoints, as the autopilot will drive them, in local metres."""
    lat, lon = np.array([w[:2] for w in read_plan(plan).waypoints]).T
    x, y = FRAME.to_local(lat, lon)
    return np.column_stack([x, y])


def fraction_seen(region: shapely.Geometry, grid: CoverageGrid) -> float:
    west, north = grid.west_m - FRAME.anchor_e, grid.north_m - FRAME.anchor_n
    cells = cells_geometry(grid.meets(1), west, north, grid.cell_m)
    return float(shapely.area(shapely.intersection(region, cells)) / shapely.area(region))


@pytest.fixture(scope="module")
def skipped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The survey folder of the lawnmower that skipped a lane, and its area next to it."""
    folder = write_survey(tmp_path_factory.mktemp("replan") / "survey", (SKIPPED,))
    write_area(folder.parent / "area.geojson", OUTER, HOLE)
    return folder


@pytest.fixture(scope="module")
def replanned(skipped: Path) -> dict:
    out = skipped.parent / "gaps" / "gaps.plan"
    return replan_survey(
        skipped.parent / "area.geojson", out, SiteConfig(), coverage=skipped / "coverage.tif"
    )


def test_the_replan_maps_the_skipped_stripe_and_keeps_out_of_the_hole(replanned: dict) -> None:
    assert replanned["gaps"] == 1 and replanned["unreachable"] == 0
    assert replanned["gaps_m2"] == pytest.approx(STRIPE.area, rel=0.1)
    assert replanned["coverage"] >= 0.97  # planning's swath model
    # The sonar's own coverage model, driven along the mission's waypoints as the boat
    # would: what the new lanes see of the stripe the survey missed.
    path = local_path(Path(replanned["files"][0]))
    again = seen(*track([tuple(p) for p in path], 5000.0))
    stripe_seen = fraction_seen(STRIPE, again)
    assert stripe_seen >= 0.97
    # Lanes over the gap, not a new survey: the new path sees little of the rest.
    assert fraction_seen(shapely.box(0, 0, 60, 40), again) < 0.35
    # No leg, nor the autopilot's straight way to the first waypoint from the start,
    # comes closer to the hole than the clearance.
    start = FRAME.to_local(*replanned["start"])
    legs = shapely.linestrings(np.stack([np.vstack([start, path[:-1]]), path], axis=1))
    assert float(shapely.distance(legs, shapely.Polygon(HOLE)).min()) >= CLEARANCE - 1e-3
    print(
        f"stripe {STRIPE.area:.0f} m²: {100 * stripe_seen:.1f} % seen by the replan "
        f"({100 * replanned['coverage']:.1f} % in the swath model); "
        f"{replanned['distance_m']:.0f} m, {replanned['lanes']} lanes, "
        f"{replanned['waypoints']} waypoints"
    )


def test_the_plan_files_are_the_survey_plans_and_show_the_gaps(replanned: dict) -> None:
    names = [Path(f).name for f in replanned["files"]]
    assert names == ["gaps.plan", "gaps.waypoints", "gaps.geojson", "gaps.png"]
    mission = read_plan(Path(replanned["files"][0]))
    assert len(mission.waypoints) == replanned["waypoints"]
    assert mission.speed_mps == 1.0 and mission.firmware == "ardupilot"
    assert len(load_plan(replanned["files"][0]).items) == 1 + replanned["waypoints"]
    features = json.loads(Path(replanned["files"][2]).read_text())["features"]
    gaps = [f for f in features if f["properties"]["role"] == "gap"]
    assert len(gaps) == 1 and gaps[0]["properties"]["reached"]
    assert gaps[0]["properties"]["area_m2"] == pytest.approx(replanned["gaps_m2"], abs=0.1)
    area = next(f for f in features if f["properties"]["role"] == "area")
    assert area["properties"]["covered_fraction"] == pytest.approx(
        1 - STRIPE.area / (2400 - 30), abs=0.01
    )
    # What the gap mission is to cover, for the daemon's coverage when it is started: the
    # gaps, not the whole area.
    target = load_plan(replanned["files"][0]).area
    assert target is not None and target["type"] == "MultiPolygon"
    (gap,) = target["coordinates"]
    x, y = FRAME.to_local([p[1] for p in gap[0]], [p[0] for p in gap[0]])
    outline = shapely.Polygon(np.column_stack([x, y]))
    assert outline.area == pytest.approx(replanned["gaps_m2"], rel=1e-3)
    assert shapely.hausdorff_distance(outline, STRIPE) < 1.0


def test_two_gaps_are_taken_nearest_first_from_where_the_boat_is(tmp_path: Path) -> None:
    survey = write_survey(tmp_path / "survey", (9.0, 51.0))  # two stripes, 42 m apart
    area = write_area(tmp_path / "area.geojson", OUTER)
    firsts, approaches = [], []
    for name, east in (("west", -20.0), ("east", 80.0)):
        lat, lon = FRAME.to_latlon(east, 20.0)
        summary = replan_survey(
            area,
            tmp_path / f"{name}.plan",
            SiteConfig(),
            coverage=survey / "coverage.tif",
            start=(float(lat), float(lon)),
        )
        assert summary["gaps"] == 2 and summary["groups"] == 2
        assert summary["start_from"] == "--from"
        path = local_path(Path(summary["files"][0]))
        firsts.append(path[0, 0])
        approaches.append(summary["approach_m"])
        # the first stripe done before the boat crosses to the other
        near, far = (9.0, 51.0) if name == "west" else (51.0, 9.0)
        reached_far = np.flatnonzero(np.abs(path[:, 0] - far) < 3.0)[0]
        assert np.all(np.abs(path[:reached_far, 0] - near) < 3.0)
    assert abs(firsts[0] - 9.0) < 3.0 and abs(firsts[1] - 51.0) < 3.0
    assert max(approaches) < 40.0  # straight to the nearer stripe's end, not across


def test_gaps_along_one_lane_line_are_one_lane_with_a_transit() -> None:
    area = Area((Polygon(OUTER),))
    gaps = [shapely.box(20.0, 4.0, 23.0, 15.0), shapely.box(20.0, 27.0, 23.0, 37.0)]
    planned = plan_gaps(area, gaps, start=(21.5, -10.0), spacing_m=HALF, half_width_m=HALF)
    assert len(planned.groups) == 1 and planned.groups[0].gaps == (0, 1)
    kinds = [leg.kind for leg in planned.plan.legs]
    assert kinds == [LegKind.LANE, LegKind.TRANSIT, LegKind.LANE]
    assert planned.coverage.fraction == pytest.approx(1.0)
    # From the south the boat enters at the south end and goes north.
    assert planned.plan.legs[0].start[1] < 0 and planned.approach_m < 10.0


def test_the_way_between_gaps_goes_round_a_hole_between_them() -> None:
    hole = np.array([[40.0, 4.0], [60.0, 4.0], [60.0, 36.0], [40.0, 36.0]])
    area = Area((Polygon(np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 40.0], [0.0, 40.0]]),
                         (hole,)),))  # fmt: skip
    gaps = [shapely.box(10.0, 17.0, 14.0, 23.0), shapely.box(86.0, 17.0, 90.0, 23.0)]
    for start in ((0.0, 20.0), (50.0, 1.0)):
        planned = plan_gaps(
            area, gaps, start=start, spacing_m=HALF, half_width_m=HALF, clearance_m=CLEARANCE
        )
        legs = planned.plan.legs
        ends = np.vstack([start, planned.plan.waypoints])  # the boat is at the start
        path = shapely.linestrings(np.stack([ends[:-1], ends[1:]], axis=1))
        assert float(shapely.distance(path, shapely.Polygon(hole)).min()) >= CLEARANCE - 1e-3
        assert len(planned.groups) == 2 and planned.coverage.fraction == pytest.approx(1.0)
        between = [leg for leg in legs if leg.kind == LegKind.DETOUR]
        assert between and all(leg.lane < 0 for leg in between)  # corners, not lanes
        assert planned.approach_m < 45.0  # to the nearer gap, round the hole


def test_the_command_line_replans_a_survey_folder(skipped: Path, tmp_path: Path) -> None:
    out = tmp_path / "gaps.plan"
    done = subprocess.run(
        [sys.executable, "-m", "seamap", "survey", "replan", "--survey", str(skipped),
         "--area", str(skipped.parent / "area.geojson"), "--out", str(out)],
        capture_output=True, text=True, timeout=300, check=False,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    lines = done.stdout.splitlines()
    assert lines[0].startswith(f"{out}: 1 gap of 1 m² or more")
    assert "from trajectory.csv" in done.stdout and "of the gaps" in done.stdout
    for suffix in (".plan", ".waypoints", ".geojson", ".png"):
        assert out.with_suffix(suffix).stat().st_size > 0
    mission = read_plan(out)
    assert len(mission.waypoints) >= 2
    assert len(load_plan(out).items) == 1 + len(mission.waypoints)
    # The survey ended at its last lane's end: the plan's home is there.
    last = np.loadtxt(skipped / "trajectory.csv", delimiter=",", skiprows=1)[-1]
    assert mission.home == pytest.approx((last[1], last[2], 0.0), abs=1e-7)


def run(args: list[str], capfd: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    status = main(args)
    captured = capfd.readouterr()
    return status, captured.out, captured.err


def test_a_fully_covered_area_has_nothing_to_replan(
    tmp_path: Path, skipped: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    survey = write_survey(tmp_path / "survey", ())
    area = str(skipped.parent / "area.geojson")
    out = tmp_path / "gaps.plan"
    status, stdout, stderr = run(
        ["survey", "replan", "--survey", str(survey), "--area", area, "--out", str(out)], capfd
    )
    assert (status, stderr) == (0, "")
    assert stdout.count("\n") == 1 and "nothing to re-plan" in stdout
    assert "100.0 %" in stdout
    assert list(tmp_path.glob("gaps*")) == []
    # A gap smaller than --min-gap is no gap to re-plan either.
    status, stdout, _ = run(
        ["survey", "replan", "--coverage", str(skipped / "coverage.tif"), "--area", area,
         "--min-gap", "1000", "--out", str(out)], capfd,
    )  # fmt: skip
    assert status == 0 and "nothing to re-plan" in stdout and "1000 m²" in stdout
    assert list(tmp_path.glob("gaps*")) == []


def bad_inputs(folder: Path, skipped: Path) -> dict[str, tuple[list[str], str]]:
    """Name: (the arguments after `seamap survey replan`, what the one line says)."""
    area = str(skipped.parent / "area.geojson")
    tif = str(skipped / "coverage.tif")
    one_band = folder / "mosaic.tif"
    write_geotiff(one_band, np.ones((8, 8), np.uint8), FRAME.anchor_e, FRAME.anchor_n, 0.5,
                  FRAME.epsg)  # fmt: skip
    (folder / "text.tif").write_text("not a raster\n")
    far = write_area(folder / "far.geojson", OUTER + 3000.0)
    (folder / "empty").mkdir()
    return {
        "missing": (["--coverage", str(folder / "nope.tif"), "--area", area], "no such file"),
        "one band": (["--coverage", str(one_band), "--area", area], "not a seamap coverage"),
        "text": (["--coverage", str(folder / "text.tif"), "--area", area], "not a GeoTIFF"),
        "no coverage.tif": (["--survey", str(folder / "empty"), "--area", area], "no such file"),
        "elsewhere": (["--coverage", tif, "--area", str(far)], "does not overlap"),
        "missing area": (["--coverage", tif, "--area", str(folder / "a.geojson")], "no such"),
        "min gap": (["--coverage", tif, "--area", area, "--min-gap", "lots"], "not a number"),
        "spacing": (["--coverage", tif, "--area", area, "--spacing", "-2"], "spacing"),
        "from": (["--coverage", tif, "--area", area, "--from", "43.1"], "LAT,LON"),
        "range": (["--coverage", tif, "--area", area, "--from", "95,5.9"], "out of range"),
        "swapped": (["--coverage", tif, "--area", area, "--from", "5.9,43.1"], "km from the area"),
    }


def test_bad_inputs_are_one_line_and_status_2(
    tmp_path: Path, skipped: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "gaps.plan"
    for name, (args, reason) in bad_inputs(tmp_path, skipped).items():
        status, stdout, stderr = run(["survey", "replan", *args, "--out", str(out)], capfd)
        assert status == 2, name
        assert stderr.count("\n") == 1 and reason in stderr, (name, stderr)
        assert stderr.startswith("seamap survey: ") and not stdout
        assert not out.exists(), name


@pytest.mark.parametrize("name", ["text", "one band", "min gap"])
def test_bad_inputs_leave_no_traceback_nor_warning_in_a_real_process(
    tmp_path: Path, skipped: Path, name: str
) -> None:
    args, reason = bad_inputs(tmp_path, skipped)[name]
    done = subprocess.run(
        [sys.executable, "-m", "seamap", "survey", "replan", *args, "--out",
         str(tmp_path / "gaps.plan")],
        capture_output=True, text=True, timeout=300, check=False,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    assert done.returncode == 2
    assert len(done.stderr.splitlines()) == 1 and reason in done.stderr, done.stderr
