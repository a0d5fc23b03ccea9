"""The boat's zenoh side: pose, status, tiles and coverage out; catch-up and survey control in.

The event loop only hands things over (``pose``, ``status``, ``tile``, ``final_tiles``):
each goes into a latest-wins slot and wakes the publisher's own thread, which encodes the
PNGs and puts. Live puts use congestion control DROP, so a slow shore loses stale poses
instead of queueing them, and the publisher thread never waits on the network; only the
final tiles, put once from the survey-end pass's thread, wait for the link.

The pose (``seamap/{vehicle}/pose``) is the newest frame's; the frames the live map places
anew afterwards (its window's solve, its re-solves: ``refine``) ride with the next pose put,
as ``refined`` rows of ``[time, lat, lon, east, north, heading_deg]`` (the track's columns,
each frame's latest), so a shore's track follows the map instead of keeping each frame's
first, rougher estimate. Without a newer pose they go with the newest one again. A pose
dropped on a congested link takes its rows with it: the next refinement of those frames
comes with a later pose.

Queries arrive on zenoh's threads and are handed to the same thread (no work inside a
zenoh callback): a ``get`` on ``seamap/{vehicle}/survey/{survey}/tile/**`` (or any part of
it) gets every current tile of the surveys it names, the live survey's from memory and
finished surveys' from their folders (``tiles/``, written at the survey-end pass). The
survey control queryable (``seamap/{vehicle}/control/survey``) is answered on the event
loop, where the daemon lives.

Tile versions are millisecond UNIX times, forced to grow per tile: they keep growing
across daemon restarts, so a shore that held a tile before a crash takes the new one.

At survey end the final tiles replace the live ones: every tile the live map published
is republished, empty (all "no data") where the survey-end pass put nothing, since the
contract has no tile deletes and a shore would otherwise keep a stale live tile beside
the final mosaic. Once a survey's final tiles are out, no live tile of it follows them.
The session comes and goes (``attach``/``detach``, by the daemon's supervised zenoh task);
the caches do not, so a shore reconnecting after an outage catches up with a ``get``.

Coverage (``coverage``): each survey's latest publication (``daemon.coverage``) is put on
``seamap/{vehicle}/survey/{survey}/coverage`` (JSON) and ``.../coverage/raster`` (PNG,
attachment ``CoverageInfo``) and kept; a ``get`` on ``.../coverage/**`` answers the kept
ones, and for surveys mapped before this run, the final coverage of their result folder.
Once a survey's final coverage is out, live ones of it are dropped.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import rasterio
import zenoh

from daemon.live_coverage import CoverageMessage, final_message
from drivers import zenoh_io
from drivers.zenoh_io import TileInfo
from mapping.streaming import PoseUpdate, TileUpdate

log = logging.getLogger(__name__)

TILES_DIR = "tiles"
MAX_REFINED = 2000
"""Refined frames held for the next pose at most (a re-solve moves a few hundred)."""
TILES_INDEX = "index.json"

ControlHandler = Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]


@dataclass
class PublisherStats:
    poses: int = 0
    statuses: int = 0
    tiles: int = 0
    queries: int = 0
    replies: int = 0
    put_errors: int = 0
    session_opens: int = 0
    coverages: int = 0


@dataclass(frozen=True)
class _Tile:
    png: bytes
    info: TileInfo


class ZenohPublisher:
    """See the module docstring. ``vehicle`` names the keys; ``surveys_dir`` holds the
    finished surveys' tiles; ``control`` answers survey start/stop requests."""

    def __init__(
        self,
        vehicle: str,
        surveys_dir: Path,
        loop: asyncio.AbstractEventLoop,
        control: ControlHandler | None = None,
    ) -> None:
        self.vehicle = vehicle
        self.surveys_dir = surveys_dir
        self.control = control
        self.stats = PublisherStats()
        self._loop = loop
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self._wake = threading.Condition()
        self._pose: dict[str, Any] | None = None
        """The newest pose's message."""
        self._pose_due = False
        self._refined: dict[float, list[float]] = {}
        """By frame time: frames placed anew since the last pose put (at most MAX_REFINED)."""
        self._status: bytes | None = None
        self._pending_tiles: dict[tuple[str, tuple[int, int]], TileUpdate] = {}
        self._finished: set[str] = set()
        """Surveys whose final tiles are out; their live tiles are dropped."""
        self._tile_order = threading.Lock()
        """Held while tiles are stored and put, so a live tile in flight cannot pass the
        final ones."""
        self._queries: list[tuple[Callable[[zenoh.Query], None], zenoh.Query]] = []
        self._coverage: dict[str, CoverageMessage] = {}
        """Each survey's latest coverage publication (guarded by ``_lock``)."""
        self._pending_coverage: dict[str, CoverageMessage] = {}
        self._tiles: dict[str, dict[tuple[int, int], _Tile]] = {}
        self._lock = threading.Lock()  # guards _tiles
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="zenoh-publisher", daemon=True)
        self._thread.start()

    # --- session (event loop) --------------------------------------------------------------

    def attach(self, session: zenoh.Session) -> None:
        """Start publishing on ``session``: queryables, then the liveliness token (a shore
        catches up with a ``get`` when the token appears, so the tiles must answer first)."""
        v = self.vehicle
        declared = [
            session.declare_queryable(zenoh_io.tiles_selector(v), self._on_query, complete=True),
            session.declare_queryable(
                zenoh_io.coverage_selector(v), self._on_coverage_query, complete=True
            ),
            session.declare_queryable(zenoh_io.control_key(v), self._on_control, complete=True),
            session.liveliness().declare_token(zenoh_io.alive_key(v)),
        ]
        with self._wake:
            self._session, self._declared = session, declared
            self.stats.session_opens += 1
            self._wake.notify()

    def detach(self) -> zenoh.Session | None:
        """Stop publishing; the session (to be closed by the caller), if any."""
        with self._wake:
            session, self._session = self._session, None
            declared, self._declared = self._declared, []
        for item in declared:
            try:
                item.undeclare()
            except Exception as exc:  # a session already closed by zenoh
                log.debug("undeclare failed: %s", exc)
        return session

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify()
        self._thread.join(timeout=5.0)

    # --- hand-over (event loop) ------------------------------------------------------------

    def pose(self, update: PoseUpdate) -> None:
        message = {
            "time": update.time,
            "lat": update.lat,
            "lon": update.lon,
            "east": update.east,
            "north": update.north,
            "heading_deg": update.heading_deg,
            "epsg": update.epsg,
            "frame": update.frame,
            "final": update.final,
        }
        zenoh_io.json_bytes(message)  # refused here (NaN), not on the publisher's thread
        with self._wake:
            self._pose, self._pose_due = message, True
            self._refined.pop(update.time, None)  # the pose itself says where it is
            self._wake.notify()

    def refine(self, update: PoseUpdate) -> None:
        """An earlier frame placed anew: sent with the next pose (the newest kept)."""
        row = [update.time, update.lat, update.lon, update.east, update.north, update.heading_deg]
        if not all(math.isfinite(v) for v in row):
            return  # a frame the map gave up placing: its point stays
        with self._wake:
            self._refined.pop(update.time, None)
            self._refined[update.time] = row
            if len(self._refined) > MAX_REFINED:
                del self._refined[next(iter(self._refined))]  # the one left waiting longest
            self._pose_due = self._pose is not None
            self._wake.notify()

    def status(self, snapshot: dict[str, Any]) -> None:
        with self._wake:
            self._status = json.dumps(snapshot, default=str).encode()
            self._wake.notify()

    def tile(self, survey: str, update: TileUpdate) -> None:
        with self._wake:
            if survey in self._finished:
                return
            self._pending_tiles[(survey, update.key)] = update
            self._wake.notify()

    def coverage(self, survey: str, message: CoverageMessage) -> None:
        """A survey's coverage publication (any thread): kept, and put by the thread."""
        with self._lock:
            held = self._coverage.get(survey)
            if held is not None and held.summary["final"] and not message.summary["final"]:
                return  # the final coverage is out: a late live one would undo it
            self._coverage[survey] = message
        with self._wake:
            self._pending_coverage[survey] = message
            self._wake.notify()

    def survey_ended(self, survey: str) -> None:
        """Forget the live tiles of a survey: from now on its tiles come from its folder."""
        with self._lock:
            self._tiles.pop(survey, None)

    def final_tiles(self, survey: str, survey_dir: Path) -> int:
        """Cut the survey's final ``mosaic.tif`` into tiles, add an empty tile for every
        live tile it leaves out, keep them in ``tiles/`` for later queries and publish
        them (newer versions than any live tile); the survey's live tiles stop here. Runs
        on the caller's thread (the survey-end pass's); returns the number of tiles."""
        with self._tile_order:
            with self._wake:
                self._finished.add(survey)
                for pending in [k for k in self._pending_tiles if k[0] == survey]:
                    del self._pending_tiles[pending]  # superseded before it was put
            with self._lock:
                held = dict(self._tiles.get(survey, {}))
            out = _final_set(cut_mosaic(survey_dir / "mosaic.tif"), held, _version_now())
            if not out:
                return 0
            write_tiles(survey_dir / TILES_DIR, out)
            with self._lock:
                self._tiles[survey] = out
            with self._wake:
                session = self._session
            if session is not None:
                for key, tile in out.items():
                    # Sent once and never replaced: wait for the link rather than drop.
                    self._put_tile(session, survey, key, tile, zenoh.CongestionControl.BLOCK)
        return len(out)

    # --- zenoh callbacks (zenoh threads): hand over only -----------------------------------

    def _on_query(self, query: zenoh.Query) -> None:
        with self._wake:
            self._queries.append((self._answer, query))
            self._wake.notify()

    def _on_coverage_query(self, query: zenoh.Query) -> None:
        with self._wake:
            self._queries.append((self._answer_coverage, query))
            self._wake.notify()

    def _on_control(self, query: zenoh.Query) -> None:
        if self.control is None:
            query.reply_err(b'{"ok": false, "error": "no survey control"}')
            return
        asyncio.run_coroutine_threadsafe(self._answer_control(query), self._loop)

    async def _answer_control(self, query: zenoh.Query) -> None:
        try:
            raw = query.payload.to_bytes() if query.payload is not None else b"{}"
            request = json.loads(raw or b"{}")
            if not isinstance(request, dict):
                raise ValueError("not a JSON object")
        except ValueError as exc:
            reply: dict[str, Any] = {"ok": False, "error": f"bad request ({exc})"}
        else:
            assert self.control is not None
            reply = await self.control(request)
        try:
            query.reply(zenoh_io.control_key(self.vehicle), zenoh_io.json_bytes(reply))
        finally:
            query.drop()

    # --- the publisher thread --------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._wake:
                while not (
                    self._closed
                    or self._queries
                    or self._pending_tiles
                    or (self._session is not None and self._pending_coverage)
                    or (self._session is not None and (self._pose_due or self._status))
                ):
                    self._wake.wait()
                if self._closed:
                    return
                session = self._session
                pending, self._pending_tiles = self._pending_tiles, {}
                queries, self._queries = self._queries, []
                coverage: dict[str, CoverageMessage] = {}
                if session is not None:
                    coverage, self._pending_coverage = self._pending_coverage, {}
            self._put_pose_and_status(session)
            for survey, message in coverage.items():
                assert session is not None
                self._put_coverage(session, survey, message)
            with self._tile_order:
                for (survey, key), update in pending.items():
                    if survey in self._finished:
                        continue  # its final tiles went out while this one waited
                    tile = self._store(survey, update)
                    if session is not None:
                        self._put_tile(session, survey, key, tile)
                    # A pose handed over meanwhile goes out now, not behind the other
                    # tiles' encoding (where the next one would replace it).
                    self._put_pose_and_status(session)
            for answer, query in queries:
                answer(query)

    def _put_pose_and_status(self, session: zenoh.Session | None) -> None:
        """Put the pose and status waiting, if any (without a session they wait, latest
        wins, for one)."""
        if session is None:
            return
        with self._wake:
            pose = None
            if self._pose_due and self._pose is not None:
                message = self._pose
                if self._refined:
                    message = message | {"refined": sorted(self._refined.values())}
                pose = zenoh_io.json_bytes(message)
                self._pose_due, self._refined = False, {}
            status, self._status = self._status, None
        v = self.vehicle
        if pose is not None and self._put(session, zenoh_io.pose_key(v), pose):
            self.stats.poses += 1
        if status is not None and self._put(session, zenoh_io.status_key(v), status):
            self.stats.statuses += 1

    def _store(self, survey: str, update: TileUpdate) -> _Tile:
        with self._lock:
            held = self._tiles.setdefault(survey, {})
            previous = held.get(update.key)
        version = max(_version_now(), previous.info.version + 1 if previous else 0)
        info = TileInfo(
            update.epsg, update.res_m, update.west, update.north, update.size_px, version
        )
        tile = _Tile(zenoh_io.encode_tile(update.values), info)
        with self._lock:
            self._tiles.setdefault(survey, {})[update.key] = tile
        return tile

    def _put(self, session: zenoh.Session, key: str, payload: bytes, **kw: Any) -> bool:
        try:
            session.put(
                key,
                payload,
                congestion_control=kw.pop("congestion_control", zenoh.CongestionControl.DROP),
                encoding=kw.pop("encoding", zenoh.Encoding.APPLICATION_JSON),
                **kw,
            )
            return True
        except Exception as exc:
            self.stats.put_errors += 1
            log.debug("zenoh put %s failed: %s", key, exc)
            return False

    def _put_tile(
        self,
        session: zenoh.Session,
        survey: str,
        key: tuple[int, int],
        tile: _Tile,
        congestion: zenoh.CongestionControl = zenoh.CongestionControl.DROP,
    ) -> None:
        if self._put(
            session,
            zenoh_io.tile_key(self.vehicle, survey, *key),
            tile.png,
            encoding=zenoh.Encoding.IMAGE_PNG,
            attachment=tile.info.to_json(),
            congestion_control=congestion,
        ):
            self.stats.tiles += 1

    def _put_coverage(self, session: zenoh.Session, survey: str, message: CoverageMessage) -> None:
        """Put a coverage publication's two keys (a final one waits for the link)."""
        v = self.vehicle
        summary = (zenoh_io.coverage_key(v, survey), zenoh_io.json_bytes(message.summary))
        raster = (zenoh_io.coverage_raster_key(v, survey), message.png)
        final = message.summary["final"]
        congestion = zenoh.CongestionControl.BLOCK if final else zenoh.CongestionControl.DROP
        if self._put(session, *summary, congestion_control=congestion) and self._put(
            session,
            *raster,
            encoding=zenoh.Encoding.IMAGE_PNG,
            attachment=message.info.to_json(),
            congestion_control=congestion,
        ):
            self.stats.coverages += 1

    def _coverage_of(self, survey: str) -> CoverageMessage | None:
        """The survey's kept coverage, else its result folder's final one (kept then)."""
        with self._lock:
            held = self._coverage.get(survey)
        if held is not None:
            return held
        found = final_message(self.surveys_dir / survey, survey, _version_now())
        if found is not None:
            with self._lock:
                found = self._coverage.setdefault(survey, found)
        return found

    def _answer(self, query: zenoh.Query) -> None:
        """Reply with every held tile whose key the query's key expression intersects."""
        self.stats.queries += 1
        try:
            wanted = query.key_expr
            for survey in self._surveys():
                if not wanted.intersects(
                    zenoh.KeyExpr(zenoh_io.tiles_selector(self.vehicle, survey))
                ):
                    continue
                for key, tile in self._tiles_of(survey).items():
                    name = zenoh_io.tile_key(self.vehicle, survey, *key)
                    if wanted.intersects(zenoh.KeyExpr(name)):
                        query.reply(
                            name,
                            tile.png,
                            encoding=zenoh.Encoding.IMAGE_PNG,
                            attachment=tile.info.to_json(),
                        )
                        self.stats.replies += 1
        except Exception as exc:
            log.warning("tile query failed", extra={"fields": {"reason": str(exc)}})
        finally:
            query.drop()

    def _answer_coverage(self, query: zenoh.Query) -> None:
        """Reply with the coverage (summary, raster) of every survey the query names."""
        self.stats.queries += 1
        v = self.vehicle
        try:
            wanted = query.key_expr
            with self._lock:
                live = set(self._coverage)
            on_disk = {p.parent.name for p in self.surveys_dir.glob("*/report.json")}
            for survey in sorted(live | on_disk):
                if not wanted.intersects(zenoh.KeyExpr(zenoh_io.coverage_selector(v, survey))):
                    continue
                message = self._coverage_of(survey)
                if message is None:
                    continue
                summary_key = zenoh_io.coverage_key(v, survey)
                if wanted.intersects(zenoh.KeyExpr(summary_key)):
                    query.reply(
                        summary_key,
                        zenoh_io.json_bytes(message.summary),
                        encoding=zenoh.Encoding.APPLICATION_JSON,
                    )
                    self.stats.replies += 1
                raster_key = zenoh_io.coverage_raster_key(v, survey)
                if wanted.intersects(zenoh.KeyExpr(raster_key)):
                    query.reply(
                        raster_key,
                        message.png,
                        encoding=zenoh.Encoding.IMAGE_PNG,
                        attachment=message.info.to_json(),
                    )
                    self.stats.replies += 1
        except Exception as exc:
            log.warning("coverage query failed", extra={"fields": {"reason": str(exc)}})
        finally:
            query.drop()

    def _surveys(self) -> list[str]:
        with self._lock:
            live = set(self._tiles)
        on_disk = {
            p.parent.parent.name for p in self.surveys_dir.glob(f"*/{TILES_DIR}/{TILES_INDEX}")
        }
        return sorted(live | on_disk)

    def _tiles_of(self, survey: str) -> dict[tuple[int, int], _Tile]:
        with self._lock:
            held = self._tiles.get(survey)
            if held is not None:
                return dict(held)
        return read_tiles(self.surveys_dir / survey / TILES_DIR)


