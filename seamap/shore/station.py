"""The shore station: follow boats' live maps over zenoh and keep them on disk.

``ShoreStation`` subscribes to a vehicle's pose, status, tiles and coverage (CONTRACT.md
"Zenoh") and to its liveliness token, and catches up with a ``get`` of every current tile
and of the latest coverage at start and each time the boat's token (re)appears. zenoh
callbacks only turn what arrives into ``_Received`` items on one queue (``_hand_over``, the
single bridge from zenoh's threads); ``run`` takes them off on the caller's thread, applies
them to what it holds (``seamap.shore.state``) and, at a steady cadence, shows a status
line and rewrites (atomically, only what changed):

- ``DIR/{vehicle}/{survey}/mosaic.tif`` and ``mosaic.png``: the survey's tiles held;
- ``DIR/{vehicle}/{survey}/coverage.png`` (and its world file ``coverage.pgw``),
  ``coverage.json`` and ``gaps.geojson``: the survey's latest coverage raster and summary
  (``state.write_coverage_*``);
- ``DIR/{vehicle}/track.csv`` and ``track.geojson``: the vehicle's track;
- ``DIR/{vehicle}/status.json``: its latest status.

Bad payloads are counted and told in one line; they never stop the station.

An ``on_event`` listener (the live map page, ``seamap.shore.web``) is told each item
applied, as a ``ShoreEvent``, on the run thread; it must hand over and return at once.
"""

from __future__ import annotations

import math
import queue
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from functools import partial
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

import zenoh

from daemon.config import SiteConfig, ZenohConfig
from drivers.errors import SeamapError
from drivers.zenoh_io import (
    ROOT,
    CoverageKeyParts,
    alive_key,
    coverage_selector,
    id_problem,
    open_session,
    parse_alive_key,
    parse_coverage_key,
    parse_tile_key,
    pose_key,
    status_key,
    tiles_selector,
    with_endpoints,
)
from seamap.shore.state import (
    BadPayload,
    HeldCoverage,
    HeldSurvey,
    HeldTile,
    HeldVehicle,
    Mosaic,
    ShoreEvent,
    ShoreState,
    TrackPoint,
    write_coverage_raster,
    write_coverage_summary,
    write_mosaic,
    write_status,
    write_track,
)

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
WRITE_INTERVAL_S = 5.0
TTY_STATUS_INTERVAL_S = 1.0
LOG_STATUS_INTERVAL_S = 10.0
CATCHUP_TIMEOUT_S = 300.0
"""A catch-up over a slow radio link can take minutes; live tiles keep coming meanwhile."""
MAX_MOSAIC_PX = 500_000_000
"""Mosaics larger than this (tiles far apart, e.g. a long diagonal transit) are not
assembled: the shore says so once instead of exhausting its memory."""
BAD_LINE_INTERVAL_S = 1.0


def _default_session() -> ZenohConfig:
    """Without a config: a peer that connects to DEFAULT_CONNECT, listens nowhere, and does
    no multicast scouting."""
    return ZenohConfig(mode="peer", listen=[], connect=[DEFAULT_CONNECT], multicast_scouting=False)


@dataclass(frozen=True)
class ShoreSettings:
    out_dir: Path
    zenoh: ZenohConfig = field(default_factory=_default_session)
    vehicle: str = "*"
    """The vehicle id followed, or ``*`` for every vehicle."""
    survey: str = "*"
    """The survey id followed, or ``*`` for every survey."""
    write_interval_s: float = WRITE_INTERVAL_S
    status_interval_s: float | None = None
    """How often the status line is shown; None: every second on a terminal, else every 10 s."""
    catchup_timeout_s: float = CATCHUP_TIMEOUT_S


