"""``seamap bench``: the streaming engine in-process over a simulated survey, measured.

The simulator renders the pings and navigation in a process of its own
(``tools.sim.stream``), as the sonar and the autopilot are other machines on the boat:
the memory measured is the engine's alone, and only the time spent inside the engine
counts. Reported: milliseconds per frame per
stage and in total, frames per second, the multiple of real time at 10 Hz, peak and
current memory (RSS), the growth of memory per thousand frames (a straight line fitted
to the second half of the run, when the working set has settled), and the latency from
a ping's arrival to the update of its tiles (survey time the engine held the ping and
waited to render, plus the time it took to process).
"""

from __future__ import annotations

import contextlib
import ctypes
import heapq
import math
import multiprocessing
import os
import queue
import signal
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from daemon.memory import return_large_blocks
from drivers.errors import SeamapError
from drivers.formats.tilespill import DiskSpill
from drivers.oculus.logfile import iter_pings
from mapping import kernels
from mapping.samples import Ping
from mapping.streaming import Sample, StreamingEngine, StreamingParams, TileUpdate

_BATCH = 64
"""Events a message from the simulator's process carries."""
_AHEAD = 16
"""Messages the simulator may run ahead of the engine (about 1,000 events)."""


def _put(out: Any, message: tuple[Any, ...]) -> None:
    """Hand a message to the engine's process; leave if that process has gone (killed)."""
    parent = multiprocessing.parent_process()
    while True:
        try:
            out.put(message, timeout=1.0)
            return
        except queue.Full:
            if parent is not None and not parent.is_alive():
                # Nobody reads the pipe any more: leave now (a normal exit would wait for
                # the queue's feeder thread, blocked on the full pipe, for ever).
                out.cancel_join_thread()
                os._exit(0)


def _simulate_into(
    out: Any, scenario: str, seed: int, overrides: dict[str, Any], record: Path | None
) -> None:
    """The simulator's process: the stream's set-up, then its events in batches, then
    "end" (or one line, if the simulator fails); ``record``: the pings also written there
    as an Oculus log, as the daemon records them (closed before "end")."""
    from drivers.oculus.logfile import OculusLogWriter
    from tools.sim.stream import survey_events

    overrides = _range_overrides(overrides)
    try:
        with contextlib.ExitStack() as stack:
            log = None if record is None else stack.enter_context(OculusLogWriter(record))
            stream = survey_events(
                scenario, seed, on_ping_message=None if log is None else log.write, **overrides
            )
            _put(out, ("setup", stream.site_config, stream.ping_count))
            batch: list[Any] = []
            for event in stream.events:
                batch.append(event)
                if len(batch) == _BATCH:
                    _put(out, ("events", batch))
                    batch = []
            _put(out, ("events", batch))
        _put(out, ("end",))
    except SeamapError as error:
        _put(out, ("error", str(error)))
    except Exception as error:  # one line to the parent, not a traceback
        _put(out, ("error", f"the simulator failed: {type(error).__name__}: {error}"))


def _range_overrides(overrides: dict[str, Any]) -> dict[str, Any]:
    """A range set on the sonar brings its range resolution (about range / 600 lines)."""
    from tools.sim.swath import range_resolution_for

    if "range_m" in overrides and "range_resolution_m" not in overrides:
        return {**overrides, "range_resolution_m": range_resolution_for(overrides["range_m"])}
    return overrides


def _simulate_folder(
    out: Any, scenario: str, seed: int, overrides: dict[str, Any], folder: Path
) -> None:
    """The simulator's process for a recorded feed: the survey's logs written to
    ``folder``, then ("done", pings) or ("error", one line). It ends with the bench's
    process, killed or not (Linux: the parent's death signals it)."""
    from tools.sim.survey import simulate

    _end_with_parent()

    try:
        summary = simulate(scenario, seed, folder, **_range_overrides(overrides))
        out.put(("done", summary.ping_count))
    except SeamapError as error:
        out.put(("error", str(error)))
    except Exception as error:  # one line to the parent, not a traceback
        out.put(("error", f"the simulator failed: {type(error).__name__}: {error}"))


