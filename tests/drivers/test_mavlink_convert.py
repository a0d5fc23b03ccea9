"""One message in, one sample out: units, sentinels, frames (drivers/mavlink/convert.py)."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import DFReader
from pymavlink.dialects.v20 import all as mavlink

from drivers.mavlink import convert
from mapping.samples import GnssFixType
from tests.drivers.mavlink_fixtures import ARDUPILOT_FORMATS, ATT_DEGREES, body_from_ned
from tests.drivers.mavlink_fixtures import earth_field_ned as field_ned

T = 1_718_000_000.25
DEG = math.radians(1.0)


def on_the_wire(msg: Any) -> Any:
    """The message as a receiver decodes it (float32 rounding, MAVLink 2 truncation)."""
    return mavlink.MAVLink(None).decode(bytearray(msg.pack(mavlink.MAVLink(None, 1, 1))))


# --- IMU -------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"])
def test_ardupilot_imu_scaling_milli_g_mrad_milligauss(kind: str) -> None:
    fields = (1000, -500, -1000, 1000, -250, 0, 300, -120, 450)
    if kind == "RAW_IMU":
        msg = mavlink.MAVLink_raw_imu_message(123, *fields)
    else:
        cls = getattr(mavlink, f"MAVLink_{kind.lower()}_message")
        msg = cls(123, *fields)
    sample = convert.imu_from_mavlink(on_the_wire(msg), T)
    assert sample is not None
    assert sample.time == T
    assert sample.accel_mps2 == pytest.approx((9.80665, -4.903325, -9.80665), rel=1e-12)
    assert sample.gyro_rps == pytest.approx((1.0, -0.25, 0.0), abs=1e-15)
    assert sample.mag_gauss == pytest.approx((0.3, -0.12, 0.45), rel=1e-12)
    assert sample.source == kind


def test_imu_without_compass_has_no_mag() -> None:
    msg = mavlink.MAVLink_raw_imu_message(0, 10, 20, -1000, 1, 2, 3, 0, 0, 0)
    sample = convert.imu_from_mavlink(on_the_wire(msg), T)
    assert sample is not None and sample.mag_gauss is None


def test_highres_imu_is_si_already() -> None:
    msg = mavlink.MAVLink_highres_imu_message(
        5, 0.5, -0.25, -9.75, 0.125, -0.0625, 1.5, 0.25, -0.125, 0.5, 1013.0, 0, 10, 20, 0x1FF, 0
    )
    sample = convert.imu_from_mavlink(on_the_wire(msg), T)
    assert sample is not None
    assert sample.accel_mps2 == (0.5, -0.25, -9.75)
    assert sample.gyro_rps == (0.125, -0.0625, 1.5)
    assert sample.mag_gauss == (0.25, -0.125, 0.5)
    assert sample.source == "HIGHRES_IMU"


def test_highres_imu_with_nan_gives_no_sample() -> None:
    msg = mavlink.MAVLink_highres_imu_message(5, math.nan, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert convert.imu_from_mavlink(on_the_wire(msg), T) is None


def test_raw_imu_is_not_used_for_px4() -> None:
    assert not convert.imu_source_usable("raw", "px4")
    assert convert.imu_source_usable("raw", "ardupilot")
    assert convert.imu_source_usable("raw", "unknown")
    assert convert.imu_source_usable("highres", "px4")


def test_imu_instance_comes_from_the_mavlink2_id_extension() -> None:
    msg = mavlink.MAVLink_raw_imu_message(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 2, 0)
    assert convert.imu_instance(on_the_wire(msg)) == 2
    assert convert.imu_instance(on_the_wire(mavlink.MAVLink_scaled_imu2_message(0, *[1] * 9))) == 0


# --- GNSS ------------------------------------------------------------------------------------


def gps_raw(**changes: int) -> Any:
    fields = dict(
        time_usec=0, fix_type=6, lat=-353632621, lon=1491652374, alt=584200, eph=87, epv=120,
        vel=250, cog=27000, satellites_visible=14, alt_ellipsoid=0, h_acc=1350, v_acc=2000,
        vel_acc=0, hdg_acc=0, yaw=0,
    )  # fmt: skip
    fields.update(changes)
    return on_the_wire(mavlink.MAVLink_gps_raw_int_message(**fields))


def test_gps_raw_int_units() -> None:
    fix = convert.gnss_from_mavlink(gps_raw(), T)
    assert fix is not None
    assert (fix.lat_deg, fix.lon_deg) == (-35.3632621, 149.1652374)
    assert fix.alt_m == pytest.approx(584.2, abs=1e-12)
    assert fix.fix_type is GnssFixType.RTK_FIXED and fix.usable
    assert fix.hdop == pytest.approx(0.87)
    assert fix.speed_mps == pytest.approx(2.5)
    assert fix.course_rad == pytest.approx(1.5 * math.pi)
    assert fix.satellites == 14
    assert fix.h_acc_m == pytest.approx(1.35)
    assert fix.source == "GPS_RAW_INT"


def test_gps_raw_int_unknown_sentinels_become_none() -> None:
    fix = convert.gnss_from_mavlink(
        gps_raw(eph=65535, vel=65535, cog=65535, satellites_visible=255, h_acc=0, fix_type=1), T
    )
    assert fix is not None
    assert (fix.hdop, fix.speed_mps, fix.course_rad, fix.satellites, fix.h_acc_m) == (None,) * 5
    assert fix.fix_type is GnssFixType.NO_FIX and not fix.usable


def test_gps_raw_int_out_of_range_position_is_rejected() -> None:
    assert convert.gnss_from_mavlink(gps_raw(lat=950_000_000), T) is None


def test_global_position_int_fallback_is_marked_and_derives_speed_and_course() -> None:
    msg = mavlink.MAVLink_global_position_int_message(
        0, 480000000, -40000000, 12_340, 100, 300, -300, 5, 65535
    )
    fix = convert.gnss_from_mavlink(on_the_wire(msg), T)
    assert fix is not None
    assert fix.source == "GLOBAL_POSITION_INT"
    assert (fix.lat_deg, fix.lon_deg, fix.alt_m) == (48.0, -4.0, 12.34)
    assert fix.speed_mps == pytest.approx(math.hypot(3.0, 3.0))
    assert fix.course_rad == pytest.approx(math.radians(315.0))
    assert fix.fix_type is GnssFixType.FIX_3D
    assert (fix.hdop, fix.h_acc_m, fix.satellites) == (None, None, None)


def test_global_position_int_without_position_is_no_fix() -> None:
    msg = mavlink.MAVLink_global_position_int_message(0, 0, 0, 0, 0, 0, 0, 0, 0)
    fix = convert.gnss_from_mavlink(on_the_wire(msg), T)
    assert fix is not None and fix.fix_type is GnssFixType.NO_FIX and fix.course_rad is None


# --- heading and attitude ----------------------------------------------------------------------


def attitude(roll: float, pitch: float, yaw: float) -> Any:
    return on_the_wire(mavlink.MAVLink_attitude_message(0, roll, pitch, yaw, 0, 0, 0))


@pytest.mark.parametrize(
    ("yaw", "expected"),
    [(-math.pi / 2, 1.5 * math.pi), (0.5, 0.5), (-1e-9, 2 * math.pi - 1e-9), (math.pi, math.pi)],
)
def test_attitude_yaw_becomes_compass_heading(yaw: float, expected: float) -> None:
    heading = convert.heading_from_mavlink(attitude(0.0, 0.0, yaw), T)
    assert heading is not None and heading.source == "ATTITUDE"
    assert heading.heading_rad == pytest.approx(expected, abs=1e-7)
    assert 0.0 <= heading.heading_rad < 2 * math.pi


def test_attitude_sample_is_radians_frd() -> None:
    sample = convert.attitude_from_mavlink(attitude(0.25, -0.125, -0.5), T)
    assert sample is not None
    assert (sample.roll_rad, sample.pitch_rad) == (0.25, -0.125)
    assert sample.yaw_rad == pytest.approx(2 * math.pi - 0.5)
    assert convert.attitude_from_mavlink(attitude(math.nan, 0, 0), T) is None


def test_global_position_heading_centidegrees_and_unknown() -> None:
    def hdg(value: int) -> Any:
        return on_the_wire(
            mavlink.MAVLink_global_position_int_message(0, 1, 1, 0, 0, 0, 0, 0, value)
        )

    heading = convert.heading_from_mavlink(hdg(27050), T)
    assert heading is not None and heading.source == "GLOBAL_POSITION_INT"
    assert heading.heading_rad == pytest.approx(math.radians(270.5))
    assert heading.resolution_rad == pytest.approx(math.radians(0.01))
    assert convert.heading_from_mavlink(hdg(65535), T) is None
    wrapped = convert.heading_from_mavlink(hdg(36000), T)
    assert wrapped is not None and wrapped.heading_rad == 0.0


def test_vfr_hud_heading_is_whole_degrees() -> None:
    def hud(value: int) -> Any:
        return on_the_wire(mavlink.MAVLink_vfr_hud_message(0, 1.5, value, 0, 0, 0))

    heading = convert.heading_from_mavlink(hud(359), T)
    assert heading is not None and heading.source == "VFR_HUD"
    assert heading.heading_rad == pytest.approx(math.radians(359))
    assert heading.resolution_rad == pytest.approx(math.radians(1))
    north = convert.heading_from_mavlink(hud(360), T)
    assert north is not None and north.heading_rad == 0.0


def test_wrap_never_returns_two_pi() -> None:
    assert convert.wrap_2pi(-1e-17) == 0.0
    assert convert.wrap_2pi(2 * math.pi) == 0.0
    assert convert.wrap_2pi(-math.pi) == pytest.approx(math.pi)


# --- tilt-compensated compass --------------------------------------------------------------


def test_compass_recovers_heading_with_roll_pitch_and_declination() -> None:
    # True heading 30 deg, roll 10, pitch -5, a field dipping 64 deg, declination 12.5 E.
    field = field_ned(declination_deg=12.5, inclination_deg=64.0, strength_gauss=0.48)
    body = body_from_ned(field, 30.0, 10.0, -5.0)
    heading = convert.tilt_compensated_heading(
        body, math.radians(10.0), math.radians(-5.0), math.radians(12.5)
    )
    assert heading == pytest.approx(math.radians(30.0), abs=1e-9)
    # Without the tilt compensation the same reading is degrees off: it matters.
    level = convert.tilt_compensated_heading(body, 0.0, 0.0, math.radians(12.5))
    assert level is not None and abs(level - math.radians(30.0)) > math.radians(2.0)


@settings(max_examples=200, deadline=None)
@given(
    heading=st.floats(0.0, 359.99),
    roll=st.floats(-60.0, 60.0),
    pitch=st.floats(-60.0, 60.0),
    inclination=st.floats(-80.0, 80.0),
    declination=st.floats(-30.0, 30.0),
)
def test_compass_heading_property(
    heading: float, roll: float, pitch: float, inclination: float, declination: float
) -> None:
    body = body_from_ned(field_ned(declination, inclination), heading, roll, pitch)
    result = convert.tilt_compensated_heading(
        body, math.radians(roll), math.radians(pitch), math.radians(declination)
    )
    assert result is not None and 0.0 <= result < 2 * math.pi
    error = (result - math.radians(heading) + math.pi) % (2 * math.pi) - math.pi
    assert abs(error) < 1e-7


def test_compass_heading_sample_needs_a_magnetometer() -> None:
    imu = convert.imu_from_mavlink(
        on_the_wire(mavlink.MAVLink_raw_imu_message(0, 0, 0, -1000, 0, 0, 0, 200, 0, 400)), T
    )
    assert imu is not None
    sample = convert.compass_heading(imu, 0.0, 0.0, 0.0)
    assert sample is not None and sample.source == "MAG" and sample.time == T
    assert sample.heading_rad == pytest.approx(0.0)
    no_mag = convert.imu_from_mavlink(
        on_the_wire(mavlink.MAVLink_raw_imu_message(0, 0, 0, -1000, 0, 0, 0, 0, 0, 0)), T
    )
    assert no_mag is not None and convert.compass_heading(no_mag, 0.0, 0.0, 0.0) is None


def test_vertical_field_gives_no_heading() -> None:
    assert convert.tilt_compensated_heading((0.0, 0.0, 0.5), 0.0, 0.0) is None


# --- DataFlash -------------------------------------------------------------------------------


def dataflash(name: str, values: dict[str, Any], fmt: tuple[str, str] | None = None) -> Any:
    """A DataFlash message as pymavlink's DFReader gives it, from logged (raw) values."""
    type_id, chars, columns = ARDUPILOT_FORMATS.get(name, (0, "", ""))
    if fmt is not None:
        chars, columns = fmt
    described = DFReader.DFFormat(type_id, name, 0, chars, columns)
    elements = [values.get(column, 0) for column in described.columns]
    return DFReader.DFMessage(described, elements, True, None)


