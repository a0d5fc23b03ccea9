"""The daemon's parts on their own: the mapping thread's bounded backlog and its recovery
from an engine failure, task supervision, survey state files, the log line format and the
control socket."""

from __future__ import annotations

import asyncio
import functools
import io
import json
import logging
import threading
from pathlib import Path
from typing import Any

import pytest

from daemon.control import request, serve_control
from daemon.logs import LineFormatter, configure_logging, format_fields
from daemon.mapper import MappingWorker
from daemon.replay import mount_from_config, pipeline_params
from daemon.supervisor import Supervisor
from daemon.survey import SurveyState, new_survey_id, read_state, unfinished, write_state
from drivers.errors import SeamapError
from mapping.samples import Ping
from mapping.streaming import PoseUpdate, StreamingEngine, StreamingParams
from tools.sim.stream import survey_events


@functools.cache
def _events(pings: int) -> tuple[list[Any], Any]:
    """A short simulated survey in arrival order and its site (simulated once a size)."""
    stream = survey_events("quadrats", 4, max_pings=pings, n_beams=128)
    return [sample for _, sample in stream.events], stream.site_config


def _factory(config: Any, gate: threading.Event | None = None) -> Any:
    params = StreamingParams(pipeline=pipeline_params(config))
    mount = mount_from_config(config.sonar)

    class Gated(StreamingEngine):
        def add(self, sample: Any) -> None:
            if gate is not None:
                gate.wait()
            super().add(sample)

    return lambda: Gated(mount, params)


def test_worker_maps_off_the_loop_and_hands_poses_back() -> None:
    samples, config = _events(40)
    poses: list[PoseUpdate] = []
    loop_thread: list[int] = []

    async def main() -> Any:
        loop = asyncio.get_running_loop()

        def on_pose(update: PoseUpdate) -> None:
            loop_thread.append(threading.get_ident())
            poses.append(update)

        worker = MappingWorker(
            _factory(config), loop=loop, max_backlog_frames=1000, on_pose=on_pose
        )
        for sample in samples:
            assert worker.submit(sample)
        stats = await worker.finish()
        await asyncio.sleep(0.05)  # the last call_soon_threadsafe callbacks
        return stats, worker

    stats, worker = asyncio.run(main())
    pings = sum(isinstance(s, Ping) for s in samples)
    assert stats.frames_received == pings == worker.stats.frames_submitted
    assert stats.frames_mapped > 0.9 * pings
    assert worker.backlog_frames == 0 and worker.lag_s() == 0.0
    assert set(loop_thread) == {threading.get_ident()}  # callbacks ran on the loop's thread
    assert len({p.frame for p in poses if p.final}) == stats.frames_mapped


def test_full_backlog_skips_frames_never_navigation() -> None:
    samples, config = _events(30)
    gate = threading.Event()  # the engine is stuck until the gate opens

    async def main() -> Any:
        worker = MappingWorker(
            _factory(config, gate), loop=asyncio.get_running_loop(), max_backlog_frames=5
        )
        accepted = [worker.submit(s) for s in samples]
        lag = worker.lag_s()
        gate.set()
        stats = await worker.finish()
        return accepted, worker, stats, lag

    accepted, worker, stats, lag = asyncio.run(main())
    pings = [s for s in samples if isinstance(s, Ping)]
    refused = [s for s, ok in zip(samples, accepted, strict=True) if not ok]
    assert all(isinstance(s, Ping) for s in refused)
    assert worker.stats.frames_skipped == len(pings) - 5
    assert stats.frames_received == 5
    assert lag > 0.0  # frames were waiting


def test_engine_failure_restarts_the_live_map() -> None:
    samples, config = _events(30)
    params = StreamingParams(pipeline=pipeline_params(config))
    mount = mount_from_config(config.sonar)
    made: list[int] = []

    class Fragile(StreamingEngine):
        def add(self, sample: Any) -> None:
            if not made[1:] and isinstance(sample, Ping) and self.stats.frames_received == 3:
                raise RuntimeError("boom")
            super().add(sample)

    def factory() -> StreamingEngine:
        made.append(1)
        return Fragile(mount, params)

    async def main() -> Any:
        worker = MappingWorker(factory, loop=asyncio.get_running_loop(), max_backlog_frames=100)
        for sample in samples:
            worker.submit(sample)
        stats = await worker.finish()
        return worker, stats

    worker, stats = asyncio.run(main())
    assert worker.stats.restarts == 1 and "boom" in (worker.stats.last_error or "")
    assert len(made) == 2
    assert stats.frames_mapped > 10  # the new engine went on mapping


def test_supervisor_restarts_a_failing_task_and_leaves_the_others(caplog: Any) -> None:
    import daemon.supervisor as supervisor_module

    runs = {"flaky": 0, "steady": 0}

    async def flaky() -> None:
        runs["flaky"] += 1
        if runs["flaky"] < 3:
            raise OSError("port busy")
        await asyncio.Event().wait()

    async def steady() -> None:
        runs["steady"] += 1
        await asyncio.Event().wait()

    async def main() -> Supervisor:
        supervisor_module.BACKOFF_INITIAL_S = 0.01
        supervisor = Supervisor()
        supervisor.spawn("flaky", flaky)
        supervisor.spawn("steady", steady)
        await asyncio.sleep(0.3)
        await supervisor.stop()
        return supervisor

    original = supervisor_module.BACKOFF_INITIAL_S
    try:
        with caplog.at_level(logging.ERROR):
            supervisor = asyncio.run(main())
    finally:
        supervisor_module.BACKOFF_INITIAL_S = original
    assert runs == {"flaky": 3, "steady": 1}
    assert supervisor.restarts == {"flaky": 2, "steady": 0}
    failures = [r for r in caplog.records if r.getMessage() == "task failed, restarting"]
    assert len(failures) == 2
    assert failures[0].__dict__["fields"]["reason"] == "OSError: port busy"


