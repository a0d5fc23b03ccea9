"""Writers of real MAVLink navigation logs for the tests: .tlog and ArduPilot DataFlash .bin.

The .tlog writer frames pymavlink-encoded messages exactly as MAVProxy, QGroundControl and
Mission Planner do: an 8-byte big-endian UNIX receive time in microseconds, then the
MAVLink 1 or 2 frame. MAVLink 1 frames are cut to the message's base length (no extension
fields), as a MAVLink 1 sender sends them; pymavlink's own ``force_mavlink1`` would keep
the extensions.

The DataFlash writer declares each type with an FMT message (type 128, FMT describing
itself first, as ArduPilot does), then writes ``A3 95 <type> <packed fields>``, with
ArduPilot's own formats, field names and scalings (format L: degE7, c/C/e: x 100).

Scenarios produce the messages of a boat sailing a known track, so tests can check
the samples against the messages sent and against the truth.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pymavlink import DFReader
from pymavlink.dialects.v20 import all as mavlink

G = 9.80665
T0_US = 1_718_000_000_000_000
"""2024-06-10 06:13:20 UTC, the receive time of the first record."""
MAV_TYPE_SURFACE_BOAT = 11
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_INVALID = 8

# MAVLink 1 payload lengths (the fields before the extensions) of the messages we write.
_MAVLINK1_LENGTH = {
    "HEARTBEAT": 9,
    "RAW_IMU": 26,
    "SCALED_IMU": 22,
    "SCALED_IMU2": 22,
    "SCALED_IMU3": 22,
    "HIGHRES_IMU": 62,
    "GPS_RAW_INT": 30,
    "GLOBAL_POSITION_INT": 28,
    "VFR_HUD": 20,
    "ATTITUDE": 28,
    "SYSTEM_TIME": 12,
    "STATUSTEXT": 51,
    "DISTANCE_SENSOR": 14,
    "RANGEFINDER": 8,
}


@dataclass(frozen=True)
class Sent:
    """One message as a log holds it: receive time (µs), sender, wire version."""

    time_us: int
    msg: Any
    sysid: int = 1
    compid: int = 1
    mavlink1: bool = False

    @property
    def time(self) -> float:
        """The receive time as pymavlink stamps it (s)."""
        return self.time_us * 1.0e-6


class TlogWriter:
    """Builds a .tlog in memory; one sequence counter per (system, component)."""

    def __init__(self) -> None:
        self.data = bytearray()
        self._links: dict[tuple[int, int], Any] = {}
        self.offsets: list[int] = []
        """Start of each record in ``data``."""

    def frame(self, sent: Sent) -> bytes:
        """The MAVLink frame of one message (advancing the sender's sequence number)."""
        link = self._links.setdefault(
            (sent.sysid, sent.compid), mavlink.MAVLink(None, sent.sysid, sent.compid)
        )
        if sent.mavlink1:
            # get_msgId(), not .id: RAW_IMU and HIGHRES_IMU have a field called "id".
            msg_id = sent.msg.get_msgId()
            full = sent.msg.pack(link, force_mavlink1=True)
            payload = full[6:-2][: _MAVLINK1_LENGTH[sent.msg.get_type()]]
            header = struct.pack(
                "<BBBBBB", 0xFE, len(payload), link.seq, sent.sysid, sent.compid, msg_id
            )
            crc = mavlink.x25crc(header[1:] + payload)
            crc.accumulate(bytes([sent.msg.crc_extra]))
            frame = header + payload + struct.pack("<H", crc.crc)
        else:
            frame = sent.msg.pack(link)
        link.seq = (link.seq + 1) % 256
        return bytes(frame)

    def add(self, sent: Sent) -> None:
        self.offsets.append(len(self.data))
        self.data += struct.pack(">Q", sent.time_us) + self.frame(sent)

    def extend(self, messages: Iterable[Sent]) -> TlogWriter:
        for sent in messages:
            self.add(sent)
        return self

    def save(self, path: Path) -> Path:
        path.write_bytes(bytes(self.data))
        return path


def write_tlog(path: Path, messages: Iterable[Sent]) -> Path:
    return TlogWriter().extend(messages).save(path)


# --- the truth ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Truth:
    """The boat at time t (s after the start): SI, degrees where named so."""

    t: float

    @property
    def heading_deg(self) -> float:
        return (350.0 + 7.0 * self.t) % 360.0  # crosses north

    @property
    def roll_deg(self) -> float:
        return 10.0 * math.sin(1.3 * self.t)

    @property
    def pitch_deg(self) -> float:
        return -5.0 * math.cos(0.9 * self.t)

    @property
    def lat_deg(self) -> float:
        return -35.3632621 + 1.1e-5 * self.t

    @property
    def lon_deg(self) -> float:
        return 149.1652374 + 1.7e-5 * self.t

    @property
    def velocity_ne(self) -> tuple[float, float]:
        return (1.2, 1.5)

    @property
    def depth_m(self) -> float:
        """The downward echosounder's distance to the bottom (m): a slope and a swell."""
        return 3.0 + 0.2 * self.t + 0.3 * math.sin(0.8 * self.t)


def earth_field_ned(
    declination_deg: float, inclination_deg: float, strength_gauss: float = 0.58
) -> tuple[float, float, float]:
    """The geomagnetic field (gauss, NED) for a declination (east +) and inclination (down +)."""
    dec, inc = math.radians(declination_deg), math.radians(inclination_deg)
    return (
        strength_gauss * math.cos(inc) * math.cos(dec),
        strength_gauss * math.cos(inc) * math.sin(dec),
        strength_gauss * math.sin(inc),
    )


def body_from_ned(
    vector_ned: tuple[float, float, float], heading_deg: float, roll_deg: float, pitch_deg: float
) -> tuple[float, float, float]:
    """A NED vector seen in body FRD axes: R^T v, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy = math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))
    cp, sp = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    cr, sr = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    rotation = (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )
    x, y, z = vector_ned
    body = [rotation[0][i] * x + rotation[1][i] * y + rotation[2][i] * z for i in range(3)]
    return (body[0], body[1], body[2])


# Southern Australia, where ArduPilot SITL starts: declination 12.5 deg E, inclination -65.
SITE_DECLINATION_DEG = 12.5
SITE_INCLINATION_DEG = -65.0


def _mag_mgauss(truth: Truth) -> tuple[int, int, int]:
    """The site's field as the boat's compass reads it (body FRD, whole milligauss)."""
    field = earth_field_ned(SITE_DECLINATION_DEG, SITE_INCLINATION_DEG)
    body = body_from_ned(field, truth.heading_deg, truth.roll_deg, truth.pitch_deg)
    return (round(body[0] * 1000), round(body[1] * 1000), round(body[2] * 1000))


def _wrap_pi(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


# --- MAVLink scenarios -----------------------------------------------------------------------


def ardupilot_messages(
    seconds: float = 3.0,
    rate_hz: float = 10.0,
    *,
    mavlink1_until_s: float = 0.0,
    with_gcs: bool = True,
    with_gps_raw: bool = True,
    with_attitude: bool = True,
) -> list[Sent]:
    """A Rover on a boat as MAVProxy logs it: ArduPilot's streams at rate_hz (GPS at half),
    heartbeats at 1 Hz, a GCS (255) heartbeat and follow-me position, a companion computer
    (1/191) heartbeat and ATTITUDE that must not be mistaken for the autopilot's.
    Frames before ``mavlink1_until_s`` are MAVLink 1 (ArduPilot starts so until the GCS
    speaks MAVLink 2)."""
    out: list[Sent] = []
    steps = round(seconds * rate_hz)
    for k in range(steps):
        t = k / rate_hz
        time_us = T0_US + round(t * 1e6)
        truth = Truth(t)
        v1 = t < mavlink1_until_s

        def send(
            msg: Any,
            sysid: int = 1,
            compid: int = 1,
            dt_us: int = 0,
            at: int = time_us,
            mavlink1: bool = v1,
        ) -> None:
            out.append(Sent(at + dt_us, msg, sysid, compid, mavlink1))

        if k % round(rate_hz) == 0:
            send(mavlink.MAVLink_heartbeat_message(MAV_TYPE_SURFACE_BOAT, 3, 129, 10, 4, 3))
            if with_gcs:
                send(mavlink.MAVLink_heartbeat_message(MAV_TYPE_GCS, 8, 0, 0, 0, 3), 255, 190, 1)
                send(
                    mavlink.MAVLink_heartbeat_message(MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 4, 3),
                    1,
                    191,
                    2,
                )
        yaw = math.radians(truth.heading_deg)
        roll, pitch = math.radians(truth.roll_deg), math.radians(truth.pitch_deg)
        if with_attitude:
            send(
                mavlink.MAVLink_attitude_message(k * 100, roll, pitch, _wrap_pi(yaw), 0.01, 0, 0.1),
                dt_us=5,
            )
        mag = _mag_mgauss(truth)
        accel = (round(0.3 * 1000 / G), round(-0.2 * 1000 / G), round(-G * 1000 / G))
        gyro = (round(0.01 * 1000), -5, round(math.radians(7) * 1000))
        send(mavlink.MAVLink_raw_imu_message(k * 100_000, *accel, *gyro, *mag, 0, 4500), dt_us=10)
        send(mavlink.MAVLink_scaled_imu2_message(k * 100, *accel, *gyro, 0, 0, 0, 4400), dt_us=11)
        north, east = truth.velocity_ne
        send(
            mavlink.MAVLink_global_position_int_message(
                k * 100,
                round(truth.lat_deg * 1e7),
                round(truth.lon_deg * 1e7),
                12_340,
                1_200,
                round(north * 100),
                round(east * 100),
                -3,
                round(truth.heading_deg * 100) % 36000,
            ),
            dt_us=20,
        )
        send(
            mavlink.MAVLink_vfr_hud_message(0.0, 1.92, int(truth.heading_deg) % 360, 20, 12.3, 0.0),
            dt_us=21,
        )
        if with_gps_raw and k % 2 == 0:
            send(
                mavlink.MAVLink_gps_raw_int_message(
                    k * 100_000,
                    3 if k > 2 else 1,
                    round(truth.lat_deg * 1e7),
                    round(truth.lon_deg * 1e7),
                    12_500,
                    121,
                    65535 if k < 6 else 180,
                    192,
                    round(math.degrees(math.atan2(east, north)) * 100),
                    12 if k > 0 else 255,
                    0,
                    1_350 if not v1 else 0,
                    2_100,
                    300,
                    0,
                    0,
                ),
                dt_us=30,
            )
        if with_gcs and k % 5 == 3:  # a GCS follow-me position: never the boat's
            send(
                mavlink.MAVLink_global_position_int_message(
                    0, -353000000, 1491000000, 0, 0, 0, 0, 0, 9000
                ),
                255,
                190,
                dt_us=40,
            )
            send(mavlink.MAVLink_attitude_message(0, 0.5, 0.5, 0.5, 0, 0, 0), 1, 191, dt_us=41)
    return out


DOWNWARD = 25  # MAV_SENSOR_ROTATION_PITCH_270
FORWARD = 0  # MAV_SENSOR_ROTATION_NONE
PING2_MIN_CM, PING2_MAX_CM = 30, 5000
"""A Ping2-class echosounder's span as ArduPilot reports it (0.3 .. 50 m)."""


def no_reading(k: int) -> str | None:
    """Why the echosounder's k-th downward DISTANCE_SENSOR is no reading, if it is not."""
    if k % 7 == 3:
        return "beyond max"
    if k % 11 == 5:
        return "zero"
    if k % 13 == 6:
        return "invalid signal"
    if k % 17 == 8:
        return "below min"
    return None


def echosounder_messages(
    seconds: float = 3.0,
    rate_hz: float = 10.0,
    *,
    distance_sensor: bool = True,
    forward: bool = True,
    rangefinder: bool = True,
    mavlink1: bool = False,
    sysid: int = 1,
) -> list[Sent]:
    """What ArduPilot sends for a Ping2 echosounder looking down (rangefinder instance 0)
    and an obstacle sensor looking forward (instance 1): a DISTANCE_SENSOR for each and a
    RANGEFINDER for the downward one, at rate_hz. The downward readings follow
    ``Truth.depth_m``, except those ``no_reading`` names; covariance 4 cm^2 and quality
    87 % on even k, unknown (255, 0) on odd k. Times are 100 µs after the
    ``ardupilot_messages`` at the same k, so both interleave."""
    out: list[Sent] = []
    for k in range(round(seconds * rate_hz)):
        time_us = T0_US + round(k / rate_hz * 1e6) + 100
        depth = Truth(k / rate_hz).depth_m
        current = round(depth * 100)
        quality = 87 if k % 2 == 0 else 0
        bad = no_reading(k)
        if bad == "beyond max":
            current = PING2_MAX_CM + 500
        elif bad == "zero":
            current = 0
        elif bad == "invalid signal":
            quality = 1
        elif bad == "below min":
            current = PING2_MIN_CM - 10
        if distance_sensor:
            out.append(
                Sent(
                    time_us,
                    mavlink.MAVLink_distance_sensor_message(
                        k * 100, PING2_MIN_CM, PING2_MAX_CM, current, 1, 0, DOWNWARD,
                        4 if k % 2 == 0 else 255, 0.5, 0.5, (0, 0, 0, 0), quality,
                    ),
                    sysid,
                    mavlink1=mavlink1,
                )
            )  # fmt: skip
            if forward:
                out.append(
                    Sent(
                        time_us + 1,
                        mavlink.MAVLink_distance_sensor_message(
                            k * 100, 20, 4000, 750, 1, 1, FORWARD, 0, 0, 0, (0, 0, 0, 0), 90
                        ),
                        sysid,
                        mavlink1=mavlink1,
                    )
                )
        if rangefinder:
            # ArduPilot's RANGEFINDER: the downward sensor's distance, valid or not.
            out.append(
                Sent(
                    time_us + 2,
                    mavlink.MAVLink_rangefinder_message(current / 100.0, 1.25),
                    sysid,
                    mavlink1=mavlink1,
                )
            )
    return out


def by_time(*streams: list[Sent]) -> list[Sent]:
    """Several scenarios' messages as one log, in receive order (stable)."""
    return sorted((sent for stream in streams for sent in stream), key=lambda s: s.time_us)


def px4_messages(seconds: float = 2.0, rate_hz: float = 10.0) -> list[Sent]:
    """A PX4 boat as QGroundControl logs it (MAVLink 2): HIGHRES_IMU in SI with mag,
    RAW_IMU with raw sensor counts, ATTITUDE, GPS_RAW_INT with h_acc, VFR_HUD, and
    GLOBAL_POSITION_INT with an unknown heading (65535)."""
    out: list[Sent] = []
    for k in range(round(seconds * rate_hz)):
        t = k / rate_hz
        time_us = T0_US + round(t * 1e6)
        truth = Truth(t)
        if k % round(rate_hz) == 0:
            out.append(
                Sent(time_us, mavlink.MAVLink_heartbeat_message(10, MAV_AUTOPILOT_PX4, 29, 0, 4, 3))
            )
        yaw = math.radians(truth.heading_deg)
        roll, pitch = math.radians(truth.roll_deg), math.radians(truth.pitch_deg)
        out.append(
            Sent(
                time_us + 5,
                mavlink.MAVLink_attitude_message(k, roll, pitch, _wrap_pi(yaw), 0, 0, 0),
            )
        )
        mag = tuple(m / 1000 for m in _mag_mgauss(truth))
        out.append(
            Sent(
                time_us + 10,
                mavlink.MAVLink_highres_imu_message(
                    k * 100_000, 0.31, -0.21, -9.79, 0.011, -0.004, 0.12, *mag,
                    1013.2, 0.0, 12.0, 31.5, 0x1FFF, 0,
                ),
            )
        )  # fmt: skip
        out.append(
            Sent(
                time_us + 11,
                mavlink.MAVLink_raw_imu_message(
                    k * 100_000, 512, -301, -16020, 12, -7, 210, 0, 0, 0
                ),
            )
        )
        out.append(
            Sent(
                time_us + 20,
                mavlink.MAVLink_gps_raw_int_message(
                    k * 100_000, 6, round(truth.lat_deg * 1e7), round(truth.lon_deg * 1e7),
                    12_500, 70, 110, 192, 65535, 22, 0, 14, 21, 50, 0, 0,
                ),
            )
        )  # fmt: skip
        out.append(
            Sent(
                time_us + 21,
                mavlink.MAVLink_global_position_int_message(
                    k, round(truth.lat_deg * 1e7), round(truth.lon_deg * 1e7), 12_300, 0,
                    120, 150, 0, 65535,
                ),
            )
        )  # fmt: skip
        out.append(
            Sent(
                time_us + 22,
                mavlink.MAVLink_vfr_hud_message(0, 1.9, round(truth.heading_deg) % 360, 0, 12.3, 0),
            )
        )
    return out


# --- DataFlash ---------------------------------------------------------------------------

FMT_TYPE = 0x80
_SCALED = {"L": 1e7, "c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0}

# ArduPilot's formats (libraries/*/LogStructure.h): name -> (type id, format, columns).
ATT_CENTIDEGREES = ("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF")
ATT_DEGREES = ("QffffffB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,AEKF")
ARDUPILOT_FORMATS: dict[str, tuple[int, str, str]] = {
    "UNIT": (177, "QbZ", "TimeUS,Id,Label"),
    "MULT": (178, "Qbd", "TimeUS,Id,Mult"),
    "FMTU": (179, "QBNN", "TimeUS,FmtType,UnitIds,MultIds"),
    "PARM": (64, "QNff", "TimeUS,Name,Value,Default"),
    "IMU": (
        135,
        "QBffffffIIfBBHH",
        "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
    ),
    "GPS": (
        130,
        "QBBIHBcLLeffffB",
        "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
    ),
    "GPA": (131, "QBCCCCfBIH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta"),
    "ATT": (133, *ATT_CENTIDEGREES),
    "MAG": (144, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
}


RFND_TYPE = 160
RFND_LAYOUTS: dict[str, tuple[str, str, str, str]] = {
    # name: (format, columns, FMTU units, FMTU multipliers), as ArduPilot declared RFND
    "plain": ("QCC", "TimeUS,Dist1,Dist2", "", ""),  # 3.3-3.4: no orientation, cm
    "orient": ("QCBCB", "TimeUS,Dist1,Orient1,Dist2,Orient2", "", ""),  # 3.5-3.6
    "instance": ("QBCBB", "TimeUS,Instance,Dist,Stat,Orient", "s#m--", "F-B--"),  # 3.7-4.1
    "quality": ("QBCBBb", "TimeUS,Instance,Dist,Stat,Orient,Quality", "s#m--%", "F-B--0"),
    "float": ("QBfBBb", "TimeUS,Instance,Dist,Stat,Orient,Quality", "s#m--%", "F-0--0"),
    "integer_cm": ("QBHBB", "TimeUS,Instance,Dist,Stat,Orient", "s#m--", "F-B--"),
}
"""RFND layouts over ArduPilot versions; "float" is metres as a float; "integer_cm" an
integer field whose FMTU says cm (m x 1e-2), read only through the log's declaration."""


class DataFlashWriter:
    """Builds an ArduPilot DataFlash log in memory."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.types: dict[str, tuple[int, str, list[str]]] = {}
        self.define(FMT_TYPE, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")

    def define(self, type_id: int, name: str, fmt: str, columns: str) -> None:
        """Write the FMT message that declares a type."""
        length = 3 + struct.calcsize(_struct(fmt))
        self.types[name] = (type_id, fmt, columns.split(","))
        self._message(
            FMT_TYPE,
            "BBnNZ",
            [type_id, length, name.encode(), fmt.encode(), columns.encode()],
        )

    def define_ardupilot(self, *names: str, att: tuple[str, str] = ATT_CENTIDEGREES) -> None:
        for name in names:
            type_id, fmt, columns = ARDUPILOT_FORMATS[name]
            if name == "ATT":
                fmt, columns = att
            self.define(type_id, name, fmt, columns)

    def write(self, name: str, **values: float | int | str) -> None:
        """One message; values in physical units (scaled here like ArduPilot), 0 if omitted."""
        type_id, fmt, columns = self.types[name]
        unknown = set(values) - set(columns)
        if unknown:
            raise KeyError(f"{name} has no field {sorted(unknown)}")
        packed: list[Any] = []
        for char, column in zip(fmt, columns, strict=True):
            value = values.get(column, 0)
            if char in "nNZ":
                packed.append(str(value).encode())
            elif char in _SCALED:
                packed.append(round(float(value) * _SCALED[char]))
            elif char in "fdg":
                packed.append(float(value))
            else:
                packed.append(int(value))
        self._message(type_id, fmt, packed)

    def _message(self, type_id: int, fmt: str, values: list[Any]) -> None:
        self.data += bytes((0xA3, 0x95, type_id)) + struct.pack(_struct(fmt), *values)

    def save(self, path: Path) -> Path:
        path.write_bytes(bytes(self.data))
        return path


def _struct(fmt: str) -> str:
    return "<" + "".join(DFReader.FORMAT_TO_STRUCT[c][0] for c in fmt)


GPS_WEEK = 2318
GPS_MS_AT_BOOT = 86_400_000
"""The GPS clock (week, ms of week) at TimeUS 0 of the DataFlash scenario."""


def gps_unix_time(week: int, ms_of_week: int) -> float:
    """UNIX time of a GPS week / time of week, 18 leap seconds (as pymavlink counts them)."""
    return 315_964_800 + week * 604_800 + ms_of_week / 1000.0 - 18


def ardupilot_dataflash(
    seconds: float = 3.0,
    rate_hz: float = 10.0,
    *,
    att: tuple[str, str] = ATT_CENTIDEGREES,
    gps_week: bool = True,
    units: bool = True,
    rfnd: str | None = None,
) -> DataFlashWriter:
    """A Rover DataFlash log: IMU (two instances), ATT, MAG (two), GPS + GPA at rate_hz/2
    (GPS week 0 until the third fix, or throughout when ``gps_week`` is False), with
    UNIT/MULT/FMTU metadata as ArduPilot writes it when ``units``. ``rfnd``: an
    ``RFND_LAYOUTS`` name: RFND at rate_hz too (``rfnd_messages``)."""
    log = DataFlashWriter()
    log.define_ardupilot(*ARDUPILOT_FORMATS, att=att)
    if rfnd is not None:
        log.define(RFND_TYPE, "RFND", *RFND_LAYOUTS[rfnd][:2])
    if units:
        unit_labels = [("s", "seconds"), ("#", "instance"), ("G", "Gauss"), ("-", "")]
        mults = [("F", 1e-6), ("C", 1e-3), ("-", 0.0), ("0", 1.0)]
        if rfnd is not None:
            unit_labels += [("m", "m"), ("%", "percent")]
            mults += [("B", 1e-2)]
        for ident, label in unit_labels:
            log.write("UNIT", TimeUS=1000, Id=ord(ident), Label=label)
        for ident, mult in mults:
            log.write("MULT", TimeUS=1000, Id=ord(ident), Mult=mult)
        log.write(
            "FMTU", TimeUS=1001, FmtType=144, UnitIds="s#GGGGGGGGG-s", MultIds="F-CCCCCCCCC-F"
        )
        if rfnd is not None and RFND_LAYOUTS[rfnd][2]:
            _, _, unit_ids, mult_ids = RFND_LAYOUTS[rfnd]
            log.write("FMTU", TimeUS=1001, FmtType=RFND_TYPE, UnitIds=unit_ids, MultIds=mult_ids)
    log.write("PARM", TimeUS=2000, Name="SYSID_THISMAV", Value=1.0, Default=1.0)
    boot_us = 5_000_000
    for k in range(round(seconds * rate_hz)):
        t = k / rate_hz
        time_us = boot_us + round(t * 1e6)
        truth = Truth(t)
        for instance in (0, 1):
            log.write(
                "IMU", TimeUS=time_us, I=instance, GyrX=0.01 + instance, GyrY=-0.005,
                GyrZ=math.radians(7), AccX=0.3, AccY=-0.2, AccZ=-9.80665, T=45.0, GH=1, AH=1,
                GHz=400, AHz=400,
            )  # fmt: skip
        log.write(
            "ATT", TimeUS=time_us + 10, Roll=truth.roll_deg, Pitch=truth.pitch_deg,
            Yaw=truth.heading_deg, DesYaw=truth.heading_deg,
        )  # fmt: skip
        mag = _mag_mgauss(truth)
        for instance in (0, 1):
            log.write(
                "MAG", TimeUS=time_us + 20, I=instance, MagX=mag[0] + 50 * instance,
                MagY=mag[1], MagZ=mag[2], Health=1, S=time_us,
            )  # fmt: skip
        if k % 2 == 0:
            gps_us = time_us + 30
            week = GPS_WEEK if gps_week and k >= 4 else 0
            gms = GPS_MS_AT_BOOT + gps_us // 1000 if week else 0
            north, east = truth.velocity_ne
            log.write(
                "GPS", TimeUS=gps_us, I=0, Status=3 if k >= 4 else 1, GMS=gms, GWk=week,
                NSats=14, HDop=0.87, Lat=truth.lat_deg, Lng=truth.lon_deg, Alt=12.5,
                Spd=math.hypot(north, east), GCrs=math.degrees(math.atan2(east, north)), VZ=0.0,
                U=1,
            )  # fmt: skip
            log.write("GPA", TimeUS=gps_us, I=0, VDop=1.2, HAcc=1.35 if k >= 4 else 0.0)
        if rfnd is not None:
            for values in rfnd_messages(rfnd, k, truth):
                log.write("RFND", TimeUS=time_us + 40, **values)
    return log


def rfnd_bad(k: int) -> bool:
    """Whether the downward rangefinder's k-th RFND is no reading (out of range / 0)."""
    return k % 7 == 3


def rfnd_messages(layout: str, k: int, truth: Truth) -> list[dict[str, float | int]]:
    """The RFND messages (field values, metres) of step k in a layout: a forward sensor
    (instance 0 in the instance layouts, 7.5 m) and the downward echosounder at
    ``truth.depth_m`` (Stat 3, out of range high, or Dist 0 where ``rfnd_bad``). In
    "plain" (no orientation) Dist1 is the echosounder; in "orient" Dist1 looks forward."""
    bad = rfnd_bad(k)
    depth = 0.0 if bad and layout in ("plain", "orient") else truth.depth_m
    if layout == "plain":
        return [{"Dist1": depth, "Dist2": 7.5}]
    if layout == "orient":
        return [{"Dist1": 7.5, "Orient1": FORWARD, "Dist2": depth, "Orient2": DOWNWARD}]
    quality = {"Quality": 80} if "Quality" in RFND_LAYOUTS[layout][1] else {}
    scale = 100.0 if layout == "integer_cm" else 1.0  # plain integer fields hold cm
    forward = {"Instance": 0, "Dist": 7.5 * scale, "Stat": 4, "Orient": FORWARD}
    down = {
        "Instance": 1,
        "Dist": round(depth * scale, 2) if scale == 1.0 else round(depth * scale),
        "Stat": 3 if bad else 4,
        "Orient": DOWNWARD,
    }
    return [{**forward, **quality}, {**down, **quality}]