def shore_settings(
    out_dir: Path,
    config: SiteConfig | None = None,
    *,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    vehicle: str | None = None,
    survey: str | None = None,
) -> ShoreSettings:
    """The shore's settings: the zenoh session from ``config``'s ``[zenoh]`` (or, without a
    config, a peer connecting to ``DEFAULT_CONNECT``, not listening, no multicast
    scouting), each given option replacing the config's value; the vehicle from
    ``vehicle``, else the config's ``[daemon] vehicle``, else every vehicle.
    SeamapError naming a malformed endpoint or id."""
    base = config.zenoh if config is not None else _default_session()
    session = with_endpoints(base, listen, connect, mode)
    if vehicle is None:
        vehicle = config.daemon.vehicle if config is not None else "*"
    survey = "*" if survey is None else survey
    for name, value in (("--vehicle", vehicle), ("--survey", survey)):
        if value != "*" and id_problem(value):
            raise SeamapError(f"{name} {value!r}: {id_problem(value)}")
    return ShoreSettings(out_dir=out_dir, zenoh=session, vehicle=vehicle, survey=survey)


@dataclass
class ShoreStats:
    tiles_taken: int = 0
    """Tiles stored, new or replacing an older version."""
    tiles_stale: int = 0
    """Tiles not newer than the one held (late catch-up replies, repeats): dropped."""
    poses: int = 0
    statuses: int = 0
    coverage_taken: int = 0
    """Coverage summaries and rasters stored, new or replacing an older version."""
    coverage_stale: int = 0
    """Coverage summaries and rasters not newer than the one held: dropped."""
    bad: int = 0
    """Payloads that could not be used (bad PNG, attachment, JSON, size, key)."""
    arrivals: int = 0
    """Times a boat's liveliness token appeared (a boat already up counts once at start)."""
    departures: int = 0
    catchups_started: int = 0
    catchups_done: int = 0
    """Catch-ups whose every ``get`` (tiles, coverage) has ended."""
    writes: int = 0
    """Files written."""
    listener_errors: int = 0
    """Times the ``on_event`` listener raised (told once; the station goes on)."""


class _Via(Enum):
    SUBSCRIPTION = "subscription"
    CATCHUP = "catch-up reply"
    LIVELINESS = "liveliness"
    CATCHUP_DONE = "catch-up done"
    WAKE = "wake"


@dataclass(frozen=True, slots=True)
class _Received:
    via: _Via
    key: str = ""
    payload: bytes = b""
    attachment: bytes | None = None
    put: bool = True


def _received(via: _Via, sample: zenoh.Sample) -> _Received:
    attachment = sample.attachment
    return _Received(
        via,
        str(sample.key_expr),
        sample.payload.to_bytes(),
        None if attachment is None else attachment.to_bytes(),
        sample.kind == zenoh.SampleKind.PUT,
    )


