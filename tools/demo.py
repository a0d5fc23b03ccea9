"""The whole system on one machine, on loopback (what ``seamap demo`` and ``make demo`` run).

1. The simulator makes a survey (the paper's quadrat site by default).
2. The sonar and autopilot emulators play it on 127.0.0.1 on one clock
   (``tools.emulators.playback``); the real daemon (``seamap run``, a child process) records
   and maps it live and publishes on zenoh (``tcp/127.0.0.1:7447`` unless told otherwise,
   vehicle ``demo``); the shore station (``seamap shore``, another child) follows it.
3. At the end of the playback a survey stop request goes over zenoh, as the shore would
   send it; the daemon's survey-end pass writes the result folder and publishes the final
   tiles; the shore's mosaic is compared with the daemon's.
4. Accuracy against the simulator's truth: the truth's ping times are moved to the
   times the daemon stamped on receipt (matched by ping id), and the recorded survey is
   scored by replaying it — the same computation as the daemon's survey-end pass.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio

from daemon.control import request
from drivers.oculus.logfile import iter_pings
from seamap.config import SiteConfig, ZenohConfig, config_from_dict, dump_config, load_config
from seamap.errors import SeamapError
from seamap.zenoh_io import control_key, open_session
from tools.emulators.playback import SurveyPlayback
from tools.sim import simulate

VEHICLE = "demo"
SEAMAP = str(Path(sys.executable).parent / "seamap")
SHORE_WAIT_S = 30.0
"""How long the shore may take to hold the final tiles and rewrite its mosaic (it writes
every 5 s)."""


@dataclass(frozen=True)
class DemoOptions:
    out: Path
    scenario: str = "quadrats"
    seed: int = 1
    zenoh_listen: str = "tcp/127.0.0.1:7447"
    max_pings: int | None = None
    secure: bool = False
    """Run the link on a set ``seamap security init`` makes (TLS with certificates on both
    sides, the shore's password, the boat's access rules), on the same port."""


@dataclass(frozen=True)
class _Link:
    """The daemon's [zenoh] table and the shore's (a plain loopback one, or the set's)."""

    boat: ZenohConfig
    shore: ZenohConfig
    shore_config: Path | None
    """A site file holding the shore's [zenoh] (secure), else None (``--connect``)."""


def _link(options: DemoOptions) -> _Link:
    listen = options.zenoh_listen
    connect = _connect_of(listen)
    if not options.secure:
        return _Link(
            ZenohConfig(mode="peer", listen=[listen], connect=[]),
            ZenohConfig(mode="client", listen=[], connect=[connect]),
            None,
        )
    from seamap.security import init_security

    port = int(listen.rsplit(":", 1)[1])
    made = init_security(options.out / "security", VEHICLE, ["localhost", "127.0.0.1"], 1,
                         port=port)  # fmt: skip
    boat = ZenohConfig(
        mode="peer", listen=[f"tls/127.0.0.1:{port}"], connect=[],
        config_file=str((made.boat / "boat.json5").resolve()),
    )  # fmt: skip
    folder = made.shores[0]
    shore = ZenohConfig(
        mode="peer", listen=[], connect=[f"tls/127.0.0.1:{port}"],
        config_file=str((folder / f"{folder.name}.json5").resolve()),
    )  # fmt: skip
    shore_site = options.out / "shore-site.toml"
    shore_site.write_text(dump_config(SiteConfig(zenoh=shore)))
    return _Link(boat, shore, shore_site)


def _free_port(kind: int) -> int:
    import socket

    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _step(n: int, text: str) -> None:
    print(f"[{n}/5] {text}", flush=True)


def run_demo(options: DemoOptions) -> int:
    """Run the demo; 0 on success. SeamapError for what the user can fix (a busy port...)."""
    out = options.out
    sim = out / "sim"
    _step(1, f"simulating the '{options.scenario}' survey (seed {options.seed}) into {sim}")
    started = time.monotonic()
    summary = simulate(options.scenario, options.seed, sim, max_pings=options.max_pings)
    print(summary.describe())
    print(f"      done in {time.monotonic() - started:.1f} s", flush=True)
    return asyncio.run(_live(options, sim))


async def _live(options: DemoOptions, sim: Path) -> int:
    out = options.out
    state_dir = out / "boat"
    shore_dir = out / "shore"
    mavlink_port = _free_port(2)  # SOCK_DGRAM
    link = _link(options)
    async with SurveyPlayback(
        sim / "sonar.oculus", sim / "nav.tlog", mavlink="udp", mavlink_target_port=mavlink_port
    ) as play:
        config = _daemon_config(sim, out / "site.toml", state_dir, play.sonar.tcp_port,
                                mavlink_port, link.boat)  # fmt: skip
        _step(2, "starting the emulators, the boat daemon and the shore station on 127.0.0.1")
        print(f"      sonar emulator tcp/127.0.0.1:{play.sonar.tcp_port}, autopilot emulator "
              f"-> udp/127.0.0.1:{mavlink_port}, zenoh {link.boat.listen[0]}"
              + (f" (secured by {out / 'security'})" if options.secure else ""))  # fmt: skip
        print(f"      daemon: seamap run --config {config} (log {out / 'daemon.log'})")
        daemon = await _spawn([SEAMAP, "run", "--config", str(config)], out / "daemon.log")
        reach = (
            ["--config", str(link.shore_config)] if link.shore_config is not None
            else ["--connect", link.shore.connect[0]]
        )  # fmt: skip
        shore = await _spawn(
            [SEAMAP, "shore", *reach, "--vehicle", VEHICLE, "--out", str(shore_dir)],
            out / "shore.log",
        )  # fmt: skip
        print(f"      shore:  seamap shore --vehicle {VEHICLE} --out {shore_dir} "
              f"(log {out / 'shore.log'})", flush=True)  # fmt: skip
        try:
            await asyncio.wait_for(play.started.wait(), 60)
            _step(3, f"surveying: {play.pings_total} pings, about {play.pings_total / 10:.0f} s")
            status = await _follow(play, state_dir, daemon)
            _step(4, "survey end: a stop request over zenoh; the survey-end pass maps it again")
            survey = await asyncio.to_thread(_stop_survey, link.shore)
            folder = state_dir / "surveys" / survey
            final = await _wait_done(folder, daemon)
            shore_tif = shore_dir / VEHICLE / survey / "mosaic.tif"
            same = await _wait_shore(shore_tif, folder / "mosaic.tif", SHORE_WAIT_S)
        finally:
            for child in (shore, daemon):
                if child.returncode is None:
                    child.send_signal(signal.SIGTERM)
            codes = [await asyncio.wait_for(c.wait(), 120) for c in (shore, daemon)]
    result = final["result"]
    live = status["frames"]["mapped"] if status else "?"
    print(f"      {result['frames_mapped']} of {result['frames_read']} frames mapped "
          f"({live} live), survey-end pass {result['seconds']:.1f} s")  # fmt: skip
    print(f"      result folder: {folder} (mosaic.tif, mosaic.png, trajectory.csv, report.json)")
    _tell_shore(shore_tif, same)
    _step(5, "accuracy against the simulator's truth")
    _accuracy(sim, folder, load_config(config), out / "accuracy")
    print(f"demo output in {out.resolve()} (daemon exit {codes[1]}, shore exit {codes[0]})")
    return 0 if codes == [0, 0] else 1


def _connect_of(listen: str) -> str:
    return listen.replace("0.0.0.0", "127.0.0.1")


def _daemon_config(
    sim: Path, path: Path, state_dir: Path, sonar_port: int, mavlink_port: int,
    zenoh_table: ZenohConfig,
) -> Path:  # fmt: skip
    import tomllib

    data: dict[str, Any] = tomllib.loads((sim / "site.toml").read_text())
    data.setdefault("daemon", {}).update(
        vehicle=VEHICLE, state_dir=str(state_dir), survey_autostart=True, health_interval_s=10.0
    )
    data.setdefault("sonar", {}).update(address="127.0.0.1", tcp_port=sonar_port)
    data.setdefault("mavlink", {}).update(url=f"udpin:127.0.0.1:{mavlink_port}")
    data["zenoh"] = dataclasses.asdict(zenoh_table)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_config(config_from_dict(data)))
    return path


