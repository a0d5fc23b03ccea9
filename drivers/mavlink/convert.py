"""Convert one decoded MAVLink or ArduPilot DataFlash message into typed samples.

Pure functions: a message (as pymavlink decodes it) and its receive time in, one sample
(``mapping.samples``) or None out. No file, no link, no state: the log reader
(``navlog.py``) and the live driver share them, and each keeps its own state (the latest
attitude for the compass, which source was chosen).

Units out are SI and the contract's frames: seconds (UNIX, the caller's stamp), metres,
m/s, radians; body frame FRD as MAVLink and ArduPilot already use it (no axis change);
headings and courses in radians clockwise from true north, in [0, 2*pi).

None means "no usable sample": the message has no such data (an unknown sentinel such as
GLOBAL_POSITION_INT.hdg = 65535) or a value is out of range (NaN, a latitude past 90 deg).
"""

from __future__ import annotations

import math
from typing import Any

from mapping.samples import (
    AttitudeSample,
    GnssFix,
    GnssFixType,
    HeadingSample,
    ImuSample,
    RangeSample,
)
from mapping.se2 import wrap_2pi

GRAVITY_MPS2 = 9.80665
"""Standard gravity: ArduPilot scales milli-g with exactly this (AP_Math GRAVITY_MSS)."""

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_COMP_ID_GIMBAL = 154
_NOT_VEHICLES = frozenset(
    {
        5,  # ANTENNA_TRACKER
        MAV_TYPE_GCS,
        18,  # ONBOARD_CONTROLLER (companions, seamap itself)
        26,  # GIMBAL
        27,  # ADSB
        *range(30, 35),  # CAMERA, CHARGING_STATION, FLARM, SERVO, ODID
        *range(36, 43),  # BATTERY, PARACHUTE, LOG, OSD, IMU, GPS, WINCH
        44,  # ILLUMINATOR
        48,  # GRIPPER
    }
)
"""MAV_TYPEs of components that are not a vehicle (some peripherals send heartbeats that
name the autopilot they belong to)."""

IMU_MESSAGES: dict[str, str] = {
    "highres": "HIGHRES_IMU",
    "scaled": "SCALED_IMU",
    "scaled2": "SCALED_IMU2",
    "scaled3": "SCALED_IMU3",
    "raw": "RAW_IMU",
}
"""imu_source (config) -> the MAVLink message it reads."""
IMU_AUTO_ORDER = ("highres", "scaled", "raw", "scaled2", "scaled3")
"""imu_source = "auto" takes the first of these that the log or link carries."""

HEADING_MESSAGES: dict[str, str] = {
    "attitude": "ATTITUDE",
    "global_position": "GLOBAL_POSITION_INT",
    "vfr_hud": "VFR_HUD",
}
"""heading_source (config) -> the MAVLink message it reads; "compass" reads the IMU's mag."""
HEADING_AUTO_ORDER = ("attitude", "global_position", "vfr_hud", "compass")

GNSS_MESSAGES = ("GPS_RAW_INT", "GLOBAL_POSITION_INT")
"""GPS_RAW_INT is the receiver's fix; GLOBAL_POSITION_INT (the autopilot's fused estimate)
is only a fallback for logs without any GPS_RAW_INT."""

RANGE_MESSAGES = ("DISTANCE_SENSOR", "RANGEFINDER")
"""A downward echosounder's soundings, preferred first. ArduPilot sends both for the same
sensor (RANGEFINDER for its first downward rangefinder, DISTANCE_SENSOR for each one), so
a log or link that has a downward DISTANCE_SENSOR takes only that: RANGEFINDER has no
valid span and no quality, and both together would count each sounding twice."""
MAV_SENSOR_ROTATION_PITCH_270 = 25
"""MAV_SENSOR_ORIENTATION (and ArduPilot's RNGFND_ORIENT) of a sensor looking down."""

_UINT16_UNKNOWN = 65535
_UINT8_UNKNOWN = 255
_CENTIDEGREE_RAD = math.radians(0.01)
_DEGREE_RAD = math.radians(1.0)


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def autopilot_name(autopilot: int) -> str:
    """HEARTBEAT.autopilot (MAV_AUTOPILOT) -> "ardupilot", "px4" or "unknown"."""
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    if autopilot == MAV_AUTOPILOT_PX4:
        return "px4"
    return "unknown"


