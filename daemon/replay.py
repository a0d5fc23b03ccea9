"""Replay: recorded logs through the mapping core into the result folder.

The glue between the drivers (log readers), the core (``mapping.pipeline``) and the result
writers; the same core the daemon runs live. A survey recorded in several segments (one
per daemon start: ``sonar-NNN.oculus``, ``nav-NNN.tlog``) is replayed as one survey. The
survey's coverage goes with the mosaic (``daemon.coverage``), and its gaps when its area
is given; its track, poses, area, gaps and coverage summary go as vectors into survey.gpkg
(``drivers.formats.geopackage``).
"""

from __future__ import annotations

import heapq
import math
import os
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon.config import (
    EchosounderConfig,
    LiveConfig,
    MappingConfig,
    SiteConfig,
    SonarConfig,
    load_config,
)
from daemon.coverage import AreaSource, write_coverage
from daemon.memory import return_large_blocks
from daemon.recording import segments
from daemon.workers import live_front, task_pool
from drivers.errors import SeamapError
from drivers.formats.area import read_area
from drivers.formats.geopackage import SURVEY_GPKG, write_survey_gpkg
from drivers.formats.results import write_geotiff, write_png, write_report, write_trajectory
from drivers.formats.tilespill import DiskSpill
from drivers.oculus.logfile import V1_FILE_HEADER_SIZE, CaptureClock
from mapping.bottom import BottomParams
from mapping.coverage import SonarFan
from mapping.frames import SonarMount
from mapping.live_resolve import ResolveParams
from mapping.mosaic import assemble
from mapping.pipeline import Mode, NavSamples, PipelineParams, SurveyResult, map_survey
from mapping.preprocess import lit_min_range
from mapping.samples import Ping
from mapping.single_stage import SingleStageParams
from mapping.streaming import Sample, StreamingEngine, StreamingParams, StreamStats
from mapping.tasks import TaskPool
from mapping.tiles import TileSpill

LogPaths = Path | Sequence[Path]
"""One log file, or the segments of one log in time order."""


def _log_paths(logs: LogPaths, what: str) -> list[Path]:
    """``logs`` as a list of paths; SeamapError if it names none (``what``: "sonar log")."""
    paths = [Path(logs)] if isinstance(logs, str | os.PathLike) else [Path(p) for p in logs]
    if not paths:
        raise SeamapError(f"no {what} given")
    return paths


def _names(paths: Sequence[Path]) -> str:
    """The files for a message: "a.tlog" or "a.tlog + b.tlog"."""
    return " + ".join(str(path) for path in paths)


def mount_from_config(sonar: SonarConfig) -> SonarMount:
    return SonarMount(
        forward_m=sonar.mount_x_m,
        starboard_m=sonar.mount_y_m,
        down_m=sonar.mount_z_m,
        yaw_rad=math.radians(sonar.mount_yaw_deg),
        tilt_rad=math.radians(sonar.tilt_deg),
        altitude_m=sonar.altitude_m,
    )


def bottom_params(
    echosounder: EchosounderConfig, defaults: BottomParams, from_pings: bool = True
) -> BottomParams:
    """How the seabed under each ping is found, from the [echosounder] table: whether the
    soundings are used, and where the transducer sits (body FRD, metres from the GPS
    antenna); ``from_pings`` ([sonar] seabed_from_pings): else from the sonar's own."""
    return replace(
        defaults,
        use_echosounder=echosounder.use,
        use_sonar=from_pings,
        echosounder=replace(
            defaults.echosounder,
            forward_m=echosounder.mount_x_m,
            starboard_m=echosounder.mount_y_m,
            down_m=echosounder.mount_z_m,
        ),
    )


