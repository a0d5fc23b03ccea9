"""The survey-end pass on its own (``daemon.final_pass.FinalPasses``): a recorded survey
mapped into its result folder, its final coverage shown and its gaps planned; the pass
switched off; a survey that cannot be mapped failing in one line; a full disk deferring
the pass until space returns; passes cut on purpose not counted against them."""

from __future__ import annotations

import asyncio
import logging
import shutil
import tomllib
from pathlib import Path
from typing import Any

import pytest

import daemon.final_pass as final_pass
from daemon.config import SiteConfig, config_from_dict
from daemon.final_pass import FinalPasses
from daemon.health import LiveParts
from daemon.notify import Notifier
from daemon.publishing import Publishing
from daemon.survey import SurveyState, read_state, surveys_dir, write_state
from daemon.survey_files import AREA_FILE, LIVE_TILES
from daemon.surveys import OpenSurvey
from tools.sim import simulate


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short simulated survey (its logs, site.toml and area.geojson), made once."""
    out = tmp_path_factory.mktemp("sim")
    simulate("quadrats", 2, out, max_pings=30)
    return out


def site_config(state_dir: Path, sim: Path | None = None, **tables: dict[str, Any]) -> SiteConfig:
    """The simulation's site (defaults without ``sim``) with its state in ``state_dir``;
    ``tables`` override keys of any table."""
    data: dict[str, Any] = tomllib.loads((sim / "site.toml").read_text()) if sim else {}
    for table, keys in {"daemon": {}, **tables}.items():
        data.setdefault(table, {}).update(keys)
    data["daemon"]["state_dir"] = str(state_dir)
    return config_from_dict(data)


def closed_survey(state_dir: Path, survey_id: str, sim: Path | None = None) -> SurveyState:
    """A survey folder left ``finishing`` as a closed survey leaves it (the simulated
    survey's logs as its first segment, when ``sim`` is given)."""
    folder = surveys_dir(state_dir) / survey_id
    folder.mkdir(parents=True)
    if sim is not None:
        shutil.copy(sim / "sonar.oculus", folder / "sonar-001.oculus")
        shutil.copy(sim / "nav.tlog", folder / "nav-001.tlog")
    state = SurveyState(survey_id, "boat1", state="finishing", started=1.0, reason="command")
    write_state(folder, state)
    return state


def final_passes(config: SiteConfig) -> FinalPasses:
    """The part as the daemon wires it, without zenoh (no publisher) or systemd."""
    open_survey = OpenSurvey()
    return FinalPasses(
        config,
        Path(config.daemon.state_dir),
        LiveParts(),
        Publishing(config.zenoh, open_survey),
        Notifier({}),
        asyncio.Event(),
    )


def test_a_closed_survey_is_mapped_into_its_result_folder(tmp_path: Path, sim: Path) -> None:
    state_dir = tmp_path / "state"
    config = site_config(state_dir, sim, mission={"replan_at_end": True})
    state = closed_survey(state_dir, "20260101-000000", sim)
    folder = surveys_dir(state_dir) / state.id
    shutil.copy(sim / "area.geojson", folder / AREA_FILE)
    (folder / LIVE_TILES).mkdir()  # a live map's idle tiles, no use any more
    (folder / LIVE_TILES / "tile.bin").write_bytes(b"x")

    async def main() -> FinalPasses:
        passes = final_passes(config)
        task = passes.start(state)
        assert passes.tasks == {state.id: task}
        await task
        return passes

    passes = asyncio.run(main())
    saved = read_state(folder)
    assert saved is not None and saved.state == "done", saved
    assert saved.passes_cut == 0  # it ended here: not counted as cut
    assert saved.result["frames_read"] > 0 and saved.result["frames_mapped"] > 0
    for name in ("mosaic.tif", "coverage.tif", "gaps.geojson", "report.json"):
        assert name in saved.result["files"] and (folder / name).is_file()
    # 30 pings cover a sliver of the area: the gaps are planned into the survey folder.
    replan = saved.result["replan"]
    assert replan["gaps"] > 0 and "replan.plan" in replan["files"]
    assert (folder / final_pass.REPLAN_FILE).is_file()
    assert not (folder / LIVE_TILES).exists()
    assert passes.tasks == {} and passes.running == {} and passes.progress == {}
    # The final coverage became the status's (no other survey is open), gaps left out.
    status = passes.publishing.coverage_status
    assert status is not None and status["final"] is True and status["survey"] == state.id
    assert status["area"]["fraction"] < 1.0 and "gaps" not in status


def test_without_the_pass_the_survey_is_done_at_once(tmp_path: Path, sim: Path) -> None:
    state_dir = tmp_path / "state"
    config = site_config(state_dir, sim, daemon={"final_pass": False})
    state = closed_survey(state_dir, "20260101-000000", sim)

    async def main() -> None:
        await final_passes(config).start(state)

    asyncio.run(main())
    folder = surveys_dir(state_dir) / state.id
    saved = read_state(folder)
    assert saved is not None and saved.state == "done"
    assert saved.result == {"final_pass": False}
    assert not (folder / "mosaic.tif").exists()


def test_a_survey_that_cannot_be_mapped_fails_in_one_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    state_dir = tmp_path / "state"
    config = site_config(state_dir)
    state = closed_survey(state_dir, "20260101-000000")  # nothing was recorded

    async def main() -> FinalPasses:
        passes = final_passes(config)
        await passes.start(state)
        return passes

    with caplog.at_level(logging.INFO, logger="daemon.service"):
        passes = asyncio.run(main())
    saved = read_state(surveys_dir(state_dir) / state.id)
    assert saved is not None and saved.state == "failed"
    assert saved.reason and "\n" not in saved.reason
    assert saved.passes_cut == 0
    assert passes.progress == {} and passes.running == {} and passes.deferred == {}
    failed = [r for r in caplog.records if r.getMessage() == "survey-end pass failed"]
    assert len(failed) == 1 and failed[0].name == "daemon.service"
    assert failed[0].fields == {"survey": state.id, "reason": saved.reason}  # type: ignore[attr-defined]


def test_a_full_disk_defers_the_pass_until_space_returns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    state_dir = tmp_path / "state"
    full = site_config(state_dir, daemon={"min_free_mb": 1e9})  # more than any disk has
    state = closed_survey(state_dir, "20260101-000000")
    folder = surveys_dir(state_dir) / state.id
    monkeypatch.setattr(final_pass, "DEFERRED_PASS_CHECK_S", 0.01)

    async def main() -> tuple[FinalPasses, SurveyState | None]:
        passes = final_passes(full)
        room, free = passes.room()
        assert not room and free > 0
        await passes.start(state)
        deferred = read_state(folder)
        assert passes.deferred == {state.id: state}
        checker = asyncio.create_task(passes.deferred_task())
        try:
            # Space returns: the next check starts the pass (which then fails, since
            # nothing was recorded, but it ran).
            passes.config = site_config(state_dir, daemon={"min_free_mb": 0.0})
            assert passes.room()[0]
            for _ in range(1000):
                if not passes.deferred and not passes.tasks:
                    break
                await asyncio.sleep(0.01)
        finally:
            checker.cancel()
            await asyncio.gather(checker, return_exceptions=True)
        return passes, deferred

    with caplog.at_level(logging.INFO, logger="daemon.service"):
        passes, deferred = asyncio.run(main())
    assert deferred is not None and deferred.state == "finishing"
    assert deferred.reason is not None
    assert deferred.reason.startswith("survey-end pass deferred: ")
    assert "min_free_mb" in deferred.reason and deferred.passes_cut == 0
    assert passes.deferred == {} and passes.tasks == {}
    saved = read_state(folder)
    assert saved is not None and saved.state == "failed" and saved.passes_cut == 0
    messages = [r.getMessage() for r in caplog.records if r.name == "daemon.service"]
    assert messages.index("survey-end pass deferred") < messages.index(
        "disk space is back: running the deferred survey-end pass"
    )


def test_passes_cut_on_purpose_are_not_counted_against_them(tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    passes = final_passes(site_config(state_dir))
    state = closed_survey(state_dir, "20260101-000000")
    state.passes_cut = 2  # an earlier crash, and the pass running now
    passes.running[state.id] = state
    passes.cut_on_purpose()
    saved = read_state(surveys_dir(state_dir) / state.id)
    assert saved is not None and saved.passes_cut == 1
