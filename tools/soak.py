"""``make soak`` (``python -m tools.soak``): the real daemon for hours.

A simulated survey (the two-hour ``hectare`` by default) is written once to files and
played through the sonar and autopilot emulators on 127.0.0.1 to ``seamap run``, faster
than real time (``--speed``: the playback clock runs that many survey seconds a wall
second; the daemon stamps what it receives, so its map is of a boat that went that much
faster, which is not what is measured here). Every ``--sample-s`` the daemon's resident
memory, open file descriptors and threads are read from ``/proc``, with its status
(frames received, mapped, skipped, backlog). At the end of the playback the survey is
stopped (SIGTERM) and the sampling goes on through the survey-end pass until the daemon
exits. Checked and reported:

- the curves, and their growth over the second half of the playback (a straight line
  fitted: MB, descriptors and threads per hour);
- every ping the emulator sent is in the survey's recording;
- the survey-end pass done (``survey.json`` "done", the result folder written), its time;
- the daemon's exit code and any traceback in its log.

Writes ``soak.json`` and ``soak.png`` in ``--out``. Not a test (hours); bounded: it stops
by itself (``--timeout-h``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
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
from drivers.errors import SeamapError
from drivers.oculus.logfile import iter_pings
from tools.demo import SEAMAP, _daemon_config, _free_port, _status
from tools.emulators.playback import SurveyPlayback
from tools.sim import simulate
from tools.sim.scenarios import STREAM_ONLY

# Longer than any survey: the mission's end is the cut (s).
WHOLE_SURVEY_S = 24 * 3600.0


def proc_sample(pid: int) -> dict[str, float] | None:
    """Resident memory (MB), open descriptors and threads of process ``pid`` (None when
    it is gone)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    rss_kb = float(fields.get("VmRSS", "0 kB").split()[0])
    return {"rss_mb": rss_kb / 1024.0, "fds": float(fds), "threads": float(fields["Threads"])}