def _end_with_parent() -> None:
    """Have the kernel end this process when its parent dies (Linux ``PR_SET_PDEATHSIG``;
    elsewhere nothing)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if multiprocessing.parent_process() is not None and os.getppid() == 1:
        os._exit(0)  # the parent died before the signal was asked for


class RecordedFeed:
    """A simulated survey written to its logs first, in a process of its own, then read
    back in time order as replay reads them: the simulator has finished before the engine
    is timed, and does not take the cores its workers use."""

    def __init__(self, scenario: str, seed: int, overrides: dict[str, Any], folder: Path) -> None:
        from daemon.config import load_config
        from daemon.replay import read_navigation

        context = multiprocessing.get_context("spawn")
        answer: Any = context.Queue()
        process = context.Process(
            target=_simulate_folder,
            args=(answer, scenario, seed, overrides, folder),
            name="seamap-bench-simulator",
            daemon=True,
        )
        process.start()
        message: tuple[Any, ...] | None = None
        while message is None:
            try:
                message = answer.get(timeout=1.0)
            except queue.Empty:
                if not process.is_alive():
                    raise SeamapError(
                        f"bench: the simulator's process ended (exit code {process.exitcode}) "
                        "without finishing its survey"
                    ) from None
        process.join(timeout=30.0)
        if message[0] == "error":
            raise SeamapError(message[1])
        self.ping_count: int = message[1]
        self.site_config = load_config(folder / "site.toml")
        self.recording = folder / "sonar.oculus"
        self.nav, _ = read_navigation(folder / "nav.tlog", self.site_config)

    def events(self) -> Iterator[tuple[float, Any]]:
        nav = self.nav
        samples: Iterator[Sample] = heapq.merge(
            nav.imu, nav.gnss, nav.heading, nav.attitude, nav.ranges, iter_pings(self.recording),
            key=lambda sample: sample.time,
        )  # fmt: skip
        for sample in samples:
            yield sample.time, sample


class SimulatedFeed:
    """A simulated survey's events from a process of its own (spawned: the simulator's
    world and its set-up's peak stay out of the engine's memory)."""

    def __init__(
        self, scenario: str, seed: int, overrides: dict[str, Any], record: Path | None = None
    ) -> None:
        context = multiprocessing.get_context("spawn")
        self._queue: Any = context.Queue(maxsize=_AHEAD)
        self._process = context.Process(
            target=_simulate_into,
            args=(self._queue, scenario, seed, overrides, record),
            name="seamap-bench-simulator",
            daemon=True,
        )
        self._process.start()
        message = self._next()
        if message[0] != "setup":
            self.close()
            raise SeamapError(f"bench: the simulator sent {message[0]!r} before its set-up")
        self.site_config = message[1]
        self.ping_count: int = message[2]

    def _next(self) -> tuple[Any, ...]:
        while True:
            try:
                message: tuple[Any, ...] = self._queue.get(timeout=1.0)
            except queue.Empty:
                if not self._process.is_alive():
                    raise SeamapError(
                        f"bench: the simulator's process ended (exit code "
                        f"{self._process.exitcode}) without finishing its survey"
                    ) from None
                continue
            if message[0] == "error":
                self.close()
                raise SeamapError(message[1])
            return message

    def events(self) -> Iterator[tuple[float, Any]]:
        try:
            while True:
                message = self._next()
                if message[0] == "end":
                    break
                yield from message[1]
        finally:
            self.close()

    def close(self) -> None:
        if self._process.is_alive():
            self._process.terminate()
        self._process.join(timeout=10.0)
        self._queue.close()


def reset_peak_rss() -> None:
    """Start the kernel's peak-RSS counter afresh (Linux), so the peak is the engine's
    and not the start-up's (the kernels' compile)."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as refs:
            refs.write("5")
    except OSError:
        pass


def pss_mb(pids: list[int]) -> float:
    """Proportional set size (MB) of these processes together (Linux; NaN elsewhere): the
    memory they take between them, their shared pages counted once."""
    total = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/smaps_rollup", encoding="ascii") as rollup:
                for line in rollup:
                    if line.startswith("Pss:"):
                        total += int(line.split()[1]) / 1024.0
                        break
        except OSError:
            return math.nan
    return total


def _pids(front: Any) -> list[int]:
    """This process and its front's workers, if it has any."""
    return [os.getpid(), *getattr(front, "pids", ())]


def rss_mb() -> tuple[float, float]:
    """(current, peak) resident memory of this process in MB, from /proc."""
    current = peak = math.nan
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    current = int(line.split()[1]) / 1024.0
                elif line.startswith("VmHWM:"):
                    peak = int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return current, peak


