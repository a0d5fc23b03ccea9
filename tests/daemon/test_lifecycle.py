"""The daemon's survey lifecycle and its bad inputs, with the real ``seamap run`` and
``seamap ctl``: surveys opened and closed on command, an interrupted survey-end pass run
again at start-up, and one-line errors for a bad config or an unusable state folder."""

from __future__ import annotations

import asyncio
import json
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from daemon.config import config_from_dict, dump_config
from daemon.survey import SurveyState, write_state
from drivers.oculus.logfile import OculusLogWriter
from tests.daemon.harness import SEAMAP, DaemonProcess, free_udp_port, zenoh_table
from tests.ports import free_tcp_port as closed_tcp_port
from tools.sim import simulate


def config_file(tmp_path: Path, **daemon: object) -> Path:
    """A daemon whose sonar and autopilot are nowhere to be found (nothing listens)."""
    data = {
        "daemon": {"state_dir": str(tmp_path / "state"), **daemon},
        "sonar": {"address": "127.0.0.1", "tcp_port": closed_tcp_port()},
        "mavlink": {"url": f"udpin:127.0.0.1:{free_udp_port()}"},
        "zenoh": zenoh_table(),
    }
    path = tmp_path / "site.toml"
    path.write_text(dump_config(config_from_dict(data)))
    return path


def ctl(config: Path, action: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [SEAMAP, "ctl", action, "--config", str(config)], capture_output=True, text=True,
        timeout=30,
    )  # fmt: skip