def is_autopilot_heartbeat(msg: Any) -> bool:
    """A HEARTBEAT from a flight controller, not from a GCS, companion or peripheral.

    Stricter than pymavlink's ``probably_vehicle_heartbeat``: besides MAV_AUTOPILOT_INVALID
    (GCSs, companions, seamap itself), peripheral MAV_TYPEs (camera, gimbal, GPS, ...) and
    the gimbal component id are not vehicles, whatever autopilot they name.
    """
    return (
        msg.get_type() == "HEARTBEAT"
        and msg.autopilot != MAV_AUTOPILOT_INVALID
        and msg.type not in _NOT_VEHICLES
        and msg.get_srcComponent() != MAV_COMP_ID_GIMBAL
    )


def imu_source_usable(source: str, autopilot: str) -> bool:
    """Whether an imu_source name can be used with this autopilot.

    PX4 fills RAW_IMU with raw sensor counts (the MAVLink definition: "without any
    scaling"), which cannot be converted without the sensor's calibration; ArduPilot fills it
    with the same milli-g / mrad/s / milligauss as SCALED_IMU. So RAW_IMU is never used for
    PX4; for an unknown autopilot the contract's ArduPilot scaling is assumed.
    """
    return not (source == "raw" and autopilot == "px4")


# --- MAVLink -------------------------------------------------------------------------------


def imu_from_mavlink(msg: Any, time: float) -> ImuSample | None:
    """HIGHRES_IMU, SCALED_IMU/2/3 or RAW_IMU -> ImuSample (body FRD, SI).

    HIGHRES_IMU is SI already (m/s^2, rad/s, gauss). SCALED_IMU* and ArduPilot's RAW_IMU are
    milli-g (x 9.80665e-3 -> m/s^2), mrad/s (x 1e-3) and milligauss (x 1e-3). A magnetometer
    reading of exactly (0, 0, 0) means "no compass" (ArduPilot zeroes it) and becomes None.
    Check ``imu_source_usable`` first: PX4's RAW_IMU is raw counts.
    """
    kind = msg.get_type()
    raw = (msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro)
    mag_raw = (msg.xmag, msg.ymag, msg.zmag)
    if kind == "HIGHRES_IMU":
        accel_scale, gyro_scale, mag_scale = 1.0, 1.0, 1.0
    elif kind in ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "RAW_IMU"):
        accel_scale, gyro_scale, mag_scale = GRAVITY_MPS2 / 1000.0, 1e-3, 1e-3
    else:
        return None
    if not _finite(*raw, *mag_raw):
        return None
    accel = (raw[0] * accel_scale, raw[1] * accel_scale, raw[2] * accel_scale)
    gyro = (raw[3] * gyro_scale, raw[4] * gyro_scale, raw[5] * gyro_scale)
    mag = None
    if any(mag_raw):
        mag = (mag_raw[0] * mag_scale, mag_raw[1] * mag_scale, mag_raw[2] * mag_scale)
    return ImuSample(time, accel, gyro, mag, source=kind)


def imu_instance(msg: Any) -> int:
    """The IMU index a message reports: RAW_IMU/HIGHRES_IMU.id (MAVLink 2 extension, 0 when
    absent), else 0 (SCALED_IMU2/3 are separate messages)."""
    # Not getattr(msg, "id"): on messages without that field it is the class's message id.
    return int(msg.id) if "id" in msg.get_fieldnames() else 0


def _fix_type(value: int) -> GnssFixType:
    # A fix type newer than this code knows is not trusted as a fix.
    return GnssFixType(value) if 0 <= value <= max(GnssFixType) else GnssFixType.NO_FIX


def _valid_position(lat_deg: float, lon_deg: float) -> bool:
    return -90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0