def _version_now() -> int:
    return int(time.time() * 1000)


def _final_set(
    final: dict[tuple[int, int], tuple[npt.NDArray[np.uint8], TileInfo]],
    live: dict[tuple[int, int], _Tile],
    stamp: int,
) -> dict[tuple[int, int], _Tile]:
    """The tiles that replace a survey's ``live`` ones: the ``final`` mosaic's, and an
    empty tile for each live tile the final mosaic has no data in; each versioned after
    ``stamp`` (ms) and after the live tile it replaces."""
    out: dict[tuple[int, int], _Tile] = {}
    for key in sorted(final.keys() | live.keys()):
        previous = live.get(key)
        version = max(stamp, previous.info.version + 1 if previous else 0)
        if key in final:
            values, info = final[key]
        else:
            assert previous is not None
            info = previous.info
            values = np.zeros((info.size_px, info.size_px), np.uint8)
        info = TileInfo(info.epsg, info.res_m, info.west, info.north, info.size_px, version)
        out[key] = _Tile(zenoh_io.encode_tile(values), info)
    return out


def cut_mosaic(path: Path) -> dict[tuple[int, int], tuple[npt.NDArray[np.uint8], TileInfo]]:
    """The contract's tiles of a result folder's mosaic.tif (north-up, tile-aligned: the
    mosaic is assembled from the same grid); tiles without data are left out."""
    with rasterio.open(path) as src:
        image = src.read(1)
        transform, epsg = src.transform, src.crs.to_epsg()
    res = float(transform.a)
    size = 256
    tile_m = res * size
    col0 = round(transform.c / tile_m)
    row_top = round(transform.f / tile_m) - 1
    tiles: dict[tuple[int, int], tuple[npt.NDArray[np.uint8], TileInfo]] = {}
    for y in range(0, image.shape[0], size):
        for x in range(0, image.shape[1], size):
            block = image[y : y + size, x : x + size]
            if not block.any():
                continue
            values = np.zeros((size, size), np.uint8)
            values[: block.shape[0], : block.shape[1]] = block
            col, row = col0 + x // size, row_top - y // size
            info = TileInfo(int(epsg), res, col * tile_m, (row + 1) * tile_m, size, 0)
            tiles[(col, row)] = (values, info)
    return tiles


