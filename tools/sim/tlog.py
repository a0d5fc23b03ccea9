"""Writing the simulated telemetry as a MAVLink 2 ``.tlog``.

A .tlog is a plain sequence of packets, each preceded by the boat computer's receive time
as an 8-byte big-endian count of UNIX microseconds (what MAVProxy and QGroundControl
write, and what ``pymavlink.mavutil.mavlink_connection("x.tlog")`` reads into
``msg._timestamp``).

What the autopilot (sysid 1, compid 1) streams:

- ``ardupilot`` flavour (Rover): HEARTBEAT 1 Hz (MAV_TYPE_SURFACE_BOAT,
  MAV_AUTOPILOT_ARDUPILOTMEGA, armed, AUTO = custom mode 10), SYSTEM_TIME 1 Hz, RAW_IMU at
  ``imu_rate_hz`` in ArduPilot's scaling (milli-g, mrad/s, milligauss), GPS_RAW_INT at
  ``gps_rate_hz`` (fix_type 3, or 1 without a fix during an outage; eph = HDOP x 100,
  vel cm/s, cog cdeg from true north, satellites, h_acc/v_acc mm), and at
  ``heading_rate_hz`` ATTITUDE (yaw = compass-like heading, radians from true north in
  -pi..pi), GLOBAL_POSITION_INT (hdg cdeg, position from the GPS-aided estimate, which
  knows the fix's lag; dead-reckoned with a drifting velocity error during an outage)
  and VFR_HUD (heading in whole degrees).
- ``px4`` flavour: the same but MAV_AUTOPILOT_PX4 (AUTO.MISSION custom mode), HIGHRES_IMU
  in SI units (m/s^2, rad/s, gauss) and no RAW_IMU.
- with an echosounder (``Scenario.echosounder``): DISTANCE_SENSOR at its rate (cm,
  orientation 25 = MAV_SENSOR_ROTATION_PITCH_270, signal quality; ``echosounder``), and
  on ArduPilot RANGEFINDER (metres, voltage 0) beside each; their link delays come from a
  child stream of the tlog's generator, so the other messages keep theirs.

A ground station (sysid 255, compid 190, MAV_TYPE_GCS) adds a heartbeat about once a
second, as it does in a real log. time_boot_ms / time_usec count from the autopilot's
boot (``start_time - autopilot_uptime_s``); the receive stamp is the sample time plus a
link delay (``stamp_delay_s`` + exponential jitter of mean ``stamp_jitter_s``), and the
packets are written in stamp order.

``plan_tlog`` gives the log as ``MessageTable``s (stamps plus compact field arrays, each
message built on demand), which ``write_tlog`` packs into the file and
``stream.survey_events`` turns into samples without a file.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tools.sim.echosounder import MAX_DISTANCE_M, MIN_DISTANCE_M, Soundings
from tools.sim.rngs import child_rng
from tools.sim.scenarios import Scenario
from tools.sim.sensors import GRAVITY_MPS2, CompassErrors, GpsTrack, HeadingTrack, ImuTrack
from tools.sim.site import SiteFrame
from tools.sim.trajectory import Motion

FloatArray = npt.NDArray[np.float64]

AUTOPILOT_SYSID = 1
AUTOPILOT_COMPID = 1
GCS_SYSID = 255
GCS_COMPID = 190
ROVER_MODE_AUTO = 10
PX4_CUSTOM_AUTO_MISSION = (4 << 16) | (4 << 24)
_ARMED_AUTO_BASE_MODE = (
    mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    | mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
    | mavlink.MAV_MODE_FLAG_AUTO_ENABLED
    | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
)
_GEOID_UNDULATION_M = -34.0  # WGS84 ellipsoid above mean sea level in the Chesapeake Bay


@dataclass(frozen=True)
class NavStreams:
    """The sensor tracks the tlog carries, plus the truth for GLOBAL_POSITION_INT and the
    compass's errors (for truth.json)."""

    gps: GpsTrack
    heading: HeadingTrack
    imu: ImuTrack
    motion: Motion
    compass: CompassErrors
    echosounder: Soundings | None = None


