"""The daemon's status (``StatusReporter``): what it says of itself, and where.

The status (``snapshot``: what ``seamap ctl status``, the control requests and zenoh's
``seamap/{vehicle}/status`` show) is the latest health snapshot (``daemon.health``) with
the newest pose, the live tiles published and the coverage (``daemon.publishing``). Its
one-line form (``text``) is systemd's ``STATUS=``. The health task takes a snapshot a
second and publishes it; every ``[daemon] health_interval_s`` it logs the health line and
updates systemd's status.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from daemon.health import HealthMonitor, LiveParts
from daemon.notify import Notifier
from daemon.publishing import Publishing
from daemon.surveys import OpenSurvey


class StatusReporter:
    """See the module docstring; ``task`` (the health task) runs under the daemon's
    supervisor."""

    def __init__(
        self,
        health: HealthMonitor,
        parts: LiveParts,
        open_survey: OpenSurvey,
        publishing: Publishing,
        notifier: Notifier,
        health_interval_s: float,
    ) -> None:
        self.health = health
        self.parts = parts
        self.open_survey = open_survey
        self.publishing = publishing
        self.notifier = notifier
        self.health_interval_s = health_interval_s

    def snapshot(self) -> dict[str, Any]:
        """The latest health snapshot plus the survey and the newest pose."""
        snapshot = dict(self.health.latest) or self.health.sample(self.parts)
        pose = self.publishing.latest_pose
        snapshot["pose"] = None if pose is None else {
            "time": pose.time,
            "lat": pose.lat,
            "lon": pose.lon,
            "east": pose.east,
            "north": pose.north,
            "heading_deg": pose.heading_deg,
            "epsg": pose.epsg,
        }  # fmt: skip
        snapshot["tiles_published"] = self.publishing.tiles_published
        snapshot["coverage"] = self.publishing.coverage_status
        return snapshot

    def survey_id(self) -> str | None:
        """The open survey's id (None between surveys)."""
        survey = self.open_survey.survey
        return survey.id if survey is not None else None

    def text(self) -> str:
        """The status on one line (systemd's ``STATUS=``)."""
        snap = self.health.latest
        survey = self.survey_id() or "no survey"
        if not snap:
            return survey
        text = f"{survey}: {snap['frames']['mapped']} frames mapped, lag {snap['lag_s']:.1f} s"
        coverage = self.publishing.coverage_status
        if self.open_survey.survey is not None and coverage and coverage.get("area"):
            text += f", {100 * coverage['area']['fraction']:.1f} % of the area covered"
        return text

    async def task(self) -> None:
        """A snapshot a second, published; the health line and systemd's status every
        ``health_interval_s``."""
        interval = self.health_interval_s
        next_line = time.monotonic() + min(interval, 5.0)
        while True:
            self.health.sample(self.parts)
            publisher = self.publishing.publisher
            if publisher is not None:
                publisher.status(self.snapshot())
            if time.monotonic() >= next_line:
                self.health.log_line()
                self.notifier.status(self.text())
                next_line += interval
            await asyncio.sleep(1.0)
