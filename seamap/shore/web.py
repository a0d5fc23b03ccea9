"""The shore station's live map page (``seamap shore --web``): an aiohttp server on its own
thread and event loop, fed by the station's ``on_event`` hook.

The station's run thread hands each item it applied over with ``call_soon_threadsafe``
and never waits; the loop keeps its own view of every vehicle (``WebView``: the latest PNG
and ``TileInfo`` of each tile, the latest coverage summary and raster of each survey, the
track, pose, status and liveliness) and pushes each change to the open pages as
server-sent events. Routes:

- ``/`` and ``/static/...``: the page (``seamap/shore/static``, plain JavaScript; nothing
  is fetched from elsewhere);
- ``/api/state``: the view as JSON (``WebView.snapshot``);
- ``/api/tile/{vehicle}/{survey}/{col}/{row}.png?v=VERSION``: a tile's PNG as received;
- ``/api/tile/{vehicle}/{survey}/{level}/{col}/{row}.png?v=STAMP``: a tile of the survey's
  overview pyramid (``seamap.shore.pyramid``: level 0 the tiles as received, level L
  2^L x 2^L of them merged into one of the same size); STAMP is the sum of (version + 1)
  over the level-0 tiles under it, which the page computes from the tiles it knows. Built
  on a worker thread when stale;
- ``/api/coverage/{vehicle}/{survey}.png?v=VERSION``: a survey's coverage raster (PNG as
  received; RGBA, one pixel a cell, north-up);
- ``/api/events``: server-sent events. The stream opens with a ``state`` event (the
  snapshot) and goes on with ``tile``, ``pose``, ``status``, ``alive`` and ``coverage``
  (a survey's summary and raster info, sent when either comes newer) events. Each page
  has a bounded queue: one that falls behind loses what is queued and gets a fresh
  ``state`` instead, and one that takes no data for ``WRITE_TIMEOUT_S`` is dropped;
- ``/files/{vehicle}/track.geojson``, ``/files/{vehicle}/{survey}/mosaic.tif``: the
  files the station keeps under its output folder (rewritten every few seconds).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from aiohttp import web

from drivers.errors import SeamapError
from drivers.zenoh_io import CoverageInfo, TileInfo, id_problem
from seamap.shore.pyramid import Pyramid
from seamap.shore.state import ShoreEvent, TrackPoint

STATIC_DIR = Path(__file__).with_name("static")
CLIENT_QUEUE = 256
"""Events queued per page before it counts as behind (and is sent a fresh state)."""
WRITE_TIMEOUT_S = 30.0
KEEPALIVE_S = 15.0
MAX_TRACK_POINTS = 20_000
"""Track points kept per vehicle for the page; beyond it the track is thinned by half
(the full track is in ``track.geojson``)."""
START_TIMEOUT_S = 10.0
PYRAMID_WORKERS = 2
"""Threads building overview tiles: the page's requests wait for them, the loop never."""
WARM_EVERY_S = 5.0
"""At most this often, the overview tiles that new tiles made stale are built ahead of
any page's asking (up to each survey's ``Pyramid.top_level``), so a page opened on the
whole site finds them made; one worker does it, the other stays for the pages."""


