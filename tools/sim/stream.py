"""A simulated survey as an in-process stream of typed samples, without any file.

``survey_events(scenario, seed, **overrides)`` gives a ``SimStream`` whose ``events``
yield ``(arrival_time, sample)`` in arrival order (UNIX s of the boat computer's clock,
non-decreasing): ``ImuSample``, ``GnssFix``, ``HeadingSample``, ``AttitudeSample`` (and
``RangeSample`` when the boat has an echosounder and the drivers convert its messages) as
``drivers.mavlink.read_nav_log`` reads them from the nav.tlog that ``simulate`` writes for
the same arguments (its default "auto" sources: RAW_IMU for ArduPilot or HIGHRES_IMU for
PX4, GPS_RAW_INT, the ATTITUDE heading), and ``Ping`` as
``drivers.oculus.logfile.iter_pings`` reads them from the sonar.oculus.

Equality with the files holds by construction, not by imitation: the stream runs the
simulator's own code (``survey.prepare_survey``: motion, ping plan, seabed, sensors, the
tlog's message tables and link delays) and then, per event, does what the file and the
driver would do with it: each MAVLink message is built from the same table, packed with
pymavlink, decoded by pymavlink's parser and converted by ``drivers.mavlink.convert``
(so degE7, mm, cdeg, milli-g and float32 quantisation are the driver's); each ping is
rendered, encoded as the same SimplePingResult and decoded by
``drivers.oculus.ping.parse_simple_ping`` with the receive time the log item carries.
Samples of one kind come in the reader's order (receive stamp, then log order); an
ATTITUDE message gives its AttitudeSample, then its HeadingSample; a ping received at the
same time as a nav message comes after it.

Memory. The setup (motion on a 200 Hz grid, sensor tracks) is transient; what the stream
keeps is the seabed maps, per-ping arrays (truth, poses' rotations, times) and the nav
messages as compact integer/float arrays (about 60 bytes per IMU message); sample objects
and pings are made one at a time as the iterator advances, so memory does not grow as it
runs. Setup takes a few seconds for the 2-hour ``hectare`` survey.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import all as mavlink_all
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from daemon.config import SiteConfig
from drivers.mavlink import convert
from drivers.oculus.ping import parse_simple_ping
from mapping.samples import Ping
from tools.sim import writer
from tools.sim.pings import PingSource, mean_altitude
from tools.sim.scenarios import Scenario, resolve_scenario
from tools.sim.survey import prepare_survey
from tools.sim.tlog import AUTOPILOT_COMPID, AUTOPILOT_SYSID, MessageTable, TlogPlan, merge_order

FloatArray = npt.NDArray[np.float64]
Event = tuple[float, object]
_Converter = Callable[[Any, float], object | None]
_CHUNK = 4096


@dataclass(frozen=True)
class StreamTruth:
    """The true state at each ping's acquisition (arrays indexed by ping number).

    ping_id; acquisition_time and receive_time (UNIX s); east/north: the GPS antenna (the
    vehicle reference point) in UTM metres of ``SimStream.epsg``; grid_heading_rad: grid
    heading, radians clockwise from UTM grid north in [0, 2 pi); sonar_east/sonar_north:
    the sonar head (UTM m); altitude_m: the head above the seabed's mean plane (m). The
    same numbers as truth.json's ``pings`` (there rounded, headings in degrees).
    """

    ping_id: npt.NDArray[np.int64]
    acquisition_time: FloatArray
    receive_time: FloatArray
    east: FloatArray
    north: FloatArray
    grid_heading_rad: FloatArray
    sonar_east: FloatArray
    sonar_north: FloatArray
    altitude_m: FloatArray


@dataclass(frozen=True)
class NavSources:
    """The sources the stream's nav samples come from, named as ``NavLog`` names them."""

    imu: str | None
    heading: str | None
    gnss: str | None
    autopilot: str


