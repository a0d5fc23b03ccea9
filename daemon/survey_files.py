"""The files the daemon keeps in a survey folder beside the recordings.

``survey.json`` (``save_state``: ``daemon.survey.write_state``, its failure one logged
line), the survey's area (``AREA_FILE``: ``keep_area``, read back by ``survey_area``), the
live map's counters and trajectory at the end of each recording run (``save_live``:
``live-trajectory-NNN.csv``) and the live map's idle tiles (``LIVE_TILES``, removed at the
end). Opening and closing surveys (``daemon.surveys``), the survey-end pass
(``daemon.final_pass``) and the start-up recovery (``daemon.state_dir``) all write them:
here each is written one way, and none of them crashes the daemon on a full disk.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from daemon.mapper import MappingWorker
from daemon.survey import SurveyState, write_state
from drivers.errors import SeamapError
from drivers.formats.area import SurveyArea, area_geojson, read_area
from drivers.formats.results import write_trajectory

# The daemon's lines keep the logger they always had ("service:" in the journal).
log = logging.getLogger("daemon.service")

LIVE_TILES = "live-tiles"
"""Folder (in the survey folder) where the live map's idle tiles wait; removed at the end."""
AREA_FILE = "area.geojson"
"""The survey's area (in the survey folder), as the start request or the config gave it."""


def save_state(survey_dir: Path, state: SurveyState) -> bool:
    """Write ``survey.json`` (``daemon.survey.write_state``: the folder's reserve is
    given up for it on a full disk); a failure is one logged line, never a crash."""
    try:
        write_state(survey_dir, state)
    except OSError as exc:
        log.error(
            "cannot write the survey state",
            extra={
                "fields": {
                    "survey": state.id,
                    "state": state.state,
                    "reason": exc.strerror or str(exc),
                }
            },
        )
        return False
    return True


def keep_area(survey_dir: Path, area: SurveyArea) -> None:
    """Write the survey's area into its folder (a failure is logged: the survey
    records without it)."""
    feature = {"type": "Feature", "properties": {}, "geometry": area_geojson(area)}
    try:
        tmp = survey_dir / f".{AREA_FILE}.tmp"
        tmp.write_text(json.dumps(feature) + "\n", encoding="utf-8")
        tmp.replace(survey_dir / AREA_FILE)
    except OSError as exc:
        log.error("cannot keep the survey's area", extra={"fields": {"reason": str(exc)}})


def survey_area(survey_dir: Path) -> SurveyArea | None:
    """The area kept in a survey folder, if any (an unreadable one is logged)."""
    path = survey_dir / AREA_FILE
    if not path.exists():
        return None
    try:
        return read_area(path)
    except SeamapError as exc:
        log.error("survey area unreadable", extra={"fields": {"reason": str(exc)}})
        return None


def save_live(mapper: MappingWorker, survey_dir: Path) -> dict[str, Any]:
    """The live map's counters, and its poses as ``live-trajectory-NNN.csv`` (the
    trajectory.csv format): what the boat computed as it went, for comparison with
    the survey-end pass."""
    engine, stats = mapper.engine, mapper.engine_stats
    live: dict[str, Any] = {
        "frames_received": mapper.stats.frames_submitted,
        "frames_mapped": stats.frames_mapped,
        "frames_rejected": stats.frames_rejected,
        "frames_skipped": mapper.stats.frames_skipped + stats.frames_skipped,
        "rejected": dict(stats.rejected),
        "windows_solved": stats.windows_solved,
        "frames_reblended": stats.frames_reblended,
        "resolves": stats.resolves,
        "frames_redrawn": stats.frames_redrawn,
        "redraw_wait_mean_s": round(stats.redraw_wait_mean_s, 1),
        "redraw_wait_max_s": round(stats.redraw_wait_max_s, 1),
        "engine_restarts": mapper.stats.restarts,
        "ms_per_frame": {
            k: round(1000 * v / max(stats.frames_received, 1), 2) for k, v in stats.stage_s.items()
        },
    }
    if engine.frame is not None and engine.poses:
        segment = mapper.segment
        name = f"live-trajectory-{segment:03d}.csv"
        try:
            write_trajectory(
                survey_dir / name, engine.frame, np.array(engine.times), np.array(engine.poses)
            )
            live["trajectory"] = name
        except OSError as exc:
            log.warning("cannot write the live trajectory", extra={"fields": {"reason": exc}})
    return live