def parse_web_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` (``[::1]:8080`` for IPv6) as (host, port); host 127.0.0.1 when not
    given, port 0 = a free one. SeamapError saying what is wrong."""
    host, colon, port = text.rpartition(":")
    if not colon:
        host = "127.0.0.1"
    elif host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not host or any(c.isspace() or c in "[]/" for c in host):
        raise SeamapError(f"--web {text!r}: not [HOST:]PORT (bad host)")
    if not port.isdigit() or int(port) > 65535:
        raise SeamapError(f"--web {text!r}: not [HOST:]PORT (port must be 0..65535)")
    return host, int(port)


def _finite(value: Any, depth: int = 0) -> Any:
    """``value`` with non-finite floats as None (the page's JSON.parse refuses NaN);
    nesting deeper than 20 is cut."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if depth > 20:
        return None
    if isinstance(value, dict):
        return {str(k): _finite(v, depth + 1) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v, depth + 1) for v in value]
    return value


def _tile_json(survey: str, col: int, row: int, info: TileInfo) -> dict[str, Any]:
    return {
        "survey": survey,
        "col": col,
        "row": row,
        "version": info.version,
        "epsg": info.epsg,
        "res_m": info.res_m,
        "size_px": info.size_px,
        "west": info.west,
        "north": info.north,
    }


@dataclass
class _Coverage:
    summary: dict[str, Any] | None = None
    info: CoverageInfo | None = None
    png: bytes = b""

    def to_json(self) -> dict[str, Any]:
        raster = self.info.as_dict() if self.info is not None else None
        return {"summary": self.summary, "raster": raster}


def _version(summary: dict[str, Any] | None) -> int | None:
    version = summary.get("version") if summary is not None else None
    return version if isinstance(version, int) and not isinstance(version, bool) else None


@dataclass
class _Vehicle:
    alive: bool | None = None
    status: dict[str, Any] | None = None
    pose: dict[str, Any] | None = None
    track: list[tuple[float, float, float]] = field(default_factory=list)
    """(east, north, time): each frame's latest pose, in the order the frames came."""
    track_index: dict[float, int] = field(default_factory=dict)
    """By time: the place of its point in ``track``."""
    track_epsg: int | None = None
    tiles: dict[str, dict[tuple[int, int], tuple[TileInfo, bytes]]] = field(default_factory=dict)
    """By survey, by (col, row): the latest info and PNG."""
    coverage: dict[str, _Coverage] = field(default_factory=dict)
    """By survey: its latest summary and raster."""
    pyramids: dict[str, Pyramid] = field(default_factory=dict)
    """By survey: its overview levels over ``tiles``."""


class WebView:
    """What the page shows, kept on the server's loop: ``apply`` a station event, read a
    ``snapshot`` or a tile. The display CRS (``epsg``) is the first tile's (or, before any
    tile, the first pose's); the page draws what lies in it."""

    def __init__(self) -> None:
        self.vehicles: dict[str, _Vehicle] = {}
        self.epsg: int | None = None

    def apply(self, event: ShoreEvent) -> dict[str, Any] | None:
        """Take ``event``; the page event it makes ({"event": kind, "data": ...}), or None
        when it changes nothing shown."""
        if id_problem(event.vehicle):
            return None
        held = self.vehicles.setdefault(event.vehicle, _Vehicle())
        data: dict[str, Any] = {"vehicle": event.vehicle}
        if event.kind == "tile" and event.info is not None and not id_problem(event.survey):
            info = event.info
            held.tiles.setdefault(event.survey, {})[(event.col, event.row)] = (info, event.payload)
            pyramid = held.pyramids.setdefault(event.survey, Pyramid(info.size_px))
            pyramid.put(event.col, event.row, info.version, event.payload)
            self.epsg = self.epsg if self.epsg is not None else info.epsg
            data.update(_tile_json(event.survey, event.col, event.row, info))
        elif event.kind == "pose" and event.point is not None:
            p = event.point
            epsg = _pose_epsg(event.payload)
            self.epsg = self.epsg if self.epsg is not None or epsg is None else epsg
            if epsg != held.track_epsg:
                held.track, held.track_epsg = [], epsg  # a track lies in one CRS
                held.track_index = {}
            _place(held, p, append=True)
            moved = [m for q in event.refined for m in _place(held, q, append=False)]
            if len(held.track) > MAX_TRACK_POINTS:
                held.track = [*held.track[:-1:2], held.track[-1]]
                held.track_index = {t: k for k, (_e, _n, t) in enumerate(held.track)}
            held.pose = data | {
                "time": p.time, "lat": p.lat, "lon": p.lon, "east": p.east,
                "north": p.north, "heading_deg": p.heading_deg, "epsg": epsg,
            }  # fmt: skip
            data = held.pose | {"refined": moved}
        elif event.kind == "status" and isinstance(event.status, dict):
            held.status = _finite(event.status)
            data["status"] = held.status
        elif event.kind == "alive" and event.alive is not None:
            held.alive = bool(event.alive)
            data["alive"] = held.alive
        elif event.kind in ("coverage", "coverage_raster") and not id_problem(event.survey):
            if not self._take_coverage(held, event):
                return None
            coverage = held.coverage[event.survey]
            data.update({"survey": event.survey, **coverage.to_json()})
            return {"event": "coverage", "data": data}
        else:
            return None
        return {"event": event.kind, "data": data}

    def _take_coverage(self, held: _Vehicle, event: ShoreEvent) -> bool:
        """Hold a coverage summary or raster if newer than the one held (the station
        hands over only newer ones; the page relies on it, so it is checked again)."""
        coverage = held.coverage.get(event.survey) or _Coverage()
        if event.kind == "coverage":
            version = _version(event.summary)
            held_version = _version(coverage.summary)
            if event.summary is None or version is None:
                return False
            if held_version is not None and version <= held_version:
                return False
            coverage.summary = _finite(event.summary)
        else:
            info = event.coverage_info
            if info is None or not event.payload:
                return False
            if coverage.info is not None and info.version <= coverage.info.version:
                return False
            coverage.info, coverage.png = info, event.payload
            self.epsg = self.epsg if self.epsg is not None else info.epsg
        held.coverage[event.survey] = coverage
        return True

    def snapshot(self) -> dict[str, Any]:
        """Every vehicle: alive, status, pose, track ([east, north, time] in ``track_epsg``:
        each frame's latest pose, as the boat refined it),
        surveys (their grid and tiles: col, row, version, west, north) and coverage (by
        survey: ``summary`` as the boat published it, ``raster`` its ``CoverageInfo`` with
        the top-left corner in UTM metres; either None until it came)."""
        vehicles = {}
        for name, held in sorted(self.vehicles.items()):
            surveys = {}
            for survey, tiles in sorted(held.tiles.items()):
                info = next(iter(tiles.values()))[0]
                surveys[survey] = {
                    "epsg": info.epsg,
                    "res_m": info.res_m,
                    "size_px": info.size_px,
                    "tiles": [
                        {"col": c, "row": r, "version": i.version, "west": i.west, "north": i.north}
                        for (c, r), (i, _png) in sorted(tiles.items())
                    ],
                }
            vehicles[name] = {
                "alive": held.alive,
                "status": held.status,
                "pose": held.pose,
                "track": held.track,
                "track_epsg": held.track_epsg,
                "surveys": surveys,
                "coverage": {s: c.to_json() for s, c in sorted(held.coverage.items())},
            }
        return {"epsg": self.epsg, "vehicles": vehicles}

    def tile(self, vehicle: str, survey: str, col: int, row: int) -> tuple[TileInfo, bytes] | None:
        held = self.vehicles.get(vehicle)
        return held.tiles.get(survey, {}).get((col, row)) if held is not None else None

    def pyramid(self, vehicle: str, survey: str) -> Pyramid | None:
        held = self.vehicles.get(vehicle)
        return held.pyramids.get(survey) if held is not None else None

    def coverage_raster(self, vehicle: str, survey: str) -> tuple[CoverageInfo, bytes] | None:
        held = self.vehicles.get(vehicle)
        coverage = held.coverage.get(survey) if held is not None else None
        if coverage is None or coverage.info is None:
            return None
        return coverage.info, coverage.png


def _place(held: _Vehicle, point: TrackPoint, append: bool) -> list[list[float]]:
    """Put ``point`` on the track in place of the point of its time, or (``append``) at
    its end when there is none; the [east, north, time] placed (none or one)."""
    placed = (round(point.east, 3), round(point.north, 3), point.time)
    at = held.track_index.get(point.time)
    if at is not None:
        held.track[at] = placed
    elif append:
        held.track_index[point.time] = len(held.track)
        held.track.append(placed)
    else:
        return []
    return [list(placed)]


def _pose_epsg(payload: bytes) -> int | None:
    """The pose JSON's ``epsg``, None when it has none usable."""
    try:
        epsg = json.loads(payload).get("epsg")
    except (ValueError, AttributeError):
        return None
    return epsg if isinstance(epsg, int) and 32601 <= epsg <= 32760 else None


def _png_response(request: web.Request, png: bytes, version: int, header: str) -> web.Response:
    """A PNG held at ``version``. The URL names the version (``?v=``): cache it for good
    when it is the one held."""
    fresh = request.query.get("v") == str(version)
    cache = "public, max-age=31536000, immutable" if fresh else "no-cache"
    headers = {"Cache-Control": cache, header: str(version)}
    return web.Response(body=png, content_type="image/png", headers=headers)


def _sse(kind: str, data: Any) -> bytes:
    text = json.dumps(data, separators=(",", ":"), allow_nan=False, default=str)
    return f"event: {kind}\ndata: {text}\n\n".encode()


_RESYNC = b""
"""Queued for a page that fell behind: send it a fresh state."""
_CLOSE = b"close"


class _Page:
    """One open event stream: its bounded queue and whether it fell behind."""

    def __init__(self, bound: int) -> None:
        self.queue: asyncio.Queue[bytes] = asyncio.Queue(bound)
        self.behind = False

    def push(self, message: bytes) -> bool:
        """Queue ``message``; False when the page just fell behind (its queue emptied and a
        resync queued instead)."""
        if self.behind:
            return True
        try:
            self.queue.put_nowait(message)
            return True
        except asyncio.QueueFull:
            self.behind = True
            while not self.queue.empty():
                self.queue.get_nowait()
            self.queue.put_nowait(_RESYNC)
            return False

    def end(self) -> None:
        while not self.queue.empty():
            self.queue.get_nowait()
        self.queue.put_nowait(_CLOSE)


@dataclass
class WebStats:
    events: int = 0
    """Station events taken."""
    pages: int = 0
    """Event streams open now."""
    resyncs: int = 0
    """Times a page fell behind and was sent a fresh state instead of its queue."""
    dropped_pages: int = 0
    """Pages dropped after taking no data for ``WRITE_TIMEOUT_S``."""


class WebServer:
    """The page's server on its own thread and event loop. ``start`` (returns the page's
    URL; SeamapError when it cannot listen), ``on_event`` (from any thread, never blocks),
    ``close``. ``out_dir`` is the station's output folder, whose files it serves."""

    def __init__(
        self,
        host: str,
        port: int,
        out_dir: Path,
        *,
        client_queue: int = CLIENT_QUEUE,
        write_timeout_s: float = WRITE_TIMEOUT_S,
    ) -> None:
        self.host, self.port, self.out_dir = host, port, out_dir
        self.view = WebView()
        self.stats = WebStats()
        self.url = ""
        self._client_queue = client_queue
        self._write_timeout_s = write_timeout_s
        self._pages: set[_Page] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: str | None = None
        self._builders = ThreadPoolExecutor(PYRAMID_WORKERS, thread_name_prefix="shore-pyramid")
        self._warm_due: asyncio.TimerHandle | None = None
        self._warming = False

    # --- life cycle (the caller's thread) ---------------------------------------------------

    def start(self) -> str:
        self._thread = threading.Thread(target=self._main, name="shore-web", daemon=True)
        self._thread.start()
        if not self._ready.wait(START_TIMEOUT_S):
            raise SeamapError(f"--web {self._where()}: the page's server did not start")
        if self._error is not None:
            self._thread.join()
            raise SeamapError(f"--web {self._where()}: cannot serve the page ({self._error})")
        return self.url

    def close(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is not None and thread is not None and thread.is_alive():
            with contextlib.suppress(RuntimeError):  # the loop has already closed
                loop.call_soon_threadsafe(self._shutdown)
            thread.join(timeout=START_TIMEOUT_S)
        self._builders.shutdown(wait=False, cancel_futures=True)

    def on_event(self, event: ShoreEvent) -> None:
        """Hand a station event to the loop (called on the station's run thread)."""
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # closing
            loop.call_soon_threadsafe(self._take, event)

    def _where(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"

    # --- the loop's thread --------------------------------------------------------------------

    def _main(self) -> None:
        loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._listen())
        except OSError as exc:
            self._error = exc.strerror or str(exc)
        except Exception as exc:  # e.g. a host name that does not resolve
            self._error = f"{type(exc).__name__}: {exc}"
        if self._error is not None:
            if self._runner is not None:
                loop.run_until_complete(self._runner.cleanup())
            loop.close()
            self._ready.set()
            return
        self._loop = loop
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            if self._runner is not None:
                loop.run_until_complete(self._runner.cleanup())
            loop.close()

    async def _listen(self) -> None:
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_static("/static/", STATIC_DIR, append_version=False)
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/api/tile/{vehicle}/{survey}/{col}/{row}.png", self._tile)
        app.router.add_get("/api/tile/{vehicle}/{survey}/{level}/{col}/{row}.png", self._level_tile)
        app.router.add_get("/api/coverage/{vehicle}/{survey}.png", self._coverage)
        app.router.add_get("/api/events", self._events)
        app.router.add_get("/files/{vehicle}/track.geojson", self._track_file)
        app.router.add_get("/files/{vehicle}/{survey}/mosaic.tif", self._mosaic_file)
        self._runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
        await self._runner.setup()
        await web.TCPSite(self._runner, self.host, self.port).start()
        port = self._runner.addresses[0][1]
        host = f"[{self.host}]" if ":" in self.host else self.host
        self.url = f"http://{host}:{port}/"

    def _shutdown(self) -> None:
        for page in self._pages:
            page.end()
        assert self._loop is not None
        # Let the streams see their end before the loop stops.
        self._loop.call_later(0.05, self._loop.stop)

    def _take(self, event: ShoreEvent) -> None:
        self.stats.events += 1
        try:
            change = self.view.apply(event)
        except Exception:  # the station hands over what it took; stay up whatever it is
            return
        if change is None:
            return
        if change["event"] == "tile" and self._warm_due is None:
            assert self._loop is not None
            self._warm_due = self._loop.call_later(WARM_EVERY_S, self._warm)
        if not self._pages:
            return
        message = _sse(change["event"], change["data"])
        for page in self._pages:
            if not page.push(message):
                self.stats.resyncs += 1

    def _warm(self) -> None:
        """Build the stale overview tiles on a worker (one warm-up at a time; tiles that
        come meanwhile wait for the next)."""
        self._warm_due = None
        if self._warming:
            assert self._loop is not None
            self._warm_due = self._loop.call_later(WARM_EVERY_S, self._warm)
            return
        pyramids = [p for held in self.view.vehicles.values() for p in held.pyramids.values()]

        def warm_all() -> None:
            try:
                for pyramid in pyramids:
                    pyramid.warm()
            finally:
                self._warming = False

        self._warming = True
        try:
            self._builders.submit(warm_all)
        except RuntimeError:  # closing
            self._warming = False

    # --- routes -------------------------------------------------------------------------------

    async def _index(self, _request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})

    async def _state(self, _request: web.Request) -> web.Response:
        text = json.dumps(self.view.snapshot(), separators=(",", ":"), default=str)
        return web.Response(text=text, content_type="application/json")

    async def _tile(self, request: web.Request) -> web.Response:
        match = request.match_info
        try:
            col, row = int(match["col"]), int(match["row"])
        except ValueError:
            raise web.HTTPNotFound() from None
        held = self.view.tile(match["vehicle"], match["survey"], col, row)
        if held is None:
            raise web.HTTPNotFound()
        info, png = held
        return _png_response(request, png, info.version, "X-Tile-Version")

    async def _level_tile(self, request: web.Request) -> web.Response:
        match = request.match_info
        try:
            level, col, row = int(match["level"]), int(match["col"]), int(match["row"])
        except ValueError:
            raise web.HTTPNotFound() from None
        pyramid = self.view.pyramid(match["vehicle"], match["survey"])
        if pyramid is None or pyramid.stamp(level, col, row) is None:
            raise web.HTTPNotFound()
        loop = asyncio.get_running_loop()
        try:
            held = await loop.run_in_executor(self._builders, pyramid.tile, level, col, row)
        except RuntimeError:  # closing: the workers are gone
            raise web.HTTPServiceUnavailable() from None
        if held is None:
            raise web.HTTPNotFound()
        stamp, png = held
        return _png_response(request, png, stamp, "X-Tile-Stamp")

    async def _coverage(self, request: web.Request) -> web.Response:
        match = request.match_info
        held = self.view.coverage_raster(match["vehicle"], match["survey"])
        if held is None:
            raise web.HTTPNotFound()
        info, png = held
        return _png_response(request, png, info.version, "X-Coverage-Version")

    async def _events(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                "Content-Type": "text/event-stream",
                "Cache-Control": "no-cache",
                "X-Accel-Buffering": "no",
            }
        )
        await response.prepare(request)
        page = _Page(self._client_queue)
        # The snapshot and the page's registration happen in one step on the loop: no
        # event falls between them.
        first = _sse("state", self.view.snapshot())
        self._pages.add(page)
        self.stats.pages += 1
        try:
            message = first
            while message != _CLOSE:
                await asyncio.wait_for(response.write(message), self._write_timeout_s)
                try:
                    message = await asyncio.wait_for(page.queue.get(), KEEPALIVE_S)
                except TimeoutError:
                    message = b": keep-alive\n\n"
                if message == _RESYNC:
                    page.behind = False
                    message = _sse("state", self.view.snapshot())
        except TimeoutError:
            self.stats.dropped_pages += 1
        except (ConnectionError, asyncio.CancelledError):
            pass  # the page went away
        finally:
            self._pages.discard(page)
            self.stats.pages -= 1
        return response

    async def _track_file(self, request: web.Request) -> web.StreamResponse:
        vehicle = request.match_info["vehicle"]
        return self._file(Path(vehicle, "track.geojson"), f"{vehicle}-track.geojson", vehicle)

    async def _mosaic_file(self, request: web.Request) -> web.StreamResponse:
        vehicle, survey = request.match_info["vehicle"], request.match_info["survey"]
        name = f"{vehicle}-{survey}-mosaic.tif"
        return self._file(Path(vehicle, survey, "mosaic.tif"), name, vehicle, survey)

    def _file(self, relative: Path, name: str, *ids: str) -> web.StreamResponse:
        if any(id_problem(i) for i in ids):
            raise web.HTTPNotFound()
        path = self.out_dir / relative
        if not path.is_file():
            raise web.HTTPNotFound(text=f"{relative} is not written yet (the station writes it "
                                   "every few seconds once it holds data)")  # fmt: skip
        headers = {"Content-Disposition": f'attachment; filename="{name}"'}
        return web.FileResponse(path, headers=headers)


__all__ = ["WebServer", "WebStats", "WebView", "parse_web_address"]
