"""Opening and closing surveys (``daemon.surveys.Surveys``) with the device feeds
(``daemon.feeds.Feeds``) and what is published (``daemon.publishing.Publishing``), wired
as the daemon wires them, fed a simulated survey: what is recorded, mapped live and left
for the survey-end pass; the survey's area; the sonar's standby policy."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

from daemon.config import SiteConfig, config_from_dict
from daemon.feeds import Feeds
from daemon.health import LiveParts
from daemon.publishing import Publishing
from daemon.survey import SurveyState, read_state, surveys_dir
from daemon.survey_files import AREA_FILE
from daemon.surveys import OpenSurvey, Surveys
from drivers.errors import SeamapError
from drivers.formats.area import read_area
from mapping.samples import NavSample, Ping
from tools.sim.stream import survey_events


class Rig:
    """The parts a survey goes through, wired as ``daemon.service.Daemon`` wires them."""

    def __init__(self, config: SiteConfig) -> None:
        self.parts = LiveParts()
        self.open_survey = OpenSurvey()
        self.publishing = Publishing(config.zenoh, self.open_survey)
        self.feeds = Feeds(config, self.parts, self.open_survey)
        self.changes = 0
        self.surveys = Surveys(
            config, Path(config.daemon.state_dir), self.parts, self.open_survey,
            sink=self.publishing, on_change=self._changed,
        )  # fmt: skip

    def _changed(self) -> None:
        self.changes += 1
        self.feeds.follow_survey()


def with_state_dir(config: SiteConfig, state_dir: Path, **daemon: Any) -> SiteConfig:
    return dataclasses.replace(
        config, daemon=dataclasses.replace(config.daemon, state_dir=str(state_dir), **daemon)
    )


def square(lon: float = 10.0, lat: float = 59.0, side_deg: float = 0.001) -> dict[str, Any]:
    """A GeoJSON polygon (WGS84), about 60 m by 110 m."""
    ring = [[lon, lat], [lon + side_deg, lat], [lon + side_deg, lat + side_deg],
            [lon, lat + side_deg], [lon, lat]]  # fmt: skip
    return {"type": "Polygon", "coordinates": [ring]}


def test_a_survey_records_maps_live_and_is_left_for_its_pass(tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    sent: list[bytes] = []

    async def main() -> tuple[Rig, str, SurveyState | None, int, float]:
        stream_config = survey_events("quadrats", 4, max_pings=1, n_beams=128).site_config
        config = with_state_dir(stream_config, state_dir, max_backlog_frames=10000)
        rig = Rig(config)
        survey_id = rig.surveys.start("command")
        assert rig.surveys.start("command") == survey_id  # one survey at a time

        def record(message: bytes, received: float) -> None:
            sent.append(message)
            rig.feeds.on_sonar_message(message, received)

        stream = survey_events("quadrats", 4, record, max_pings=40, n_beams=128)
        pings, last = 0, 0.0
        for _, sample in stream.events:
            if isinstance(sample, Ping):
                rig.feeds.on_ping(sample)
                pings, last = pings + 1, sample.time
            else:
                rig.feeds.on_nav_sample(cast(NavSample, sample))
        assert rig.parts.survey == survey_id and rig.open_survey.coverage is not None
        assert rig.open_survey.coverage.fan is not None  # from the first ping
        closed = await rig.surveys.close("command")
        return rig, survey_id, closed, pings, last

    rig, survey_id, closed, pings, last = asyncio.run(main())
    folder = surveys_dir(state_dir) / survey_id
    assert closed is not None and closed.id == survey_id
    saved = read_state(folder)
    assert saved is not None and saved.state == "finishing" and saved.reason == "command"
    assert saved.segments == 1 and saved.ended is not None
    # What the boat computed as it went, kept for comparison with the survey-end pass.
    live = saved.live["1"]
    assert live["frames_received"] == pings == 40
    assert 0 < live["frames_mapped"] <= pings
    trajectory = folder / live["trajectory"]
    assert trajectory.name == "live-trajectory-001.csv"
    assert len(trajectory.read_text().splitlines()) > 1
    # Every sonar message was recorded before anything parsed it.
    assert len(sent) == pings
    assert (folder / "sonar-001.oculus").stat().st_size > sum(len(m) for m in sent)
    # The links' news for the health monitor, and nothing of the survey left open.
    assert rig.parts.last_ping == last and rig.parts.last_fix is not None
    assert rig.open_survey.survey is None and rig.open_survey.coverage is None
    assert rig.parts.recorder is None and rig.parts.mapper is None and rig.parts.survey is None
    assert rig.changes == 2
    # What went out: the newest pose, the tiles, and the live map's last coverage.
    pose = rig.publishing.latest_pose
    assert pose is not None and pose.time <= last
    assert rig.publishing.tiles_published > 0
    coverage = rig.publishing.coverage_status
    assert coverage is not None and coverage["survey"] == survey_id
    assert coverage["final"] is False and coverage["seen_m2"] > 0


def test_a_survey_keeps_its_area(tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    mission = tmp_path / "mission.geojson"
    mission.write_text(json.dumps({"type": "Feature", "properties": {}, "geometry": square()}))
    config = config_from_dict({"daemon": {"state_dir": str(state_dir)}})
    with_mission = config_from_dict(
        {"daemon": {"state_dir": str(state_dir)}, "mission": {"area": str(mission)}}
    )

    async def main() -> dict[str, Any]:
        seen: dict[str, Any] = {}
        rig = Rig(config)
        rig.surveys.read_mission_area()
        assert rig.surveys.mission_area is None
        # A bad area: one line, and no survey opened.
        with pytest.raises(SeamapError, match=r"^area: "):
            rig.surveys.start("command", {"type": "Point", "coordinates": [10.0, 59.0]})
        assert not any(surveys_dir(state_dir).glob("*"))
        # Opened without an area, it takes the first one a later start brings.
        first = rig.surveys.start("command")
        folder = surveys_dir(state_dir) / first
        seen["no area"] = (folder / AREA_FILE).exists()
        assert rig.surveys.start("command", square()) == first
        assert rig.open_survey.coverage is not None and rig.open_survey.coverage.area is not None
        kept = (folder / AREA_FILE).read_text()
        assert rig.surveys.start("command", square(lon=11.0)) == first
        seen["kept"] = (folder / AREA_FILE).read_text() == kept
        await rig.surveys.close("command")
        # [mission] area, for a survey started without one.
        rig = Rig(with_mission)
        rig.surveys.read_mission_area()
        second = rig.surveys.start("autostart")
        seen["mission"] = read_area(surveys_dir(state_dir) / second / AREA_FILE)
        await rig.surveys.close("shutdown")
        assert await rig.surveys.close("shutdown") is None  # nothing open any more
        return seen

    seen = asyncio.run(main())
    assert seen["no area"] is False and seen["kept"] is True
    expected = read_area(mission).polygons_latlon[0][0]
    assert np.allclose(seen["mission"].polygons_latlon[0][0], expected)


class FakeSonar:
    """What the standby policy asks of the sonar's link."""

    def __init__(self) -> None:
        self.asked: list[bool] = []

    def set_standby(self, rest: bool) -> None:
        self.asked.append(rest)


@pytest.mark.parametrize("standby", [True, False])
def test_the_sonar_follows_the_survey(standby: bool, caplog: pytest.LogCaptureFixture) -> None:
    config = config_from_dict({"sonar": {"standby_outside_surveys": standby}})
    parts, open_survey = LiveParts(), OpenSurvey()
    feeds = Feeds(config, parts, open_survey)
    feeds.follow_survey()  # no link yet: nothing to ask
    sonar = FakeSonar()
    parts.sonar = cast(Any, sonar)
    with caplog.at_level(logging.INFO, logger="daemon.service"):
        feeds.follow_survey()
        feeds.follow_survey()  # said once a change
        open_survey.survey = SurveyState("20260101-000000", "boat1")
        assert not feeds.sonar_rests()
        feeds.follow_survey()
        open_survey.survey = None
        assert feeds.sonar_rests() is standby
        feeds.follow_survey()
    lines = [r.getMessage() for r in caplog.records]
    if standby:
        assert sonar.asked == [True, False, True]
        assert lines == [
            "sonar standing by: no survey open",
            "sonar firing: survey open",
            "sonar standing by: no survey open",
        ]
    else:
        assert sonar.asked == [False]
        assert lines == ["sonar firing: survey open"]