def write_tiles(folder: Path, tiles: dict[tuple[int, int], _Tile]) -> None:
    """Tiles as ``{col}_{row}.png`` plus ``index.json`` (their attachments), index last."""
    folder.mkdir(exist_ok=True)
    index = {}
    for (col, row), tile in tiles.items():
        (folder / f"{col}_{row}.png").write_bytes(tile.png)
        index[f"{col}_{row}"] = json.loads(tile.info.to_json())
    tmp = folder / f".{TILES_INDEX}.tmp"
    tmp.write_text(json.dumps(index))
    tmp.replace(folder / TILES_INDEX)


def read_tiles(folder: Path) -> dict[tuple[int, int], _Tile]:
    """What ``write_tiles`` wrote; an unreadable folder or tile is skipped (logged)."""
    try:
        index = json.loads((folder / TILES_INDEX).read_text())
    except (OSError, ValueError):
        return {}
    tiles = {}
    for name, raw in index.items():
        try:
            col, row = (int(part) for part in name.split("_"))
            info = TileInfo.from_json(json.dumps(raw).encode())
            tiles[(col, row)] = _Tile((folder / f"{name}.png").read_bytes(), info)
        except (OSError, ValueError) as exc:
            log.warning("stored tile unreadable", extra={"fields": {"tile": name, "why": exc}})
    return tiles
