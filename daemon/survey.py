"""Survey folders and their state: ``state_dir/surveys/{survey}/survey.json``.

A survey is opened (``recording``), ended (``finishing`` while the survey-end pass runs)
and then ``done`` (result folder written) or ``failed`` (the pass could not map it; the
recordings stay intact and ``seamap replay --survey`` can retry). The state file is
replaced atomically, so a crash at any moment leaves either the old or the new state;
the daemon reads it at start-up to resume a survey that was recording (a new segment)
or to redo a survey-end pass that was cut short.

A full disk must not cost the state: each survey folder holds a reserve file
(``.survey.reserve``, 256 KiB allocated when the survey opens), given up when a state
write meets ENOSPC so that the write goes through, and taken again once space returns.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

State = Literal["recording", "finishing", "done", "failed"]
STATE_FILE = "survey.json"
RESERVE_FILE = ".survey.reserve"
RESERVE_BYTES = 256 * 1024
"""Room kept for the state file (a few KiB) when the disk fills."""
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
_ID = re.compile(r"^\d{8}-\d{6}(-\d+)?$")


@dataclass
class SurveyState:
    """What ``survey.json`` holds (times UNIX s)."""

    id: str
    vehicle: str
    state: State = "recording"
    started: float = 0.0
    ended: float | None = None
    segments: int = 0
    """Recording segments opened (one per daemon run that recorded into the survey)."""
    reason: str | None = None
    """Why the survey failed, or what ended it ("command", "shutdown")."""
    live: dict[str, Any] = field(default_factory=dict)
    """The live map's counters at the end of each recording run (frames received, mapped,
    rejected, skipped, ...), one entry per segment."""
    result: dict[str, Any] = field(default_factory=dict)
    """Summary of the survey-end pass: frames read/mapped, files written."""
    passes_cut: int = 0
    """Survey-end passes started that never ended in the daemon: counted up when one starts,
    down when it ends in any way (done, failed, deferred) or a second stop signal cuts it;
    what is left was cut by the daemon's death (the kernel's out-of-memory killer: the
    2-hour hectare's optimisation took 21.8 GB)."""


def surveys_dir(state_dir: str | os.PathLike[str]) -> Path:
    return Path(state_dir) / "surveys"


def new_survey_id(state_dir: str | os.PathLike[str], now: float | None = None) -> str:
    """A fresh id from the UTC start time, ``YYYYMMDD-HHMMSS`` (``-2``, ``-3``... when taken)."""
    base = time.strftime("%Y%m%d-%H%M%S", time.gmtime(time.time() if now is None else now))
    root = surveys_dir(state_dir)
    candidate, n = base, 1
    while (root / candidate).exists():
        n += 1
        candidate = f"{base}-{n}"
    return candidate


def reserve_space(survey_dir: Path) -> bool:
    """Allocate the folder's reserve file if it is missing; False if there is no room."""
    path = survey_dir / RESERVE_FILE
    try:
        if path.stat().st_size >= RESERVE_BYTES:
            return True
    except OSError:
        pass
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o600)
        try:
            os.posix_fallocate(fd, 0, RESERVE_BYTES)
        finally:
            os.close(fd)
    except OSError:
        with contextlib.suppress(OSError):
            path.unlink()
        return False
    return True


def write_state(survey_dir: Path, state: SurveyState) -> None:
    """Replace ``survey.json`` atomically (temp file, fsync, rename). On a full disk the
    folder's reserve is given up for it (and taken again at a later write with room);
    OSError only if even that cannot make room."""
    text = json.dumps(asdict(state), indent=2) + "\n"
    try:
        _replace(survey_dir, text)
    except OSError as exc:
        if exc.errno not in DISK_FULL:
            raise
        with contextlib.suppress(OSError):
            (survey_dir / RESERVE_FILE).unlink()
        _replace(survey_dir, text)
        return
    reserve_space(survey_dir)


def _replace(survey_dir: Path, text: str) -> None:
    path = survey_dir / STATE_FILE
    tmp = path.with_name(f".{STATE_FILE}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    with contextlib.suppress(OSError):
        fd = os.open(survey_dir, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def disk_full(exc: BaseException) -> bool:
    """Whether an error (or one it was raised from) is a full disk or quota."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno in DISK_FULL:
            return True
        if "No space left on device" in str(seen) or "Disk quota exceeded" in str(seen):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def read_state(survey_dir: Path) -> SurveyState | None:
    """The survey's state, or None when the folder has no readable ``survey.json``."""
    try:
        data = json.loads((survey_dir / STATE_FILE).read_text(encoding="utf-8"))
        return SurveyState(**data)
    except (OSError, ValueError, TypeError):
        return None


def unfinished(state_dir: str | os.PathLike[str]) -> list[SurveyState]:
    """Surveys left ``recording`` or ``finishing`` (by a crash or a cut shutdown), oldest first."""
    root = surveys_dir(state_dir)
    if not root.is_dir():
        return []
    found = []
    for folder in sorted(root.iterdir()):
        if not (folder.is_dir() and _ID.match(folder.name)):
            continue
        state = read_state(folder)
        if state is not None and state.state in ("recording", "finishing"):
            found.append(state)
    return sorted(found, key=lambda s: s.started)
