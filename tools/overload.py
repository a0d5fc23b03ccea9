"""``make overload`` (``python -m tools.overload``): the real daemon under overload.

A simulated survey at the sonar's fastest rate (40 Hz) is played in real time through the
emulators on 127.0.0.1 to ``seamap run``, which shares one core with a CPU hog (both
pinned to core 0): the mapping thread is starved. Measured and reported:

- frames received, mapped and skipped (the daemon's own counters), the backlog's largest
  value against ``[daemon] max_backlog_frames``;
- the recording: every ping the emulator sent is in the survey's ``sonar-001.oculus``;
- what must not be late: the control socket's status replies (latency), the poses on
  zenoh (the longest gap), the systemd watchdog (``WATCHDOG=1`` on a ``$NOTIFY_SOCKET``
  this tool listens on: the longest gap against the interval the daemon was given).

Writes ``overload.json`` in ``--out`` and prints a summary. Not a test: its figures go in
the notes (``make overload``); bounded, it stops by itself.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from daemon.config import ZenohConfig
from daemon.control import request
from drivers.errors import SeamapError
from drivers.oculus.logfile import LogReadReport, iter_pings
from drivers.zenoh_io import open_session, pose_key
from tools.demo import _daemon_config, _free_port
from tools.emulators.playback import SurveyPlayback
from tools.sim import simulate

SEAMAP = str(Path(sys.executable).parent / "seamap")
VEHICLE = "demo"
WATCHDOG_USEC = 4_000_000
"""The watchdog interval the daemon is given (it pets at half of it)."""


def _hog() -> list[str]:
    return [sys.executable, "-c", "while True: pass"]


def _pin_to_core0() -> None:
    os.sched_setaffinity(0, {0})


async def _run(out: Path, seconds: float, seed: int) -> dict[str, Any]:
    sim = out / "sim"
    print(f"simulating {seconds:.0f} s of quadrats seed {seed} at 40 Hz into {sim}", flush=True)
    summary = simulate("quadrats", seed, sim, ping_rate_hz=40.0, duration_s=seconds)
    print(summary.describe(), flush=True)
    state_dir = out / "boat"
    mavlink_port = _free_port(socket.SOCK_DGRAM)
    zenoh_port = _free_port(socket.SOCK_STREAM)
    notify_path = out / "notify.sock"
    notify_path.unlink(missing_ok=True)
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.setblocking(False)
    pets: list[float] = []
    poses: list[float] = []
    statuses: list[dict[str, Any]] = []
    latencies: list[float] = []
    async with SurveyPlayback(
        sim / "sonar.oculus", sim / "nav.tlog", mavlink="udp", mavlink_target_port=mavlink_port
    ) as play:
        listen = f"tcp/127.0.0.1:{zenoh_port}"
        config = _daemon_config(
            sim, out / "site.toml", state_dir, play.sonar.tcp_port, mavlink_port,
            ZenohConfig(mode="peer", listen=[listen], connect=[]),
        )  # fmt: skip
        text = config.read_text().replace("final_pass = true", "final_pass = false")
        config.write_text(text.replace("health_interval_s = 10.0", "health_interval_s = 1.0"))
        env = {
            **os.environ, "PYTHONUNBUFFERED": "1", "NOTIFY_SOCKET": str(notify_path),
            "WATCHDOG_USEC": str(WATCHDOG_USEC),
        }  # fmt: skip
        with open(out / "daemon.log", "ab") as log:
            daemon = await asyncio.create_subprocess_exec(
                SEAMAP, "run", "--config", str(config), stdout=log, stderr=log, env=env,
                preexec_fn=_pin_to_core0,
            )  # fmt: skip
        hog = await asyncio.create_subprocess_exec(*_hog(), preexec_fn=_pin_to_core0)
        session = await asyncio.to_thread(
            open_session, ZenohConfig(mode="peer", listen=[], connect=[listen])
        )
        subscriber = session.declare_subscriber(
            pose_key(VEHICLE), lambda _: poses.append(time.monotonic())
        )
        loop = asyncio.get_running_loop()

        def on_notify() -> None:
            try:
                while True:
                    data = notify.recv(4096)
                    if b"WATCHDOG=1" in data:
                        pets.append(time.monotonic())
            except BlockingIOError:
                return

        loop.add_reader(notify.fileno(), on_notify)
        try:
            await asyncio.wait_for(play.started.wait(), 120)
            print(f"playing {play.pings_total} pings at 40 Hz; daemon and a CPU hog on core 0",
                  flush=True)  # fmt: skip
            deadline = time.monotonic() + seconds + 60
            while not play.done.is_set() and time.monotonic() < deadline:
                started = time.monotonic()
                try:
                    reply = await asyncio.to_thread(
                        request, state_dir / "control.sock", "status", 5.0
                    )
                except SeamapError:
                    reply = {}
                latencies.append(time.monotonic() - started)
                if reply.get("ok"):
                    statuses.append(reply["status"])
                await asyncio.sleep(0.5)
            await asyncio.sleep(2.0)
            final = await asyncio.to_thread(request, state_dir / "control.sock", "status", 10.0)
            if final.get("ok"):
                statuses.append(final["status"])
            sent = play.sonar.pings_sent
        finally:
            loop.remove_reader(notify.fileno())
            subscriber.undeclare()
            session.close()
            hog.kill()
            await hog.wait()
            if daemon.returncode is None:
                daemon.send_signal(signal.SIGTERM)
            code = await asyncio.wait_for(daemon.wait(), 300)
            notify.close()
    (survey,) = (state_dir / "surveys").iterdir()
    report = LogReadReport()
    recorded = sum(1 for _ in iter_pings(survey / "sonar-001.oculus", report))
    last = statuses[-1] if statuses else {}
    frames = last.get("frames", {})
    backlogs = [s.get("frames", {}).get("backlog", 0) for s in statuses]
    pose_gaps = np.diff(poses) if len(poses) > 1 else np.array([np.nan])
    pet_gaps = np.diff(pets) if len(pets) > 1 else np.array([np.nan])
    return {
        "pings_sent": sent,
        "pings_recorded": recorded,
        "frames": frames,
        "backlog_max": max(backlogs, default=0),
        "lag_s_max": max((s.get("lag_s") or 0.0 for s in statuses), default=None),
        "status_latency_s": {
            "p50": float(np.percentile(latencies, 50)) if latencies else None,
            "max": max(latencies, default=None),
        },
        "poses": len(poses),
        "pose_gap_s_max": float(np.nanmax(pose_gaps)),
        "watchdog_pets": len(pets),
        "watchdog_gap_s_max": float(np.nanmax(pet_gaps)),
        "watchdog_interval_s": WATCHDOG_USEC / 1e6,
        "daemon_exit": code,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("overload-out"))
    parser.add_argument("--seconds", type=float, default=60.0, help="survey length (s)")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if len(os.sched_getaffinity(0)) < 2:
        print("overload: needs two cores (the hog and the daemon share core 0)", file=sys.stderr)
        return 2
    result = asyncio.run(_run(args.out, args.seconds, args.seed))
    (args.out / "overload.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