@dataclass
class BenchResult:
    scenario: str
    frames: int
    engine_s: float
    stages_ms: dict[str, float]
    rss_start_mb: float
    rss_end_mb: float
    peak_rss_mb: float
    rss_growth_mb_per_1000: float
    latency_p50_s: float
    latency_p95_s: float
    stall_max_s: float
    """The longest the engine held one sample (a re-solve redrawing its stretch): the
    daemon's backlog must absorb it."""
    flush_s: float
    """The end of the stream: the last window made final and the frames a re-solve moved
    that still wait to be drawn again (once per survey, not per frame)."""
    tiles_published: int
    frames_mapped: int
    frames_rejected: int
    frames_skipped: int
    memory_samples: list[tuple[int, float]] = field(default_factory=list)
    """(frames so far, RSS in MB) every 200 frames and at the end."""
    spill_written_mb: float = 0.0
    """What the live engine wrote to its tile spill (the daemon's disk traffic)."""
    final_pass_s: float | None = None
    final_stages_s: dict[str, float] = field(default_factory=dict)
    """The survey-end pass's stages (seconds of its own process; a stage that ran on the
    workers is the time it waited for them)."""
    range_m: float = math.nan
    """The sonar's range in the pings (m): a frame's cost depends on it."""
    workers: int = 0
    """Worker processes the engine's stages ran in (``daemon.workers``)."""
    worker_stages: tuple[str, ...] = ()
    """Stages that ran in a worker: their time is the worker's, beside the engine's."""
    pss_samples: list[tuple[int, float]] = field(default_factory=list)
    """(frames so far, PSS in MB of the engine's process and its workers together)."""
    streamed: bool = False
    """The simulator ran beside the engine (a survey too long to write out first)."""

    @property
    def pss_growth_mb_per_1000(self) -> float:
        """The PSS's growth per 1000 frames over the run's second half (a straight line
        fitted; NaN with too few samples)."""
        return _second_half_growth(self.pss_samples, self.frames)

    @property
    def peak_pss_mb(self) -> float:
        """The largest PSS sampled, over the engine's process and its workers."""
        values = [v for _, v in self.pss_samples if math.isfinite(v)]
        return max(values) if values else math.nan

    @property
    def fps(self) -> float:
        return self.frames / self.engine_s if self.engine_s > 0 else math.inf

    def as_json(self) -> dict[str, Any]:
        """The report as JSON-ready values (NaN, e.g. no growth measured yet, is null)."""
        return {k: _finite(v) for k, v in self._fields().items()}

    def _fields(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "range_m": self.range_m,
            "frames": self.frames,
            "frames_mapped": self.frames_mapped,
            "frames_rejected": self.frames_rejected,
            "frames_skipped": self.frames_skipped,
            "ms_per_frame": 1000.0 * self.engine_s / max(self.frames, 1),
            "ms_per_frame_pinging": 1000.0 * (self.engine_s - self.flush_s) / max(self.frames, 1),
            "frames_per_second": self.fps,
            "realtime_factor_10hz": self.fps / 10.0,
            "peak_rss_mb": self.peak_rss_mb,
            "rss_start_mb": self.rss_start_mb,
            "rss_end_mb": self.rss_end_mb,
            "rss_growth_mb_per_1000_frames": self.rss_growth_mb_per_1000,
            "latency_p50_s": self.latency_p50_s,
            "latency_p95_s": self.latency_p95_s,
            "stall_max_s": self.stall_max_s,
            "flush_s": self.flush_s,
            "tiles_published": self.tiles_published,
            "stages": self.stages_ms,
            "final_pass_s": self.final_pass_s,
            "final_stages_s": self.final_stages_s,
            "spill_written_mb": self.spill_written_mb,
            "memory_samples": [[frames, rss] for frames, rss in self.memory_samples],
            "workers": self.workers,
            "worker_stages": list(self.worker_stages),
            "peak_pss_mb": self.peak_pss_mb,
            "pss_growth_mb_per_1000_frames": self.pss_growth_mb_per_1000,
            "pss_samples": [[frames, value] for frames, value in self.pss_samples],
            "simulator_beside_engine": self.streamed,
        }


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    return value