def pipeline_params(config: SiteConfig) -> PipelineParams:
    """The pipeline's settings from the site config's [mapping] and [echosounder] tables
    (replay, the daemon's live engine and survey-end pass, evaluate and bench all take
    them from here)."""
    m = config.mapping
    defaults = PipelineParams()
    return replace(
        defaults,
        mosaic_res_m=m.mosaic_res_m,
        optimiser=replace(defaults.optimiser, lam=m.lambda_local, alpha=m.alpha),
        registration=replace(defaults.registration, tau_p_m=m.tau_p_m, tau_a_deg=m.tau_a_deg),
        loops=replace(defaults.loops, enabled=m.loop_closures),
        blend=replace(defaults.blend, method=m.blending),
        single_stage=single_stage_params(m, defaults.single_stage),
        bottom=bottom_params(config.echosounder, defaults.bottom, config.sonar.seabed_from_pings),
    )


def streaming_params(
    pipeline: PipelineParams, live: LiveConfig, tile_memory_mb: float | None = 256.0
) -> StreamingParams:
    """The live engine's settings: the pipeline's, and the site config's [live] table
    (the daemon, replay's streaming mode and bench take them from here)."""
    return StreamingParams(
        pipeline=pipeline,
        tile_memory_mb=tile_memory_mb,
        live_registration_res_m=live.registration_res_m,
        live_yaw_from_gyro=live.yaw_from_gyro,
        live_candidates=live.candidates,
        resolve=replace(ResolveParams(), redraws_per_frame=live.redraws_per_frame),
    )


def single_stage_params(m: MappingConfig, defaults: SingleStageParams) -> SingleStageParams:
    """The single-stage fusion's error models from the [mapping] table (physical units)."""
    fusion = defaults.fusion
    gnss = replace(
        fusion.gnss,
        white_sigma_m=m.gnss_white_sigma_m,
        bias_sigma_m=m.gnss_bias_sigma_m,
        bias_tau_s=m.gnss_bias_tau_s,
        time_offset_s=m.gnss_lag_s - m.sonar_latency_s,
    )
    return replace(
        defaults,
        fusion=replace(fusion, gnss=gnss),
        graph=replace(
            defaults.graph,
            sonar_latency_s=m.sonar_latency_s,
            registration_scale=m.lambda_local / 1e4,
        ),
    )


def read_navigation(nav_logs: LogPaths, config: SiteConfig) -> tuple[NavSamples, dict[str, Any]]:
    """The navigation samples of a MAVLink log (or of its .tlog segments, read as one log)
    and what the report says of them; SeamapError if they cannot place any frame."""
    from drivers.mavlink import read_nav_log

    paths = _log_paths(nav_logs, "navigation log")
    names = _names(paths)
    nav = read_nav_log(
        paths,
        heading_source=config.mavlink.heading_source,
        imu_source=config.mavlink.imu_source,
        declination_deg=config.mavlink.declination_deg,
    )
    if nav.report.time_reference == "boot":
        raise SeamapError(
            f"{names}: times are seconds since the autopilot booted (no GPS time in the log), "
            "so they cannot be matched to the sonar's UNIX times"
        )
    if not any(f.usable for f in nav.gnss):
        raise SeamapError(f"{names}: no usable GNSS fix in the log: frames cannot be placed")
    info = {
        "autopilot": nav.autopilot,
        "time_reference": nav.report.time_reference,
        "first_time": nav.report.first_time,
        "last_time": nav.report.last_time,
        "heading_source": nav.heading_source,
        "imu_source": nav.imu_source,
        "imu_samples": len(nav.imu),
        "gnss_fixes": len(nav.gnss),
        "headings": len(nav.heading),
        "soundings": len(nav.ranges),
        "soundings_source": nav.range_source,
    }
    return NavSamples(nav.imu, nav.gnss, nav.heading, nav.attitude, ranges=nav.ranges), info


