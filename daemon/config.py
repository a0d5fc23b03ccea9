"""Site configuration: one TOML file configures a vehicle and site, for the daemon and replay.

Every key has a typed, documented default (the dataclass fields below). A file may set
any subset; an unknown table or key, or a value of the wrong type, is a ``SeamapError``
that names it. The keys of ``docs/CONTRACT.md`` are fixed; more are added here.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import tomllib
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError
from drivers.mavlink.navlog import HEADING_SOURCES, IMU_SOURCES
from drivers.zenoh_io import ZenohConfig, endpoint_problem, id_problem


@dataclass(frozen=True)
class DaemonConfig:
    vehicle: str = "boat1"
    """zenoh vehicle id (no '/')."""
    state_dir: str = "/var/lib/seamap"
    """Surveys are kept under state_dir/surveys/{survey}/."""
    survey_autostart: bool = False
    """true: open a survey as soon as the daemon runs."""
    log_level: str = "info"
    """Daemon log level on stderr: "debug", "info" (events and a health line at
    health_interval_s), "warning" or "error"."""
    health_interval_s: float = 30.0
    """How often (seconds) the daemon logs its health line."""
    min_free_mb: float = 200.0
    """Recording stops cleanly (and says so) when the state_dir filesystem has less free
    space than this (MiB)."""
    max_backlog_frames: int = 20
    """Sonar frames allowed to wait for the mapping engine; newer frames beyond this are
    skipped live (counted; they stay recorded and the survey-end pass maps them)."""
    tile_memory_mb: float = 256.0
    """Live mosaic tiles the boat has left stay in memory, the least recently used going
    to disk first, while all tiles take no more than this (MiB; a tile is 5.3 MB)."""
    final_pass: bool = True
    """Run the survey-end pass (the whole survey re-solved, the result folder written)
    when a survey ends and on SIGTERM."""
    workers: int = -1
    """Worker processes the live engine's stages run in beside the daemon's own (-1: the
    cores less one; 0: none, every stage in the daemon's process). The map is the same
    for any number."""


@dataclass(frozen=True)
class SonarConfig:
    mount_x_m: float = -0.45
    """Body-frame offset of the sonar from the GPS antenna, forward (m)."""
    mount_y_m: float = 0.0
    """Starboard (m)."""
    mount_z_m: float = 0.3
    """Down (m)."""
    mount_yaw_deg: float = 0.0
    """Sonar boresight relative to the bow, clockwise (degrees)."""
    tilt_deg: float = 15.0
    """Downward tilt of the boresight (degrees)."""
    altitude_m: float = 1.0
    """Sonar height above the seabed when known, for the ground-range correction (m)."""
    address: str = "auto"
    """"auto": take the first sonar heard on the status port; else an IPv4 address."""
    tcp_port: int = 52100
    status_port: int = 52102
    frequency: str = "low"
    """Operating frequency the sonar is fired at: "low" (M1200d: 1.2 MHz, 130 degrees,
    up to 40 m) or "high" (2.1 MHz, 60 degrees, up to 10 m)."""
    range_m: float = 5.0
    """Range the sonar is fired at (metres)."""
    gain_percent: float = 50.0
    """Receiver gain, 0..100."""
    gamma: int = 127
    """Gamma correction of the sonar's 8-bit images, 0..255 (127 is about 0.5)."""
    ping_rate_hz: int = 10
    """Maximum ping rate asked for: 2, 5, 10, 15 or 40."""
    data_bits: int = 8
    """Sample size asked for: 8 or 16 bits."""
    send_gain: bool = True
    """Ask for the per-row gain words with each ping."""
    standby_outside_surveys: bool = True
    """Put the sonar in standby while no survey is open (it stops pinging: an M1200d
    pinging in air, on the trailer, overheats) and fire it again when one opens; its
    status broadcast is still watched."""
    seabed_from_pings: bool = True
    """Without an echosounder's soundings (none in the log, or ``[echosounder] use =
    false``), take each ping's altitude and the bottom's slope from where the sonar's
    vertical beam first lights the seabed (``mapping.sonar_depth``); false: ``altitude_m``
    for every ping, on a level bed."""


@dataclass(frozen=True)
class EchosounderConfig:
    """A downward echosounder on the autopilot (a Ping2-class altimeter reported as
    MAVLink DISTANCE_SENSOR looking down, or ArduPilot's RANGEFINDER): its soundings give
    the sonar's altitude and the bottom's slope ping by ping (``mapping.bottom``), in
    place of ``[sonar] altitude_m``, which stays the fallback."""

    use: bool = True
    """Take the altitude from the echosounder's soundings when the navigation has them."""
    mount_x_m: float = 0.0
    """Body-frame offset of the transducer from the GPS antenna, forward (m)."""
    mount_y_m: float = 0.0
    """Starboard (m)."""
    mount_z_m: float = 0.3
    """Down (m): the transducer's face below the antenna."""


@dataclass(frozen=True)
class MavlinkConfig:
    url: str = "udpin:0.0.0.0:14550"
    """pymavlink connection string, or a serial device such as "/dev/ttyACM0"."""
    baud: int = 115200
    heading_source: str = "auto"
    """Which heading to use: "attitude" (ATTITUDE.yaw), "global_position"
    (GLOBAL_POSITION_INT.hdg), "vfr_hud" (VFR_HUD.heading, whole degrees), "compass"
    (tilt-compensated magnetometer plus declination_deg), or "auto": the first of
    attitude, global_position, vfr_hud, compass that the log or link carries."""
    imu_source: str = "auto"
    """Which IMU message: "highres", "scaled", "scaled2", "scaled3", "raw", or "auto":
    the first of highres, scaled, raw, scaled2, scaled3 present."""
    declination_deg: float = 0.0
    """Magnetic declination east of true north (degrees), for heading_source = "compass"."""


@dataclass(frozen=True)
class MappingConfig:
    mosaic_res_m: float = 0.02
    """Mosaic pixel size (metres); tiles are 256 pixels square."""
    lambda_local: float = 1e4
    """The paper's lambda. Single- and two-stage weigh every measurement by its own
    covariance; lambda / 1e4 scales the registrations' information (1e4: as measured),
    which is what the paper's lambda sweep varies."""
    alpha: float = 1.0 / 225.0
    """The paper's alpha (squared degrees against squared metres): kept for the paper's
    objective (``mapping.posegraph``); the fusion weighs angles by their own sigmas."""
    tau_p_m: float = 0.15
    """Largest disagreement between a registration and the EKF's relative motion (m)."""
    tau_a_deg: float = 3.0
    """Largest disagreement in relative yaw (degrees)."""
    loop_closures: bool = True
    """Register overlapping frames of different lanes and use them as constraints."""
    gnss_white_sigma_m: float = 0.6
    """Single-stage: white part of the GNSS error, per axis (m; u-blox M8N: 0.5-0.8)."""
    gnss_bias_sigma_m: float = 1.2
    """Single-stage: the GNSS error's slowly wandering part, per axis (m; M8N: 1-1.5)."""
    gnss_bias_tau_s: float = 45.0
    """Single-stage: correlation time of that wander (s; M8N: tens of seconds)."""
    gnss_lag_s: float = 0.15
    """How long before its stamp a fix saw the antenna (s; refined by the solve)."""
    sonar_latency_s: float = 0.05
    """Time from a ping's acquisition to its receive stamp (s)."""
    blending: str = "robust"
    """How overlapping frames make a mosaic pixel: "robust" (the paper's variance-based
    blending, Eq. 8-11), or one of the baselines it is compared with (Table V):
    "average" (plain mean), "hurtos" (Hurtós et al. 2013: every frame weighted by the
    pixel's place in its fan, most at the fan's centre) or "su" (Su et al. 2024: the
    variance score over fixed windows of frames, the kept candidates' plain mean)."""


@dataclass(frozen=True)
class LiveConfig:
    """The live map's economies (``mapping.stream_params``): the live map is for watching
    the survey and deciding where to go; the survey-end pass is the deliverable and keeps
    the full settings whatever these say. The defaults were chosen by runs of the
    streaming matrix (README, "Speed")."""

    registration_res_m: float = 0.03
    """Pixel size the live registrations work on (m): coarser is faster (the FFTs' work
    goes with the pixel count), finer measures each step better. 4 cm cut the live
    registration by about a third but made the live map's lanes worse where frames are
    far apart (quadrats at 2 Hz, seed 6: 8.7 -> 15.0 cm; seven surveys of the matrix,
    median 6.6 -> 8.7 cm against 3 cm's 5.9, with the gyro's turn)."""
    yaw_from_gyro: bool = True
    """Take each live registration's turn from the gyro where the filter's gyro joins the
    two frames, and search no rotation; false: search it as the survey-end pass does."""
    candidates: int = 8
    """Blending candidates each live tile keeps per pixel (the survey-end pass keeps 16)."""
    redraws_per_frame: float = 0.5
    """Frames a live re-solve moved that are drawn again per new frame, on average: lower
    costs less and leaves the drawn map further behind the re-solved poses."""


@dataclass(frozen=True)
class CoverageConfig:
    """How well each seabed cell was seen (``mapping.coverage``; the result folder's
    coverage.tif and, with the survey's area, gaps.geojson)."""

    cell_m: float = 0.25
    """Coverage cell side (metres), cells on the UTM grid (edges at multiples of it). A
    quarter metre is a tenth of the fan's depth on the seabed and finer than the boat
    keeps a lane (decimetres), yet a hectare is only 160,000 cells."""
    min_passes: int = 1
    """A cell meets the quality bar when this many separate passes saw it (2: every cell
    from two lanes, as overlapping lanes are planned to)."""
    min_range_m: float = 0.0
    """Ground range from the sonar (metres) below which a frame does not count a cell;
    0: the mapper's lit band decides (at 1 m altitude, 15 degrees tilt and a 20 degree
    vertical beam it starts 2.25 m out on the boresight). Narrows the band, never widens
    it: the mosaic holds nothing outside it."""
    max_range_m: float = 0.0
    """Ground range beyond which a frame does not count a cell (0: the lit band's end,
    4.9 m at 5 m range and 1 m altitude)."""
    min_grazing_deg: float = 10.0
    """Smallest grazing angle, atan(altitude / ground range), at which a frame counts a
    cell (degrees; 0: any). A Lambertian seabed's echo goes as sin^2 of the grazing angle
    (10 degrees: 15 dB below normal incidence; 8: 17 dB; 5: 21 dB) and relief of height
    z throws a shadow z / tan(grazing) long (a 10 cm quadrat bar or oyster clump: 0.57 m
    at 10 degrees, 1.1 m at 5). At the nominal 1 m altitude and 5 m range the lit band
    spans 24 degrees at its near edge to 11.5 at its far one, so 10 degrees keeps all of
    it and cuts only where the image fades into shadow: beyond 2.8 m with 0.5 m of water
    under the sonar, beyond 5.7 m at 1 m altitude with the range set longer."""
    pass_gap_s: float = 8.0
    """A frame begins a new pass over a cell when the last frame that saw it is more than
    this earlier (seconds), as the loop closures tell passes apart
    (``mapping.closures.ClosureParams.pass_gap_s``): a lane's pings see a cell for a few
    seconds (2.7 m of fan depth at 0.5 m/s), the next lane comes back a minute later."""
    min_gap_m2: float = 1.0
    """The smallest uncovered part of the area reported as a gap (m²): 16 cells, a patch
    a lane's fan sweeps over in two seconds; smaller ones still count as uncovered.
    ``seamap survey replan`` plans lanes over the gaps of at least this (``--min-gap``)."""


@dataclass(frozen=True)
class MissionConfig:
    """What the daemon knows of the survey's mission: its area, for the live covered
    fraction and the gaps at the end, and whether to plan the gaps' lanes then."""

    area: str = ""
    """The survey area (GeoJSON polygon, holes kept out, or a lat,lon list; as ``seamap
    survey plan --area``) of every survey the daemon opens without an area of its own (a
    lease surveyed again and again); empty: none. A relative path is taken from the
    config file's folder. A survey started by ``seamap survey start`` takes its plan's
    area instead, ``seamap ctl start --area`` the one given."""
    replan_at_end: bool = False
    """When a survey with an area ends, plan lanes over its gaps (``seamap survey
    replan``) into the survey folder as ``replan.plan`` (and .waypoints, .geojson, .png),
    from where the boat ended; starting it stays a person's decision."""


@dataclass(frozen=True)
class SiteConfig:
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    sonar: SonarConfig = field(default_factory=SonarConfig)
    echosounder: EchosounderConfig = field(default_factory=EchosounderConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    coverage: CoverageConfig = field(default_factory=CoverageConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)


_CHOICES: dict[tuple[str, str], tuple[Any, ...]] = {
    ("mavlink", "heading_source"): HEADING_SOURCES,
    ("mavlink", "imu_source"): IMU_SOURCES,
    ("zenoh", "mode"): ("peer", "client", "router"),
    ("mapping", "blending"): ("robust", "average", "hurtos", "su"),
    ("daemon", "log_level"): ("debug", "info", "warning", "error"),
    ("sonar", "frequency"): ("low", "high"),
    ("sonar", "ping_rate_hz"): (2, 5, 10, 15, 40),
    ("sonar", "data_bits"): (8, 16),
}

_RANGES: dict[tuple[str, str], tuple[float, float]] = {
    # Seconds between health lines: a tenth of a second to a day.
    ("daemon", "health_interval_s"): (0.1, 86400.0),
    ("daemon", "min_free_mb"): (0.0, 1e9),
    ("daemon", "max_backlog_frames"): (1, 10000),
    ("daemon", "tile_memory_mb"): (0.0, 1e6),
    ("daemon", "workers"): (-1, 256),
    # Where the sonar sits on a small boat: within 10 m of the antenna.
    ("sonar", "mount_x_m"): (-10.0, 10.0),
    ("sonar", "mount_y_m"): (-10.0, 10.0),
    ("sonar", "mount_z_m"): (-10.0, 10.0),
    ("sonar", "mount_yaw_deg"): (-360.0, 360.0),
    # A downward tilt: level (0) to straight down (90).
    ("sonar", "tilt_deg"): (0.0, 90.0),
    # Above the seabed: 5 cm (a sonar on a frame) to 100 m (deeper than the sonar sees).
    ("sonar", "altitude_m"): (0.05, 100.0),
    ("sonar", "range_m"): (0.1, 120.0),
    ("sonar", "gain_percent"): (0.0, 100.0),
    ("sonar", "gamma"): (0, 255),
    ("sonar", "tcp_port"): (1, 65535),
    ("sonar", "status_port"): (1, 65535),
    ("echosounder", "mount_x_m"): (-10.0, 10.0),
    ("echosounder", "mount_y_m"): (-10.0, 10.0),
    ("echosounder", "mount_z_m"): (-10.0, 10.0),
    ("mavlink", "baud"): (1200, 12_000_000),
    ("mavlink", "declination_deg"): (-180.0, 180.0),
    # Mosaic pixels from 5 mm (the sonar's finest range cell is 2.4 mm) to 1 m.
    ("mapping", "mosaic_res_m"): (0.005, 1.0),
    ("mapping", "lambda_local"): (1e-6, 1e12),
    ("mapping", "alpha"): (1e-9, 1e9),
    ("mapping", "tau_p_m"): (0.001, 100.0),
    ("mapping", "tau_a_deg"): (0.01, 180.0),
    ("mapping", "gnss_white_sigma_m"): (0.01, 100.0),
    ("mapping", "gnss_bias_sigma_m"): (0.01, 100.0),
    ("mapping", "gnss_bias_tau_s"): (1.0, 1e5),
    ("mapping", "gnss_lag_s"): (0.0, 2.0),
    ("mapping", "sonar_latency_s"): (0.0, 2.0),
    # Live registrations from a mosaic pixel's 5 mm to 20 cm (a fan 5 m deep is 25 px).
    ("live", "registration_res_m"): (0.005, 0.2),
    # At least one candidate; 64 is more than any blend keeps.
    ("live", "candidates"): (1, 64),
    ("live", "redraws_per_frame"): (0.0, 100.0),
    # Coverage cells from 5 cm (a few mosaic pixels; finer says nothing the registration's
    # centimetres allow) to 5 m (a fan's width: coarser cells cannot tell a lane's edge).
    ("coverage", "cell_m"): (0.05, 5.0),
    ("coverage", "min_passes"): (1, 1000),
    # Ground ranges within the sonar's longest range (0: the lit band's own).
    ("coverage", "min_range_m"): (0.0, 120.0),
    ("coverage", "max_range_m"): (0.0, 120.0),
    ("coverage", "min_grazing_deg"): (0.0, 90.0),
    # Twice the slowest ping interval (2 Hz) to a day.
    ("coverage", "pass_gap_s"): (1.0, 86400.0),
    ("coverage", "min_gap_m2"): (0.0, 1e8),
}


def _is_not(what: str, problem: str | None) -> str | None:
    """A shared check's answer (``drivers.zenoh_io``: the ids and endpoints the shore,
    the router and the security sets check the same way) as this file's reasons read."""
    return None if problem is None else f"is not {what} ({problem})"


def _not_empty(value: str) -> str | None:
    return "must not be empty" if not value.strip() else None


def _sonar_address(value: str) -> str | None:
    if value == "auto":
        return None
    try:
        ipaddress.IPv4Address(value)
    except ValueError:
        return 'must be "auto" or an IPv4 address such as "192.168.2.4"'
    return None


_TEXT: dict[tuple[str, str], Callable[[str], str | None]] = {
    ("daemon", "vehicle"): lambda value: _is_not("a vehicle id", id_problem(value)),
    ("daemon", "state_dir"): _not_empty,
    ("sonar", "address"): _sonar_address,
    ("mavlink", "url"): _not_empty,
    ("zenoh", "listen"): lambda value: _is_not("a zenoh endpoint", endpoint_problem(value)),
    ("zenoh", "connect"): lambda value: _is_not("a zenoh endpoint", endpoint_problem(value)),
}
"""Checks of text values (of each item, for lists): None, or why the value is wrong.
``("zenoh", "config_file")`` is free: empty means none, and the file is read when used."""

FREE_KEYS = frozenset({("zenoh", "config_file"), ("mission", "area")})
"""Keys whose type is their only check (true/false keys are also only typed); their files
are read when used (the daemon reads ``[mission] area`` at start)."""


def _coerce(where: str, value: Any, annotation: Any) -> Any:
    """Check ``value`` against a field's annotation; ints are accepted for floats."""
    origin = typing.get_origin(annotation)
    if origin is list:
        (item_type,) = typing.get_args(annotation)
        if not isinstance(value, list):
            raise SeamapError(f"config: {where} must be a list, got {type(value).__name__}")
        return [_coerce(f"{where}[{i}]", v, item_type) for i, v in enumerate(value)]
    if annotation is bool:
        if not isinstance(value, bool):
            raise SeamapError(f"config: {where} must be true or false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SeamapError(f"config: {where} must be an integer, got {value!r}")
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise SeamapError(f"config: {where} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise SeamapError(f"config: {where} must be finite, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise SeamapError(f"config: {where} must be a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config annotation {annotation!r}")  # a bug, not input


def _shown(name: str) -> str:
    """A name from the file, quoted, on one line whatever it holds."""
    return repr(str(name))


def _section(name: str, cls: type[Any], table: Any) -> Any:
    if not isinstance(table, dict):
        raise SeamapError(f"config: [{name}] must be a table")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    values: dict[str, Any] = {}
    for key, value in table.items():
        if key not in known:
            raise SeamapError(
                f"config: unknown key {_shown(key)} in [{name}] (known: {', '.join(sorted(known))})"
            )
        values[key] = _coerce(f"[{name}] {key}", value, hints[key])
        allowed = _CHOICES.get((name, key))
        if allowed is not None and values[key] not in allowed:
            choices = ", ".join(str(a) for a in allowed)
            raise SeamapError(f"config: [{name}] {key} = {value!r} is not one of {choices}")
        bounds = _RANGES.get((name, key))
        if bounds is not None and not bounds[0] <= values[key] <= bounds[1]:
            raise SeamapError(
                f"config: [{name}] {key} = {value!r} is outside {bounds[0]:g}..{bounds[1]:g}"
            )
        check = _TEXT.get((name, key))
        if check is not None:
            items = values[key] if isinstance(values[key], list) else [values[key]]
            for item in items:
                reason = check(item)
                if reason is not None:
                    raise SeamapError(f"config: [{name}] {key} = {item!r} {reason}")
    return cls(**values)


def config_from_dict(data: dict[str, Any]) -> SiteConfig:
    """Build a SiteConfig from parsed TOML; unknown tables or keys raise SeamapError."""
    hints = typing.get_type_hints(SiteConfig)
    sections: dict[str, Any] = {}
    for name, table in data.items():
        if name not in hints:
            known = ", ".join(f"[{n}]" for n in hints)
            raise SeamapError(f"config: unknown table [{_shown(name)[1:-1]}] (known: {known})")
        sections[name] = _section(name, hints[name], table)
    config = SiteConfig(**sections)
    _check_together(config)
    return config


def _check_together(config: SiteConfig) -> None:
    """Keys whose values must agree with each other."""
    cover = config.coverage
    if 0 < cover.max_range_m <= cover.min_range_m:
        raise SeamapError(
            f"config: [coverage] min_range_m = {cover.min_range_m:g} is not below "
            f"max_range_m = {cover.max_range_m:g}"
        )


def checked_keys() -> dict[tuple[str, str], str]:
    """Every key of the site file and how its value is checked beyond its type:
    "choice", "range", "text", "free" or "bool" (the property tests walk this)."""
    out: dict[tuple[str, str], str] = {}
    for table, cls in typing.get_type_hints(SiteConfig).items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            key = (table, f.name)
            if key in _CHOICES:
                out[key] = "choice"
            elif key in _RANGES:
                out[key] = "range"
            elif key in _TEXT:
                out[key] = "text"
            elif key in FREE_KEYS:
                out[key] = "free"
            elif hints[f.name] is bool:
                out[key] = "bool"
            else:
                raise TypeError(f"config key [{table}] {f.name} has no check")  # a bug
    return out


def key_rule(table: str, key: str) -> Any:
    """The choices, the (low, high) range or the text check of a key (None: none)."""
    return _CHOICES.get((table, key)) or _RANGES.get((table, key)) or _TEXT.get((table, key))


def load_config(path: str | Path | None) -> SiteConfig:
    """Load a site TOML file; None gives the defaults."""
    if path is None:
        return SiteConfig()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such config file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SeamapError(f"{path}: cannot read config ({exc})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SeamapError(f"{path}: not valid TOML ({exc})") from None
    try:
        config = config_from_dict(data)
    except SeamapError as exc:
        raise SeamapError(f"{path}: {exc}") from None
    area = config.mission.area
    if area and not Path(area).is_absolute():  # from the file's folder, not the cwd
        mission = dataclasses.replace(config.mission, area=str(path.parent / area))
        config = dataclasses.replace(config, mission=mission)
    return config


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def dump_config(config: SiteConfig) -> str:
    """The config as TOML text that ``load_config`` reads back to an equal SiteConfig."""
    lines: list[str] = []
    for section in dataclasses.fields(config):
        lines.append(f"[{section.name}]")
        table = getattr(config, section.name)
        for item in dataclasses.fields(table):
            lines.append(f"{item.name} = {_toml_value(getattr(table, item.name))}")
        lines.append("")
    return "\n".join(lines)


__all__ = [
    "HEADING_SOURCES",
    "IMU_SOURCES",
    "CoverageConfig",
    "DaemonConfig",
    "MappingConfig",
    "MavlinkConfig",
    "MissionConfig",
    "SiteConfig",
    "SonarConfig",
    "ZenohConfig",
    "config_from_dict",
    "dump_config",
    "load_config",
]
