"""``daemon.service.Daemon`` as the composition of its parts, run in this process (the
other tests run ``seamap run`` as a child): its public face (``run``, ``start_survey``,
``stop_survey``, ``status``, ``shutdown`` and what it holds) reads through to the parts,
with a real zenoh session on 127.0.0.1 and no sonar or autopilot to be found."""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path
from typing import Any

import pytest

from daemon.config import config_from_dict
from daemon.notify import Notifier
from daemon.service import Daemon
from daemon.survey import read_state, surveys_dir
from tests.daemon.harness import free_udp_port, zenoh_table
from tests.ports import free_tcp_port


def test_the_daemon_runs_a_survey_through_its_parts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", tempfile.tempdir)  # run() points it at state/tmp
    state_dir = tmp_path / "state"
    config = config_from_dict(
        {
            "daemon": {"state_dir": str(state_dir), "survey_autostart": True},
            "sonar": {"address": "127.0.0.1", "tcp_port": free_tcp_port()},
            "mavlink": {"url": f"udpin:127.0.0.1:{free_udp_port()}"},
            "zenoh": zenoh_table(),
        }
    )

    async def main() -> dict[str, Any]:
        seen: dict[str, Any] = {}
        daemon = Daemon(config, Notifier({}))
        assert daemon.survey is None and daemon.publisher is None
        runner = asyncio.create_task(daemon.run())
        try:
            for _ in range(1200):  # start-up (zenoh, compiled kernels) and the autostart
                if daemon.survey is not None or runner.done():
                    break
                await asyncio.sleep(0.1)
            assert daemon.survey is not None, "no survey opened"
            survey_id = daemon.survey.id
            seen["again"] = await daemon.start_survey("command") == survey_id
            seen["publisher"] = daemon.publisher is daemon.publishing.publisher is not None
            seen["coverage"] = daemon.coverage is daemon.open_survey.coverage is not None
            seen["pose"], seen["tiles"] = daemon.latest_pose, daemon.tiles_published
            seen["status"] = daemon.status()
            seen["stopped"] = await daemon.stop_survey("command")  # the pass awaited
            seen["survey"] = survey_id
            seen["after"] = daemon.survey, daemon.coverage, daemon.final_passes.tasks
            seen["nothing"] = await daemon.stop_survey("command")
        finally:
            daemon.shutdown()
            seen["code"] = await asyncio.wait_for(runner, 120)
        return seen

    seen = asyncio.run(main())
    assert seen["code"] == 0
    assert seen["again"] and seen["publisher"] and seen["coverage"]
    assert seen["pose"] is None and seen["tiles"] == 0
    status = seen["status"]
    assert status["vehicle"] == config.daemon.vehicle and status["survey"] == seen["survey"]
    assert status["pose"] is None and status["tiles_published"] == 0
    assert status["recording"]["active"] is True
    assert seen["stopped"] == seen["survey"] and seen["nothing"] is None
    assert seen["after"] == (None, None, {})
    # Nothing was heard, so nothing could be mapped: the pass ran and said so.
    saved = read_state(surveys_dir(state_dir) / seen["survey"])
    assert saved is not None and saved.state == "failed" and saved.passes_cut == 0
    assert "no MAVLink packet was recorded" in str(saved.reason)
    assert not (state_dir / "control.sock").exists()  # the control socket went with it