async def _spawn(argv: list[str], log: Path) -> asyncio.subprocess.Process:
    with open(log, "ab") as stream:
        return await asyncio.create_subprocess_exec(
            *argv, stdout=stream, stderr=stream, env={**os.environ, "PYTHONUNBUFFERED": "1"}
        )


async def _status(state_dir: Path) -> dict[str, Any] | None:
    try:
        reply = await asyncio.to_thread(request, state_dir / "control.sock", "status", 5.0)
    except SeamapError:
        return None
    status: dict[str, Any] | None = reply.get("status")
    return status


async def _follow(
    play: SurveyPlayback, state_dir: Path, daemon: asyncio.subprocess.Process
) -> dict[str, Any]:
    """Progress every 5 s until the playback ends; the daemon's last status."""
    status: dict[str, Any] = {}
    started = time.monotonic()
    while not play.done.is_set():
        await asyncio.wait({asyncio.create_task(play.done.wait())}, timeout=5.0)
        if daemon.returncode is not None:
            raise SeamapError(f"the daemon stopped (exit {daemon.returncode}); see daemon.log")
        status = await _status(state_dir) or status
        if status:
            frames, links = status["frames"], status["links"]
            print(
                f"      {time.monotonic() - started:5.0f} s  pings sent "
                f"{play.sonar.pings_sent}/{play.pings_total}  daemon: {frames['mapped']} mapped, "
                f"{frames['rejected']} rejected, {frames['skipped']} skipped, lag "
                f"{status['lag_s']:.2f} s, tiles published {status.get('tiles_published', 0)}, "
                f"sonar {'up' if links['sonar']['up'] else 'down'}, autopilot "
                f"{'up' if links['mavlink']['up'] else 'down'}",
                flush=True,
            )
    # The last pings leave the reorder window; the recorder flushes.
    await asyncio.sleep(1.5)
    return await _status(state_dir) or status