def growth_per_hour(times: list[float], values: list[float]) -> float:
    """Slope of a straight line fitted to the second half of the curve, per hour."""
    n = len(times)
    if n < 4:
        return float("nan")
    t = np.asarray(times[n // 2 :], float)
    v = np.asarray(values[n // 2 :], float)
    if np.ptp(t) <= 0:
        return float("nan")
    return float(np.polyfit(t / 3600.0, v, 1)[0])


def _plot(samples: list[dict[str, Any]], played_s: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    t = np.array([s["t"] for s in samples]) / 60.0
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for ax, key, label in zip(
        axes,
        ("rss_mb", "fds", "threads"),
        ("resident memory (MB)", "open file descriptors", "threads"),
        strict=True,
    ):
        ax.plot(t, [s[key] for s in samples], lw=1.0)
        ax.axvline(played_s / 60.0, color="grey", ls="--", lw=0.8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("minutes (dashed: the playback ends, the survey-end pass begins)")
    fig.suptitle("seamap run: soak")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


async def _run(args: argparse.Namespace) -> dict[str, Any]:
    out: Path = args.out
    sim = out / "sim"
    if not (sim / "truth.json").exists():
        print(f"simulating {args.scenario} seed {args.seed} into {sim}", flush=True)
        overrides: dict[str, Any] = {}
        if args.minutes is not None:
            overrides["duration_s"] = 60.0 * args.minutes
        elif args.scenario in STREAM_ONLY:
            # The whole survey: simulate refuses a stream-only one without a cut, and the
            # mission's end cuts it anyway (about 18 GB for the hectare).
            overrides["duration_s"] = WHOLE_SURVEY_S
        summary = simulate(args.scenario, args.seed, sim, **overrides)
        print(summary.describe(), flush=True)
    state_dir = out / "boat"
    mavlink_port = _free_port(socket.SOCK_DGRAM)
    zenoh_port = _free_port(socket.SOCK_STREAM)
    samples: list[dict[str, Any]] = []
    deadline = time.monotonic() + 3600.0 * args.timeout_h
    async with SurveyPlayback(
        sim / "sonar.oculus", sim / "nav.tlog", mavlink="udp",
        mavlink_target_port=mavlink_port, speed=args.speed,
    ) as play:  # fmt: skip
        config = _daemon_config(
            sim, out / "site.toml", state_dir, play.sonar.tcp_port, mavlink_port,
            ZenohConfig(mode="peer", listen=[f"tcp/127.0.0.1:{zenoh_port}"], connect=[]),
        )  # fmt: skip
        with open(out / "daemon.log", "ab") as log:
            daemon = await asyncio.create_subprocess_exec(
                SEAMAP, "run", "--config", str(config), stdout=log, stderr=log,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )  # fmt: skip
        started = time.monotonic()

        async def sample(phase: str) -> None:
            status = await _status(state_dir)
            proc = proc_sample(daemon.pid)
            if proc is None:
                return
            frames = (status or {}).get("frames", {})
            samples.append(
                {"t": round(time.monotonic() - started, 1), "phase": phase, **proc,
                 **{k: frames.get(k) for k in ("received", "mapped", "skipped", "backlog")}}
            )  # fmt: skip
            if len(samples) % 30 == 1:
                print(json.dumps(samples[-1]), flush=True)

        try:
            await asyncio.wait_for(play.started.wait(), 300)
            print(f"playing {play.pings_total} pings at {args.speed:g}x", flush=True)
            while not play.done.is_set() and time.monotonic() < deadline:
                await sample("playing")
                await asyncio.sleep(args.sample_s)
            played_s = time.monotonic() - started
            sent = play.sonar.pings_sent
            await asyncio.sleep(5.0)  # the reorder window, the recorder's flush
            daemon.send_signal(signal.SIGTERM)
            while daemon.returncode is None and time.monotonic() < deadline:
                await sample("survey-end pass")
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(daemon.wait(), args.sample_s)
        finally:
            if daemon.returncode is None:
                daemon.kill()
                await daemon.wait()
    total_s = time.monotonic() - started
    log_text = (out / "daemon.log").read_text(errors="replace")
    surveys = sorted((state_dir / "surveys").iterdir())
    survey = surveys[-1]
    state = json.loads((survey / "survey.json").read_text())
    recorded = 0
    for segment in sorted(survey.glob("sonar-*.oculus")):
        recorded += sum(1 for _ in iter_pings(segment))
    playing = [s for s in samples if s["phase"] == "playing"]
    report: dict[str, Any] = {
        "scenario": args.scenario,
        "seed": args.seed,
        "speed": args.speed,
        "pings_sent": sent,
        "pings_recorded": recorded,
        "exit_code": daemon.returncode,
        "tracebacks": log_text.count("Traceback"),
        "survey_state": state.get("state"),
        "result_written": (survey / "mosaic.tif").exists(),
        "played_s": round(played_s, 1),
        "survey_end_pass_s": round(total_s - played_s, 1),
        "growth_per_hour_while_playing": {
            key: growth_per_hour([s["t"] for s in playing], [s[key] for s in playing])
            for key in ("rss_mb", "fds", "threads")
        },
        "peak": {
            key: max((s[key] for s in samples), default=None)
            for key in ("rss_mb", "fds", "threads")
        },
        "samples": samples,
    }
    (out / "soak.json").write_text(json.dumps(report, indent=1))
    if samples:
        _plot(samples, played_s, out / "soak.png")
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.soak", description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("soak-out"))
    parser.add_argument("--scenario", default="hectare")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--minutes", type=float, default=None,
        help="survey length to simulate (default: the whole survey)",
    )  # fmt: skip
    parser.add_argument("--speed", type=float, default=4.0)
    parser.add_argument("--sample-s", type=float, default=10.0)
    parser.add_argument("--timeout-h", type=float, default=8.0)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        report = asyncio.run(_run(args))
    except (SeamapError, OSError, ValueError) as exc:
        print(f"soak: {exc}", file=sys.stderr)
        return 1
    summary = {k: v for k, v in report.items() if k != "samples"}
    print(json.dumps(summary, indent=1))
    ok = (
        report["exit_code"] == 0
        and report["tracebacks"] == 0
        and report["pings_recorded"] >= report["pings_sent"]
        and report["survey_state"] == "done"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