def gnss_from_mavlink(msg: Any, time: float) -> GnssFix | None:
    """GPS_RAW_INT (or GLOBAL_POSITION_INT as a fallback) -> GnssFix (WGS84, SI).

    GPS_RAW_INT: lat/lon degE7, alt mm above MSL, eph = HDOP x 100, vel cm/s, cog cdeg
    (course over ground), satellites_visible; 65535 (255 for satellites) means unknown.
    h_acc (mm) is a MAVLink 2 extension: 0 when absent or not reported -> None.
    GLOBAL_POSITION_INT is the autopilot's fused estimate, not a fix: source says so, it has
    no accuracy, HDOP or satellites; speed and course come from vx/vy (cm/s, north/east);
    fix_type is FIX_3D when it reports a position and NO_FIX when it reports (0, 0).
    """
    kind = msg.get_type()
    lat, lon = msg.lat / 1e7, msg.lon / 1e7
    if not _valid_position(lat, lon):
        return None
    alt = msg.alt / 1000.0
    if kind == "GPS_RAW_INT":
        h_acc = getattr(msg, "h_acc", 0) or 0
        return GnssFix(
            time,
            lat,
            lon,
            alt,
            _fix_type(msg.fix_type),
            satellites=None
            if msg.satellites_visible == _UINT8_UNKNOWN
            else int(msg.satellites_visible),
            h_acc_m=h_acc / 1000.0 if 0 < h_acc < 0xFFFFFFFF else None,
            hdop=None if msg.eph == _UINT16_UNKNOWN else msg.eph / 100.0,
            speed_mps=None if msg.vel == _UINT16_UNKNOWN else msg.vel / 100.0,
            course_rad=None
            if msg.cog == _UINT16_UNKNOWN
            else wrap_2pi(math.radians(msg.cog / 100.0)),
            source=kind,
        )
    if kind == "GLOBAL_POSITION_INT":
        north, east = msg.vx / 100.0, msg.vy / 100.0
        speed = math.hypot(north, east)
        has_position = msg.lat != 0 or msg.lon != 0
        return GnssFix(
            time,
            lat,
            lon,
            alt,
            GnssFixType.FIX_3D if has_position else GnssFixType.NO_FIX,
            speed_mps=speed,
            course_rad=wrap_2pi(math.atan2(east, north)) if speed > 0.0 else None,
            source=kind,
        )
    return None


def heading_from_mavlink(msg: Any, time: float) -> HeadingSample | None:
    """ATTITUDE.yaw (rad, -pi..pi), GLOBAL_POSITION_INT.hdg (cdeg, 65535 unknown) or
    VFR_HUD.heading (whole degrees) -> HeadingSample (rad clockwise from true north).

    resolution_rad is the source's quantisation: 0.01 deg for hdg, 1 deg for VFR_HUD.
    """
    kind = msg.get_type()
    if kind == "ATTITUDE":
        if not _finite(msg.yaw):
            return None
        return HeadingSample(time, wrap_2pi(msg.yaw), kind, 0.0)
    if kind == "GLOBAL_POSITION_INT":
        if msg.hdg == _UINT16_UNKNOWN:
            return None
        return HeadingSample(time, wrap_2pi(math.radians(msg.hdg / 100.0)), kind, _CENTIDEGREE_RAD)
    if kind == "VFR_HUD":
        return HeadingSample(time, wrap_2pi(math.radians(msg.heading)), kind, _DEGREE_RAD)
    return None


def attitude_from_mavlink(msg: Any, time: float) -> AttitudeSample | None:
    """ATTITUDE -> AttitudeSample (rad; roll/pitch FRD, yaw wrapped to [0, 2*pi))."""
    if msg.get_type() != "ATTITUDE" or not _finite(msg.roll, msg.pitch, msg.yaw):
        return None
    return AttitudeSample(time, msg.roll, msg.pitch, wrap_2pi(msg.yaw), "ATTITUDE")


def _whole(value: Any) -> int | None:
    """An integer field's value, None if it is not a whole finite number (a message
    built in code, or by a faulty sender through a dialect that has floats there)."""
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        return None
    return int(number) if math.isfinite(number) and number.is_integer() else None


def downward_range_sensor(msg: Any) -> int | None:
    """The sensor id of a downward-looking range message, else None.

    DISTANCE_SENSOR: its ``id`` when ``orientation`` is MAV_SENSOR_ROTATION_PITCH_270
    (looking down), None for any other orientation (a forward obstacle sensor).
    RANGEFINDER: 0 (ArduPilot sends it for its first downward rangefinder only).
    """
    kind = msg.get_type()
    if kind == "DISTANCE_SENSOR":
        if _whole(msg.orientation) != MAV_SENSOR_ROTATION_PITCH_270:
            return None
        return _whole(msg.id) or 0
    if kind == "RANGEFINDER":
        return 0
    return None


