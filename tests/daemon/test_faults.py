"""Faults during a live survey, one after another, against the real daemon on loopback with
the autopilot on a pseudo-terminal: the sonar drops the connection; garbage bytes on both
links; GPS stops for a minute; the serial device disappears and returns; the daemon is
killed (SIGKILL) and started again. Each is survived, shows in the daemon's health (status
and log), and loses no recorded data: outside the moments a link was really down, the
recorded sonar and navigation streams have no holes, and the survey-end pass maps both
segments."""

from __future__ import annotations

import asyncio
import itertools
import json
import signal
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from drivers.mavlink.framing import open_log, scan_tlog
from drivers.mavlink.navlog import NavReadReport
from drivers.oculus.logfile import LogReadReport, iter_pings
from tests.daemon.harness import DaemonProcess, DaemonRun, write_config
from tools.emulators.playback import SurveyPlayback
from tools.sim import simulate

PING_RATE_HZ = 5.0  # the field day's sonar
PINGS = 550  # 110 s of survey; the faults' times below are seconds into it
SONAR_DROP_AT = 8.0
GARBAGE_AT = 12.0
GPS_PAUSE = (16.0, 60.0)  # from, for how long
SERIAL_GONE = (30.0, 4.0)
KILL_AT, RESTART_AFTER = 80.0, 2.0


@dataclass
class Outcome(DaemonRun):
    outages: dict[str, tuple[float, float]] = field(default_factory=dict)
    """What was really down, UNIX s (from, to) on the receive clock."""
    pings_sent: int = 0
    ping_times: dict[int, float] = field(default_factory=dict)
    """Each played ping's id and when it was due on the receive clock (UNIX s)."""
    started: float = 0.0


@pytest.fixture(scope="module")
def outcome(tmp_path_factory: pytest.TempPathFactory) -> Outcome:
    root = tmp_path_factory.mktemp("faults")
    sim = root / "sim"
    simulate("farm", 21, sim, max_pings=PINGS, ping_rate_hz=PING_RATE_HZ)
    state_dir = root / "state"
    log_path = root / "daemon.log"

    async def at(play: SurveyPlayback, seconds: float) -> None:
        assert play.clock.origin is not None
        await asyncio.sleep(max(0.0, play.clock.origin[1] + seconds - time.monotonic()))

    async def main() -> Outcome:
        async with SurveyPlayback(sim / "sonar.oculus", sim / "nav.tlog", mavlink="pty") as play:
            assert play.autopilot.device_path is not None
            # The faults are the point, not the map: a coarser mosaic and no loop closures
            # make the live map and the survey-end pass cheaper, both still run.
            config = write_config(
                sim, root / "site.toml", state_dir, play.sonar.tcp_port,
                str(play.autopilot.device_path), max_backlog_frames=50,
                mapping={"mosaic_res_m": 0.05, "loop_closures": False},
            )  # fmt: skip
            first = DaemonProcess(config, state_dir, log_path)
            await first.start()
            await asyncio.wait_for(play.started.wait(), 60)
            assert play.clock.origin is not None
            sim_t0, wall_t0 = play.clock.origin
            unix_t0 = time.time() - (time.monotonic() - wall_t0)
            ping_times = {
                p.ping_id: unix_t0 + p.time - sim_t0
                for p in itertools.islice(iter_pings(sim / "sonar.oculus"), PINGS)
            }
            outages: dict[str, tuple[float, float]] = {}

            await at(play, SONAR_DROP_AT)
            play.sonar.drop_connection()
            dropped = time.time()
            await first.wait_status(lambda s: s["links"]["sonar"]["reconnects"] >= 1, 20)
            await first.wait_status(
                lambda s: (s["links"]["sonar"]["last_ping_age_s"] or 9) < 0.5, 20
            )
            outages["sonar_drop"] = (dropped, time.time())

            await at(play, GARBAGE_AT)
            play.sonar.inject_garbage(20_000)
            play.autopilot.inject_garbage(5_000)

            await at(play, GPS_PAUSE[0])
            outages["gps"] = play.autopilot.pause_gps(GPS_PAUSE[1])

            await at(play, SERIAL_GONE[0])
            gone = time.time()
            play.autopilot.stop()
            await asyncio.sleep(SERIAL_GONE[1])
            play.autopilot.restart()
            await first.wait_status(lambda s: s["links"]["mavlink"]["up"], 30)
            outages["serial"] = (gone, time.time())

            await at(play, KILL_AT)
            killed = time.time()
            statuses = list(first.statuses)
            await first.stop(signal.SIGKILL, 10)
            await asyncio.sleep(RESTART_AFTER)
            second = DaemonProcess(config, state_dir, log_path)
            await second.start()
            await second.wait_status(
                lambda s: s["links"]["sonar"]["up"] and s["links"]["mavlink"]["up"], 60
            )
            outages["killed"] = (killed, time.time())

            await asyncio.wait_for(play.done.wait(), PINGS / PING_RATE_HZ + 60)
            await second.wait_status(lambda s: s["frames"]["backlog"] == 0, 30)
            await asyncio.sleep(1.5)
            code = await second.stop(signal.SIGTERM, 600)
            (survey,) = (state_dir / "surveys").iterdir()
            return Outcome(
                survey, code, log_path.read_text(), statuses + second.statuses, outages,
                play.sonar.pings_sent, ping_times, unix_t0,
            )  # fmt: skip

    return asyncio.run(main())