def check_captures(
    paths: Sequence[Path],
    clock: CaptureClock | None,
    unstamped: str = "give --sonar-start (UNIX s of its first ping, the navigation log's "
    "clock) to map it",
) -> None:
    """SeamapError (one line) unless every sonar file can be stamped: a raw network
    capture has no receipt times, so it needs ``clock`` (one capture, alone; its pings
    v2, whose own clock spaces them, or a rate); ``clock`` with a log that has times is
    refused too (it would be ignored). ``unstamped``: what to do about a capture without
    a clock, for the message."""
    from drivers.oculus.logfile import RAW_CAPTURE, LogReadReport, iter_log_items
    from drivers.oculus.ping import read_ping_info

    for path in paths:
        report = LogReadReport()
        items = iter_log_items(path, report)
        raw = report.version == RAW_CAPTURE
        if not raw:
            if clock is not None:
                raise SeamapError(
                    f"{path}: a {report.format} log has its own receipt times: --sonar-start "
                    "and --sonar-rate are for raw captures"
                )
            continue
        if clock is None:
            raise SeamapError(f"{path}: a raw Oculus capture has no receipt times: {unstamped}")
        if len(paths) > 1:
            raise SeamapError(f"{_names(paths)}: --sonar-start stamps one raw capture, not several")
        if clock.rate_hz is None:
            for item in items:
                try:
                    version = read_ping_info(item.message).version
                except SeamapError:
                    continue
                if version == 1:
                    raise SeamapError(
                        f"{path}: SimplePingResult v1 pings carry no clock with a documented "
                        "unit: give the capture's ping rate (--sonar-rate HZ)"
                    )
                break


def ping_source(
    sonar_logs: LogPaths, skipped: dict[str, int], clock: CaptureClock | None = None
) -> Callable[[], Iterator[Ping]]:
    """A callable yielding the pings of the log (or of its segments, one after another)
    afresh on each call (the pipeline reads the logs more than once instead of holding
    every frame in memory). At the end of each pass ``skipped`` holds the corrupt pings
    and the number of files cut inside an item, over all the segments. ``clock`` stamps
    a raw network capture's pings (``check_captures``)."""
    from drivers.oculus.logfile import LogReadReport, iter_pings

    paths = _log_paths(sonar_logs, "sonar log")

    def pings() -> Iterator[Ping]:
        corrupt = truncated = 0
        for path in paths:
            report = LogReadReport()
            yield from iter_pings(path, report, clock)
            corrupt += report.corrupt_pings
            truncated += int(report.truncated)
        skipped["corrupt_pings"] = corrupt
        skipped["truncated"] = truncated

    return pings


def render(result: SurveyResult) -> tuple[np.ndarray, float, float]:
    rendered = {tile.key: tile.values for tile in result.mosaic.rendered_tiles()}
    image, (west, north) = assemble(result.mosaic.grid, rendered)
    return image, west, north


def _unlit(
    names: str, result: SurveyResult, ping: Ping, config: SiteConfig, params: PipelineParams
) -> str:
    """Why a survey whose frames were all placed has an empty mosaic: no ping reached the
    seabed (the fan's vertical beam meets the bed beyond the range set)."""
    p = params.preprocess
    reach = lit_min_range(config.sonar.altitude_m, config.sonar.tilt_deg,
                          p.vertical_aperture_deg, 0.0)  # fmt: skip
    return (
        f"{names}: no ping shows the seabed ({result.frames_mapped} frames placed, none lit): "
        f"the pings reach {ping.max_range_m:.1f} m, and at {config.sonar.altitude_m:.1f} m "
        f"above a level bed with the sonar tilted {config.sonar.tilt_deg:.0f} deg the "
        f"vertical beam first meets it at {reach:.1f} m; set a longer [sonar] range_m or a "
        "steeper tilt_deg"
    )


