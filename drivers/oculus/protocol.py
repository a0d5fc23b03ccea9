"""Oculus M-series network messages: header, enumerations, Status and SimpleFire.

Every message is a 16-byte little-endian header (``<HHHHHIH``: oculusId 0x4F53, srcDeviceId,
dstDeviceId, msgId, msgVersion, payloadSize, spare) followed by ``payloadSize`` bytes. The
layouts are in ``/work/shared/docs/PROTOCOLS.md``; SimplePingResult lives in ``ping.py``.
"""

from __future__ import annotations

import socket
import struct
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from typing import TYPE_CHECKING

from drivers.errors import SeamapError

if TYPE_CHECKING:
    pass

OCULUS_ID = 0x4F53
OCULUS_MAGIC = b"SO"  # OCULUS_ID as it appears on the wire (little-endian)
HEADER_SIZE = 16
STATUS_SIZE = 142
SIMPLE_FIRE_V1_SIZE = 53
SIMPLE_FIRE_V2_SIZE = 89

_HEADER = struct.Struct("<HHHHHIH")
# IP addresses and the MAC are read as raw bytes: the sonar sends them in network order.
_STATUS_BODY = struct.Struct("<IHHI6I4s4s4s6s8dd")
FIRE_V1_BODY = struct.Struct("<BBBBBdddd")  # bytes 16..53 of a v1 or v2 fire/ping message
FIRE_V2_EXT = struct.Struct("<I8I")  # bytes 53..89 of a v2 fire/ping message

assert _HEADER.size == HEADER_SIZE
assert HEADER_SIZE + _STATUS_BODY.size == STATUS_SIZE
assert HEADER_SIZE + FIRE_V1_BODY.size == SIMPLE_FIRE_V1_SIZE
assert SIMPLE_FIRE_V1_SIZE + FIRE_V2_EXT.size == SIMPLE_FIRE_V2_SIZE


class OculusFormatError(SeamapError):
    """Bytes that are not a valid Oculus message or log; the message names what is off."""


class MessageId(IntEnum):
    """Oculus msgId values."""

    STATUS = 0x01
    SIMPLE_FIRE = 0x15
    PING_RESULT = 0x22
    SIMPLE_PING_RESULT = 0x23
    USER_CONFIG = 0x55
    LOGS = 0x80
    DUMMY = 0xFF

    @property
    def display_name(self) -> str:
        """The Blueprint name, e.g. ``SimplePingResult``."""
        return _DISPLAY_NAMES[self]


_DISPLAY_NAMES = {
    MessageId.STATUS: "Status",
    MessageId.SIMPLE_FIRE: "SimpleFire",
    MessageId.PING_RESULT: "PingResult",
    MessageId.SIMPLE_PING_RESULT: "SimplePingResult",
    MessageId.USER_CONFIG: "UserConfig",
    MessageId.LOGS: "Logs",
    MessageId.DUMMY: "Dummy",
}


def message_name(msg_id: int) -> str:
    """A readable name for any msgId (``0x42`` for ids we do not know)."""
    try:
        return MessageId(msg_id).display_name
    except ValueError:
        return f"0x{msg_id:02X}"


class PingRate(IntEnum):
    """Maximum ping rate requested in SimpleFire (the enum values are not in rate order)."""

    HZ10 = 0
    HZ15 = 1
    HZ40 = 2
    HZ5 = 3
    HZ2 = 4
    STANDBY = 5

    @property
    def hz(self) -> float:
        """Maximum ping rate in Hz (0 for standby)."""
        return _PING_RATE_HZ[self]


_PING_RATE_HZ = {
    PingRate.HZ10: 10.0,
    PingRate.HZ15: 15.0,
    PingRate.HZ40: 40.0,
    PingRate.HZ5: 5.0,
    PingRate.HZ2: 2.0,
    PingRate.STANDBY: 0.0,
}


class DataSize(IntEnum):
    """Sample size of a ping image."""

    BITS8 = 0
    BITS16 = 1
    BITS24 = 2
    BITS32 = 3

    @property
    def bytes(self) -> int:
        return int(self) + 1


class FireFlags(IntFlag):
    """SimpleFire ``flags`` bits (echoed back in every SimplePingResult)."""

    RANGE_IN_METRES = 0x01
    DATA_16BIT = 0x02
    SEND_GAIN = 0x04
    SIMPLE_RETURN = 0x08
    GAIN_ASSIST = 0x10
    LOW_POWER = 0x20
    BEAMS_512 = 0x40
    NETWORK_TRIGGER = 0x80


class MasterMode(IntEnum):
    """Operating frequency (M1200d: 1 = 1.2 MHz 130° up to 40 m, 2 = 2.1 MHz 60° up to 10 m)."""

    LOW_FREQUENCY = 1
    HIGH_FREQUENCY = 2


def _as_bytes(buf: bytes | bytearray | memoryview) -> bytes:
    return buf if isinstance(buf, bytes) else bytes(buf)


