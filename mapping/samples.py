"""Typed sensor samples: what the mapping core takes in.

Drivers (``drivers/``) turn bytes from devices and logs into these records; the core never
sees a wire format. Units are SI and frames are the contract's:

- time: UNIX seconds (float) of the boat computer's clock, stamped on receipt;
- body frame FRD (x forward, y starboard, z down), as MAVLink uses it;
- headings: radians clockwise from *true* north, in [0, 2*pi);
- sonar bearings: radians, positive to starboard; polar row 0 is the nearest range.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import numpy.typing as npt


class GnssFixType(IntEnum):
    """MAVLink GPS_FIX_TYPE values that matter to us."""

    NO_GPS = 0
    NO_FIX = 1
    FIX_2D = 2
    FIX_3D = 3
    DGPS = 4
    RTK_FLOAT = 5
    RTK_FIXED = 6
    STATIC = 7
    PPP = 8


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One inertial measurement, body frame FRD.

    accel_mps2: specific force (m/s^2), as an accelerometer measures it (at rest: z = -9.81).
    gyro_rps: angular rate (rad/s).
    mag_gauss: magnetic field (gauss), or None when the message has none.
    source: the message it came from, e.g. ``"RAW_IMU"`` or ``"IMU[0]"``.
    """

    time: float
    accel_mps2: tuple[float, float, float]
    gyro_rps: tuple[float, float, float]
    mag_gauss: tuple[float, float, float] | None = None
    source: str = ""


@dataclass(frozen=True, slots=True)
class GnssFix:
    """One GNSS position fix (WGS84).

    lat_deg/lon_deg: degrees; alt_m: metres above mean sea level.
    h_acc_m: reported horizontal accuracy (1 sigma, metres) or None when not reported;
    hdop: horizontal dilution of precision or None.
    speed_mps / course_rad: ground speed and course over ground (radians clockwise from
    true north), None when unknown. Course is not heading: a boat crabbing in a current
    moves along its course and points along its heading.
    """

    time: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    fix_type: GnssFixType
    satellites: int | None = None
    h_acc_m: float | None = None
    hdop: float | None = None
    speed_mps: float | None = None
    course_rad: float | None = None
    source: str = ""

    @property
    def usable(self) -> bool:
        """A 2D fix or better."""
        return self.fix_type >= GnssFixType.FIX_2D


@dataclass(frozen=True, slots=True)
class HeadingSample:
    """A heading observation: radians clockwise from true north, in [0, 2*pi).

    source names where it came from (``"ATTITUDE"``, ``"VFR_HUD"``, ``"GLOBAL_POSITION_INT"``,
    ``"MAG"``); resolution_rad is the quantisation of the source (VFR_HUD gives whole degrees).
    """

    time: float
    heading_rad: float
    source: str = ""
    resolution_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    """Roll and pitch (radians, FRD: roll positive starboard down, pitch positive nose up)."""

    time: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    source: str = ""


@dataclass(frozen=True, slots=True)
class RangeSample:
    """One sounding of a downward-looking echosounder (a Ping2-class altimeter on the
    autopilot): the distance from its transducer to the bottom along its beam (metres),
    which is along the body's down axis. Not the sonar's altitude: the transducer sits at
    its own mount offset, and the boat's roll and pitch tilt the beam.

    min_m / max_m: the sensor's valid span (None: unknown); signal_quality: 1..100 percent
    (None: not reported); variance_m2: the sensor's own variance of the distance (None:
    not reported). source: the message, e.g. ``"DISTANCE_SENSOR"``, ``"RANGEFINDER"``,
    ``"RFND"``.
    """

    time: float
    distance_m: float
    min_m: float | None = None
    max_m: float | None = None
    signal_quality: int | None = None
    variance_m2: float | None = None
    source: str = ""


NavSample = ImuSample | GnssFix | HeadingSample | AttitudeSample | RangeSample


@dataclass(frozen=True, slots=True, eq=False)
class Ping:
    """One sonar ping, as the mapping core sees it.

    time: receive time (UNIX s). ping_id: the sonar's counter.
    master_mode: 1 low frequency (wide), 2 high frequency (narrow).
    frequency_hz: the carrier the sonar reports.
    range_resolution_m: metres per range bin; range of bin i ~= (i + 0.5) * range_resolution_m.
    bearings_rad: (n_beams,) float64, positive to starboard, ascending, NOT evenly spaced.
    image: (n_ranges, n_beams) uint8 or uint16 echo intensities, row 0 nearest.
    gains: (n_ranges,) per-row gain the sonar applied, or None when it did not send them.
    speed_of_sound_mps: the speed of sound the sonar used.
    gain_percent / gamma: the fire settings echoed back.
    heading/pitch/roll_rad: the sonar's own attitude sensor (v2 pings only), else None.
    """

    time: float
    ping_id: int
    master_mode: int
    frequency_hz: float
    range_resolution_m: float
    bearings_rad: npt.NDArray[np.float64]
    image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]
    gains: npt.NDArray[np.float64] | None = None
    speed_of_sound_mps: float = 0.0
    gain_percent: float = 0.0
    gamma: int = 0
    heading_rad: float | None = None
    pitch_rad: float | None = None
    roll_rad: float | None = None
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def n_ranges(self) -> int:
        return int(self.image.shape[0])

    @property
    def n_beams(self) -> int:
        return int(self.image.shape[1])

    @property
    def max_range_m(self) -> float:
        return self.n_ranges * self.range_resolution_m

    @property
    def sample_bits(self) -> int:
        return 8 * int(self.image.dtype.itemsize)