def stream_survey(
    pings: Callable[[], Iterator[Ping]],
    nav: NavSamples,
    mount: SonarMount,
    params: PipelineParams,
    progress: Callable[[str, int, int], None] | None = None,
    spill: TileSpill | None = None,
    final_spill: TileSpill | None = None,
    tile_memory_mb: float | None = 256.0,
    final_pass: bool = True,
    live: LiveConfig | None = None,
    workers: int = 0,
    pool: TaskPool | None = None,
) -> tuple[SurveyResult, tuple[SurveyResult, StreamStats]]:
    """The streaming engine fed with the logs in arrival order (as the daemon would be),
    then its survey-end pass. Returns the final result and the live one (the live poses
    and tiles as they stood before the survey-end pass) with the engine's statistics;
    without ``final_pass`` (``[daemon] final_pass = false``), the live one twice.
    ``workers``: worker processes for the live engine's stages (``daemon.workers``);
    ``pool``: where the survey-end pass's tasks run (``mapping.tasks``)."""
    streaming = streaming_params(params, live or LiveConfig(), tile_memory_mb)
    front = live_front(mount, streaming, workers, log=_say)
    engine = StreamingEngine(mount, streaming, spill=spill, front=front)
    try:
        return _stream(engine, pings, nav, progress, final_spill, final_pass, pool)
    finally:
        engine.close()


def _say(line: str) -> None:
    print(f"seamap replay: {line}", file=sys.stderr, flush=True)


def _stream(
    engine: StreamingEngine,
    pings: Callable[[], Iterator[Ping]],
    nav: NavSamples,
    progress: Callable[[str, int, int], None] | None,
    final_spill: TileSpill | None,
    final_pass: bool,
    pool: TaskPool | None,
) -> tuple[SurveyResult, tuple[SurveyResult, StreamStats]]:
    arrivals: Iterator[Sample] = heapq.merge(
        nav.imu, nav.gnss, nav.heading, nav.attitude, nav.ranges, pings(),
        key=lambda sample: sample.time,
    )  # fmt: skip
    for sample in arrivals:
        engine.add(sample)
        if progress is not None and isinstance(sample, Ping):
            progress("streaming", engine.stats.frames_received, engine.stats.frames_received)
    engine.flush()
    if not final_pass:
        live_only = engine.live_result()
        return live_only, (live_only, engine.stats)
    final = engine.finish(pings, progress, final_spill, pool)
    poses = np.array(engine.poses) if engine.poses else np.zeros((0, 3))
    live_map = replace(
        final,
        poses=poses,
        mapped=np.all(np.isfinite(poses), axis=1),
        mosaic=engine.tiles,
    )
    return final, (live_map, engine.stats)


Scorer = Callable[
    [SurveyResult, npt.NDArray[np.uint8], float, float, float, SonarFan], dict[str, Any]
]
"""What scores a result against a reference (``report.json``'s ``accuracy``): called with
the result, its north-up mosaic, the mosaic's west and north edges (UTM m), its pixel (m)
and the sonar's fan as the mapper keeps it (range, fan, vertical beam: what a reference
without the sonar's own geometry scores the lanes with). ``seamap replay --truth`` takes
one from the ``seamap.scorers`` entry point ``truth`` (a simulator's truth or a reference
trajectory: ``tools.evaluation.truth.truth_scorer``); the product holds none."""