def range_from_mavlink(msg: Any, time: float) -> RangeSample | None:
    """DISTANCE_SENSOR looking down, or ArduPilot's RANGEFINDER -> RangeSample (metres).

    DISTANCE_SENSOR (#132): current/min/max_distance in cm (uint16); only orientation 25
    (MAV_SENSOR_ROTATION_PITCH_270, looking down) is a sounding. No reading -> None: a
    current_distance of 0 or 65535 (UINT16_MAX), outside the sensor's own [min, max], or a
    signal_quality of 1 (MAVLink: "invalid signal"; ArduPilot sends its 0 and 1 % so). A
    span that is not one (max 0 or 65535, max <= min) is unknown: min_m/max_m None, the
    distance unchecked. covariance (cm^2) -> variance_m2, 0 and 255 = unknown -> None;
    signal_quality (%, a MAVLink 2 extension: 0 when absent) 0 = unknown -> None, above
    100 is no percentage -> None.
    RANGEFINDER (#173, ardupilotmega): ``distance`` in metres (float), no span or quality;
    0, negative or not finite -> None.
    A non-reading is dropped rather than kept with a flag: the mapper must never take one
    as a distance, and a flag would leave that to every reader of the samples.
    """
    kind = msg.get_type()
    if kind == "RANGEFINDER":
        try:
            distance = float(msg.distance)
        except (TypeError, ValueError, OverflowError):
            return None
        if not _finite(distance) or distance <= 0.0:
            return None
        return RangeSample(time, distance, source=kind)
    if kind != "DISTANCE_SENSOR" or downward_range_sensor(msg) is None:
        return None
    current = _whole(msg.current_distance)
    if current is None or not 0 < current < _UINT16_UNKNOWN:
        return None
    quality = _whole(getattr(msg, "signal_quality", 0)) or 0
    if quality == 1:
        return None
    distance = current / 100.0
    low, high = _whole(msg.min_distance), _whole(msg.max_distance)
    min_m: float | None = None
    max_m: float | None = None
    if low is not None and high is not None and 0 <= low < high < _UINT16_UNKNOWN:
        min_m, max_m = low / 100.0, high / 100.0
        if not min_m <= distance <= max_m:
            return None
    covariance = _whole(msg.covariance) or 0
    return RangeSample(
        time,
        distance,
        min_m=min_m,
        max_m=max_m,
        signal_quality=quality if 1 < quality <= 100 else None,
        variance_m2=covariance * 1e-4 if 0 < covariance < _UINT8_UNKNOWN else None,
        source=kind,
    )


# --- Magnetometer ----------------------------------------------------------------------------


def tilt_compensated_heading(
    mag_frd: tuple[float, float, float],
    roll_rad: float,
    pitch_rad: float,
    declination_rad: float = 0.0,
) -> float | None:
    """Heading (rad clockwise from true north, [0, 2*pi)) from a body-frame field and attitude.

    The measured field m (body FRD, any unit) is rotated back to the level frame with the
    ZYX Euler angles (roll phi, pitch theta):
        Xh = mx cos(theta) + (my sin(phi) + mz cos(phi)) sin(theta)
        Yh = my cos(phi) - mz sin(phi)
    and the magnetic heading is atan2(-Yh, Xh); true heading adds the declination (east
    positive). Caruso, "Applications of magnetic sensors for low cost compass systems",
    IEEE PLANS 2000, doi:10.1109/PLANS.2000.838300. None when the field is (nearly) vertical
    or not finite: no heading can be read from it.
    """
    mx, my, mz = mag_frd
    if not _finite(mx, my, mz, roll_rad, pitch_rad, declination_rad):
        return None
    sin_r, cos_r = math.sin(roll_rad), math.cos(roll_rad)
    sin_p, cos_p = math.sin(pitch_rad), math.cos(pitch_rad)
    x_level = mx * cos_p + (my * sin_r + mz * cos_r) * sin_p
    y_level = my * cos_r - mz * sin_r
    if math.hypot(x_level, y_level) <= 1e-9 * max(1.0, math.hypot(mx, my, mz)):
        return None
    return wrap_2pi(math.atan2(-y_level, x_level) + declination_rad)


def compass_heading(
    imu: ImuSample, roll_rad: float, pitch_rad: float, declination_rad: float
) -> HeadingSample | None:
    """HeadingSample (source "MAG") from an IMU sample's magnetometer and the attitude."""
    if imu.mag_gauss is None:
        return None
    heading = tilt_compensated_heading(imu.mag_gauss, roll_rad, pitch_rad, declination_rad)
    return None if heading is None else HeadingSample(imu.time, heading, "MAG", 0.0)


