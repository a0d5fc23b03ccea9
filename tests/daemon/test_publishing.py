"""What the daemon publishes (``daemon.publishing.Publishing``) and says of itself
(``daemon.status.StatusReporter``): the newest pose, the tile count, the coverage status
(live, then final), the live coverage's timer, and the status snapshot, line and health
task (to systemd over a real datagram socket)."""

from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

import daemon.publishing as publishing_module
from daemon.config import ZenohConfig
from daemon.health import HealthMonitor, LiveParts
from daemon.live_coverage import CoverageMessage, LiveCoverage
from daemon.notify import Notifier
from daemon.publishing import Publishing
from daemon.status import StatusReporter
from daemon.survey import SurveyState
from daemon.surveys import OpenSurvey
from drivers.zenoh_io import CoverageInfo
from mapping.streaming import PoseUpdate, TileUpdate


def pose(frame: int, time: float) -> PoseUpdate:
    return PoseUpdate(frame, time, 500000.0 + frame, 6540000.0, 90.0, 59.0, 10.0, 32632, False)


def tile() -> TileUpdate:
    return TileUpdate((0, 0), np.zeros((4, 4), np.uint8), 1, 32632, 0.05, 4, 500000.0, 6540000.0)


def message(survey: str, final: bool, fraction: float = 0.25) -> CoverageMessage:
    summary = {
        "survey": survey,
        "final": final,
        "seen_m2": 10.0,
        "area": {"fraction": fraction},
        "gaps": {"type": "FeatureCollection", "features": []},
    }
    return CoverageMessage(summary, b"", CoverageInfo(32632, 0.25, 500000.0, 6540000.0, 1, 1, 1))


class FakeCoverage:
    """A live coverage's face: frames counted, and its publications (counted)."""

    def __init__(self, fail: bool = False) -> None:
        self.counted = 0
        self.reads = 0
        self.made: list[str] = []
        self.fail = fail

    @property
    def frames(self) -> int:
        self.reads += 1
        return self.counted

    def message(self, survey: str) -> CoverageMessage | None:
        if self.fail:
            raise ValueError("no fan")
        self.made.append(survey)
        return message(survey, final=False) if self.counted else None


def live(coverage: FakeCoverage) -> LiveCoverage:
    return cast(LiveCoverage, coverage)


def test_the_newest_pose_is_where_the_boat_is() -> None:
    publishing = Publishing(ZenohConfig(), OpenSurvey())
    publishing.on_pose(pose(2, 10.0))
    publishing.on_pose(pose(1, 9.0))  # a refinement of an older frame
    assert publishing.latest_pose == pose(2, 10.0)
    publishing.on_pose(pose(3, 10.5))
    assert publishing.latest_pose == pose(3, 10.5)
    publishing.on_tile("20260101-000000", tile())
    publishing.on_tile("20260101-000000", tile())
    assert publishing.tiles_published == 2
    publishing.coverage_status = {"survey": "20260101-000000"}
    publishing.survey_opened()  # a new survey: nothing of its own yet
    assert publishing.latest_pose is None and publishing.tiles_published == 0
    assert publishing.coverage_status is None


def test_the_coverage_status_is_the_open_surveys_then_the_final_one() -> None:
    open_survey = OpenSurvey(survey=SurveyState("A", "boat1"))
    publishing = Publishing(ZenohConfig(), open_survey)
    coverage = FakeCoverage()
    coverage.counted = 3

    async def main() -> None:
        await publishing.publish_coverage("B", live(coverage))  # not the open survey's
        assert publishing.coverage_status is None
        await publishing.publish_coverage("A", live(coverage))
        assert publishing.coverage_status == {
            k: v for k, v in message("A", final=False).summary.items() if k != "gaps"
        }
        publishing.final_coverage("B", message("B", final=True))  # A is still open
        assert publishing.coverage_status is not None
        assert publishing.coverage_status["survey"] == "A"
        open_survey.survey = None
        publishing.final_coverage("B", message("B", final=True))
        assert publishing.coverage_status is not None
        assert publishing.coverage_status["survey"] == "B"
        assert publishing.coverage_status["final"] is True
        await publishing.publish_coverage("C", live(FakeCoverage()))  # no frame yet: nothing
        assert publishing.coverage_status["survey"] == "B"

    asyncio.run(main())