def wait_for(check: object, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():  # type: ignore[operator]
            return
        time.sleep(0.1)
    raise AssertionError("timed out")


def test_surveys_open_and_close_on_command(tmp_path: Path) -> None:
    config = config_file(tmp_path)
    state_dir = tmp_path / "state"

    async def main() -> tuple[int, str]:
        daemon = DaemonProcess(config, state_dir, tmp_path / "daemon.log")
        await daemon.start()
        await asyncio.to_thread(wait_for, lambda: (state_dir / "control.sock").exists(), 30)
        status = await asyncio.to_thread(ctl, config, "status")
        assert status.returncode == 0, status.stderr
        assert json.loads(status.stdout)["survey"] is None  # no autostart

        started = await asyncio.to_thread(ctl, config, "start")
        survey_id = started.stdout.strip()
        again = await asyncio.to_thread(ctl, config, "start")
        assert again.stdout.strip() == survey_id  # one survey at a time
        folder = state_dir / "surveys" / survey_id
        assert (folder / "sonar-001.oculus").is_file() and (folder / "nav-001.tlog").is_file()
        assert json.loads((folder / "survey.json").read_text())["state"] == "recording"
        status = await asyncio.to_thread(ctl, config, "status")
        snapshot = json.loads(status.stdout)
        assert snapshot["survey"] == survey_id
        assert snapshot["links"]["sonar"]["up"] is False
        assert snapshot["links"]["mavlink"]["up"] is False

        stopped = await asyncio.to_thread(ctl, config, "stop")
        assert stopped.stdout.strip() == survey_id

        def ended() -> bool:
            return json.loads((folder / "survey.json").read_text())["state"] == "failed"

        await asyncio.to_thread(wait_for, ended, 30)
        nothing = await asyncio.to_thread(ctl, config, "stop")
        assert nothing.stdout.strip() == "no survey was open"
        code = await daemon.stop(signal.SIGTERM, 60)
        return code, daemon.log()

    code, log = asyncio.run(main())
    assert code == 0 and "Traceback" not in log
    (folder,) = (state_dir / "surveys").iterdir()
    state = json.loads((folder / "survey.json").read_text())
    # Nothing was heard, so nothing can be mapped: said in one line, recordings kept.
    assert "no MAVLink packet was recorded" in state["reason"]
    assert "survey-end pass failed" in log
    assert (folder / "sonar-001.oculus").is_file()
    gone = ctl(config, "status")
    assert gone.returncode == 2 and gone.stderr.count("\n") == 1


def _recorded_survey(tmp_path: Path, pings: int) -> tuple[Path, Path]:
    """A simulated survey's logs as a recorded survey folder's first segment: the folder
    and the simulation's folder."""
    sim = tmp_path / "sim"
    simulate("quadrats", 2, sim, max_pings=pings)
    folder = tmp_path / "state" / "surveys" / "20260101-000000"
    folder.mkdir(parents=True)
    shutil.copy(sim / "sonar.oculus", folder / "sonar-001.oculus")
    shutil.copy(sim / "nav.tlog", folder / "nav-001.tlog")
    return folder, sim


def test_an_interrupted_survey_end_pass_runs_again_at_start(tmp_path: Path) -> None:
    folder, _ = _recorded_survey(tmp_path, 30)
    config = config_file(tmp_path)
    # A second run that died at once: its segments hold nothing and are left out.
    OculusLogWriter(folder / "sonar-002.oculus").close()
    (folder / "nav-002.tlog").touch()
    # One pass was cut by a crash already: one more may run.
    write_state(
        folder, SurveyState(folder.name, "boat1", state="finishing", started=1.0, passes_cut=1)
    )

    async def main() -> tuple[int, str]:
        daemon = DaemonProcess(config, tmp_path / "state", tmp_path / "daemon.log")
        await daemon.start()

        def done() -> bool:
            return json.loads((folder / "survey.json").read_text())["state"] == "done"

        await asyncio.to_thread(wait_for, done, 120)
        code = await daemon.stop(signal.SIGTERM, 60)
        return code, daemon.log()

    code, log = asyncio.run(main())
    assert code == 0, log
    assert "rerunning an interrupted survey-end pass" in log
    files = [
        "mosaic.tif", "mosaic.png", "trajectory.csv", "coverage.tif", "coverage.png",
        "survey.gpkg",
    ]  # fmt: skip
    for name in files:
        assert (folder / name).is_file()
    assert json.loads((folder / "survey.json").read_text())["result"]["files"] == [
        *files,
        "report.json",
    ]
    # It was not resumed as a recording: no new segment.
    assert not (folder / "sonar-003.oculus").exists()
    report = json.loads((folder / "report.json").read_text())
    assert [Path(p).name for p in report["inputs"]["sonar"]] == ["sonar-001.oculus"]
    # The crash before counts; this pass, which ended, does not.
    assert json.loads((folder / "survey.json").read_text())["passes_cut"] == 1


def test_a_pass_that_kept_killing_the_daemon_is_given_up(tmp_path: Path) -> None:
    """A survey-end pass cut twice by the daemon's death (the kernel's out-of-memory
    killer, say) is not rerun at every start: the survey fails with the reason, in one
    line, and its recordings stay as they are."""
    folder, sim = _recorded_survey(tmp_path, 10)
    config = config_file(tmp_path)
    write_state(
        folder,
        SurveyState(folder.name, "boat1", state="finishing", started=1.0, passes_cut=2),
    )

    async def main() -> tuple[int, str]:
        daemon = DaemonProcess(config, tmp_path / "state", tmp_path / "daemon.log")
        await daemon.start()
        await daemon.wait_status(lambda s: True, 30)
        code = await daemon.stop(signal.SIGTERM, 60)
        return code, daemon.log()

    code, log = asyncio.run(main())
    assert code == 0, log
    state = json.loads((folder / "survey.json").read_text())
    assert state["state"] == "failed"
    assert "cut 2 times" in state["reason"] and "seamap replay --survey" in state["reason"]
    assert "survey-end pass given up" in log and "rerunning" not in log
    assert not (folder / "mosaic.tif").exists()
    assert (folder / "sonar-001.oculus").read_bytes() == (sim / "sonar.oculus").read_bytes()


@pytest.mark.parametrize(
    ("table", "expected"),
    [
        ("[daemon]\nsurvey_autostrat = true\n", "unknown key 'survey_autostrat' in [daemon]"),
        ("[sonar]\nping_rate_hz = 12\n", "ping_rate_hz = 12 is not one of 2, 5, 10, 15, 40"),
        ("[daemon]\nmax_backlog_frames = 0\n", "max_backlog_frames = 0 is outside 1..10000"),
        (
            '[zenoh]\nlisten = ["tcp/0.0.0.0"]\n',
            "[zenoh] listen = 'tcp/0.0.0.0' is not a zenoh endpoint",
        ),
    ],
)
def test_bad_config_is_one_line(tmp_path: Path, table: str, expected: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(table)
    done = subprocess.run(
        [SEAMAP, "run", "--config", str(path)], capture_output=True, text=True, timeout=30
    )
    assert done.returncode == 2
    assert expected in done.stderr and done.stderr.count("\n") == 1, done.stderr


def test_unusable_state_folder_is_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    config = config_file(tmp_path)
    text = config.read_text().replace(str(tmp_path / "state"), str(blocker / "state"))
    config.write_text(text)
    done = subprocess.run(
        [SEAMAP, "run", "--config", str(config)], capture_output=True, text=True, timeout=30
    )
    assert done.returncode == 2
    assert "cannot create the state folder" in done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