def run_bench(
    scenario: str,
    seed: int,
    max_pings: int | None,
    overrides: dict[str, Any],
    params: StreamingParams | None = None,
    final_pass: bool = False,
    progress: Any = None,
    workers: int = 0,
) -> BenchResult:
    """``workers``: worker processes for the engine's stages (``daemon.workers``)."""
    from daemon.replay import mount_from_config, pipeline_params, streaming_params
    from daemon.workers import live_front, task_pool
    from tools.sim.scenarios import STREAM_ONLY

    if max_pings is not None:
        overrides = {**overrides, "max_pings": max_pings}
    # Tiles the boat leaves go to disk, as on the boat; with the survey-end pass, the pings
    # are recorded there too, and the pass reads the recording, as the daemon's does.
    spill_dir = tempfile.TemporaryDirectory(prefix="seamap-bench-")
    stream: RecordedFeed | SimulatedFeed
    streamed = scenario in STREAM_ONLY and max_pings is None and "duration_s" not in overrides
    if streamed:
        # Too long to write out first (tens of GB): the simulator runs beside the engine.
        recording = Path(spill_dir.name) / "sonar.oculus" if final_pass else None
        stream = SimulatedFeed(scenario, seed, overrides, recording)
    else:
        stream = RecordedFeed(scenario, seed, overrides, Path(spill_dir.name) / "survey")
        recording = stream.recording
    config = stream.site_config
    params = params or streaming_params(
        pipeline_params(config), config.live, config.daemon.tile_memory_mb
    )
    ping_time: list[float] = []
    latencies: list[float] = []
    tiles_published = 0
    engine: StreamingEngine

    def on_tile(update: TileUpdate) -> None:
        nonlocal tiles_published
        tiles_published += 1
        released = engine._released  # survey time at which this render happened
        for frame in update.frames:
            # A frame's first appearance counts; later ones are re-blends.
            if frame < len(ping_time) and frame not in seen:
                seen.add(frame)
                waited = max(released - ping_time[frame], 0.0)  # survey time held
                latencies.append(waited + time.perf_counter() - engine.sent_at[frame])

    seen: set[int] = set()
    spill = DiskSpill(Path(spill_dir.name) / "live")
    mount = mount_from_config(config.sonar)
    threads = cv2.getNumThreads()
    front = live_front(mount, params, workers, log=print, threads=threads)
    engine = StreamingEngine(mount, params, on_tile=on_tile, spill=spill, front=front)
    return_large_blocks()  # as the daemon does at start
    kernels.warm()  # as the daemon does at start: the compile is not a frame's time
    reset_peak_rss()
    rss_start, _ = rss_mb()
    memory: list[tuple[int, float]] = []
    pss: list[tuple[int, float]] = []
    engine_s = 0.0
    stall = 0.0
    frames = 0
    range_m = math.nan
    for _, sample in stream.events():
        started = time.perf_counter()
        engine.add(sample)
        spent = time.perf_counter() - started
        engine_s += spent
        stall = max(stall, spent)
        if isinstance(sample, Ping):
            frames += 1
            range_m = sample.max_range_m
            ping_time.append(sample.time)
            if frames % 200 == 0:
                memory.append((frames, rss_mb()[0]))
                pss.append((frames, pss_mb(_pids(front))))
                if progress is not None:
                    progress("bench", frames, stream.ping_count)
    started = time.perf_counter()
    engine.flush()
    flush_s = time.perf_counter() - started
    engine_s += flush_s
    rss_end, peak = rss_mb()
    memory.append((frames, rss_end))
    pss.append((frames, pss_mb(_pids(front))))
    engine.close()  # the live engine's worker (the survey-end pass has its own)
    growth = _second_half_growth(memory, frames)
    stats = engine.stats
    stages = {k: 1000.0 * v / max(frames, 1) for k, v in sorted(stats.stage_s.items())}
    if front is not None:
        stages["front wait"] = 1000.0 * stats.front_wait_s / max(frames, 1)
    final_s: float | None = None
    final_stages: dict[str, float] = {}
    if final_pass:

        def pings_again() -> Iterator[Ping]:
            assert recording is not None
            return iter_pings(recording)

        started = time.perf_counter()
        final_spill = DiskSpill(Path(spill_dir.name) / "final")
        pool = task_pool(workers, log=print, threads=threads)
        try:
            final = engine.finish(pings_again, spill=final_spill, pool=pool)
            final_stages = dict(final.timings)
        finally:
            if pool is not None:
                pool.close()
        final_s = time.perf_counter() - started
    spill_written = spill.bytes_written / 2**20
    spill_dir.cleanup()
    lat = np.array(latencies) if latencies else np.array([math.nan])
    return BenchResult(
        scenario=scenario,
        frames=frames,
        engine_s=engine_s,
        stages_ms=stages,
        rss_start_mb=rss_start,
        rss_end_mb=rss_end,
        peak_rss_mb=peak,
        rss_growth_mb_per_1000=growth,
        latency_p50_s=float(np.percentile(lat, 50)),
        latency_p95_s=float(np.percentile(lat, 95)),
        stall_max_s=stall,
        flush_s=flush_s,
        tiles_published=tiles_published,
        frames_mapped=stats.frames_mapped,
        frames_rejected=stats.frames_rejected,
        frames_skipped=stats.frames_skipped,
        memory_samples=memory,
        spill_written_mb=spill_written,
        final_pass_s=final_s,
        final_stages_s=final_stages,
        range_m=range_m,
        workers=workers if front is not None else 0,
        worker_stages=(
            ("preprocess", "registration", "closure registration") if front is not None else ()
        ),
        pss_samples=pss,
        streamed=streamed,
    )


