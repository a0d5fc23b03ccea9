"""What the daemon publishes of its surveys (``Publishing``): the newest pose, the live
tiles, the coverage, and the zenoh session that carries them.

The live map's output comes here (it is the surveys' ``SurveySink``): a pose becomes "where
the boat is" unless it refines an older frame, each tile is counted, and both go to the
``ZenohPublisher`` (``daemon.publisher``, the wire side, on its own thread). Every
``COVERAGE_EVERY_S`` the open survey's live coverage (``daemon.live_coverage``) becomes the
status's ``coverage`` and a publication; a survey's final coverage (from its survey-end
pass) becomes the status's unless another survey is open. The session itself is opened,
attached and closed by ``zenoh_task`` (supervised: it comes back after a failure, and the
publisher's caches let a shore catch up).
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from daemon.config import ZenohConfig
from daemon.live_coverage import CoverageMessage, LiveCoverage
from daemon.publisher import ZenohPublisher
from daemon.surveys import OpenSurvey
from drivers.zenoh_io import open_session
from mapping.streaming import PoseUpdate, TileUpdate

# The daemon's lines keep the logger they always had ("service:" in the journal).
log = logging.getLogger("daemon.service")

COVERAGE_EVERY_S = 5.0
"""Seconds between live coverage publications: a boat at 0.5 m/s moves 2.5 m, about the
fan's depth; the gaps of a hectare take tens of milliseconds to compute."""


class Publishing:
    """See the module docstring. ``publisher`` is set once the event loop runs (the
    daemon's ``run``); until then nothing goes out, but the status still counts."""

    def __init__(self, zenoh: ZenohConfig, open_survey: OpenSurvey) -> None:
        self.zenoh = zenoh
        self.open_survey = open_survey
        self.publisher: ZenohPublisher | None = None
        self.latest_pose: PoseUpdate | None = None
        """Where the boat is: the newest pose of the open survey's live map."""
        self.tiles_published = 0
        """Live tiles of the open survey handed to the publisher."""
        self.coverage_status: dict[str, Any] | None = None
        """The status's ``coverage``: the open survey's latest, else the last survey's
        (final once its survey-end pass wrote the result folder)."""

    def survey_opened(self) -> None:
        """A new survey opened: nothing of its own to show yet."""
        self.coverage_status = None
        self.latest_pose, self.tiles_published = None, 0

    # --- the live map's output (event loop) ------------------------------------------------

    def on_pose(self, update: PoseUpdate) -> None:
        # Refinements of older frames move the map, not "where the boat is": they go out
        # with the next pose, for the shores' tracks to follow the map.
        if self.latest_pose is None or update.time >= self.latest_pose.time:
            self.latest_pose = update
            if self.publisher is not None:
                self.publisher.pose(update)
        elif self.publisher is not None:
            self.publisher.refine(update)

    def on_tile(self, survey: str, update: TileUpdate) -> None:
        self.tiles_published += 1
        if self.publisher is not None:
            self.publisher.tile(survey, update)

    # --- coverage ----------------------------------------------------------------------------

    async def coverage_task(self) -> None:
        """The open survey's live coverage, every ``COVERAGE_EVERY_S`` while it grows."""
        counted = -1
        while True:
            await asyncio.sleep(COVERAGE_EVERY_S)
            coverage, state = self.open_survey.coverage, self.open_survey.survey
            if coverage is None or state is None or coverage.frames == counted:
                continue
            counted = coverage.frames
            await self.publish_coverage(state.id, coverage)

    async def publish_coverage(self, survey_id: str, coverage: LiveCoverage) -> None:
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
        survey = self.open_survey.survey
        if survey is None or survey.id == survey_id:
            self.coverage_status = message.status()
        if self.publisher is not None:
            self.publisher.coverage(survey_id, message)

    def final_coverage(self, survey_id: str, message: CoverageMessage) -> None:
        """A survey's final coverage becomes the status's, unless another survey is open
        (event loop)."""
        if self.open_survey.survey is None:
            self.coverage_status = message.status()

    # --- the session -------------------------------------------------------------------------

    async def zenoh_task(self) -> None:
        assert self.publisher is not None
        session = await asyncio.to_thread(open_session, self.zenoh)
        self.publisher.attach(session)
        z = self.zenoh
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
