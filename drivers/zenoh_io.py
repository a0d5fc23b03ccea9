"""The zenoh edge of the contract (CONTRACT.md "Zenoh"): key expressions, payloads, sessions.

Keys, ``{vehicle}`` and ``{survey}`` being ids without ``/``:

- ``seamap/{vehicle}/pose``: JSON ``{"time", "lat", "lon", "east", "north", "heading_deg",
  "epsg", ...}``;
- ``seamap/{vehicle}/status``: JSON health;
- ``seamap/{vehicle}/survey/{survey}/tile/{col}/{row}``: a mosaic tile as PNG (8-bit grey +
  alpha, alpha 0 = no data), encoding ``image/png``, attachment JSON ``{"epsg", "res_m",
  "west", "north", "size_px", "version"}``; tile (col, row) covers easting
  [col*T, (col+1)*T) and northing [row*T, (row+1)*T), T = size_px * res_m;
- ``seamap/{vehicle}/survey/{survey}/coverage``: JSON, how well the survey has seen the
  seabed so far (``coverage_summary``: the covered fraction of its area and its gaps as
  GeoJSON when the area is known); ``.../coverage/raster``: the coverage raster for eyes
  as PNG (RGBA, one pixel a cell, north-up, ``coverage.png``'s colours), attachment JSON
  ``CoverageInfo``. Both are republished every few seconds while the survey records and
  once more, ``"final": true``, from the result folder after the survey-end pass; a
  ``get`` on ``seamap/{vehicle}/survey/{survey}/coverage/**`` answers the latest;
- ``seamap/{vehicle}/alive``: the vehicle's liveliness token;
- ``seamap/{vehicle}/control/survey``: a queryable; a ``get`` with payload
  ``{"action": "start"|"stop"|"status"}`` opens or ends a survey and replies JSON
  ``{"ok", "survey", ...}``.

Both the boat (``daemon.publisher``) and the shore (``seamap.shore``) speak through here.
"""

from __future__ import annotations

import io
import ipaddress
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh
from PIL import Image

from drivers.errors import SeamapError

ROOT = "seamap"


def pose_key(vehicle: str) -> str:
    return f"{ROOT}/{vehicle}/pose"


def status_key(vehicle: str) -> str:
    return f"{ROOT}/{vehicle}/status"


def alive_key(vehicle: str) -> str:
    return f"{ROOT}/{vehicle}/alive"


def parse_alive_key(key: str) -> str | None:
    """The vehicle of a liveliness token's key, or None when ``key`` is not one."""
    parts = key.split("/")
    if len(parts) != 3 or parts[0] != ROOT or parts[2] != "alive":
        return None
    return parts[1]


def control_key(vehicle: str) -> str:
    return f"{ROOT}/{vehicle}/control/survey"


def tile_key(vehicle: str, survey: str, col: int, row: int) -> str:
    return f"{ROOT}/{vehicle}/survey/{survey}/tile/{col}/{row}"


def tiles_selector(vehicle: str, survey: str = "*") -> str:
    """Every tile of one survey (or of every survey, ``*``) of a vehicle."""
    return f"{ROOT}/{vehicle}/survey/{survey}/tile/**"


def coverage_key(vehicle: str, survey: str) -> str:
    return f"{ROOT}/{vehicle}/survey/{survey}/coverage"


def coverage_raster_key(vehicle: str, survey: str) -> str:
    return f"{ROOT}/{vehicle}/survey/{survey}/coverage/raster"


def coverage_selector(vehicle: str, survey: str = "*") -> str:
    """The coverage summary and raster of one survey (or of every survey, ``*``)."""
    return f"{ROOT}/{vehicle}/survey/{survey}/coverage/**"


@dataclass(frozen=True)
class CoverageKeyParts:
    vehicle: str
    survey: str
    raster: bool
    """True for ``.../coverage/raster``, False for the summary ``.../coverage``."""


def parse_coverage_key(key: str) -> CoverageKeyParts | None:
    """The parts of a coverage key, or None when ``key`` is not one."""
    parts = key.split("/")
    if len(parts) not in (5, 6) or parts[0] != ROOT or parts[2] != "survey":
        return None
    if parts[4] != "coverage" or (len(parts) == 6 and parts[5] != "raster"):
        return None
    return CoverageKeyParts(parts[1], parts[3], len(parts) == 6)