class _Console:
    """Event lines and the status line on one stream. On a terminal the status line is
    rewritten in place and events print above it; elsewhere both are plain lines."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        try:
            self.tty = stream.isatty()
        except (AttributeError, ValueError):
            self.tty = False
        self._drawn = False

    def event(self, text: str) -> None:
        self._write(("\r\x1b[K" if self._drawn else "") + f"shore: {text}\n")
        self._drawn = False

    def status(self, text: str, final: bool = False) -> None:
        if self.tty:
            width = max(20, shutil.get_terminal_size().columns - 1)
            self._write("\r" + text[:width] + "\x1b[K" + ("\n" if final else ""))
            self._drawn = not final
        else:
            self._write(f"shore: {text}\n")

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):
            pass  # a closed terminal must not stop the station


class ShoreStation:
    """Follow ``settings.vehicle`` over zenoh and keep its map, track and status on disk.

    ``open`` (or ``with``) opens the session (blocking ~0.5 s), subscribes and catches up;
    ``run`` applies what arrives and writes the files until stopped; ``close`` ends the
    session. The readers (``tiles``, ``mosaic``, ``coverage``, ``track``, ``status``,
    ``alive``, ``status_line``, ``stats``) belong to the thread that calls ``run``: use them
    between runs or from its ``until`` predicate. Only ``stop`` may be called from elsewhere.
    """

    def __init__(
        self,
        settings: ShoreSettings,
        *,
        console: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_event: Callable[[ShoreEvent], None] | None = None,
    ) -> None:
        self.settings = settings
        self._on_event = on_event
        self.stats = ShoreStats()
        self._console = _Console(console if console is not None else sys.stderr)
        self._clock = clock
        self._inbox: queue.SimpleQueue[_Received] = queue.SimpleQueue()
        self._session: zenoh.Session | None = None
        self._state = ShoreState()
        self._stop_requested = False
        self._status_interval = settings.status_interval_s or (
            TTY_STATUS_INTERVAL_S if self._console.tty else LOG_STATUS_INTERVAL_S
        )
        self._next_write = math.inf
        self._next_status = math.inf
        self._bad_told: dict[str, tuple[float, int]] = {}
        """Per kind of payload: when its last bad-payload line was told, how many since."""
        self._write_failing: set[Path] = set()
        self._catchups = 0
        self._catchup_gets: dict[int, int] = {}
        """Per catch-up (by number): its ``get``s not ended yet."""

    # --- life cycle -------------------------------------------------------------------------

    def __enter__(self) -> ShoreStation:
        self.open()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Open the session, subscribe and start the first catch-up; SeamapError in one line."""
        if self._session is not None:
            return
        out_dir = self.settings.out_dir
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SeamapError(f"{out_dir}: cannot create the output folder ({exc})") from None
        cfg = self.settings.zenoh
        try:
            session = open_session(cfg)
        except SeamapError as exc:
            if cfg.mode == "client":
                raise SeamapError(
                    f"{exc}; client mode needs a reachable zenoh router "
                    "(--mode peer waits for the boat instead)"
                ) from None
            raise
        vehicle, survey = self.settings.vehicle, self.settings.survey
        try:
            session.declare_subscriber(pose_key(vehicle), self._on_sample)
            session.declare_subscriber(status_key(vehicle), self._on_sample)
            session.declare_subscriber(tiles_selector(vehicle, survey), self._on_sample)
            session.declare_subscriber(coverage_selector(vehicle, survey), self._on_sample)
            session.liveliness().declare_subscriber(
                alive_key(vehicle), self._on_liveliness, history=True
            )
        except zenoh.ZError as exc:
            session.close()
            raise SeamapError(f"zenoh: cannot subscribe to {ROOT}/{vehicle} ({exc})") from None
        self._session = session
        now = self._clock()
        self._next_write = now + self.settings.write_interval_s
        self._next_status = now + self._status_interval
        links = [f"connecting to {', '.join(cfg.connect)}"] if cfg.connect else []
        links += [f"listening on {', '.join(cfg.listen)}"] if cfg.listen else []
        self._console.event(
            f"following {ROOT}/{vehicle} (survey {survey}) as a zenoh {cfg.mode} "
            f"{' and '.join(links) or 'without endpoints'}; writing to {out_dir}"
        )
        self.catch_up()

    def close(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def stop(self) -> None:
        """Make ``run`` return (now, or at once when next called). Safe from any thread and
        from a signal handler."""
        self._stop_requested = True
        self._hand_over(_Received(_Via.WAKE))

    @property
    def stopping(self) -> bool:
        return self._stop_requested

    def run(
        self,
        duration_s: float | None = None,
        until: Callable[[ShoreStation], bool] | None = None,
    ) -> bool:
        """Apply what arrives, show the status line and write the files at their cadence,
        until ``stop``, ``duration_s`` seconds, or ``until(self)`` holds; then (unless
        ``until`` was met) apply what has already arrived, and write what changed one last
        time. True when ``until`` was met."""
        self.open()
        end = math.inf if duration_s is None else self._clock() + duration_s
        met = False
        while not self._stop_requested:
            if until is not None and until(self):
                met = True
                break
            now = self._clock()
            if now >= end:
                break
            self._on_time(now)
            wait = min(end, self._next_write, self._next_status) - now
            try:
                item = self._inbox.get(timeout=max(wait, 0.0))
            except queue.Empty:
                continue
            self._apply(item)
        if not met:  # the station ends
            self._drain()
        self.write_files()
        self._console.status(self.status_line(), final=True)
        return met

    def _drain(self) -> None:
        """Apply what has already arrived (a boat's final tiles just before a SIGTERM), so
        the last files hold it; liveliness changes are left: no catch-up on the way out.
        Only what is queued now: a boat that keeps publishing cannot hold the station."""
        for _ in range(self._inbox.qsize()):
            try:
                item = self._inbox.get_nowait()
            except queue.Empty:
                return
            if item.via is not _Via.LIVELINESS:
                self._apply(item)

    def catch_up(self, vehicle: str | None = None) -> None:
        """Ask for every current tile and the latest coverage of ``vehicle`` (default: the
        vehicles followed) of the survey(s) followed; the replies arrive like live ones.
        The catch-up is done when both ``get``s have ended."""
        if self._session is None:
            raise RuntimeError("catch_up before open")
        self._catchups += 1
        number, asked = self._catchups, 0
        done = partial(self._on_catchup_done, number)
        for selector in (
            tiles_selector(vehicle or self.settings.vehicle, self.settings.survey),
            coverage_selector(vehicle or self.settings.vehicle, self.settings.survey),
        ):
            try:
                self._session.get(
                    selector,
                    zenoh.handlers.Callback(self._on_reply, done),
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=self.settings.catchup_timeout_s,
                )
            except zenoh.ZError as exc:
                self._console.event(f"cannot catch up with {selector} ({exc})")
                continue
            asked += 1
        if asked:
            self._catchup_gets[number] = asked
            self.stats.catchups_started += 1

    # --- the one bridge from zenoh's threads --------------------------------------------------

    def _hand_over(self, item: _Received) -> None:
        """Runs on zenoh's threads (and in signal handlers): hands over, never blocks."""
        self._inbox.put(item)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._hand_over(_received(_Via.SUBSCRIPTION, sample))

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        self._hand_over(_received(_Via.LIVELINESS, sample))

    def _on_reply(self, reply: zenoh.Reply) -> None:
        sample = reply.ok
        if sample is not None:  # an error reply carries no tile
            self._hand_over(_received(_Via.CATCHUP, sample))

    def _on_catchup_done(self, number: int) -> None:
        self._hand_over(_Received(_Via.CATCHUP_DONE, key=str(number)))

    # --- applying what arrived (the run thread) -----------------------------------------------

    def _apply(self, item: _Received) -> None:
        if item.via is _Via.WAKE:
            return
        if item.via is _Via.CATCHUP_DONE:
            self._catchup_get_done(int(item.key))
            return
        if item.via is _Via.LIVELINESS:
            vehicle = parse_alive_key(item.key)
            if vehicle is not None and not id_problem(vehicle):
                self._take_liveliness(vehicle, item.put)
            return
        parts = item.key.split("/")
        try:
            if len(parts) == 3 and parts[0] == ROOT and parts[2] in ("pose", "status"):
                self._take_pose_or_status(parts[1], parts[2], item)
            elif (coverage := parse_coverage_key(item.key)) is not None:
                self._take_coverage(coverage, item)
            else:
                self._take_tile(item)
        except BadPayload as exc:
            self._bad(item.key, str(exc))

    def _catchup_get_done(self, number: int) -> None:
        left = self._catchup_gets.get(number)
        if left is None:
            return
        if left > 1:
            self._catchup_gets[number] = left - 1
        else:
            del self._catchup_gets[number]
            self.stats.catchups_done += 1

    def _tell(self, event: ShoreEvent) -> None:
        if self._on_event is None:
            return
        try:
            self._on_event(event)
        except Exception as exc:  # a listener's bug must not stop the intake
            self.stats.listener_errors += 1
            if self.stats.listener_errors == 1:
                self._console.event(f"event listener failed ({type(exc).__name__}: {exc})")

    def _take_liveliness(self, vehicle: str, alive: bool) -> None:
        self._state.take_liveliness(vehicle, alive)
        self._tell(ShoreEvent("alive", vehicle, alive=alive))
        if alive:
            self.stats.arrivals += 1
            self._console.event(f"{vehicle}: boat up, catching up")
            self.catch_up(vehicle)
        else:
            self.stats.departures += 1
            self._console.event(f"{vehicle}: boat away (its map is kept; waiting for it)")

    def _take_pose_or_status(self, vehicle: str, what: str, item: _Received) -> None:
        if id_problem(vehicle):
            raise BadPayload("vehicle id unusable as a folder name")
        if not item.put:
            return  # a delete of the pose or status means nothing here
        if what == "pose":
            taken = self._state.take_pose(vehicle, item.payload)
            self.stats.poses += 1
            self._tell(
                ShoreEvent(
                    "pose", vehicle, payload=item.payload, point=taken.point, refined=taken.refined
                )
            )
        else:
            self._state.take_status(vehicle, item.payload)
            self.stats.statuses += 1
            self._tell(ShoreEvent("status", vehicle, status=self._state.status(vehicle)))

    def _take_tile(self, item: _Received) -> None:
        where = parse_tile_key(item.key)
        if where is None:
            raise BadPayload("not a tile key")
        if not item.put:
            return  # the contract has no tile deletes; keep what we hold
        if self._state.take_tile(where, item.payload, item.attachment):
            self.stats.tiles_taken += 1
            held = self._state.vehicles[where.vehicle].surveys[where.survey]
            info = held.tiles[(where.col, where.row)].info
            self._tell(
                ShoreEvent(
                    "tile", where.vehicle, where.survey, where.col, where.row, info, item.payload
                )
            )
        else:
            self.stats.tiles_stale += 1

    def _take_coverage(self, where: CoverageKeyParts, item: _Received) -> None:
        if not item.put:
            return  # the contract has no coverage deletes; keep what we hold
        if where.raster:
            taken = self._state.take_coverage_raster(where, item.payload, item.attachment)
        else:
            taken = self._state.take_coverage_summary(where, item.payload)
        if not taken:
            self.stats.coverage_stale += 1
            return
        self.stats.coverage_taken += 1
        coverage = self._state.vehicles[where.vehicle].surveys[where.survey].coverage
        if where.raster:
            event = ShoreEvent(
                "coverage_raster", where.vehicle, where.survey,
                coverage_info=coverage.raster_info, payload=item.payload,
            )  # fmt: skip
        else:
            event = ShoreEvent("coverage", where.vehicle, where.survey, summary=coverage.summary)
        self._tell(event)

    def _bad(self, key: str, reason: str) -> None:
        """Count a bad payload; tell it in one line, at most one line a second per kind
        (pose, status, tile, coverage summary, coverage raster), so a flood of one kind
        hides neither itself nor the others."""
        self.stats.bad += 1
        coverage = parse_coverage_key(key)
        if key.endswith(("/pose", "/status")):
            kind = key.rsplit("/", 1)[-1]
        elif coverage is not None:
            kind = "coverage raster" if coverage.raster else "coverage"
        else:
            kind = "tile"
        now = self._clock()
        told_at, untold = self._bad_told.get(kind, (-math.inf, 0))
        if now - told_at < BAD_LINE_INTERVAL_S:
            self._bad_told[kind] = (told_at, untold + 1)
            return
        more = f" (+{untold} more since the last such line)" if untold else ""
        self._console.event(f"bad payload on {key}: {reason}{more}")
        self._bad_told[kind] = (now, 0)

    def _on_time(self, now: float) -> None:
        if now >= self._next_status:
            self._console.status(self.status_line())
            self._next_status = now + self._status_interval
        if now >= self._next_write:
            self.write_files()
            self._next_write = now + self.settings.write_interval_s

    # --- files --------------------------------------------------------------------------------

    def write_files(self) -> None:
        """Write what changed since the last write; a failed write is told once and retried
        at the next cadence."""
        out_dir = self.settings.out_dir
        for vehicle, held in self._state.vehicles.items():
            folder = out_dir / vehicle
            if held.track_changed:
                track = partial(write_track, folder, held.track)
                held.track_changed = not self._attempt(folder / "track.csv", track)
            if held.status_changed:
                status = partial(write_status, folder, held.status_raw)
                held.status_changed = not self._attempt(folder / "status.json", status)
            for survey_id, survey in held.surveys.items():
                if survey.changed:
                    survey.changed = not self._write_mosaic(vehicle, survey_id, survey)
                self._write_coverage(folder / survey_id, survey.coverage)

    def _write_coverage(self, folder: Path, coverage: HeldCoverage) -> None:
        if coverage.summary_changed and coverage.summary is not None:
            summary = partial(write_coverage_summary, folder, coverage.summary)
            coverage.summary_changed = not self._attempt(folder / "coverage.json", summary)
        if coverage.raster_changed and coverage.raster_info is not None:
            raster = partial(write_coverage_raster, folder, coverage.raster, coverage.raster_info)
            coverage.raster_changed = not self._attempt(folder / "coverage.png", raster)

    def _write_mosaic(self, vehicle: str, survey_id: str, survey: HeldSurvey) -> bool:
        folder = self.settings.out_dir / vehicle / survey_id
        pixels = survey.mosaic_px()
        if pixels > MAX_MOSAIC_PX:
            if not survey.too_big_told:
                self._console.event(
                    f"{vehicle}/{survey_id}: the mosaic would be {pixels / 1e6:.0f} Mpx "
                    f"(tiles far apart); not written (limit {MAX_MOSAIC_PX / 1e6:.0f} Mpx)"
                )
                survey.too_big_told = True
            return True
        mosaic = survey.mosaic()
        if mosaic is None:
            return True
        return self._attempt(folder / "mosaic.tif", partial(write_mosaic, folder, mosaic))

    def _attempt(self, path: Path, write: Callable[[], None]) -> bool:
        try:
            write()
        except OSError as exc:
            if path not in self._write_failing:
                self._console.event(f"cannot write {path} ({exc}); will retry")
                self._write_failing.add(path)
            return False
        self._write_failing.discard(path)
        self.stats.writes += 1
        return True

    # --- what it holds ------------------------------------------------------------------------

    def vehicles(self) -> list[str]:
        return sorted(self._state.vehicles)

    def surveys(self, vehicle: str) -> list[str]:
        held = self._state.vehicles.get(vehicle)
        return sorted(held.surveys) if held is not None else []

    def tiles(self, vehicle: str, survey: str) -> dict[tuple[int, int], HeldTile]:
        """The tiles held for one survey, by (col, row)."""
        return self._state.tiles(vehicle, survey)

    def mosaic(self, vehicle: str, survey: str) -> Mosaic | None:
        """The survey's tiles as one image spanning those with data (None without tiles)."""
        return self._state.mosaic(vehicle, survey)

    def coverage(self, vehicle: str, survey: str) -> HeldCoverage | None:
        """The survey's latest coverage summary and raster (None when neither came)."""
        return self._state.coverage(vehicle, survey)

    def track(self, vehicle: str) -> list[TrackPoint]:
        return self._state.track(vehicle)

    def status(self, vehicle: str) -> dict[str, Any] | None:
        return self._state.status(vehicle)

    def alive(self, vehicle: str) -> bool | None:
        """Whether the vehicle's liveliness token is up (None: never seen)."""
        return self._state.alive(vehicle)

    def status_line(self) -> str:
        """One line: per vehicle its survey, tiles held, coverage, pose, frames mapped, lag,
        links, and "boat away" when its liveliness token is gone."""
        if not self._state.vehicles:
            cfg = self.settings.zenoh
            where = ", ".join(cfg.connect) or "no endpoint"
            line = f"waiting for {ROOT}/{self.settings.vehicle} ({cfg.mode}, connect {where})"
        else:
            line = " ; ".join(_vehicle_line(v, h) for v, h in sorted(self._state.vehicles.items()))
        if self.stats.bad:
            line += f" | bad payloads {self.stats.bad}"
        return line


def _vehicle_line(vehicle: str, held: HeldVehicle) -> str:
    """The most telling first, as a narrow terminal cuts the end off."""
    status = held.status or {}
    survey = status.get("survey")
    if not isinstance(survey, str) or not survey:
        survey = held.latest_survey
    parts = [vehicle]
    if held.alive is False:
        parts.append("boat away")
    held_survey = held.surveys.get(survey) if survey else None
    parts.append(f"survey {survey or '-'}")
    parts.append(f"tiles {len(held_survey.tiles) if held_survey else 0}")
    summary = held_survey.coverage.summary if held_survey else None
    if summary is not None:
        parts.append(_coverage_fragment(summary))
    if held.track:
        p = held.track[-1]
        parts.append(f"{p.lat:.6f} {p.lon:.6f} hdg {p.heading_deg:.0f}")
    else:
        parts.append("no pose")
    frames = status.get("frames")
    if isinstance(frames, dict) and isinstance(frames.get("mapped"), int):
        parts.append(f"mapped {frames['mapped']}")
    lag = status.get("lag_s")
    if isinstance(lag, int | float):
        parts.append(f"lag {lag:.1f} s")
    links = status.get("links")
    if isinstance(links, dict) and links:
        parts.append(
            " ".join(
                f"{name} {'up' if isinstance(link, dict) and link.get('up') else 'down'}"
                for name, link in links.items()
            )
        )
    return " | ".join(parts)


def _coverage_fragment(summary: dict[str, Any]) -> str:
    """``covered 63.4 %`` of the survey's area, or ``seen 812 m²`` when the area is not
    known; `` (final)`` once the survey-end pass has made it final."""
    area = summary["area"]
    if area is not None:
        text = f"covered {100 * area['fraction']:.1f} %"
    else:
        text = f"seen {summary['seen_m2']:.0f} m²"
    return text + (" (final)" if summary["final"] else "")


def serve(
    settings: ShoreSettings,
    duration_s: float | None = None,
    web: tuple[str, int] | None = None,
    out: TextIO | None = None,
) -> int:
    """Run a shore station until ``duration_s`` has passed or SIGINT/SIGTERM (the files are
    then written one last time); 0. A second signal interrupts at once. With ``web``
    (host, port; port 0 = a free one), also serve the live map page there and print its
    address as one line on ``out`` (stdout); SeamapError when it cannot be served."""
    page = None
    if web is not None:
        from seamap.shore.web import WebServer

        page = WebServer(web[0], web[1], settings.out_dir)
        url = page.start()
        print(f"web: {url}", file=out if out is not None else sys.stdout, flush=True)
    station = ShoreStation(settings, on_event=page.on_event if page is not None else None)

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        if station.stopping:
            raise KeyboardInterrupt
        station.stop()

    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    try:
        with station:
            station.run(duration_s)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if page is not None:
            page.close()
    return 0


__all__ = [
    "DEFAULT_CONNECT",
    "HeldCoverage",
    "HeldTile",
    "Mosaic",
    "ShoreEvent",
    "ShoreSettings",
    "ShoreStation",
    "ShoreStats",
    "TrackPoint",
    "serve",
    "shore_settings",
]
