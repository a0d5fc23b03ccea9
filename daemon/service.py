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

``Daemon`` is the composition of parts that each do one job; it wires them, owns the
supervised tasks and the lifecycle (start-up, signals, shutdown):

- ``daemon.state_dir``: the state folder made at start-up, and what a crash left in it;
- ``daemon.surveys.Surveys``: opening and closing surveys (recorder, mapping thread, live
  coverage, area), their state on disk through ``daemon.survey_files``;
- ``daemon.final_pass.FinalPasses``: the survey-end pass, its deferral on a full disk;
- ``daemon.feeds.Feeds``: the sonar and MAVLink feeds and the sonar's standby policy;
- ``daemon.publishing.Publishing``: the newest pose, the tiles, the coverage and the zenoh
  session that carries them;
- ``daemon.status.StatusReporter``: the status and the health task that says it;
- ``daemon.watchdog.Watchdog``: the recorder's flush timer and systemd's watchdog;
- ``daemon.zenoh_control``: survey requests over zenoh (``daemon.control``: the socket's).
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
from pathlib import Path
from typing import Any

from daemon.config import SiteConfig
from daemon.feeds import Feeds
from daemon.final_pass import FinalPasses
from daemon.health import HealthMonitor, LiveParts
from daemon.live_coverage import LiveCoverage
from daemon.memory import return_large_blocks
from daemon.notify import Notifier
from daemon.publisher import ZenohPublisher
from daemon.publishing import Publishing
from daemon.state_dir import prepare_state_dir, recover
from daemon.status import StatusReporter
from daemon.supervisor import Supervisor
from daemon.survey import SurveyState, surveys_dir
from daemon.surveys import OpenSurvey, Surveys
from daemon.watchdog import Watchdog
from daemon.zenoh_control import answer
from drivers.errors import SeamapError
from drivers.zenoh_io import insecure_listen, session_config
from mapping import kernels
from mapping.streaming import PoseUpdate

log = logging.getLogger(__name__)


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
        self._shutdown = asyncio.Event()
        self._signals = 0
        self.open_survey = OpenSurvey()
        """The open survey, as every part reads it (``surveys`` writes it)."""
        self.publishing = Publishing(config.zenoh, self.open_survey)
        self.feeds = Feeds(config, self.parts, self.open_survey)
        self.surveys = Surveys(
            config, self.state_dir, self.parts, self.open_survey,
            sink=self.publishing, on_change=self.feeds.follow_survey,
        )  # fmt: skip
        self.final_passes = FinalPasses(
            config, self.state_dir, self.parts, self.publishing, self.notifier, self._shutdown
        )
        self.reporter = StatusReporter(
            self.health, self.parts, self.open_survey, self.publishing, self.notifier,
            config.daemon.health_interval_s,
        )  # fmt: skip
        self.watchdog = Watchdog(self.parts, self.notifier)

    # --- what the parts hold (read here as before the parts were split out) -------------------

    @property
    def survey(self) -> SurveyState | None:
        """The open survey's state (None between surveys)."""
        return self.open_survey.survey

    @property
    def coverage(self) -> LiveCoverage | None:
        """The open survey's live coverage."""
        return self.open_survey.coverage

    @property
    def latest_pose(self) -> PoseUpdate | None:
        """Where the boat is: the open survey's newest live pose."""
        return self.publishing.latest_pose

    @property
    def tiles_published(self) -> int:
        """Live tiles of the open survey handed to zenoh."""
        return self.publishing.tiles_published

    @property
    def publisher(self) -> ZenohPublisher | None:
        """The zenoh side, once ``run()`` made it."""
        return self.publishing.publisher

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
        prepare_state_dir(self.state_dir)
        self.surveys.read_mission_area()  # a bad area file is a start-up error, said in a line
        return_large_blocks()  # tiles' stacks go back to the system when freed
        kernels.warm()  # the tiles' compiled loops, before the first ping needs them
        loop = asyncio.get_running_loop()
        publisher = self.publishing.publisher = ZenohPublisher(
            self.config.daemon.vehicle, surveys_dir(self.state_dir), loop, self._control
        )
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self._on_signal, sig)
        for name, task in (
            ("sonar", self.feeds.sonar_task),
            ("mavlink", self.feeds.mavlink_task),
            ("recording", self.watchdog.recording_task),
            ("health", self.reporter.task),
            ("watchdog", self.watchdog.task),
            ("control", self._control_task),
            ("zenoh", self.publishing.zenoh_task),
            ("deferred passes", self.final_passes.deferred_task),
            ("coverage", self.publishing.coverage_task),
        ):
            self.supervisor.spawn(name, task)
        self._recover()
        if self.survey is None and self.config.daemon.survey_autostart:
            await self.start_survey("autostart")
        self.notifier.ready(self.reporter.text())
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
        log.info("shutting down", extra={"fields": {"survey": self.reporter.survey_id()}})
        await self.stop_survey("shutdown", wait=False)
        # Nothing records any more: let the sonar go quiet and the autopilot link close
        # while the survey-end pass runs (health, watchdog and control stay up).
        await self.supervisor.cancel("sonar", "mavlink")
        await self.final_passes.wait()
        await self.supervisor.stop()
        publisher.close()
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
            extra={
                "fields": {"signal": sig.name, "pending": ",".join(self.final_passes.tasks) or None}
            },
        )
        self.final_passes.cut_on_purpose()
        logging.shutdown()
        os._exit(0)

    def _recover(self) -> None:
        """Resume the survey a crash interrupted; rerun survey-end passes that were cut
        (``daemon.state_dir.recover`` decides which, and gives up on the others)."""
        found = recover(self.state_dir)
        for state in found.rerun:
            self.final_passes.start(state)
        if found.resume is not None:
            self.surveys.open(found.resume, resumed=True)

    # --- surveys -----------------------------------------------------------------------------

    async def start_survey(
        self, reason: str = "command", area: dict[str, Any] | None = None
    ) -> str:
        """Open a new survey (or return the one already open): its id. ``area``: the
        GeoJSON geometry (WGS84) it is to cover (else ``[mission] area``, if set); a survey
        already open without an area takes it. SeamapError (one line) for a bad area."""
        return self.surveys.start(reason, area)

    async def stop_survey(self, reason: str = "command", *, wait: bool = True) -> str | None:
        """Close the open survey and run its survey-end pass (awaited when ``wait``)."""
        state = await self.surveys.close(reason)
        if state is None:
            return None
        task = self.final_passes.start(state)
        if wait:
            await asyncio.gather(task, return_exceptions=True)
        return state.id

    # --- control and status ------------------------------------------------------------------

    async def _control(self, request: dict[str, Any]) -> dict[str, Any]:
        """A survey request from zenoh: ``{"action": "start"|"stop"|"status"}``."""
        return await answer(self, request)

    async def _control_task(self) -> None:
        from daemon.control import serve_control

        await serve_control(self, self.state_dir / "control.sock")

    def status(self) -> dict[str, Any]:
        """The latest health snapshot plus the survey and the newest pose."""
        return self.reporter.snapshot()
