"""The whole system on one machine, on loopback (what ``seamap demo`` and ``make demo`` run).

1. The simulator makes a survey (the paper's quadrat site by default) for each boat
   (``--boats N``: neighbouring areas, 24 m apart to the east, one seed each).
2. The sonar and autopilot emulators play each on 127.0.0.1 on one clock
   (``tools.emulators.playback``); each boat's real daemon (``seamap run``, a child process)
   records and maps it live and publishes on zenoh through a zenoh router (``seamap
   router``, a child; its endpoint ``tcp/127.0.0.1:7447`` unless told otherwise; vehicle
   ``demo``, then ``demo2``, ``demo3``...); the shore station (``seamap shore``, another
   child) follows every boat, and with ``--web`` serves the live map page.
   Each daemon knows its survey's area (the simulator's ``area.geojson``, as ``[mission]
   area``): its status and zenoh carry the covered fraction as it maps.
3. At the end of the playback a survey stop request goes over zenoh to each boat, as the
   shore would send it; the survey-end passes write the result folders (with the area's
   gaps, ``gaps.geojson``, and with ``[mission] replan_at_end`` the lanes back to them)
   and publish the final tiles and coverage; the shore's mosaics are compared with the
   daemons'.
4. Accuracy against the simulator's truth: the truth's ping times are moved to the
   times the daemon stamped on receipt (matched by ping id), and the recorded survey is
   scored by replaying it — the same computation as the daemon's survey-end pass.

With ``--secure`` the one boat's daemon is the zenoh endpoint itself (a peer with TLS, the
shore's password and the boat's access rules from ``seamap security init``), without a
router: the security set is made for one boat and its shores.
"""

from __future__ import annotations

import asyncio
import contextlib
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

from daemon.config import SiteConfig, ZenohConfig, config_from_dict, dump_config, load_config
from daemon.control import request
from drivers.errors import SeamapError
from drivers.oculus.logfile import iter_pings
from drivers.zenoh_io import control_key, open_session
from tools.emulators.playback import SurveyPlayback
from tools.sim import simulate

VEHICLE = "demo"
SEAMAP = str(Path(sys.executable).parent / "seamap")
SHORE_WAIT_S = 30.0
"""How long the shore may take to hold the final tiles and rewrite its mosaic (it writes
every 5 s)."""
NEIGHBOUR_EAST_M = 24.0
"""How far east each next boat's survey lies (the quadrat site's lanes span 8 m)."""
MAX_BOATS = 4


@dataclass(frozen=True)
class DemoOptions:
    out: Path
    scenario: str = "quadrats"
    seed: int = 1
    zenoh_listen: str = "tcp/127.0.0.1:7447"
    """The router's endpoint (the boat's own with ``secure``)."""
    max_pings: int | None = None
    secure: bool = False
    """Run the link on a set ``seamap security init`` makes (TLS with certificates on both
    sides, the shore's password, the boat's access rules), on the same port, one boat, no
    router."""
    boats: int = 1
    web: str | None = None
    """``[HOST:]PORT`` of the shore's live map page; the demo then stays up after the
    surveys until SIGINT or SIGTERM."""


@dataclass(frozen=True)
class _Link:
    """The daemons' [zenoh] table and the shore's (through the router, or the set's)."""

    boat: ZenohConfig
    shore: ZenohConfig
    shore_config: Path | None
    """A site file holding the shore's [zenoh] (secure), else None (``--connect``)."""
    router: str | None
    """The router's listen endpoint (None: the boat is the endpoint)."""


@dataclass
class _Boat:
    vehicle: str
    sim: Path
    state_dir: Path
    log: Path
    config: Path | None = None
    play: SurveyPlayback | None = None
    daemon: asyncio.subprocess.Process | None = None
    status: dict[str, Any] = dataclasses.field(default_factory=dict)


def vehicle_ids(boats: int) -> list[str]:
    """``demo``, ``demo2``, ``demo3``...: the first is the contract's demo vehicle."""
    return [VEHICLE if n == 1 else f"{VEHICLE}{n}" for n in range(1, boats + 1)]