@dataclass
class SimStream:
    """A simulated survey in memory (see the module doc).

    events: single-use iterator of (arrival time UNIX s, sample), non-decreasing in time.
    site_config: the SiteConfig ``simulate`` writes as site.toml. ping_count: pings the
    events will give. epsg: the site's UTM zone; utm_origin: the UTM (east, north) of the
    scenario's local frame origin (its positions, e.g. ``quadrat_centre_east_m``, are
    metres from there). start_time/end_time/duration_s: the nav log's span (UNIX s, s).
    truth: per-ping true poses (``truth_pose`` reads one). nav_sources: which messages
    the nav samples come from.
    """

    scenario: Scenario
    """The scenario of the field day (the seed's drawn values in place)."""
    seed: int
    events: Iterator[Event]
    site_config: SiteConfig
    ping_count: int
    epsg: int
    utm_origin: tuple[float, float]
    start_time: float
    end_time: float
    truth: StreamTruth
    nav_sources: NavSources

    @property
    def duration_s(self) -> float:
        return self.end_time - self.start_time

    def truth_pose(self, ping_index: int) -> tuple[float, float, float]:
        """(east, north, grid_heading_rad) of the antenna at ping ``ping_index``'s
        acquisition: UTM metres and radians clockwise from grid north."""
        t = self.truth
        k = ping_index
        return float(t.east[k]), float(t.north[k]), float(t.grid_heading_rad[k])


def _pick_table(plan: TlogPlan, names: tuple[str, ...]) -> MessageTable | None:
    present = {t.name: t for t in plan.tables if len(t)}
    return next((present[n] for n in names if n in present), None)


def _nav_tables(
    plan: TlogPlan, autopilot: str
) -> tuple[list[tuple[MessageTable, list[_Converter]]], NavSources]:
    """The tables the reader takes samples from with its "auto" choices, each with the
    conversions it applies to every message (in the reader's order), in log order."""
    imu_names = [n for n in convert.IMU_AUTO_ORDER if convert.imu_source_usable(n, autopilot)]
    heading_names = [n for n in convert.HEADING_AUTO_ORDER if n in convert.HEADING_MESSAGES]
    imu = _pick_table(plan, tuple(convert.IMU_MESSAGES[n] for n in imu_names))
    gnss = _pick_table(plan, convert.GNSS_MESSAGES)
    heading = _pick_table(plan, tuple(convert.HEADING_MESSAGES[n] for n in heading_names))
    attitude = _pick_table(plan, ("ATTITUDE",))
    # (A log without any plain heading would give a compass heading: not simulated.)
    # Soundings: a downward DISTANCE_SENSOR outranks RANGEFINDER, as in the reader.
    sounding = convert.range_from_mavlink
    ranges = _pick_table(plan, ("DISTANCE_SENSOR", "RANGEFINDER"))
    converters: dict[str, list[_Converter]] = {}
    for table, function in (
        (attitude, convert.attitude_from_mavlink),
        (imu, convert.imu_from_mavlink),
        (gnss, convert.gnss_from_mavlink),
        (heading, convert.heading_from_mavlink),
        (ranges, sounding),
    ):
        if table is not None and function is not None:
            converters.setdefault(table.name, []).append(function)
    imu_source = {m: n for n, m in convert.IMU_MESSAGES.items()}
    heading_source = {m: n for n, m in convert.HEADING_MESSAGES.items()}
    sources = NavSources(
        imu=imu_source[imu.name] if imu else None,
        heading=heading_source[heading.name] if heading else None,
        gnss=gnss.name if gnss else None,
        autopilot=autopilot,
    )
    return [(t, converters[t.name]) for t in plan.tables if t.name in converters], sources


def _nav_events(tables: list[tuple[MessageTable, list[_Converter]]]) -> Iterator[Event]:
    """Each message built, packed, decoded and converted, in log order."""
    sender = mavlink.MAVLink(None, AUTOPILOT_SYSID, AUTOPILOT_COMPID)
    parser = mavlink_all.MAVLink(None)
    order, which, index = merge_order(tuple(t for t, _ in tables))
    stamps = np.concatenate([t.stamps for t, _ in tables])
    for first in range(0, len(order), _CHUNK):  # Python ints for a chunk at a time
        chunk = order[first : first + _CHUNK]
        for w, k, stamp in zip(
            which[chunk].tolist(), index[chunk].tolist(), stamps[chunk].tolist(), strict=True
        ):
            table, functions = tables[w]
            msg = parser.decode(bytearray(table.build(k).pack(sender)))
            time = stamp * 1.0e-6  # as drivers.mavlink.framing stamps a tlog record
            for function in functions:
                sample = function(msg, time)
                if sample is not None:
                    yield time, sample


