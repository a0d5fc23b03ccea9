"""The state folder at start-up (``daemon.state_dir``): made, checked and its scratch
emptied; and what a crash left in it sorted into passes to rerun, the survey to resume
and surveys given up on."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import pytest

from daemon.state_dir import MAX_PASSES_CUT, prepare_state_dir, recover
from daemon.survey import State, SurveyState, read_state, surveys_dir, write_state
from drivers.errors import SeamapError


def test_the_state_folder_is_made_and_its_scratch_emptied(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", tempfile.tempdir)  # restored afterwards
    state_dir = tmp_path / "state"
    stale = state_dir / "tmp" / "pass-scratch"
    stale.mkdir(parents=True)
    (stale / "tile.spill").write_bytes(b"left by a killed pass")
    prepare_state_dir(state_dir)
    assert surveys_dir(state_dir).is_dir()
    assert list((state_dir / "tmp").iterdir()) == []
    assert tempfile.gettempdir() == str(state_dir / "tmp")
    prepare_state_dir(state_dir)  # a second start finds it made


def test_a_state_folder_that_cannot_be_made_is_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(SeamapError) as raised:
        prepare_state_dir(blocker / "state")
    message = str(raised.value)
    assert "cannot create the state folder" in message and "\n" not in message


def _left(state_dir: Path, survey_id: str, state: State, started: float, cut: int = 0) -> Path:
    """A survey folder as a run of the daemon left it."""
    folder = surveys_dir(state_dir) / survey_id
    folder.mkdir(parents=True)
    write_state(
        folder, SurveyState(survey_id, "boat1", state=state, started=started, passes_cut=cut)
    )
    return folder


def test_what_a_crash_left_is_sorted(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    state_dir = tmp_path / "state"
    older = _left(state_dir, "20260101-000000", "recording", 1.0)  # a crash before
    cut_once = _left(state_dir, "20260101-010000", "finishing", 2.0, cut=1)
    killer = _left(state_dir, "20260101-020000", "finishing", 3.0, cut=MAX_PASSES_CUT)
    done = _left(state_dir, "20260101-030000", "done", 4.0)
    newest = _left(state_dir, "20260101-040000", "recording", 5.0)
    (surveys_dir(state_dir) / "not-a-survey").mkdir()

    with caplog.at_level(logging.INFO, logger="daemon.service"):
        found = recover(state_dir)

    # The newest recording survey resumes; the older one ends and its pass runs, as
    # does the pass cut once; the one cut MAX_PASSES_CUT times is given up.
    assert found.resume is not None and found.resume.id == newest.name
    assert found.resume.state == "recording"
    assert [s.id for s in found.rerun] == [older.name, cut_once.name]
    ended = read_state(older)
    assert ended is not None and ended.state == "finishing" and ended.reason == "interrupted"
    assert ended.ended is not None
    given_up = read_state(killer)
    assert given_up is not None and given_up.state == "failed" and given_up.reason
    assert f"cut {MAX_PASSES_CUT} times" in given_up.reason
    assert f"seamap replay --survey {killer}" in given_up.reason
    for folder, state in ((cut_once, "finishing"), (done, "done"), (newest, "recording")):
        kept = read_state(folder)
        assert kept is not None and kept.state == state
    lines = [(r.getMessage(), r.fields["survey"]) for r in caplog.records]  # type: ignore[attr-defined]
    assert lines == [
        ("rerunning an interrupted survey-end pass", older.name),
        ("rerunning an interrupted survey-end pass", cut_once.name),
        ("survey-end pass given up", killer.name),
    ]


def test_a_clean_state_folder_leaves_nothing_to_do(tmp_path: Path) -> None:
    found = recover(tmp_path / "nowhere")
    assert found.rerun == [] and found.resume is None