@dataclass(frozen=True)
class MessageTable:
    """One stream of the tlog: receive stamps (UNIX microseconds, in generation order) and
    a builder of its k-th pymavlink message from compact per-message arrays, so that a
    long log need not hold its messages as objects. ``sysid`` is the sender."""

    name: str
    stamps: npt.NDArray[np.int64]
    build: Callable[[int], Any]
    sysid: int = AUTOPILOT_SYSID

    def __len__(self) -> int:
        return len(self.stamps)


@dataclass(frozen=True)
class TlogPlan:
    """Every stream of the tlog, in the order the writer adds them (which breaks ties of
    equal stamps: an earlier table's message goes first). ``imu``/``gps``/``attitude``
    name the tables the navigation reader takes its samples from."""

    tables: tuple[MessageTable, ...]

    def table(self, name: str) -> MessageTable:
        """The table of messages ``name`` ("RAW_IMU", "ATTITUDE", ...)."""
        return next(t for t in self.tables if t.name == name)


class _Stamper:
    """Receive stamps and autopilot clocks, drawing the link delays from one generator."""

    def __init__(self, s: Scenario, rng: np.random.Generator) -> None:
        self.boot = s.start_time - s.autopilot_uptime_s
        self.delay_s = s.stamp_delay_s
        self.jitter_s = s.stamp_jitter_s
        self.rng = rng

    def stamps(self, times: FloatArray) -> npt.NDArray[np.int64]:
        """Receive stamps (UNIX us) of messages generated at ``times``."""
        delay = self.delay_s + np.minimum(
            self.rng.exponential(self.jitter_s, len(times)), 10 * self.jitter_s
        )
        return np.rint((np.asarray(times) + delay) * 1e6).astype(np.int64)

    def boot_ms(self, times: FloatArray) -> npt.NDArray[np.int64]:
        return np.rint((np.asarray(times) - self.boot) * 1e3).astype(np.int64)

    def boot_us(self, times: FloatArray) -> npt.NDArray[np.int64]:
        return np.rint((np.asarray(times) - self.boot) * 1e6).astype(np.int64)


def _write(path: Path, plan: TlogPlan) -> dict[str, int]:
    """Pack in stamp order (sequence numbers follow that order) and write the file."""
    senders = {
        AUTOPILOT_SYSID: mavlink.MAVLink(None, AUTOPILOT_SYSID, AUTOPILOT_COMPID),
        GCS_SYSID: mavlink.MAVLink(None, GCS_SYSID, GCS_COMPID),
    }
    order, which, index = merge_order(plan.tables)
    stamps = np.concatenate([t.stamps for t in plan.tables])[order].tolist()
    prefix = struct.Struct(">Q")
    counts: dict[str, int] = {}
    with open(path, "wb") as out:
        for stamp, w, k in zip(stamps, which[order].tolist(), index[order].tolist(), strict=True):
            table = plan.tables[w]
            sender = senders[table.sysid]
            msg = table.build(k)
            out.write(prefix.pack(stamp) + msg.pack(sender))
            sender.seq = (sender.seq + 1) % 256
            counts[table.name] = counts.get(table.name, 0) + 1
    return dict(sorted(counts.items()))