def _ping_events(
    source: PingSource, on_message: Callable[[bytes, float], None] | None = None
) -> Iterator[tuple[float, Ping]]:
    """Each ping rendered, encoded and decoded as iter_pings reads it from the log (the
    encoded message and its receive time to ``on_message`` first, e.g. to record it)."""
    for message, receive in zip(source, source.plan.receive.tolist(), strict=True):
        if on_message is not None:
            on_message(message, receive)
        yield receive, parse_simple_ping(message, receive)


def _merge(
    nav: Iterator[Event], pings: Iterator[tuple[float, Ping]], receive: FloatArray
) -> Iterator[Event]:
    """Nav events and pings in arrival order; a ping is rendered only when it is its turn
    (``receive``: the pings' receive times), after the nav events of the same time."""
    times = receive.tolist()
    k, n = 0, len(times)
    for time, sample in nav:
        while k < n and times[k] < time:
            yield next(pings)
            k += 1
        yield time, sample
    yield from pings


def _truth(source: PingSource, east0: float, north0: float) -> StreamTruth:
    at, plan = source.frames.state, source.plan
    return StreamTruth(
        ping_id=plan.ids,
        acquisition_time=plan.acquisition,
        receive_time=plan.receive,
        east=at["east"] + east0,
        north=at["north"] + north0,
        grid_heading_rad=np.mod(at["heading"], 2 * math.pi),
        sonar_east=at["sonar_east"] + east0,
        sonar_north=at["sonar_north"] + north0,
        altitude_m=at["altitude"],
    )


def _release_memory() -> None:
    """Give the setup's freed memory back to the system (glibc keeps freed heap pages
    otherwise, and a benchmark would see them as the stream's): collect, then
    ``malloc_trim(0)`` where the C library has it."""
    gc.collect()
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        if libc is not None and hasattr(libc, "malloc_trim"):
            libc.malloc_trim(0)
    except OSError:
        pass


def survey_events(
    scenario: str,
    seed: int,
    on_ping_message: Callable[[bytes, float], None] | None = None,
    **overrides: Any,
) -> SimStream:
    """Stream survey ``scenario`` with ``seed``; ``overrides`` as for ``simulate`` (e.g.
    ``max_pings``, ``duration_s``, ``n_beams``, ``flavour``). The events equal what the
    drivers read from the files ``simulate`` writes for the same arguments; SeamapError
    for a bad name, key or value. ``on_ping_message`` sees each ping's Oculus message and
    receive time as it is rendered (a recorder, as on the boat)."""
    s = resolve_scenario(scenario, **overrides)
    setup = prepare_survey(s, seed)
    s = setup.scenario  # the field day's
    source = setup.ping_source()
    autopilot = "px4" if s.flavour == "px4" else "ardupilot"
    # The sensor tracks and the dense motion are dropped once the tables hold what the
    # messages need.
    tables, sources = _nav_tables(setup.tlog_plan(setup.nav_streams()), autopilot)
    site, start, end = setup.site, setup.start, setup.end
    events = _merge(_nav_events(tables), _ping_events(source, on_ping_message), source.plan.receive)
    del setup
    _release_memory()
    return SimStream(
        scenario=s,
        seed=seed,
        events=events,
        site_config=writer.site_config(s, mean_altitude(s, source.frames)),
        ping_count=len(source.plan),
        epsg=site.epsg,
        utm_origin=(site.utm_east0, site.utm_north0),
        start_time=start,
        end_time=end,
        truth=_truth(source, site.utm_east0, site.utm_north0),
        nav_sources=sources,
    )
