"""Coverage live and at the end, on loopback: the emulators play a simulated survey whose
boat skips the middle one of three lanes, leaving a stripe of seabed unseen; the real
daemon is asked over zenoh to open a survey of the area (with a keep-out hole in the
stripe), publishes its coverage as it maps, and at the end writes the gaps and, with
``[mission] replan_at_end``, the lanes that go back for them.

The stripe is worked out from the simulator's truth alone: the driven lanes' lines and
the sonar's reach to the side (the truth's range, tilt and vertical beam at the site's
altitude, with the 10 degree grazing limit of ``[coverage]``), not from the mapper."""

from __future__ import annotations

import asyncio
import csv
import io
import json
import math
import signal
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely
from PIL import Image

from drivers.mission import load_plan
from drivers.zenoh_io import CoverageInfo, parse_coverage_key, parse_coverage_summary
from mapping.geo import LocalFrame
from tests.daemon.harness import (
    DaemonProcess,
    Heard,
    ZenohObserver,
    free_tcp_port,
    free_udp_port,
    write_config,
)
from tests.daemon.test_e2e import wait_for_state
from tools.emulators.playback import SurveyPlayback
from tools.sim import simulate

SCENARIO = {
    "n_lanes": 3,
    "skip_lanes": (1,),
    "lane_spacing_m": 6.0,
    "lane_length_m": 12.0,
    "speed_mps": 1.0,
    "ping_rate_hz": 5.0,
}
"""Lanes 6 m apart (a planned overlap of a quarter): without the middle one, the two
lanes left see all but a stripe about 3.3 m wide between them. Two 12 m lanes at 1 m/s:
the survey plays in about 50 s."""
HOLE_M = 1.0
"""Side of the square keep-out hole in the middle of the stripe (a mooring buoy)."""
TOLERANCE_M = 1.0
"""How far the gaps' outline may lie from the stripe's: an eighth of the sonar's swath
(8.7 m), allowing for the lanes' cross-track error and the GNSS error."""


@dataclass
class Run:
    sim: Path
    survey: Path
    area: dict[str, Any]
    exit_code: int
    log: str
    statuses: list[dict[str, Any]]
    heard: list[Heard]
    late: list[Heard]
    started: list[Heard]


