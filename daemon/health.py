"""The daemon's health: one JSON-able snapshot a second, events on state changes.

``HealthMonitor.sample`` builds the snapshot from the live parts (links, mapper, recorder)
and keeps it for the log line and for publishing (CONTRACT: ``seamap/{vehicle}/status``:
links up, frames received/mapped/rejected, processing lag in seconds, disk free, ...).
It also notices transitions — sonar silent or back, autopilot heartbeat lost or back, no
GNSS fix, recording stopped, frames being skipped — and logs each once, when it happens.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from daemon.mapper import MappingWorker
from daemon.recording import SurveyRecorder
from drivers.mavlink.link import MavlinkLink
from drivers.oculus.link import OculusLink

log = logging.getLogger(__name__)

SONAR_SILENT_S = 2.0
"""No ping for this long: the sonar counts as down in the status."""
SONAR_STATUS_LOST_S = 3.5
"""Standing by, no status (broadcast about once a second) for this long: down."""
GNSS_STALE_S = 5.0
"""No usable GNSS fix for this long while the autopilot talks: GNSS lost."""
START_GRACE_S = 5.0
"""A link not up yet this long after start-up is not reported down yet."""


@dataclass
class LiveParts:
    """What the monitor looks at; any part may be absent (not started, no survey)."""

    sonar: OculusLink | None = None
    mavlink: MavlinkLink | None = None
    mapper: MappingWorker | None = None
    recorder: SurveyRecorder | None = None
    survey: str | None = None
    last_ping: float | None = None
    """Receive time (UNIX s) of the newest ping."""
    last_fix: float | None = None
    """Receive time (UNIX s) of the newest usable GNSS fix."""
    task_restarts: dict[str, int] = field(default_factory=dict)
    final_passes: dict[str, str] = field(default_factory=dict)
    """Survey id to what its survey-end pass is doing."""


class HealthMonitor:
    """Snapshots and transition events (see the module docstring)."""

    def __init__(self, vehicle: str, state_dir: Path) -> None:
        self.vehicle = vehicle
        self.state_dir = state_dir
        self.started = time.time()
        self.latest: dict[str, Any] = {}
        self._sonar_pings = (time.monotonic(), 0)
        self._sonar_rate = 0.0
        self._flags: dict[str, bool] = {}
        self._started_mono = time.monotonic()
        self._mav_up_since: float | None = None
        self._skipped_reported = 0
        self._skipped_warned_at = -float("inf")  # monotonic s; the warning comes at most every 30 s

    def sample(self, parts: LiveParts, now: float | None = None) -> dict[str, Any]:
        """The current snapshot (also kept as ``latest``); logs what changed."""
        now = time.time() if now is None else now
        snapshot = {
            "time": round(now, 3),
            "vehicle": self.vehicle,
            "uptime_s": round(now - self.started, 1),
            "survey": parts.survey,
            "links": {"sonar": self._sonar(parts, now), "mavlink": self._mavlink(parts, now)},
            "frames": self._frames(parts),
            "lag_s": round(parts.mapper.lag_s(now), 3) if parts.mapper is not None else 0.0,
            "recording": self._recording(parts),
            "disk_free_mb": self._disk_free_mb(),
            "tasks": {"restarts": dict(parts.task_restarts)},
            "final_passes": dict(parts.final_passes),
        }
        mission = snapshot["links"]["mavlink"].get("mission")  # type: ignore[index]
        if mission is not None:
            snapshot["mission"] = mission
        self._events(snapshot, parts)
        self.latest = snapshot
        return snapshot

    # --- parts ------------------------------------------------------------------------------

    def _sonar(self, parts: LiveParts, now: float) -> dict[str, Any]:
        link = parts.sonar
        if link is None:
            return {"up": False}
        mono = time.monotonic()
        then, pings = self._sonar_pings
        if mono - then >= 1.0:
            self._sonar_rate = (link.stats.pings - pings) / (mono - then)
            self._sonar_pings = (mono, link.stats.pings)
        pinging = parts.last_ping is not None and now - parts.last_ping < SONAR_SILENT_S
        heard = link.stats.last_status_time
        # Standing by (no survey open), the sonar is up while its status is heard.
        resting = link.standby and heard is not None and now - heard < SONAR_STATUS_LOST_S
        return {
            "up": pinging or resting,
            "standby": link.standby,
            "last_status_age_s": None if heard is None else round(now - heard, 2),
            "address": link.stats.sonar_address,
            "pings": link.stats.pings,
            "rate_hz": round(self._sonar_rate, 2),
            "connects": link.stats.connects,
            "reconnects": link.stats.reconnects,
            "silences": link.stats.silences,
            "bytes_skipped": link.stats.bytes_skipped,
            "parse_errors": link.stats.parse_errors,
            "last_ping_age_s": None if parts.last_ping is None else round(now - parts.last_ping, 2),
        }

    def _mavlink(self, parts: LiveParts, now: float) -> dict[str, Any]:
        link = parts.mavlink
        if link is None:
            return {"up": False}
        s = link.stats
        return {
            "up": s.link_up,
            "autopilot": s.autopilot,
            "packets": s.packets,
            "bad_packets": s.bad_packets,
            "bad_bytes": s.bad_bytes,
            "rates_hz": {k: round(v, 1) for k, v in sorted(s.rates_hz.items()) if v > 0},
            "link_downs": s.link_downs,
            "reconnects": s.reconnects,
            "reopens": s.reopens,
            "gnss_fix_age_s": None if parts.last_fix is None else round(now - parts.last_fix, 2),
            "mission": s.mission.to_dict() if s.mission is not None else None,
        }

    @staticmethod
    def _frames(parts: LiveParts) -> dict[str, Any]:
        mapper = parts.mapper
        if mapper is None:
            return {"received": 0, "mapped": 0, "rejected": 0, "skipped": 0, "backlog": 0}
        engine = mapper.engine_stats
        return {
            "received": mapper.stats.frames_submitted,
            "mapped": engine.frames_mapped,
            "rejected": engine.frames_rejected,
            "rejected_why": dict(engine.rejected),
            "skipped": mapper.stats.frames_skipped + engine.frames_skipped,
            "backlog": mapper.backlog_frames,
            "engine_restarts": mapper.stats.restarts,
            "tiles_not_spilled": engine.tile_spill_failures,
            "tile_spill_error": engine.tile_spill_error,
        }

    @staticmethod
    def _recording(parts: LiveParts) -> dict[str, Any]:
        rec = parts.recorder
        if rec is None:
            return {"active": False}
        s = rec.stats
        return {
            "active": rec.recording,
            "segment": s.segment,
            "sonar_items": s.sonar.items,
            "nav_items": s.nav.items,
            "bytes": s.sonar.bytes + s.nav.bytes,
            "dropped": s.sonar.dropped + s.nav.dropped,
            "full": s.full,
            "stop_reason": s.stop_reason if s.stop_reason != "closed" else None,
        }

    def _disk_free_mb(self) -> float | None:
        try:
            return round(shutil.disk_usage(self.state_dir).free / 2**20, 1)
        except OSError:
            return None

    # --- events -----------------------------------------------------------------------------

    def _flag(
        self, name: str, bad: bool, on: str, off: str | None, since: float, **fields: Any
    ) -> None:
        """Log ``on`` (a warning) when condition ``name`` turns bad and ``off`` (info) when
        it clears. At first the condition is undecided: good is logged as ``off``, bad only
        once it has lasted ``START_GRACE_S`` since ``since`` (monotonic s)."""
        before = self._flags.get(name)
        if before is None and bad and time.monotonic() - since < START_GRACE_S:
            return
        self._flags[name] = bad
        if bad and not before:
            log.warning(on, extra={"fields": fields})
        elif not bad and (before or before is None) and off is not None:
            log.info(off, extra={"fields": fields})

    def _events(self, snap: dict[str, Any], parts: LiveParts) -> None:
        sonar, mav = snap["links"]["sonar"], snap["links"]["mavlink"]
        started = self._started_mono
        if parts.sonar is not None:
            self._flag(
                "sonar_down", not sonar["up"], "sonar silent", "sonar pinging", started,
                address=sonar.get("address"), pings=sonar.get("pings"),
            )  # fmt: skip
        if parts.mavlink is not None:
            self._flag(
                "mavlink_down", not mav["up"], "autopilot link down", "autopilot link up",
                started, autopilot=mav.get("autopilot"), packets=mav.get("packets"),
            )  # fmt: skip
            if mav["up"]:  # without the autopilot, no news about its GNSS
                if self._mav_up_since is None:
                    self._mav_up_since = time.monotonic()
                age = mav.get("gnss_fix_age_s")
                stale = age is None or age > GNSS_STALE_S
                self._flag(
                    "gnss_lost", stale, "no GNSS fix", "GNSS fix", self._mav_up_since, age_s=age
                )
            else:
                self._mav_up_since = None
        rec = snap["recording"]
        self._flag(
            "recording_stopped", bool(rec.get("stop_reason")),
            "recording stopped", None, started, reason=rec.get("stop_reason"),
        )  # fmt: skip
        skipped = snap["frames"]["skipped"]
        mono = time.monotonic()
        if skipped > self._skipped_reported and mono - self._skipped_warned_at >= 30.0:
            self._skipped_warned_at = mono
            log.warning(
                "mapping behind: frames skipped live (they stay recorded)",
                extra={"fields": {"skipped": skipped, "lag_s": snap["lag_s"]}},
            )
            self._skipped_reported = skipped
        elif skipped < self._skipped_reported:  # a new survey restarted the counters
            self._skipped_reported = skipped

    def log_line(self) -> None:
        """The steady health line (INFO)."""
        snap = self.latest
        if not snap:
            return
        sonar, mav = snap["links"]["sonar"], snap["links"]["mavlink"]
        frames, rec = snap["frames"], snap["recording"]
        fields = {
            "survey": snap["survey"],
            "sonar": "up" if sonar["up"] else "down",
            "ping_hz": sonar.get("rate_hz"),
            "mavlink": "up" if mav["up"] else "down",
            "gnss_age_s": mav.get("gnss_fix_age_s"),
            "received": frames["received"],
            "mapped": frames["mapped"],
            "rejected": frames["rejected"],
            "skipped": frames["skipped"],
            "lag_s": snap["lag_s"],
            "rec_segment": rec.get("segment"),
            "rec_mb": round(rec.get("bytes", 0) / 2**20, 1),
            "disk_free_mb": snap["disk_free_mb"],
        }
        log.info("health", extra={"fields": fields})
