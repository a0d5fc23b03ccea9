"""MAVLink navigation: logs (.tlog, DataFlash .bin) and messages into typed samples.

``convert`` turns one decoded message into a sample (shared with the live link);
``framing`` finds and decodes the messages of a log file, past damage;
``navlog`` reads whole logs into samples and summarises them for ``seamap info``.
"""

from drivers.mavlink.convert import (
    GNSS_MESSAGES,
    GRAVITY_MPS2,
    HEADING_AUTO_ORDER,
    HEADING_MESSAGES,
    IMU_AUTO_ORDER,
    IMU_MESSAGES,
    RANGE_MESSAGES,
    attitude_from_dataflash,
    attitude_from_mavlink,
    autopilot_name,
    compass_heading,
    gnss_from_dataflash,
    gnss_from_mavlink,
    heading_from_dataflash,
    heading_from_mavlink,
    imu_from_dataflash,
    imu_from_mavlink,
    imu_instance,
    imu_source_usable,
    is_autopilot_heartbeat,
    range_from_mavlink,
    ranges_from_dataflash,
    tilt_compensated_heading,
    wrap_2pi,
)
from drivers.mavlink.navlog import (
    NavLog,
    NavLogError,
    NavReadReport,
    read_nav_log,
    summarize_nav_log,
)

__all__ = [
    "GNSS_MESSAGES",
    "GRAVITY_MPS2",
    "HEADING_AUTO_ORDER",
    "HEADING_MESSAGES",
    "IMU_AUTO_ORDER",
    "IMU_MESSAGES",
    "RANGE_MESSAGES",
    "NavLog",
    "NavLogError",
    "NavReadReport",
    "attitude_from_dataflash",
    "attitude_from_mavlink",
    "autopilot_name",
    "compass_heading",
    "gnss_from_dataflash",
    "gnss_from_mavlink",
    "heading_from_dataflash",
    "heading_from_mavlink",
    "imu_from_dataflash",
    "imu_from_mavlink",
    "imu_instance",
    "imu_source_usable",
    "is_autopilot_heartbeat",
    "range_from_mavlink",
    "ranges_from_dataflash",
    "read_nav_log",
    "summarize_nav_log",
    "tilt_compensated_heading",
    "wrap_2pi",
]