def _area_with_hole(sim: Path) -> dict[str, Any]:
    """The simulator's area with a square hole at the survey's centre (the stripe's middle)."""
    truth = json.loads((sim / "truth.json").read_text())
    site = truth["site"]
    frame = LocalFrame(site["epsg"], site["utm_origin_east"], site["utm_origin_north"])
    lanes = truth["vehicle"]["lanes"]
    cx = (lanes[0]["start_east"] + lanes[-1]["start_east"]) / 2 - site["utm_origin_east"]
    cy = (lanes[0]["start_north"] + lanes[0]["end_north"]) / 2 - site["utm_origin_north"]
    half = HOLE_M / 2
    square = [(cx - half, cy - half), (cx - half, cy + half), (cx + half, cy + half),
              (cx + half, cy - half), (cx - half, cy - half)]  # fmt: skip
    hole = []
    for x, y in square:  # clockwise: an interior ring
        lat, lon = frame.to_latlon(x, y)
        hole.append([float(lon), float(lat)])
    geometry: dict[str, Any] = json.loads((sim / "area.geojson").read_text())["geometry"]
    geometry["coordinates"].append(hole)
    return geometry


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    root = tmp_path_factory.mktemp("coverage")
    sim = root / "sim"
    simulate("quadrats", 4, sim, **SCENARIO)
    area = _area_with_hole(sim)
    state_dir = root / "state"

    async def main() -> Run:
        mavlink_port, zenoh_port = free_udp_port(), free_tcp_port()
        endpoint = f"tcp/127.0.0.1:{zenoh_port}"
        async with SurveyPlayback(
            sim / "sonar.oculus", sim / "nav.tlog", mavlink="udp", mavlink_target_port=mavlink_port
        ) as play:
            config = write_config(
                sim, root / "site.toml", state_dir, play.sonar.tcp_port,
                f"udpin:127.0.0.1:{mavlink_port}", zenoh_port,
                tables={"mission": {"replan_at_end": True}}, survey_autostart=False,
            )  # fmt: skip
            daemon = DaemonProcess(config, state_dir, root / "daemon.log")
            await daemon.start()
            try:
                await daemon.wait_status(lambda s: True, 30)
                shore = ZenohObserver(endpoint)
                await asyncio.to_thread(shore.open)
                # The sonar stands by until the survey opens: the playback waits for it.
                request = json.dumps({"action": "start", "area": area}).encode()
                started = await asyncio.to_thread(shore.get, "seamap/boat1/control/survey", request)
                await asyncio.wait_for(play.done.wait(), 180)
                await daemon.wait_status(lambda s: s["frames"]["backlog"] == 0, 30)
                await asyncio.sleep(1.5)
                await asyncio.to_thread(
                    shore.get, "seamap/boat1/control/survey", b'{"action": "stop"}'
                )
                (survey,) = (state_dir / "surveys").iterdir()
                await asyncio.to_thread(wait_for_state, survey, "done", 240)
                await daemon.wait_status(
                    lambda s: bool(s.get("coverage") and s["coverage"]["final"]), 30
                )
                await asyncio.sleep(1.0)  # the final coverage's puts
                late_shore = ZenohObserver(endpoint)
                await asyncio.to_thread(late_shore.open)
                late = await asyncio.to_thread(
                    late_shore.get, f"seamap/boat1/survey/{survey.name}/coverage/**"
                )
                await asyncio.to_thread(late_shore.close)
                await asyncio.to_thread(shore.close)
                code = await daemon.stop(signal.SIGTERM)
            finally:
                await daemon.ensure_stopped()
            return Run(
                sim, survey, area, code, daemon.log(), daemon.statuses, shore.heard, late,
                started,
            )  # fmt: skip

    return asyncio.run(main())


def _report(run: Run) -> dict[str, Any]:
    report: dict[str, Any] = json.loads((run.survey / "report.json").read_text())
    return report


def _to_utm(rings: list[list[list[float]]], frame: LocalFrame) -> shapely.Polygon:
    def metric(ring: list[list[float]]) -> list[tuple[float, float]]:
        x, y = frame.to_local([p[1] for p in ring], [p[0] for p in ring])
        return list(zip(np.asarray(x).tolist(), np.asarray(y).tolist(), strict=True))

    return shapely.Polygon(metric(rings[0]), [metric(r) for r in rings[1:]])


@dataclass(frozen=True)
class Expected:
    frame: LocalFrame
    """UTM itself (anchor 0, 0)."""
    area: shapely.Polygon
    hole: shapely.Polygon
    stripe: shapely.Geometry
    """What the driven lanes leave unseen of the area (the hole left out)."""
    half_swath_m: float


def _expected(run: Run) -> Expected:
    truth = json.loads((run.sim / "truth.json").read_text())
    frame = LocalFrame(truth["site"]["epsg"], 0.0, 0.0)
    area = _to_utm(run.area["coordinates"], frame)
    sonar = truth["sonar"]
    site = tomllib.loads((run.sim / "site.toml").read_text())
    altitude = site["sonar"]["altitude_m"]
    # The far edge: the last range bin, or the 10 degree grazing limit if nearer.
    far = math.sqrt(sonar["range_m"] ** 2 - altitude**2)
    far = min(far, altitude / math.tan(math.radians(site["coverage"]["min_grazing_deg"])))
    # The near edge ahead: the steep edge of the vertical beam (less the 1 degree trim).
    steep = math.radians(sonar["tilt_deg"] + sonar["vertical_aperture_deg"] / 2 - 1.0)
    half_swath = math.sqrt(far**2 - (altitude / math.tan(steep)) ** 2)
    lanes = truth["vehicle"]["lanes"]
    west, east = sorted(lane["start_east"] for lane in lanes)
    band = shapely.box(west + half_swath, -1e9, east - half_swath, 1e9)
    return Expected(
        frame,
        area,
        shapely.Polygon(area.interiors[0]),
        shapely.intersection(band, area),
        half_swath,
    )


