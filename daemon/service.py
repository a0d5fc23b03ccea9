"""The boat daemon (``seamap run``): record first, map live, end each survey with its result.

One asyncio loop; one supervised task per concern (``daemon.supervisor``):

- **sonar**: ``OculusLink`` keeps the sonar pinging; every message it receives goes to the
  recorder before anything parses it; pings go to the mapper.
- **mavlink**: ``MavlinkLink`` talks to the autopilot; every packet goes to the recorder,
  typed samples to the mapper.
- **recording**: flushes the recorder on a timer, so a pause in the data is still on disk
  within a second.
- **health**: a snapshot a second (``daemon.health``), a log line every
  ``health_interval_s``; **watchdog**: pets systemd while the loop, the recorder and the
  mapping thread are alive; **control**: the local control socket (``daemon.control``).
- **coverage**: every ``COVERAGE_EVERY_S`` the open survey's live coverage
  (``daemon.live_coverage.LiveCoverage``: each frame counted where the live map placed it)
  becomes the status's ``coverage`` and a zenoh publication; with the survey's area, its
  covered fraction and gaps. The area comes with the start request (``seamap survey
  start`` sends its plan's, ``seamap ctl start --area``), else from ``[mission] area``,
  and is kept in the survey folder (``area.geojson``) for the survey-end pass, which
  writes the result folder's gaps from it, publishes the final coverage and, with
  ``[mission] replan_at_end``, plans lanes over the gaps (``replan.plan``).

The mapping engine runs on its own thread (``daemon.mapper``). A survey is a folder
``state_dir/surveys/{id}/`` with ``survey.json`` (``daemon.survey``), the recorder's
segments, and at the end the contract's result folder, written by the survey-end pass:
the recorded segments replayed through the single-stage pipeline (``daemon.replay``),
exactly what ``seamap replay --survey`` computes. The pass runs off the loop, after the
survey is closed, while the daemon carries on (a new survey may already record).

SIGTERM or SIGINT ends the current survey (its pass runs to the end, with systemd's stop
timeout extended while it progresses) and the daemon exits 0; a second signal abandons
the pass, which then runs again at the next start. After a crash or ``kill -9`` the next
start resumes the survey that was recording in a new segment, and reruns passes that
were cut short.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import shutil
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from daemon.config import SiteConfig
from daemon.live_coverage import CoverageMessage, LiveCoverage, final_message
from daemon.health import HealthMonitor, LiveParts
from daemon.mapper import MappingWorker
from daemon.memory import return_large_blocks
from daemon.notify import Notifier
from daemon.publisher import ZenohPublisher
from daemon.recording import SurveyRecorder
from daemon.replay import mount_from_config, pipeline_params
from daemon.supervisor import Supervisor
from daemon.survey import (
    SurveyState,
    disk_full,
    new_survey_id,
    surveys_dir,
    unfinished,
    write_state,
)
from drivers.errors import SeamapError
from drivers.formats.area import SurveyArea, area_geojson, parse_area, read_area
from drivers.formats.results import write_trajectory
from drivers.formats.tilespill import DiskSpill
from drivers.mavlink.link import MavlinkLink
from drivers.oculus.link import OculusLink
from drivers.zenoh_io import insecure_listen, open_session, session_config
from mapping import kernels
from mapping.coverage import SonarFan
from mapping.samples import GnssFix, NavSample, Ping
from mapping.streaming import PoseUpdate, StreamingEngine, StreamingParams, TileUpdate

log = logging.getLogger(__name__)

RECORDER_POLL_S = 0.25
DEFERRED_PASS_CHECK_S = 10.0
"""How often a survey-end pass deferred by a full disk looks for space again."""
MAX_PASSES_CUT = 2
"""Survey-end passes a survey may lose to the daemon's death before it is given up on (the
first could be an unrelated crash; a second, the pass itself)."""
LIVE_TILES = "live-tiles"
"""Folder (in the survey folder) where the live map's idle tiles wait; removed at the end."""
AREA_FILE = "area.geojson"
"""The survey's area (in the survey folder), as the start request or the config gave it."""
REPLAN_FILE = "replan.plan"
"""The gaps' lanes ``[mission] replan_at_end`` writes into the survey folder (with
replan.waypoints, replan.geojson and replan.png)."""
COVERAGE_EVERY_S = 5.0
"""Seconds between live coverage publications: a boat at 0.5 m/s moves 2.5 m, about the
fan's depth; the gaps of a hectare take tens of milliseconds to compute."""