@dataclass(frozen=True)
class CoverageInfo:
    """The coverage raster's attachment: its UTM top-left corner (``west``, ``north``
    metres), its cell side (``cell_m``), size in cells and version (millisecond UNIX
    time, as the summary's)."""

    epsg: int
    cell_m: float
    west: float
    north: float
    cols: int
    rows: int
    version: int

    def as_dict(self) -> dict[str, Any]:
        return {
            "epsg": self.epsg,
            "cell_m": self.cell_m,
            "west": self.west,
            "north": self.north,
            "cols": self.cols,
            "rows": self.rows,
            "version": self.version,
        }

    def to_json(self) -> bytes:
        return json_bytes(self.as_dict())

    @classmethod
    def from_json(cls, data: bytes) -> CoverageInfo:
        """Parse an attachment; ValueError naming what is wrong."""
        try:
            raw = json.loads(data)
            info = cls(
                int(raw["epsg"]), float(raw["cell_m"]), float(raw["west"]),
                float(raw["north"]), int(raw["cols"]), int(raw["rows"]), int(raw["version"]),
            )  # fmt: skip
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"bad coverage attachment ({exc})") from None
        if not (info.cell_m > 0 and info.cols > 0 and info.rows > 0):
            raise ValueError("bad coverage attachment (size)")
        if not math.isfinite(info.west + info.north):
            raise ValueError("bad coverage attachment (position)")
        return info


COVERAGE_SUMMARY_KEYS = (
    "survey", "time", "final", "version", "epsg", "cell_m", "min_passes", "seen_m2",
    "covered_m2", "area", "gaps",
)  # fmt: skip
"""What a coverage summary holds (``daemon.coverage``'s publications)."""


def parse_coverage_summary(data: bytes, survey: str | None = None) -> dict[str, Any]:
    """A coverage summary (JSON object) checked for its keys and types (and, given
    ``survey``, that it is that survey's); ValueError naming what is wrong. ``area`` is
    None or ``{"area_m2", "covered_m2", "fraction", "gaps", "gaps_m2", "min_gap_m2"}``;
    ``gaps`` a GeoJSON FeatureCollection (WGS84)."""
    try:
        summary = json.loads(data)
    except ValueError as exc:
        raise ValueError(f"coverage summary is not JSON ({exc})") from None
    if not isinstance(summary, dict):
        raise ValueError("coverage summary is not a JSON object")
    missing = [key for key in COVERAGE_SUMMARY_KEYS if key not in summary]
    if missing:
        raise ValueError(f"coverage summary lacks {', '.join(missing)}")
    if survey is not None and summary["survey"] != survey:
        raise ValueError(
            f"coverage summary: names survey {summary['survey']!r}, published under {survey!r}"
        )
    if not isinstance(summary["final"], bool):
        raise ValueError("coverage summary: final is not true or false")
    if not isinstance(summary["version"], int) or isinstance(summary["version"], bool):
        raise ValueError("coverage summary: version is not an integer")
    for key in ("time", "cell_m", "seen_m2", "covered_m2"):
        value = summary[key]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"coverage summary: {key} is not a number")
        if not math.isfinite(value):
            raise ValueError(f"coverage summary: {key} is not finite")
    area = summary["area"]
    if area is not None:
        if not isinstance(area, dict):
            raise ValueError("coverage summary: area is not an object")
        for key in ("area_m2", "covered_m2", "fraction"):
            value = area.get(key)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"coverage summary: area {key} is not a number")
    gaps = summary["gaps"]
    if not (isinstance(gaps, dict) and gaps.get("type") == "FeatureCollection"):
        raise ValueError("coverage summary: gaps is not a GeoJSON FeatureCollection")
    if not isinstance(gaps.get("features"), list):
        raise ValueError("coverage summary: gaps has no features list")
    return summary


@dataclass(frozen=True)
class TileKeyParts:
    vehicle: str
    survey: str
    col: int
    row: int


def parse_tile_key(key: str) -> TileKeyParts | None:
    """The parts of a tile key, or None when ``key`` is not one."""
    parts = key.split("/")
    if len(parts) != 7 or parts[0] != ROOT or parts[2] != "survey" or parts[4] != "tile":
        return None
    try:
        return TileKeyParts(parts[1], parts[3], int(parts[5]), int(parts[6]))
    except ValueError:
        return None


