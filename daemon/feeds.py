"""The device feeds (``Feeds``): the sonar and the autopilot links, and where what they
deliver goes.

- **sonar**: ``OculusLink`` keeps the sonar pinging; every message it receives goes to the
  recorder before anything parses it; pings go to the mapper (the first one's fan to the
  live coverage).
- **mavlink**: ``MavlinkLink`` talks to the autopilot; every packet goes to the recorder,
  typed samples to the mapper (a usable GNSS fix is noted for the health monitor).

Between surveys nothing is recorded, and with ``[sonar] standby_outside_surveys`` the
sonar stands by (``follow_survey``, called whenever a survey opens or closes, and for
each new link).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from daemon.config import SiteConfig
from daemon.health import LiveParts
from daemon.replay import pipeline_params
from daemon.surveys import OpenSurvey
from drivers.mavlink.link import MavlinkLink
from drivers.oculus.link import OculusLink
from mapping.coverage import SonarFan
from mapping.samples import GnssFix, NavSample, Ping

# The daemon's lines keep the logger they always had ("service:" in the journal).
log = logging.getLogger("daemon.service")


class Feeds:
    """The sonar and MAVLink feeds and the sonar's standby policy (see the module doc);
    ``sonar_task`` and ``mavlink_task`` run under the daemon's supervisor."""

    def __init__(self, config: SiteConfig, parts: LiveParts, open_survey: OpenSurvey) -> None:
        self.config = config
        self.parts = parts
        self.open_survey = open_survey
        self._sonar_resting: bool | None = None
        """What the sonar was last asked for (standby or firing); None: nothing yet."""

    # --- sonar -------------------------------------------------------------------------------

    async def sonar_task(self) -> None:
        link = OculusLink.from_config(self.config.sonar, on_message=self.on_sonar_message)
        self.parts.sonar = link
        self._sonar_resting = None  # a new link: say what it is asked for
        self.follow_survey()
        async with contextlib.aclosing(link.pings()) as pings:
            async for ping in pings:
                self.on_ping(ping)

    def on_sonar_message(self, message: bytes, received: float) -> None:
        """Every message from the sonar, as received: recorded (the link's callback)."""
        recorder = self.parts.recorder
        if recorder is not None:
            recorder.record_sonar(message, received)

    def on_ping(self, ping: Ping) -> None:
        """A parsed ping: to the live map (and its fan to the live coverage)."""
        self.parts.last_ping = ping.time
        coverage = self.open_survey.coverage
        if coverage is not None and coverage.fan is None:
            # The fan of the first ping, as the survey-end pass takes it.
            preprocess = pipeline_params(self.config).preprocess
            coverage.set_fan(SonarFan.of_ping(ping, coverage.mount, preprocess))
        mapper = self.parts.mapper
        if mapper is not None:
            mapper.submit(ping)

    # --- standby -----------------------------------------------------------------------------

    def sonar_rests(self) -> bool:
        """Whether the sonar should stand by now: no survey open and the config says so."""
        return self.open_survey.survey is None and self.config.sonar.standby_outside_surveys

    def follow_survey(self) -> None:
        """Stand the sonar by or fire it, as the survey's state asks (said once a change)."""
        link = self.parts.sonar
        rest = self.sonar_rests()
        if link is None or self._sonar_resting == rest:
            return
        self._sonar_resting = rest
        link.set_standby(rest)
        survey = self.open_survey.survey
        log.info(
            "sonar standing by: no survey open" if rest else "sonar firing: survey open",
            extra={"fields": {"survey": survey.id if survey else None}},
        )

    # --- autopilot ---------------------------------------------------------------------------

    async def mavlink_task(self) -> None:
        m = self.config.mavlink
        link = MavlinkLink(
            m.url,
            baud=m.baud,
            heading_source=m.heading_source,
            imu_source=m.imu_source,
            declination_deg=m.declination_deg,
            on_packet=self.on_nav_packet,
            on_sample=self.on_nav_sample,
        )
        self.parts.mavlink = link
        try:
            await link.start()
            await asyncio.Event().wait()
        finally:
            await link.close()

    def on_nav_packet(self, packet: bytes, received: float) -> None:
        """Every MAVLink packet, as received: recorded (the link's callback)."""
        recorder = self.parts.recorder
        if recorder is not None:
            recorder.record_mavlink(packet, received)

    def on_nav_sample(self, sample: NavSample) -> None:
        """A typed navigation sample: to the live map (a usable fix noted)."""
        if isinstance(sample, GnssFix) and sample.usable:
            self.parts.last_fix = sample.time
        mapper = self.parts.mapper
        if mapper is not None:
            mapper.submit(sample)
