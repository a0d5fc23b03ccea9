"""Opening and closing surveys (``Surveys``), and the open survey the other parts read
(``OpenSurvey``).

A survey opens (``start``: a new folder ``state_dir/surveys/{id}/``, or ``open`` with
``resumed`` for the survey a crash interrupted) with its live parts: the recorder (a new
segment), the mapping thread and the live coverage, its area taken from the start
request, else from ``[mission] area``, and kept in the folder. It closes (``close``) in
the order that loses nothing: the recorder first, then the live map flushed, its last
coverage published, its counters and trajectory written, and ``survey.json`` left
``finishing`` for the survey-end pass, which the daemon then starts
(``daemon.final_pass``).

What the live map gives out goes to a ``SurveySink`` (``daemon.publishing``); the sonar's
standby policy hears of each change of the open survey (``on_change``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from daemon.config import SiteConfig
from daemon.health import LiveParts
from daemon.live_coverage import LiveCoverage
from daemon.mapper import MappingWorker
from daemon.recording import SurveyRecorder
from daemon.replay import mount_from_config, pipeline_params, streaming_params
from daemon.survey import SurveyState, new_survey_id, surveys_dir
from daemon.survey_files import (
    AREA_FILE,
    LIVE_TILES,
    keep_area,
    save_live,
    save_state,
    survey_area,
)
from daemon.workers import live_front
from drivers.formats.area import SurveyArea, parse_area, read_area
from drivers.formats.tilespill import DiskSpill
from mapping.streaming import PoseUpdate, StreamingEngine, TileUpdate

# The daemon's lines keep the logger they always had ("service:" in the journal).
log = logging.getLogger("daemon.service")


@dataclass
class OpenSurvey:
    """The open survey, as the other parts read it (``Surveys`` alone writes it)."""

    survey: SurveyState | None = None
    """The open survey's state; None between surveys."""
    folder: Path | None = None
    """The folder of the survey opened last (kept after it closes)."""
    coverage: LiveCoverage | None = None
    """The open survey's live coverage (kept until its last publication at the end)."""


class SurveySink(Protocol):
    """Where an open survey's live output goes (``daemon.publishing.Publishing``)."""

    def on_pose(self, update: PoseUpdate) -> None: ...

    def on_tile(self, survey: str, update: TileUpdate) -> None: ...

    def survey_opened(self) -> None: ...

    async def publish_coverage(self, survey_id: str, coverage: LiveCoverage) -> None: ...