def test_survey_state_survives_and_unfinished_surveys_are_found(tmp_path: Path) -> None:
    first = new_survey_id(tmp_path, now=1_700_000_000.0)
    assert first == "20231114-221320"
    folder = tmp_path / "surveys" / first
    folder.mkdir(parents=True)
    assert new_survey_id(tmp_path, now=1_700_000_000.0) == f"{first}-2"
    write_state(folder, SurveyState(first, "boat1", started=1.0))
    done = tmp_path / "surveys" / "20231114-221400"
    done.mkdir()
    write_state(done, SurveyState(done.name, "boat1", state="done", started=2.0))
    (tmp_path / "surveys" / "not-a-survey").mkdir()
    assert [s.id for s in unfinished(tmp_path)] == [first]
    state = read_state(folder)
    assert state is not None and state.state == "recording"
    (folder / "survey.json").write_text("{broken")
    assert read_state(folder) is None and unfinished(tmp_path) == []


def test_log_lines_carry_fields_and_journald_priorities() -> None:
    record = logging.LogRecord("daemon.service", logging.WARNING, "", 1, "sonar silent", None, None)
    fields = {"address": "10.0.0.5", "reason": "no ping for 5 s", "n": 3}
    record.__dict__["fields"] = fields
    line = LineFormatter(journald=True).format(record)
    assert line == '<4>warning service: sonar silent address=10.0.0.5 reason="no ping for 5 s" n=3'
    plain = LineFormatter(journald=False).format(record)
    assert plain.endswith("warning service: sonar silent " + format_fields(fields))
    assert plain[:4].isdigit() and "Z " in plain
    stream = io.StringIO()
    configure_logging("warning", stream)
    try:
        logging.getLogger("daemon.x").info("quiet")
        logging.getLogger("daemon.x").warning("loud")
    finally:
        configure_logging("warning", None)
        logging.getLogger().handlers.clear()
    assert "quiet" not in stream.getvalue() and "loud" in stream.getvalue()


class _FakeDaemon:
    def __init__(self) -> None:
        self.survey: str | None = None
        self.areas: list[dict[str, Any] | None] = []

    async def start_survey(self, reason: str, area: dict[str, Any] | None = None) -> str:
        if area is not None and area.get("type") != "Polygon":
            raise SeamapError("area: not a polygon")
        self.areas.append(area)
        self.survey = self.survey or "20260101-000000"
        return self.survey

    async def stop_survey(self, reason: str, *, wait: bool) -> str | None:
        survey, self.survey = self.survey, None
        return survey

    def status(self) -> dict[str, Any]:
        return {"survey": self.survey}


def test_control_socket_commands_and_errors(tmp_path: Path) -> None:
    path = tmp_path / "control.sock"

    async def main() -> list[Any]:
        server = asyncio.create_task(serve_control(_FakeDaemon(), path))
        while not path.exists():
            await asyncio.sleep(0.01)
        replies = [
            await asyncio.to_thread(request, path, command)
            for command in ("status", "start", "status", "stop", "stop", "launch")
        ]
        server.cancel()
        await asyncio.gather(server, return_exceptions=True)
        return replies

    replies = asyncio.run(main())
    assert replies[0] == {"ok": True, "status": {"survey": None}}
    assert replies[1] == {"ok": True, "survey": "20260101-000000"}
    assert replies[2]["status"]["survey"] == "20260101-000000"
    assert replies[3]["survey"] == "20260101-000000" and replies[4]["survey"] is None
    assert replies[5]["ok"] is False and "unknown command" in replies[5]["error"]
    assert not path.exists()  # removed on shutdown
    with pytest.raises(SeamapError, match="no daemon control socket"):
        request(path, "status")


def test_control_socket_passes_the_area_and_says_why_it_refuses_one(tmp_path: Path) -> None:
    path = tmp_path / "control.sock"
    daemon = _FakeDaemon()
    polygon = {"type": "Polygon", "coordinates": [[[0.0, 0.0], [1e-4, 0.0], [0.0, 1e-4]]] * 400}

    async def main() -> list[Any]:
        server = asyncio.create_task(serve_control(daemon, path))
        while not path.exists():
            await asyncio.sleep(0.01)
        replies = [
            await asyncio.to_thread(request, path, "start", 5.0, area=area)
            for area in (polygon, {"type": "Point"}, "north field")
        ]
        server.cancel()
        await asyncio.gather(server, return_exceptions=True)
        return replies

    replies = asyncio.run(main())
    assert len(json.dumps(polygon)) > 4096  # beyond the old request limit
    assert replies[0] == {"ok": True, "survey": "20260101-000000"}
    assert daemon.areas == [polygon]
    assert replies[1] == {"ok": False, "error": "area: not a polygon"}
    assert replies[2] == {"ok": False, "error": "area must be a GeoJSON object"}