@dataclass(frozen=True)
class TileInfo:
    """A tile's attachment: where it lies (UTM metres) and its version."""

    epsg: int
    res_m: float
    west: float
    north: float
    size_px: int
    version: int

    def to_json(self) -> bytes:
        return json.dumps(
            {
                "epsg": self.epsg,
                "res_m": self.res_m,
                "west": self.west,
                "north": self.north,
                "size_px": self.size_px,
                "version": self.version,
            }
        ).encode()

    @classmethod
    def from_json(cls, data: bytes) -> TileInfo:
        """Parse an attachment; ValueError naming what is wrong."""
        try:
            raw = json.loads(data)
            info = cls(
                int(raw["epsg"]), float(raw["res_m"]), float(raw["west"]),
                float(raw["north"]), int(raw["size_px"]), int(raw["version"]),
            )  # fmt: skip
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"bad tile attachment ({exc})") from None
        if not (info.res_m > 0 and info.size_px > 0 and math.isfinite(info.west + info.north)):
            raise ValueError("bad tile attachment (size or position)")
        return info

    def key(self) -> tuple[int, int]:
        """The tile's (col, row) from its position."""
        t = self.res_m * self.size_px
        return round(self.west / t), round(self.north / t) - 1


def encode_tile(values: npt.NDArray[np.uint8]) -> bytes:
    """A tile's values (1..255, 0 = no data) as PNG, 8-bit grey + alpha."""
    alpha = np.where(values > 0, np.uint8(255), np.uint8(0))
    image = Image.fromarray(np.dstack([values, alpha]), mode="LA")
    out = io.BytesIO()
    image.save(out, format="PNG", compress_level=6)
    return out.getvalue()


def decode_tile(png: bytes) -> npt.NDArray[np.uint8]:
    """The values of a tile PNG (grey where alpha > 0, else 0); ValueError if not one."""
    try:
        image = Image.open(io.BytesIO(png))
        image.load()
    except Exception as exc:
        raise ValueError(f"not a PNG tile ({exc})") from None
    if image.mode != "LA":
        raise ValueError(f"not a grey + alpha PNG tile (mode {image.mode})")
    data = np.asarray(image)
    return np.where(data[:, :, 1] > 0, data[:, :, 0], 0).astype(np.uint8)


@dataclass(frozen=True)
class ZenohConfig:
    mode: str = "peer"
    """zenoh session mode: "peer", "client" (through a router) or "router"."""
    listen: list[str] = field(default_factory=lambda: ["tcp/0.0.0.0:7447"])
    """Endpoints the session listens on (zenoh locators, e.g. "tcp/0.0.0.0:7447")."""
    connect: list[str] = field(default_factory=list)
    """Endpoints the session connects to (a router, or a peer on shore)."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast (off: only listen/connect)."""
    config_file: str = ""
    """A zenoh JSON5 configuration file read first (TLS, user/password authentication,
    access control); mode, listen, connect and multicast_scouting above override it."""
    allow_insecure: bool = False
    """Let the daemon listen in plain TCP (or UDP, WebSocket) on an address other hosts
    reach: anyone who reaches the port can then stop surveys and publish as the boat.
    Off: such a listen endpoint stops the daemon at start; make a secure set with
    `seamap security init` instead. Loopback endpoints are always allowed."""


def id_problem(value: str) -> str | None:
    """Why ``value`` cannot be a vehicle or survey id (a key chunk and a folder name)."""
    if not value or value in (".", ".."):
        return "not an id"
    if any(c in value for c in "/*?#$") or any(c.isspace() for c in value):
        return "an id holds no '/', '*', '?', '#', '$' or spaces"
    return None


_LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost"})


def insecure_listen(endpoints: list[str]) -> list[str]:
    """The endpoints that listen unencrypted on an address other hosts can reach (plain
    TCP, UDP or WebSocket on anything but loopback)."""
    found = []
    for endpoint in endpoints:
        locator = endpoint.split("#", 1)[0].split("?", 1)[0]
        protocol, _, address = locator.partition("/")
        if protocol not in ("tcp", "udp", "ws"):
            continue
        host = address.rpartition(":")[0].strip("[]")
        if host in _LOOPBACK_NAMES:
            continue
        try:
            if ipaddress.ip_address(host).is_loopback:
                continue
        except ValueError:
            pass  # a host name other than localhost: reachable from elsewhere
        found.append(endpoint)
    return found


_HOST_PORT_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})