# --- ArduPilot DataFlash --------------------------------------------------------------------
# Messages as pymavlink's DFMessage gives them: the format characters' own scaling is
# applied (L: degE7 -> deg, c/C/e: x 0.01), FMTU multipliers are not (MAG stays in mGauss).

DATAFLASH_MESSAGES: dict[str, tuple[str, int]] = {
    "IMU": ("IMU", 0),
    "IMU2": ("IMU", 1),
    "IMU3": ("IMU", 2),
    "GPS": ("GPS", 0),
    "GPS2": ("GPS", 1),
    "GPA": ("GPA", 0),
    "GPA2": ("GPA", 1),
    "MAG": ("MAG", 0),
    "MAG2": ("MAG", 1),
    "MAG3": ("MAG", 2),
    "ATT": ("ATT", 0),
}
"""DataFlash message name -> (kind, instance when the message has no I field)."""


def dataflash_kind(msg: Any) -> tuple[str, int] | None:
    """(kind, instance) of a DataFlash message we read, else None.

    Current logs give the instance in the I field; logs before ArduPilot 3.6 or so used
    separate types (IMU2, GPS2, MAG2).
    """
    known = DATAFLASH_MESSAGES.get(msg.get_type())
    if known is None:
        return None
    kind, instance = known
    if "I" in msg.fmt.colhash:
        instance = int(msg.I)
    return kind, instance


def _source(kind: str, instance: int) -> str:
    return f"{kind}[{instance}]"


def imu_from_dataflash(msg: Any, time: float) -> ImuSample | None:
    """DataFlash IMU (GyrX..Z rad/s, AccX..Z m/s^2, body FRD) -> ImuSample without mag."""
    known = dataflash_kind(msg)
    if known is None or known[0] != "IMU":
        return None
    gyro = (msg.GyrX, msg.GyrY, msg.GyrZ)
    accel = (msg.AccX, msg.AccY, msg.AccZ)
    if not _finite(*gyro, *accel):
        return None
    return ImuSample(time, accel, gyro, None, _source(*known))


def mag_from_dataflash(msg: Any) -> tuple[float, float, float] | None:
    """DataFlash MAG -> body-frame field (gauss), None if not finite.

    MagX..Z is the corrected field (offsets, scaling and board orientation applied) as int16
    milligauss; a FMTU saying plain "Gauss" (no milli multiplier) is honoured.
    """
    field = (msg.MagX, msg.MagY, msg.MagZ)
    scale = 1.0 if msg.fmt.get_unit("MagX") == "Gauss" else 1e-3
    if not _finite(*field):
        return None
    return (field[0] * scale, field[1] * scale, field[2] * scale)


def gnss_from_dataflash(msg: Any, time: float, h_acc_m: float | None = None) -> GnssFix | None:
    """DataFlash GPS -> GnssFix.

    Status is AP_GPS::GPS_Status, numbered like MAVLink's GPS_FIX_TYPE; Lat/Lng degrees
    (format L), Alt metres above MSL (format e, cm), Spd m/s, GCrs degrees (course), NSats,
    HDop (format C/c, x 0.01). The horizontal accuracy is in the GPA message logged with
    it (``h_acc_from_dataflash``).
    """
    known = dataflash_kind(msg)
    if known is None or known[0] != "GPS":
        return None
    lat, lon, alt = msg.Lat, msg.Lng, msg.Alt
    if not _finite(lat, lon, alt) or not _valid_position(lat, lon):
        return None
    speed = getattr(msg, "Spd", None)
    course = getattr(msg, "GCrs", None)
    hdop = getattr(msg, "HDop", None)
    return GnssFix(
        time,
        lat,
        lon,
        alt,
        _fix_type(int(msg.Status)),
        satellites=int(msg.NSats),
        h_acc_m=h_acc_m,
        hdop=float(hdop) if hdop is not None and _finite(hdop) else None,
        speed_mps=float(speed) if speed is not None and _finite(speed) else None,
        course_rad=wrap_2pi(math.radians(course))
        if course is not None and _finite(course)
        else None,
        source=_source(*known),
    )


def h_acc_from_dataflash(msg: Any) -> float | None:
    """DataFlash GPA.HAcc (format C: metres) -> metres, None when 0 (not reported)."""
    h_acc = getattr(msg, "HAcc", None)
    if h_acc is None or not _finite(h_acc) or h_acc <= 0.0:
        return None
    return float(h_acc)