def merge_order(
    tables: tuple[MessageTable, ...],
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The order of all the tables' messages in the log: by stamp, ties in table order
    then message order. Returns (order, table number, message number), the last two
    indexed by the concatenation of the tables (``order`` permutes it)."""
    stamps = np.concatenate([t.stamps for t in tables]) if tables else np.zeros(0, np.int64)
    which = np.repeat(np.arange(len(tables), dtype=np.int64), [len(t) for t in tables])
    index = np.concatenate([np.arange(len(t), dtype=np.int64) for t in tables]) if tables else which
    return np.argsort(stamps, kind="stable"), which, index


def _times(start: float, end: float, rate_hz: float, phase: float) -> FloatArray:
    """Sample times at ``rate_hz`` from ``start + phase`` up to ``end``."""
    return np.arange(start + phase, end, 1.0 / rate_hz)


def _wrap_pi(angle: FloatArray) -> FloatArray:
    return np.mod(np.asarray(angle) + math.pi, 2 * math.pi) - math.pi


def _i(values: FloatArray) -> npt.NDArray[np.int64]:
    return np.rint(values).astype(np.int64)


def plan_tlog(
    s: Scenario,
    site: SiteFrame,
    streams: NavStreams,
    start: float,
    end: float,
    rng: np.random.Generator,
) -> TlogPlan:
    """The telemetry between ``start`` and ``end`` (UNIX s) as message tables (the link
    delays drawn from ``rng`` in a fixed order, so a plan is the same for the same rng)."""
    stamper = _Stamper(s, rng)
    px4 = s.flavour == "px4"

    # Heartbeats and the autopilot's clock.
    hb_times = _times(start, end, 1.0, 0.37)
    autopilot = mavlink.MAV_AUTOPILOT_PX4 if px4 else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    custom = PX4_CUSTOM_AUTO_MISSION if px4 else ROVER_MODE_AUTO
    base_mode = _ARMED_AUTO_BASE_MODE
    if px4:  # PX4 does not flag manual input in a mission
        base_mode &= ~mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    heartbeat = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_SURFACE_BOAT, autopilot, base_mode, custom, mavlink.MAV_STATE_ACTIVE, 3
    )
    tables = [MessageTable("HEARTBEAT", stamper.stamps(hb_times), lambda k: heartbeat)]
    st_times = _times(start, end, 1.0, 0.61)
    st_us, st_ms = st_times.tolist(), stamper.boot_ms(st_times).tolist()
    tables.append(
        MessageTable(
            "SYSTEM_TIME",
            stamper.stamps(st_times),
            lambda k: mavlink.MAVLink_system_time_message(round(st_us[k] * 1e6), st_ms[k]),
        )
    )
    gcs_times = _times(start, end, 1.0 / s.gcs_heartbeat_period_s, 0.83)
    gcs_times = gcs_times + rng.uniform(-0.05, 0.05, len(gcs_times))
    gcs = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
    )
    tables.append(
        MessageTable("HEARTBEAT", stamper.stamps(gcs_times), lambda k: gcs, sysid=GCS_SYSID)
    )
    tables.append(_imu_table(stamper, streams.imu, px4, start, end))
    tables.append(_gps_table(stamper, streams.gps, start, end))
    tables.extend(_heading_tables(stamper, s, site, streams, start, end))
    if streams.echosounder is not None:  # its link delays from a child stream of rng
        link = _Stamper(s, child_rng(rng, 1))
        tables.extend(_echosounder_tables(link, s, streams.echosounder, start, end))
    return TlogPlan(tuple(tables))


def write_tlog(path: Path, plan: TlogPlan) -> dict[str, int]:
    """Write the planned telemetry as a .tlog; returns the message counts by type."""
    return _write(path, plan)


def _window(times: FloatArray, start: float, end: float) -> npt.NDArray[np.bool_]:
    return (times >= start) & (times < end)


def _imu_table(
    stamper: _Stamper, imu: ImuTrack, px4: bool, start: float, end: float
) -> MessageTable:
    sel = _window(imu.time, start, end)
    t = imu.time[sel]
    acc, gyro, mag = imu.accel[sel], imu.gyro[sel], imu.mag[sel]
    us = stamper.boot_us(t)
    stamps = stamper.stamps(t)
    if px4:
        values = np.concatenate([acc, gyro, mag], axis=1)

        def highres(k: int) -> Any:
            return mavlink.MAVLink_highres_imu_message(
                int(us[k]), *values[k].tolist(), 1013.0, 0.0, 0.12, 31.5, 0x1FFF, 0
            )

        return MessageTable("HIGHRES_IMU", stamps, highres)
    # ArduPilot's scaling: milli-g, mrad/s, milligauss (int16 on the wire).
    scaled = np.concatenate(
        [_i(acc / GRAVITY_MPS2 * 1000.0), _i(gyro * 1000.0), _i(mag * 1000.0)], axis=1
    ).astype(np.int32)

    def raw(k: int) -> Any:
        return mavlink.MAVLink_raw_imu_message(int(us[k]), *scaled[k].tolist(), 0, 3150)

    return MessageTable("RAW_IMU", stamps, raw)


def _gps_table(stamper: _Stamper, gps: GpsTrack, start: float, end: float) -> MessageTable:
    sel = _window(gps.time, start, end)
    t = gps.time[sel]
    us = stamper.boot_us(t)
    h_acc = _i(gps.h_acc[sel] * 1000.0)
    fix_type = gps.fix_type[sel].tolist()
    # lat, lon (degE7), alt, alt_ellipsoid (mm), eph (HDOP x 100), vel (cm/s),
    # cog (cdeg from true north), satellites, h_acc, v_acc (mm).
    fields = np.stack(
        [
            _i(gps.lat[sel] * 1e7),
            _i(gps.lon[sel] * 1e7),
            _i(gps.alt[sel] * 1000.0),
            _i((gps.alt[sel] + _GEOID_UNDULATION_M) * 1000.0),
            _i(gps.hdop[sel] * 100.0),
            _i(gps.speed[sel] * 100.0),
            _i(np.degrees(gps.course_true[sel]) * 100.0) % 36000,
            gps.satellites[sel],
            h_acc,
            (h_acc * 1.6).astype(np.int64),
        ],
        axis=1,
    )

    def build(k: int) -> Any:
        lat, lon, alt, alt_ell, eph, vel, cog, sats, h, v = fields[k].tolist()
        return mavlink.MAVLink_gps_raw_int_message(
            int(us[k]), fix_type[k], lat, lon, alt, eph, 150, vel, cog, sats, alt_ell, h, v,
            150, 0, 0,
        )  # fmt: skip

    return MessageTable("GPS_RAW_INT", stamper.stamps(t), build)


def _heading_tables(
    stamper: _Stamper, s: Scenario, site: SiteFrame, streams: NavStreams, start: float, end: float
) -> list[MessageTable]:
    """ATTITUDE, GLOBAL_POSITION_INT and VFR_HUD, at the heading rate."""
    hd = streams.heading
    sel = _window(hd.time, start, end)
    t = hd.time[sel]
    ms = stamper.boot_ms(t)
    yaw = _wrap_pi(hd.heading_true[sel])
    angles = np.stack(
        [hd.roll[sel], hd.pitch[sel], yaw, hd.rollspeed[sel], hd.pitchspeed[sel], hd.yawspeed[sel]],
        axis=1,
    )
    tables = [
        MessageTable(
            "ATTITUDE",
            stamper.stamps(t),
            lambda k: mavlink.MAVLink_attitude_message(int(ms[k]), *angles[k].tolist()),
        )
    ]

    # The autopilot's own position estimate: the GPS bias (it cannot know it) without the
    # GPS white noise, which its filter mostly removes, and without the fix's lag, which
    # it compensates. Without a fix it dead-reckons: the bias stays as it was and a
    # velocity error of a few cm/s accumulates.
    gps = streams.gps
    truth = streams.motion.at(t)
    valid = gps.fix_type >= 3
    if not np.any(valid):
        valid = np.ones(len(gps.time), bool)
    fix_times = gps.time[valid]
    bias_e = np.interp(t, fix_times, gps.bias_east[valid])
    bias_n = np.interp(t, fix_times, gps.bias_north[valid])
    last = np.searchsorted(fix_times, t, side="right") - 1
    since = np.where(last >= 0, t - fix_times[np.maximum(last, 0)] - 1.0 / s.gps_rate_hz, 0.0)
    since = np.maximum(since, 0.0)
    drift = stamper.rng.normal(0.0, 0.05, 2)  # m/s, grid east/north
    lat, lon = site.to_latlon(
        truth["east"] + bias_e + drift[0] * since + stamper.rng.normal(0, 0.05, len(t)),
        truth["north"] + bias_n + drift[1] * since + stamper.rng.normal(0, 0.05, len(t)),
    )
    vn, ve = site.rotate_grid_to_true(truth["vel_north"], truth["vel_east"])
    alt_m = truth["up"]
    position = np.stack(
        [
            _i(lat * 1e7),
            _i(lon * 1e7),
            _i(alt_m * 1000.0),
            _i((alt_m - s.antenna_height_m) * 1000.0),
            _i(vn * 100),
            _i(ve * 100),
            _i(-truth["vel_up"] * 100),
            _i(np.degrees(hd.heading_true[sel]) * 100.0) % 36000,
        ],
        axis=1,
    )
    tables.append(
        MessageTable(
            "GLOBAL_POSITION_INT",
            stamper.stamps(t),
            lambda k: mavlink.MAVLink_global_position_int_message(
                int(ms[k]), *position[k].tolist()
            ),
        )
    )

    speed = np.hypot(vn, ve)
    heading_deg = _i(np.degrees(hd.heading_true[sel])) % 360
    throttle = [round(35 * v / s.speed_mps) for v in speed.tolist()]
    vel_up = truth["vel_up"]

    def hud(k: int) -> Any:
        v = float(speed[k])
        return mavlink.MAVLink_vfr_hud_message(
            v, v, int(heading_deg[k]), throttle[k], float(alt_m[k]), float(vel_up[k])
        )

    tables.append(MessageTable("VFR_HUD", stamper.stamps(t), hud))
    return tables


def _echosounder_tables(
    stamper: _Stamper, s: Scenario, sounding: Soundings, start: float, end: float
) -> list[MessageTable]:
    """DISTANCE_SENSOR (and RANGEFINDER on ArduPilot) of each sounding sent: distances in
    cm (RANGEFINDER in m), orientation 25 (PITCH_270: looking down), type ultrasound,
    covariance the range variance in cm^2 on PX4 (which fills it in) and 255 (unknown)
    on ArduPilot, the cone as both fields of view (rad), signal quality 1-100."""
    sel = _window(sounding.time, start, end) & sounding.sent
    t = sounding.time[sel]
    ms = stamper.boot_ms(t)
    cm = np.clip(_i(sounding.reported_m[sel] * 100.0), 0, 65535).tolist()
    quality = sounding.quality[sel].tolist()
    if s.flavour == "px4":
        covariance = np.clip(_i((sounding.noise_sigma_m[sel] * 100.0) ** 2), 0, 254).tolist()
    else:
        covariance = [255] * len(t)
    fov = math.radians(s.echosounder_beam_deg)
    low, high = round(MIN_DISTANCE_M * 100), round(MAX_DISTANCE_M * 100)

    def distance(k: int) -> Any:
        return mavlink.MAVLink_distance_sensor_message(
            int(ms[k]), low, high, cm[k], mavlink.MAV_DISTANCE_SENSOR_ULTRASOUND, 0,
            mavlink.MAV_SENSOR_ROTATION_PITCH_270, covariance[k], fov, fov, (0.0, 0.0, 0.0, 0.0),
            quality[k],
        )  # fmt: skip

    tables = [MessageTable("DISTANCE_SENSOR", stamper.stamps(t), distance)]
    if s.flavour != "px4":
        metres = sounding.reported_m[sel].tolist()
        tables.append(
            MessageTable(
                "RANGEFINDER",
                stamper.stamps(t),
                # A serial rangefinder: ArduPilot reports no analogue voltage.
                lambda k: mavlink.MAVLink_rangefinder_message(metres[k], 0.0),
            )
        )
    return tables