def _link(options: DemoOptions) -> _Link:
    listen = options.zenoh_listen
    connect = _connect_of(listen)
    if not options.secure:
        return _Link(
            ZenohConfig(mode="client", listen=[], connect=[connect]),
            ZenohConfig(mode="client", listen=[], connect=[connect]),
            None,
            listen,
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
    return _Link(boat, shore, shore_site, None)


def _free_port(kind: int) -> int:
    import socket

    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _step(n: int, text: str) -> None:
    print(f"[{n}/5] {text}", flush=True)


def run_demo(options: DemoOptions) -> int:
    """Run the demo; 0 on success. SeamapError for what the user can fix (a busy port...)."""
    if not 1 <= options.boats <= MAX_BOATS:
        raise SeamapError(f"--boats {options.boats}: 1 to {MAX_BOATS}")
    if options.secure and options.boats > 1:
        raise SeamapError("--secure runs one boat (its security set is made for one boat)")
    out = options.out
    boats = []
    for n, vehicle in enumerate(vehicle_ids(options.boats)):
        one = options.boats == 1
        sim = out / ("sim" if one else f"sim-{vehicle}")
        boats.append(
            _Boat(vehicle, sim, out / ("boat" if one else f"boat-{vehicle}"),
                  out / ("daemon.log" if one else f"daemon-{vehicle}.log"))
        )  # fmt: skip
        seed = options.seed + n
        where = f" {NEIGHBOUR_EAST_M * n:.0f} m east of the first" if n else ""
        _step(1, f"simulating the '{options.scenario}' survey (seed {seed}){where} into {sim}")
        started = time.monotonic()
        summary = simulate(options.scenario, seed, sim, **_neighbour(options, n))
        print(summary.describe())
        print(f"      done in {time.monotonic() - started:.1f} s", flush=True)
    return asyncio.run(_live(options, boats))


def _neighbour(options: DemoOptions, n: int) -> dict[str, Any]:
    """The simulator's overrides of boat ``n`` (0 first): its cut and, after the first,
    its site origin moved east."""
    overrides: dict[str, Any] = {"max_pings": options.max_pings}
    if n:
        from tools.sim.scenarios import resolve_scenario

        s = resolve_scenario(options.scenario)
        metres_per_degree = 111_320.0 * math.cos(math.radians(s.origin_lat_deg))
        overrides["origin_lon_deg"] = s.origin_lon_deg + NEIGHBOUR_EAST_M * n / metres_per_degree
    return overrides


async def _live(options: DemoOptions, boats: list[_Boat]) -> int:
    out = options.out
    shore_dir = out / "shore"
    link = _link(options)
    children: list[asyncio.subprocess.Process] = []
    async with contextlib.AsyncExitStack() as stack:
        _step(2, "starting the emulators, the boat daemons, the zenoh router and the shore "
                 "station on 127.0.0.1")  # fmt: skip
        if link.router is not None:
            router = await _spawn(
                [SEAMAP, "router", "--listen", link.router], out / "router.log"
            )  # fmt: skip
            children.append(router)
            await _wait_log(out / "router.log", "listening on", router)
            print(f"      router: seamap router --listen {link.router} (log {out / 'router.log'})")
        for boat in boats:
            mavlink_port = _free_port(2)  # SOCK_DGRAM
            boat.play = await stack.enter_async_context(
                SurveyPlayback(boat.sim / "sonar.oculus", boat.sim / "nav.tlog", mavlink="udp",
                               mavlink_target_port=mavlink_port)
            )  # fmt: skip
            boat.config = _daemon_config(
                boat.sim, boat.state_dir.parent / f"site-{boat.vehicle}.toml"
                if len(boats) > 1 else out / "site.toml",
                boat.state_dir, boat.play.sonar.tcp_port, mavlink_port, link.boat, boat.vehicle,
            )  # fmt: skip
            zenoh_at = link.router or link.boat.listen[0]
            print(f"      {boat.vehicle}: sonar emulator tcp/127.0.0.1:{boat.play.sonar.tcp_port}, "
                  f"autopilot emulator -> udp/127.0.0.1:{mavlink_port}, zenoh {zenoh_at}"
                  + (f" (secured by {out / 'security'})" if options.secure else ""))  # fmt: skip
            print(f"      daemon: seamap run --config {boat.config} (log {boat.log})")
            boat.daemon = await _spawn([SEAMAP, "run", "--config", str(boat.config)], boat.log)
            children.append(boat.daemon)
        reach = (
            ["--config", str(link.shore_config), "--vehicle", VEHICLE]
            if link.shore_config is not None
            else ["--connect", link.shore.connect[0]]
        )  # fmt: skip
        web = ["--web", options.web] if options.web is not None else []
        shore = await _spawn(
            [SEAMAP, "shore", *reach, "--out", str(shore_dir), *web], out / "shore.log"
        )  # fmt: skip
        children.insert(0, shore)
        print(f"      shore:  seamap shore --out {shore_dir} {' '.join(web)}".rstrip()
              + f" (log {out / 'shore.log'})", flush=True)  # fmt: skip
        try:
            if web:
                page = await _wait_log(out / "shore.log", "web: ", shore)
                print(f"      live map: {page.split('web: ', 1)[1].strip()}", flush=True)
            plays = [boat.play for boat in boats if boat.play is not None]
            await asyncio.wait_for(asyncio.gather(*(p.started.wait() for p in plays)), 60)
            total, longest = sum(p.pings_total for p in plays), max(p.pings_total for p in plays)
            _step(3, f"surveying: {total} pings, about {longest / 10:.0f} s")
            await _follow(boats)
            _step(4, "survey end: a stop request over zenoh; the survey-end pass maps it again")
            results = []
            for boat in boats:
                assert boat.daemon is not None
                survey = await asyncio.to_thread(_stop_survey, link.shore, boat.vehicle)
                folder = boat.state_dir / "surveys" / survey
                results.append((boat, folder, await _wait_done(folder, boat.daemon)))
            for boat, folder, final in results:
                shore_tif = shore_dir / boat.vehicle / folder.name / "mosaic.tif"
                same = await _wait_shore(shore_tif, folder / "mosaic.tif", SHORE_WAIT_S)
                result = final["result"]
                live = boat.status["frames"]["mapped"] if boat.status else "?"
                print(f"      {boat.vehicle}: {result['frames_mapped']} of "
                      f"{result['frames_read']} frames mapped ({live} live), survey-end pass "
                      f"{result['seconds']:.1f} s")  # fmt: skip
                print(f"      result folder: {folder} (mosaic.tif, mosaic.png, trajectory.csv, "
                      "report.json, coverage.tif, coverage.png, gaps.geojson)")  # fmt: skip
                print(f"      {_coverage_line(folder, result)}")
                _tell_shore(shore_tif, same)
            if web:
                print("      the live map page stays up: Ctrl-C (or SIGTERM) ends the demo",
                      flush=True)  # fmt: skip
                await _until_signal(children)
        finally:
            for child in children:
                if child.returncode is None:
                    child.send_signal(signal.SIGTERM)
            codes = [await asyncio.wait_for(c.wait(), 120) for c in children]
    _step(5, "accuracy against the simulator's truth")
    for boat, folder, _ in results:
        assert boat.config is not None
        if len(boats) > 1:
            print(f"      {boat.vehicle}:")
        scores = out / ("accuracy" if len(boats) == 1 else f"accuracy-{boat.vehicle}")
        _accuracy(boat.sim, folder, load_config(boat.config), scores)
    names = ["shore", *(["router"] if link.router else []), *(f"{b.vehicle} daemon" for b in boats)]
    exits = ", ".join(f"{name} exit {code}" for name, code in zip(names, codes, strict=True))
    print(f"demo output in {out.resolve()} ({exits})")
    return 0 if all(code == 0 for code in codes) else 1


async def _wait_log(log: Path, text: str, child: asyncio.subprocess.Process) -> str:
    """The first line of ``log`` holding ``text``, once the child wrote it (SeamapError if
    it stops first or takes more than 30 s)."""
    deadline = time.monotonic() + 30.0
    while True:
        for line in log.read_text(errors="replace").splitlines():
            if text in line:
                return line
        if child.returncode is not None:
            raise SeamapError(f"{log.stem} stopped (exit {child.returncode}); see {log}")
        if time.monotonic() > deadline:
            raise SeamapError(f"{log.stem} did not start in 30 s; see {log}")
        await asyncio.sleep(0.1)


async def _until_signal(children: list[asyncio.subprocess.Process]) -> None:
    """Wait for SIGINT or SIGTERM (or a child to stop)."""
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        waits: list[asyncio.Task[Any]] = [asyncio.create_task(stop.wait())]
        waits += [asyncio.create_task(child.wait()) for child in children]
        _, pending = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def _connect_of(listen: str) -> str:
    return listen.replace("0.0.0.0", "127.0.0.1")


def _daemon_config(
    sim: Path, path: Path, state_dir: Path, sonar_port: int, mavlink_port: int,
    zenoh_table: ZenohConfig, vehicle: str = VEHICLE,
) -> Path:  # fmt: skip
    import tomllib

    data: dict[str, Any] = tomllib.loads((sim / "site.toml").read_text())
    data.setdefault("daemon", {}).update(
        vehicle=vehicle, state_dir=str(state_dir), survey_autostart=True, health_interval_s=10.0
    )
    data.setdefault("sonar", {}).update(address="127.0.0.1", tcp_port=sonar_port)
    data.setdefault("mavlink", {}).update(url=f"udpin:127.0.0.1:{mavlink_port}")
    data["zenoh"] = dataclasses.asdict(zenoh_table)
    data["mission"] = {"area": str((sim / "area.geojson").resolve()), "replan_at_end": True}
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


async def _follow(boats: list[_Boat]) -> None:
    """Progress every 5 s until every playback ends; each boat's last status kept."""
    started = time.monotonic()
    plays = [boat.play for boat in boats if boat.play is not None]
    while not all(p.done.is_set() for p in plays):
        done = asyncio.gather(*(p.done.wait() for p in plays))
        await asyncio.wait({asyncio.ensure_future(done)}, timeout=5.0)
        for boat in boats:
            assert boat.daemon is not None and boat.play is not None
            if boat.daemon.returncode is not None:
                raise SeamapError(
                    f"the {boat.vehicle} daemon stopped (exit {boat.daemon.returncode}); "
                    f"see {boat.log}"
                )
            boat.status = await _status(boat.state_dir) or boat.status
            if boat.status:
                status = boat.status
                frames, links = status["frames"], status["links"]
                print(
                    f"      {time.monotonic() - started:5.0f} s  {boat.vehicle}: pings sent "
                    f"{boat.play.sonar.pings_sent}/{boat.play.pings_total}, {frames['mapped']} "
                    f"mapped, {frames['rejected']} rejected, {frames['skipped']} skipped, lag "
                    f"{status['lag_s']:.2f} s, tiles published {status.get('tiles_published', 0)}"
                    f"{_covered(status)}, sonar {'up' if links['sonar']['up'] else 'down'}, "
                    f"autopilot {'up' if links['mavlink']['up'] else 'down'}",
                    flush=True,
                )
    # The last pings leave the reorder window; the recorder flushes.
    await asyncio.sleep(1.5)
    for boat in boats:
        boat.status = await _status(boat.state_dir) or boat.status


def _covered(status: dict[str, Any]) -> str:
    """The status's covered fraction of the survey's area, as ", covered 63.4 %"."""
    coverage = status.get("coverage")
    if not coverage or not coverage.get("area"):
        return ""
    return f", covered {100 * coverage['area']['fraction']:.1f} %"


def _coverage_line(folder: Path, result: dict[str, Any]) -> str:
    """What the survey covered of its planned area, its gaps and the plan back to them."""
    report = json.loads((folder / "report.json").read_text())
    area = report["coverage"].get("area")
    if area is None:
        return f"coverage: {report['coverage']['covered_m2']:.0f} m² seen (no area known)"
    line = (
        f"coverage: {100 * area['covered_fraction']:.1f} % of the planned area "
        f"({area['area_m2']:.0f} m²), {area['gaps']} gaps of {area['gaps_m2']:.1f} m² "
        f"(gaps.geojson)"
    )
    replan = result.get("replan")
    if replan and replan.get("gaps"):
        line += (
            f"; the way back to them: {folder / 'replan.plan'} ({replan['lanes']} lanes, "
            f"{replan['distance_m']:.0f} m, `seamap survey start` to run it)"
        )
    return line


def _stop_survey(shore: ZenohConfig, vehicle: str = VEHICLE) -> str:
    session = open_session(shore)
    try:
        replies = list(
            session.get(control_key(vehicle), payload=b'{"action": "stop"}', timeout=10.0)
        )
    finally:
        session.close()
    for reply in replies:
        if reply.ok is not None:
            answer = json.loads(reply.ok.payload.to_bytes())
            if answer.get("ok") and answer.get("survey"):
                return str(answer["survey"])
    raise SeamapError(f"the {vehicle} daemon did not answer the survey stop request over zenoh")


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
    from daemon.replay import replay_survey
    from tools.evaluation.truth import truth_scorer

    truth = json.loads((sim / "truth.json").read_text())
    stamped = {p.ping_id: p.time for seg in sorted(folder.glob("sonar-*.oculus"))
               for p in iter_pings(seg)}  # fmt: skip
    pings = [dict(p, time=stamped[p["ping_id"]]) for p in truth["pings"] if p["ping_id"] in stamped]
    retimed = out / "truth-as-received.json"
    out.mkdir(parents=True, exist_ok=True)
    retimed.write_text(json.dumps(dict(truth, pings=pings)))
    report = replay_survey(folder, config, out, scorer=truth_scorer(retimed))
    accuracy = report["accuracy"]
    trajectory, spacing = accuracy["trajectory"], accuracy.get("quadrat_spacing")
    print(f"      trajectory error {trajectory['rmse']:.2f} m (GPS-limited), "
          f"{trajectory['aligned_rmse']:.3f} m in shape")  # fmt: skip
    if spacing and spacing.get("located") and math.isfinite(spacing["rmse"]):
        print(f"      quadrat spacing RMSE {spacing['rmse'] * 100:.1f} cm over "
              f"{int(spacing['located'])} quadrats")  # fmt: skip