def attitude_from_dataflash(msg: Any, time: float) -> AttitudeSample | None:
    """DataFlash ATT (Roll, Pitch, Yaw in degrees, whether logged as c/C centidegrees or
    f degrees) -> AttitudeSample (rad, yaw in [0, 2*pi))."""
    if msg.get_type() != "ATT" or not _finite(msg.Roll, msg.Pitch, msg.Yaw):
        return None
    return AttitudeSample(
        time,
        math.radians(msg.Roll),
        math.radians(msg.Pitch),
        wrap_2pi(math.radians(msg.Yaw)),
        "ATT",
    )


def heading_from_dataflash(msg: Any, time: float) -> HeadingSample | None:
    """DataFlash ATT.Yaw (degrees) -> HeadingSample; 0.01 deg resolution when logged as C."""
    if msg.get_type() != "ATT" or not _finite(msg.Yaw):
        return None
    yaw_format = msg.fmt.format[msg.fmt.colhash["Yaw"]]
    resolution = _CENTIDEGREE_RAD if yaw_format in "cC" else 0.0
    return HeadingSample(time, wrap_2pi(math.radians(msg.Yaw)), "ATT", resolution)


DATAFLASH_RANGE_MESSAGES = ("RFND",)
"""DataFlash messages of the rangefinders (``ranges_from_dataflash``)."""

_RFND_GOOD = 4
"""AP_RangeFinder RangeFinder::Status::Good (0 NotConnected, 1 NoData, 2 OutOfRangeLow,
3 OutOfRangeHigh)."""


def _rfnd_metres(msg: Any, column: str) -> float:
    """A RFND distance field in metres, whatever the log declares it as.

    ArduPilot logged it as format C (uint16 cm, which DFMessage scales by 0.01 to metres),
    and newer versions as a float in metres. A plain integer is centimetres unless the
    log's FMTU says metres; a float is metres unless the FMTU says centimetres.
    """
    value = float(getattr(msg, column))
    char = msg.fmt.format[msg.fmt.colhash[column]]
    unit = msg.fmt.get_unit(column)
    if char in "cCeE":
        return value
    if char in "fdg":
        return value / 100.0 if unit == "cm" else value
    return value if unit == "m" else value / 100.0


def ranges_from_dataflash(msg: Any, time: float) -> list[tuple[int, RangeSample | None]]:
    """DataFlash RFND -> (rangefinder instance, RangeSample or None) of each downward one.

    Layouts met in ArduPilot logs (read from the log's own FMT, not assumed):
    ``TimeUS,Instance,Dist,Stat,Orient[,Quality]`` (one instance per message, 3.7 on),
    ``TimeUS,Dist1,Orient1,Dist2,Orient2`` and, before orientations, ``TimeUS,Dist1,Dist2``
    (every rangefinder then looked down). Dist: see ``_rfnd_metres``. Orient 25 is
    downward; others are left out. No reading -> None: Stat other than Good (4), Dist 0 or
    less or not finite, Quality 0 (no signal) or 1 (ArduPilot sends both as MAVLink's
    "invalid"); Quality -1 is unknown -> signal_quality None.
    """
    columns = msg.fmt.colhash
    if "Dist" in columns:
        instance = (_whole(msg.Instance) or 0) if "Instance" in columns else 0
        fields = [(instance, "Dist", "Orient")]
    else:
        fields = [(k - 1, f"Dist{k}", f"Orient{k}") for k in (1, 2) if f"Dist{k}" in columns]
    out: list[tuple[int, RangeSample | None]] = []
    for instance, dist, orient in fields:
        if orient in columns and _whole(getattr(msg, orient)) != MAV_SENSOR_ROTATION_PITCH_270:
            continue
        out.append((instance, _rfnd_sample(msg, time, dist)))
    return out


def _rfnd_sample(msg: Any, time: float, dist: str) -> RangeSample | None:
    columns = msg.fmt.colhash
    if "Stat" in columns and _whole(msg.Stat) != _RFND_GOOD:
        return None
    quality = _whole(msg.Quality) if "Quality" in columns else -1
    if quality in (0, 1):
        return None
    distance = _rfnd_metres(msg, dist)
    if not _finite(distance) or distance <= 0.0:
        return None
    return RangeSample(
        time,
        distance,
        signal_quality=quality if quality is not None and 1 < quality <= 100 else None,
        source="RFND",
    )
