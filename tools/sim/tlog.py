"""Writing the simulated telemetry as a MAVLink 2 ``.tlog``.

A .tlog is a plain sequence of packets, each preceded by the boat computer's receive time
as an 8-byte big-endian count of UNIX microseconds (what MAVProxy and QGroundControl
write, and what ``pymavlink.mavutil.mavlink_connection("x.tlog")`` reads into
``msg._timestamp``).

What the autopilot (sysid 1, compid 1) streams:

- ``ardupilot`` flavour (Rover): HEARTBEAT 1 Hz (MAV_TYPE_SURFACE_BOAT,
  MAV_AUTOPILOT_ARDUPILOTMEGA, armed, AUTO = custom mode 10), SYSTEM_TIME 1 Hz, RAW_IMU at
  ``imu_rate_hz`` in ArduPilot's scaling (milli-g, mrad/s, milligauss), GPS_RAW_INT at
  ``gps_rate_hz`` (fix_type 3, eph = HDOP x 100, vel cm/s, cog cdeg from true north,
  satellites, h_acc/v_acc mm), and at ``heading_rate_hz`` ATTITUDE (yaw = compass-like
  heading, radians from true north in -pi..pi), GLOBAL_POSITION_INT (hdg cdeg, position
  from the GPS-aided estimate) and VFR_HUD (heading in whole degrees).
- ``px4`` flavour: the same but MAV_AUTOPILOT_PX4 (AUTO.MISSION custom mode), HIGHRES_IMU
  in SI units (m/s^2, rad/s, gauss) and no RAW_IMU.

A ground station (sysid 255, compid 190, MAV_TYPE_GCS) adds a heartbeat about once a
second, as it does in a real log. time_boot_ms / time_usec count from the autopilot's
boot (``start_time - autopilot_uptime_s``); the receive stamp is the sample time plus a
link delay (``stamp_delay_s`` + exponential jitter of mean ``stamp_jitter_s``), and the
packets are written in stamp order.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tools.sim.scenarios import Scenario
from tools.sim.sensors import GRAVITY_MPS2, GpsTrack, HeadingTrack, ImuTrack
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
    """The sensor tracks the tlog carries, plus the truth for GLOBAL_POSITION_INT."""

    gps: GpsTrack
    heading: HeadingTrack
    imu: ImuTrack
    motion: Motion


class _Log:
    """Messages collected with their stamps, packed in stamp order at the end."""

    def __init__(self, s: Scenario, rng: np.random.Generator) -> None:
        self.boot = s.start_time - s.autopilot_uptime_s
        self.delay_s = s.stamp_delay_s
        self.jitter_s = s.stamp_jitter_s
        self.rng = rng
        self.items: list[tuple[int, int, Any]] = []

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

    def add(
        self, stamps: npt.NDArray[np.int64], messages: list[Any], sysid: int = AUTOPILOT_SYSID
    ) -> None:
        self.items.extend(zip(stamps.tolist(), [sysid] * len(messages), messages, strict=True))

    def write(self, path: Path) -> dict[str, int]:
        """Pack in stamp order (sequence numbers follow that order) and write the file."""
        senders = {
            AUTOPILOT_SYSID: mavlink.MAVLink(None, AUTOPILOT_SYSID, AUTOPILOT_COMPID),
            GCS_SYSID: mavlink.MAVLink(None, GCS_SYSID, GCS_COMPID),
        }
        order = sorted(range(len(self.items)), key=lambda i: (self.items[i][0], i))
        chunks: list[bytes] = []
        counts: dict[str, int] = {}
        prefix = struct.Struct(">Q")
        for i in order:
            stamp, sysid, msg = self.items[i]
            sender = senders[sysid]
            chunks.append(prefix.pack(stamp))
            chunks.append(msg.pack(sender))
            sender.seq = (sender.seq + 1) % 256
            name = msg.get_type()
            counts[name] = counts.get(name, 0) + 1
        path.write_bytes(b"".join(chunks))
        return dict(sorted(counts.items()))


def _times(start: float, end: float, rate_hz: float, phase: float) -> FloatArray:
    """Sample times at ``rate_hz`` from ``start + phase`` up to ``end``."""
    return np.arange(start + phase, end, 1.0 / rate_hz)


def _wrap_pi(angle: FloatArray) -> FloatArray:
    return np.mod(np.asarray(angle) + math.pi, 2 * math.pi) - math.pi


def _i(values: FloatArray) -> list[int]:
    return [int(v) for v in np.rint(values)]


def write_tlog(
    path: Path,
    s: Scenario,
    site: SiteFrame,
    streams: NavStreams,
    start: float,
    end: float,
    rng: np.random.Generator,
) -> dict[str, int]:
    """Write the telemetry between ``start`` and ``end`` (UNIX s); returns message counts."""
    log = _Log(s, rng)
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
    log.add(log.stamps(hb_times), [heartbeat] * len(hb_times))
    st_times = _times(start, end, 1.0, 0.61)
    log.add(
        log.stamps(st_times),
        [
            mavlink.MAVLink_system_time_message(round(t * 1e6), int(ms))
            for t, ms in zip(st_times, log.boot_ms(st_times), strict=True)
        ],
    )
    gcs_times = _times(start, end, 1.0 / s.gcs_heartbeat_period_s, 0.83)
    gcs_times = gcs_times + rng.uniform(-0.05, 0.05, len(gcs_times))
    gcs = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
    )
    log.add(log.stamps(gcs_times), [gcs] * len(gcs_times), sysid=GCS_SYSID)

    _add_imu(log, streams.imu, px4, start, end)
    _add_gps(log, streams.gps, start, end)
    _add_heading(log, s, site, streams, start, end)
    return log.write(path)


def _window(times: FloatArray, start: float, end: float) -> npt.NDArray[np.bool_]:
    return (times >= start) & (times < end)


def _add_imu(log: _Log, imu: ImuTrack, px4: bool, start: float, end: float) -> None:
    sel = _window(imu.time, start, end)
    t = imu.time[sel]
    acc, gyro, mag = imu.accel[sel], imu.gyro[sel], imu.mag[sel]
    us = log.boot_us(t)
    if px4:
        values = np.concatenate([acc, gyro, mag], axis=1).tolist()
        msgs = [
            mavlink.MAVLink_highres_imu_message(
                int(us[k]), *values[k], 1013.0, 0.0, 0.12, 31.5, 0x1FFF, 0
            )
            for k in range(len(t))
        ]
    else:
        acc_mg = np.rint(acc / GRAVITY_MPS2 * 1000.0).astype(np.int64)
        gyro_mrad = np.rint(gyro * 1000.0).astype(np.int64)
        mag_mg = np.rint(mag * 1000.0).astype(np.int64)
        msgs = [
            mavlink.MAVLink_raw_imu_message(
                int(us[k]),
                *acc_mg[k].tolist(),
                *gyro_mrad[k].tolist(),
                *mag_mg[k].tolist(),
                0,
                3150,
            )
            for k in range(len(t))
        ]
    log.add(log.stamps(t), msgs)


def _add_gps(log: _Log, gps: GpsTrack, start: float, end: float) -> None:
    sel = _window(gps.time, start, end)
    t = gps.time[sel]
    us = log.boot_us(t)
    lat, lon = _i(gps.lat[sel] * 1e7), _i(gps.lon[sel] * 1e7)
    alt = _i(gps.alt[sel] * 1000.0)
    alt_ell = _i((gps.alt[sel] + _GEOID_UNDULATION_M) * 1000.0)
    eph = _i(gps.hdop[sel] * 100.0)
    vel = _i(gps.speed[sel] * 100.0)
    cog = [c % 36000 for c in _i(np.degrees(gps.course_true[sel]) * 100.0)]
    h_acc = _i(gps.h_acc[sel] * 1000.0)
    sats = gps.satellites[sel].tolist()
    msgs = [
        mavlink.MAVLink_gps_raw_int_message(
            int(us[k]),
            mavlink.GPS_FIX_TYPE_3D_FIX,
            lat[k],
            lon[k],
            alt[k],
            eph[k],
            150,
            vel[k],
            cog[k],
            int(sats[k]),
            alt_ell[k],
            h_acc[k],
            int(h_acc[k] * 1.6),
            150,
            0,
            0,
        )
        for k in range(len(t))
    ]
    log.add(log.stamps(t), msgs)


def _add_heading(
    log: _Log, s: Scenario, site: SiteFrame, streams: NavStreams, start: float, end: float
) -> None:
    hd = streams.heading
    sel = _window(hd.time, start, end)
    t = hd.time[sel]
    ms = log.boot_ms(t)
    yaw = _wrap_pi(hd.heading_true[sel])
    angles = np.stack(
        [hd.roll[sel], hd.pitch[sel], yaw, hd.rollspeed[sel], hd.pitchspeed[sel], hd.yawspeed[sel]],
        axis=1,
    ).tolist()
    attitude = [mavlink.MAVLink_attitude_message(int(ms[k]), *angles[k]) for k in range(len(t))]
    log.add(log.stamps(t), attitude)

    # The autopilot's own position estimate: the GPS bias (it cannot know it) without the
    # GPS white noise, which its filter mostly removes.
    gps = streams.gps
    truth = streams.motion.at(t)
    bias_e = np.interp(t, gps.time, gps.bias_east)
    bias_n = np.interp(t, gps.time, gps.bias_north)
    lat, lon = site.to_latlon(
        truth["east"] + bias_e + log.rng.normal(0, 0.05, len(t)),
        truth["north"] + bias_n + log.rng.normal(0, 0.05, len(t)),
    )
    vn, ve = site.rotate_grid_to_true(truth["vel_north"], truth["vel_east"])
    alt_m = truth["up"]
    hdg_cdeg = [h % 36000 for h in _i(np.degrees(hd.heading_true[sel]) * 100.0)]
    lat_i, lon_i = _i(lat * 1e7), _i(lon * 1e7)
    alt_mm, rel_mm = _i(alt_m * 1000.0), _i((alt_m - s.antenna_height_m) * 1000.0)
    vx, vy, vz = _i(vn * 100), _i(ve * 100), _i(-truth["vel_up"] * 100)
    position = [
        mavlink.MAVLink_global_position_int_message(
            int(ms[k]), lat_i[k], lon_i[k], alt_mm[k], rel_mm[k], vx[k], vy[k], vz[k], hdg_cdeg[k]
        )
        for k in range(len(t))
    ]
    log.add(log.stamps(t), position)

    speed = np.hypot(vn, ve)
    heading_deg = [h % 360 for h in _i(np.degrees(hd.heading_true[sel]))]
    hud = [
        mavlink.MAVLink_vfr_hud_message(
            float(speed[k]),
            float(speed[k]),
            heading_deg[k],
            round(35 * speed[k] / s.speed_mps),
            float(alt_m[k]),
            float(truth["vel_up"][k]),
        )
        for k in range(len(t))
    ]
    log.add(log.stamps(t), hud)
