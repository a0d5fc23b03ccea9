"""SimplePingResult (msgId 0x23) v1/v2 <-> ``mapping.samples.Ping``.

Layout (PROTOCOLS.md): header + fire message + ping fields = 122 bytes (v1) or 202 bytes
(v2), then the int16 bearing table (1/100 degree, positive to starboard), then, at
``imageOffset``, the range-major image (row 0 nearest). With gain rows each image row is
prefixed by a 4-byte gain word.

Gain word: decoded as a little-endian **uint32** and returned as float64 (lossless). Two
independent readers (ENSTA Bretagne's oculus_driver and oculus-python) read it as uint32,
liboculus reads it as float32; the real captures we have carry no gain rows, so this could
not be settled on data. Should it prove to be float32, ``gains.astype(np.uint32).view(
np.float32)`` recovers it exactly.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from drivers.oculus.protocol import (
    HEADER_SIZE,
    SIMPLE_FIRE_V1_SIZE,
    SIMPLE_FIRE_V2_SIZE,
    DataSize,
    FireFlags,
    MessageHeader,
    MessageId,
    OculusFormatError,
    RawMessage,
    SimpleFire,
    StatusMessage,
    _as_bytes,
    _check_length,
    message_name,
)
from mapping.samples import Ping

_TAIL_V1 = struct.Struct("<IIddddIBdHHIII")  # at byte 53
_TAIL_V2 = struct.Struct("<IIddddddddBdHHIIIIIII")  # at byte 89
PING_V1_STRUCT_SIZE = SIMPLE_FIRE_V1_SIZE + _TAIL_V1.size
PING_V2_STRUCT_SIZE = SIMPLE_FIRE_V2_SIZE + _TAIL_V2.size
GAIN_WORD_SIZE = 4
# The M1200d puts the image at byte 2048 (after the bearing table and some padding); the
# builder does the same so that built messages look like the real ones.
IMAGE_ALIGN = 2048
_CENTIDEG_TO_RAD = math.pi / 18000.0
_DEFAULT_FLAGS = int(FireFlags.RANGE_IN_METRES | FireFlags.SIMPLE_RETURN | FireFlags.GAIN_ASSIST)

assert PING_V1_STRUCT_SIZE == 122
assert PING_V2_STRUCT_SIZE == 202


@dataclass(frozen=True)
class PingInfo:
    """The fixed part of a SimplePingResult, checked for size consistency (no image).

    version: the layout (1 or 2), decided by sizes and offsets, not by msgVersion.
    heading/pitch/roll_deg: v2 only (degrees, as sent), else None.
    ping_start_time: v1 uint32 (sonar clock, unit undocumented); v2 seconds since power-up.
    """

    header: MessageHeader
    version: int
    fire: SimpleFire
    ping_id: int
    status: int
    frequency_hz: float
    temperature_c: float
    pressure_bar: float
    heading_deg: float | None
    pitch_deg: float | None
    roll_deg: float | None
    speed_of_sound_mps: float
    ping_start_time: float
    data_size: int
    range_resolution_m: float
    n_ranges: int
    n_beams: int
    image_offset: int
    image_size: int
    message_size: int

    @property
    def struct_size(self) -> int:
        return PING_V2_STRUCT_SIZE if self.version == 2 else PING_V1_STRUCT_SIZE

    @property
    def sample_size(self) -> int:
        """Bytes per sample (1..4)."""
        return self.data_size + 1

    @property
    def has_gain_rows(self) -> bool:
        # Inferred from sizes: the SEND_GAIN flag is unreliable in v2 pings.
        return self.image_size > self.n_beams * self.n_ranges * self.sample_size


def _read_layout(
    buf: bytes | bytearray | memoryview, header: MessageHeader, version: int
) -> PingInfo | str:
    """The PingInfo if ``buf`` is consistent as a v1/v2 layout, else why not (one line)."""
    struct_size = PING_V2_STRUCT_SIZE if version == 2 else PING_V1_STRUCT_SIZE
    total = header.message_size
    if len(buf) < struct_size or total < struct_size:
        return f"shorter than the {struct_size}-byte v{version} struct"
    fire = SimpleFire.from_fields(buf, version, header)
    heading: float | None = None
    pitch: float | None = None
    roll: float | None = None
    if version == 2:
        (ping_id, status, freq, temp, press, heading, pitch, roll, sos, start, data_size,
         res, n_ranges, n_beams, _s0, _s1, _s2, _s3, offset, size, msg_size) = (
            _TAIL_V2.unpack_from(buf, SIMPLE_FIRE_V2_SIZE))  # fmt: skip
    else:
        (ping_id, status, freq, temp, press, sos, start, data_size, res, n_ranges, n_beams,
         offset, size, msg_size) = _TAIL_V1.unpack_from(buf, SIMPLE_FIRE_V1_SIZE)  # fmt: skip
    if n_beams == 0 or n_ranges == 0:
        return f"empty image ({n_ranges} ranges x {n_beams} beams)"
    if data_size > DataSize.BITS32:
        return f"dataSize {data_size} is not 0..3"
    if offset + size != total:
        return f"imageOffset {offset} + imageSize {size} != payloadSize + 16 ({total})"
    if msg_size not in (0, total):
        return f"messageSize {msg_size} != payloadSize + 16 ({total})"
    if offset < struct_size + 2 * n_beams:
        return f"imageOffset {offset} overlaps the {n_beams}-beam bearing table"
    plain = n_beams * n_ranges * (data_size + 1)
    if size not in (plain, plain + GAIN_WORD_SIZE * n_ranges):
        return (
            f"imageSize {size} is neither nBeams*nRanges*sampleSize ({plain}) nor that plus "
            f"4-byte gain rows ({plain + GAIN_WORD_SIZE * n_ranges})"
        )
    return PingInfo(
        header=header,
        version=version,
        fire=fire,
        ping_id=ping_id,
        status=status,
        frequency_hz=freq,
        temperature_c=temp,
        pressure_bar=press,
        heading_deg=heading,
        pitch_deg=pitch,
        roll_deg=roll,
        speed_of_sound_mps=sos,
        ping_start_time=start,
        data_size=data_size,
        range_resolution_m=res,
        n_ranges=n_ranges,
        n_beams=n_beams,
        image_offset=offset,
        image_size=size,
        message_size=total,
    )


def read_ping_info(message: bytes | bytearray | memoryview) -> PingInfo:
    """Check and decode the fixed part of a SimplePingResult (needs only its first 202 bytes).

    v1 pings are sent with msgVersion 0 or 1, so the layout is the one whose sizes and
    offsets agree with payloadSize (msgVersion only says which to try first).
    Raises OculusFormatError naming what is inconsistent.
    """
    header = MessageHeader.unpack(message)
    if header.msg_id != MessageId.SIMPLE_PING_RESULT:
        raise OculusFormatError(
            f"SimplePingResult: msgId 0x{header.msg_id:02X} is not 0x23 (not a ping)"
        )
    order = (2, 1) if header.msg_version == 2 else (1, 2)
    first = _read_layout(message, header, order[0])
    if isinstance(first, PingInfo):
        return first
    second = _read_layout(message, header, order[1])
    if isinstance(second, PingInfo):
        return second
    raise OculusFormatError(f"SimplePingResult v{order[0]}: {first}")


def parse_simple_ping(message: bytes | bytearray | memoryview, time: float) -> Ping:
    """Decode a whole SimplePingResult message into a Ping stamped ``time`` (UNIX s).

    Bearings become radians (positive to starboard), the image (n_ranges, n_beams) uint8
    or uint16 with row 0 nearest, gains a float64 (n_ranges,) array when the rows carry
    them. Fields without a Ping field go to ``Ping.extra``. 24/32-bit samples and any
    inconsistency raise OculusFormatError.
    """
    info = read_ping_info(message)
    if len(message) < info.message_size:
        raise OculusFormatError(
            f"SimplePingResult ping {info.ping_id}: {len(message)} of {info.message_size} "
            "bytes (truncated message)"
        )
    if info.data_size > DataSize.BITS16:
        raise OculusFormatError(
            f"SimplePingResult ping {info.ping_id}: {8 * info.sample_size}-bit samples unsupported"
        )
    n_ranges, n_beams, sample = info.n_ranges, info.n_beams, info.sample_size
    bearings = np.frombuffer(message, "<i2", n_beams, info.struct_size).astype(np.float64)
    bearings *= _CENTIDEG_TO_RAD
    raw = np.frombuffer(message, np.uint8, info.image_size, info.image_offset)
    gains: npt.NDArray[np.float64] | None = None
    if info.has_gain_rows:
        rows = raw.reshape(n_ranges, GAIN_WORD_SIZE + n_beams * sample)
        gain_words = np.ascontiguousarray(rows[:, :GAIN_WORD_SIZE]).view("<u4")
        gains = gain_words.reshape(n_ranges).astype(np.float64)
        pixels = rows[:, GAIN_WORD_SIZE:]
    else:
        pixels = raw.reshape(n_ranges, n_beams * sample)
    # Both branches copy, so the Ping owns its pixels (the message buffer may be reused).
    image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]
    if sample == 1:
        image = pixels.reshape(n_ranges, n_beams).copy()
    else:
        image = pixels.view("<u2").reshape(n_ranges, n_beams).astype(np.uint16)
    fire = info.fire
    extra: dict[str, object] = {
        "layout_version": info.version,
        "msg_version": info.header.msg_version,
        "src_device_id": info.header.src_device_id,
        "dst_device_id": info.header.dst_device_id,
        "status": info.status,
        "ping_start_time": info.ping_start_time,
        "temperature_c": info.temperature_c,
        "pressure_bar": info.pressure_bar,
        "flags": fire.flags,
        "ping_rate": fire.ping_rate,
        "network_speed": fire.network_speed,
        "data_size": info.data_size,
        "range_demand": fire.range_m,
        "speed_of_sound_demand_mps": fire.speed_of_sound,
        "salinity_ppt": fire.salinity,
    }
    if info.version == 2:
        extra["ext_flags"] = fire.ext_flags
    return Ping(
        time=time,
        ping_id=info.ping_id,
        master_mode=fire.master_mode,
        frequency_hz=info.frequency_hz,
        range_resolution_m=info.range_resolution_m,
        bearings_rad=bearings,
        image=image,
        gains=gains,
        speed_of_sound_mps=info.speed_of_sound_mps,
        gain_percent=fire.gain_percent,
        gamma=fire.gamma,
        heading_rad=_heading_rad(info.heading_deg),
        pitch_rad=_angle_rad(info.pitch_deg),
        roll_rad=_angle_rad(info.roll_deg),
        extra=extra,
    )


def _angle_rad(deg: float | None) -> float | None:
    return math.radians(deg) if deg is not None and math.isfinite(deg) else None


def _heading_rad(deg: float | None) -> float | None:
    rad = _angle_rad(deg)
    return None if rad is None else rad % (2.0 * math.pi)


def _extra_number(ping: Ping, key: str, default: float) -> float:
    value = ping.extra.get(key, default)
    return float(value) if isinstance(value, int | float) else default


def _gain_words(ping: Ping, send_gain: bool) -> npt.NDArray[np.uint32] | None:
    if not send_gain:
        return None
    if ping.gains is None:
        # Asked for gain rows without gains: unity gain, as a sonar applying none would send.
        return np.ones(ping.n_ranges, np.uint32)
    gains = np.asarray(ping.gains, np.float64)
    if gains.shape != (ping.n_ranges,):
        raise ValueError(f"gains shape {gains.shape} != ({ping.n_ranges},)")
    words = np.rint(gains)
    if not (np.all(words == gains) and np.all(words >= 0) and np.all(words < 2.0**32)):
        raise ValueError("gains must be integers in 0..2**32-1 (they travel as uint32)")
    return words.astype(np.uint32)


def build_simple_ping(
    ping: Ping,
    *,
    version: int = 2,
    send_gain: bool | None = None,
    ping_rate: int = 0,
    gamma: int | None = None,
    flags: int | None = None,
    src_device_id: int = 0x1ED4,
    dst_device_id: int = 0,
    msg_version: int | None = None,
) -> bytes:
    """Encode a Ping as the SimplePingResult a sonar would send (v1: 122-byte struct, v2: 202).

    Gain rows are written iff ``send_gain`` (default: the ping has gains). ``flags``
    (default: ``ping.extra["flags"]`` or range-in-metres | simple-return | gain-assist) gets
    its DATA_16BIT, SEND_GAIN and BEAMS_512 bits set from the data. ``msg_version`` defaults
    to ``version``; pass 0 to mimic real v1 pings. Fields without a Ping field come from
    ``ping.extra`` when present. Bearings are quantised to 1/100 degree.
    """
    if version not in (1, 2):
        raise ValueError(f"SimplePingResult version must be 1 or 2, not {version}")
    image = ping.image
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"image must be 2-D uint8 or uint16, not {image.dtype} {image.shape}")
    n_ranges, n_beams = image.shape
    centideg = np.rint(np.degrees(np.asarray(ping.bearings_rad, np.float64)) * 100.0)
    if centideg.shape != (n_beams,) or np.any(np.abs(centideg) > 32767):
        raise ValueError(f"bearings must be ({n_beams},) within ±327 degrees")
    sample = image.dtype.itemsize
    gain_words = _gain_words(ping, ping.gains is not None if send_gain is None else send_gain)

    pixels = np.ascontiguousarray(image, image.dtype.newbyteorder("<")).view(np.uint8)
    pixels = pixels.reshape(n_ranges, n_beams * sample)
    if gain_words is not None:
        rows = np.empty((n_ranges, GAIN_WORD_SIZE + n_beams * sample), np.uint8)
        rows[:, :GAIN_WORD_SIZE] = gain_words.astype("<u4").view(np.uint8).reshape(n_ranges, 4)
        rows[:, GAIN_WORD_SIZE:] = pixels
        pixels = rows
    image_bytes = pixels.tobytes()

    struct_size = PING_V2_STRUCT_SIZE if version == 2 else PING_V1_STRUCT_SIZE
    image_offset = -(-(struct_size + 2 * n_beams) // IMAGE_ALIGN) * IMAGE_ALIGN
    total = image_offset + len(image_bytes)

    base_flags = flags if flags is not None else int(_extra_number(ping, "flags", _DEFAULT_FLAGS))
    consistent = FireFlags.DATA_16BIT | FireFlags.SEND_GAIN | FireFlags.BEAMS_512
    fire_flags = base_flags & ~consistent & 0xFF
    fire_flags |= FireFlags.DATA_16BIT if sample == 2 else 0
    fire_flags |= FireFlags.SEND_GAIN if gain_words is not None else 0
    fire_flags |= FireFlags.BEAMS_512 if n_beams > 256 else 0

    fire = SimpleFire(
        version=version,
        master_mode=ping.master_mode,
        ping_rate=ping_rate,
        network_speed=int(_extra_number(ping, "network_speed", 0xFF)),
        gamma=ping.gamma if gamma is None else gamma,
        flags=int(fire_flags),
        range_m=_extra_number(ping, "range_demand", ping.max_range_m),
        gain_percent=ping.gain_percent,
        speed_of_sound=_extra_number(ping, "speed_of_sound_demand_mps", 0.0),
        salinity=_extra_number(ping, "salinity_ppt", 0.0),
        ext_flags=int(_extra_number(ping, "ext_flags", 0)),
    )
    header = MessageHeader(
        src_device_id,
        dst_device_id,
        MessageId.SIMPLE_PING_RESULT,
        version if msg_version is None else msg_version,
        total - HEADER_SIZE,
    )
    common = (
        ping.ping_id,
        int(_extra_number(ping, "status", 0)),
        ping.frequency_hz,
        _extra_number(ping, "temperature_c", 0.0),
        _extra_number(ping, "pressure_bar", 0.0),
    )
    start = _extra_number(ping, "ping_start_time", 0.0)
    layout = (sample - 1, ping.range_resolution_m, n_ranges, n_beams)
    sizes = (image_offset, len(image_bytes), total)
    if version == 2:
        # NaN stands for "no attitude sensor" so that None survives a round trip.
        attitude = tuple(
            math.nan if angle is None else math.degrees(angle)
            for angle in (ping.heading_rad, ping.pitch_rad, ping.roll_rad)
        )
        tail = _TAIL_V2.pack(
            *common, *attitude, ping.speed_of_sound_mps, start, *layout, 0, 0, 0, 0, *sizes
        )
    else:
        v1_start = int(start) & 0xFFFFFFFF
        tail = _TAIL_V1.pack(*common, ping.speed_of_sound_mps, v1_start, *layout, *sizes)

    message = bytearray(total)
    fixed = header.pack() + fire.pack_body() + tail
    message[: len(fixed)] = fixed
    bearing_bytes = centideg.astype("<i2").tobytes()
    message[struct_size : struct_size + len(bearing_bytes)] = bearing_bytes
    message[image_offset:] = image_bytes
    return bytes(message)


def parse_message(
    message: bytes | bytearray | memoryview, time: float = 0.0
) -> StatusMessage | SimpleFire | Ping | RawMessage:
    """Decode one whole message (header + payload) by its msgId.

    SimplePingResult becomes a ``mapping.samples.Ping`` stamped with ``time`` (UNIX s);
    messages whose layout we do not decode come back as ``RawMessage``.
    """
    header = MessageHeader.unpack(message)
    if header.msg_id == MessageId.STATUS:
        return StatusMessage.unpack(message)
    if header.msg_id == MessageId.SIMPLE_FIRE:
        return SimpleFire.unpack(message)
    if header.msg_id == MessageId.SIMPLE_PING_RESULT:
        return parse_simple_ping(message, time)
    _check_length(message, header, f"{message_name(header.msg_id)} message")
    return RawMessage(header, _as_bytes(message[HEADER_SIZE : header.message_size]))