def _stop_survey(shore: ZenohConfig) -> str:
    session = open_session(shore)
    try:
        replies = list(
            session.get(control_key(VEHICLE), payload=b'{"action": "stop"}', timeout=10.0)
        )
    finally:
        session.close()
    for reply in replies:
        if reply.ok is not None:
            answer = json.loads(reply.ok.payload.to_bytes())
            if answer.get("ok") and answer.get("survey"):
                return str(answer["survey"])
    raise SeamapError("the daemon did not answer the survey stop request over zenoh")


async def _wait_done(folder: Path, daemon: asyncio.subprocess.Process) -> dict[str, Any]:
    while True:
        state: dict[str, Any] = json.loads((folder / "survey.json").read_text())
        if state["state"] == "done":
            return state
        if state["state"] == "failed":
            raise SeamapError(f"the survey-end pass failed: {state['reason']}")
        if daemon.returncode is not None:
            raise SeamapError(f"the daemon stopped (exit {daemon.returncode}); see daemon.log")
        await asyncio.sleep(0.5)


async def _wait_shore(shore_tif: Path, boat_tif: Path, timeout_s: float) -> bool:
    """Whether the shore's mosaic becomes the daemon's within ``timeout_s``: the final
    tiles cross zenoh and the shore rewrites its files at its own cadence."""
    deadline = time.monotonic() + timeout_s
    while True:
        if await asyncio.to_thread(_same_mosaic, shore_tif, boat_tif):
            return True
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(0.5)


def _same_mosaic(shore_tif: Path, boat_tif: Path) -> bool:
    try:
        with rasterio.open(shore_tif) as a, rasterio.open(boat_tif) as b:
            same_grid = a.transform == b.transform and a.shape == b.shape and a.crs == b.crs
            return same_grid and bool(np.array_equal(a.read(1), b.read(1)))
    except rasterio.RasterioIOError:  # not written yet
        return False


def _tell_shore(shore_tif: Path, same: bool) -> None:
    if not shore_tif.is_file():
        print(f"      shore mosaic: not written ({shore_tif} missing; see shore.log)")
        return
    verdict = "identical to the daemon's" if same else "DIFFERS from the daemon's"
    print(f"      shore mosaic: {shore_tif} ({verdict})")


def _accuracy(sim: Path, folder: Path, config: Any, out: Path) -> None:
    from seamap.replay import replay_survey

    truth = json.loads((sim / "truth.json").read_text())
    stamped = {p.ping_id: p.time for seg in sorted(folder.glob("sonar-*.oculus"))
               for p in iter_pings(seg)}  # fmt: skip
    pings = [dict(p, time=stamped[p["ping_id"]]) for p in truth["pings"] if p["ping_id"] in stamped]
    retimed = out / "truth-as-received.json"
    out.mkdir(parents=True, exist_ok=True)
    retimed.write_text(json.dumps(dict(truth, pings=pings)))
    report = replay_survey(folder, config, out, truth=retimed)
    accuracy = report["accuracy"]
    trajectory, spacing = accuracy["trajectory"], accuracy.get("quadrat_spacing")
    print(f"      trajectory error {trajectory['rmse']:.2f} m (GPS-limited), "
          f"{trajectory['aligned_rmse']:.3f} m in shape")  # fmt: skip
    if spacing and spacing.get("located") and math.isfinite(spacing["rmse"]):
        print(f"      quadrat spacing RMSE {spacing['rmse'] * 100:.1f} cm over "
              f"{int(spacing['located'])} quadrats")  # fmt: skip