def _second_half_growth(samples: list[tuple[int, float]], frames: int) -> float:
    """MB per 1000 frames, a straight line fitted to the samples of the second half (NaN
    with fewer than three)."""
    half = [m for m in samples if m[0] >= frames / 2 and math.isfinite(m[1])]
    if len(half) < 3:
        return math.nan
    x = np.array([m[0] for m in half], float)
    y = np.array([m[1] for m in half], float)
    return float(np.polyfit(x, y, 1)[0] * 1000.0)


def _growth(value: float | None) -> str:
    if value is None:
        return "- (run more frames to measure it)"
    return f"{value:.2f} MB per 1000 frames"


def format_table(result: BenchResult) -> str:
    j = result.as_json()
    lines = [
        f"seamap bench: {result.scenario} at a {result.range_m:.3g} m range, "
        f"{result.frames} frames "
        f"({result.frames_mapped} mapped, {result.frames_rejected} rejected, "
        f"{result.frames_skipped} skipped)",
        "",
        f"  {'stage':<14}{'ms/frame':>10}",
    ]
    for stage, ms in result.stages_ms.items():
        where = "   (in a worker, beside the rest)" if stage in result.worker_stages else ""
        lines.append(f"  {stage:<14}{ms:>10.2f}{where}")
    lines += [
        f"  {'total':<14}{j['ms_per_frame']:>10.2f}",
        f"  {'  pinging':<14}{j['ms_per_frame_pinging']:>10.2f}   (the end of the stream "
        f"apart: {j['flush_s']:.1f} s)",
        "",
        f"  frames per second        {j['frames_per_second']:.1f}",
        f"  real time at 10 Hz       x{j['realtime_factor_10hz']:.1f}",
        f"  latency p50 / p95        {j['latency_p50_s']:.2f} s / {j['latency_p95_s']:.2f} s",
        f"  longest stall            {j['stall_max_s']:.2f} s",
        f"  memory start / end / peak {j['rss_start_mb']:.0f} / {j['rss_end_mb']:.0f} / "
        f"{j['peak_rss_mb']:.0f} MB",
        f"  memory growth            {_growth(j['rss_growth_mb_per_1000_frames'])}",
        f"  workers                  {result.workers} (peak PSS with them "
        f"{j['peak_pss_mb'] or math.nan:.0f} MB, growth "
        f"{_growth(j['pss_growth_mb_per_1000_frames'])})",
        f"  tiles published          {j['tiles_published']}",
        f"  tile spill written       {j['spill_written_mb']:.0f} MB",
    ]
    if result.final_pass_s is not None:
        lines.append(f"  survey-end pass          {result.final_pass_s:.1f} s")
        for stage, seconds in result.final_stages_s.items():
            lines.append(f"    {stage:<22}{seconds:>8.1f} s")
    return "\n".join(lines)


def plot_memory(result: BenchResult, path: Path) -> None:
    """The memory curve as a PNG: the engine's RSS and the PSS of the engine and its
    workers together against frames, with the growth fitted to its second half."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    frames = [m[0] for m in result.memory_samples]
    rss = [m[1] for m in result.memory_samples]
    figure, axes = plt.subplots(figsize=(8, 4.5), dpi=100)
    try:
        axes.plot(frames, rss, lw=1.2, label="the engine's process (RSS)")
        axes.axhline(result.peak_rss_mb, color="grey", ls=":", lw=1, label="its peak")
        growth = result.rss_growth_mb_per_1000
        if result.workers and result.pss_samples:
            axes.plot(
                [m[0] for m in result.pss_samples],
                [m[1] for m in result.pss_samples],
                lw=1.2,
                label="the engine and its workers (PSS)",
            )
            growth = result.pss_growth_mb_per_1000
        title = f"seamap bench: {result.scenario}, {result.frames} frames"
        if math.isfinite(growth):
            title += f" (growth {growth:.2f} MB per 1000 frames, second half)"
        axes.set_title(title, fontsize=10)
        axes.set_xlabel("frames")
        axes.set_ylabel("MB")
        axes.set_ylim(bottom=0)
        axes.grid(alpha=0.3)
        axes.legend(loc="lower right", fontsize=9)
        figure.tight_layout()
        figure.savefig(path)
    finally:
        plt.close(figure)