def test_dataflash_imu_is_si_frd_with_instance() -> None:
    msg = dataflash(
        "IMU",
        {"I": 1, "GyrX": 0.5, "GyrY": -0.25, "GyrZ": 0.125, "AccX": 1.5, "AccY": 0, "AccZ": -9.75},
    )
    sample = convert.imu_from_dataflash(msg, T)
    assert sample is not None
    assert sample.gyro_rps == (0.5, -0.25, 0.125)
    assert sample.accel_mps2 == (1.5, 0.0, -9.75)
    assert sample.mag_gauss is None and sample.source == "IMU[1]"


def test_dataflash_old_imu2_type_is_instance_one() -> None:
    msg = dataflash(
        "IMU2",
        {"GyrX": 0.5},
        fmt=("QffffffIIfBBHH", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    )
    assert convert.dataflash_kind(msg) == ("IMU", 1)


def test_dataflash_gps_units() -> None:
    msg = dataflash(
        "GPS",
        {"I": 0, "Status": 3, "NSats": 11, "HDop": 87, "Lat": -353632621, "Lng": 1491652374,
         "Alt": 58420, "Spd": 2.5, "GCrs": 271.5},
    )  # fmt: skip
    fix = convert.gnss_from_dataflash(msg, T, h_acc_m=1.35)
    assert fix is not None
    assert (fix.lat_deg, fix.lon_deg) == (-35.3632621, 149.1652374)
    assert fix.alt_m == pytest.approx(584.2)
    assert fix.hdop == pytest.approx(0.87)
    assert fix.speed_mps == 2.5
    assert fix.course_rad == pytest.approx(math.radians(271.5))
    assert fix.fix_type is GnssFixType.FIX_3D and fix.satellites == 11
    assert fix.h_acc_m == 1.35 and fix.source == "GPS[0]"


def test_dataflash_gpa_horizontal_accuracy() -> None:
    assert convert.h_acc_from_dataflash(dataflash("GPA", {"HAcc": 135})) == pytest.approx(1.35)
    assert convert.h_acc_from_dataflash(dataflash("GPA", {"HAcc": 0})) is None


def test_dataflash_att_centidegrees_and_degrees_agree() -> None:
    old = dataflash("ATT", {"Roll": 1000, "Pitch": -550, "Yaw": 35050})
    new = dataflash("ATT", {"Roll": 10.0, "Pitch": -5.5, "Yaw": 350.5}, fmt=ATT_DEGREES)
    for msg, resolution in ((old, math.radians(0.01)), (new, 0.0)):
        sample = convert.attitude_from_dataflash(msg, T)
        assert sample is not None
        assert sample.roll_rad == pytest.approx(math.radians(10.0))
        assert sample.pitch_rad == pytest.approx(math.radians(-5.5))
        assert sample.yaw_rad == pytest.approx(math.radians(350.5))
        heading = convert.heading_from_dataflash(msg, T)
        assert heading is not None and heading.source == "ATT"
        assert heading.heading_rad == pytest.approx(math.radians(350.5))
        assert heading.resolution_rad == pytest.approx(resolution)


def test_dataflash_mag_milligauss_to_gauss() -> None:
    msg = dataflash("MAG", {"MagX": 200, "MagY": -35, "MagZ": 410})
    assert convert.mag_from_dataflash(msg) == pytest.approx((0.2, -0.035, 0.41))
    # With the log's units (FMTU): "G" with multiplier "C" (1e-3) is mGauss, still x 1e-3.
    msg.fmt.set_unit_ids("s#GGGGGGGGG-s", {"G": "Gauss"})
    msg.fmt.set_mult_ids("F-CCCCCCCCC-F", {"C": 1e-3, "F": 1e-6})
    assert convert.mag_from_dataflash(msg) == pytest.approx((0.2, -0.035, 0.41))
    plain = dataflash(
        "MAG", {"MagX": 0.25, "MagY": 0, "MagZ": 0.5}, fmt=("QBfff", "TimeUS,I,MagX,MagY,MagZ")
    )
    plain.fmt.set_unit_ids("s#GGG", {"G": "Gauss"})
    assert convert.mag_from_dataflash(plain) == (0.25, 0.0, 0.5)


def test_autopilot_heartbeats() -> None:
    def heartbeat(mav_type: int, autopilot: int) -> Any:
        return on_the_wire(mavlink.MAVLink_heartbeat_message(mav_type, autopilot, 0, 0, 0, 3))

    assert convert.is_autopilot_heartbeat(heartbeat(11, 3))
    assert convert.is_autopilot_heartbeat(heartbeat(10, 12))
    assert not convert.is_autopilot_heartbeat(heartbeat(6, 8))  # GCS
    assert not convert.is_autopilot_heartbeat(heartbeat(6, 3))  # GCS claiming ArduPilot
    assert not convert.is_autopilot_heartbeat(heartbeat(18, 8))  # companion computer
    assert not convert.is_autopilot_heartbeat(heartbeat(30, 12))  # a camera naming PX4
    assert not convert.is_autopilot_heartbeat(heartbeat(26, 3))  # a gimbal naming ArduPilot
    assert [convert.autopilot_name(a) for a in (3, 12, 0)] == ["ardupilot", "px4", "unknown"]