class Surveys:
    """Opens and closes surveys (see the module docstring); one at a time."""

    def __init__(
        self,
        config: SiteConfig,
        state_dir: Path,
        parts: LiveParts,
        open_survey: OpenSurvey,
        sink: SurveySink,
        on_change: Callable[[], None],
    ) -> None:
        self.config = config
        self.state_dir = state_dir
        self.parts = parts
        self.open_survey = open_survey
        self.sink = sink
        self.on_change = on_change
        """Called when a survey opens or closes (the sonar's standby follows it)."""
        self.mission_area: SurveyArea | None = None
        """``[mission] area``, read at start-up (``read_mission_area``)."""

    def read_mission_area(self) -> None:
        """Read ``[mission] area``, if set: a bad area file is a start-up error, said in a
        line (SeamapError)."""
        if self.config.mission.area:
            self.mission_area = read_area(Path(self.config.mission.area))

    def start(self, reason: str = "command", area: dict[str, Any] | None = None) -> str:
        """Open a new survey (or return the one already open): its id. ``area``: the
        GeoJSON geometry (WGS84) it is to cover (else ``[mission] area``, if set); a survey
        already open without an area takes it. SeamapError (one line) for a bad area."""
        given = parse_area(json.dumps(area), "area") if area is not None else None
        if self.open_survey.survey is not None:
            self.adopt_area(given)
            return self.open_survey.survey.id
        survey_id = new_survey_id(self.state_dir)
        state = SurveyState(survey_id, self.config.daemon.vehicle, started=time.time())
        state.reason = reason
        survey_dir = surveys_dir(self.state_dir) / survey_id
        survey_dir.mkdir(parents=True)
        chosen = given if given is not None else self.mission_area
        if chosen is not None:
            keep_area(survey_dir, chosen)
        self.open(state, resumed=False)
        return survey_id

    def adopt_area(self, area: SurveyArea | None) -> None:
        """The open survey takes ``area`` if it has none yet."""
        folder, coverage = self.open_survey.folder, self.open_survey.coverage
        if area is None or folder is None or coverage is None or (folder / AREA_FILE).exists():
            return
        keep_area(folder, area)
        coverage.area = area

    def open(self, state: SurveyState, *, resumed: bool) -> None:
        """Open ``state``'s survey for recording and live mapping (a new segment)."""
        survey_dir = surveys_dir(self.state_dir) / state.id
        live_tiles = survey_dir / LIVE_TILES
        shutil.rmtree(live_tiles, ignore_errors=True)  # a crashed run's live map is stale
        recorder = SurveyRecorder(
            survey_dir,
            min_free_bytes=int(self.config.daemon.min_free_mb * 2**20),
            fsync_in_background=True,
        )
        state.segments = max(state.segments + 1, recorder.stats.segments)
        save_state(survey_dir, state)
        params = streaming_params(
            pipeline_params(self.config), self.config.live, self.config.daemon.tile_memory_mb
        )
        mount = mount_from_config(self.config.sonar)
        workers = self.config.daemon.workers
        coverage = LiveCoverage(mount, self.config.coverage, survey_area(survey_dir))
        sink = self.sink
        mapper = MappingWorker(
            lambda: StreamingEngine(
                mount,
                params,
                spill=DiskSpill(live_tiles),
                front=live_front(mount, params, workers, log=log.error),
            ),
            loop=asyncio.get_running_loop(),
            max_backlog_frames=self.config.daemon.max_backlog_frames,
            on_pose=sink.on_pose,
            on_tile=lambda update: sink.on_tile(state.id, update),
            segment=recorder.stats.segment,
            on_final=coverage.add,
        )
        self.open_survey.coverage = coverage
        self.open_survey.survey, self.open_survey.folder = state, survey_dir
        self.parts.recorder, self.parts.mapper, self.parts.survey = recorder, mapper, state.id
        sink.survey_opened()
        self.on_change()
        log.info(
            "survey resumed" if resumed else "survey started",
            extra={
                "fields": {
                    "survey": state.id,
                    "segment": recorder.stats.segment,
                    "folder": str(survey_dir),
                }
            },
        )
        if recorder.stats.stopped:
            log.error(
                "survey is not being recorded",
                extra={"fields": {"survey": state.id, "reason": recorder.stats.stop_reason}},
            )

    async def close(self, reason: str = "command") -> SurveyState | None:
        """Close the open survey, left ``finishing`` for its survey-end pass: its state
        (None when no survey was open)."""
        live = self.open_survey
        state, recorder, mapper = live.survey, self.parts.recorder, self.parts.mapper
        if state is None:
            return None
        # This survey's folder and coverage are taken before the mapping thread's finish is
        # awaited: a start request answered meanwhile opens the next survey in their place.
        # (The thread adds its last frames to the coverage it was given, held here.)
        folder, coverage = live.folder, live.coverage
        assert folder is not None
        live.survey, live.coverage = None, None
        self.parts.recorder = self.parts.mapper = None
        self.parts.survey = None
        self.on_change()
        if recorder is not None:
            recorder.close()
        stats = await mapper.finish() if mapper is not None else None
        if coverage is not None:  # every frame is final now: the live map's last word
            await self.sink.publish_coverage(state.id, coverage)
        state.state, state.ended, state.reason = "finishing", time.time(), reason
        if mapper is not None and recorder is not None:
            state.live[str(recorder.stats.segment)] = save_live(mapper, folder)
        save_state(folder, state)
        log.info(
            "survey ended",
            extra={
                "fields": {
                    "survey": state.id,
                    "reason": reason,
                    "live_mapped": stats.frames_mapped if stats else None,
                    "recorded_pings": recorder.stats.sonar.items if recorder else None,
                }
            },
        )
        return state