def test_the_daemon_took_the_area_and_ended_cleanly(run: Run) -> None:
    assert run.exit_code == 0, run.log
    assert "Traceback" not in run.log
    (reply,) = run.started
    assert json.loads(reply.payload) == {"ok": True, "survey": run.survey.name}
    kept = json.loads((run.survey / "area.geojson").read_text())["geometry"]
    assert kept["type"] == "MultiPolygon" and len(kept["coordinates"][0]) == 2  # the hole kept
    assert _report(run)["coverage"]["area"]["file"].endswith("area.geojson")


def _trajectory(path: Path) -> dict[float, tuple[float, float, float]]:
    with open(path, newline="") as stream:
        return {
            round(float(r["time"]), 3): (
                float(r["east"]),
                float(r["north"]),
                float(r["heading_deg"]),
            )
            for r in csv.DictReader(stream)
        }


def _live_against_final_m(run: Run) -> float:
    """How far the live map placed the fan's far corners from where the survey-end pass
    placed them (95th percentile over the frames both mapped, metres): the live poses'
    own difference, position plus heading at the fan's 5 m range."""
    live = _trajectory(run.survey / "live-trajectory-001.csv")
    final = _trajectory(run.survey / "trajectory.csv")
    moved = []
    for stamp in live.keys() & final.keys():
        (e0, n0, h0), (e1, n1, h1) = live[stamp], final[stamp]
        turn = abs(math.remainder(math.radians(h0 - h1), 2 * math.pi))
        moved.append(math.hypot(e0 - e1, n0 - n1) + 5.0 * turn)
    assert len(moved) > 100
    return float(np.percentile(moved, 95))


def test_the_live_fraction_grows_and_reaches_the_result_folders(run: Run) -> None:
    live = [
        s["coverage"]
        for s in run.statuses
        if s.get("coverage") and s["coverage"]["survey"] == run.survey.name
    ]
    during = [c["area"]["fraction"] for c in live if not c["final"]]
    final = [c for c in live if c["final"]]
    report = _report(run)["coverage"]
    result = report["area"]
    # The live map counts each frame where it placed it; the survey-end pass places the
    # frames afresh. The fractions may differ by what that move shifts across the gaps'
    # edges (their outline within the area, the hole's left out) and no more.
    expected = _expected(run)
    gaps = json.loads((run.survey / "gaps.geojson").read_text())["features"]
    edges = sum(_to_utm(g["geometry"]["coordinates"], expected.frame).exterior.length for g in gaps)
    moved = _live_against_final_m(run)
    allowed = edges * (moved + report["cell_m"]) / result["area_m2"]
    print(f"live covered fraction: {during[0]:.3f} ... {during[-1]:.3f}; result folder "
          f"{result['covered_fraction']:.4f} ({result['gaps']} gaps, {result['gaps_m2']} m²); "
          f"live poses {moved:.2f} m from the final ones, so up to {allowed:.3f} "
          "apart")  # fmt: skip
    assert len(set(during)) >= 4, during  # it grew in steps through the survey
    assert during == sorted(during), during  # and never went back
    assert during[0] < during[-1] - 0.2, during
    assert abs(during[-1] - result["covered_fraction"]) <= allowed
    assert final, "the status never showed the final coverage"
    assert final[-1]["area"]["fraction"] == result["covered_fraction"]
    assert final[-1]["area"]["gaps"] == result["gaps"]
    assert final[-1]["covered_m2"] == report["covered_m2"]