class Daemon:
    """See the module docstring. ``run()`` until a signal or ``shutdown()``; returns 0."""

    def __init__(self, config: SiteConfig, notifier: Notifier | None = None) -> None:
        self.config = config
        self.state_dir = Path(config.daemon.state_dir)
        self.notifier = notifier if notifier is not None else Notifier()
        self.health = HealthMonitor(config.daemon.vehicle, self.state_dir)
        self.parts = LiveParts()
        self.supervisor = Supervisor()
        self.parts.task_restarts = self.supervisor.restarts
        self.survey: SurveyState | None = None
        self.latest_pose: PoseUpdate | None = None
        self.tiles_published = 0
        self._survey_dir: Path | None = None
        self._passes: dict[str, asyncio.Task[None]] = {}
        self._running_passes: dict[str, SurveyState] = {}
        """Surveys whose survey-end pass is mapping now."""
        self._deferred: dict[str, SurveyState] = {}
        self._sonar_resting: bool | None = None
        """Surveys whose survey-end pass waits for disk space."""
        self._pass_progress: dict[str, str] = {}
        self.publisher: ZenohPublisher | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._mission_area: SurveyArea | None = None
        """``[mission] area``, read at start-up."""
        self.coverage: LiveCoverage | None = None
        """The open survey's live coverage."""
        self._coverage_status: dict[str, Any] | None = None
        """The status's ``coverage``: the open survey's latest, else the last survey's
        (final once its survey-end pass wrote the result folder)."""
        self._shutdown = asyncio.Event()
        self._last_recorder_poll = time.monotonic()
        self._signals = 0

    # --- lifecycle ---------------------------------------------------------------------------

    async def run(self) -> int:
        session_config(self.config.zenoh)  # a malformed [zenoh] is a start-up error
        exposed = insecure_listen(self.config.zenoh.listen)
        if exposed and not self.config.zenoh.allow_insecure:
            raise SeamapError(
                f"config: [zenoh] listen {exposed[0]!r} is plain, unauthenticated and open to "
                "the network (anyone reaching it could stop surveys and publish as the boat): "
                "run `seamap security init` and use its [zenoh] lines, listen on 127.0.0.1, "
                "or set [zenoh] allow_insecure = true"
            )
        self._prepare_state_dir()
        if self.config.mission.area:  # a bad area file is a start-up error, said in a line
            self._mission_area = read_area(Path(self.config.mission.area))
        return_large_blocks()  # tiles' stacks go back to the system when freed
        kernels.warm()  # the tiles' compiled loops, before the first ping needs them
        loop = self._loop = asyncio.get_running_loop()
        self.publisher = ZenohPublisher(
            self.config.daemon.vehicle, surveys_dir(self.state_dir), loop, self._control
        )
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self._on_signal, sig)
        for name, task in (
            ("sonar", self._sonar_task),
            ("mavlink", self._mavlink_task),
            ("recording", self._recording_task),
            ("health", self._health_task),
            ("watchdog", self._watchdog_task),
            ("control", self._control_task),
            ("zenoh", self._zenoh_task),
            ("deferred passes", self._deferred_task),
            ("coverage", self._coverage_task),
        ):
            self.supervisor.spawn(name, task)
        self._recover()
        if self.survey is None and self.config.daemon.survey_autostart:
            await self.start_survey("autostart")
        self.notifier.ready(self._status_text())
        log.info(
            "daemon ready",
            extra={
                "fields": {
                    "vehicle": self.config.daemon.vehicle,
                    "state_dir": str(self.state_dir),
                    "survey": self.survey.id if self.survey else None,
                }
            },
        )
        await self._shutdown.wait()
        self.notifier.stopping("ending the survey")
        log.info("shutting down", extra={"fields": {"survey": self._survey_id()}})
        await self.stop_survey("shutdown", wait=False)
        # Nothing records any more: let the sonar go quiet and the autopilot link close
        # while the survey-end pass runs (health, watchdog and control stay up).
        await self.supervisor.cancel("sonar", "mavlink")
        while self._passes:
            await asyncio.gather(*self._passes.values(), return_exceptions=True)
        await self.supervisor.stop()
        self.publisher.close()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)
        self.notifier.close()
        log.info("stopped")
        return 0

    def shutdown(self) -> None:
        """Ask ``run()`` to end the survey and return (as SIGTERM does)."""
        self._shutdown.set()

    def _on_signal(self, sig: signal.Signals) -> None:
        self._signals += 1
        if self._signals == 1:
            log.info("signal received", extra={"fields": {"signal": sig.name}})
            self._shutdown.set()
            return
        # A second signal: leave now. Recordings are closed; cut passes rerun at next start
        # (cut on purpose: not counted against them).
        log.warning(
            "second signal: leaving without waiting for the survey-end pass",
            extra={"fields": {"signal": sig.name, "pending": ",".join(self._passes) or None}},
        )
        for state in list(self._running_passes.values()):
            state.passes_cut -= 1
            self._save_state(surveys_dir(self.state_dir) / state.id, state)
        logging.shutdown()
        os._exit(0)

    def _prepare_state_dir(self) -> None:
        tmp = self.state_dir / "tmp"
        try:
            surveys_dir(self.state_dir).mkdir(parents=True, exist_ok=True)
            tmp.mkdir(exist_ok=True)
        except OSError as exc:
            raise SeamapError(
                f"{self.state_dir}: cannot create the state folder ({exc.strerror or exc})"
            ) from None
        if not os.access(self.state_dir, os.W_OK):
            raise SeamapError(f"{self.state_dir}: the state folder is not writable")
        # Scratch files of the survey-end pass (spilled tiles) go to the state disk, not
        # to a small /tmp.
        for stale in tmp.iterdir():
            shutil.rmtree(stale, ignore_errors=True)
        tempfile.tempdir = str(tmp)

    def _recover(self) -> None:
        """Resume the survey a crash interrupted; rerun survey-end passes that were cut,
        unless crashes cut them ``MAX_PASSES_CUT`` times: the survey then fails, said
        in one line, so that a pass that kills the daemon (out of memory) is not rerun at
        every start, cutting each new survey in turn."""
        left = unfinished(self.state_dir)
        recording = [s for s in left if s.state == "recording"]
        for state in left:
            if recording and state is recording[-1]:
                continue
            folder = surveys_dir(self.state_dir) / state.id
            if state.state == "recording":
                state.state, state.ended = "finishing", time.time()
                state.reason = state.reason or "interrupted"
                self._save_state(folder, state)
            if state.passes_cut >= MAX_PASSES_CUT:
                state.state = "failed"
                state.reason = (
                    f"the survey-end pass was cut {state.passes_cut} times by the daemon "
                    "stopping while it ran (out of memory?); not run again here. The "
                    f"recordings are intact: `seamap replay --survey {folder}` maps them"
                )
                log.error(
                    "survey-end pass given up",
                    extra={"fields": {"survey": state.id, "reason": state.reason}},
                )
                self._save_state(folder, state)
                continue
            log.info(
                "rerunning an interrupted survey-end pass", extra={"fields": {"survey": state.id}}
            )
            self._start_pass(state)
        if recording:
            self._open(recording[-1], resumed=True)

    # --- surveys -----------------------------------------------------------------------------

    async def start_survey(
        self, reason: str = "command", area: dict[str, Any] | None = None
    ) -> str:
        """Open a new survey (or return the one already open): its id. ``area``: the
        GeoJSON geometry (WGS84) it is to cover (else ``[mission] area``, if set); a survey
        already open without an area takes it. SeamapError (one line) for a bad area."""
        given = parse_area(json.dumps(area), "area") if area is not None else None
        if self.survey is not None:
            self._adopt_area(given)
            return self.survey.id
        survey_id = new_survey_id(self.state_dir)
        state = SurveyState(survey_id, self.config.daemon.vehicle, started=time.time())
        state.reason = reason
        survey_dir = surveys_dir(self.state_dir) / survey_id
        survey_dir.mkdir(parents=True)
        chosen = given if given is not None else self._mission_area
        if chosen is not None:
            self._keep_area(survey_dir, chosen)
        self._open(state, resumed=False)
        return survey_id

    def _adopt_area(self, area: SurveyArea | None) -> None:
        """The open survey takes ``area`` if it has none yet."""
        folder, coverage = self._survey_dir, self.coverage
        if area is None or folder is None or coverage is None or (folder / AREA_FILE).exists():
            return
        self._keep_area(folder, area)
        coverage.area = area

    @staticmethod
    def _keep_area(survey_dir: Path, area: SurveyArea) -> None:
        """Write the survey's area into its folder (a failure is logged: the survey
        records without it)."""
        feature = {"type": "Feature", "properties": {}, "geometry": area_geojson(area)}
        try:
            tmp = survey_dir / f".{AREA_FILE}.tmp"
            tmp.write_text(json.dumps(feature) + "\n", encoding="utf-8")
            tmp.replace(survey_dir / AREA_FILE)
        except OSError as exc:
            log.error("cannot keep the survey's area", extra={"fields": {"reason": str(exc)}})

    @staticmethod
    def _survey_area(survey_dir: Path) -> SurveyArea | None:
        """The area kept in a survey folder, if any (an unreadable one is logged)."""
        path = survey_dir / AREA_FILE
        if not path.exists():
            return None
        try:
            return read_area(path)
        except SeamapError as exc:
            log.error("survey area unreadable", extra={"fields": {"reason": str(exc)}})
            return None

    def _open(self, state: SurveyState, *, resumed: bool) -> None:
        survey_dir = surveys_dir(self.state_dir) / state.id
        live_tiles = survey_dir / LIVE_TILES
        shutil.rmtree(live_tiles, ignore_errors=True)  # a crashed run's live map is stale
        recorder = SurveyRecorder(
            survey_dir,
            min_free_bytes=int(self.config.daemon.min_free_mb * 2**20),
            fsync_in_background=True,
        )
        state.segments = max(state.segments + 1, recorder.stats.segments)
        self._save_state(survey_dir, state)
        params = StreamingParams(
            pipeline=pipeline_params(self.config),
            tile_memory_mb=self.config.daemon.tile_memory_mb,
        )
        mount = mount_from_config(self.config.sonar)
        coverage = LiveCoverage(mount, self.config.coverage, self._survey_area(survey_dir))
        mapper = MappingWorker(
            lambda: StreamingEngine(mount, params, spill=DiskSpill(live_tiles)),
            loop=asyncio.get_running_loop(),
            max_backlog_frames=self.config.daemon.max_backlog_frames,
            on_pose=self._on_pose,
            on_tile=lambda update: self._on_tile(state.id, update),
            segment=recorder.stats.segment,
            on_final=coverage.add,
        )
        self.coverage, self._coverage_status = coverage, None
        self.survey, self._survey_dir = state, survey_dir
        self.parts.recorder, self.parts.mapper, self.parts.survey = recorder, mapper, state.id
        self._sonar_follows_survey()
        self.latest_pose, self.tiles_published = None, 0
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

    async def stop_survey(self, reason: str = "command", *, wait: bool = True) -> str | None:
        """Close the open survey and run its survey-end pass (awaited when ``wait``)."""
        state, recorder, mapper = self.survey, self.parts.recorder, self.parts.mapper
        if state is None:
            return None
        self.survey = None
        self.parts.recorder = self.parts.mapper = None
        self.parts.survey = None
        self._sonar_follows_survey()
        if recorder is not None:
            recorder.close()
        stats = await mapper.finish() if mapper is not None else None
        coverage, self.coverage = self.coverage, None
        if coverage is not None:  # every frame is final now: the live map's last word
            await self._publish_coverage(state.id, coverage)
        state.state, state.ended, state.reason = "finishing", time.time(), reason
        assert self._survey_dir is not None
        if mapper is not None and recorder is not None:
            state.live[str(recorder.stats.segment)] = self._save_live(mapper, self._survey_dir)
        self._save_state(self._survey_dir, state)
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
        task = self._start_pass(state)
        if wait:
            await asyncio.gather(task, return_exceptions=True)
        return state.id

    @staticmethod
    def _save_live(mapper: MappingWorker, survey_dir: Path) -> dict[str, Any]:
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
                k: round(1000 * v / max(stats.frames_received, 1), 2)
                for k, v in stats.stage_s.items()
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

    @staticmethod
    def _save_state(survey_dir: Path, state: SurveyState) -> bool:
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

    def _room_for_pass(self) -> tuple[bool, float]:
        """Whether the state disk has ``min_free_mb`` free for a survey-end pass, and how
        many MiB it has."""
        try:
            free = shutil.disk_usage(self.state_dir).free / 2**20
        except OSError:
            return True, math.nan
        return free >= self.config.daemon.min_free_mb, free

    def _defer_pass(self, state: SurveyState, why: str) -> None:
        """Leave the survey ``finishing`` with the reason: the pass runs when space returns
        (checked every ``DEFERRED_PASS_CHECK_S`` while the daemon runs, and at start-up)."""
        state.state, state.reason = "finishing", why
        self._deferred[state.id] = state
        log.warning(
            "survey-end pass deferred", extra={"fields": {"survey": state.id, "reason": why}}
        )

    async def _deferred_task(self) -> None:
        """Start deferred survey-end passes once the disk has room again."""
        while True:
            await asyncio.sleep(DEFERRED_PASS_CHECK_S)
            if not self._deferred or self._shutdown.is_set() or not self._room_for_pass()[0]:
                continue
            for survey_id, state in list(self._deferred.items()):
                del self._deferred[survey_id]
                log.info("disk space is back: running the deferred survey-end pass",
                         extra={"fields": {"survey": survey_id}})  # fmt: skip
                self._start_pass(state)

    def _sonar_rests(self) -> bool:
        """Whether the sonar should stand by now: no survey open and the config says so."""
        return self.survey is None and self.config.sonar.standby_outside_surveys

    def _sonar_follows_survey(self) -> None:
        """Stand the sonar by or fire it, as the survey's state asks (said once a change)."""
        link = self.parts.sonar
        rest = self._sonar_rests()
        if link is None or self._sonar_resting == rest:
            return
        self._sonar_resting = rest
        link.set_standby(rest)
        log.info(
            "sonar standing by: no survey open" if rest else "sonar firing: survey open",
            extra={"fields": {"survey": self.survey.id if self.survey else None}},
        )

    def _start_pass(self, state: SurveyState) -> asyncio.Task[None]:
        task = asyncio.create_task(self._final_pass(state), name=f"final-pass-{state.id}")
        self._passes[state.id] = task
        task.add_done_callback(lambda _: self._passes.pop(state.id, None))
        return task

    async def _final_pass(self, state: SurveyState) -> None:
        survey_dir = surveys_dir(self.state_dir) / state.id
        self._pass_progress[state.id] = "starting"
        self.parts.final_passes = self._pass_progress
        if not self.config.daemon.final_pass:
            state.state, state.result = "done", {"final_pass": False}
            self._save_state(survey_dir, state)
            self._pass_progress.pop(state.id, None)
            return
        # The live map's idle tiles are no use once the survey ended: their room first.
        shutil.rmtree(survey_dir / LIVE_TILES, ignore_errors=True)
        room, free = self._room_for_pass()
        if not room:
            self._defer_pass(
                state,
                f"survey-end pass deferred: {free:.0f} MiB free on {self.state_dir}, less "
                f"than [daemon] min_free_mb ({self.config.daemon.min_free_mb:g}); it runs "
                "when space returns (recordings intact)",
            )
            self._pass_progress.pop(state.id, None)
            self._save_state(survey_dir, state)
            return
        started = time.monotonic()
        state.passes_cut += 1  # until it ends here: a crash leaves it counted
        self._save_state(survey_dir, state)
        self._running_passes[state.id] = state
        keepalive = asyncio.create_task(self._extend_stop_timeout(state.id))
        try:
            report = await asyncio.to_thread(self._replay, survey_dir, state.id)
        except Exception as exc:
            if disk_full(exc) or not self._room_for_pass()[0]:
                # The disk filled while the pass wrote: not the survey's fault.
                self._defer_pass(
                    state,
                    f"survey-end pass deferred: the disk of {self.state_dir} filled while "
                    "it ran; it runs again when space returns (recordings intact)",
                )
            else:
                reason = (
                    str(exc) if isinstance(exc, SeamapError) else f"{type(exc).__name__}: {exc}"
                )
                state.state, state.reason = "failed", reason
                log.error(
                    "survey-end pass failed",
                    extra={"fields": {"survey": state.id, "reason": reason}},
                )
                if not isinstance(exc, SeamapError):
                    log.debug("survey-end pass failure", exc_info=True)
        else:
            frames = report["frames"]
            state.state = "done"
            state.result = {
                "frames_read": frames["read"],
                "frames_mapped": frames["mapped"],
                "rejected": frames["rejected"],
                "seconds": round(time.monotonic() - started, 1),
                "files": report["files"],
            }
            if "replan" in report:
                state.result["replan"] = report["replan"]
            log.info(
                "survey mapped",
                extra={
                    "fields": {
                        "survey": state.id,
                        "frames": frames["read"],
                        "mapped": frames["mapped"],
                        "seconds": state.result["seconds"],
                        "result": str(survey_dir),
                    }
                },
            )
        finally:
            keepalive.cancel()
            self._pass_progress.pop(state.id, None)
            self._running_passes.pop(state.id, None)
            state.passes_cut -= 1
        shutil.rmtree(survey_dir / LIVE_TILES, ignore_errors=True)
        self._save_state(survey_dir, state)

    def _replay(self, survey_dir: Path, survey_id: str) -> dict[str, Any]:
        from daemon.replay import replay_survey

        def progress(stage: str, done: int, total: int) -> None:
            self._pass_progress[survey_id] = f"{stage} {done}/{total}"

        area = survey_dir / AREA_FILE
        report = replay_survey(
            survey_dir, self.config, survey_dir, progress=progress,
            area=area if area.exists() else None,
        )  # fmt: skip
        final = final_message(survey_dir, survey_id, int(time.time() * 1000))
        if final is not None:
            self._loop_call(self._final_coverage, survey_id, final)
        if self.publisher is not None:
            self._pass_progress[survey_id] = "publishing tiles"
            report["tiles_published"] = self.publisher.final_tiles(survey_id, survey_dir)
            self.publisher.survey_ended(survey_id)
            if final is not None:
                self.publisher.coverage(survey_id, final)
        if self.config.mission.replan_at_end and area.exists():
            self._pass_progress[survey_id] = "planning the gaps"
            report["replan"] = self._replan(survey_dir, area)
        return report

    def _replan(self, survey_dir: Path, area: Path) -> dict[str, Any]:
        """Plan lanes over the survey's gaps into the survey folder (``REPLAN_FILE``), from
        where the boat ended, for the autopilot that was heard; what came of it (a
        failure is said in the summary and the log, never fails the pass)."""
        from daemon.replan_files import replan_survey

        link = self.parts.mavlink
        firmware = "px4" if link is not None and link.stats.autopilot == "px4" else "ardupilot"
        try:
            summary = replan_survey(
                area, survey_dir / REPLAN_FILE, self.config, survey=survey_dir, firmware=firmware
            )
        except SeamapError as exc:
            log.warning("gaps not planned", extra={"fields": {"reason": str(exc)}})
            return {"error": str(exc)}
        if not summary["gaps"]:
            for stale in survey_dir.glob("replan.*"):  # an earlier run's plan is not this one's
                stale.unlink(missing_ok=True)
            log.info("no gap to plan: the survey covered its area")
            return {"gaps": 0, "files": []}
        files = [Path(f).name for f in summary["files"]]
        log.info(
            "gaps planned (start it with `seamap survey start`)",
            extra={"fields": {"gaps": summary["gaps"], "gaps_m2": summary["gaps_m2"],
                              "lanes": summary["lanes"], "plan": str(survey_dir / REPLAN_FILE),
                              "covers": summary["coverage"]}},
        )  # fmt: skip
        return {
            "gaps": summary["gaps"],
            "gaps_m2": summary["gaps_m2"],
            "lanes": summary["lanes"],
            "distance_m": summary["distance_m"],
            "duration_s": summary["duration_s"],
            "coverage": summary["coverage"],
            "unreachable": summary["unreachable"],
            "files": files,
        }

    def _loop_call(self, callback: Any, *args: Any) -> None:
        """Run ``callback(*args)`` on the event loop (from the survey-end pass's thread)."""
        if self._loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed
                self._loop.call_soon_threadsafe(callback, *args)

    def _final_coverage(self, survey_id: str, message: CoverageMessage) -> None:
        """A survey's final coverage becomes the status's, unless another survey is open."""
        if self.survey is None:
            self._coverage_status = message.status()

    async def _extend_stop_timeout(self, survey_id: str) -> None:
        """While a pass runs during shutdown, keep systemd's stop timeout ahead of it."""
        while True:
            if self._shutdown.is_set():
                self.notifier.extend_timeout(60.0)
                self.notifier.status(
                    f"survey-end pass {survey_id}: {self._pass_progress.get(survey_id)}"
                )
            await asyncio.sleep(10.0)

    # --- sensors -----------------------------------------------------------------------------

    async def _sonar_task(self) -> None:
        link = OculusLink.from_config(self.config.sonar, on_message=self._on_sonar_message)
        self.parts.sonar = link
        self._sonar_resting = None  # a new link: say what it is asked for
        self._sonar_follows_survey()
        async with contextlib.aclosing(link.pings()) as pings:
            async for ping in pings:
                self._on_ping(ping)

    def _on_sonar_message(self, message: bytes, received: float) -> None:
        recorder = self.parts.recorder
        if recorder is not None:
            recorder.record_sonar(message, received)

    def _on_ping(self, ping: Ping) -> None:
        self.parts.last_ping = ping.time
        coverage = self.coverage
        if coverage is not None and coverage.fan is None:
            # The fan of the first ping, as the survey-end pass takes it.
            preprocess = pipeline_params(self.config).preprocess
            coverage.set_fan(SonarFan.of_ping(ping, coverage.mount, preprocess))
        mapper = self.parts.mapper
        if mapper is not None:
            mapper.submit(ping)

    async def _mavlink_task(self) -> None:
        m = self.config.mavlink
        link = MavlinkLink(
            m.url,
            baud=m.baud,
            heading_source=m.heading_source,
            imu_source=m.imu_source,
            declination_deg=m.declination_deg,
            on_packet=self._on_nav_packet,
            on_sample=self._on_nav_sample,
        )
        self.parts.mavlink = link
        try:
            await link.start()
            await asyncio.Event().wait()
        finally:
            await link.close()

    def _on_nav_packet(self, packet: bytes, received: float) -> None:
        recorder = self.parts.recorder
        if recorder is not None:
            recorder.record_mavlink(packet, received)

    def _on_nav_sample(self, sample: NavSample) -> None:
        if isinstance(sample, GnssFix) and sample.usable:
            self.parts.last_fix = sample.time
        mapper = self.parts.mapper
        if mapper is not None:
            mapper.submit(sample)

    # --- mapping output ----------------------------------------------------------------------

    def _on_pose(self, update: PoseUpdate) -> None:
        # Refinements of older frames update the map, not "where the boat is".
        if self.latest_pose is None or update.time >= self.latest_pose.time:
            self.latest_pose = update
            if self.publisher is not None:
                self.publisher.pose(update)

    def _on_tile(self, survey: str, update: TileUpdate) -> None:
        self.tiles_published += 1
        if self.publisher is not None:
            self.publisher.tile(survey, update)

    # --- housekeeping ------------------------------------------------------------------------

    async def _recording_task(self) -> None:
        while True:
            self._last_recorder_poll = time.monotonic()
            recorder = self.parts.recorder
            if recorder is not None:
                recorder.poll()
            await asyncio.sleep(RECORDER_POLL_S)

    async def _health_task(self) -> None:
        interval = self.config.daemon.health_interval_s
        next_line = time.monotonic() + min(interval, 5.0)
        while True:
            self.health.sample(self.parts)
            if self.publisher is not None:
                self.publisher.status(self.status())
            if time.monotonic() >= next_line:
                self.health.log_line()
                self.notifier.status(self._status_text())
                next_line += interval
            await asyncio.sleep(1.0)

    def _alive(self) -> bool:
        """What the systemd watchdog vouches for: the recorder is flushed on time and the
        mapping thread runs (the loop itself runs, or this is not called)."""
        if time.monotonic() - self._last_recorder_poll > 5.0:
            return False
        mapper = self.parts.mapper
        return mapper is None or mapper.alive

    async def _watchdog_task(self) -> None:
        interval = self.notifier.watchdog_interval_s
        if interval is None:
            await asyncio.Event().wait()
            return
        while True:
            if self._alive():
                self.notifier.watchdog()
            else:
                log.error("watchdog withheld: recorder or mapping stalled")
            await asyncio.sleep(interval / 2)

    async def _coverage_task(self) -> None:
        """The open survey's live coverage, every ``COVERAGE_EVERY_S`` while it grows."""
        counted = -1
        while True:
            await asyncio.sleep(COVERAGE_EVERY_S)
            coverage, state = self.coverage, self.survey
            if coverage is None or state is None or coverage.frames == counted:
                continue
            counted = coverage.frames
            await self._publish_coverage(state.id, coverage)

    async def _publish_coverage(self, survey_id: str, coverage: LiveCoverage) -> None:
        """Make the live coverage's publication (off the loop), show it in the status and
        hand it to zenoh; a failure is logged, never raised."""
        try:
            message = await asyncio.to_thread(coverage.message, survey_id)
        except Exception as exc:
            log.warning("live coverage failed", extra={"fields": {"reason": str(exc)}})
            log.debug("live coverage failure", exc_info=True)
            return
        if message is None:
            return
        if self.survey is None or self.survey.id == survey_id:
            self._coverage_status = message.status()
        if self.publisher is not None:
            self.publisher.coverage(survey_id, message)

    async def _zenoh_task(self) -> None:
        assert self.publisher is not None
        session = await asyncio.to_thread(open_session, self.config.zenoh)
        self.publisher.attach(session)
        z = self.config.zenoh
        log.info(
            "zenoh session open",
            extra={"fields": {"mode": z.mode, "listen": ",".join(z.listen) or None,
                              "connect": ",".join(z.connect) or None}},
        )  # fmt: skip
        try:
            await asyncio.Event().wait()
        finally:
            closing = self.publisher.detach()
            if closing is not None:
                await asyncio.to_thread(closing.close)

    async def _control(self, request: dict[str, Any]) -> dict[str, Any]:
        """A survey request from zenoh: ``{"action": "start"|"stop"|"status"}``."""
        action = request.get("action")
        if action == "start":
            area = request.get("area")
            if area is not None and not isinstance(area, dict):
                return {"ok": False, "error": "area must be a GeoJSON object"}
            try:
                return {"ok": True, "survey": await self.start_survey("zenoh", area)}
            except SeamapError as exc:
                return {"ok": False, "error": str(exc)}
        if action == "stop":
            return {"ok": True, "survey": await self.stop_survey("zenoh", wait=False)}
        if action == "status":
            return {"ok": True, "survey": self._survey_id(), "status": self.status()}
        return {"ok": False, "error": f"unknown action {action!r} (start, stop, status)"}

    async def _control_task(self) -> None:
        from daemon.control import serve_control

        await serve_control(self, self.state_dir / "control.sock")

    def status(self) -> dict[str, Any]:
        """The latest health snapshot plus the survey and the newest pose."""
        snapshot = dict(self.health.latest) or self.health.sample(self.parts)
        pose = self.latest_pose
        snapshot["pose"] = None if pose is None else {
            "time": pose.time,
            "lat": pose.lat,
            "lon": pose.lon,
            "east": pose.east,
            "north": pose.north,
            "heading_deg": pose.heading_deg,
            "epsg": pose.epsg,
        }  # fmt: skip
        snapshot["tiles_published"] = self.tiles_published
        snapshot["coverage"] = self._coverage_status
        return snapshot

    def _survey_id(self) -> str | None:
        return self.survey.id if self.survey is not None else None

    def _status_text(self) -> str:
        snap = self.health.latest
        survey = self._survey_id() or "no survey"
        if not snap:
            return survey
        text = f"{survey}: {snap['frames']['mapped']} frames mapped, lag {snap['lag_s']:.1f} s"
        coverage = self._coverage_status
        if self.survey is not None and coverage and coverage.get("area"):
            text += f", {100 * coverage['area']['fraction']:.1f} % of the area covered"
        return text
