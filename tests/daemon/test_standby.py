"""The sonar rests between surveys (issue 13, 7): the real daemon puts the emulated M1200d
in standby while no survey is open, watches it through its status, fires it when a
survey opens and stands it by again when the survey ends."""

from __future__ import annotations

import asyncio
import json
import signal
from collections.abc import Callable
from pathlib import Path

from daemon.config import config_from_dict, dump_config
from tests.daemon.harness import DaemonProcess, free_udp_port, zenoh_table
from tests.daemon.test_lifecycle import ctl
from tests.drivers.test_oculus_link import source
from tools.emulators.sonar import SonarEmulator


async def until(check: Callable[[], bool], timeout_s: float) -> None:
    """Wait on the event loop (the emulator's state is read there) until ``check()``."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not check():
        assert loop.time() < deadline, "timed out"
        await asyncio.sleep(0.05)


def test_the_sonar_stands_by_outside_surveys(tmp_path: Path) -> None:
    status_port = free_udp_port()

    async def main() -> tuple[int, str]:
        sonar = SonarEmulator(
            source(10**6), status_to=("127.0.0.1", status_port), status_interval_s=0.5,
            fire_timeout_s=2.0, rate_hz=20.0,
        )  # fmt: skip
        async with sonar:
            data = {
                "daemon": {"state_dir": str(tmp_path / "state"), "health_interval_s": 0.5},
                "sonar": {
                    "address": "127.0.0.1",
                    "tcp_port": sonar.tcp_port,
                    "status_port": status_port,
                },
                "mavlink": {"url": f"udpin:127.0.0.1:{free_udp_port()}"},
                "zenoh": zenoh_table(),
            }
            config = tmp_path / "site.toml"
            config.write_text(dump_config(config_from_dict(data)))
            daemon = DaemonProcess(config, tmp_path / "state", tmp_path / "daemon.log")
            await daemon.start()
            try:

                def fired(pinging: bool) -> bool:
                    return sonar.last_fire is not None and sonar.pinging == pinging

                # No survey: the link fires standby, and the sonar counts as up by its status.
                await until(lambda: fired(False), 30)
                status = await daemon.wait_status(
                    lambda s: s["links"]["sonar"].get("standby") and s["links"]["sonar"]["up"], 30
                )
                sent = sonar.pings_sent
                await asyncio.sleep(1.5)
                assert sonar.pings_sent == sent, "no pings while standing by"
                started = await asyncio.to_thread(ctl, config, "start")
                assert started.returncode == 0, started.stderr
                await until(lambda: fired(True), 5)
                await daemon.wait_status(
                    lambda s: s["links"]["sonar"]["up"] and not s["links"]["sonar"]["standby"], 10
                )
                folder = tmp_path / "state" / "surveys" / started.stdout.strip()
                await until(lambda: sonar.pings_sent > sent + 10, 10)
                stopped = await asyncio.to_thread(ctl, config, "stop")
                assert stopped.returncode == 0, stopped.stderr
                await until(lambda: fired(False), 5)
                assert json.loads((folder / "survey.json").read_text())["state"] != "recording"
                assert status["links"]["sonar"]["last_status_age_s"] < 3.5
                code = await daemon.stop(signal.SIGTERM, 60)
            finally:
                await daemon.ensure_stopped()
            return code, daemon.log()

    code, log = asyncio.run(asyncio.wait_for(main(), 120))
    assert code == 0 and "Traceback" not in log, log
    assert "sonar standing by: no survey open" in log and "sonar firing: survey open" in log