def endpoint_problem(endpoint: str) -> str | None:
    """None when ``endpoint`` has the form of a zenoh endpoint (``tcp/HOST:PORT``,
    ``udp/...``, ``unixsock-stream/PATH``, with optional ``?metadata`` and ``#config``),
    else what is wrong in a few words. zenoh itself accepts some malformed ones in peer
    mode (``tcp/HOST`` without a port, port 70000) and then retries them for ever."""
    if not endpoint or any(c.isspace() for c in endpoint):
        return "empty or contains spaces"
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    protocol, slash, address = locator.partition("/")
    if not slash or not protocol or not address:
        return "not PROTOCOL/ADDRESS, e.g. tcp/192.168.1.10:7447"
    if protocol in _HOST_PORT_PROTOCOLS:
        host, colon, port = address.rpartition(":")
        if not colon or not host:
            return f"no HOST:PORT after {protocol}/"
        if not port.isdigit() or int(port) > 65535:
            return f"port {port!r} is not 0..65535"
    return None


def with_endpoints(
    base: ZenohConfig,
    listen: Sequence[str] | None,
    connect: Sequence[str] | None,
    mode: str | None = None,
) -> ZenohConfig:
    """``base`` with the command line's ``--listen``, ``--connect`` (and mode) in place of
    its own where given; SeamapError naming a malformed endpoint, by the option it came
    from or its ``[zenoh]`` key."""
    session = replace(
        base,
        mode=mode if mode is not None else base.mode,
        listen=list(listen) if listen is not None else list(base.listen),
        connect=list(connect) if connect is not None else list(base.connect),
    )
    for name, given, endpoints in (
        ("listen", listen is not None, session.listen),
        ("connect", connect is not None, session.connect),
    ):
        where = f"--{name}" if given else f"[zenoh] {name}"
        for endpoint in endpoints:
            problem = endpoint_problem(endpoint)
            if problem is not None:
                raise SeamapError(f"{where} {endpoint!r}: not a zenoh endpoint ({problem})")
    return session


def session_config(cfg: ZenohConfig) -> zenoh.Config:
    """A zenoh configuration from the site config's [zenoh] table (its ``config_file`` first);
    SeamapError naming a malformed endpoint."""
    for key, endpoints in (("listen", cfg.listen), ("connect", cfg.connect)):
        for endpoint in endpoints:
            problem = endpoint_problem(endpoint)
            if problem is not None:
                raise SeamapError(f"config: [zenoh] {key} {endpoint!r}: {problem}")
    if cfg.config_file:
        try:
            config = zenoh.Config.from_file(cfg.config_file)
        except Exception as exc:
            raise SeamapError(f"{cfg.config_file}: not a usable zenoh config ({exc})") from None
        _refuse_example_secrets(cfg.config_file, config)
    else:
        config = zenoh.Config()
    try:
        config.insert_json5("mode", json.dumps(cfg.mode))
        config.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        config.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    except Exception as exc:
        raise SeamapError(f"config: [zenoh] is not valid for zenoh ({exc})") from None
    return config


PLACEHOLDER = "REPLACE-ME"
"""Marks the example security files' passwords (systemd/zenoh-*.json5, zenoh-users)."""


def _refuse_example_secrets(path: str, config: zenoh.Config) -> None:
    """SeamapError when the zenoh config (or its user dictionary) still holds the
    example's placeholder password: a boat must not run with a published secret."""
    try:
        auth = json.loads(config.get_json("transport/auth/usrpwd"))
    except Exception:
        return
    if not isinstance(auth, dict):
        return
    if PLACEHOLDER in str(auth.get("password") or ""):
        raise SeamapError(f"{path}: the password is still the example's {PLACEHOLDER}...")
    dictionary = auth.get("dictionary_file")
    if dictionary:
        try:
            text = open(dictionary, encoding="utf-8").read()  # noqa: SIM115
        except OSError as exc:
            raise SeamapError(
                f"{dictionary}: cannot read the zenoh user dictionary ({exc})"
            ) from None
        if PLACEHOLDER in text:
            raise SeamapError(f"{dictionary}: a password is still the example's {PLACEHOLDER}...")


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    """Open a session (blocks ~0.5 s: call it from a thread); SeamapError in one line."""
    config = session_config(cfg)
    try:
        return zenoh.open(config)
    except Exception as exc:
        where = ", ".join([*cfg.listen, *cfg.connect]) or "no endpoint"
        raise SeamapError(f"zenoh: cannot open a {cfg.mode} session on {where} ({exc})") from None


def json_bytes(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()
