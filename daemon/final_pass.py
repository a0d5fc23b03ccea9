"""The survey-end pass and its scheduling (``FinalPasses``).

When a survey closes, its recorded segments are replayed through the single-stage
pipeline into the contract's result folder (``daemon.replay.replay_survey``: exactly what
``seamap replay --survey`` computes), off the loop, while the daemon carries on (a new
survey may already record). Then the final coverage becomes the status's, the final tiles
and coverage go out on zenoh, and with ``[mission] replan_at_end`` lanes are planned over
the gaps (``REPLAN_FILE``). ``survey.json`` says how it went: ``done`` with a summary,
``failed`` with the reason in one line (the recordings stay intact), or ``finishing``
with the reason when a full disk deferred it: a deferred pass runs once the state disk
has ``[daemon] min_free_mb`` again (checked every ``DEFERRED_PASS_CHECK_S``, and at the
next start).

Each pass counts itself in ``passes_cut`` while it runs, so that the next start can tell
a pass the daemon's death cut (``daemon.state_dir.recover``) from one that ended. During
shutdown systemd's stop timeout is extended while a pass progresses.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from daemon.config import SiteConfig
from daemon.health import LiveParts
from daemon.live_coverage import final_message
from daemon.notify import Notifier
from daemon.publishing import Publishing
from daemon.survey import SurveyState, disk_full, surveys_dir
from daemon.survey_files import AREA_FILE, LIVE_TILES, save_state
from drivers.errors import SeamapError

# The daemon's lines keep the logger they always had ("service:" in the journal).
log = logging.getLogger("daemon.service")

DEFERRED_PASS_CHECK_S = 10.0
"""How often a survey-end pass deferred by a full disk looks for space again."""
REPLAN_FILE = "replan.plan"
"""The gaps' lanes ``[mission] replan_at_end`` writes into the survey folder (with
replan.waypoints, replan.geojson and replan.png)."""


class FinalPasses:
    """The survey-end passes of the daemon (see the module docstring): ``start`` one for a
    closed survey; ``deferred_task`` runs under the daemon's supervisor; ``wait`` for all
    at shutdown."""

    def __init__(
        self,
        config: SiteConfig,
        state_dir: Path,
        parts: LiveParts,
        publishing: Publishing,
        notifier: Notifier,
        shutdown: asyncio.Event,
    ) -> None:
        self.config = config
        self.state_dir = state_dir
        self.parts = parts
        self.publishing = publishing
        self.notifier = notifier
        self.shutdown = shutdown
        """Set once the daemon is shutting down (then the stop timeout is extended)."""
        self.tasks: dict[str, asyncio.Task[None]] = {}
        """Survey id to its pass's task, while it runs (deferred ones included)."""
        self.running: dict[str, SurveyState] = {}
        """Surveys whose survey-end pass is mapping now."""
        self.deferred: dict[str, SurveyState] = {}
        """Surveys whose survey-end pass waits for disk space."""
        self.progress: dict[str, str] = {}
        """Survey id to what its pass is doing (the health snapshot's ``final_passes``)."""
        parts.final_passes = self.progress
        self._loop: asyncio.AbstractEventLoop | None = None

    def start(self, state: SurveyState) -> asyncio.Task[None]:
        """Run ``state``'s survey-end pass in the background (event loop); its task."""
        self._loop = asyncio.get_running_loop()
        task = asyncio.create_task(self._run(state), name=f"final-pass-{state.id}")
        self.tasks[state.id] = task
        task.add_done_callback(lambda _: self.tasks.pop(state.id, None))
        return task

    async def wait(self) -> None:
        """Until every pass has ended (passes started meanwhile included)."""
        while self.tasks:
            await asyncio.gather(*self.tasks.values(), return_exceptions=True)

    def cut_on_purpose(self) -> None:
        """The daemon leaves now without waiting (a second stop signal): the passes
        running are cut on purpose, not counted against them; they rerun at next start."""
        for state in list(self.running.values()):
            state.passes_cut -= 1
            save_state(surveys_dir(self.state_dir) / state.id, state)

    # --- room on the disk --------------------------------------------------------------------

    def room(self) -> tuple[bool, float]:
        """Whether the state disk has ``min_free_mb`` free for a survey-end pass, and how
        many MiB it has."""
        try:
            free = shutil.disk_usage(self.state_dir).free / 2**20
        except OSError:
            return True, math.nan
        return free >= self.config.daemon.min_free_mb, free

    def _defer(self, state: SurveyState, why: str) -> None:
        """Leave the survey ``finishing`` with the reason: the pass runs when space returns
        (checked every ``DEFERRED_PASS_CHECK_S`` while the daemon runs, and at start-up)."""
        state.state, state.reason = "finishing", why
        self.deferred[state.id] = state
        log.warning(
            "survey-end pass deferred", extra={"fields": {"survey": state.id, "reason": why}}
        )

    async def deferred_task(self) -> None:
        """Start deferred survey-end passes once the disk has room again."""
        while True:
            await asyncio.sleep(DEFERRED_PASS_CHECK_S)
            if not self.deferred or self.shutdown.is_set() or not self.room()[0]:
                continue
            for survey_id, state in list(self.deferred.items()):
                del self.deferred[survey_id]
                log.info("disk space is back: running the deferred survey-end pass",
                         extra={"fields": {"survey": survey_id}})  # fmt: skip
                self.start(state)

    # --- the pass ----------------------------------------------------------------------------

    async def _run(self, state: SurveyState) -> None:
        survey_dir = surveys_dir(self.state_dir) / state.id
        self.progress[state.id] = "starting"
        if not self.config.daemon.final_pass:
            state.state, state.result = "done", {"final_pass": False}
            save_state(survey_dir, state)
            self.progress.pop(state.id, None)
            return
        # The live map's idle tiles are no use once the survey ended: their room first.
        shutil.rmtree(survey_dir / LIVE_TILES, ignore_errors=True)
        room, free = self.room()
        if not room:
            self._defer(
                state,
                f"survey-end pass deferred: {free:.0f} MiB free on {self.state_dir}, less "
                f"than [daemon] min_free_mb ({self.config.daemon.min_free_mb:g}); it runs "
                "when space returns (recordings intact)",
            )
            self.progress.pop(state.id, None)
            save_state(survey_dir, state)
            return
        started = time.monotonic()
        state.passes_cut += 1  # until it ends here: a crash leaves it counted
        save_state(survey_dir, state)
        self.running[state.id] = state
        keepalive = asyncio.create_task(self._extend_stop_timeout(state.id))
        try:
            report = await asyncio.to_thread(self._replay, survey_dir, state.id)
        except Exception as exc:
            if disk_full(exc) or not self.room()[0]:
                # The disk filled while the pass wrote: not the survey's fault.
                self._defer(
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
            self.progress.pop(state.id, None)
            self.running.pop(state.id, None)
            state.passes_cut -= 1
        shutil.rmtree(survey_dir / LIVE_TILES, ignore_errors=True)
        save_state(survey_dir, state)

    def _replay(self, survey_dir: Path, survey_id: str) -> dict[str, Any]:
        """The pass itself (a worker thread): the result folder, the final coverage and
        tiles out, the gaps planned; replay's report."""
        from daemon.replay import replay_survey

        def progress(stage: str, done: int, total: int) -> None:
            self.progress[survey_id] = f"{stage} {done}/{total}"

        area = survey_dir / AREA_FILE
        report = replay_survey(
            survey_dir, self.config, survey_dir, progress=progress,
            area=area if area.exists() else None,
        )  # fmt: skip
        final = final_message(survey_dir, survey_id, int(time.time() * 1000))
        if final is not None:
            self._loop_call(self.publishing.final_coverage, survey_id, final)
        publisher = self.publishing.publisher
        if publisher is not None:
            self.progress[survey_id] = "publishing tiles"
            report["tiles_published"] = publisher.final_tiles(survey_id, survey_dir)
            publisher.survey_ended(survey_id)
            if final is not None:
                publisher.coverage(survey_id, final)
        if self.config.mission.replan_at_end and area.exists():
            self.progress[survey_id] = "planning the gaps"
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

    def _loop_call(self, callback: Callable[..., None], *args: Any) -> None:
        """Run ``callback(*args)`` on the event loop (from the survey-end pass's thread)."""
        if self._loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed
                self._loop.call_soon_threadsafe(callback, *args)

    async def _extend_stop_timeout(self, survey_id: str) -> None:
        """While a pass runs during shutdown, keep systemd's stop timeout ahead of it."""
        while True:
            if self.shutdown.is_set():
                self.notifier.extend_timeout(60.0)
                self.notifier.status(f"survey-end pass {survey_id}: {self.progress.get(survey_id)}")
            await asyncio.sleep(10.0)