def test_a_failed_live_coverage_is_logged_not_raised(caplog: pytest.LogCaptureFixture) -> None:
    publishing = Publishing(ZenohConfig(), OpenSurvey(survey=SurveyState("A", "boat1")))
    with caplog.at_level(logging.WARNING, logger="daemon.service"):
        asyncio.run(publishing.publish_coverage("A", live(FakeCoverage(fail=True))))
    assert publishing.coverage_status is None
    assert [r.getMessage() for r in caplog.records] == ["live coverage failed"]


def test_the_live_coverage_is_published_while_it_grows(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(publishing_module, "COVERAGE_EVERY_S", 0.001)
    coverage = FakeCoverage()
    open_survey = OpenSurvey(survey=SurveyState("A", "boat1"), coverage=live(coverage))
    publishing = Publishing(ZenohConfig(), open_survey)

    async def until(check: Any) -> None:
        for _ in range(5000):
            if check():
                return
            await asyncio.sleep(0.001)
        raise AssertionError("timed out")

    async def main() -> None:
        task = asyncio.create_task(publishing.coverage_task())
        try:
            await until(lambda: coverage.made == ["A"])  # the first look: frames 0 != -1
            coverage.counted = 5
            await until(lambda: len(coverage.made) == 2)
            reads = coverage.reads
            await until(lambda: coverage.reads >= reads + 5)  # looked again, unchanged
            assert coverage.made == ["A", "A"]
            assert publishing.coverage_status is not None
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    asyncio.run(main())


@pytest.fixture
def manager(tmp_path: Path) -> Iterator[socket.socket]:
    """systemd's end of $NOTIFY_SOCKET."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    sock.settimeout(10.0)
    yield sock
    sock.close()


def test_the_status_and_its_line(tmp_path: Path, manager: socket.socket) -> None:
    parts, open_survey = LiveParts(), OpenSurvey()
    publishing = Publishing(ZenohConfig(), open_survey)
    notifier = Notifier({"NOTIFY_SOCKET": manager.getsockname()})
    health = HealthMonitor("boat1", tmp_path)
    reporter = StatusReporter(health, parts, open_survey, publishing, notifier, 0.5)
    assert reporter.text() == "no survey"  # no snapshot yet
    snapshot = reporter.snapshot()
    assert snapshot["vehicle"] == "boat1" and snapshot["survey"] is None
    assert snapshot["pose"] is None and snapshot["tiles_published"] == 0
    assert snapshot["coverage"] is None
    publishing.on_pose(pose(7, 12.0))
    publishing.on_tile("A", tile())
    publishing.coverage_status = message("A", final=False).status()
    snapshot = reporter.snapshot()
    assert snapshot["pose"] == {
        "time": 12.0, "lat": 59.0, "lon": 10.0, "east": 500007.0, "north": 6540000.0,
        "heading_deg": 90.0, "epsg": 32632,
    }  # fmt: skip
    assert snapshot["tiles_published"] == 1 and snapshot["coverage"]["survey"] == "A"
    health.sample(parts)
    assert reporter.text() == "no survey: 0 frames mapped, lag 0.0 s"
    open_survey.survey = SurveyState("A", "boat1")
    assert reporter.survey_id() == "A"
    line = "A: 0 frames mapped, lag 0.0 s, 25.0 % of the area covered"
    assert reporter.text() == line

    async def main() -> bytes:
        task = asyncio.create_task(reporter.task())
        try:
            return await asyncio.to_thread(manager.recv, 4096)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    assert (
        asyncio.run(main()) == b"STATUS=A: 0 frames mapped, lag 0.0 s, 25.0 % of the area covered"
    )
