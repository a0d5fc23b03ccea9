"""The state folder at start-up: made and checked (``prepare_state_dir``), its scratch
emptied, and what a crash left in it found again (``recover``).

``recover`` settles the surveys' states on disk (an older survey left recording is
ended, a survey whose survey-end pass kept killing the daemon is given up) and says what
the daemon is to do with the rest: which survey-end passes to run again, which survey to
resume recording. The daemon does it (``daemon.final_pass``, ``daemon.surveys``).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from daemon.survey import SurveyState, surveys_dir, unfinished
from daemon.survey_files import save_state
from drivers.errors import SeamapError

# The daemon's lines keep the logger they always had ("service:" in the journal).
log = logging.getLogger("daemon.service")

MAX_PASSES_CUT = 2
"""Survey-end passes a survey may lose to the daemon's death before it is given up on (the
first could be an unrelated crash; a second, the pass itself)."""


def prepare_state_dir(state_dir: Path) -> None:
    """Make the state folder (``surveys/``, ``tmp/``) and check it is writable, else
    SeamapError (one line); empty ``tmp/`` and make it the process's temporary folder."""
    tmp = state_dir / "tmp"
    try:
        surveys_dir(state_dir).mkdir(parents=True, exist_ok=True)
        tmp.mkdir(exist_ok=True)
    except OSError as exc:
        raise SeamapError(
            f"{state_dir}: cannot create the state folder ({exc.strerror or exc})"
        ) from None
    if not os.access(state_dir, os.W_OK):
        raise SeamapError(f"{state_dir}: the state folder is not writable")
    # Scratch files of the survey-end pass (spilled tiles) go to the state disk, not
    # to a small /tmp.
    for stale in tmp.iterdir():
        shutil.rmtree(stale, ignore_errors=True)
    tempfile.tempdir = str(tmp)


@dataclass
class Recovery:
    """What a crash left to do: the surveys whose survey-end pass runs again (oldest
    first) and the survey that resumes recording, if any."""

    rerun: list[SurveyState] = field(default_factory=list)
    resume: SurveyState | None = None


def recover(state_dir: Path) -> Recovery:
    """Find the survey a crash interrupted (to resume) and the survey-end passes that were
    cut (to rerun), unless crashes cut them ``MAX_PASSES_CUT`` times: the survey then
    fails, said in one line, so that a pass that kills the daemon (out of memory) is not
    rerun at every start, cutting each new survey in turn."""
    left = unfinished(state_dir)
    recording = [s for s in left if s.state == "recording"]
    found = Recovery()
    for state in left:
        if recording and state is recording[-1]:
            continue
        folder = surveys_dir(state_dir) / state.id
        if state.state == "recording":
            state.state, state.ended = "finishing", time.time()
            state.reason = state.reason or "interrupted"
            save_state(folder, state)
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
            save_state(folder, state)
            continue
        log.info("rerunning an interrupted survey-end pass", extra={"fields": {"survey": state.id}})
        found.rerun.append(state)
    if recording:
        found.resume = recording[-1]
    return found