@dataclass(frozen=True)
class MessageHeader:
    """The 16-byte header that starts every Oculus message."""

    src_device_id: int
    dst_device_id: int
    msg_id: int
    msg_version: int
    payload_size: int
    spare: int = 0

    @property
    def message_size(self) -> int:
        """Whole message length in bytes (header + payload)."""
        return HEADER_SIZE + self.payload_size

    def pack(self) -> bytes:
        return _HEADER.pack(
            OCULUS_ID,
            self.src_device_id,
            self.dst_device_id,
            self.msg_id,
            self.msg_version,
            self.payload_size,
            self.spare,
        )

    @classmethod
    def unpack(cls, buf: bytes | bytearray | memoryview) -> MessageHeader:
        """Read the header at the start of ``buf``; OculusFormatError if short or not Oculus."""
        if len(buf) < HEADER_SIZE:
            raise OculusFormatError(
                f"Oculus header: {len(buf)} bytes, need {HEADER_SIZE} (truncated message)"
            )
        oculus_id, src, dst, msg_id, version, payload_size, spare = _HEADER.unpack_from(buf, 0)
        if oculus_id != OCULUS_ID:
            raise OculusFormatError(
                f"Oculus header: magic 0x{oculus_id:04X} is not 0x{OCULUS_ID:04X} (not an Oculus "
                "message)"
            )
        return cls(src, dst, msg_id, version, payload_size, spare)


def _check_length(buf: bytes | bytearray | memoryview, header: MessageHeader, what: str) -> None:
    if len(buf) < header.message_size:
        raise OculusFormatError(
            f"{what}: {len(buf)} bytes, header says {header.message_size} (truncated message)"
        )


@dataclass(frozen=True)
class StatusMessage:
    """OculusStatusMsg (142 bytes), broadcast by UDP about once a second.

    IP addresses are dotted strings and ``mac`` is 6 raw bytes, both in the wire (network)
    byte order; prefer the UDP sender address to reach the sonar. ``temperatures`` are the
    8 internal sensors (°C), ``pressure`` in bar. ``status`` is the raw flag word (bits 0..2
    master state, bit 14 high temperature, bit 15 over-temperature shutdown).
    """

    device_id: int = 0
    device_type: int = 1
    part_number: int = 1042
    status: int = 0
    firmware_version0: int = 0
    firmware_date0: int = 0
    firmware_version1: int = 0
    firmware_date1: int = 0
    firmware_version2: int = 0
    firmware_date2: int = 0
    ip_addr: str = "0.0.0.0"
    ip_mask: str = "0.0.0.0"
    connected_ip: str = "0.0.0.0"
    mac: bytes = bytes(6)
    temperatures: tuple[float, ...] = (0.0,) * 8
    pressure: float = 0.0
    src_device_id: int = 0
    dst_device_id: int = 0
    msg_version: int = 0

    def pack(self) -> bytes:
        if len(self.mac) != 6 or len(self.temperatures) != 8:
            raise ValueError("StatusMessage needs a 6-byte mac and 8 temperatures")
        header = MessageHeader(
            self.src_device_id,
            self.dst_device_id,
            MessageId.STATUS,
            self.msg_version,
            _STATUS_BODY.size,
        )
        body = _STATUS_BODY.pack(
            self.device_id,
            self.device_type,
            self.part_number,
            self.status,
            self.firmware_version0,
            self.firmware_date0,
            self.firmware_version1,
            self.firmware_date1,
            self.firmware_version2,
            self.firmware_date2,
            socket.inet_aton(self.ip_addr),
            socket.inet_aton(self.ip_mask),
            socket.inet_aton(self.connected_ip),
            bytes(self.mac),
            *self.temperatures,
            self.pressure,
        )
        return header.pack() + body

    @classmethod
    def unpack(cls, buf: bytes | bytearray | memoryview) -> StatusMessage:
        header = MessageHeader.unpack(buf)
        if header.msg_id != MessageId.STATUS:
            raise OculusFormatError(f"Status message: msgId 0x{header.msg_id:02X} is not 0x01")
        if header.message_size != STATUS_SIZE:
            raise OculusFormatError(
                f"Status message: {header.message_size} bytes, expected {STATUS_SIZE}"
            )
        _check_length(buf, header, "Status message")
        v = _STATUS_BODY.unpack_from(buf, HEADER_SIZE)
        return cls(
            device_id=v[0],
            device_type=v[1],
            part_number=v[2],
            status=v[3],
            firmware_version0=v[4],
            firmware_date0=v[5],
            firmware_version1=v[6],
            firmware_date1=v[7],
            firmware_version2=v[8],
            firmware_date2=v[9],
            ip_addr=socket.inet_ntoa(v[10]),
            ip_mask=socket.inet_ntoa(v[11]),
            connected_ip=socket.inet_ntoa(v[12]),
            mac=v[13],
            temperatures=tuple(v[14:22]),
            pressure=v[22],
            src_device_id=header.src_device_id,
            dst_device_id=header.dst_device_id,
            msg_version=header.msg_version,
        )