def replay(
    sonar: LogPaths,
    nav: LogPaths,
    config_path: Path | None,
    mode: str,
    out: Path,
    *,
    config: SiteConfig | None = None,
    scorer: Scorer | None = None,
    params: PipelineParams | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    area: Path | None = None,
    workers: int | None = None,
    clock: CaptureClock | None = None,
) -> dict[str, Any]:
    """Map the logs and write the result folder; returns the report.

    ``sonar`` and ``nav`` are each one log or the segments of one survey in time order
    (Oculus logs; .tlog segments, or one .tlog or DataFlash .bin). ``config``, when given,
    is used instead of loading ``config_path`` (which may then be None). ``area``: the
    survey's area (GeoJSON or a lat,lon list, ``drivers.formats.area``), read before any
    mapping: its covered fraction and gaps go into the result folder. ``workers``: the
    live engine's worker processes (streaming; None: ``[daemon] workers``). ``clock``:
    how a raw network capture's pings are stamped (``check_captures``). Bad input ends in
    one SeamapError naming the files.
    """
    started = time.perf_counter()
    return_large_blocks()  # the tiles' stacks go back to the system when freed
    sonar_paths = _log_paths(sonar, "sonar log")
    nav_paths = _log_paths(nav, "navigation log")
    sonar_names, nav_names = _names(sonar_paths), _names(nav_paths)
    config = config if config is not None else load_config(config_path)
    survey_area = AreaSource(area, read_area(area)) if area is not None else None
    params = params or pipeline_params(config)
    samples, nav_info = read_navigation(nav_paths, config)
    check_captures(sonar_paths, clock)
    skipped: dict[str, int] = {}
    pings = ping_source(sonar_paths, skipped, clock)
    mount = mount_from_config(config.sonar)
    live: tuple[SurveyResult, StreamStats] | None = None
    # Tiles the boat has left wait on disk, so a long survey fits in memory.
    spill_dir = tempfile.TemporaryDirectory(prefix="seamap-tiles-")
    spill_root = Path(spill_dir.name)
    workers = config.daemon.workers if workers is None else workers
    pool = task_pool(workers, log=_say)
    try:
        if mode == "streaming":
            result, live = stream_survey(
                pings, samples, mount, params, progress,
                DiskSpill(spill_root / "live"), DiskSpill(spill_root / "final"),
                config.daemon.tile_memory_mb, config.daemon.final_pass, config.live,
                workers, pool,
            )  # fmt: skip
        else:
            result = map_survey(
                pings, samples, mount, params, Mode(mode), progress,
                spill=DiskSpill(spill_root / "tiles"), pool=pool,
            )  # fmt: skip
    except ValueError as exc:
        spill_dir.cleanup()
        raise SeamapError(f"{nav_names}: {exc}") from None
    finally:
        if pool is not None:
            pool.close()
    if result.frames_read == 0:
        raise SeamapError(f"{sonar_names}: no sonar pings in the log")
    if result.frames_mapped == 0:
        first, last = float(result.times.min()), float(result.times.max())
        nav_first = nav_info["first_time"] or 0.0
        nav_last = nav_info["last_time"] or 0.0
        raise SeamapError(
            f"{sonar_names}: no frame could be placed: the pings ({first:.0f}..{last:.0f} s) and "
            f"the navigation log ({nav_first:.0f}..{nav_last:.0f} s) do not overlap in time"
            if not (nav_first <= last and first <= nav_last)
            else f"{sonar_names}: no frame could be placed ({dict(result.rejected)})"
        )
    t0 = time.perf_counter()
    image, west, north = render(result)
    render_s = time.perf_counter() - t0
    if image.size == 0:
        raise SeamapError(_unlit(sonar_names, result, next(iter(pings())), config, params))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SeamapError(f"{out}: cannot create the result folder ({exc.strerror})") from None
    epsg = result.frame.epsg
    write_geotiff(out / "mosaic.tif", image, west, north, params.mosaic_res_m, epsg)
    write_png(out / "mosaic.png", image)
    rows = write_trajectory(out / "trajectory.csv", result.frame, result.times, result.poses)
    t0 = time.perf_counter()
    # The sonar's fan as the mapper kept it, from the first ping (as the loop closures do).
    fan = SonarFan.of_ping(next(iter(pings())), mount, params.preprocess)
    written = write_coverage(out, result, fan, config.coverage, survey_area)
    coverage = written.report
    coverage_s = time.perf_counter() - t0
    write_survey_gpkg(
        out / SURVEY_GPKG, result.frame, result.times, result.poses, coverage,
        written.area, written.gaps,
    )  # fmt: skip
    files = ["mosaic.tif", "mosaic.png", "trajectory.csv", *written.files, SURVEY_GPKG]
    timings = {k: round(v, 4) for k, v in result.timings.items()}
    timings["render"] = round(render_s, 4)
    timings["coverage"] = round(coverage_s, 4)
    timings["total"] = round(time.perf_counter() - started, 4)
    n = max(result.frames_read, 1)
    report: dict[str, Any] = {
        "mode": mode,
        "inputs": {
            "sonar": [str(path) for path in sonar_paths],
            "nav": [str(path) for path in nav_paths],
            "config": str(config_path) if config_path else None,
        },
        "frames": {
            "read": result.frames_read,
            "mapped": result.frames_mapped,
            "rejected": dict(result.rejected),
            "placed_without_registration": result.frames_unregistered,
            "registrations": len(result.edges),
            "registrations_in_workers": dict(result.ahead),
            "loop_closures": asdict(result.loops),
            "skipped_in_log": skipped,
        },
        "navigation": nav_info,
        "bottom": result.bottom,
        "fusion": result.fusion,
        "crs": {"epsg": epsg, "res_m": params.mosaic_res_m, "west": west, "north": north},
        "mosaic": {
            "width": int(image.shape[1]),
            "height": int(image.shape[0]),
            "tiles": len(result.mosaic.all_keys()),
        },
        "trajectory_rows": rows,
        "coverage": coverage,
        "files": [*files, "report.json"],
        "timings_s": timings,
        "seconds_per_frame": {k: round(v / n, 6) for k, v in timings.items()},
        "settings": {"config": asdict(config), "pipeline": asdict(params)},
    }
    if live is not None:
        stats = live[1]
        report["streaming"] = {
            "frames_received": stats.frames_received,
            "frames_mapped": stats.frames_mapped,
            "frames_rejected": stats.frames_rejected,
            "frames_skipped": stats.frames_skipped,
            "samples_late": stats.samples_late,
            "samples_duplicate": stats.samples_duplicate,
            "windows_solved": stats.windows_solved,
            "frames_reblended": stats.frames_reblended,
            "resolves": stats.resolves,
            "frames_redrawn": stats.frames_redrawn,
            "redraw_wait_mean_s": round(stats.redraw_wait_mean_s, 1),
            "redraw_wait_max_s": round(stats.redraw_wait_max_s, 1),
            "ms_per_frame": {
                k: round(1000 * v / max(stats.frames_received, 1), 3)
                for k, v in stats.stage_s.items()
            },
        }
    if scorer is not None:
        report["accuracy"] = scorer(result, image, west, north, params.mosaic_res_m, fan)
        if live is not None and live[0] is result:
            report["accuracy_live"] = report["accuracy"]  # no survey-end pass: the live map
        elif live is not None:
            live_image, live_west, live_north = render(live[0])
            report["accuracy_live"] = scorer(
                live[0], live_image, live_west, live_north, params.mosaic_res_m, fan
            )
    write_report(out / "report.json", report)
    spill_dir.cleanup()
    return report