def test_the_gaps_are_the_skipped_lanes_stripe(run: Run) -> None:
    expected = _expected(run)
    gaps = json.loads((run.survey / "gaps.geojson").read_text())["features"]
    found = shapely.union_all([_to_utm(g["geometry"]["coordinates"], expected.frame) for g in gaps])
    distance = shapely.hausdorff_distance(found, expected.stripe)
    stripe_m2 = shapely.area(expected.stripe)
    print(f"stripe {stripe_m2:.1f} m² (half swath {expected.half_swath_m:.2f} m); "
          f"gaps {shapely.area(found):.1f} m² in {len(gaps)} parts, {distance:.2f} m from the "
          "stripe")  # fmt: skip
    assert shapely.area(expected.stripe) > 10.0  # the scenario does leave a stripe out
    assert distance < TOLERANCE_M
    assert (
        shapely.area(shapely.difference(expected.stripe, shapely.buffer(found, TOLERANCE_M))) < 0.01
    )
    assert (
        shapely.area(shapely.difference(found, shapely.buffer(expected.stripe, TOLERANCE_M))) < 0.01
    )
    assert not shapely.intersects(found, expected.hole.buffer(-0.01))  # the hole is not a gap


def test_the_replan_covers_the_stripe_and_keeps_off_the_hole(run: Run) -> None:
    expected = _expected(run)
    state = json.loads((run.survey / "survey.json").read_text())
    replan = state["result"]["replan"]
    assert replan["gaps"] >= 1 and replan["coverage"] >= 0.97, replan
    plan = load_plan(run.survey / "replan.plan")  # what `seamap survey start` loads
    assert plan.area is not None and plan.area["type"] == "MultiPolygon"
    points = [(item.params[4], item.params[5]) for item in plan.items if item.command == 16]
    x, y = expected.frame.to_local([p[0] for p in points], [p[1] for p in points])
    path = shapely.LineString(np.column_stack([x, y]))
    assert not shapely.intersects(path, expected.hole), "the gap plan crosses the hole"
    seen = shapely.area(shapely.intersection(path.buffer(expected.half_swath_m), expected.stripe))
    print(f"the gap plan: {replan['lanes']} lanes, {replan['distance_m']} m; its path's swath "
          f"covers {100 * seen / shapely.area(expected.stripe):.1f} % of the stripe")  # fmt: skip
    assert seen >= 0.97 * shapely.area(expected.stripe)


def test_coverage_is_published_live_and_a_late_shore_gets_the_final(run: Run) -> None:
    summaries, rasters = [], []
    for heard in run.heard:
        parts = parse_coverage_key(heard.key)
        if parts is None or parts.survey != run.survey.name:
            continue
        if parts.raster:
            assert heard.attachment is not None
            info = CoverageInfo.from_json(heard.attachment)
            image = Image.open(io.BytesIO(heard.payload))
            assert image.size == (info.cols, info.rows) and image.mode == "RGBA"
            rasters.append(info)
        else:
            summaries.append(parse_coverage_summary(heard.payload))
    versions = [s["version"] for s in summaries]
    assert len(summaries) >= 4 and versions == sorted(versions), versions
    assert [s["final"] for s in summaries].count(True) >= 1 and summaries[-1]["final"]
    assert {r.version for r in rasters} == set(versions)
    live_gaps = [len(s["gaps"]["features"]) for s in summaries if not s["final"]]
    assert live_gaps[0] >= 1  # the area not yet surveyed is all gap at first
    late = {parse_coverage_key(h.key).raster: h for h in run.late}  # type: ignore[union-attr]
    assert set(late) == {False, True}
    summary = parse_coverage_summary(late[False].payload)
    assert summary["final"]
    assert summary["gaps"] == json.loads((run.survey / "gaps.geojson").read_text())
    assert late[True].payload == (run.survey / "coverage.png").read_bytes()