_DEFAULT_FIRE_FLAGS = int(
    FireFlags.RANGE_IN_METRES | FireFlags.SIMPLE_RETURN | FireFlags.GAIN_ASSIST
)


@dataclass(frozen=True)
class SimpleFire:
    """OculusSimpleFireMessage (v1, 53 bytes) or OculusSimpleFireMessage2 (v2, 89 bytes).

    range_m: range demand, metres when ``flags`` has RANGE_IN_METRES, else percent.
    gain_percent: 0..100. gamma: 0..255 (127 ~ gamma 0.5). network_speed: Mbit/s, 0xFF =
    link speed. speed_of_sound: m/s, 0 = computed by the sonar from ``salinity`` (ppt).
    ext_flags / reserved exist in v2 only (ext_flags bits: 0 -6 dB, 1 -12 dB, 2 gain boost,
    3 chirp). ping_rate is an int because sonars echo garbage there; see ``PingRate``.
    """

    version: int = 2
    master_mode: int = MasterMode.HIGH_FREQUENCY
    ping_rate: int = PingRate.HZ10
    network_speed: int = 0xFF
    gamma: int = 127
    flags: int = _DEFAULT_FIRE_FLAGS
    range_m: float = 10.0
    gain_percent: float = 50.0
    speed_of_sound: float = 0.0
    salinity: float = 0.0
    ext_flags: int = 0
    reserved: tuple[int, ...] = field(default=(0,) * 8)
    src_device_id: int = 0
    dst_device_id: int = 0

    @property
    def size(self) -> int:
        return SIMPLE_FIRE_V2_SIZE if self.version == 2 else SIMPLE_FIRE_V1_SIZE

    def pack_body(self) -> bytes:
        """The fire fields without the header (37 bytes v1, 73 bytes v2)."""
        body = FIRE_V1_BODY.pack(
            self.master_mode,
            self.ping_rate,
            self.network_speed,
            self.gamma,
            self.flags,
            self.range_m,
            self.gain_percent,
            self.speed_of_sound,
            self.salinity,
        )
        if self.version == 2:
            if len(self.reserved) != 8:
                raise ValueError("SimpleFire v2 needs 8 reserved words")
            body += FIRE_V2_EXT.pack(self.ext_flags, *self.reserved)
        return body

    def pack(self) -> bytes:
        if self.version not in (1, 2):
            raise ValueError(f"SimpleFire version must be 1 or 2, not {self.version}")
        body = self.pack_body()
        header = MessageHeader(
            self.src_device_id, self.dst_device_id, MessageId.SIMPLE_FIRE, self.version, len(body)
        )
        return header.pack() + body

    @classmethod
    def from_fields(
        cls, buf: bytes | bytearray | memoryview, version: int, header: MessageHeader
    ) -> SimpleFire:
        """Read the fire fields at byte 16 of a fire or ping message (``buf`` long enough)."""
        mode, rate, speed, gamma, flags, range_m, gain, sos, salinity = FIRE_V1_BODY.unpack_from(
            buf, HEADER_SIZE
        )
        ext_flags, reserved = 0, (0,) * 8
        if version == 2:
            ext = FIRE_V2_EXT.unpack_from(buf, SIMPLE_FIRE_V1_SIZE)
            ext_flags, reserved = ext[0], tuple(ext[1:])
        return cls(
            version=version,
            master_mode=mode,
            ping_rate=rate,
            network_speed=speed,
            gamma=gamma,
            flags=flags,
            range_m=range_m,
            gain_percent=gain,
            speed_of_sound=sos,
            salinity=salinity,
            ext_flags=ext_flags,
            reserved=reserved,
            src_device_id=header.src_device_id,
            dst_device_id=header.dst_device_id,
        )

    @classmethod
    def unpack(cls, buf: bytes | bytearray | memoryview) -> SimpleFire:
        """Parse a SimpleFire message; the version is taken from its size (53 or 89)."""
        header = MessageHeader.unpack(buf)
        if header.msg_id != MessageId.SIMPLE_FIRE:
            raise OculusFormatError(f"SimpleFire message: msgId 0x{header.msg_id:02X} is not 0x15")
        sizes = {SIMPLE_FIRE_V1_SIZE: 1, SIMPLE_FIRE_V2_SIZE: 2}
        if header.message_size not in sizes:
            raise OculusFormatError(
                f"SimpleFire message: {header.message_size} bytes, expected 53 (v1) or 89 (v2)"
            )
        _check_length(buf, header, "SimpleFire message")
        return cls.from_fields(buf, sizes[header.message_size], header)


@dataclass(frozen=True)
class RawMessage:
    """A message we pass through undecoded (Dummy, UserConfig, Logs, PingResult, unknown)."""

    header: MessageHeader
    payload: bytes