def replay_survey(
    survey_dir: Path,
    config: SiteConfig,
    out: Path,
    *,
    mode: str = "single-stage",
    scorer: Scorer | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    area: Path | None = None,
    workers: int | None = None,
) -> dict[str, Any]:
    """Replay every segment of a recorded survey folder (``sonar-NNN.oculus`` and
    ``nav-NNN.tlog``, in segment order) into ``out``; returns the report. ``area``: the
    survey's area file, for its gaps, and ``workers`` (``replay``).

    Empty segments (a daemon run that heard nothing from that device) are left out.
    SeamapError naming the folder if it is missing or holds no sonar or no nav segment, or
    nothing was recorded in them.
    """
    if not survey_dir.is_dir():
        raise SeamapError(f"{survey_dir}: no such survey folder")
    sonar, nav = segments(survey_dir)
    for found, what in ((sonar, "sonar-NNN.oculus"), (nav, "nav-NNN.tlog")):
        if not found:
            raise SeamapError(f"{survey_dir}: no {what} segment in the survey folder")
    nav = [path for path in nav if _size(path) > 0]
    if not nav:
        raise SeamapError(f"{survey_dir}: no MAVLink packet was recorded (nav segments empty)")
    sonar = [path for path in sonar if _size(path) > V1_FILE_HEADER_SIZE]
    if not sonar:
        raise SeamapError(f"{survey_dir}: no sonar message was recorded (sonar segments empty)")
    return replay(
        sonar, nav, None, mode, out, config=config, scorer=scorer, progress=progress, area=area,
        workers=workers,
    )  # fmt: skip


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0