def _fresh_ping(status: dict[str, Any], age_s: float) -> bool:
    age = status["links"]["sonar"].get("last_ping_age_s")
    return age is not None and age < age_s


def _inside(t: float, windows: list[tuple[float, float]], slack: float = 1.5) -> bool:
    return any(a - slack <= t <= b + slack for a, b in windows)


def _holes(times: np.ndarray, longest: float) -> list[tuple[float, float]]:
    gaps = np.flatnonzero(np.diff(times) > longest)
    return [(float(times[i]), float(times[i + 1])) for i in gaps]


def test_daemon_survived_and_ended_the_survey(outcome: Outcome) -> None:
    assert outcome.exit_code == 0, outcome.log[-3000:]
    assert "Traceback" not in outcome.log
    state = json.loads((outcome.survey / "survey.json").read_text())
    assert state["state"] == "done", state
    assert state["segments"] == 2
    assert "survey resumed" in outcome.log  # after the SIGKILL, into segment 2
    assert sorted(p.name for p in outcome.survey.glob("*-00?.*[gs]")) == [
        "nav-001.tlog", "nav-002.tlog", "sonar-001.oculus", "sonar-002.oculus",
    ]  # fmt: skip
    assert state["result"]["frames_read"] >= 0.9 * outcome.pings_sent


def test_sonar_drop_and_garbage_are_reported_and_lose_no_pings(outcome: Outcome) -> None:
    first = [s for s in outcome.statuses if s["links"]["sonar"].get("reconnects") is not None]
    assert max(s["links"]["sonar"]["reconnects"] for s in first) >= 1
    assert max(s["links"]["sonar"]["bytes_skipped"] for s in first) >= 10_000
    report = LogReadReport()
    recorded = [
        p.ping_id for seg in ("sonar-001.oculus", "sonar-002.oculus")
        for p in iter_pings(outcome.survey / seg, report)
    ]  # fmt: skip
    assert report.corrupt_pings == 0
    assert recorded == sorted(set(recorded))  # in order, none twice
    # Every ping the sonar sent was recorded, but for what it sent in the last second
    # before the SIGKILL (the recorder's buffer).
    assert outcome.pings_sent - len(recorded) <= 15, (outcome.pings_sent, len(recorded))
    # The pings that are missing are those of the moments the sonar was not connected.
    windows = [outcome.outages["sonar_drop"], outcome.outages["killed"]]
    missing = [t for ping_id, t in outcome.ping_times.items() if ping_id not in set(recorded)]
    assert all(_inside(t, windows) for t in missing), [t - outcome.started for t in missing]


def test_gps_minute_and_serial_loss_are_reported_and_navigation_is_whole(
    outcome: Outcome,
) -> None:
    ages = [s["links"]["mavlink"].get("gnss_fix_age_s") or 0.0 for s in outcome.statuses]
    assert max(ages) > 55.0
    lost = outcome.log.index("warning health: no GNSS fix")
    assert "info health: GNSS fix" in outcome.log[lost:]
    assert "autopilot link down" in outcome.log and "autopilot link up" in outcome.log
    reopened = [s["links"]["mavlink"]["reopens"] for s in outcome.statuses]
    assert max(reopened) >= 1
    assert max(s["links"]["mavlink"]["bad_bytes"] for s in outcome.statuses) > 0
    imu, gps = [], []
    for segment in ("nav-001.tlog", "nav-002.tlog"):
        report = NavReadReport(segment, "tlog")
        with open_log(outcome.survey / segment) as (_, buf):
            for stamp, msg in scan_tlog(buf, report):
                kind = msg.get_type()
                if kind == "RAW_IMU":
                    imu.append(stamp)
                elif kind == "GPS_RAW_INT":
                    gps.append(stamp)
    windows = [outcome.outages["serial"], outcome.outages["killed"]]
    holes = _holes(np.array(imu), 0.5)
    assert all(_inside(a, windows) and _inside(b, windows) for a, b in holes), holes
    gps_from, gps_to = outcome.outages["gps"]
    gps_holes = _holes(np.array(gps), 2.0)
    assert any(a <= gps_from + 1 and b >= gps_to - 1 for a, b in gps_holes), gps_holes
    assert all(_inside(a, [*windows, (gps_from, gps_to)]) for a, _ in gps_holes), gps_holes
